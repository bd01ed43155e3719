"""nhfctl against a running daemon: human output, --json, one-line errors, light imports."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from types import SimpleNamespace

import pytest

from nhfd.cli.nhfctl import main
from tests.words import PYTHON_REPR

from .conftest import Running

HEAVY = ("torch", "numba", "onnxruntime")


def test_client_and_nhfctl_import_nothing_heavy_and_answer_fast(running: Running):
    probe = ("import sys, time; t = time.monotonic()\n"
             "from nhfd.cli.nhfctl import main\n"
             f"code = main(['--socket', {str(running.socket)!r}, '--json', 'status'])\n"
             "print('ELAPSED', time.monotonic() - t, file=sys.stderr)\n"
             "print('MODULES', ' '.join(sorted(sys.modules)), file=sys.stderr)\n"
             "sys.exit(code)\n")
    t = time.monotonic()
    res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=20)
    wall = time.monotonic() - t
    assert res.returncode == 0, res.stderr
    modules = set(res.stderr.split("MODULES ")[1].split())
    assert not modules & set(HEAVY)
    assert json.loads(res.stdout)["daemon"]["state"] == "ready"
    elapsed = float(res.stderr.split("ELAPSED ")[1].split()[0])
    # What makes it fast is the import list above; these bounds only catch a gross regression
    # and stay loose so a loaded CI machine cannot fail them.
    assert elapsed < 3.0, elapsed  # import + connect + status, after interpreter start
    assert wall < 15.0


def test_nhfctl_commands(running: Running, capsys):
    sock = ["--socket", str(running.socket)]
    assert main([*sock, "set-view", "--orbit", "30,10,4"]) == 0
    assert capsys.readouterr().out.startswith("view seq 1: ")
    assert main([*sock, "--json", "set-view", "--by-orbit", "5,0,0"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["seq"] == 2 and out["view"]["azimuth_deg"] == 35.0
    assert main([*sock, "status"]) == 0
    text = capsys.readouterr().out
    assert "laser    not armed; emitting: none" in text and "model    none loaded" in text
    assert "colour   hw-sync" in text and "calib    none (uncalibrated focus mapping)" in text
    assert main([*sock, "load-model", "/etc/passwd"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("nhfctl load-model: error: path_not_allowed: ")
    assert "outside the allowed directories" in err
    assert main([*sock, "blank"]) == 0 and "showing blank" in capsys.readouterr().out
    assert main([*sock, "focus", "9"]) == 1
    err = capsys.readouterr().err
    assert err == ("nhfctl focus: error: invalid_params: z_mm: got 9.0; allowed: a finite number "
                   "in [-5, 5]\n")
    assert main([*sock, "laser", "power", "red", "3"]) == 0  # power alone emits nothing
    assert "power 3 %" in capsys.readouterr().out
    assert main([*sock, "stop"]) == 0
    assert main([*sock, "--json", "watch", "--count", "2", "--interval-s", "0.05"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and json.loads(lines[-1])["view"]["seq"] == 2
    assert main([*sock, "shutdown"]) == 0
    running.thread.join(10)
    assert not running.socket.exists()




def test_human_output_is_words_and_json_is_the_data(running: Running, capsys):
    sock = ["--socket", str(running.socket)]
    assert main([*sock, "--json", "focus", "1.5", "--home", "--wait"]) == 0
    job = json.loads(capsys.readouterr().out)["id"]
    commands = [["set-view", "--orbit", "30,10,4", "--quality", "sgd"], ["status"],
                ["laser", "power", "red", "3"], ["focus", "1.5", "--wait"], ["blank"],
                ["job", str(job)], ["stop"]]
    for command in commands:
        assert main([*sock, *command]) == 0, command
        text = capsys.readouterr().out
        assert text.strip() and not PYTHON_REPR.search(text), (command, text)
        assert main([*sock, "--json", *command]) == 0, command
        data = json.loads(capsys.readouterr().out)
        assert json.loads(json.dumps(data)) == data and isinstance(data, dict)
    # A job waited for reads as a sentence, its times local ISO times.
    assert main([*sock, "focus", "1.0", "--wait"]) == 0
    line = capsys.readouterr().out.strip()
    assert re.fullmatch(r"job \d+ \(focus\) done in \d+\.\d s, started "
                        r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d[+-]\d\d:\d\d: z 1 mm, "
                        r"stage [-\d.]+ mm", line), line


def test_a_bad_number_names_the_token_and_the_form(running: Running, capsys):
    sock = ["--socket", str(running.socket)]
    for bad, said in ((["--orbit", "30,abc,0"], "'abc' is not a number: expected AZ,EL,R, 3 "
                                                 "numbers separated by commas"),
                      (["--by-pose", "1,2"], "2 numbers in '1,2': expected DX,DY,DZ,RX,RY,RZ, "
                                             "6 numbers separated by commas")):
        with pytest.raises(SystemExit) as exit_:
            main([*sock, "set-view", *bad])
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert f"argument {bad[0]}: {said}" in err, err


def test_load_commands_wait_for_their_job_and_fail_with_its_error(running: Running, capsys):
    root = running.daemon.base_dir
    sock = ["--socket", str(running.socket)]
    (root / "models" / "m.onnx").write_bytes(b"x")  # garbage: the worker refuses it
    (root / "scenes" / "garbage.ply").write_bytes(b"ply\nformat nonsense\n")
    assert main([*sock, "load-model", "m.onnx"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("nhfctl load-model: error: job ")
    assert " failed: " in captured.err and "not a readable ONNX model" in captured.err
    assert captured.err.count("\n") == 1
    assert main([*sock, "load-scene", "garbage.ply"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("nhfctl load-scene: error: job ") and " failed: " in err
    assert main([*sock, "load-model", "--no-wait", "m.onnx"]) == 0  # queued, not judged
    out = capsys.readouterr().out
    assert out.startswith("job ") and out.endswith(f" queued (path {root}/models/m.onnx)\n")


def test_status_prints_the_model_as_one_line(running: Running, capsys, monkeypatch):
    info = {"path": "/lab/models/fast-v3.onnx", "profile": "fast", "train_size_hw": [576, 1024],
            "fx": 900.0, "amplitude_scale": 1.3, "z0_m": 0.006, "volume_m": [-0.003, 0.003],
            "mapping": {"kind": "linear"}, "pose_envelope": {"azimuth_deg": [-20, 20]},
            "parameters": 123456, "train_steps": 10000, "scene_sha256": "ab" * 32,
            "providers": ["CUDAExecutionProvider", "CPUExecutionProvider"], "loaded_s": 1.0}
    def served(report: dict) -> SimpleNamespace:  # status's "model" is its to_json()
        return SimpleNamespace(to_json=lambda: report, variant=None, variant_reason=None,
                               tuned_for=report.get("tuned_for"), bench_warning="")

    monkeypatch.setattr(running.daemon.frames.loads, "model", served(info))
    assert main(["--socket", str(running.socket), "status"]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if x.startswith("model ")]
    assert lines == ["model    fast-v3.onnx (profile fast; trained 1024 x 576 px; "
                     "CUDAExecutionProvider, CPUExecutionProvider)"]
    checked = dict(info, checked_sizes_hw=[[576, 1024], [1080, 1920]])
    monkeypatch.setattr(running.daemon.frames.loads, "model", served(checked))
    assert main(["--socket", str(running.socket), "status"]) == 0
    assert ("model    fast-v3.onnx (profile fast; trained 1024 x 576 px; CUDAExecutionProvider, "
            "CPUExecutionProvider; checked at 1024 x 576 px, 1920 x 1080 px)\n"
            in capsys.readouterr().out)
    tuned = dict(info, tuned_for={"calibration": "bench-a.toml (2026-12-01)",
                                  "calibration_sha256": "cd" * 32, "date": "2026-12-02"})
    monkeypatch.setattr(running.daemon.frames.loads, "model", served(tuned))
    assert main(["--socket", str(running.socket), "status"]) == 0
    assert ("CPUExecutionProvider; tuned for calibration bench-a.toml (2026-12-01) "
            "(2026-12-02))\n" in capsys.readouterr().out)


def test_the_socket_is_the_given_one_else_the_configured_daemons(tmp_path):
    """`socket_path`, which nhfctl, nhfd replay, nhfd calib capture and nhfd model build --serve
    share: a --socket wins and no configuration is read; without one, the configured runtime
    directory's control socket (a loaded configuration or a function that loads it)."""
    from types import SimpleNamespace

    from nhfd.daemon.paths import SOCKET_NAME, socket_path

    loads = []

    def load():
        loads.append(1)
        return SimpleNamespace(daemon=SimpleNamespace(
            server=SimpleNamespace(runtime_dir=str(tmp_path / "rt"))))

    assert socket_path("/elsewhere/c.sock", load) == "/elsewhere/c.sock" and loads == []
    assert socket_path(None, load) == str(tmp_path / "rt" / SOCKET_NAME) and loads == [1]
    assert socket_path("", load()) == str(tmp_path / "rt" / SOCKET_NAME)
