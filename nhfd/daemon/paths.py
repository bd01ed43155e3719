"""Where the daemon lives (runtime directory, socket, lock) and which files it may touch.

Standard library only: the client resolves the socket path with the same rules.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from .protocol import PATH_NOT_ALLOWED, RpcError

SOCKET_NAME = "control.sock"
LOCK_NAME = "nhfd.lock"
TOKEN_NAME = "tcp.token"


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


def control_socket(configured_runtime_dir: str = "",
                   env: Mapping[str, str] | None = None) -> Path:
    return runtime_dir(configured_runtime_dir, env) / SOCKET_NAME


def resolve_dirs(dirs: Sequence[str], base: Path) -> list[Path]:
    """Allowed directories as absolute, symlink-free paths (relative ones from `base`)."""
    return [(base / Path(d).expanduser()).resolve() for d in dirs]


def inside(field: str, raw: str, allowed: Sequence[Path], base: Path) -> Path:
    """`raw` resolved (symlinks and `..` included) if it lies inside one of `allowed`; otherwise
    RpcError(PATH_NOT_ALLOWED) naming the field and the allowed directories. Relative paths are
    taken from the first allowed directory."""
    if not allowed:
        raise RpcError(PATH_NOT_ALLOWED, f"{field}: no directories are configured for this",
                       {"field": field, "allowed": []})
    path = Path(raw).expanduser()
    resolved = (path if path.is_absolute() else allowed[0] / path).resolve()
    for root in allowed:
        if resolved == root or resolved.is_relative_to(root):
            return resolved
    shown = [str(a) for a in allowed]
    raise RpcError(PATH_NOT_ALLOWED,
                   f"{field} = {raw!r} resolves to {resolved}, outside the allowed "
                   f"directories {', '.join(shown)}",
                   {"field": field, "allowed": shown})
