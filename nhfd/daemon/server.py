"""The line server: a Unix socket (mode 0660, a lab group) and optional TCP, TLS where asked.

Single-threaded and non-blocking, driven by the control loop's `poll()`, so request handling and
the laser heartbeat share one thread: if handling hangs, the heartbeat stops and the guardian
switches the lasers off. So no peer may hold the loop, and none may lock the bench's own user
out:

- Slots. Unix-socket clients count against `max_clients` alone: no remote peer takes a local
  slot. TCP clients count against `max_tcp_clients`; of them, those still in the TLS handshake
  or before `auth` count against `max_unauthenticated` too, and each is dropped `auth_timeout_s`
  after it connected unless it has authenticated. A refused connection gets a JSON-RPC `busy`
  error in its own protocol (inside TLS once the handshake is done; see `_accept`).
- Input. At most `max_buffered_bytes` received and not yet handled per connection (a peer past
  it is dropped; drops are logged with the peer, summarised); at most `lines_per_poll` lines per
  connection per poll, empty lines counted; and `tick_budget_s` of serving per poll, after which
  the rest waits, in turn, for the next poll: the control loop sends its heartbeat in between.
  A line over `max_line_bytes` is answered with an error and skipped up to its newline; a
  client that stops reading its replies is dropped once `max_pending_bytes` are waiting.
- Descriptors. `accept` failing for want of file descriptors (EMFILE, ENFILE) pauses that
  listener for `ACCEPT_BACKOFF_S` (logged once per episode); existing clients are still served.

The TCP port listens on loopback unless `daemon.server.tcp_host` says otherwise, and then only
with TLS (`daemon.server.tls_cert`, `daemon.server.tls_key`): a token never crosses a network in
clear. The TLS handshake runs non-blocking in the same loop, so a slow or silent peer holds an
unauthenticated slot until its deadline, never the loop.

The socket, the port and every bound above but `max_pending_bytes` are `[daemon.server]`'s
(`nhfd.config.ServerSettings`), which the server takes whole.
"""

from __future__ import annotations

import contextlib
import errno
import grp
import logging
import os
import pwd
import resource
import selectors
import socket
import ssl
import stat
import struct
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from nhfd.config import ServerSettings

from . import protocol
from .protocol import BUSY, INTERNAL_ERROR, INVALID_REQUEST, RpcError

log = logging.getLogger("nhfd.daemon.server")

LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")

# One recv per connection per poll reads at most this much: a fast sender cannot make a single
# poll copy megabytes.
RECV_CHUNK_BYTES = 65536
# How long a listener whose accept failed for want of descriptors stays out of the selector. Its
# socket stays readable while connections wait in the kernel's backlog, so without the pause the
# loop would spin on EMFILE; a quarter second lets closing clients free descriptors first.
ACCEPT_BACKOFF_S = 0.25
# accept's errors that mean "no descriptor or memory for it now", not "this one peer failed".
FD_EXHAUSTED = frozenset({errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM})
# Refusals and drops are logged with the peer's identity the first time, then summarised at most
# this often: a peer that reconnects in a loop must not flood the journal.
REFUSAL_LOG_EVERY_S = 60.0


