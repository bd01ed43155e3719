"""The web view's server: aiohttp on a thread of `nhfd serve`, a client of the daemon's socket.

    GET  /             the page (with the token: ?token=... once, or the login form's POST
                       /login, sets an HttpOnly SameSite=Strict cookie); 401 without it
    GET  /ws           the WebSocket (the cookie again; 401 before the upgrade without it, 403
                       from another origin): state pushed every push_interval_s, operations in
    GET  /snapshots/N  a snapshot PNG the page asked for (daemon.paths.snapshot_dir)
    GET  /static/...   the page's script and style

Pushed: {"type": "state", "status": <the daemon's status>, "fps": frames per second shown,
"slm": thumbnail, "camera": thumbnail} (a thumbnail is sent again only when it changed) or
{"type": "state", "daemon_error": why}. Operations: {"id", "op": one of OPERATIONS, ...} answered
{"type": "reply", "id", "op", "ok", "result" | "error": {"name", "message"}}.

Arming is not an operation: the page cannot arm the lasers whatever it sends (`refused`), and
the daemon's own rule (arming only from a person on the bench's machine) stays the authority.

Bounds (the server runs inside the daemon's process, so what it holds, the daemon holds):
- connections: at most `max_connections` at once, HTTP and WebSocket, counted from the accept
  (a TLS handshake included); more get a 503 (plain HTTP) or are closed (TLS). A connection
  idle for `idle_timeout_s` without a request (no request yet, a request cut off halfway, or
  keep-alive) and a TLS handshake that takes as long are dropped. Running out of descriptors
  while accepting (EMFILE) is logged (once a minute at most) and waited out; nothing stops.
- messages: each WebSocket spends one token of a bucket of `messages_per_s` per second (a burst
  of as many) per message; one without a token is refused without being parsed or answered (a
  {"type": "refused", "count"} notice at most once a second), and a socket refused more than
  FLOOD_FACTOR times its rate within a second (FLOOD_MIN_REFUSED at least) is closed (1008). A
  new socket goes on with the bucket its host's last socket left: reconnecting buys no burst.
  A message over
  `max_message_bytes` closes the socket (1009); one nested deeper than MAX_DEPTH, or not a JSON
  object, is answered `invalid_request`. At most MAX_IN_FLIGHT operations per socket run at
  once (one snapshot); more are answered `busy`, except `lasers_off`.
- refusals reach the log and the daemon's audit log as the daemon's own RPC refusals do: the
  first of each kind at once, then one line per window with the count.
- an exception in a handler or the push loop is logged and the server goes on; if the server's
  thread itself ends, that is logged and the daemon goes on without the page, lasers untouched.

What the page asks of the daemon is audited with the web client's identity (`web_client`: its
address, "web view", the token file), which the daemon accepts only from its own process.
"""

from __future__ import annotations

import asyncio
import base64
import collections
import contextlib
import contextvars
import errno
import hashlib
import hmac
import io
import json
import logging
import math
import os
import re
import secrets
import socket
import ssl
import threading
import time
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from aiohttp import WSCloseCode, WSMsgType, web
from PIL import Image

from nhfd.config import LOOPBACK_HOSTS, DaemonSettings, WebSettings
from nhfd.daemon.audit import AuditLog
from nhfd.daemon.client import Client, DaemonUnavailable
from nhfd.daemon.paths import resolve_dirs
from nhfd.daemon.protocol import (
    BUSY,
    DEVICE_ERROR,
    FORBIDDEN,
    INTERNAL_ERROR,
    INVALID_REQUEST,
    METHOD_NOT_FOUND,
    Code,
    RpcError,
)
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
# Operations of one WebSocket running at once (each waits for the daemon, a snapshot for its
# job): more are answered `busy`. `lasers_off` is never held back by this (the way out), only by
# the message rate.
MAX_IN_FLIGHT = 8
# The deepest nesting a message may have. The page's deepest is 2 ({"orbit": {...}}); more would
# only cost recursion (json raised RecursionError on a 30,000-deep message) and would be passed
# on to the daemon.
MAX_DEPTH = 8
ID_CHARS = 100  # an id is a string of at most this many characters or an integer
# A WebSocket refused more than this many times its messages_per_s within one second is closed
# (1008): refused messages still cost a frame's parsing each, in the daemon's process.
FLOOD_FACTOR = 10
FLOOD_MIN_REFUSED = 100  # ... and never fewer than this (a slow rate is no reason to close sooner)
NOTICE_INTERVAL_S = 1.0  # refused messages are told to the page at most this often
# The buckets of closed WebSockets, by the peer's host, that a new socket from that host goes on
# with (reconnecting does not refill a burst); the oldest are forgotten past this many hosts.
BUCKETS_KEPT = 256
# A page that reads nothing holds a push (or a reply) at most this long, then is closed.
SEND_TIMEOUT_S = 10.0
# Accepting while out of descriptors (EMFILE, ENFILE) or buffers: retry after this, doubling.
ACCEPT_BACKOFF_S = (0.05, 1.0)
SHORTAGE_LOG_S = 60.0  # ... logged at most once this often, with the count of failures since
OUT_OF_RESOURCES = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)
LISTEN_BACKLOG = 128
LOGIN_BODY_BYTES = 4096  # the login form's body (the token): every other request has none
_BUSY_BODY = b"the web view has daemon.web.max_connections connections already\n"
BUSY_REPLY = (b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\n"
              b"Content-Length: %d\r\nRetry-After: 5\r\nConnection: close\r\n\r\n%s"
              % (len(_BUSY_BODY), _BUSY_BODY))
