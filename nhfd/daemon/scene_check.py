"""A scene file read in a child process under a memory budget, for the daemon's load_scene.

Why a child process: a scene file is untrusted input, and reading one costs memory and CPU in
proportion to what it declares (up to `[daemon.paths] max_gaussians` Gaussians, a few hundred bytes
each while decoding). Read in the daemon, as load_scene did, that memory is the daemon's and a
long decode holds the GIL against the control loop that feeds the laser guardian's heartbeat
(a 12 MB .spz bomb took the daemon to 4.9 GB and stalled the loop 5 s, issue 32). In a child:

* its address space is limited (RLIMIT_AS) to what the interpreter holds after its imports
  plus `[daemon.paths] scene_memory_mb`: a file that needs more fails there with MemoryError, which
  is reported as the budget it exceeded, and the daemon's memory does not move;
* the daemon's thread only waits on a pipe, so the control loop keeps its time;
* a cancelled job (`stop`) or one past its time kills the child.

Only the summary the job reports comes back (counts, as `SceneLoad.counts()`), not the
Gaussians: the frame worker, which renders, reads its own copy after the check passed.
"""

from __future__ import annotations

import builtins
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from nhfd.scene.gaussians import SceneFileError

__all__ = ["SCENE_READ_TIMEOUT_S", "read_scene_counts"]

# How long a scene read may take in the child: the frame worker's own load is given as long
# (frame_link.LOAD_TIMEOUT_S); a scene of max_gaussians reads in well under this on 2 cores.
SCENE_READ_TIMEOUT_S = 120.0
# How often the waiting job looks at its cancel flag.
_POLL_S = 0.1
# The child's program. Its imports come first (what the readers load on demand too: Pillow's
# WebP plugin, zstandard), so the budget counts the scene's memory, not the interpreter's.
_CHILD = r"""
import errno, json, re, resource, sys
import PIL.Image, PIL.WebPImagePlugin, zstandard
from nhfd.scene.io import read_scene

path, max_gaussians, budget = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
try:
    with open("/proc/self/status") as f:
        base = int(re.search(r"VmSize:\s+(\d+) kB", f.read()).group(1)) * 1024
except (OSError, AttributeError):
    base = 256 << 20  # no /proc: an allowance for the interpreter
limit = base + budget
_, hard = resource.getrlimit(resource.RLIMIT_AS)
if hard != resource.RLIM_INFINITY:
    limit = min(limit, hard)
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
try:
    out = {"ok": True, "counts": read_scene(path, max_gaussians).counts()}
except MemoryError:
    out = {"ok": False, "type": "MemoryError", "message": ""}
except Exception as e:
    if isinstance(e, OSError) and e.errno == errno.ENOMEM:  # a refused mmap
        out = {"ok": False, "type": "MemoryError", "message": ""}
    else:
        out = {"ok": False, "type": type(e).__name__, "message": str(e)}
sys.stdout.write(json.dumps(out))
"""


def _environment() -> dict[str, str]:
    """The daemon's environment, one BLAS/OpenMP thread (each reserves address space, and the
    child does no linear algebra), and the daemon's import path, so the child finds nhfd
    however the daemon found it."""
    env = dict(os.environ)
    env.update({var: "1" for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                     "MKL_NUM_THREADS")})
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
    return env


def read_scene_counts(path: Path, max_gaussians: int, memory_mb: int,
                      check: Callable[[], None] = lambda: None,
                      timeout_s: float = SCENE_READ_TIMEOUT_S) -> dict[str, Any]:
    """`read_scene(path, max_gaussians).counts()`, computed in a child process whose memory
    beyond its imports is limited to `memory_mb` MiB. Raises what the read raised (a
    SceneFileError naming the file and the problem; an OSError by its type), a SceneFileError
    naming `[daemon.paths] scene_memory_mb` when the read needs more memory, TimeoutError past
    `timeout_s`. `check` is called while waiting (a job's cancel check): whatever it raises
    ends the child first."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(path), str(int(max_gaussians)),
         str(int(memory_mb) << 20)],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        env=_environment(), close_fds=True)
    deadline_s = time.monotonic() + timeout_s
    try:
        while True:
            try:
                out, err = proc.communicate(timeout=_POLL_S)
                break
            except subprocess.TimeoutExpired:
                check()
                if time.monotonic() >= deadline_s:
                    raise TimeoutError(f"{path}: reading the scene took more than "
                                       f"{timeout_s:g} s") from None
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    try:
        result = json.loads(out)
    except ValueError:
        tail = err.decode(errors="replace").strip()[-400:]
        raise RuntimeError(f"{path}: the scene reader ended with exit status {proc.returncode} "
                           f"and no result{f' ({tail})' if tail else ''}") from None
    if result["ok"]:
        return result["counts"]
    kind, message = result["type"], result["message"]
    if kind == "MemoryError":
        raise SceneFileError(f"{path}: reading the scene needs more than "
                             f"daemon.paths.scene_memory_mb = {memory_mb} MiB (allowed: 64 to "
                             "1048576 MiB)")
    cls = SceneFileError if kind == "SceneFileError" else getattr(builtins, kind, None)
    if not (isinstance(cls, type) and issubclass(cls, Exception)):
        cls = RuntimeError
        message = f"{kind}: {message}"
    raise cls(message)
