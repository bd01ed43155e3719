"""The README's serving block runs as written, on the simulated bench, in a fresh folder: the
commands a new user copies, in order, against a real `nhfd serve` started by the block itself.
What the text promises is asserted from the commands' own output: the daemon answers, the
view is shown, the stage focuses, the snapshot has signal above the camera's noise with a
preview beside it and no warning, and the lasers are off when the block ends."""

from __future__ import annotations

import os
import re
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

REPO = Path(__file__).resolve().parents[1]


def readme_block(heading: str) -> str:
    """The first ```sh block after the README heading `heading`."""
    text = (REPO / "README.md").read_text()
    start = text.index(heading)
    m = re.search(r"```sh\n(.*?)```", text[start:], re.S)
    assert m, f"no sh block after {heading!r}"
    return m.group(1)


@pytest.mark.skipif(not (REPO / ".venv" / "bin" / "nhfd").exists(),
                    reason="the README's commands use .venv/bin (make test creates it)")
def test_the_serving_block_runs_as_written():
    block = readme_block("## Serving the bench")
    with tempfile.TemporaryDirectory(prefix="nhfd-readme-", dir="/tmp") as tmp:
        root = Path(tmp)
        for name in (".venv", "models"):  # what a clone has beside the commands
            (root / name).symlink_to(REPO / name)
        (root / "run").mkdir(mode=0o700)
        env = {k: v for k, v in os.environ.items() if not k.startswith("NHFD_")}
        env.update(XDG_RUNTIME_DIR=str(root / "run"), HOME=str(root))
        # As a person pastes it, each command echoed; the daemon's logs apart.
        script = f"set -e\nexec 3>{root / 'serve.log'}\n" + block.replace(
            "nhfd serve &", "nhfd serve 2>&3 &")
        res = subprocess.run(["bash", "-c", script], cwd=root, env=env, capture_output=True,
                             text=True, timeout=300)
        out = res.stdout
        assert res.returncode == 0, (out, res.stderr, (root / "serve.log").read_text()[-3000:])
        assert re.search(r"^daemon   ready", out, re.M), out
        assert "loaded nhf-donut-512.onnx" in out and "view seq 1: orbit azimuth 30 deg" in out
        assert re.search(r"job \d+ \(focus\) done .*: z 1\.5 mm, stage [\d.]+ mm", out), out
        snap = re.search(r"job \d+ \(snapshot\) done .*: path (\S+), preview (\S+),.*"
                         r"emitting green", out)
        assert snap and "warning" not in out, out
        image = np.asarray(Image.open(snap.group(1)), np.float64)
        preview = np.asarray(Image.open(snap.group(2)))
        assert image.shape == preview.shape and preview.dtype == np.uint8
        # Signal above the noise floor: the view's light stands out of the sensor's dark level.
        dark = np.median(image)
        noise = 1.4826 * np.median(np.abs(image - dark))  # the sensor noise, robustly
        peak = np.percentile(image, 99.9)
        assert peak - dark > 5 * noise, (peak, dark, noise)
        log = (root / "serve.log").read_text()
        assert "stopped; lasers: read back off through the guardian" in log, log[-2000:]
