"""The line server: a Unix socket (mode 0660, a lab group) and optional TCP, TLS where asked.

Single-threaded and non-blocking, driven by the control loop's `poll()`, so request handling and
the laser heartbeat share one thread: if handling hangs, the heartbeat stops and the guardian
switches the lasers off. Each connection gets at most `lines_per_poll` requests per poll, so one
flooding client cannot starve the others or the heartbeat. A line over the size cap is answered
with an error and skipped up to its newline; a client that stops reading its replies is dropped
once `max_pending_bytes` are waiting.

The TCP port listens on loopback unless `daemon.tcp_host` says otherwise, and then only with TLS
(`daemon.tls_cert`, `daemon.tls_key`): a token never crosses a network in clear. The TLS handshake
runs non-blocking in the same loop, so a slow or silent peer holds a client slot, never the loop.
"""

from __future__ import annotations

import contextlib
import grp
import logging
import os
import pwd
import selectors
import socket
import ssl
import stat
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import protocol
from .protocol import INVALID_REQUEST, RpcError

log = logging.getLogger("nhfd.daemon.server")

LOOPBACK = "127.0.0.1"
LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")


def server_tls_context(cert_path: str | os.PathLike[str], key_path: str | os.PathLike[str],
                       section: str = "daemon") -> ssl.SSLContext:
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


@dataclass
class Connection:
    sock: socket.socket
    transport: str  # "unix" or "tcp"
    peer: dict[str, Any]
    inbuf: bytearray = field(default_factory=bytearray)
    outbuf: bytearray = field(default_factory=bytearray)
    discarding: bool = False  # inside an oversized line: skip to its newline
    authed: bool = False
    closing: bool = False
    handshaking: bool = False  # TLS: the handshake is not finished yet

    @property
    def who(self) -> dict[str, Any]:
        return {"transport": self.transport, **self.peer}


Handler = Callable[[Connection, bytes], bytes | None]


def peer_credentials(sock: socket.socket) -> dict[str, Any]:
    """uid, gid and pid of a Unix-socket peer from the kernel (SO_PEERCRED): not forgeable; and
    the peer's process name, which says when the socket is forwarded through SSH (`sshd`)."""
    pid, uid, gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                        struct.calcsize("3i")))
    try:
        user = pwd.getpwuid(uid).pw_name
    except KeyError:
        user = None
    try:
        process: str | None = Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        process = None
    return {"uid": uid, "gid": gid, "pid": pid, "user": user, "process": process}


def forwarded_by_ssh(peer: dict[str, Any]) -> bool:
    """The Unix-socket peer is sshd (`ssh -L local.sock:control.sock`, OpenSSH's session process
    `sshd` or, from 9.8, `sshd-session`): a person on another machine, not at the bench."""
    return str(peer.get("process") or "").startswith("sshd")


