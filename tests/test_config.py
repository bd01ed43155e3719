"""Configuration: search order, provenance, and every validation error with its message."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from nhfd.cli.main import main
from nhfd.config import (
    DEVICES,
    Config,
    ConfigError,
    check_file,
    default_text,
    device_choice,
    load_config,
)

REPO = Path(__file__).resolve().parents[1]


def write(tmp_path: Path, text: str, name: str = "nhfd.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_packaged_default_is_the_repository_file_and_validates():
    assert default_text() == (REPO / "nhfd.toml").read_text()
    cfg = Config.model_validate(tomllib.loads(default_text()))
    assert cfg.slm.width_px == 1920 and cfg.slm.height_px == 1080 and cfg.slm.pitch_um == 8.0
    assert cfg.optics.wavelengths_nm == [660.0, 520.0, 450.0]
    assert cfg.optics.wavelengths_m == pytest.approx((660e-9, 520e-9, 450e-9))
    assert cfg.devices.laser == "simulated"
    # the schema's own defaults agree with the annotated file
    assert Config() == cfg


def test_search_order(tmp_path, monkeypatch):
    cwd, xdg = tmp_path / "cwd", tmp_path / "xdg"
    (xdg / "nhfd").mkdir(parents=True)
    cwd.mkdir()
    env = {"XDG_CONFIG_HOME": str(xdg), "HOME": str(tmp_path)}
    assert load_config(env=env, cwd=cwd).path is None  # packaged default only
    xdg_file = write(xdg / "nhfd", "[optics]\nz0_mm = 7.0\n")
    assert load_config(env=env, cwd=cwd).path == xdg_file
    cwd_file = write(cwd, "[optics]\nz0_mm = 8.0\n")
    assert load_config(env=env, cwd=cwd).path == cwd_file
    env_file = write(tmp_path, "[optics]\nz0_mm = 9.0\n", "env.toml")
    loaded = load_config(env={**env, "NHFD_CONFIG": str(env_file)}, cwd=cwd)
    assert loaded.path == env_file and loaded.config.optics.z0_mm == 9.0
    explicit = write(tmp_path, "[optics]\nz0_mm = 10.0\n", "explicit.toml")
    loaded = load_config(explicit, env={**env, "NHFD_CONFIG": str(env_file)}, cwd=cwd)
    assert loaded.config.optics.z0_mm == 10.0


def test_partial_file_overlays_default_and_sources_say_which(tmp_path):
    path = write(tmp_path, "[optics.aperture]\nshape = 'circle'\n")
    loaded = load_config(path, env={})
    assert loaded.config.optics.aperture.shape == "circle"
    assert loaded.config.optics.aperture.cutoff_per_px == [0.25, 0.25, 0.25]
    assert loaded.sources["optics.aperture.shape"] == str(path)
    assert loaded.sources["optics.aperture.cutoff_per_px"] == "packaged default"


def test_named_file_must_exist(tmp_path):
    with pytest.raises(ConfigError, match=r"--config names .*missing\.toml, which is not"):
        load_config(tmp_path / "missing.toml", env={})
    with pytest.raises(ConfigError, match=r"\$NHFD_CONFIG names"):
        load_config(env={"NHFD_CONFIG": str(tmp_path / "nope.toml")}, cwd=tmp_path)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[slm]\nwidth = 1920\n", r"slm\.width: unknown key; allowed here: grey_invert, height_px"),
        (
            "[lasers]\n",
            r"lasers: unknown key; allowed here: calibration, coding, daemon, devices, model, "
            r"optics, refine, slm",
        ),
        ("[optics.aperture]\nradius = 1\n", r"optics\.aperture\.radius: unknown key"),
        ("[slm]\npitch_um = '8'\n", r"slm\.pitch_um = '8': Input should be a valid number"),
        ("[slm]\nwidth_px = 1920.5\n", r"slm\.width_px = 1920\.5: Input should be a valid integer"),
        ("[slm]\ngrey_invert = 1\n", r"slm\.grey_invert = 1: Input should be a valid boolean"),
        ("[slm]\npitch_um = 0.0\n", r"slm\.pitch_um = 0\.0: Input should be greater than 0"),
        ("[slm]\nphase_sign = 2\n", r"slm\.phase_sign = 2: Input should be 1 or -1"),
        (
            "[slm]\nphase_stroke_rad = [6.0, 6.0]\n",
            r"slm\.phase_stroke_rad = \[6\.0, 6\.0\]: "
            r"List should have at least 3 items",
        ),
        (
            "[optics]\nwavelengths_nm = [660.0, -520.0, 450.0]\n",
            r"optics\.wavelengths_nm\.1 = -520\.0: Input should be greater than or equal to 200",
        ),
        ("[optics]\nwavelengths_nm = [660.0, nan, 450.0]\n", r"optics\.wavelengths_nm\.1 = nan"),
        ("[optics]\npadding = '3x'\n", r"optics\.padding = '3x': Input should be 'none', '2x' or"),
        (
            "[optics.aperture]\ncutoff_per_px = [0.25, 0.6, 0.25]\n",
            r"optics\.aperture\.cutoff_per_px\.1 = 0\.6: "
            r"Input should be less than or equal to 0\.5",
        ),
        ("[optics.aperture]\nshape = 'hexagon'\n", r"optics\.aperture\.shape = 'hexagon'"),
        (
            "[optics]\nvolume_mm = [3.0, -3.0]\n",
            r"volume_mm = \[3\.0, -3\.0\]: needs z_min < z_max",
        ),
        (
            "[optics]\nz0_mm = 2.0\n",
            r"z0_mm = 2\.0 with volume_mm = \[-3\.0, 3\.0\] puts the volume's far end at -1 mm",
        ),
        ("[optics]\nhologram_width_px = 4096\n", r"4096 x 576 does not fit the panel 1920 x 1080"),
        ("[devices]\nlaser = 'fisba'\n", r"devices\.laser = 'fisba': Input should be 'simulated'"),
        ("[optics\n", r"not valid TOML"),
        (
            "[model.profiles.thin]\nwidth = 8\ndepth = 1\nunshuffle = 2\n"
            "single_conv_levels = 3\n",
            r"single_conv_levels = 3: the network has 2 levels \(depth \+ 1\)",
        ),
    ],
)
def test_validation_errors_name_key_value_and_allowed(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError, match=message) as info:
        check_file(path)
    assert str(path) in str(info.value)


def test_cli_show_and_check(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("NHFD_CONFIG", raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    path = write(tmp_path, "[optics]\nz0_mm = 7.5\n", "lab.toml")
    assert main(["config", "show", "--config", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["values"]["optics.z0_mm"] == {"value": 7.5, "source": str(path)}
    assert out["values"]["slm.pitch_um"]["source"] == "packaged default"
    assert main(["config", "show"]) == 0
    text = capsys.readouterr().out
    assert "none (packaged default only)" in text and "optics.z0_mm" in text
    assert main(["config", "check", str(path)]) == 0
    assert f"{path}: ok" in capsys.readouterr().out
    bad = write(tmp_path, "[optics]\nz0_mm = -1.0\n", "bad.toml")
    assert main(["config", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "optics.z0_mm = -1.0: Input should be greater than 0" in err


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "[daemon.frames]\nsize_px = [4096, 2160]\n",
            r": daemon\.frames\.size_px = \[4096, 2160\] does not fit the panel 1920 x 1080 "
            r"\(slm\.width_px x height_px\)$",
        ),
        (
            "[slm]\nwidth_px = 1000\n[optics]\nhologram_width_px = 1000\n[daemon.frames]\n"
            "size_px = [1024, 576]\n",
            r": daemon\.frames\.size_px = \[1024, 576\] does not fit the panel 1000 x 1080",
        ),
        (
            "[daemon.arming]\nheartbeat_s = 0.2\n",
            r": daemon\.arming\.heartbeat_s = 0\.2 s: must be at most 1/4 of "
            r"devices\.readybeam\.guardian\.heartbeat_timeout_s = 0\.5 s$",
        ),
        (
            "[daemon.arming]\nheartbeat_s = 0.05\n[devices.readybeam.guardian]\n"
            "heartbeat_timeout_s = 0.1\n",
            r": daemon\.arming\.heartbeat_s = 0\.05 s: must be at most 1/4 of .*= 0\.1 s$",
        ),
        ("[optics]\nvolume_mm = [3.0, -3.0]\n", r": optics\.volume_mm = \[3\.0, -3\.0\]: needs"),
        ("[daemon.bench]\nfocus_range_mm = [2.0, 1.0]\n",
         r": daemon\.bench\.focus_range_mm = \[2\.0, 1\.0\]: needs min < max"),
        ("[daemon.bench]\ncamera_roi_px = [0, 0, 0, 16]\n",
         r": daemon\.bench\.camera_roi_px = \[0, 0, 0, 16\]: give \[top, left, height, width\]"),
        ("[daemon.frames]\nsize_px = [1024]\n",
         r": daemon\.frames\.size_px = \[1024\]: give \[width, height\] or \[\]"),
        ("[daemon.server]\ntls_cert = 'bench.pem'\n",
         r": daemon\.server\.tls_cert = 'bench\.pem', tls_key = '': give both "
         r"daemon\.server\.tls_cert and daemon\.server\.tls_key, or neither"),
        ("[daemon.server]\ntcp_host = '0.0.0.0'\n",
         r": daemon\.server\.tcp_host = '0\.0\.0\.0' is not loopback"),
        ("[model]\nprofile = 'huge'\n", r": model\.profile = 'huge': not one of the profiles"),
        ("[devices.apt]\nsoft_limits_mm = [5.0, 1.0]\n", r": devices\.apt\.soft_limits_mm = "),
    ],
)
def test_cross_field_errors_name_the_key_not_a_section_dict(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError, match=message) as info:
        check_file(path)
    assert "{" not in str(info.value)


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("[optics]\nwavelengths_nm = [660.0, nan, 450.0]\n", "optics.wavelengths_nm.1 = nan"),
        ("[optics]\nz0_mm = inf\n", "optics.z0_mm = inf"),
        ("[optics]\nvolume_mm = [nan, 3.0]\n", "optics.volume_mm.0 = nan"),
        ("[daemon.bench]\nfocus_range_mm = [-5.0, inf]\n", "daemon.bench.focus_range_mm.1 = inf"),
        ("[devices.apt]\nsoft_limits_mm = [nan, 25.0]\n", "devices.apt.soft_limits_mm.0 = nan"),
    ],
)
def test_nan_and_inf_are_reported_as_not_finite(tmp_path, text, key):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        check_file(path)
    assert str(info.value) == f"{path}: {key}: not finite"


class _NoDaemon:
    """Stands in for `nhfd serve`'s daemon: these configurations must be refused before one
    starts (a real one would open the shared runtime directory and the laser guardian)."""

    def __init__(self, *args, **kwargs) -> None:
        raise AssertionError("nhfd serve started a daemon for a configuration it must refuse")


def _calibration_text() -> str:
    import math

    from nhfd.calibration import Calibration

    table = tuple(2 * math.pi * i / 255 for i in range(256))
    return Calibration((6.6e-7, 5.2e-7, 4.5e-7), 8e-6, 1, (table,) * 3, (0.01,) * 3, 1.0, 0.0,
                       10.0, 0.0, (0.0,) * 3, (0.0,) * 3, 1.0, 0.0, 180.0, 0.0, False,
                       (0.0, 0.0), (1.0,) * 3, (0.0,) * 3).to_toml()


def _without_section(text: str, name: str) -> str:
    head, _, rest = text.partition(f"\n[{name}]\n")
    return head + "\n" + rest[rest.index("\n[") :]


CORRUPT_CALIBRATIONS = {
    "truncated": (lambda t: t[: len(t) // 2].encode(), r"corrupt \(|missing or malformed key"),
    "empty": (lambda t: b"", r"not an nhfd calibration \(format = None\)"),
    "random": (lambda t: np.random.default_rng(21).bytes(4096), r"corrupt \("),
    "nan": (lambda t: t.replace("stage_scale = 1.0\n", "stage_scale = nan\n", 1).encode(),
            r"stage_scale = nan"),
    "missing_section": (lambda t: _without_section(t, "geometry").encode(),
                        r"missing or malformed key 'geometry'"),
}


@pytest.mark.parametrize("kind", sorted(CORRUPT_CALIBRATIONS))
def test_config_check_and_serve_refuse_a_corrupt_calibration(tmp_path, capsys, monkeypatch, kind):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("nhfd.daemon.service.Daemon", _NoDaemon)
    make, reason = CORRUPT_CALIBRATIONS[kind]
    text = _calibration_text()
    good = tmp_path / "good.toml"
    good.write_text(text)
    ok = write(tmp_path, "[calibration]\nfile = 'good.toml'\n", "ok.toml")
    assert main(["config", "check", str(ok)]) == 0
    assert capsys.readouterr().out == f"{ok}: ok\n"
    (tmp_path / "cal.toml").write_bytes(make(text))
    lab = write(tmp_path, "[calibration]\nfile = 'cal.toml'\n", "lab.toml")
    for argv in (["config", "check", str(lab)], ["serve", "--config", str(lab)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1, err  # one line
        assert err.startswith(f"nhfd {argv[0]}: error: {lab}: calibration.file = 'cal.toml': "
                              "calibration file cal.toml: ")
        assert re.search(reason, err), err


def test_serve_exits_2_on_a_cross_field_error(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("nhfd.daemon.service.Daemon", _NoDaemon)
    lab = write(tmp_path, "[daemon.frames]\nsize_px = [4096, 2160]\n", "lab.toml")
    assert main(["serve", "--config", str(lab)]) == 2
    err = capsys.readouterr().err
    assert err == (f"nhfd serve: error: {lab}: daemon.frames.size_px = [4096, 2160] does not fit "
                   "the panel 1920 x 1080 (slm.width_px x height_px)\n")


# -- device names: the one check every setting and flag uses -----------------------------------

ALL_DEVICES = "must be one of auto, cpu, cuda, cuda:N (N: a CUDA device index)"
NO_AUTO = ("cpu", "cuda", "cuda:N")


@pytest.mark.parametrize(
    ("value", "cuda_count", "allowed", "name"),
    [
        ("cpu", 0, DEVICES, "cpu"),
        (" CPU ", 0, DEVICES, "cpu"),
        ("cpu", None, NO_AUTO, "cpu"),
        ("cuda", 2, DEVICES, "cuda:0"),
        ("cuda:1", 2, DEVICES, "cuda:1"),
        ("CUDA:01", 2, NO_AUTO, "cuda:1"),
        ("auto", 0, DEVICES, "cpu"),
        ("auto", 2, DEVICES, "cuda:0"),
        ("auto", None, DEVICES, "auto"),  # the name only: nothing to pick with
        ("cuda:7", None, DEVICES, "cuda:7"),  # the name only: the index is not checked
    ],
)
def test_device_choice_returns_the_normalised_name(value, cuda_count, allowed, name):
    assert device_choice(value, "daemon.frames.device", cuda_count=cuda_count,
                         allowed=allowed) == name


@pytest.mark.parametrize(
    ("value", "cuda_count", "setting", "allowed", "message"),
    [
        *[(bad, count, "daemon.frames.device", DEVICES,
           rf"daemon\.frames\.device = {re.escape(repr(bad))}: " + re.escape(ALL_DEVICES))
          for bad in ("gpu", "cuda:x", "cudaXYZ", "cuda:-1", "", "cuda:", "cpu:0", "auto:1")
          for count in (None, 0, 2)],
        ("cuda:2", 2, "--device", DEVICES,
         r"--device = 'cuda:2': torch \S+ sees 2 CUDA devices \(indices 0\.\.1\); "
         r"use \"auto\" or \"cpu\""),
        ("cuda:1", 1, "device", DEVICES,
         r"device = 'cuda:1': torch \S+ sees 1 CUDA device \(index 0\); use \"auto\" or \"cpu\""),
        ("cuda", 0, "daemon.frames.device", DEVICES,
         r"daemon\.frames\.device = 'cuda': torch \S+ sees 0 CUDA devices \(a CPU-only build, "
         r"no GPU, or no driver\); use \"auto\" or \"cpu\""),
        # a setting that takes no "auto" lists what it takes, and offers only the CPU
        ("auto", 2, "--device", NO_AUTO,
         r"--device = 'auto': must be one of cpu, cuda, cuda:N \(N: a CUDA device index\)"),
        ("cuda:0", 0, "--device", NO_AUTO,
         r"--device = 'cuda:0': torch \S+ sees 0 CUDA devices .*; use \"cpu\""),
        ("cuda:1", None, "x", ("auto", "cpu", "cuda"), r"x = 'cuda:1': must be one of auto, cpu, "
         r"cuda"),
    ],
)
def test_device_choice_refuses_naming_the_setting_the_value_and_what_is_allowed(
        value, cuda_count, setting, allowed, message):
    with pytest.raises(ValueError) as info:
        device_choice(value, setting, cuda_count=cuda_count, allowed=allowed)
    assert re.fullmatch(message, str(info.value)), str(info.value)


def test_daemon_device_is_checked_by_name_when_the_file_is_read(tmp_path):
    config = check_file(write(tmp_path, "[daemon.frames]\ndevice = 'cuda:3'\n"))
    assert config.daemon.frames.device == "cuda:3"
    path = write(tmp_path, "[daemon.frames]\ndevice = 'gpu'\n")
    with pytest.raises(ConfigError) as info:
        check_file(path)
    assert str(info.value) == f"{path}: daemon.frames.device = 'gpu': {ALL_DEVICES}"
