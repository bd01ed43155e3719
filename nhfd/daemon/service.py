"""The daemon core: start-up in a safe order, the control loop, and shutdown with lasers off.

Start-up: runtime directory -> single-instance lock (fcntl on `nhfd.lock`) -> audit log ->
laser guardian (connect or start) -> every laser off *and read back* -> SLM (showing the
zero-amplitude pattern), stage (identified, never moved), camera -> sockets -> READY=1.

The loop (main thread): serve requests, heartbeat to the guardian, feed systemd's watchdog,
write audit summaries. It sleeps in `select` until the next thing due (`wait_s`): the heartbeat
every `daemon.tick_s`, or the navigator's next read; a request or the frame worker's pipe wakes it
at once. So an idle daemon wakes only for its heartbeats, and a stuck loop stops both the
heartbeat (the guardian switches the lasers off) and the watchdog (systemd restarts the unit; its
stop hook runs `nhfd laser-off`).

Exit paths and the lasers:
  shutdown / SIGTERM / SIGINT / an exception in the loop -> `close()`: lasers off via the
      guardian and read back first, then jobs, stage, SLM (blank), sockets, lock;
  SIGKILL, OOM, a native crash, a hang -> the guardian sees the connection close or the
      heartbeat stop and switches everything off (it keeps running and owns the port);
  afterwards, under systemd -> ExecStopPost=nhfd laser-off.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import queue
import resource
import secrets
import signal
import socket
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

from nhfd import __version__
from nhfd.calibration import active_calibration, calibration_refusal, new_refusal
from nhfd.config import ConfigError, cross_field_problems

from . import protocol
from .arming import ArmingGate
from .audit import AuditLog, compact_params
from .bench import Bench, focus_stage_mm
from .frame_link import FrameEvents, FrameLink, apply_camera_roi
from .guardian_link import LaserLink
from .jobs import Job, JobRunner
from .methods import METHODS
from .navigation import NavigatorInput
from .notify import Notifier
from .panel import Panel
from .paths import LOCK_NAME, SOCKET_NAME, TOKEN_NAME, make_private_dir, resolve_dirs, runtime_dir
from .protocol import (
    BUSY,
    INTERNAL_ERROR,
    INVALID_PARAMS,
    INVALID_REQUEST,
    METHOD_NOT_FOUND,
    SHUTTING_DOWN,
    UNAUTHORIZED,
    Params,
    RpcError,
)
from .recording import SessionRecorder, view_params
from .server import Connection, LineServer, raise_open_files, server_tls_context
from .views import ViewSlot

log = logging.getLogger("nhfd.daemon")

SIGNAL_WAKE = ("signal",)  # the selector's tag of the signal wake-up socket


class AlreadyRunning(RuntimeError):
    """Another `nhfd serve` holds the lock in this runtime directory."""


class _Logfmt(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage().replace('"', "'").replace("\n", " | ")
        when = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        line = f'ts={when}.{int(record.msecs):03d}Z level={record.levelname.lower()} ' \
               f'logger={record.name} msg="{msg}"'
        if record.exc_info:
            line += ' exc="' + self.formatException(record.exc_info).replace("\n", " | ") + '"'
        return line


class _Json(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out = {"ts": record.created, "level": record.levelname.lower(), "logger": record.name,
               "msg": record.getMessage()}
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


def setup_logging(fmt: str, level: int = logging.INFO) -> None:
    """Structured lines on stderr (journald stores them as they are)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Json() if fmt == "json" else _Logfmt())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)


