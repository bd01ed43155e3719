"""JSON-RPC lines to the methods: parsing, batches, authentication on TCP, refusals while
stopping, and what each method's table entry asks for (the audit log, the session recording).

The line server (`server.LineServer`) hands every line it reads to `Dispatcher.handle_line` on
the control loop's thread; the reply (or None for a notification) goes back on the same
connection. The dispatcher knows the methods' context (`methods.RpcContext`), the audit log and
the recorder, and reports through callbacks given at construction: an internal error for
`status`, and a change of the bench (the next heartbeat goes out at once, so `status` shows the
guardian's state after it).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

from . import protocol
from .audit import AuditLog, compact_params
from .methods import METHODS, Method, RpcContext
from .protocol import (
    INTERNAL_ERROR,
    INVALID_PARAMS,
    INVALID_REQUEST,
    METHOD_NOT_FOUND,
    SHUTTING_DOWN,
    UNAUTHORIZED,
    Params,
    RpcError,
)
from .recording import SessionRecorder
from .server import Connection

log = logging.getLogger("nhfd.daemon")


class Dispatcher:
    """One request (or batch) at a time, from the control loop: the method's reply, or the
    error reply that names what was wrong."""

    def __init__(self, context: RpcContext, audit: AuditLog, recorder: SessionRecorder, *,
                 max_batch: int, stopping: Callable[[], bool],
                 on_error: Callable[[str, str], None], on_change: Callable[[], None],
                 methods: Mapping[str, Method] = METHODS) -> None:
        """`context`: what the methods act on. `audit`, `recorder`: where bench-changing
        requests are written. `max_batch`: `daemon.server.max_batch` (0: batches refused).
        `stopping()`: whether the daemon is shutting down (only `while_stopping` methods are
        served then). `on_error(source, message)`: a method that failed inside the daemon, for
        `status`. `on_change()`: an audited method succeeded (the bench, or the lasers, may
        have changed). `methods`: the method table (the module's, looked up per request)."""
        self.context = context
        self.audit = audit
        self.recorder = recorder
        self.max_batch = max_batch
        self.stopping = stopping
        self.on_error = on_error
        self.on_change = on_change
        self.methods = methods

    def handle_line(self, conn: Connection, line: bytes) -> bytes | None:
        """One line from `conn` -> the reply line (None: nothing to send back)."""
        try:
            msg = protocol.loads(line)
        except RpcError as exc:
            return protocol.dumps(protocol.error_reply(None, exc))
        if isinstance(msg, list):
            return self._batch(conn, msg)
        reply = self.handle_message(conn, msg)
        return protocol.dumps(reply) if reply is not None else None

    def _batch(self, conn: Connection, batch: list[Any]) -> bytes | None:
        cap = self.max_batch
        if cap == 0:
            err = RpcError(INVALID_REQUEST, "batches are not supported "
                           "(daemon.server.max_batch = 0); send one request per line")
        elif not batch:
            err = RpcError(INVALID_REQUEST, "empty batch")
        elif len(batch) > cap:
            err = RpcError(INVALID_REQUEST, f"batch of {len(batch)} requests",
                           {"field": "batch", "allowed": f"1 to {cap} requests"})
        else:
            replies = [r for m in batch if (r := self.handle_message(conn, m)) is not None]
            return protocol.dumps(replies) if replies else None
        return protocol.dumps(protocol.error_reply(None, err))

    def handle_message(self, conn: Connection, msg: Any) -> dict[str, Any] | None:
        """One request -> its reply (None for a notification, even when it failed)."""
        notification = isinstance(msg, dict) and "id" not in msg
        try:
            req = protocol.to_request(msg)
        except RpcError as exc:
            if notification and exc.code == INVALID_PARAMS.code:
                return None
            return protocol.error_reply(exc.request_id, exc)
        try:
            result = self._call(conn, req)
        except RpcError as exc:
            return None if req.notification else protocol.error_reply(req.id, exc)
        return None if req.notification else protocol.result_reply(req.id, result)

    def _call(self, conn: Connection, req: protocol.Request) -> Any:
        if conn.transport == "tcp" and not conn.authed and req.method != "auth":
            raise RpcError(UNAUTHORIZED, "send auth {token} first on a TCP connection")
        method = self.methods.get(req.method)
        if method is None:
            raise RpcError(METHOD_NOT_FOUND, f"no method {req.method[:80]!r}",
                           {"field": "method", "allowed": sorted(self.methods)})
        if self.stopping() and not method.while_stopping:
            raise RpcError(SHUTTING_DOWN, "the daemon is shutting down")
        try:
            result = method.func(self.context, conn, Params(req.params))
        except RpcError as exc:
            if method.audited:  # compact and summarised: any client can send refusals
                self.audit.refused(conn.who, req.method, exc.code, exc.name, exc.message,
                                   req.params)
            raise
        except Exception as exc:
            log.exception("%s failed", req.method)
            self.on_error("daemon", f"{req.method}: {type(exc).__name__}: {exc}")
            if method.audited:
                self.audit.write(conn.who, req.method, params=compact_params(req.params),
                                 outcome=f"internal error: {exc}")
            raise RpcError(INTERNAL_ERROR, f"{req.method} failed: {type(exc).__name__}: "
                           f"{exc}") from None
        if method.audited:
            self.audit.write(conn.who, req.method, params=req.params, outcome="ok",
                             result=result)
            # Arming and the guardian's state reach `status` through the heartbeat's reply:
            # after a command that changed the bench (or the lasers, as a device fault or a
            # crashed worker does), the next one goes out in this step.
            self.on_change()
        if self.recorder.recording and (method.audited or req.method == "set_view"):
            self.recorder.record_request(req.method, req.params, conn.who, result)
        return result
