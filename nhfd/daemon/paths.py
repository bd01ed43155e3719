"""Where the daemon lives (runtime directory, socket, lock) and which files it may touch.

Standard library only: the client resolves the socket path with the same rules, which live in
`nhfd.drivers.rundir` (shared with the laser guardian and `nhfd laser-off`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from nhfd.drivers.rundir import UnsafeDirectory, check_private_dir, make_private_dir, runtime_dir

from .protocol import PATH_NOT_ALLOWED, RpcError

if TYPE_CHECKING:  # the annotation only: the client imports this module without pydantic
    from nhfd.config import Config

__all__ = ["UnsafeDirectory", "check_private_dir", "make_private_dir", "runtime_dir"]

SOCKET_NAME = "control.sock"
LOCK_NAME = "nhfd.lock"
TOKEN_NAME = "tcp.token"


def control_socket(configured_runtime_dir: str = "",
                   env: Mapping[str, str] | None = None) -> Path:
    """The control socket in the runtime directory (`daemon.server.runtime_dir`, else the default
    one for this user and environment)."""
    return runtime_dir(configured_runtime_dir, env) / SOCKET_NAME


def socket_path(socket_arg: str | None, config: Config | Callable[[], Config]) -> str:
    """The control socket a command talks to: its `--socket` when given, else the configured
    daemon's (`config.daemon.server.runtime_dir`, by the daemon's own rules). `config` may be a
    function that loads the configuration: it is then called only when no `--socket` is given, so a
    command given one reads no configuration."""
    if socket_arg:
        return str(socket_arg)
    if callable(config):
        config = config()
    return str(control_socket(config.daemon.server.runtime_dir))


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
