"""Runtime directories (sockets, lock, tokens) and the rule that makes them trustworthy.

Standard library only: the daemon, its client, the laser guardian and `nhfd laser-off` all
resolve the same directory with the same rules, and refuse it by the same rule.

Without $XDG_RUNTIME_DIR (sudo, cron, ssh without logind) the directory is /tmp/nhfd-<uid>,
which any local user can create first and fill with a fake guardian. So a directory is used only
when it belongs to this user and no one else can write to it (the group only where the daemon's
socket group is configured, which needs a group-writable directory).
"""

from __future__ import annotations

import os
import stat
from collections.abc import Mapping
from pathlib import Path

GUARDIAN_SOCKET_NAME = "laser.sock"


class UnsafeDirectory(Exception):
    """A runtime or guardian directory that another user owns or may write to."""


def runtime_dir(configured: str = "", env: Mapping[str, str] | None = None) -> Path:
    """The configured directory, else systemd's $RUNTIME_DIRECTORY, else $XDG_RUNTIME_DIR/nhfd,
    else /tmp/nhfd-<uid> (the guardian's default socket sits in the same place)."""
    env = os.environ if env is None else env
    if configured:
        return Path(configured).expanduser()
    if env.get("RUNTIME_DIRECTORY"):
        # systemd may list several, separated by ':'; the first is ours.
        return Path(env["RUNTIME_DIRECTORY"].split(":")[0])
    if env.get("XDG_RUNTIME_DIR"):
        return Path(env["XDG_RUNTIME_DIR"]) / "nhfd"
    return Path(f"/tmp/nhfd-{os.getuid()}")


def check_private_dir(path: str | os.PathLike[str], *, group_writable_ok: bool = False) -> None:
    """UnsafeDirectory unless `path` is a directory owned by this user that nobody else may write
    to (its group may, when `group_writable_ok`: the configured daemon.server.socket_group)."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise UnsafeDirectory(f"{path}: no such directory") from None
    mode = stat.S_IMODE(st.st_mode)
    rule = (f"it must belong to uid {os.getuid()} and be writable by no one else "
            "(group-writable only with daemon.server.socket_group set)")
    problem = None
    if not stat.S_ISDIR(st.st_mode):
        problem = "is not a directory"
    elif st.st_uid != os.getuid():
        problem = f"belongs to uid {st.st_uid}"
    elif mode & stat.S_IWOTH:
        problem = "is writable by other users"
    elif mode & stat.S_IWGRP and not group_writable_ok:
        problem = "is group-writable"
    if problem:
        raise UnsafeDirectory(f"{path} {problem} (owner uid {st.st_uid}, mode {mode:04o}); "
                              f"refusing it: {rule}")


def make_private_dir(path: str | os.PathLike[str], *, group_writable_ok: bool = False,
                     mode: int = 0o700) -> Path:
    """Create `path` (mode `mode`) if missing, then `check_private_dir` it."""
    path = Path(path)
    path.mkdir(mode=mode, parents=True, exist_ok=True)
    check_private_dir(path, group_writable_ok=group_writable_ok)
    return path
