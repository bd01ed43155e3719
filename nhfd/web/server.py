"""The web view's server: aiohttp on a thread of `nhfd serve`, a client of the daemon's socket.

    GET  /             the page (with the token: ?token=... once, or the login form's POST
                       /login, sets an HttpOnly SameSite=Strict cookie); 401 without it
    GET  /ws           the WebSocket (the cookie again; 401 before the upgrade without it, 403
                       from another origin): state pushed every push_interval_s, operations in
    GET  /snapshots/N  a snapshot PNG the page asked for (daemon.snapshot_dir)
    GET  /static/...   the page's script and style

Pushed: {"type": "state", "status": <the daemon's status>, "fps": frames per second shown,
"slm": thumbnail, "camera": thumbnail} (a thumbnail is sent again only when it changed) or
{"type": "state", "daemon_error": why}. Operations: {"id", "op": one of OPERATIONS, ...} answered
{"type": "reply", "id", "op", "ok", "result" | "error": {"name", "message"}}.

Arming is not an operation: the page cannot arm the lasers whatever it sends (`refused`), and
the daemon's own rule (arming only from a person on the bench's machine) stays the authority.
"""

from __future__ import annotations

import asyncio
import base64
import collections
import contextlib
import hashlib
import hmac
import io
import json
import logging
import os
import re
import secrets
import ssl
import threading
import time
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from aiohttp import WSMsgType, web
from PIL import Image

from nhfd.config import LOOPBACK_HOSTS, WebSettings
from nhfd.daemon.client import Client, DaemonUnavailable
from nhfd.daemon.protocol import DEVICE_ERROR, RpcError
from nhfd.daemon.server import server_tls_context

log = logging.getLogger("nhfd.web")

COOKIE = "nhfd_token"
TOKEN_NAME = "web.token"
# What the page may ask of the daemon, and the daemon method each becomes. `laser` is absent on
# purpose: arming must come from a person at the bench (the Unix socket); only "lasers_off" (all
# channels off, disarmed) reaches the laser from here.
OPERATIONS = ("focus", "view", "snapshot", "stop", "lasers_off")
FPS_WINDOW_S = 2.0
SNAPSHOT_WAIT_S = 60.0
SNAPSHOT_NAME = re.compile(r"[A-Za-z0-9._-]+\.png")
HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; connect-src 'self'; "
                               "style-src 'self'; script-src 'self'; frame-ancestors 'none'",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


class Refused(Exception):
    """An operation the web view does not offer (its message says why)."""


def web_token(settings: WebSettings, *, runtime_dir: Path, daemon_token: str | None,
              base_dir: Path) -> tuple[str, Path | None]:
    """The token the page asks for, and the file made for it (to remove at stop) or None."""
    if settings.token_file:
        path = base_dir / Path(settings.token_file).expanduser()
        token = path.read_text().strip()
        if not token:
            raise ValueError(f"daemon.web.token_file = {settings.token_file!r}: {path} is empty")
        return token, None
    if daemon_token:
        return daemon_token, None
    token = secrets.token_urlsafe(32)
    path = runtime_dir / TOKEN_NAME
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    return token, path


def serve_daemon(daemon: Any) -> WebView:
    """Start the web view of a started `nhfd.daemon.service.Daemon` (in this process) with its
    `[daemon.web]` settings, token and snapshot directory; `stop()` it before the daemon ends."""
    settings = daemon.config.daemon.web
    token, made = web_token(settings, runtime_dir=daemon.runtime_dir,
                            daemon_token=daemon.tcp_token, base_dir=daemon.base_dir)
    view = WebView(settings, socket_path=daemon.socket_path, token=token,
                   snapshot_dir=daemon.snapshot_dirs[0] if daemon.snapshot_dirs else None,
                   base_dir=daemon.base_dir, token_file_made=made)
    view.token_source = made or (
        daemon.base_dir / settings.token_file if settings.token_file
        else daemon.runtime_dir / "tcp.token")
    try:
        view.start()
    except BaseException:
        view.stop()
        raise
    return view


def tls_context(settings: WebSettings, base_dir: Path) -> ssl.SSLContext | None:
    if not settings.tls_cert:
        return None
    return server_tls_context(base_dir / Path(settings.tls_cert).expanduser(),
                              base_dir / Path(settings.tls_key).expanduser(), "daemon.web")