# The web client a request comes from, set by the WebSocket's handler for its tasks (the
# bridge's thread sees it too: asyncio.to_thread copies the context).
WEB_CLIENT: contextvars.ContextVar[dict[str, Any] | None] = contextvars.ContextVar(
    "nhfd_web_client", default=None)
HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; connect-src 'self'; "
                               "style-src 'self'; script-src 'self'; frame-ancestors 'none'",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


class Refused(Exception):
    """An operation the web view does not offer (its message says why)."""


class TokenBucket:
    """`rate_per_s` tokens a second, at most `burst` saved up; each message spends one."""

    def __init__(self, rate_per_s: float, burst: float, now_s: float) -> None:
        self.rate_per_s = rate_per_s
        self.burst = burst
        self.tokens = burst
        self.last_s = now_s

    def take(self, now_s: float) -> bool:
        """Spend a token if there is one (True), else False (the message is refused)."""
        self.tokens = min(self.burst, self.tokens + (now_s - self.last_s) * self.rate_per_s)
        self.last_s = now_s
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


class Refusals:
    """Refusals as log lines and audit records, the way the daemon's audit log summarises RPC
    refusals: the first of each kind (what and code, whoever sent it) at once, then one line
    per `window_s` with the count of the rest. A flood costs a counter, not a line each.

    Used on the web view's event loop only; the audit log takes its own lock."""

    def __init__(self, audit: AuditLog | None, window_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.audit = audit
        self.window_s = window_s
        self.clock = clock
        self._open: dict[tuple[str, int], dict[str, Any]] = {}

    def note(self, who: dict[str, Any], what: str, code: Code, message: str) -> None:
        """One refusal of `what` (e.g. "web message rate") with `code`, from `who`."""
        key = (what, code.code)
        now = self.clock()
        entry = self._open.get(key)
        if entry is not None and now - entry["since"] < self.window_s:
            entry["count"] += 1
            entry["last_who"] = who
            return
        if entry is not None:
            self._summarise(key, entry)
        log.warning("web view: refused %s from %s: %s (more within %g s are counted)", what,
                    who.get("address"), message, self.window_s)
        if self.audit is not None:
            self.audit.write(who, what, code=code.code,
                             outcome=_clip(f"refused: {code.name}: {message}"))
        self._open[key] = {"since": now, "count": 0, "who": who, "last_who": who,
                           "message": message}

    def tick(self, *, everything: bool = False) -> None:
        """Write the summary of each window that has passed (of every one: `everything`)."""
        now = self.clock()
        for key, entry in list(self._open.items()):
            if everything or now - entry["since"] >= self.window_s:
                del self._open[key]
                self._summarise(key, entry)

    def _summarise(self, key: tuple[str, int], entry: dict[str, Any]) -> None:
        count = entry["count"]
        if not count:
            return
        what, code = key
        log.warning("web view: %d more %s refused within %g s (%s), the last from %s", count,
                    what, self.window_s, entry["message"], entry["last_who"].get("address"))
        if self.audit is not None:
            self.audit.write(entry["who"], f"{what} (refusals summary)", code=code, count=count,
                             outcome=f"{count} more like this", window_s=self.window_s,
                             last_who=entry["last_who"])


def _clip(text: str, limit: int = 200) -> str:
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} chars)"


