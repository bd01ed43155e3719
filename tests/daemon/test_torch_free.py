"""`nhfd serve` with nothing configured stays a small process: no torch, numba or onnxruntime
(issue 22: they cost +183 MB RSS and +1.2 s at start, for a daemon that computes nothing)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

# Every device "none", no model, scene or calibration: the daemon starts, serves and shuts
# down, and reports the heavy modules it imported on the way.
_PROBE = textwrap.dedent("""
    import shutil, sys, tempfile, threading, tomllib
    from pathlib import Path

    from nhfd.config import Config, _overlay, default_text
    from nhfd.daemon.client import Client
    from nhfd.daemon.service import Daemon

    root = Path(tempfile.mkdtemp(prefix="nhfd-t-", dir="/tmp"))
    user = {"devices": {"laser": "none", "slm": "none", "stage": "none", "camera": "none",
                        "navigator": "none"},
            "daemon": {"server": {"runtime_dir": str(root / "run")}}}
    config = Config.model_validate(_overlay(tomllib.loads(default_text()), user))
    assert (config.daemon.frames.model, config.daemon.paths.scene,
            config.calibration.file) == ("", "", "")
    daemon = Daemon(config, base_dir=root, env={}, handle_signals=False)
    daemon.start()
    loop = threading.Thread(target=daemon.run, daemon=True)
    loop.start()
    status = Client(daemon.socket_path).status()
    daemon.request_shutdown("probe over")
    loop.join(10)
    assert not loop.is_alive(), "the control loop did not stop"
    shutil.rmtree(root, ignore_errors=True)
    print("model:", status["model"])
    print("heavy:", sorted(m for m in ("torch", "numba", "onnxruntime") if m in sys.modules))
    above = {"nhfd.pipeline", "nhfd.models", "nhfd.calib"}
    print("above the daemon:", sorted(m for m in sys.modules
                                      if ".".join(m.split(".")[:2]) in above))
""")


def test_a_daemon_with_nothing_configured_imports_no_torch_numba_or_onnxruntime():
    done = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "model: none loaded" in done.stdout, done.stdout
    assert "heavy: []" in done.stdout, done.stdout
    # The frame pipeline, the models and calib are the spawned worker's (by name), never loaded
    # in the daemon's own process.
    assert "above the daemon: []" in done.stdout, done.stdout
