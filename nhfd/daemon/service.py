"""The daemon core: start-up in a safe order, the control loop, and shutdown with lasers off.

Start-up: runtime directory -> single-instance lock (fcntl on `nhfd.lock`) -> audit log ->
laser guardian (connect or start) -> every laser off *and read back* -> SLM (showing the
zero-amplitude pattern), stage (identified, never moved), camera -> sockets -> READY=1.

The loop (main thread): serve requests, heartbeat to the guardian, feed systemd's watchdog,
write audit summaries. It sleeps in `select` until the next thing due (`wait_s`): the heartbeat
every `daemon.arming.heartbeat_s`, or the navigator's next read; a request or the frame worker's
pipe wakes it at once. So an idle daemon wakes only for its heartbeats, and a stuck loop stops both
the heartbeat (the guardian switches the lasers off) and the watchdog (systemd restarts the unit;
its stop hook runs `nhfd laser-off`).

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
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from nhfd import __version__
from nhfd.calibration import CalibrationStore, fingerprint, other_bench
from nhfd.config import Config, ConfigError, ServerSettings, cross_field_problems
from nhfd.frame_message import CaptureReply, CaptureRequest

from .arming import ArmingGate
from .audit import AuditLog, audit_path
from .bench import Bench
from .citl import CitlStopped, citl_capture, citl_ended
from .dispatch import Dispatcher
from .errors import ErrorList
from .frame_link import FrameEvents, FrameLink
from .guardian_link import EmissionEnded, LaserLink
from .jobs import Cancelled, Job, JobRunner
from .methods import METHODS, RpcContext, no_model_hint
from .navigation import NavigatorInput
from .notify import Notifier
from .paths import LOCK_NAME, SOCKET_NAME, TOKEN_NAME, make_private_dir, resolve_dirs, runtime_dir
from .protocol import Params
from .recording import SessionRecorder
from .server import Connection, LineServer, raise_open_files, server_tls_context
from .views import ViewSlot

log = logging.getLogger("nhfd.daemon")

SIGNAL_WAKE = ("signal",)  # the selector's tag of the signal wake-up socket
# What a run that could emit is told once a shutdown is asked (its refusal, and status).
SHUTDOWN_EMISSION_END = "lasers off: the daemon is shutting down"


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


def _raise_open_files(wanted: int) -> None:
    """The soft limit on open files up to `wanted` (daemon.paths.open_files; the hard limit caps
    it): a distribution's default soft limit of 1024 is what 1,100 idle connections once hit."""
    soft, hard = raise_open_files(wanted)
    shown = "unlimited" if hard == resource.RLIM_INFINITY else str(hard)
    if soft != resource.RLIM_INFINITY and soft < wanted:
        log.warning("open files: soft limit %d, below daemon.paths.open_files = %d (the hard limit "
                    "is %s; raise it, e.g. LimitNOFILE= in the unit)", soft, wanted, shown)
    else:
        log.info("open files: soft limit %s (daemon.paths.open_files = %d, hard limit %s)",
                 "unlimited" if soft == resource.RLIM_INFINITY else soft, wanted, shown)


def _take_lock(path: Path) -> IO[str]:
    """The single-instance lock (fcntl on `path`, which then holds this pid): the open file,
    kept open while the daemon runs. AlreadyRunning, naming the holder, when it is taken."""
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
    return f


