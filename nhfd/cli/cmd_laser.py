"""`nhfd laser-off` and `nhfd laser-guardian`: laser safety from any shell.

`laser-off` asks the guardian to switch every channel off and read it back; when no guardian
answers it opens the laser port itself (identify first, then all off, read back). Exit code 0
only when the channels were read back off. It is what the service manager's stop hook runs.

Drivers are imported inside the handlers so `nhfd --help` stays instant.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any


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


def _settings(args: argparse.Namespace) -> Any:
    """LaserSettings from the configuration's [devices.readybeam], with the command line's port
    and socket on top. A broken configuration file must not stop an emergency off, so it is
    reported and the defaults are used."""
    from nhfd.drivers.settings import LaserSettings

    settings = LaserSettings()
    try:
        from nhfd.config import load_config

        settings = load_config(args.config).config.devices.readybeam
    except Exception as exc:
        print(f"nhfd {args.command}: warning: configuration not used: {exc}", file=sys.stderr)
    update: dict[str, Any] = {}
    if args.port:
        update.update(port=args.port, usb_serial="")
    if args.usb_serial:
        update.update(usb_serial=args.usb_serial, port="")
    if args.socket:
        update["guardian"] = settings.guardian.model_copy(update={"socket_path": args.socket})
    return settings.model_copy(update=update) if update else settings


def _laser_off(args: argparse.Namespace) -> int:
    from nhfd.drivers.errors import DeviceError, PortBusy
    from nhfd.drivers.guardian import (
        GuardianClient,
        GuardianError,
        GuardianUnavailable,
        socket_path_for,
    )
    from nhfd.drivers.laser import MecomLaser

    settings = _settings(args)
    path = socket_path_for(settings)
    try:
        with GuardianClient(path, timeout_s=args.timeout_s) as client:
            client.all_off()
        print(f"all laser channels off (read back by the guardian at {path})")
        return 0
    except GuardianUnavailable as exc:
        reason = str(exc)
    except GuardianError as exc:
        print(f"nhfd laser-off: error: {exc}", file=sys.stderr)
        return 1
    if not (settings.port or settings.usb_serial):
        print(f"nhfd laser-off: error: {reason}, and no laser port is configured "
              "(--port or --usb-serial)", file=sys.stderr)
        return 1
    laser = MecomLaser(settings)
    try:
        laser.open()  # identifies, then switches every channel off and reads it back
        laser.close()
    except PortBusy as exc:
        print(f"nhfd laser-off: error: {reason}; {exc} (a hung guardian? stop it, then retry)",
              file=sys.stderr)
        return 1
    except DeviceError as exc:
        print(f"nhfd laser-off: error: {exc}", file=sys.stderr)
        return 1
    print(f"all laser channels off (read back on {settings.port or settings.usb_serial}; "
          f"no guardian: {reason})")
    return 0


def _guardian(args: argparse.Namespace) -> int:
    import logging

    from nhfd.drivers.guardian import run

    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s laser-guardian %(levelname)s %(message)s")
    return run(_settings(args), args.socket)
