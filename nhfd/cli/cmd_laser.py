"""`nhfd laser-off` and `nhfd laser-guardian`: laser safety from any shell.

`laser-off` asks the guardian to switch every channel off and read it back; when no guardian
answers it opens the laser port itself (identify first, then all off, read back). Exit code 0
only when the channels were read back off by something it trusts: a guardian in a safe
directory, running as this user, driving the configured port; or its own port read-back. A hung
nhfd guardian of this user (verified in /proc) is killed first, which frees the port. It is what
the service manager's stop hook runs.

The emergency path stays light: this module imports the vocabulary and the laser drivers only
(no torch, numba or numpy compute), and `nhfd` imports it only for these two commands.
`nhfctl laser off` and `laser disarm` use the same path (`laser_settings`, `switch_all_off`)
whenever the daemon does not switch the lasers off itself.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from nhfd.config import ServerSettings, load_config
from nhfd.device_settings import LaserSettings
from nhfd.drivers.errors import DeviceError, PortBusy
from nhfd.drivers.guardian import (
    GuardianClient,
    GuardianError,
    GuardianRefused,
    GuardianUnavailable,
    GuardianUnresponsive,
    guardian_pid,
    guardian_port,
    is_our_guardian,
    kill_guardian,
    port_holders,
    run,
    socket_path_for,
    verify_guardian,
)
from nhfd.drivers.laser import MecomLaser
from nhfd.drivers.rundir import UnsafeDirectory, check_private_dir, runtime_dir
from nhfd.drivers.transport import same_port


def register(sub: argparse._SubParsersAction) -> None:
    off = sub.add_parser(
        "laser-off",
        help="switch every laser channel off and read it back",
        description="Switch every laser channel off through the laser guardian, or directly on "
        "the laser port when no guardian answers; exit code 0 only when read back off.",
    )
    _common(off)
    off.add_argument("--timeout-s", type=float, default=3.0,
                     help="how long to wait for the guardian (default 3)")
    off.set_defaults(handler=_laser_off)

    guard = sub.add_parser(
        "laser-guardian",
        help="run the laser guardian in the foreground",
        description="Own the laser port, listen on the guardian socket, and switch every channel "
        "off when the daemon's heartbeat stops.",
    )
    _common(guard)
    guard.set_defaults(handler=_guardian)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="configuration file (its [devices.readybeam] section)")
    p.add_argument("--socket", help="guardian socket path")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--port", help="laser port path, e.g. /dev/ttyUSB0")
    where.add_argument("--usb-serial", help="USB serial number of the laser's port")


def _settings(args: argparse.Namespace) -> tuple[LaserSettings, ServerSettings | None]:
    return laser_settings(args.config, port=args.port or "", usb_serial=args.usb_serial or "",
                          guardian_socket=args.socket or "", prog=f"nhfd {args.command}")


def laser_settings(config: str | None = None, *, port: str = "", usb_serial: str = "",
                   guardian_socket: str = "", prog: str = "nhfd laser-off"
                   ) -> tuple[LaserSettings, ServerSettings | None]:
    """LaserSettings from the configuration's [devices.readybeam], with a port and guardian
    socket given on the command line on top, and [daemon.server] (runtime directory, socket
    group; None when the configuration could not be read). A broken configuration file must not
    stop an emergency off, so it is reported (as `prog`) and the defaults are used."""

    settings, server = LaserSettings(), None
    try:
        loaded = load_config(config).config
        settings, server = loaded.devices.readybeam, loaded.daemon.server
    except Exception as exc:
        print(f"{prog}: warning: configuration not used: {exc}", file=sys.stderr)
    update: dict[str, Any] = {}
    if port:
        update.update(port=port, usb_serial="")
    if usb_serial:
        update.update(usb_serial=usb_serial, port="")
    if guardian_socket:
        update["guardian"] = settings.guardian.model_copy(update={"socket_path": guardian_socket})
    return (settings.model_copy(update=update) if update else settings), server


def _off_through_guardian(settings: LaserSettings, path: Path, group_ok: bool, timeout_s: float,
                          prog: str = "nhfd laser-off") -> str:
    """All off through a guardian this command can trust; returns what it did. Raises
    GuardianUnavailable (none answers; a hung one of ours is killed first) or GuardianRefused."""

    try:
        check_private_dir(path.parent, group_writable_ok=group_ok)
    except UnsafeDirectory as exc:
        raise GuardianRefused(f"laser guardian directory: {exc}") from None
    try:
        with GuardianClient(path, timeout_s=timeout_s) as client:
            hello = client.hello()
            port = str(hello.get("port") or "")
            if not port or (settings.port and not same_port(port, settings.port)):
                raise GuardianRefused(f"the laser guardian at {path} (pid {client.peer_pid}) "
                                      f"drives port {port!r}, not {settings.port!r}")
            verify_guardian(client.peer_pid, port, f"the laser guardian at {path}")
            client.all_off()
            st = client.status()
            on = [ch for ch, c in st["channels"].items()
                  if c["enabled"] or abs(c["power_pct"]) > settings.readback_tolerance_pct]
            if on or st["armed"]:
                raise GuardianRefused(f"guardian at {path} says off but reads back {on}")
            return f"read back by the guardian at {path}, pid {client.peer_pid}, port {port}"
    except GuardianUnresponsive as exc:
        pid = guardian_pid(path, settings.port)
        port = guardian_port(pid) if pid is not None else ""
        if pid is None or not kill_guardian(pid):
            raise GuardianRefused(f"{exc}, and no nhfd guardian of this user to end") from None
        print(f"{prog}: {exc}: killed the hung guardian, pid {pid}", file=sys.stderr)
        raise _HungGuardianKilled(f"{exc}; hung guardian pid {pid} killed", port) from None


class _HungGuardianKilled(Exception):
    """The port is free now; `port` is the one the killed guardian drove ("" if unknown)."""

    def __init__(self, message: str, port: str) -> None:
        super().__init__(message)
        self.port = port


def _end_guardian_holding(port: str, prog: str = "nhfd laser-off") -> bool:
    """An nhfd guardian of this user holds `port` but did not answer on the socket asked (hung,
    or serving another socket): SIGKILL it (verified in /proc), which frees the port."""

    if not port:
        return False
    pids = [pid for pid in port_holders(port) if pid != os.getpid() and is_our_guardian(pid)]
    for pid in pids:
        kill_guardian(pid)
        print(f"{prog}: killed nhfd guardian pid {pid}, which held {port}", file=sys.stderr)
    return bool(pids)


@dataclass(frozen=True)
class OffOutcome:
    """What `switch_all_off` achieved."""

    confirmed: bool  # every channel read back off, by a guardian it trusts or on the port itself
    how: str  # what read them back off, or why they are not confirmed off


def _laser_off(args: argparse.Namespace) -> int:
    settings, server = _settings(args)
    path = socket_path_for(settings, runtime_dir(server.runtime_dir if server else ""))
    outcome = switch_all_off(settings, path, server, timeout_s=args.timeout_s)
    if outcome.confirmed:
        print(f"all laser channels off ({outcome.how})")
        return 0
    print(f"nhfd laser-off: error: {outcome.how}", file=sys.stderr)
    return 1


def switch_all_off(settings: LaserSettings, path: Path, server: ServerSettings | None, *,
                   timeout_s: float = 3.0, prog: str = "nhfd laser-off",
                   port_hint: str = "--port or --usb-serial") -> OffOutcome:
    """Every laser channel off without the daemon: through the guardian at `path` if it can be
    trusted, else directly on the configured port (a hung nhfd guardian of this user is killed
    first, which frees it). Notes on the way go to stderr as `prog`; `port_hint` says where a
    port would be given when none is configured. `server`: `[daemon.server]` (its socket
    group lets the guardian's directory be group-writable; None: the configuration could not
    be read)."""
    group_ok = bool(server and server.socket_group)
    try:
        return OffOutcome(True, _off_through_guardian(settings, path, group_ok, timeout_s,
                                                      prog))
    except _HungGuardianKilled as exc:
        reason = str(exc)
        if not (settings.port or settings.usb_serial) and exc.port:
            settings = settings.model_copy(update={"port": exc.port})
    except GuardianUnavailable as exc:
        reason = str(exc)
    except GuardianRefused as exc:
        reason = f"refused: {exc}"
        print(f"{prog}: {reason}", file=sys.stderr)
    except GuardianError as exc:
        return OffOutcome(False, str(exc))
    if not (settings.port or settings.usb_serial):
        return OffOutcome(False, f"{reason}, and no laser port is configured ({port_hint})")
    laser = MecomLaser(settings)
    try:
        try:
            laser.open()  # identifies, then switches every channel off and reads it back
        except PortBusy:
            if not _end_guardian_holding(settings.port, prog):
                raise
            laser.open()
        laser.close()
    except PortBusy as exc:
        return OffOutcome(False, f"{reason}; {exc} (not an nhfd guardian of this user: stop "
                          "it, then retry)")
    except DeviceError as exc:
        return OffOutcome(False, str(exc))
    return OffOutcome(True, f"read back on {settings.port or settings.usb_serial}; no guardian "
                      f"used: {reason}")


def _guardian(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s laser-guardian %(levelname)s %(message)s")
    settings, server = _settings(args)
    # The same socket the daemon of this configuration looks for (its runtime directory).
    path = socket_path_for(settings, runtime_dir(server.runtime_dir if server else ""))
    return run(settings, str(path), group_writable_ok=bool(server and server.socket_group))