def server_tls_context(cert_path: str | os.PathLike[str], key_path: str | os.PathLike[str],
                       section: str = "daemon.server") -> ssl.SSLContext:
    """A server context (TLS 1.2 at least) from PEM files; ValueError naming the settings
    (`section`.tls_cert and .tls_key) when they cannot be loaded."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert_path, key_path)
    except (OSError, ssl.SSLError) as exc:
        raise ValueError(f"{section}.tls_cert = {str(cert_path)!r}, {section}.tls_key = "
                         f"{str(key_path)!r}: cannot load them as a PEM certificate and its "
                         f"key ({exc})") from None
    return ctx


def raise_open_files(wanted: int) -> tuple[int, int]:
    """Raise this process's soft limit on open files (RLIMIT_NOFILE) to `wanted`, or to the hard
    limit if that is lower; never lower it. Returns the (soft, hard) limits now in effect
    (resource.RLIM_INFINITY for "unlimited")."""
    if wanted < 1:
        raise ValueError(f"open files wanted = {wanted}: must be at least 1")
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if soft != resource.RLIM_INFINITY and soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        except (ValueError, OSError) as exc:  # a sandbox may refuse even within the hard limit
            log.warning("cannot raise the open-files limit from %d to %d: %s", soft, target, exc)
    return resource.getrlimit(resource.RLIMIT_NOFILE)


@dataclass
class Connection:
    """One client connection: its socket, `transport` ("unix" or "tcp"), the peer's identity, the
    bytes received and not yet handled (`inbuf`) and not yet sent (`outbuf`), and its state
    (authenticated, in the TLS handshake, closing)."""
    sock: socket.socket
    transport: str  # "unix" or "tcp"
    peer: dict[str, Any]
    inbuf: bytearray = field(default_factory=bytearray)
    outbuf: bytearray = field(default_factory=bytearray)
    discarding: bool = False  # inside an oversized line: skip to its newline
    authed: bool = False
    closing: bool = False
    handshaking: bool = False  # TLS: the handshake is not finished yet
    accepted_s: float = 0.0  # the server's clock at accept: the auth deadline counts from it
    # TLS over a cap: this busy error goes out once the handshake is done, then the connection
    # closes (a plaintext reply would reach the client as a TLS protocol error).
    refusal: RpcError | None = None

    @property
    def who(self) -> dict[str, Any]:
        """The peer as the audit log names it: the transport, and for the Unix socket the kernel's
        uid, gid and pid with the user and process names, for TCP the address."""
        return {"transport": self.transport, **self.peer}

    @property
    def remote(self) -> bool:
        """A peer beyond this machine's Unix socket: a TCP client, or a web client the daemon's
        web view names (`web_client`)."""
        return self.transport != "unix" or bool(self.peer.get("web_client"))

    def describe(self) -> str:
        """Who this is, in a few words, for messages and the audit log's reasons."""
        web = self.peer.get("web_client")
        if web:
            return f"the web view's client at {web.get('address', '?')}"
        if self.transport != "unix":
            return f"a TCP peer at {self.peer.get('address', '?')}"
        user = self.peer.get("user")
        uid = self.peer.get("uid")
        if uid is None:
            return "the daemon itself"
        return f"uid {uid}" + (f" ({user})" if user else "") + " on the Unix socket"


Handler = Callable[[Connection, bytes], bytes | None]


def peer_credentials(sock: socket.socket) -> dict[str, Any]:
    """uid, gid and pid of a Unix-socket peer from the kernel (SO_PEERCRED, taken at connect):
    not forgeable, and the uid is what arming authority rests on (`arming.arm_refusal`). Also the
    user's name and the peer's process name (/proc/<pid>/comm), for the audit log and the
    `forwarded_by_ssh` heuristic only: a process chooses its own name."""
    pid, uid, gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                        struct.calcsize("3i")))
    try:
        user = pwd.getpwuid(uid).pw_name
    except KeyError:
        user = None
    try:
        process: str | None = Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:  # gone already, or no descriptor free to read it (EMFILE)
        process = None
    return {"uid": uid, "gid": gid, "pid": pid, "user": user, "process": process}


def forwarded_by_ssh(peer: dict[str, Any]) -> bool:
    """The Unix-socket peer calls itself sshd (`ssh -L local.sock:control.sock`, OpenSSH's session
    process `sshd` or, from 9.8, `sshd-session`): most likely a person on another machine.
    Defence in depth only (it can refuse an arm, never allow one): any relay with another
    name passes, so no guarantee rests on it."""
    return str(peer.get("process") or "").startswith("sshd")


def busy_error(setting: str, limit: int, what: str, extra: str = "") -> RpcError:
    """The `busy` refusal of a connection over a cap, naming the setting (a key of
    `[daemon.server]`) and its value."""
    return RpcError(BUSY, f"too many {what} (daemon.server.{setting} = {limit}){extra}; retry "
                    "later", {"field": f"daemon.server.{setting}",
                              "allowed": f"at most {limit} at once"})