def tcp_token(settings: ServerSettings, base_dir: Path, runtime_dir: Path
              ) -> tuple[str, Path | None]:
    """The TCP clients' token: read from `daemon.server.tcp_token_file` (relative to `base_dir`), or
    made and written, mode 0600, to `tcp.token` in the runtime directory. Returns the token and
    the file made for it (the daemon removes it at stop), None when it was read."""
    if settings.tcp_token_file:
        return (base_dir / settings.tcp_token_file).read_text().strip(), None
    path = runtime_dir / TOKEN_NAME
    token = secrets.token_urlsafe(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    return token, path


def calibration_status(config: Config, calibration: CalibrationStore,
                       note_error: Callable[[str, str], None]) -> dict[str, Any]:
    """`status.calibration`: the focus mapping in use (`config.daemon.bench`'s without a
    calibration) and the calibration it comes from; a refused hot swap (the accepted version
    kept) is also noted once with `note_error`."""
    c = config.daemon.bench
    try:
        cal = calibration.active()
    except ValueError as exc:  # unreadable, with no accepted version to keep
        return {"loaded": False, "error": str(exc), "focus_range_mm": list(c.focus_range_mm)}
    refused = calibration.new_refusal()  # a refused hot swap: the accepted version is kept
    if refused:
        note_error("calibration", refused)
    if cal is None:
        return {"loaded": False,
                "focus_mapping": "stage_mm = stage_at_reference_mm + z_mm",
                "stage_at_reference_mm": c.stage_at_reference_mm,
                "focus_range_mm": list(c.focus_range_mm)}
    return {"loaded": True, "file": cal.source, "created": cal.created,
            "sha256": fingerprint(cal),
            "fitted_on": cal.fitted_on.get("capture", ""),
            "focus_mapping": "stage_mm = stage_at_slm_mm + (z0 + z_mm - z_offset_G) / "
                             "stage_scale",
            "stage_at_slm_mm": cal.stage_at_slm_mm, "stage_scale": cal.stage_scale,
            "phase_sign": cal.phase_sign, "focus_range_mm": list(c.focus_range_mm),
            "refused": calibration.refusal()}


class SignalWake:
    """SIGTERM and SIGINT ask for shutdown (`on_signal(reason)`) and wake the loop's select at
    once: Python retries a select interrupted by a signal (PEP 475), so without the wake-up
    socket SIGTERM would wait for the next heartbeat."""

    def __init__(self, on_signal: Callable[[str], None]) -> None:
        self.on_signal = on_signal
        self._pair: tuple[socket.socket, socket.socket] | None = None

    def install(self, server: LineServer) -> None:
        """The handlers, and the wake-up socket in `server`'s selector (the main thread)."""
        signal.signal(signal.SIGTERM, self._handle)
        signal.signal(signal.SIGINT, self._handle)
        self._pair = socket.socketpair()
        for sock in self._pair:
            sock.setblocking(False)
        signal.set_wakeup_fd(self._pair[1].fileno(), warn_on_full_buffer=False)
        server.watch(self._pair[0].fileno(), SIGNAL_WAKE)

    def _handle(self, signum: int, frame: Any) -> None:
        self.on_signal(f"signal {signal.Signals(signum).name}")

    def drain(self) -> None:
        """Empty the wake-up socket (the loop woke for it)."""
        if self._pair is not None:
            with contextlib.suppress(OSError):
                self._pair[0].recv(4096)

    def close(self, server: LineServer | None) -> None:
        """Give the wake-up fd back and close the socket pair (out of `server`'s selector)."""
        if self._pair is None:
            return
        with contextlib.suppress(ValueError):  # only the main thread may reset it
            signal.set_wakeup_fd(-1)
        if server is not None:
            server.unwatch(self._pair[0].fileno())
        for sock in self._pair:
            sock.close()
        self._pair = None


class Daemon:
    """`nhfd serve`: start-up in a safe order, the control loop, shutdown with lasers off
    (the module's docstring). It owns the parts and wires them; each part gets at construction
    what it uses (its settings, the few parts it calls, callbacks for what it reports), never
    the daemon."""

    def __init__(self, config: Config, *, base_dir: Path | None = None,
                 env: dict[str, str] | None = None, handle_signals: bool = True,
                 calibration: CalibrationStore | None = None) -> None:
        """`config`: the validated configuration (`start` checks its cross-field rules
        again: a copied config skips validation). `base_dir`: relative paths in it are taken
        from here (default: the working directory). `env`: the environment (runtime
        directory, systemd's sockets and directories; default: this process's).
        `handle_signals`: SIGTERM and SIGINT shut down (the main thread only). `calibration`:
        the store of `config`'s calibration file (default: a new one; `nhfd serve` hands over
        the one it checked), the one every part that applies the calibration is given."""
        self.config = config
        self.calibration = calibration or CalibrationStore.of(config)
        self.env = dict(os.environ if env is None else env)
        self.base_dir = (base_dir or Path.cwd()).resolve()
        c = config.daemon
        self.runtime_dir = runtime_dir(c.server.runtime_dir, self.env)
        self.socket_path = self.runtime_dir / SOCKET_NAME
        self.notifier = Notifier(self.env)
        self._shutdown = threading.Event()
        self.signals = SignalWake(self.request_shutdown) if handle_signals else None
        # The audit log and the session recording write nothing until start opens them (in
        # place: the parts below hold them from here).
        self.errors = ErrorList()  # status "errors": what the parts report
        self.audit = AuditLog.for_settings(c.audit)
        self.recorder = SessionRecorder()  # daemon.audit.record / serve --record
        self.laser = LaserLink(config.devices.readybeam, config.devices.laser,
                               c.arming.guardian, self.audit,
                               refresh_s=c.arming.laser_refresh_s, runtime_dir=self.runtime_dir,
                               socket_group=c.server.socket_group,
                               on_session_end=self._emission_ended)
        # opened at start, with the guardian's simulated laser
        self.bench = Bench(config, self.calibration)
        self.panel = self.bench.panel  # what the SLM shows
        # Each view remembers the emission session it was asked in (a citl run belongs to it).
        self.views = ViewSlot(session=lambda: self.laser.session)
        # The spawned render/inference worker, started on demand; its events come back here.
        panel = self.panel
        self.frames = FrameLink(config, self.calibration, self.views, lambda: panel, FrameEvents(
            shown=self.views.mark_applied, error=self.errors.note,
            crashed=self._frame_worker_crashed, slm_lost=self.bench.note_slm_lost,
            capture=self._citl_capture))
        kept = c.paths.jobs_kept
        self.bench_jobs = JobRunner("bench", kept=kept, on_finish=self._job_finished)
        self.load_jobs = JobRunner("load", kept=kept, on_finish=self._job_finished)
        self.navigation = NavigatorInput(config.devices, c.bench.navigator_period_s, self.views,
                                         self.audit, self.recorder)
        # Who may arm and the bench's confirmation (a ConfigError here names the missing input).
        self.arming = ArmingGate(c.arming, config.devices.navigator, laser=self.laser,
                                 audit=self.audit, bench_jobs=self.bench_jobs,
                                 navigation=self.navigation)
        self.rpc = RpcContext(
            config=config, calibration=self.calibration, base_dir=self.base_dir,
            scene_dirs=resolve_dirs(c.paths.scene_dirs, self.base_dir),
            model_dirs=resolve_dirs(c.paths.model_dirs, self.base_dir),
            snapshot_dirs=resolve_dirs([c.paths.snapshot_dir], self.base_dir),
            pattern_dirs=resolve_dirs(c.paths.pattern_dirs, self.base_dir),
            audit=self.audit, laser=self.laser, arming=self.arming, bench=self.bench,
            panel=self.panel, views=self.views, frames=self.frames, bench_jobs=self.bench_jobs,
            load_jobs=self.load_jobs, status=self.status,
            request_shutdown=self.request_shutdown)
        self.dispatcher = Dispatcher(self.rpc, self.audit, self.recorder,
                                     max_batch=c.server.max_batch,
                                     stopping=self._shutdown.is_set,
                                     on_error=self.errors.note, on_change=self.beat_soon)
        self.server: LineServer | None = None
        self.state = "starting"
        self.started_s = time.time()
        self._lock_file: IO[str] | None = None
        self._token_written: Path | None = None  # the tcp.token this daemon made (removed at stop)
        self._shutdown_reason = ""
        self._closed = False
        self._next_beat_s = 0.0  # monotonic time the next heartbeat is due (0: at once)
        # The frame worker's pipe in the loop's selector, and its fd (None: not watched).
        self._watched: tuple[Any, int | None] = (None, None)

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
        server = c.server
        problems = cross_field_problems(self.config)  # a copied config skips validation
        if problems:
            raise ConfigError("; ".join(problems))
        self.calibration.active()  # a configured but unreadable file stops the start here
        _raise_open_files(c.paths.open_files)  # before anything opens sockets or devices
        # Another user could have made /tmp/nhfd-<uid> first, with a fake guardian in it.
        make_private_dir(self.runtime_dir, group_writable_ok=bool(server.socket_group),
                         mode=0o750)
        self._lock_file = _take_lock(self.runtime_dir / LOCK_NAME)
        self.audit.open(audit_path(c.audit, self.base_dir, self.env, self.runtime_dir))
        self.audit.write({"who": "daemon", "pid": os.getpid()}, "start",
                         version=__version__, runtime_dir=str(self.runtime_dir))
        if c.audit.record:
            self.recorder.open(self.base_dir / Path(c.audit.record).expanduser())
        self.notifier.status("starting: laser guardian")
        self.laser.start()  # every channel off and read back, or this raises
        self.notifier.status("starting: devices")
        self.bench.open(laser_twin=self.laser.twin)
        self.navigation.open()
        # The configured scene and model load as a client's load_scene and load_model would.
        for method, path in (("load_scene", c.paths.scene), ("load_model", c.frames.model)):
            if path:
                METHODS[method].func(self.rpc, Connection(None, "config", {}),  # type: ignore[arg-type]
                                     Params({"path": path}))
        if server.tcp_port:
            self.rpc.tcp_token, self._token_written = tcp_token(server, self.base_dir,
                                                                self.runtime_dir)
        tls = (server_tls_context(self.base_dir / Path(server.tls_cert).expanduser(),
                                  self.base_dir / Path(server.tls_key).expanduser())
               if server.tcp_port and server.tls_cert else None)
        self.server = LineServer(self.dispatcher.handle_line, unix_path=self.socket_path,
                                 settings=server, tls=tls)
        self.server.listen()
        if self.signals is not None:
            self.signals.install(self.server)
        self.state = "ready"
        devices = ", ".join(k for k, v in self.bench.status().items() if v["open"])
        log.info("ready: lasers off (read back); devices: %s; socket %s", devices or "none",
                 self.socket_path)
        self.notifier.ready(f"ready: lasers off; devices: {devices or 'none'}")

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
        until the next heartbeat, `daemon.arming.heartbeat_s`, as it did when the loop woke every
        tick."""
        due = self._next_beat_s
        if self.navigation.navigator is not None:
            due = min(due, self.navigation.next_read_s)
        due = min(due, self.frames.wake_s)  # a frame waiting for its refresh (slm.refresh_hz)
        return max(0.0, due - now)

    def step(self, timeout_s: float) -> None:
        """One turn of the loop: requests (waiting at most `timeout_s` for one), device faults,
        the navigator, the frame link, and the heartbeat, watchdog and audit summaries when a
        tick is due."""
        assert self.server is not None
        if SIGNAL_WAKE in self.server.poll(timeout_s) and self.signals is not None:
            self.signals.drain()
        self._device_faults()
        now = time.monotonic()
        self.navigation.step(now)  # navigator motion -> the same latest-wins view slot
        crashes = self.frames.crashes
        self.frames.step()  # never blocks: collects finished frames, sends the newest view
        if self.frames.crashes != crashes:  # it switched the lasers off: read that back now
            self.beat_soon()
        self._watch_worker()
        if now >= self._next_beat_s:
            # Once per tick however many requests woke the loop: a storm of set_view must not
            # turn into a storm of guardian round trips.
            self._next_beat_s = now + self.config.daemon.arming.heartbeat_s
            self.laser.heartbeat(now)
            self.notifier.watchdog(now)
            self.audit.tick()

    def _watch_worker(self) -> None:
        """Keep the frame worker's pipe in the loop's selector while `frames.step` drains it
        (the worker starting or running), so a finished frame, a load's reply or the worker's
        death wakes the loop at once. Out of it otherwise: a readable pipe nobody drains (a
        crashed worker's end of file) would wake the loop without end."""
        assert self.server is not None
        conn = self.frames.pipe
        watched, fd = self._watched
        if conn is watched:
            return
        if fd is not None:
            self.server.unwatch(fd)
        self._watched = (conn, None)
        if conn is not None:
            try:
                fd = conn.fileno()
            except OSError:  # closed already: the next frames.step sees the crash
                return
            self._watched = (conn, fd)
            self.server.watch(fd, ("frame worker",))

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
            self.beat_soon()  # the guardian's state as it is now, for the next status
            if lost:
                message = f"output lost ({detail})"
                try:
                    if self.laser.present:
                        self.laser.off(f"lasers off: the SLM output was lost ({detail})")
                        message += "; lasers switched off"
                except Exception as exc:
                    message += f"; lasers off FAILED: {exc}"
                log.error("%s: %s", device, message)
                self.panel.output_lost()
                self.errors.note(device, message)
                self.audit.write({"who": "daemon"}, "slm output lost", detail=message)
            else:
                try:
                    self.panel.blank()
                except Exception as exc:
                    self.errors.note(device, f"output back, but blank failed: {exc}")
                    continue
                self.frames.resend()  # the current view again (a frame cache hit)
                log.warning("%s: output back (%s); blank, then the current view; lasers stay "
                            "off until turned on", device, detail)
                self.audit.write({"who": "daemon"}, "slm output back", detail=detail)

    def beat_soon(self) -> None:
        """The next heartbeat goes out in this step (not a tick later): arming and the
        guardian's state reach `status` through its reply, after a command that changed the
        bench, a device fault or a crashed worker."""
        self._next_beat_s = 0.0

    def request_shutdown(self, reason: str) -> None:
        """Stop the loop (at its next step: lasers off first, then everything else)."""
        if not self._shutdown.is_set():
            self._shutdown_reason = reason
            # From here no diode switches on: a run that could emit (citl's captures, a
            # capture-mode snapshot) is refused at its next switch-on, not only once the loop's
            # next step ends its session (a loaded machine let citl light green twice between).
            self.laser.refuse_from_now(SHUTDOWN_EMISSION_END)
            log.info("shutting down: %s", reason)
            self._shutdown.set()

    @property
    def stopping(self) -> bool:
        """Whether shutdown was requested."""
        return self._shutdown.is_set()

    def close(self) -> bool:
        """Lasers off (read back) first, then everything else. True when lasers were confirmed
        off (or there are none)."""
        if self._closed:
            return True
        self._closed = True
        self.state = "stopping"
        # First: from here no run that could emit switches anything on (the lasers go off
        # below, and nothing resumes them).
        self.laser.end_session(SHUTDOWN_EMISSION_END)
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
            runner.cancel_all()
        with contextlib.suppress(Exception):
            self.bench.stop_stage()
        for runner in (self.bench_jobs, self.load_jobs):
            runner.close()
        self.bench.close()
        if self.server is not None:
            self.server.close()  # removes the socket
        if self._token_written is not None:  # a token outlives nothing it guarded
            with contextlib.suppress(OSError):
                self._token_written.unlink()
            self._token_written = None
        if self.signals is not None:
            self.signals.close(self.server)
        self.audit.write({"who": "daemon", "pid": os.getpid()}, "stop",
                         reason=self._shutdown_reason or "start failed or loop error",
                         lasers=how)
        self.audit.close()
        self.recorder.close()
        (log.info if confirmed else log.error)("stopped; lasers: %s", how)
        self.notifier.close()
        if self._lock_file is not None:
            self._lock_file.close()  # releases the flock
            self._lock_file = None
        return confirmed

    # -- what the parts report ------------------------------------------------------------

    def _job_finished(self, job: Job, state: str, error: str | None) -> None:
        """Called before the job's end state is published (`JobRunner`)."""
        if state == "failed":
            self.errors.note(f"job {job.id} ({job.kind})", error or "failed")
        self.audit.write({"who": "daemon"}, f"job {job.kind} {state}", job=job.id, error=error)

    def _citl_capture(self, req_id: int, request: CaptureRequest) -> None:
        """A citl step's captures (`FrameEvents.capture`): a bench job, one at a time with the
        other bench work, whose answer goes back to the worker. A stop on the bench (lasers
        disarmed, the view changed) is the answer, not a failed job; a full queue is refused."""
        frames = self.frames
        # The emission session of the view's request: a laser off, disarm, stop or shutdown
        # since then has ended this citl run, and a later arm does not resume it.
        session = self.views.session
        try:
            self.laser.check_session(session)
        except EmissionEnded as exc:
            frames.answer_capture(req_id, CaptureReply(error=citl_ended(str(exc))))
            return

        def run(job: Job) -> dict[str, Any]:
            try:
                reply = citl_capture(job, request, config=self.config, calibration=self.calibration,
                                     bench=self.bench,
                                     panel=self.panel, laser=self.laser, audit=self.audit,
                                     shown=frames, wanted=lambda: frames.capture_wanted(req_id),
                                     session=session,
                                     phase=lambda what: frames.capture_phase(req_id, what))
            except CitlStopped as exc:
                frames.answer_capture(req_id, CaptureReply(error=str(exc)))
                return {"stopped": str(exc)}
            except (EmissionEnded, Cancelled) as exc:
                # Ended with its session (a cancel by `stop` ends the session first).
                try:
                    self.laser.check_session(session)
                    why = str(exc)
                except EmissionEnded as ended:
                    why = citl_ended(str(ended))
                frames.answer_capture(req_id, CaptureReply(error=why))
                return {"stopped": why}
            except BaseException as exc:
                frames.answer_capture(req_id, CaptureReply(error=f"{type(exc).__name__}: {exc}"))
                raise
            frames.answer_capture(req_id, reply)
            return {"planes": len(request.z_m), "subframes": int(request.grey.shape[0])}

        job = Job("citl capture", {"planes": len(request.z_m),
                                   "subframes": int(request.grey.shape[0])}, run)
        try:
            self.bench_jobs.submit(job)
        except queue.Full:
            frames.answer_capture(req_id, CaptureReply(error="the bench's job queue is full"))

    def _frame_worker_crashed(self, message: str) -> None:
        """The frame worker died (`FrameEvents.crashed`): the panel may hold a half-updated or
        stale frame the daemon no longer controls, so the lasers go off first, then the panel
        shows the blank pattern; status says what happened."""
        try:
            self.laser.off("lasers off: the frame worker crashed")
            message += "; lasers switched off"
        except Exception as exc:
            message += f"; lasers off FAILED: {exc}"
        with contextlib.suppress(Exception):
            self.panel.blank()
        self.errors.note("frame worker", message)

    def _view_warnings(self) -> list[str]:
        """What `status` warns of the view requested (one that shows nothing) and of the model
        serving it (tuned for another bench than the calibration in use now)."""
        view = self.views.view
        hint = None if view is None else no_model_hint(view.quality, self.frames,
                                                       self.load_jobs)
        model = self.frames.model
        other = None
        if model is not None and model.tuned_for:
            try:
                other = other_bench(model.tuned_for, self.calibration.active())
            except ValueError:  # an unreadable calibration: its own error says so
                other = None
        if other:
            other = (model.bench_warning or f"{other}: the calibration changed since the model "
                     "was loaded; it keeps serving until another model is loaded")
        return [w for w in (hint, other) if w]

    def _emission_ended(self, reason: str) -> None:
        """An emission session ended (`LaserLink.end_session`; any thread): the citl run of the
        view on the panel ends with it, and `status` says why at once."""
        self.frames.emission_ended(citl_ended(reason))

    def status(self) -> dict[str, Any]:
        """The `status` reply: the daemon, lasers, devices, panel, scene, model, calibration,
        view, navigator, frames, errors and jobs."""
        c = self.config.daemon
        jobs = [*self.bench_jobs.jobs(), *self.load_jobs.jobs()]
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
                       "clients": len(self.server.connections) if self.server else 0,
                       # whether TCP and web-view peers may start emission
                       "remote_emission": c.arming.remote_emission},
            "laser": laser,
            "devices": devices,
            "display": self.panel.current,
            "panel": {"width_px": self.config.slm.width_px,
                      "height_px": self.config.slm.height_px,
                      "pitch_m": self.config.slm.pitch_m,
                      "wavelengths_m": list(self.config.optics.wavelengths_m),
                      "z0_m": self.config.optics.z0_m},
            "colour": {"mode": c.frames.colour_mode,
                       "single_colour": c.frames.single_colour},
            "scene": self.rpc.scene,
            "model": self.frames.model.to_json() if self.frames.model else "none loaded",
            "calibration": calibration_status(self.config, self.calibration, self.errors.note),
            "view": self.views.snapshot(),
            "navigator": self.navigation.status(),
            "timings": self.frames.timings,  # the last frame's per-stage timings (ms)
            "frames": self.frames.status(),
            "warnings": [f"view outside the model's pose envelope: {w}"
                         for w in self.frames.warnings] + self._view_warnings(),
            "errors": [*device_errors, *self.errors.entries()],
            "jobs": [j.to_json() for j in sorted(jobs, key=lambda j: j.id)],
        }