def _too_deep(value: Any, limit: int) -> bool:
    """Whether `value` nests lists and objects deeper than `limit` (iterative: no recursion)."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        children = item.values() if isinstance(item, dict) else item if isinstance(
            item, list) else None
        if children is None:
            continue
        if depth > limit:
            return True
        stack.extend((child, depth + 1) for child in children)
    return False


def _valid_id(value: Any) -> bool:
    if isinstance(value, bool):
        return False
    if isinstance(value, int):
        return abs(value) < 2 ** 53  # what the page's JavaScript can hold exactly
    return value is None or (isinstance(value, str) and len(value) <= ID_CHARS)


def _address(peer: Any) -> str:
    """"host:port" of a peer address tuple (IPv4 or IPv6), or "unknown"."""
    if isinstance(peer, tuple) and len(peer) >= 2:
        host = f"[{peer[0]}]" if ":" in str(peer[0]) else str(peer[0])
        return f"{host}:{peer[1]}"
    return "unknown"


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


def serve_web_view(settings: DaemonSettings, *, socket_path: Path, runtime_dir: Path,
                   base_dir: Path, tcp_token: str | None, audit: AuditLog) -> WebView:
    """Start the web view of a started daemon in this process: `settings` is its `[daemon]`
    (`web`, `paths.snapshot_dir`, `server.auth_timeout_s`, `audit.summary_s`: four of its
    sections, so it takes them all), `socket_path` the Unix socket the page's requests go to,
    `runtime_dir` where a token file is made when none is configured, `base_dir` what relative
    paths are taken from, `tcp_token` the daemon's TCP token (the page asks for it when it has
    one), `audit` the daemon's audit log (refusals go there). `stop()` it before the daemon
    ends."""
    web_settings = settings.web
    token, made = web_token(web_settings, runtime_dir=runtime_dir, daemon_token=tcp_token,
                            base_dir=base_dir)
    # A connection that has not sent a request within daemon.server.auth_timeout_s is dropped, as
    # an unauthenticated TCP client of the daemon is; refusals go to the daemon's audit log.
    view = WebView(web_settings, socket_path=socket_path, token=token,
                   snapshot_dir=resolve_dirs([settings.paths.snapshot_dir], base_dir)[0],
                   base_dir=base_dir, token_file_made=made, audit=audit,
                   idle_timeout_s=settings.server.auth_timeout_s,
                   summary_s=settings.audit.summary_s)
    view.token_source = made or (
        base_dir / web_settings.token_file if web_settings.token_file
        else runtime_dir / "tcp.token")
    try:
        view.start()
    except BaseException:
        view.stop()
        raise
    return view


def tls_context(settings: WebSettings, base_dir: Path) -> ssl.SSLContext | None:
    """The web view's TLS context from `daemon.web.tls_cert` and `tls_key` (relative to
    `base_dir`), or None when no certificate is configured."""
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
    dropped and made again on the next call (never a call retried: focus twice is not focus).

    A call made for a web client (`WEB_CLIENT` set) first tells the daemon who that is
    (`web_client`, once per change), so that the audit log names the web client, not the daemon:
    the daemon takes that word from its own process only."""

    def __init__(self, socket_path: Path, timeout_s: float = 5.0) -> None:
        self.socket_path = socket_path
        self.timeout_s = timeout_s
        self._client: Client | None = None
        self._said: dict[str, Any] | None = None  # the web client this connection speaks for
        self._lock = threading.Lock()

    def call(self, method: str, **params: Any) -> Any:
        """`method` on the daemon, for the web client in `WEB_CLIENT` if one is set."""
        web_client = WEB_CLIENT.get()
        with self._lock:
            if self._client is None:
                self._client = Client(self.socket_path, timeout_s=self.timeout_s)
                self._said = None
            try:
                if web_client is not None and web_client != self._said:
                    self._tell(web_client)
                return self._client.call(method, **params)
            except DaemonUnavailable:
                self._client.close()
                self._client = None
                raise

    def _tell(self, web_client: dict[str, Any]) -> None:
        assert self._client is not None
        try:
            self._client.call("web_client", **web_client)
        except RpcError as exc:
            # The request still goes: "lasers off" must not wait on an audit detail. The audit
            # line then names this process, as before.
            log.warning("web view: the daemon did not take the web client's identity (%s); "
                        "its requests are audited as the daemon's own", exc.message)
        self._said = web_client

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
                 call: Callable[..., Any] | None = None, audit: AuditLog | None = None,
                 idle_timeout_s: float = 5.0, summary_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        """`call(method, **params)` replaces the daemon (tests); `audit` is the daemon's audit
        log, for refusals; `idle_timeout_s`: how long a connection may go without a request (or
        take for its TLS handshake); `summary_s`: the window refusals are counted over;
        `clock`: the time message rates and refusal windows are measured in (tests)."""
        if settings.host not in LOOPBACK_HOSTS and not settings.tls_cert:
            raise ValueError(f"daemon.web.host = {settings.host!r} is not loopback: listening "
                             "elsewhere needs TLS, set daemon.web.tls_cert and daemon.web.tls_key")
        if not 0 < idle_timeout_s <= 3600:
            raise ValueError(f"idle_timeout_s = {idle_timeout_s!r}: allowed (0, 3600] s")
        self.settings = settings
        self.token = token
        self.token_file_made = token_file_made  # removed at stop
        self.token_source: Path | None = token_file_made
        self.snapshot_dir = snapshot_dir
        self.base_dir = base_dir or Path.cwd()
        self.bridge = DaemonBridge(socket_path)
        self._call = call or self.bridge.call
        self.tls = tls_context(settings, self.base_dir)
        self.idle_timeout_s = idle_timeout_s
        self.clock = clock
        self.refusals = Refusals(audit, summary_s, clock)
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
        self._stopping = False
        self._listeners: list[socket.socket] = []
        self._background: set[asyncio.Task] = set()  # accept loops and housekeeping
        self._handshakes: set[asyncio.Task] = set()  # accepted, not yet handed to aiohttp
        self._errors: dict[str, float] = {}  # an internal error's kind -> when last logged
        self._short = 0  # accepts failed for want of descriptors, not logged yet
        self._short_logged_s = -math.inf
        self.messages_refused = 0  # WebSocket messages dropped for their rate, all sockets
        self._buckets: collections.OrderedDict[str, TokenBucket] = collections.OrderedDict()

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

    @property
    def alive(self) -> bool:
        """Whether the server's thread is running (False before start, after stop or a failure)."""
        return self._thread is not None and self._thread.is_alive()

    def _run(self, ready: threading.Event) -> None:
        loop = self._loop
        assert loop is not None
        asyncio.set_event_loop(loop)
        loop.set_exception_handler(self._loop_error)
        try:
            loop.run_until_complete(self._listen())
        except BaseException as exc:
            self._failed = exc
            ready.set()
            with contextlib.suppress(BaseException):
                loop.run_until_complete(self._close())
            loop.close()
            return
        ready.set()
        try:
            loop.run_forever()
        except BaseException as exc:
            # This thread is the web view only: whatever ends it ends the page, never the daemon.
            # The control socket, the heartbeat and the lasers are the main thread's; nothing
            # here touches them.
            log.error("web view failed (%s: %s): the page is off until the daemon restarts; "
                      "the daemon goes on, lasers as they were", type(exc).__name__, exc,
                      exc_info=exc)
        finally:
            try:
                loop.run_until_complete(self._close())
            except BaseException as exc:
                log.error("web view: closing after a failure failed too (%s: %s)",
                          type(exc).__name__, exc)
            loop.close()

    def _loop_error(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """asyncio's report of an error nobody caught (a task's, a callback's): logged, once per
        kind and second, instead of asyncio's line each; the loop goes on."""
        exc = context.get("exception")
        kind = f"{context.get('message')}: {type(exc).__name__ if exc else ''}"
        now = time.monotonic()
        if now - self._errors.get(kind, -1e9) >= 1.0:
            self._errors[kind] = now
            log.error("web view: %s", kind, exc_info=exc)

    async def _listen(self) -> None:
        app = web.Application(middlewares=[self._headers], client_max_size=LOGIN_BODY_BYTES)
        app.router.add_get("/", self._page)
        app.router.add_post("/login", self._login)
        app.router.add_get("/ws", self._socket)
        app.router.add_get("/snapshots/{name}", self._snapshot_file)
        app.router.add_get("/static/{name}", self._static)
        # keepalive_timeout also closes a connection that sends no request at all, or stops
        # halfway through its headers (aiohttp's handler is idle until a request is complete).
        self._runner = web.AppRunner(app, access_log=None, keepalive_timeout=self.idle_timeout_s)
        await self._runner.setup()
        s = self.settings
        self._listeners = _listening_sockets(s.host, s.port)
        self.port = self._listeners[0].getsockname()[1]
        host = f"[{s.host}]" if ":" in s.host else s.host
        self.url = f"{'https' if self.tls else 'http'}://{host}:{self.port}/"
        for listener in self._listeners:
            self._spawn(self._accept_loop(listener))
        self._spawn(self._housekeeping())

    def _spawn(self, coro: Any) -> None:
        # Without the WebSocket handler's context (its WEB_CLIENT), and kept: asyncio only holds
        # weak references to tasks.
        task = asyncio.get_running_loop().create_task(coro, context=contextvars.Context())
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    async def _close(self) -> None:
        self._stopping = True
        for task in list(self._background) + list(self._handshakes):
            task.cancel()
        for listener in self._listeners:
            listener.close()
        for ws in list(self._clients):
            with contextlib.suppress(Exception):
                await ws.close()
        if self._poller is not None:
            self._poller.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._poller
        for task in list(self._background) + list(self._handshakes):
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self.refusals.tick(everything=True)
        if self._runner is not None:
            await self._runner.cleanup()

    def stop(self) -> None:
        """Close every connection and the listening socket; remove the token file it made."""
        if self._loop is not None and self._thread is not None and self._thread.is_alive():
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile (a failure)
                self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(10)
        self.bridge.close()
        if self.token_file_made is not None:
            with contextlib.suppress(OSError):
                self.token_file_made.unlink()

    # -- connections ---------------------------------------------------------------------------

    def connections(self) -> int:
        """Connections held now: accepted and handed to aiohttp (HTTP or WebSocket), and those
        accepted but still in their TLS handshake."""
        server = self._runner.server if self._runner is not None else None
        return len(self._handshakes) + (len(server.connections) if server is not None else 0)

    async def _accept_loop(self, listener: socket.socket) -> None:
        """Accept, admit up to max_connections, refuse the rest at once. Out of descriptors
        (EMFILE): logged once, then retried with a growing pause; the pending connections wait
        in the kernel's backlog, and the loop never ends on it."""
        loop = asyncio.get_running_loop()
        backoff_s = ACCEPT_BACKOFF_S[0]
        while True:
            try:
                sock, peer = await loop.sock_accept(listener)
            except asyncio.CancelledError:
                raise
            except OSError as exc:
                if self._stopping or listener.fileno() < 0:
                    return
                if exc.errno in OUT_OF_RESOURCES:
                    self._out_of_descriptors(exc)
                    await asyncio.sleep(backoff_s)
                    backoff_s = min(backoff_s * 2, ACCEPT_BACKOFF_S[1])
                    continue
                # ECONNABORTED and the like: that peer is gone, the next one is not
                self._internal_error("accept", exc)
                await asyncio.sleep(ACCEPT_BACKOFF_S[0])
                continue
            backoff_s = ACCEPT_BACKOFF_S[0]
            try:
                self._admit(sock, peer)
            except Exception as exc:  # a bug here must not end accepting
                sock.close()
                self._internal_error("admit", exc)

    def _out_of_descriptors(self, exc: OSError) -> None:
        """One line per SHORTAGE_LOG_S however often accepting fails: while connections come
        and go at the limit it fails and succeeds by turns."""
        self._short += 1
        now = time.monotonic()
        if now - self._short_logged_s < SHORTAGE_LOG_S:
            return
        log.error("web view: cannot accept a connection: %s (%d connections held, %d such "
                  "failures since the last line); new connections wait in the kernel's "
                  "backlog, retried every %g s at most", exc, self.connections(),
                  self._short - 1, ACCEPT_BACKOFF_S[1])
        self._short, self._short_logged_s = 0, now

    def _admit(self, sock: socket.socket, peer: Any) -> None:
        sock.setblocking(False)
        cap = self.settings.max_connections
        if self.connections() >= cap:
            who = {"transport": "web", "address": _address(peer)}
            self.refusals.note(who, "web connection", BUSY, f"{cap} connections held already "
                               "(daemon.web.max_connections)")
            if self.tls is None:  # TLS would need a handshake first: only closed
                with contextlib.suppress(OSError):
                    sock.send(BUSY_REPLY)
            sock.close()
            return
        task = asyncio.get_running_loop().create_task(self._hand_over(sock, peer),
                                                      context=contextvars.Context())
        self._handshakes.add(task)
        task.add_done_callback(self._handshakes.discard)

    async def _hand_over(self, sock: socket.socket, peer: Any) -> None:
        """The accepted socket to aiohttp's HTTP handler, after the TLS handshake if any."""
        assert self._runner is not None and self._runner.server is not None
        loop = asyncio.get_running_loop()
        tls: dict[str, Any] = ({"ssl": self.tls, "ssl_handshake_timeout": self.idle_timeout_s}
                               if self.tls is not None else {})
        try:
            await loop.connect_accepted_socket(self._runner.server, sock, **tls)
            # aiohttp counts it from here on: out of the handshakes now, not in the task's done
            # callback a loop turn later, or it counts twice meanwhile and a connection within
            # max_connections is refused (seen in tests under load)
            self._handshakes.discard(asyncio.current_task())
        except asyncio.CancelledError:
            sock.close()
            raise
        except (OSError, ssl.SSLError, TimeoutError) as exc:  # counted: a peer can send many
            self.refusals.note({"transport": "web", "address": _address(peer)},
                               "web handshake", INVALID_REQUEST,
                               f"dropped before its first request: {exc or type(exc).__name__}")
            sock.close()

    async def _housekeeping(self) -> None:
        """Refusal summaries whose window has passed, whether or not anything else happens."""
        while True:
            await asyncio.sleep(min(1.0, self.refusals.window_s))
            self.refusals.tick()

    def _internal_error(self, kind: str, exc: BaseException) -> None:
        """A bug or an unexpected condition in the server: logged (once per kind and second),
        and the server goes on."""
        now = time.monotonic()
        if now - self._errors.get(kind, -1e9) >= 1.0:
            self._errors[kind] = now
            log.error("web view: %s failed: %s: %s", kind, type(exc).__name__, exc,
                      exc_info=exc)

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
        try:  # a body sent a byte at a time would hold the connection (and a slot) for ever
            async with asyncio.timeout(self.idle_timeout_s):
                form = await request.post()
        except TimeoutError:
            raise web.HTTPRequestTimeout(text="the login form came too slowly") from None
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

    def _web_client(self, request: web.Request) -> dict[str, Any]:
        """Who a WebSocket is, for the audit log: its address (as this socket sees it: behind
        an SSH tunnel, loopback), that it came through the web view, and the token it holds."""
        peer = request.transport.get_extra_info("peername") if request.transport else None
        who: dict[str, Any] = {"address": _address(peer), "tls": self.tls is not None}
        if self.token_source is not None:
            who["token_file"] = str(self.token_source)
        return who

    async def _socket(self, request: web.Request) -> web.StreamResponse:
        if not self._authed(request):
            raise web.HTTPUnauthorized(text="wrong or missing token")
        origin = request.headers.get("Origin")
        if origin is not None and origin.split("://", 1)[-1] != request.host:
            raise web.HTTPForbidden(text=f"origin {origin} is not this page's")
        s = self.settings
        ws = web.WebSocketResponse(heartbeat=20, max_msg_size=s.max_message_bytes)
        await ws.prepare(request)
        client = self._web_client(request)
        WEB_CLIENT.set(client)  # this handler's context: its operations' tasks copy it
        who = {"transport": "web", **client}
        self._clients[ws] = {}
        if self._poller is None or self._poller.done():
            self._poller = asyncio.get_running_loop().create_task(
                self._push_loop(), context=contextvars.Context())
        # Each operation runs on its own (a snapshot waits for its job): a focus sent meanwhile
        # is not held up behind it. The daemon still takes one call at a time (the bridge).
        # What a socket may start is bounded: messages by the bucket, operations at once by
        # MAX_IN_FLIGHT; a message without a token is dropped here, costing a counter.
        tasks: set[asyncio.Task] = set()
        snapshots: set[asyncio.Task] = set()
        host = client["address"].rsplit(":", 1)[0]
        bucket = self._buckets.pop(host, None) or TokenBucket(
            s.messages_per_s, max(1.0, s.messages_per_s), self.clock())
        flood_limit = max(FLOOD_MIN_REFUSED, FLOOD_FACTOR * s.messages_per_s)
        refused = 0  # since the last notice to the page
        second_start, refused_this_second = self.clock(), 0
        next_notice = -math.inf
        try:
            async for msg in ws:
                now = self.clock()
                if msg.type == WSMsgType.ERROR:  # aiohttp has closed the socket already
                    if getattr(msg.data, "code", None) == WSCloseCode.MESSAGE_TOO_BIG:
                        self.refusals.note(who, "web message size", INVALID_REQUEST,
                                           f"a message over {s.max_message_bytes} bytes "
                                           "(daemon.web.max_message_bytes); socket closed")
                    break
                if msg.type not in (WSMsgType.TEXT, WSMsgType.BINARY):
                    continue
                if not bucket.take(now):
                    refused += 1
                    self.messages_refused += 1
                    if now - second_start >= 1.0:
                        second_start, refused_this_second = now, 0
                    refused_this_second += 1
                    self.refusals.note(who, "web message rate", BUSY,
                                       f"over {s.messages_per_s:g} messages per s "
                                       "(daemon.web.messages_per_s)")
                    if refused_this_second > flood_limit:
                        self.refusals.note(who, "web socket flood", BUSY,
                                           f"over {flood_limit:g} refused messages in a second; "
                                           "socket closed")
                        await ws.close(code=WSCloseCode.POLICY_VIOLATION,
                                       message=b"too many messages")
                        break
                    if now >= next_notice:
                        next_notice = now + NOTICE_INTERVAL_S
                        await self._send(ws, {
                            "type": "refused", "count": refused, "error": {
                                "name": "busy", "message": f"more than {s.messages_per_s:g} "
                                "messages per s: the rest were dropped unanswered"}})
                        refused = 0
                    continue
                parsed = self._parse(msg.data if msg.type == WSMsgType.TEXT else None)
                if "error" in parsed:
                    self.refusals.note(who, parsed.pop("what"), parsed.pop("code"),
                                       parsed["error"]["message"])
                    await self._send(ws, parsed)
                    continue
                op = parsed["op"]
                if op != "lasers_off" and (len(tasks) >= MAX_IN_FLIGHT or
                                           (op == "snapshot" and snapshots)):
                    what = "a snapshot is" if op == "snapshot" and snapshots else (
                        f"{MAX_IN_FLIGHT} operations are")
                    self.refusals.note(who, "web operation busy", BUSY,
                                       f"{what} running already")
                    await self._send(ws, {"type": "reply", "id": parsed["id"], "op": op,
                                          "ok": False, "error": {
                                              "name": "busy", "message": f"{what} running "
                                              "already on this page; wait for its reply"}})
                    continue
                task = asyncio.get_running_loop().create_task(self._answer(ws, parsed))
                tasks.add(task)
                task.add_done_callback(tasks.discard)
                if op == "snapshot":
                    snapshots.add(task)
                    task.add_done_callback(snapshots.discard)
        finally:
            self._clients.pop(ws, None)
            for task in tasks:
                task.cancel()
            self._buckets[host] = bucket
            while len(self._buckets) > BUCKETS_KEPT:
                self._buckets.popitem(last=False)
        return ws

    def _parse(self, text: str | None) -> dict[str, Any]:
        """A message as {"op", "id", "msg"} if it asks for an operation the page may do, else
        the reply refusing it with its "code" (for the refusal's summary)."""
        def refuse(name: str, code: Code, message: str, rid: Any = None) -> dict[str, Any]:
            what = "web operation" if name == "refused" else "web message"
            return {"type": "reply", "id": rid, "ok": False, "what": what, "code": code,
                    "error": {"name": name, "message": message}}

        if text is None:
            return refuse("invalid_request", INVALID_REQUEST, "not a JSON object: a binary "
                          "message; send text")
        try:
            msg = json.loads(text)
        except RecursionError:
            return refuse("invalid_request", INVALID_REQUEST, "not a JSON object: nested too "
                          f"deeply; allowed: at most {MAX_DEPTH} levels")
        except ValueError as exc:
            return refuse("invalid_request", INVALID_REQUEST,
                          f"not a JSON object: {_clip(str(exc), 120)}")
        if not isinstance(msg, dict):
            return refuse("invalid_request", INVALID_REQUEST, "not a JSON object: "
                          f"a {type(msg).__name__}")
        if _too_deep(msg, MAX_DEPTH):
            return refuse("invalid_request", INVALID_REQUEST, "nested too deeply; allowed: at "
                          f"most {MAX_DEPTH} levels")
        rid = msg.get("id")
        if not _valid_id(rid):
            return refuse("invalid_request", INVALID_REQUEST, "id: allowed: a string of at "
                          f"most {ID_CHARS} characters, an integer below 2**53, or null")
        op = msg.get("op")
        if op not in OPERATIONS:
            shown = op[:40] if isinstance(op, str) else _clip(json.dumps(op), 40)
            if op in ("arm", "laser") or msg.get("action") == "arm":
                return refuse("refused", FORBIDDEN, "arming the lasers is not possible from the "
                              "web view: a person arms them at the bench (nhfctl laser arm over "
                              "the Unix socket)", rid)
            return refuse("refused", METHOD_NOT_FOUND, f"no operation {shown!r}; the web view "
                          f"offers {', '.join(OPERATIONS)}", rid)
        return {"op": op, "id": rid, "msg": msg}

    async def _answer(self, ws: web.WebSocketResponse, parsed: dict[str, Any]) -> None:
        await self._send(ws, await self._operate(parsed))

    async def _send(self, ws: web.WebSocketResponse, message: dict[str, Any]) -> None:
        """`message` to one page; a page that has not taken it within SEND_TIMEOUT_S (it reads
        nothing) is closed rather than waited for."""
        try:
            async with asyncio.timeout(SEND_TIMEOUT_S):
                await ws.send_str(json.dumps(message))
        except TimeoutError:
            log.warning("web view: closing a page that reads nothing")
            with contextlib.suppress(Exception):
                await ws.close(code=WSCloseCode.POLICY_VIOLATION, message=b"not reading")
        except (ConnectionError, RuntimeError):
            pass  # the page went away meanwhile

    async def _operate(self, parsed: dict[str, Any]) -> dict[str, Any]:
        op, msg = parsed["op"], parsed["msg"]
        out: dict[str, Any] = {"type": "reply", "id": parsed["id"], "op": op}
        try:
            out.update(ok=True, result=await self._run_op(op, msg))
        except Refused as exc:
            out.update(ok=False, error={"name": "refused", "message": str(exc)})
        except RpcError as exc:
            out.update(ok=False, error={"name": exc.name, "message": exc.message})
        except DaemonUnavailable as exc:
            out.update(ok=False, error={"name": "daemon_unavailable", "message": str(exc)})
        except Exception as exc:  # a bug: this page's reply says so, the server goes on
            self._internal_error(f"operation {op}", exc)
            out.update(ok=False, error={"name": INTERNAL_ERROR.name,
                                        "message": f"{type(exc).__name__}: {exc}"})
        return out

    async def _run_op(self, op: str, msg: dict[str, Any]) -> Any:
        if op == "focus":
            return await self._daemon("focus", z_mm=msg.get("z_mm"))
        if op == "view":
            kind = "orbit" if "orbit" in msg else "relative"
            return await self._daemon("set_view", **{kind: msg.get(kind)})
        if op == "stop":
            return await self._daemon("stop")
        if op == "lasers_off":  # never arm: off (every channel off, disarmed) is all it sends
            return await self._daemon("laser", action="off")
        if op == "snapshot":
            return await self._take_snapshot()
        raise Refused(f"no operation {op!r}")  # _parse lets only OPERATIONS through

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
            except Exception as exc:  # a bug or a reply it did not expect: logged, next push
                self._internal_error("push", exc)
                message, images = {"type": "state", "daemon_error": "the web view could not "
                                   f"read the daemon's state: {type(exc).__name__}: {exc}"}, {}
            for ws, sent in list(self._clients.items()):
                out = dict(message)
                for source, (digest, image) in images.items():
                    if sent.get(source) != digest:  # only what this page has not got yet
                        out[source] = image
                        sent[source] = digest
                await self._send(ws, out)
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


def _listening_sockets(host: str, port: int) -> list[socket.socket]:
    """Non-blocking listening sockets on every address of `host` (one, the first, for port 0:
    each would get a different port)."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    sockets: list[socket.socket] = []
    try:
        for family, kind, proto, _, address in infos[:1] if port == 0 else infos:
            sock = socket.socket(family, kind, proto)
            sockets.append(sock)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:  # ::1 alone, as asked; 127.0.0.1 is its own socket
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            sock.bind(address)
            sock.listen(LISTEN_BACKLOG)
            sock.setblocking(False)
    except BaseException:
        for sock in sockets:
            sock.close()
        raise
    return sockets


def _asset(name: str) -> str:
    return resources.files("nhfd.web").joinpath(name).read_text(encoding="utf-8")