class LineServer:
    """The line server (the module's docstring): the Unix socket at `unix_path`, TCP on
    `settings.tcp_port` (0: none) at `settings.tcp_host`, TLS with `tls`; each complete line goes
    to `handler(connection, line)`, whose reply bytes (None: none) are sent back. Sizes in bytes,
    times in seconds of `clock`."""
    def __init__(self, handler: Handler, *, unix_path: Path,
                 settings: ServerSettings | None = None,
                 tls: ssl.SSLContext | None = None, max_pending_bytes: int = 4 << 20,
                 clock: Callable[[], float] = time.monotonic) -> None:
        """`settings`: `[daemon.server]` (the socket's group, the TCP port and host, and the
        bounds on clients; its TLS files are the caller's to load into `tls`); None: the
        defaults."""
        s = settings = ServerSettings() if settings is None else settings
        if s.tcp_port and s.tcp_host not in LOOPBACK_HOSTS and tls is None:
            # validation refuses this too; a copied configuration skips validation
            raise ValueError(f"daemon.server.tcp_host = {s.tcp_host!r} is not loopback: "
                             "listening elsewhere needs TLS, set daemon.server.tls_cert and "
                             "daemon.server.tls_key")
        self.handler = handler
        self.unix_path = unix_path
        self.settings = settings
        self.socket_group = s.socket_group
        self.tcp_port = s.tcp_port
        self.tcp_host = s.tcp_host
        self.tls = tls
        self.max_line_bytes = s.max_line_bytes
        self.max_clients = s.max_clients  # Unix-socket clients only
        self.max_tcp_clients = s.max_tcp_clients
        self.max_unauthenticated = s.max_unauthenticated
        self.auth_timeout_s = s.auth_timeout_s
        self.max_buffered_bytes = s.max_buffered_bytes
        # One line of the allowed length always fits, whatever the two settings say, so a peer
        # sending one is answered ("line longer than ...") rather than dropped.
        self._inbuf_cap = max(s.max_buffered_bytes, s.max_line_bytes + 1)
        self.lines_per_poll = s.lines_per_poll
        self.tick_budget_s = s.tick_budget_s
        self.max_pending_bytes = max_pending_bytes
        self.clock = clock  # the deadlines' clock (tests may step it)
        self.selector = selectors.DefaultSelector()
        self._listeners: dict[int, tuple[socket.socket, str]] = {}
        self._paused: dict[int, float] = {}  # listener fd -> clock time it is watched again
        self._accept_failing: set[str] = set()  # transports in an EMFILE episode (logged once)
        self.connections: dict[int, Connection] = {}
        self._counts: Counter[str] = Counter()  # served connections per transport
        self._unauthenticated: dict[int, Connection] = {}  # TCP, handshake or before auth
        self._refusing: dict[int, Connection] = {}  # TLS handshakes that end in `busy`
        # Connections with complete lines still unhandled, in the order they are served next.
        self._backlog: dict[int, None] = {}
        self._deadline_s = 0.0  # this poll's serving ends at this clock time
        self.tcp_address: tuple[str, int] | None = None
        # Refusals and drops by reason (busy, auth timeout, input over the cap, accept failed).
        self.refused: Counter[str] = Counter()
        self._logged: dict[str, tuple[float, int]] = {}  # reason -> (clock, count) last logged
        # The most bytes one connection has held received and unhandled (never above the cap).
        self.peak_buffered_bytes = 0

    # -- listening -----------------------------------------------------------------------------

    def listen(self) -> None:
        """Bind and listen: the Unix socket (mode 0660, group `socket_group`; a stale socket
        replaced, any other file refused), then TCP when `tcp_port` is set (`tcp_address` is
        where)."""
        path = self.unix_path
        if path.exists() or path.is_symlink():
            if not stat.S_ISSOCK(path.lstat().st_mode):
                raise RuntimeError(f"{path} exists and is not a socket; not replacing it")
            path.unlink()  # stale: the single-instance lock is already ours
        unix = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o117)  # set before bind: the socket is created 0660, never wider
        try:
            unix.bind(str(path))
        finally:
            os.umask(old)
        if self.socket_group:
            try:
                os.chown(path, -1, grp.getgrnam(self.socket_group).gr_gid)
            except (KeyError, PermissionError) as exc:
                unix.close()
                path.unlink()
                raise RuntimeError(f"daemon.server.socket_group = {self.socket_group!r}: "
                                   f"{exc}") from None
        self._add_listener(unix, "unix")
        if self.tcp_port:
            family, _, _, _, address = socket.getaddrinfo(
                self.tcp_host, self.tcp_port, type=socket.SOCK_STREAM)[0]
            tcp = socket.socket(family, socket.SOCK_STREAM)
            tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            tcp.bind(address)  # loopback, or (checked in __init__) TLS
            self.tcp_address = tcp.getsockname()[:2]
            self._add_listener(tcp, "tcp")

    def _add_listener(self, sock: socket.socket, transport: str) -> None:
        sock.listen(64)
        sock.setblocking(False)
        self._listeners[sock.fileno()] = (sock, transport)
        self.selector.register(sock, selectors.EVENT_READ, ("listen", transport))

    def close(self) -> None:
        """Flush and drop every connection, close the listeners and remove the Unix socket."""
        for conn in list(self.connections.values()):
            self._flush(conn)
            self._drop(conn)
        for sock, transport in self._listeners.values():
            with contextlib.suppress(KeyError, ValueError):  # a paused one is not registered
                self.selector.unregister(sock)
            sock.close()
            if transport == "unix":
                with contextlib.suppress(FileNotFoundError):
                    self.unix_path.unlink()
        self._listeners.clear()
        self._paused.clear()

    # -- loop ----------------------------------------------------------------------------------

    def poll(self, timeout_s: float) -> list[Any]:
        """Serve ready sockets for at most `tick_budget_s`; returns the data of other registered
        files that are ready (those are never held back by the budget)."""
        others = []
        self._resume_listeners(self.clock())
        events = self.selector.select(0 if self._backlog else timeout_s)
        now = self.clock()
        self._deadline_s = now + self.tick_budget_s
        self._expire(now)
        self._summarise(now)
        served: set[int] = set()
        for key, mask in events:
            kind = key.data[0] if isinstance(key.data, tuple) else None
            if kind == "listen":
                # Past the budget a ready socket is left for the next poll: select reports it
                # again at once (level-triggered), so nothing is lost.
                if not self._over_budget():
                    self._accept(key.fileobj, key.data[1])  # type: ignore[arg-type]
            elif kind == "conn":
                conn = key.data[1]
                if key.fd in self.connections and not self._over_budget():
                    served.add(key.fd)
                    self._service(conn, mask)
            else:
                others.append(key.data)
        # The backlog in turn: a connection whose lines were cut short by the budget keeps its
        # place; one served above already had its lines_per_poll for this poll.
        for fd in list(self._backlog):
            if self._over_budget():
                break
            if fd in served:
                continue
            self._backlog.pop(fd, None)
            conn = self.connections.get(fd)
            if conn is not None:
                self._handle_lines(conn)
        return others

    def _over_budget(self) -> bool:
        return self.clock() >= self._deadline_s

    def watch(self, fd: int, data: Any) -> None:
        """Wake `poll` when another file (the frame worker's pipe) is readable; `poll` returns
        `data` for it. The caller drains it, or unwatches it first."""
        self.selector.register(fd, selectors.EVENT_READ, data)

    def unwatch(self, fd: int) -> None:
        """Stop watching fd (safe after it was closed: epoll dropped it then)."""
        with contextlib.suppress(KeyError, ValueError):
            self.selector.unregister(fd)

    def flush_all(self) -> None:
        """Send what every connection has waiting, as far as its socket takes it."""
        for conn in list(self.connections.values()):
            self._flush(conn)

    def buffered_bytes(self) -> int:
        """Bytes received from all connections and not yet handled."""
        return sum(len(c.inbuf) for c in self.connections.values())

    def client_counts(self) -> dict[str, int]:
        """Connections now: served per transport, and TCP ones before `auth` or being refused."""
        return {"unix": self._counts["unix"], "tcp": self._counts["tcp"],
                "unauthenticated": len(self._unauthenticated), "refusing": len(self._refusing)}

    # -- accepting -----------------------------------------------------------------------------

    def _accept(self, listener: socket.socket, transport: str) -> None:
        try:
            sock, address = listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            if exc.errno in FD_EXHAUSTED:
                self._back_off(listener, transport, exc)
            else:  # this one peer's trouble (ECONNABORTED, EPROTO...): the next may be fine
                log.debug("%s accept failed: %s", transport, exc)
            return
        if transport in self._accept_failing:
            self._accept_failing.discard(transport)
            log.info("%s listener: accepting connections again", transport)
        sock.setblocking(False)
        now = self.clock()
        if transport == "unix":
            peer = peer_credentials(sock)
            refusal = (busy_error("max_clients", self.max_clients, "clients on the Unix socket")
                       if self._counts["unix"] >= self.max_clients else None)
        else:
            peer = {"address": f"{address[0]}:{address[1]}"}
            refusal = self._tcp_refusal()
        if refusal is not None and not (transport == "tcp" and self.tls is not None):
            # Plain text: the busy line is the connection's own protocol.
            self._note(f"{transport} connection refused (busy)", {"transport": transport,
                                                                 **peer})
            with contextlib.suppress(OSError):
                sock.send(protocol.dumps(protocol.error_reply(None, refusal)))
            sock.close()
            return
        handshaking = False
        if transport == "tcp" and self.tls is not None:
            if refusal is not None and len(self._refusing) >= self.max_unauthenticated:
                # Even the handshakes that would carry `busy` are at their cap: close at once.
                # The client sees the connection closed during its handshake, never plaintext.
                self._note("tls connection closed unanswered (busy)", peer)
                sock.close()
                return
            try:
                sock = self.tls.wrap_socket(sock, server_side=True,
                                            do_handshake_on_connect=False)
            except (OSError, ssl.SSLError):
                sock.close()
                return
            peer["tls"] = True
            handshaking = True
        conn = Connection(sock, transport, peer, handshaking=handshaking, accepted_s=now,
                          refusal=refusal)
        fd = sock.fileno()
        self.connections[fd] = conn
        if refusal is not None:
            self._note("tls connection refused (busy)", peer)
            self._refusing[fd] = conn
        else:
            self._counts[transport] += 1
            if transport == "tcp":
                self._unauthenticated[fd] = conn
        self.selector.register(sock, selectors.EVENT_READ, ("conn", conn))
        if handshaking:
            self._handshake(conn)

    def _tcp_refusal(self) -> RpcError | None:
        if self._counts["tcp"] >= self.max_tcp_clients:
            return busy_error("max_tcp_clients", self.max_tcp_clients, "TCP clients")
        if len(self._unauthenticated) >= self.max_unauthenticated:
            return busy_error("max_unauthenticated", self.max_unauthenticated,
                              "TCP connections waiting to authenticate",
                              f", each dropped after daemon.server.auth_timeout_s = "
                              f"{self.auth_timeout_s:g} s")
        return None

    def _expire(self, now: float) -> None:
        """Forget connections that have authenticated; drop those past their deadline."""
        for pool in (self._unauthenticated, self._refusing):
            for fd, conn in list(pool.items()):
                if conn.authed:
                    del pool[fd]
                elif now - conn.accepted_s >= self.auth_timeout_s:
                    self._note(f"dropped: no auth within daemon.server.auth_timeout_s = "
                               f"{self.auth_timeout_s:g} s", conn.who)
                    self._drop(conn)

    def _back_off(self, listener: socket.socket, transport: str, exc: OSError) -> None:
        """Out of descriptors: stop watching this listener for ACCEPT_BACKOFF_S. Connections
        wait in the kernel's backlog (or are refused by it); the served ones go on."""
        with contextlib.suppress(KeyError, ValueError):
            self.selector.unregister(listener)
        self._paused[listener.fileno()] = self.clock() + ACCEPT_BACKOFF_S
        self.refused[f"{transport} accept failed"] += 1
        if transport not in self._accept_failing:
            self._accept_failing.add(transport)
            log.warning("%s listener: accept failed (%s); not accepting for %g s at a time "
                        "until descriptors are free; connected clients are still served",
                        transport, exc.strerror or exc, ACCEPT_BACKOFF_S)

    def _resume_listeners(self, now: float) -> None:
        for fd, until in list(self._paused.items()):
            if now >= until and fd in self._listeners:
                del self._paused[fd]
                sock, transport = self._listeners[fd]
                self.selector.register(sock, selectors.EVENT_READ, ("listen", transport))

    def _note(self, reason: str, who: dict[str, Any]) -> None:
        """Count a refusal or drop; log it with the peer the first time, then at most once per
        REFUSAL_LOG_EVERY_S (the others are counted, and summed up by `_summarise`)."""
        self.refused[reason] += 1
        now = self.clock()
        last = self._logged.get(reason)
        if last is not None and now - last[0] < REFUSAL_LOG_EVERY_S:
            return
        since = self.refused[reason] - (last[1] if last else 0) - 1
        log.warning("%s: %s%s", reason, who,
                    f" ({since} more like this before it)" if since else "")
        self._logged[reason] = (now, self.refused[reason])

    def _summarise(self, now: float) -> None:
        """One line per reason whose window has passed with refusals not yet logged."""
        for reason, (when, count) in list(self._logged.items()):
            if now - when >= REFUSAL_LOG_EVERY_S and self.refused[reason] > count:
                log.warning("%s: %d more in the last %.0f s", reason,
                            self.refused[reason] - count, now - when)
                self._logged[reason] = (now, self.refused[reason])

    def _handshake(self, conn: Connection) -> bool:
        """Advance a TLS handshake; True once it is done. A failed one (a plain-text client, an
        untrusted certificate on the client's side) drops the connection; so does a done one
        that was accepted over a cap, after its `busy` reply."""
        want = selectors.EVENT_READ
        try:
            conn.sock.do_handshake()  # type: ignore[attr-defined]
        except ssl.SSLWantReadError:
            return False
        except ssl.SSLWantWriteError:
            want |= selectors.EVENT_WRITE
            with contextlib.suppress(KeyError, ValueError):
                self.selector.modify(conn.sock, want, ("conn", conn))
            return False
        except (OSError, ssl.SSLError) as exc:
            log.info("TLS handshake with %s failed: %s", conn.peer.get("address"), exc)
            self._drop(conn)
            return False
        conn.handshaking = False
        if conn.refusal is not None:
            # The reply, then close_notify: the client reads an RPC error, then a clean end.
            conn.outbuf += protocol.dumps(protocol.error_reply(None, conn.refusal))
            self._flush(conn)
            with contextlib.suppress(OSError, ValueError):
                conn.sock.unwrap()  # type: ignore[attr-defined]  # sends close_notify
            self._drop(conn)
            return False
        with contextlib.suppress(KeyError, ValueError):
            self.selector.modify(conn.sock, want, ("conn", conn))
        return True

    # -- reading and handling ------------------------------------------------------------------

    def _service(self, conn: Connection, events: int) -> None:
        if conn.handshaking and not self._handshake(conn):
            return
        if events & selectors.EVENT_WRITE:
            self._flush(conn)
            if conn.sock.fileno() < 0:
                return
        if events & selectors.EVENT_READ:
            # One byte more than fits tells a peer that sent more than may wait from one that
            # merely filled the buffer; reading no more than that keeps the copy bounded.
            data = self._receive(conn, self._inbuf_cap - len(conn.inbuf) + 1)
            if data is None:
                return
            if not data:
                self._drop(conn)
                return
            conn.inbuf += data
            pending = getattr(conn.sock, "pending", None)
            if len(conn.inbuf) > self._inbuf_cap or (
                    pending is not None and pending() and len(conn.inbuf) >= self._inbuf_cap):
                self._overflow(conn)  # (TLS: more already decrypted than fits)
                return
            self.peak_buffered_bytes = max(self.peak_buffered_bytes, len(conn.inbuf))
            self._handle_lines(conn)

    def _receive(self, conn: Connection, limit: int) -> bytes | None:
        """At most `limit` bytes of what the peer sent (b"" when it hung up), None when nothing
        is there yet. TLS hands out one record per recv and may hold more already decrypted,
        which select cannot see: that is read too, up to the limit."""
        data = bytearray()
        try:
            while len(data) < limit:
                chunk = conn.sock.recv(min(RECV_CHUNK_BYTES, limit - len(data)))
                if not chunk:
                    break
                data += chunk
                pending = getattr(conn.sock, "pending", None)
                if pending is None or not pending():
                    break
        except (BlockingIOError, InterruptedError, ssl.SSLWantReadError,
                ssl.SSLWantWriteError):
            return bytes(data) if data else None
        except OSError:
            pass
        return bytes(data)

    def _overflow(self, conn: Connection) -> None:
        self._note(f"dropped: more than daemon.server.max_buffered_bytes = {self._inbuf_cap} bytes "
                   "received and not yet handled", conn.who)
        self._drop(conn)

    def _handle_lines(self, conn: Connection) -> None:
        for _ in range(self.lines_per_poll):  # empty lines and skipped tails count too
            if conn.sock.fileno() < 0:
                return
            if self._over_budget():
                break
            end = conn.inbuf.find(b"\n")
            if end < 0:
                if conn.discarding:
                    conn.inbuf.clear()
                elif len(conn.inbuf) > self.max_line_bytes:
                    self._oversize(conn)
                    conn.inbuf.clear()
                    conn.discarding = True
                return
            line = bytes(conn.inbuf[:end])
            del conn.inbuf[: end + 1]
            if conn.discarding:  # the tail of an oversized line
                conn.discarding = False
                continue
            if len(line) > self.max_line_bytes:
                self._oversize(conn)
                continue
            if not line.strip():
                continue
            try:
                reply = self.handler(conn, line)
            except RecursionError:
                # Parsing already refuses deep nesting; whatever else recursion breaks on, one
                # request must not end the loop (and with it the daemon).
                log.error("request from %s: nested too deeply for its handler", conn.who)
                reply = protocol.dumps(protocol.error_reply(None, RpcError(
                    INTERNAL_ERROR, "request nested too deeply; not applied")))
            if reply:
                self._send(conn, reply)
            if conn.closing:
                self._flush(conn)
                self._drop(conn)
                return
        fd = conn.sock.fileno()
        if fd >= 0:
            self._backlog.pop(fd, None)
            if b"\n" in conn.inbuf:
                self._backlog[fd] = None  # to the back of the queue

    def _oversize(self, conn: Connection) -> None:
        err = RpcError(INVALID_REQUEST, f"line longer than {self.max_line_bytes} bytes "
                       "(daemon.server.max_line_bytes); skipped",
                       {"field": "line", "allowed": f"at most {self.max_line_bytes} bytes"})
        self._send(conn, protocol.dumps(protocol.error_reply(None, err)))

    # -- writing and closing -------------------------------------------------------------------

    def _send(self, conn: Connection, data: bytes) -> None:
        conn.outbuf += data
        self._flush(conn)
        if len(conn.outbuf) > self.max_pending_bytes:
            self._note("dropped: does not read its replies", conn.who)
            self._drop(conn)

    def _flush(self, conn: Connection) -> None:
        if conn.sock.fileno() < 0:
            return
        try:
            while conn.outbuf:
                sent = conn.sock.send(conn.outbuf)
                del conn.outbuf[:sent]
        except (BlockingIOError, InterruptedError, ssl.SSLWantReadError, ssl.SSLWantWriteError):
            pass
        except OSError:
            self._drop(conn)
            return
        want = selectors.EVENT_READ | (selectors.EVENT_WRITE if conn.outbuf else 0)
        with contextlib.suppress(KeyError, ValueError):
            self.selector.modify(conn.sock, want, ("conn", conn))

    def _drop(self, conn: Connection) -> None:
        fd = conn.sock.fileno()
        if fd >= 0:
            with contextlib.suppress(KeyError, ValueError):
                self.selector.unregister(conn.sock)
            if self.connections.pop(fd, None) is not None and conn.refusal is None:
                self._counts[conn.transport] -= 1
            self._unauthenticated.pop(fd, None)
            self._refusing.pop(fd, None)
            self._backlog.pop(fd, None)
            conn.sock.close()