def thumbnail(preview: dict[str, Any]) -> dict[str, Any] | None:
    """The daemon's `preview` reply as a PNG data URL plus what it shows, or None."""
    if not preview.get("available"):
        return None
    h, w, c = preview["shape_hwc"]
    pixels = np.frombuffer(base64.b64decode(preview["pixels_b64"]), np.uint8).reshape(h, w, c)
    image = Image.fromarray(pixels[..., 0] if c == 1 else pixels, "L" if c == 1 else "RGB")
    buf = io.BytesIO()
    image.save(buf, "PNG", compress_level=1)  # fast: the frame changes often
    rest = {k: v for k, v in preview.items() if k not in ("pixels_b64", "available")}
    return {"png": "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode(), **rest}


class DaemonBridge:
    """One client of the daemon's Unix socket, one call at a time; a failed connection is
    dropped and made again on the next call (never a call retried: focus twice is not focus)."""

    def __init__(self, socket_path: Path, timeout_s: float = 5.0) -> None:
        self.socket_path = socket_path
        self.timeout_s = timeout_s
        self._client: Client | None = None
        self._lock = threading.Lock()

    def call(self, method: str, **params: Any) -> Any:
        with self._lock:
            if self._client is None:
                self._client = Client(self.socket_path, timeout_s=self.timeout_s)
            try:
                return self._client.call(method, **params)
            except DaemonUnavailable:
                self._client.close()
                self._client = None
                raise

    def close(self) -> None:
        with self._lock:
            if self._client is not None:
                self._client.close()
                self._client = None


class WebView:
    """The page's server, on its own thread and event loop (`start`, `stop`)."""

    def __init__(self, settings: WebSettings, *, socket_path: Path, token: str,
                 snapshot_dir: Path | None = None, base_dir: Path | None = None,
                 token_file_made: Path | None = None,
                 call: Callable[..., Any] | None = None) -> None:
        if settings.host not in LOOPBACK_HOSTS and not settings.tls_cert:
            raise ValueError(f"daemon.web.host = {settings.host!r} is not loopback: listening "
                             "elsewhere needs TLS, set daemon.web.tls_cert and daemon.web.tls_key")
        self.settings = settings
        self.token = token
        self.token_file_made = token_file_made  # removed at stop
        self.token_source: Path | None = token_file_made
        self.snapshot_dir = snapshot_dir
        self.base_dir = base_dir or Path.cwd()
        self.bridge = DaemonBridge(socket_path)
        self._call = call or self.bridge.call
        self.tls = tls_context(settings, self.base_dir)
        self.url: str | None = None
        self.port: int | None = None
        self._clients: dict[web.WebSocketResponse, dict[str, str]] = {}
        self._poller: asyncio.Task | None = None
        self._frames: collections.deque[tuple[float, int]] = collections.deque()
        self._images: dict[str, tuple[str, dict[str, Any] | None]] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._runner: web.AppRunner | None = None
        self._failed: BaseException | None = None

    # -- lifecycle -----------------------------------------------------------------------------

    def start(self, timeout_s: float = 10.0) -> str:
        """Listen; returns the page's URL (without the token). Raises what binding raised."""
        ready = threading.Event()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, args=(ready,), name="nhfd-web",
                                        daemon=True)
        self._thread.start()
        if not ready.wait(timeout_s):
            raise RuntimeError(f"the web view did not start within {timeout_s:g} s")
        if self._failed is not None:
            raise self._failed
        assert self.url is not None
        return self.url

    def _run(self, ready: threading.Event) -> None:
        loop = self._loop
        assert loop is not None
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._listen())
        except BaseException as exc:
            self._failed = exc
            ready.set()
            loop.close()
            return
        ready.set()
        try:
            loop.run_forever()
        finally:
            loop.run_until_complete(self._close())
            loop.close()

    async def _listen(self) -> None:
        app = web.Application(middlewares=[self._headers])
        app.router.add_get("/", self._page)
        app.router.add_post("/login", self._login)
        app.router.add_get("/ws", self._socket)
        app.router.add_get("/snapshots/{name}", self._snapshot_file)
        app.router.add_get("/static/{name}", self._static)
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        s = self.settings
        site = web.TCPSite(self._runner, s.host, s.port, ssl_context=self.tls)
        await site.start()
        self.port = self._runner.addresses[0][1]
        host = f"[{s.host}]" if ":" in s.host else s.host
        self.url = f"{'https' if self.tls else 'http'}://{host}:{self.port}/"

    async def _close(self) -> None:
        for ws in list(self._clients):
            with contextlib.suppress(Exception):
                await ws.close()
        if self._poller is not None:
            self._poller.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._poller
        if self._runner is not None:
            await self._runner.cleanup()

    def stop(self) -> None:
        if self._loop is not None and self._thread is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(10)
        self.bridge.close()
        if self.token_file_made is not None:
            with contextlib.suppress(OSError):
                self.token_file_made.unlink()

    # -- authentication ------------------------------------------------------------------------

    def _token_ok(self, given: str | None) -> bool:
        return bool(given) and hmac.compare_digest(str(given).encode(), self.token.encode())

    def _authed(self, request: web.Request) -> bool:
        return self._token_ok(request.cookies.get(COOKIE))

    def _login_page(self, message: str, status: int = 401) -> web.Response:
        body = _asset("login.html").replace("{message}", message)
        return web.Response(text=body, status=status, content_type="text/html")

    def _signed_in(self) -> web.Response:
        """To the page, the token in a cookie (raised: aiohttp's redirects are exceptions)."""
        response = web.HTTPSeeOther("/", headers=HEADERS)
        response.set_cookie(COOKIE, self.token, httponly=True, samesite="Strict",
                            secure=self.tls is not None, path="/")
        raise response

    @web.middleware
    async def _headers(self, request: web.Request, handler: Any) -> web.StreamResponse:
        response = await handler(request)
        if not isinstance(response, web.WebSocketResponse):
            response.headers.update(HEADERS)
        return response

    async def _page(self, request: web.Request) -> web.StreamResponse:
        given = request.query.get("token")
        if given is not None:  # a link with the token: into the cookie, out of the address bar
            if not self._token_ok(given):
                return self._login_page("Wrong token.")
            return self._signed_in()
        if not self._authed(request):
            return self._login_page("The daemon's token, please.")
        return web.Response(text=_asset("index.html"), content_type="text/html")

    async def _login(self, request: web.Request) -> web.StreamResponse:
        form = await request.post()
        if not self._token_ok(str(form.get("token", ""))):
            return self._login_page("Wrong token.")
        return self._signed_in()

    async def _static(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        types = {"app.js": "text/javascript", "style.css": "text/css"}
        if name not in types:
            raise web.HTTPNotFound()
        return web.Response(text=_asset(name), content_type=types[name])

    async def _snapshot_file(self, request: web.Request) -> web.StreamResponse:
        if not self._authed(request):
            raise web.HTTPUnauthorized(text="wrong or missing token")
        name = request.match_info["name"]
        if self.snapshot_dir is None or not SNAPSHOT_NAME.fullmatch(name):
            raise web.HTTPNotFound()
        path = self.snapshot_dir / name
        if not path.is_file():
            raise web.HTTPNotFound()
        return web.FileResponse(path, headers={"Content-Disposition":
                                               f'attachment; filename="{name}"'})

    # -- the WebSocket -------------------------------------------------------------------------

    async def _socket(self, request: web.Request) -> web.StreamResponse:
        if not self._authed(request):
            raise web.HTTPUnauthorized(text="wrong or missing token")
        origin = request.headers.get("Origin")
        if origin is not None and origin.split("://", 1)[-1] != request.host:
            raise web.HTTPForbidden(text=f"origin {origin} is not this page's")
        ws = web.WebSocketResponse(heartbeat=20, max_msg_size=65536)
        await ws.prepare(request)
        self._clients[ws] = {}
        if self._poller is None or self._poller.done():
            self._poller = asyncio.create_task(self._push_loop())
        # Each operation runs on its own (a snapshot waits for its job): a focus sent meanwhile
        # is not held up behind it. The daemon still takes one call at a time (the bridge).
        tasks: set[asyncio.Task] = set()

        async def answer(text: str) -> None:
            reply = await self._operate(text)
            with contextlib.suppress(ConnectionError, RuntimeError):
                await ws.send_str(json.dumps(reply))

        try:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    task = asyncio.create_task(answer(msg.data))
                    tasks.add(task)
                    task.add_done_callback(tasks.discard)
        finally:
            self._clients.pop(ws, None)
            for task in tasks:
                task.cancel()
        return ws

    async def _operate(self, text: str) -> dict[str, Any]:
        try:
            msg = json.loads(text)
            if not isinstance(msg, dict):
                raise ValueError("not an object")
        except ValueError as exc:
            return {"type": "reply", "id": None, "ok": False,
                    "error": {"name": "invalid_request", "message": f"not a JSON object: {exc}"}}
        op = msg.get("op")
        out: dict[str, Any] = {"type": "reply", "id": msg.get("id"), "op": op}
        try:
            out.update(ok=True, result=await self._run_op(str(op), msg))
        except Refused as exc:
            log.warning("web view: refused %r", op)
            out.update(ok=False, error={"name": "refused", "message": str(exc)})
        except RpcError as exc:
            out.update(ok=False, error={"name": exc.name, "message": exc.message})
        except DaemonUnavailable as exc:
            out.update(ok=False, error={"name": "daemon_unavailable", "message": str(exc)})
        return out

    async def _run_op(self, op: str, msg: dict[str, Any]) -> Any:
        if op not in OPERATIONS:
            if op in ("arm", "laser") or msg.get("action") == "arm":
                raise Refused("arming the lasers is not possible from the web view: a person "
                              "arms them at the bench (nhfctl laser arm over the Unix socket)")
            raise Refused(f"no operation {op[:40]!r}; the web view offers "
                          f"{', '.join(OPERATIONS)}")
        if op == "focus":
            return await self._daemon("focus", z_mm=msg.get("z_mm"))
        if op == "view":
            kind = "orbit" if "orbit" in msg else "relative"
            return await self._daemon("set_view", **{kind: msg.get(kind)})
        if op == "stop":
            return await self._daemon("stop")
        if op == "lasers_off":  # never arm: off (every channel off, disarmed) is all it sends
            return await self._daemon("laser", action="off")
        return await self._take_snapshot()

    async def _daemon(self, method: str, **params: Any) -> Any:
        return await asyncio.to_thread(self._call, method, **params)

    async def _take_snapshot(self) -> dict[str, Any]:
        queued = await self._daemon("snapshot")
        end = time.monotonic() + SNAPSHOT_WAIT_S
        while True:
            job = await self._daemon("job", id=queued["job"])
            if job["state"] not in ("queued", "running"):
                break
            if time.monotonic() > end:
                return {"job": job["id"], "state": job["state"], "path": queued["path"]}
            await asyncio.sleep(0.1)
        if job["state"] != "done":
            raise RpcError(DEVICE_ERROR,
                           f"snapshot job {job['id']} {job['state']}: {job.get('error')}")
        name = Path(queued["path"]).name
        return {"job": job["id"], "state": "done", "path": queued["path"],
                "url": f"/snapshots/{name}", "result": job.get("result")}

    # -- pushing state -------------------------------------------------------------------------

    async def _push_loop(self) -> None:
        while self._clients:
            started = time.monotonic()
            try:
                message, images = await self._state()
            except (DaemonUnavailable, RpcError) as exc:
                message, images = {"type": "state", "daemon_error": str(exc)}, {}
            for ws, sent in list(self._clients.items()):
                out = dict(message)
                for source, (digest, image) in images.items():
                    if sent.get(source) != digest:  # only what this page has not got yet
                        out[source] = image
                        sent[source] = digest
                with contextlib.suppress(ConnectionError, RuntimeError):
                    await ws.send_str(json.dumps(out))
            elapsed = time.monotonic() - started
            await asyncio.sleep(max(0.0, self.settings.push_interval_s - elapsed))

    async def _state(self) -> tuple[dict[str, Any], dict[str, tuple[str, Any]]]:
        status = await self._daemon("status")
        images = {}
        for source in ("slm", "camera"):
            preview = await self._daemon("preview", source=source,
                                         max_px=self.settings.thumbnail_px)
            digest = hashlib.sha1(json.dumps(preview, sort_keys=True).encode()).hexdigest()
            cached = self._images.get(source)
            if cached is None or cached[0] != digest:
                cached = (digest, await asyncio.to_thread(thumbnail, preview))
                self._images[source] = cached
            images[source] = cached
        now = time.monotonic()
        shown = int((status.get("frames") or {}).get("frames_shown") or 0)
        self._frames.append((now, shown))
        while len(self._frames) > 2 and now - self._frames[0][0] > FPS_WINDOW_S:
            self._frames.popleft()
        (t0, n0), (t1, n1) = self._frames[0], self._frames[-1]
        fps = (n1 - n0) / (t1 - t0) if t1 > t0 and n1 >= n0 else None
        return {"type": "state", "time_s": time.time(), "status": status, "fps": fps}, images


def _asset(name: str) -> str:
    return resources.files("nhfd.web").joinpath(name).read_text(encoding="utf-8")
