"""The reference client of `nhfd serve`: JSON-RPC 2.0 lines over the Unix socket or TCP (TLS).

Standard library only (no torch, numba, onnxruntime, not even numpy), so `nhfctl` answers in a
fraction of a second. Every call is bounded by `timeout_s`.

    with Client() as c:                       # the socket from the configuration's rules
        c.call("set_view", orbit={"azimuth_deg": 30, "elevation_deg": 10, "radius": 4})
        print(c.status()["laser"]["armed"])

    # another machine: TLS, the daemon's certificate (or its CA) pinned, and the token
    with Client(tcp=("bench.lab", 7700), tls_ca="bench.pem", token=token) as c: ...

A token is sent to a host other than loopback only over TLS (ValueError otherwise).
"""

from __future__ import annotations

import itertools
import os
import socket
import ssl
import time
from pathlib import Path
from typing import Any

from . import protocol
from .paths import control_socket
from .protocol import RpcError

LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")


class DaemonUnavailable(ConnectionError):
    """Nothing answers on the socket (or it hung up / timed out)."""


class TLSFailure(DaemonUnavailable):
    """The TLS handshake failed: most often the daemon's certificate is not the one trusted."""


def client_tls_context(ca_path: str | os.PathLike[str] | None = None) -> ssl.SSLContext:
    """Verifies the daemon's certificate and host name: against `ca_path` (the daemon's own
    self-signed certificate, or the CA that signed it: pinning) or the system's CAs."""
    ctx = ssl.create_default_context(cafile=str(ca_path) if ca_path else None)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    return ctx


class Client:
    """A connection to `nhfd serve`: the Unix socket (`socket_path`, default the configuration's
    control socket) or TCP (`tcp` = (host, port); TLS with `tls` or `tls_ca`, and `token` sent as
    `auth`). Every send and read is bounded by `timeout_s` (s); DaemonUnavailable when nothing
    answers, TLSFailure when the handshake fails."""
    def __init__(self, socket_path: str | os.PathLike[str] | None = None, *,
                 tcp: tuple[str, int] | None = None, token: str | None = None,
                 tls: bool | ssl.SSLContext = False,
                 tls_ca: str | os.PathLike[str] | None = None,
                 timeout_s: float = 5.0) -> None:
        self._ids = itertools.count(1)
        self._buffer = bytearray()
        use_tls = bool(tls) or tls_ca is not None
        if tcp is not None:
            host, port = tcp
            self.where = f"{host}:{port}"
            if token is not None and not use_tls and host not in LOOPBACK_HOSTS:
                raise ValueError(f"{self.where} is not loopback: the token goes there only over "
                                 "TLS (tls_ca / nhfctl --tls-ca) or through an SSH tunnel")
            try:
                self._sock = socket.create_connection((host, port), timeout=timeout_s)
            except OSError as exc:
                raise DaemonUnavailable(f"no nhfd serve at {self.where} "
                                        f"({exc.strerror or exc})") from None
            if use_tls:
                ctx = tls if isinstance(tls, ssl.SSLContext) else client_tls_context(tls_ca)
                try:
                    self._sock = ctx.wrap_socket(self._sock, server_hostname=host)
                except ssl.SSLCertVerificationError as exc:
                    self._sock.close()
                    raise TLSFailure(f"TLS with nhfd serve at {self.where} failed: certificate "
                                     f"verify failed: {exc.verify_message} (the certificate "
                                     "trusted is tls_ca / nhfctl --tls-ca)") from None
                except (OSError, ssl.SSLError) as exc:
                    self._sock.close()
                    raise TLSFailure(f"TLS with nhfd serve at {self.where} failed: "
                                     f"{exc}") from None
        else:
            path = Path(socket_path) if socket_path else control_socket()
            self.where = str(path)
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            self._sock.settimeout(timeout_s)
            try:
                self._sock.connect(str(path))
            except OSError as exc:
                self._sock.close()
                raise DaemonUnavailable(f"no nhfd serve at {self.where} "
                                        f"({exc.strerror or exc})") from None
        if token is not None:
            self.call("auth", token=token)

    def send_raw(self, data: bytes) -> None:
        """Send `data` as it is (request lines, or any bytes a test sends); DaemonUnavailable when
        the socket fails."""
        try:
            self._sock.sendall(data)
        except OSError as exc:
            raise DaemonUnavailable(f"nhfd serve at {self.where}: {exc}") from None

    def read_reply(self) -> Any:
        """The next reply line, parsed."""
        try:
            while (end := self._buffer.find(b"\n")) < 0:
                chunk = self._sock.recv(65536)
                if not chunk:
                    raise DaemonUnavailable(f"nhfd serve at {self.where} hung up")
                self._buffer += chunk
        except TimeoutError:
            raise DaemonUnavailable(f"nhfd serve at {self.where} did not answer") from None
        except OSError as exc:
            raise DaemonUnavailable(f"nhfd serve at {self.where}: {exc}") from None
        line = bytes(self._buffer[:end])
        del self._buffer[: end + 1]
        return protocol.loads(line)

    def call(self, method: str, **params: Any) -> Any:
        """Call and wait; RpcError (with the daemon's code, message and data) on an error."""
        request_id = next(self._ids)
        self.send_raw(protocol.dumps(protocol.request(method, params, request_id)))
        reply = self.read_reply()
        if not isinstance(reply, dict) or reply.get("id") != request_id:
            raise DaemonUnavailable(f"nhfd serve at {self.where}: unexpected reply {reply!r:.200}")
        if "error" in reply:
            err = reply["error"]
            raise RpcError(int(err.get("code", 0)), str(err.get("message", "")),
                           err.get("data"), request_id=request_id)
        return reply.get("result")

    def notify(self, method: str, **params: Any) -> None:
        """A notification: no reply comes back."""
        self.send_raw(protocol.dumps(protocol.request(method, params)))

    def status(self) -> dict[str, Any]:
        """The daemon's `status` reply."""
        return self.call("status")

    def wait_job(self, job_id: int, timeout_s: float = 600.0, poll_s: float = 0.1
                 ) -> dict[str, Any]:  # fmt: skip
        """The job `job_id` once it has ended, or as it stands after `timeout_s` (its state then
        still "queued" or "running": the caller decides what a timeout means)."""
        end = time.monotonic() + timeout_s
        while True:
            job = self.call("job", id=job_id)
            if job["state"] not in ("queued", "running") or time.monotonic() > end:
                return job
            time.sleep(poll_s)

    def wait_view(self, seq: int, refined: bool, timeout_s: float = 600.0, poll_s: float = 0.2
                  ) -> dict[str, Any]:  # fmt: skip
        """The `status` once view `seq` rests: shown, and with `refined` (it asked for a tier
        above the network's) its refinement stopped; or as it stands when a newer view
        replaced it, or after `timeout_s` (the caller reads `view` and `frames.refine`)."""
        end = time.monotonic() + timeout_s
        while True:
            s = self.status()
            view, refine = s["view"], (s.get("frames") or {}).get("refine") or {}
            shown = (view.get("applied_seq") or 0) >= seq
            stopped = refine.get("seq") == seq and bool(refine.get("stop"))
            if view["seq"] != seq or time.monotonic() > end or (
                    shown and (stopped or not refined)):
                return s
            time.sleep(poll_s)

    def close(self) -> None:
        """Close the connection."""
        self._sock.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
