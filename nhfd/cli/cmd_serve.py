"""`nhfd serve`: run the daemon in the foreground (systemd Type=notify ready).

Imports the daemon, which is torch-free at module level: a daemon with nothing configured never
loads torch, numba or onnxruntime (the frame pipeline runs in its own process).
Exit codes: 0 clean shutdown with lasers read back off, 1 lasers not confirmed off or a failed
start, 2 configuration error, 3 another daemon holds the lock.

With `[daemon.web] enabled = true` it also serves the live web view (nhfd.web.server, the `web`
extra: aiohttp) on a thread, a client of the daemon's own Unix socket; it stops with the daemon.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import sys

from nhfd.calibration import check_calibration_file
from nhfd.config import load_config
from nhfd.daemon import service


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="run the bench daemon in the foreground",
        description="Run the daemon: laser guardian, devices (lasers off and read back), the "
        "JSON-RPC control socket; logs to stderr; systemd Type=notify ready. Steer it with "
        "nhfctl.",
    )
    p.add_argument("--config", help="configuration file")
    p.add_argument("--scene", help="scene to load at start (inside daemon.paths.scene_dirs)")
    p.add_argument("--runtime-dir", help="runtime directory (overrides daemon.server.runtime_dir)")
    p.add_argument("--record", metavar="FILE",
                   help="record every bench-changing request to FILE (JSON lines; overrides "
                   "daemon.audit.record); `nhfd replay FILE` plays it back")
    p.set_defaults(handler=_serve)


def _serve(args: argparse.Namespace) -> int:
    loaded = load_config(args.config)  # a ConfigError: one line, exit 2 (nhfd.cli.main)
    config = loaded.config
    calibration = check_calibration_file(config, str(loaded.path or "packaged default"))
    # The flags replace one key each, in its section (daemon.paths.scene, daemon.server.runtime_dir,
    # daemon.audit.record).
    settings = config.daemon
    sections = {}
    if args.scene:
        sections["paths"] = settings.paths.model_copy(update={"scene": args.scene})
    if args.runtime_dir:
        sections["server"] = settings.server.model_copy(update={"runtime_dir": args.runtime_dir})
    if args.record:
        sections["audit"] = settings.audit.model_copy(update={"record": args.record})
    if sections:
        config = config.model_copy(update={"daemon": settings.model_copy(update=sections)})
    web = config.daemon.web
    if web.enabled and importlib.util.find_spec("aiohttp") is None:
        print("nhfd serve: error: daemon.web.enabled = true needs the web extra: "
              "pip install 'nhfd[web]'", file=sys.stderr)
        return 2
    service.setup_logging(config.daemon.audit.log_format)
    daemon = service.Daemon(config, calibration=calibration)
    try:
        daemon.start()
    except service.AlreadyRunning as exc:
        print(f"nhfd serve: error: {exc}", file=sys.stderr)
        return 3
    except Exception as exc:
        print(f"nhfd serve: error: start failed, lasers left to the guardian: "
              f"{type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    view = None
    if web.enabled:
        try:
            view = _start_web(daemon)
        except Exception as exc:
            print(f"nhfd serve: error: the web view did not start: {type(exc).__name__}: {exc}",
                  file=sys.stderr)
            daemon.request_shutdown("the web view did not start")
            daemon.run()  # the loop sees the request at once: lasers off, read back, closed
            return 1
    try:
        return daemon.run()
    finally:
        if view is not None:
            view.stop()


def _start_web(daemon: service.Daemon):  # -> nhfd.web.server.WebView
    # The optional path: aiohttp loads only when [daemon.web] is enabled (a listed seam).
    from nhfd.web.server import serve_web_view

    view = serve_web_view(daemon.config.daemon, socket_path=daemon.socket_path,
                          runtime_dir=daemon.runtime_dir, base_dir=daemon.base_dir,
                          tcp_token=daemon.rpc.tcp_token, audit=daemon.audit)
    logging.getLogger("nhfd.web").info("web view at %s (token in %s)", view.url,
                                       view.token_source)
    return view