class LineServer:
    def __init__(self, handler: Handler, *, unix_path: Path, socket_group: str = "",
                 tcp_port: int = 0, tcp_host: str = LOOPBACK, tls: ssl.SSLContext | None = None,
                 max_line_bytes: int = 65536, max_clients: int = 64,
                 lines_per_poll: int = 64, max_pending_bytes: int = 4 << 20) -> None:
        if tcp_port and tcp_host not in LOOPBACK_HOSTS and tls is None:
            raise ValueError(f"daemon.tcp_host = {tcp_host!r} is not loopback: listening "
                             "elsewhere needs TLS, set daemon.tls_cert and daemon.tls_key")
        self.handler = handler
        self.unix_path = unix_path
        self.socket_group = socket_group
        self.tcp_port = tcp_port
        self.tcp_host = tcp_host
        self.tls = tls
        self.max_line_bytes = max_line_bytes
        self.max_clients = max_clients
        self.lines_per_poll = lines_per_poll
        self.max_pending_bytes = max_pending_bytes
        self.selector = selectors.DefaultSelector()
        self._listeners: dict[int, tuple[socket.socket, str]] = {}
        self.connections: dict[int, Connection] = {}
        self._backlog: set[int] = set()  # connections with complete lines still unhandled
        self.tcp_address: tuple[str, int] | None = None

    # -- listening -----------------------------------------------------------------------------

    def listen(self) -> None:
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
                raise RuntimeError(f"daemon.socket_group = {self.socket_group!r}: {exc}") from None
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
        for conn in list(self.connections.values()):
            self._flush(conn)
            self._drop(conn)
        for sock, transport in self._listeners.values():
            self.selector.unregister(sock)
            sock.close()
            if transport == "unix":
                with contextlib.suppress(FileNotFoundError):
                    self.unix_path.unlink()
        self._listeners.clear()

    # -- loop ----------------------------------------------------------------------------------

    def poll(self, timeout_s: float) -> list[Any]:
        """Serve ready sockets; returns the data of other registered files that are ready."""
        others = []
        for key, _ in self.selector.select(0 if self._backlog else timeout_s):
            kind = key.data[0] if isinstance(key.data, tuple) else None
            if kind == "listen":
                self._accept(key.fileobj, key.data[1])  # type: ignore[arg-type]
            elif kind == "conn":
                conn = key.data[1]
                if key.fd in self.connections:
                    self._service(conn, key.events)
            else:
                others.append(key.data)
        for fd in list(self._backlog):
            conn = self.connections.get(fd)
            self._backlog.discard(fd)
            if conn is not None:
                self._handle_lines(conn)
        return others

    def watch(self, fd: int, data: Any) -> None:
        """Wake `poll` when another file (the frame worker's pipe) is readable; `poll` returns
        `data` for it. The caller drains it, or unwatches it first."""
        self.selector.register(fd, selectors.EVENT_READ, data)

    def unwatch(self, fd: int) -> None:
        """Stop watching fd (safe after it was closed: epoll dropped it then)."""
        with contextlib.suppress(KeyError, ValueError):
            self.selector.unregister(fd)

    def flush_all(self) -> None:
        for conn in list(self.connections.values()):
            self._flush(conn)

    def _accept(self, listener: socket.socket, transport: str) -> None:
        try:
            sock, address = listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        if len(self.connections) >= self.max_clients:
            with contextlib.suppress(OSError):
                sock.sendall(protocol.dumps(protocol.error_reply(None, RpcError(
                    protocol.BUSY, f"too many clients (daemon.max_clients = "
                    f"{self.max_clients})"))))
            sock.close()
            return
        sock.setblocking(False)
        peer = (peer_credentials(sock) if transport == "unix"
                else {"address": f"{address[0]}:{address[1]}"})
        handshaking = False
        if transport == "tcp" and self.tls is not None:
            try:
                sock = self.tls.wrap_socket(sock, server_side=True,
                                            do_handshake_on_connect=False)
            except (OSError, ssl.SSLError):
                sock.close()
                return
            peer["tls"] = True
            handshaking = True
        conn = Connection(sock, transport, peer, handshaking=handshaking)
        self.connections[sock.fileno()] = conn
        self.selector.register(sock, selectors.EVENT_READ, ("conn", conn))
        if handshaking:
            self._handshake(conn)

    def _handshake(self, conn: Connection) -> bool:
        """Advance a TLS handshake; True once it is done. A failed one (a plain-text client, an
        untrusted certificate on the client's side) drops the connection."""
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
        with contextlib.suppress(KeyError, ValueError):
            self.selector.modify(conn.sock, want, ("conn", conn))
        return True

    def _service(self, conn: Connection, events: int) -> None:
        if conn.handshaking and not self._handshake(conn):
            return
        if events & selectors.EVENT_WRITE:
            self._flush(conn)
        if events & selectors.EVENT_READ:
            data = self._receive(conn)
            if data is None:
                return
            if not data:
                self._drop(conn)
                return
            conn.inbuf += data
            self._handle_lines(conn)

    def _receive(self, conn: Connection) -> bytes | None:
        """What the peer sent (b"" when it hung up), None when nothing is there yet. TLS hands
        out one record per recv and may hold more already decrypted, which select cannot see:
        that is read too."""
        data = bytearray()
        try:
            while True:
                chunk = conn.sock.recv(65536)
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

    def _handle_lines(self, conn: Connection) -> None:
        for _ in range(self.lines_per_poll):
            if conn.sock.fileno() < 0:
                return
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
            reply = self.handler(conn, line)
            if reply:
                self._send(conn, reply)
            if conn.closing:
                self._flush(conn)
                self._drop(conn)
                return
        if b"\n" in conn.inbuf:
            self._backlog.add(conn.sock.fileno())

    def _oversize(self, conn: Connection) -> None:
        err = RpcError(INVALID_REQUEST, f"line longer than {self.max_line_bytes} bytes "
                       "(daemon.max_line_bytes); skipped",
                       {"field": "line", "allowed": f"at most {self.max_line_bytes} bytes"})
        self._send(conn, protocol.dumps(protocol.error_reply(None, err)))

    def _send(self, conn: Connection, data: bytes) -> None:
        conn.outbuf += data
        self._flush(conn)
        if len(conn.outbuf) > self.max_pending_bytes:
            log.warning("dropping a client that does not read its replies: %s", conn.who)
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
            self.connections.pop(fd, None)
            self._backlog.discard(fd)
            conn.sock.close()
