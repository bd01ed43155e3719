"""`nhfd warmup` compiles the frame path's kernels into numba's disk cache, and a later process
loads them from it instead of compiling (the first view after an install took 25 s)."""

from __future__ import annotations

import json
import os
import subprocess
import sys


def _warm(cache_dir: str) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir}
    res = subprocess.run([sys.executable, "-m", "nhfd.cli.main", "warmup", "--json"],
                         capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_warmup_fills_the_kernel_cache_that_the_next_process_hits(tmp_path):
    first = _warm(str(tmp_path))
    kernels = first["kernels"]
    # The renderer's and the coder's kernels ran, each compiled in the empty cache.
    assert any(k.startswith("_kernels.") for k in kernels), kernels
    assert any(k.startswith("_coding.") for k in kernels), kernels
    assert all(k["misses"] >= 1 and k["hits"] == 0 for k in kernels.values()), kernels
    assert any(p.suffix == ".nbc" for p in tmp_path.rglob("*")), "nothing cached"
    second = _warm(str(tmp_path))
    assert second["kernels"].keys() == kernels.keys()
    assert all(k["misses"] == 0 and k["hits"] >= 1 for k in second["kernels"].values()), second