class Daemon:
    def __init__(self, config: Any, *, base_dir: Path | None = None,
                 env: dict[str, str] | None = None, handle_signals: bool = True) -> None:
        self.config = config
        self.env = dict(os.environ if env is None else env)
        self.base_dir = (base_dir or Path.cwd()).resolve()
        c = config.daemon
        self.runtime_dir = runtime_dir(c.runtime_dir, self.env)
        self.socket_path = self.runtime_dir / SOCKET_NAME
        self.scene_dirs = resolve_dirs(c.scene_dirs, self.base_dir)
        self.model_dirs = resolve_dirs(c.model_dirs, self.base_dir)
        self.snapshot_dirs = resolve_dirs([c.snapshot_dir], self.base_dir)
        self.pattern_dirs = resolve_dirs(c.pattern_dirs, self.base_dir)
        self.handle_signals = handle_signals
        self.notifier = Notifier(self.env)
        self.audit = self._audit_log(None)
        self.laser: LaserLink = LaserLink(config.devices.readybeam, config.devices.laser,
                                          c.guardian, self.audit, refresh_s=c.laser_refresh_s,
                                          runtime_dir=self.runtime_dir,
                                          socket_group=c.socket_group)
        self.bench = Bench(config)
        self.views = ViewSlot()
        # The spawned render/inference worker, started on demand. Its events come back here;
        # the bench (and so the panel) is replaced at start, hence the getters.
        self.frames = FrameLink(config, self.views, lambda: self.panel, FrameEvents(
            shown=self.views.mark_applied, error=self._error,
            crashed=self._frame_worker_crashed,
            slm_lost=lambda detail: self.bench.note_slm_lost(detail)))
        self.navigation = NavigatorInput(self)
        # Who may arm and the bench's confirmation (a ConfigError here names the missing input).
        self.arming = ArmingGate(c, config.devices.navigator)
        self.recorder: SessionRecorder | None = None  # daemon.record / serve --record
        self.scene: dict[str, Any] | None = None
        self.errors: deque[dict[str, Any]] = deque(maxlen=20)
        self.bench_jobs: JobRunner = None  # type: ignore[assignment]  # set in start()
        self.load_jobs: JobRunner = None  # type: ignore[assignment]
        self.server: LineServer | None = None
        self.tcp_token: str | None = None
        self._token_written: Path | None = None  # the tcp.token this daemon made (removed at stop)
        self.state = "starting"
        self.started_s = time.time()
        self._lock_file: Any = None
        self._shutdown = threading.Event()
        self._shutdown_reason = ""
        self._snapshots = 0
        self._closed = False
        self._next_beat_s = 0.0  # monotonic time the next heartbeat is due (0: at once)
        self._watched_conn: Any = None  # the frame worker's pipe in the loop's selector
        self._watched_fd: int | None = None
        self._signal_wake: tuple[socket.socket, socket.socket] | None = None

    @property
    def panel(self) -> Panel:
        """What the SLM shows (the bench's: a bench opened at start brings its own)."""
        return self.bench.panel

    # -- start ---------------------------------------------------------------------------------

    def start(self) -> None:
        """Everything up to READY=1; on any failure, what was started is undone (lasers off)."""
        try:
            self._start()
        except BaseException:
            self.close()
            raise

    def _start(self) -> None:
        c = self.config.daemon
        problems = cross_field_problems(self.config)  # a copied config skips validation
        if problems:
            raise ConfigError("; ".join(problems))
        active_calibration(self.config)  # a configured but unreadable file stops the start here
        self._raise_open_files()  # before anything opens sockets or devices
        # Another user could have made /tmp/nhfd-<uid> first, with a fake guardian in it.
        make_private_dir(self.runtime_dir, group_writable_ok=bool(c.socket_group), mode=0o750)
        self._take_lock()
        self.audit = self._audit_log(self._audit_path())
        self.laser.audit = self.audit
        self.audit.write({"who": "daemon", "pid": os.getpid()}, "start",
                         version=__version__, runtime_dir=str(self.runtime_dir))
        if c.record:
            self.recorder = SessionRecorder(self.base_dir / Path(c.record).expanduser())
        self.notifier.status("starting: laser guardian")
        self.laser.start()  # every channel off and read back, or this raises
        self.bench = Bench(self.config, laser_twin=self.laser.twin)
        self.notifier.status("starting: devices")
        self.bench.open()
        apply_camera_roi(self.bench, self.config)
        self.navigation.open()
        kept = c.jobs_kept
        self.bench_jobs = JobRunner("bench", kept=kept, on_finish=self._job_finished)
        self.load_jobs = JobRunner("load", kept=kept, on_finish=self._job_finished)
        # The configured scene and model load as a client's load_scene and load_model would.
        for method, path in (("load_scene", c.scene), ("load_model", c.model)):
            if path:
                METHODS[method].func(self, Connection(None, "config", {}),  # type: ignore[arg-type]
                                     Params({"path": path}))
        if c.tcp_port:
            self.tcp_token = self._token()
        tls = (server_tls_context(self.base_dir / Path(c.tls_cert).expanduser(),
                                  self.base_dir / Path(c.tls_key).expanduser())
               if c.tcp_port and c.tls_cert else None)
        self.server = LineServer(self.handle_line, unix_path=self.socket_path,
                                 socket_group=c.socket_group, tcp_port=c.tcp_port,
                                 tcp_host=c.tcp_host, tls=tls,
                                 max_line_bytes=c.max_line_bytes, max_clients=c.max_clients,
                                 max_tcp_clients=c.max_tcp_clients,
                                 max_unauthenticated=c.max_unauthenticated,
                                 auth_timeout_s=c.auth_timeout_s,
                                 max_buffered_bytes=c.max_buffered_bytes,
                                 lines_per_poll=c.lines_per_poll, tick_budget_s=c.tick_budget_s)
        self.server.listen()
        if self.handle_signals:
            signal.signal(signal.SIGTERM, self._on_signal)
            signal.signal(signal.SIGINT, self._on_signal)
            self._wake_on_signals()
        self.state = "ready"
        devices = ", ".join(k for k, v in self.bench.status().items() if v["open"])
        log.info("ready: lasers off (read back); devices: %s; socket %s", devices or "none",
                 self.socket_path)
        self.notifier.ready(f"ready: lasers off; devices: {devices or 'none'}")

    def _raise_open_files(self) -> None:
        """The soft limit on open files up to daemon.open_files (the hard limit caps it):
        a distribution's default soft limit of 1024 is what 1,100 idle connections once hit."""
        wanted = self.config.daemon.open_files
        soft, hard = raise_open_files(wanted)
        shown = "unlimited" if hard == resource.RLIM_INFINITY else str(hard)
        if soft != resource.RLIM_INFINITY and soft < wanted:
            log.warning("open files: soft limit %d, below daemon.open_files = %d (the hard limit "
                        "is %s; raise it, e.g. LimitNOFILE= in the unit)", soft, wanted, shown)
        else:
            log.info("open files: soft limit %s (daemon.open_files = %d, hard limit %s)",
                     "unlimited" if soft == resource.RLIM_INFINITY else soft, wanted, shown)

    def _take_lock(self) -> None:
        path = self.runtime_dir / LOCK_NAME
        f = path.open("a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            other = f.read().strip() or "?"
            f.close()
            raise AlreadyRunning(f"another nhfd serve (pid {other}) holds {path}") from None
        f.seek(0)
        f.truncate()
        f.write(f"{os.getpid()}\n")
        f.flush()
        self._lock_file = f

    def _audit_log(self, path: Path | None) -> AuditLog:
        c = self.config.daemon
        return AuditLog(path, summary_s=c.audit_summary_s, max_bytes=c.audit_max_bytes,
                        backups=c.audit_backups)

    def _audit_path(self) -> Path:
        c = self.config.daemon
        if c.audit_log:
            return self.base_dir / Path(c.audit_log).expanduser()
        logs = self.env.get("LOGS_DIRECTORY")
        return (Path(logs.split(":")[0]) if logs else self.runtime_dir) / "audit.jsonl"

    def _token(self) -> str:
        c = self.config.daemon
        path = (self.base_dir / c.tcp_token_file) if c.tcp_token_file else (
            self.runtime_dir / TOKEN_NAME)
        if c.tcp_token_file:
            return path.read_text().strip()
        token = secrets.token_urlsafe(32)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(token + "\n")
        self._token_written = path
        return token

    def _wake_on_signals(self) -> None:
        """A signal wakes the loop's select at once: Python retries a select interrupted by a
        signal (PEP 475), so without this SIGTERM would wait for the next heartbeat."""
        assert self.server is not None
        self._signal_wake = socket.socketpair()
        for sock in self._signal_wake:
            sock.setblocking(False)
        signal.set_wakeup_fd(self._signal_wake[1].fileno(), warn_on_full_buffer=False)
        self.server.watch(self._signal_wake[0].fileno(), SIGNAL_WAKE)

    def _drain_signal_wake(self) -> None:
        if self._signal_wake is not None:
            with contextlib.suppress(OSError):
                self._signal_wake[0].recv(4096)

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.request_shutdown(f"signal {signal.Signals(signum).name}")

    # -- loop ----------------------------------------------------------------------------------

    def run(self) -> int:
        """The control loop until shutdown; then close(). Returns the exit code."""
        assert self.server is not None, "start() first"
        try:
            while not self._shutdown.is_set():
                self.step(self.wait_s(time.monotonic()))
        except BaseException:
            log.exception("control loop failed; shutting down with lasers off")
            self.close()
            return 1
        return 0 if self.close() else 1

    def wait_s(self, now: float) -> float:
        """How long the loop may sleep in select: until the next heartbeat, or the navigator's
        next read if sooner. Everything else wakes it: requests (the server's sockets) and
        frames, loads and crashes (the worker's pipe is in the same selector). What other
        threads queue for the loop (a lost SLM output, a reloaded model's resend) waits at most
        until the next heartbeat, `daemon.tick_s`, as it did when the loop woke every tick."""
        due = self._next_beat_s
        if self.navigation.navigator is not None:
            due = min(due, self.navigation.next_read_s)
        due = min(due, self.frames.wake_s)  # a frame waiting for its refresh (slm.refresh_hz)
        return max(0.0, due - now)

    def step(self, timeout_s: float) -> None:
        assert self.server is not None
        if SIGNAL_WAKE in self.server.poll(timeout_s):
            self._drain_signal_wake()
        self._device_faults()
        now = time.monotonic()
        self.navigation.step(now)  # navigator motion -> the same latest-wins view slot
        crashes = self.frames.crashes
        self.frames.step()  # never blocks: collects finished frames, sends the newest view
        if self.frames.crashes != crashes:  # it switched the lasers off: read that back now
            self._next_beat_s = 0.0
        self._watch_worker()
        if now >= self._next_beat_s:
            # Once per tick however many requests woke the loop: a storm of set_view must not
            # turn into a storm of guardian round trips.
            self._next_beat_s = now + self.config.daemon.tick_s
            self.laser.heartbeat(now)
            self.notifier.watchdog(now)
            self.audit.tick()

    def _watch_worker(self) -> None:
        """Keep the frame worker's pipe in the loop's selector while `frames.step` drains it
        (the worker starting or running), so a finished frame, a load's reply or the worker's
        death wakes the loop at once. Out of it otherwise: a readable pipe nobody drains (a
        crashed worker's end of file) would wake the loop without end."""
        assert self.server is not None
        frames = self.frames
        conn = frames.worker.conn if frames.state in ("starting", "running") else None
        if conn is self._watched_conn:
            return
        if self._watched_fd is not None:
            self.server.unwatch(self._watched_fd)
        self._watched_conn, self._watched_fd = conn, None
        if conn is not None:
            try:
                self._watched_fd = conn.fileno()
            except OSError:  # closed already: the next frames.step sees the crash
                return
            self.server.watch(self._watched_fd, ("frame worker",))

    def _device_faults(self) -> None:
        """Act on what the bench monitor noticed. SLM output lost: the panel no longer shows
        what the daemon computed, so every laser goes off (the guardian reads it back); back:
        the blank pattern, then the current view again. Lasers and arming are never restored
        automatically: a person turns them on again."""
        while True:
            try:
                device, lost, detail = self.bench.faults.get_nowait()
            except queue.Empty:
                return
            self._next_beat_s = 0.0  # the guardian's state as it is now, for the next status
            if lost:
                message = f"output lost ({detail})"
                try:
                    if self.laser.present:
                        self.laser.off()
                        message += "; lasers switched off"
                except Exception as exc:
                    message += f"; lasers off FAILED: {exc}"
                log.error("%s: %s", device, message)
                self.panel.output_lost()
                self._error(device, message)
                self.audit.write({"who": "daemon"}, "slm output lost", detail=message)
            else:
                try:
                    self.panel.blank()
                except Exception as exc:
                    self._error(device, f"output back, but blank failed: {exc}")
                    continue
                self.frames.resend()  # the current view again (a frame cache hit)
                log.warning("%s: output back (%s); blank, then the current view; lasers stay "
                            "off until turned on", device, detail)
                self.audit.write({"who": "daemon"}, "slm output back", detail=detail)

    def request_shutdown(self, reason: str) -> None:
        if not self._shutdown.is_set():
            self._shutdown_reason = reason
            log.info("shutting down: %s", reason)
            self._shutdown.set()

    @property
    def stopping(self) -> bool:
        return self._shutdown.is_set()

    def close(self) -> bool:
        """Lasers off (read back) first, then everything else. True when lasers were confirmed
        off (or there are none)."""
        if self._closed:
            return True
        self._closed = True
        self.state = "stopping"
        self.notifier.stopping()
        if self.server is not None:
            self.server.flush_all()  # the shutdown caller hears its reply
        self.arming.close()  # an arm still waiting for its confirmation never lands after this
        how = self.laser.close()
        confirmed = how != "not confirmed"
        with contextlib.suppress(Exception):
            self.frames.close()
        if self.server is not None:
            self._watch_worker()  # stopped: out of the selector
        self.navigation.close()
        for runner in (self.bench_jobs, self.load_jobs):
            if runner is not None:
                runner.cancel_all()
        with contextlib.suppress(Exception):
            self.bench.stop_stage()
        for runner in (self.bench_jobs, self.load_jobs):
            if runner is not None:
                runner.close()
        self.bench.close()
        if self.server is not None:
            self.server.close()  # removes the socket
        if self._token_written is not None:  # a token outlives nothing it guarded
            with contextlib.suppress(OSError):
                self._token_written.unlink()
            self._token_written = None
        if self._signal_wake is not None:
            with contextlib.suppress(ValueError):  # only the main thread may reset it
                signal.set_wakeup_fd(-1)
            if self.server is not None:
                self.server.unwatch(self._signal_wake[0].fileno())
            for sock in self._signal_wake:
                sock.close()
            self._signal_wake = None
        self.audit.write({"who": "daemon", "pid": os.getpid()}, "stop",
                         reason=self._shutdown_reason or "start failed or loop error",
                         lasers=how)
        self.audit.close()
        if self.recorder is not None:
            self.recorder.close()
        (log.info if confirmed else log.error)("stopped; lasers: %s", how)
        self.notifier.close()
        if self._lock_file is not None:
            self._lock_file.close()  # releases the flock
            self._lock_file = None
        return confirmed

    # -- requests ------------------------------------------------------------------------------

    def handle_line(self, conn: Connection, line: bytes) -> bytes | None:
        try:
            msg = protocol.loads(line)
        except RpcError as exc:
            return protocol.dumps(protocol.error_reply(None, exc))
        if isinstance(msg, list):
            return self._batch(conn, msg)
        reply = self.handle_message(conn, msg)
        return protocol.dumps(reply) if reply is not None else None

    def _batch(self, conn: Connection, batch: list[Any]) -> bytes | None:
        cap = self.config.daemon.max_batch
        if cap == 0:
            err = RpcError(INVALID_REQUEST, "batches are not supported (daemon.max_batch = 0); "
                           "send one request per line")
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
        method = METHODS.get(req.method)
        if method is None:
            raise RpcError(METHOD_NOT_FOUND, f"no method {req.method[:80]!r}",
                           {"field": "method", "allowed": sorted(METHODS)})
        if self.stopping and not method.while_stopping:
            raise RpcError(SHUTTING_DOWN, "the daemon is shutting down")
        try:
            result = method.func(self, conn, Params(req.params))
        except RpcError as exc:
            if method.audited:  # compact and summarised: any client can send refusals
                self.audit.refused(conn.who, req.method, exc.code, exc.name, exc.message,
                                   req.params)
            raise
        except Exception as exc:
            log.exception("%s failed", req.method)
            self._error("daemon", f"{req.method}: {type(exc).__name__}: {exc}")
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
            self._next_beat_s = 0.0
        if self.recorder is not None and (method.audited or req.method == "set_view"):
            self.record(req.method, req.params, conn.who, result)
        return result

    def record(self, method: str, params: dict[str, Any], who: dict[str, Any],
               result: Any = None) -> None:
        """One bench-changing request into the session recording; a view as the absolute view
        it produced, so that replay does not depend on where a relative move started."""
        if self.recorder is None:
            return
        if method == "set_view" and isinstance(result, dict) and "view" in result:
            params = view_params(result["view"])
        self.recorder.record(method, params, who)

    # -- helpers for methods -------------------------------------------------------------------

    def focus_stage_mm(self, z_mm: float) -> float:
        cal = active_calibration(self.config)
        if cal is not None:  # the fitted depth -> stage mapping, green's focus
            return cal.stage_mm_for(self.config.optics.z0_m + z_mm * 1e-3, 1)
        return focus_stage_mm(z_mm, self.config.daemon.stage_at_reference_mm)

    def submit_bench_job(self, job: Job) -> Job:
        try:
            return self.bench_jobs.submit(job)
        except queue.Full:
            raise RpcError(BUSY, "the bench job queue is full; wait or stop") from None

    def next_snapshot(self) -> int:
        self._snapshots += 1
        return self._snapshots

    def _job_finished(self, job: Job, state: str, error: str | None) -> None:
        """Called before the job's end state is published (`JobRunner`)."""
        if state == "failed":
            self._error(f"job {job.id} ({job.kind})", error or "failed")
        self.audit.write({"who": "daemon"}, f"job {job.kind} {state}", job=job.id, error=error)

    def _error(self, source: str, message: str) -> None:
        self.errors.append({"time_s": time.time(), "source": source, "message": message})

    def _frame_worker_crashed(self, message: str) -> None:
        """The frame worker died (`FrameEvents.crashed`): the panel may hold a half-updated or
        stale frame the daemon no longer controls, so the lasers go off first, then the panel
        shows the blank pattern; status says what happened."""
        try:
            self.laser.off()
            message += "; lasers switched off"
        except Exception as exc:
            message += f"; lasers off FAILED: {exc}"
        with contextlib.suppress(Exception):
            self.panel.blank()
        self._error("frame worker", message)

    def _calibration_status(self) -> dict[str, Any]:
        c = self.config.daemon
        try:
            cal = active_calibration(self.config)
        except ValueError as exc:  # unreadable, with no accepted version to keep
            return {"loaded": False, "error": str(exc), "focus_range_mm": list(c.focus_range_mm)}
        refused = new_refusal(self.config)  # a refused hot swap: the accepted version is kept
        if refused:
            self._error("calibration", refused)
        if cal is None:
            return {"loaded": False,
                    "focus_mapping": "stage_mm = stage_at_reference_mm + z_mm",
                    "stage_at_reference_mm": c.stage_at_reference_mm,
                    "focus_range_mm": list(c.focus_range_mm)}
        return {"loaded": True, "file": cal.source, "created": cal.created,
                "fitted_on": cal.fitted_on.get("capture", ""),
                "focus_mapping": "stage_mm = stage_at_slm_mm + (z0 + z_mm - z_offset_G) / "
                                 "stage_scale",
                "stage_at_slm_mm": cal.stage_at_slm_mm, "stage_scale": cal.stage_scale,
                "phase_sign": cal.phase_sign, "focus_range_mm": list(c.focus_range_mm),
                "refused": calibration_refusal(self.config)}

    def status(self) -> dict[str, Any]:
        c = self.config.daemon
        jobs = [*(self.bench_jobs.jobs() if self.bench_jobs else []),
                *(self.load_jobs.jobs() if self.load_jobs else [])]
        devices = self.bench.status()
        device_errors = [{"source": k, "message": v["error"]} for k, v in devices.items()
                         if v.get("error")]
        laser = self.laser.status()
        if laser.get("error"):
            device_errors.append({"source": "laser", "message": laser["error"]})
        return {
            "daemon": {"version": __version__, "pid": os.getpid(), "state": self.state,
                       "uptime_s": round(time.time() - self.started_s, 3),
                       "socket": str(self.socket_path),
                       "tcp": (f"{self.server.tcp_address[0]}:{self.server.tcp_address[1]}"
                               if self.server and self.server.tcp_address else None),
                       "clients": len(self.server.connections) if self.server else 0},
            "laser": laser,
            "devices": devices,
            "display": self.panel.current,
            "panel": {"width_px": self.config.slm.width_px,
                      "height_px": self.config.slm.height_px,
                      "pitch_m": self.config.slm.pitch_m,
                      "wavelengths_m": list(self.config.optics.wavelengths_m)},
            "colour": {"mode": c.colour_mode, "single_colour": c.single_colour},
            "scene": self.scene,
            "model": self.frames.model_info or "none loaded",
            "calibration": self._calibration_status(),
            "view": self.views.snapshot(),
            "navigator": self.navigation.status(),
            "timings": self.frames.timings,  # the last frame's per-stage timings (ms)
            "frames": self.frames.status(),
            "warnings": [f"view outside the model's pose envelope: {w}"
                         for w in self.frames.warnings],
            "errors": [*device_errors, *self.errors],
            "jobs": [j.to_json() for j in sorted(jobs, key=lambda j: j.id)],
        }
