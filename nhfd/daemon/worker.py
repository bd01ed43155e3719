"""The frame worker: one spawned process that renders, runs the network and codes frames.

Why a process: rendering (numba), inference (onnxruntime) and propagation (torch) hold the CPU
for tens of milliseconds at a time; in the daemon's own process they would delay the control
loop that feeds the laser guardian's heartbeat. Why spawned, not forked: a fork copies the
daemon's threads' locks and the already-initialised thread pools of torch/OpenMP in whatever state
they are in; a fresh interpreter sets its thread counts before any pool exists.

Protocol (tuples over one duplex `multiprocessing` pipe):

  daemon -> worker   ("model", req_id, path)   ("scene", req_id, path)
                     ("frame", seq, view)       ("stop",)
  worker -> daemon   ("ready", pid)
                     ("model" | "scene", req_id, ok, info | error message)
                     ("frame", seq, payload)    ("frame_error", seq, message)

The worker drains its pipe before each frame and computes only the newest view (latest wins);
loads are applied in order, and a failed load leaves the previous model or scene in use. The
daemon side (`FrameLink`) never blocks on the pipe: it polls it once per control-loop tick.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import multiprocessing as mp
import os
import threading
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from .colour import panel_for_mode

log = logging.getLogger("nhfd.daemon.worker")

# How long a load may take in the worker before the load job gives up waiting (s).
LOAD_TIMEOUT_S = 120.0
# A crashed worker is restarted at most this often (s), so a worker that dies at start-up does
# not spin.
RESTART_BACKOFF_S = 2.0


# -- the worker process ------------------------------------------------------------------------


def _set_threads(threads: int, layer: str) -> None:
    """Thread counts before any library starts its pools (the process is fresh: spawned)."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[var] = str(threads)
    os.environ["NUMBA_THREADING_LAYER"] = layer
    # OpenMP threads sleep when idle instead of spinning: each stage hands the cores to another
    # library (render and coding in numba, propagation in torch, inference in onnxruntime), and a
    # spinning pool takes them from the next stage. Set before torch or numba load libgomp.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch

    torch.set_num_threads(threads)
    torch.set_num_interop_threads(1)


def open_model(path: str, config: Any, threads: int) -> Any:
    """An `OnnxModel` checked against the configured optics, on the configured providers, with
    `threads` intra-op threads in pools that do not spin (`nhfd.models.export.session_options`)."""
    import onnxruntime as ort

    from nhfd.models.export import check_providers, load_model

    # Checked here too, so the error names the setting to change. No silent fallback: a bench
    # configured for CUDA that quietly ran on the CPU would be 10x slower with nothing but a
    # warning to say why; the load fails instead and the previous model keeps running.
    providers = check_providers(list(config.daemon.onnx_providers),
                                ort.get_available_providers(), "daemon.onnx_providers")
    # validates; raises ModelMismatch etc.
    return load_model(path, config, threads=threads, providers=tuple(providers))


class ModelUnfit(ValueError):
    """A model whose graph cannot take the daemon's frames, or whose test inference gives
    outputs of another shape or non-finite values; the message names the file and what differs."""


# The test inference's input: mid-grey sRGB everywhere and, for an rgbd model, the reference
# plane's depth (0): a frame the daemon could send, so a model that fails it fails real frames.
TEST_GREY = 0.5


def check_inference(model: Any, window_hw: tuple[int, int], path: str) -> None:
    """Run `model` once on a frame of `window_hw` (padded to its input multiple, as frames are)
    and refuse it, with `ModelUnfit`, unless it takes that input and returns finite amplitude
    and phase of [1, colours, H, W]. Before the swap: a model that passes the metadata check
    but cannot serve frames must not replace a working one."""
    h, w = window_hw
    c, m = model.channels, model.multiple
    ph, pw = h + (-h) % m, w + (-w) % m
    inp = model.session.get_inputs()[0]
    declared = list(inp.shape)
    want = f"[B, {c}, {ph}, {pw}] ({inp.name}, a {h} x {w} frame window padded to multiples " \
           f"of {m})"
    if len(declared) != 4:
        raise ModelUnfit(f"{path}: input shape: expected {want}, found {declared}")
    for what, expected, found in zip(("channels", "height", "width"), (c, ph, pw),
                                     declared[1:], strict=True):
        if isinstance(found, int) and found != expected:
            raise ModelUnfit(f"{path}: input {what}: expected {expected}, found {found} "
                             f"(input shape: expected {want}, found {declared})")
    x = np.full((1, c, ph, pw), TEST_GREY, np.float32)
    if c == 4:
        x[:, 3] = 0.0
    try:
        outputs = model.run_raw(x)
    except Exception as exc:  # onnxruntime's own types: the first line says what
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:300]
        raise ModelUnfit(f"{path}: a test inference on a {want} input failed: {first}") from None
    colours = len(model.metadata["wavelengths_m"])
    for name, out in zip(("amplitude", "phase"), outputs, strict=True):
        if list(out.shape) != [1, colours, ph, pw]:
            raise ModelUnfit(f"{path}: output {name} shape: expected [1, {colours}, {ph}, {pw}], "
                             f"found {list(out.shape)}")
        bad = int(out.size - np.count_nonzero(np.isfinite(out)))
        if bad:
            raise ModelUnfit(f"{path}: output {name}: expected finite values, found {bad} of "
                             f"{out.size} not finite (test inference on a mid-grey frame)")


def model_info(model: Any, path: str) -> dict[str, Any]:
    m = model.metadata
    return {"path": path, "profile": m.get("profile"), "train_size_hw": m.get("train_size_hw"),
            "fx": m.get("fx"), "amplitude_scale": m.get("amplitude_scale"),
            "z0_m": m.get("z0_m"), "volume_m": m.get("volume_m"), "mapping": m.get("mapping"),
            "pose_envelope": m.get("pose_envelope"), "parameters": m.get("parameters"),
            "train_steps": m.get("train_steps"), "scene_sha256": m.get("scene_sha256"),
            "providers": list(model.session.get_providers()), "loaded_s": time.time()}


class _WorkerState:
    def __init__(self, config: Any) -> None:
        self.config = config
        self.threads = int(config.daemon.worker_threads)
        self.model: Any = None
        self.model_id = 0
        self.scene: Any = None
        self.scene_frame: Any = None
        self.scene_id = 0
        self.pipelines: dict[float, Any] = {}  # refocus_m -> Pipeline (each its own kernels)
        self.cache: OrderedDict[str, dict[str, Any]] = OrderedDict()
        self.cache_size = int(config.daemon.frame_cache_frames)

    def load_model(self, path: str) -> dict[str, Any]:
        from nhfd.daemon.frames import frame_window_hw

        model = open_model(path, self.config, self.threads)
        check_inference(model, frame_window_hw(self.config, model.metadata), path)
        self.model, self.model_id = model, self.model_id + 1
        self.pipelines.clear()
        return model_info(model, path)

    def load_scene(self, path: str) -> dict[str, Any]:
        from nhfd.daemon.frames import scene_frame
        from nhfd.scene.io import read_scene

        load = read_scene(path)
        scene = load.gaussians
        self.scene, self.scene_frame = scene, scene_frame(scene, path)
        self.scene_id += 1
        self.pipelines.clear()
        return {"path": path, **load.counts(), "center": self.scene_frame.center,
                "up": self.scene_frame.up}

    def pipeline(self, refocus_m: float) -> Any:
        from nhfd.daemon.frames import Pipeline, frame_settings

        if refocus_m not in self.pipelines:
            if len(self.pipelines) >= 8:  # a refocus sweep must not grow kernels without bound
                self.pipelines.clear()
            settings = frame_settings(self.config, self.model.metadata, refocus_m=refocus_m)
            self.pipelines[refocus_m] = Pipeline(self.model, settings, self.scene,
                                                 self.scene_frame)
        return self.pipelines[refocus_m]

    def frame(self, view: dict[str, Any]) -> dict[str, Any]:
        from nhfd.daemon.frames import envelope_warnings

        if self.model is None:
            raise RuntimeError("no model loaded (load_model, or daemon.model)")
        if self.scene is None:
            raise RuntimeError("no scene loaded (load_scene, or daemon.scene)")
        refocus_m = float(view.get("refocus_mm", 0.0)) * 1e-3
        key = json.dumps([view, self.model_id, self.scene_id], sort_keys=True)
        if key in self.cache:
            self.cache.move_to_end(key)
            hit = dict(self.cache[key])
            hit["cached"] = True
            hit["timings_s"] = {k: 0.0 for k in hit["timings_s"]}
            return hit
        pipe = self.pipeline(refocus_m)
        frame = pipe.compute(view)
        r = frame.region
        rgb = frame.rgb
        payload = {
            "region": [r.top, r.left, r.height, r.width, r.window_top, r.window_left],
            "grey": frame.grey,
            "rgb": (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8) if rgb is not None else None,
            "timings_s": frame.timings_s,
            "clipped_fraction": frame.clipped_fraction,
            "warnings": envelope_warnings(view, self.scene_frame,
                                          self.model.metadata.get("pose_envelope")),
            "cached": False,
        }
        if self.cache_size:
            self.cache[key] = payload
            while len(self.cache) > self.cache_size:
                self.cache.popitem(last=False)
        return payload


def worker_main(conn: Any, config_data: dict[str, Any], calibration: Any = None) -> None:
    """Entry point of the spawned process. `calibration`: the daemon's accepted one (kept when
    the file on disk is refused, as in the daemon)."""
    from nhfd.config import Config

    config = Config.model_validate(config_data)
    if calibration is not None:
        from nhfd.calibration import keep

        keep(config, calibration)
    _set_threads(int(config.daemon.worker_threads), config.daemon.worker_threading_layer)
    import numba

    numba.set_num_threads(int(config.daemon.worker_threads))
    state = _WorkerState(config)
    conn.send(("ready", os.getpid()))
    while True:
        try:
            msgs = [conn.recv()]
            while conn.poll(0):
                msgs.append(conn.recv())
        except (EOFError, OSError):
            return  # the daemon is gone: nothing to show frames to
        latest: tuple | None = None
        for msg in msgs:
            if msg[0] == "stop":
                return
            if msg[0] == "frame":
                latest = msg  # latest wins: an older view that was overtaken is never computed
                continue
            kind, req_id, path = msg
            try:
                info = state.load_model(path) if kind == "model" else state.load_scene(path)
                conn.send((kind, req_id, True, info))
            except Exception as exc:  # reported to the daemon; the old model/scene stays
                conn.send((kind, req_id, False, f"{type(exc).__name__}: {exc}"))
        if latest is not None:
            _, seq, view = latest
            try:
                conn.send(("frame", seq, state.frame(view)))
            except Exception as exc:
                conn.send(("frame_error", seq, f"{type(exc).__name__}: {exc}"))


# -- the daemon side ---------------------------------------------------------------------------


class Pending:
    """A load sent to the worker; the control loop fills in its outcome."""

    def __init__(self) -> None:
        self.done = threading.Event()
        self.ok = False
        self.result: Any = None

    def wait(self, timeout_s: float) -> Any:
        if not self.done.wait(timeout_s):
            raise TimeoutError(f"the frame worker did not answer within {timeout_s:g} s")
        if not self.ok:
            raise ValueError(str(self.result))
        return self.result


class FrameWorker:
    """The worker process and its pipe, seen from the daemon. Non-blocking except `start`."""

    _ids = itertools.count(1)

    def __init__(self, config: Any) -> None:
        self.config = config
        self.process: Any = None
        self.conn: Any = None
        self.pid: int | None = None
        self.ready = False
        self._send_lock = threading.Lock()  # load jobs send from their own thread
        self.pending: dict[int, Pending] = {}

    def start(self) -> None:
        ctx = mp.get_context("spawn")
        here, there = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=worker_main,
                                   args=(there, self.config.model_dump(),
                                         _accepted_calibration(self.config)),
                                   name="nhfd-frame-worker", daemon=True)
        self.process.start()
        there.close()
        self.conn, self.ready, self.pid = here, False, self.process.pid

    @property
    def alive(self) -> bool:
        return self.process is not None and self.process.is_alive()

    def send(self, msg: tuple) -> None:
        with self._send_lock:
            self.conn.send(msg)

    def request(self, kind: str, path: str) -> Pending:
        req_id = next(self._ids)
        pending = self.pending[req_id] = Pending()
        self.send((kind, req_id, path))
        return pending

    def receive(self) -> list[tuple]:
        """Every message waiting on the pipe (never blocks); EOFError when the worker is gone."""
        out = []
        while self.conn.poll(0):
            out.append(self.conn.recv())
        return out

    def close(self, timeout_s: float = 2.0) -> None:
        if self.process is None:
            return
        with contextlib.suppress(Exception):
            self.send(("stop",))
        self.process.join(timeout_s)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(timeout_s)
        with contextlib.suppress(Exception):
            self.conn.close()
        for p in self.pending.values():
            p.ok, p.result = False, "the frame worker stopped"
            p.done.set()
        self.pending.clear()


class FrameLink:
    """The daemon's use of the worker: send the newest view when the worker is free, show the
    frames it returns, load models and scenes, and turn a worker crash into lasers off plus an
    error in `status` (then restart it with the same model and scene)."""

    def __init__(self, daemon: Any) -> None:
        self.d = daemon
        self.worker = FrameWorker(daemon.config)
        self.model_path: str | None = None
        self.model_info: dict[str, Any] | None = None
        self.scene_path: str | None = None
        self.inflight: tuple[int, float] | None = None  # (seq, sent at perf_counter)
        self.sent_seq = 0
        self.shown_seq = 0
        self.timings: dict[str, Any] | None = None
        self.warnings: list[str] = []
        self.last_rgb: np.ndarray | None = None
        self.last_frame: np.ndarray | None = None
        self.frames_shown = 0
        self.crashes = 0
        self.state = "idle"
        self._start_lock = threading.Lock()
        self._zero: Any = None  # a PanelBuffer of the blank frame `_zero_of`, built on use
        self._zero_of: np.ndarray | None = None
        self._restart_at = 0.0

    # -- lifecycle -----------------------------------------------------------------------------

    def start(self) -> None:
        self.worker.start()
        self.state = "starting"
        if self.scene_path:
            self._track(self.worker.request("scene", self.scene_path), "scene", self.scene_path)
        if self.model_path:
            self._track(self.worker.request("model", self.model_path), "model", self.model_path)

    def ensure_started(self) -> None:
        """The worker starts with the first load: a daemon with no model or scene (most tests,
        a bench used only for captures) never pays for a process that imports torch."""
        with self._start_lock:
            if self.state == "idle":
                self.start()

    def close(self) -> None:
        self.state = "stopped"
        self.worker.close()

    def _track(self, pending: Pending, kind: str, path: str) -> Pending:
        """Restarts reload in the background: their outcome only matters if it failed."""
        def watch() -> None:
            pending.done.wait(LOAD_TIMEOUT_S)
            if pending.done.is_set() and not pending.ok:
                self.d._error("frame worker", f"reloading {kind} {path}: {pending.result}")
        threading.Thread(target=watch, daemon=True, name="nhfd-reload-watch").start()
        return pending

    # -- loads (from load jobs' threads) --------------------------------------------------------

    def load_model(self, path: str) -> dict[str, Any]:
        """Blocks the calling job until the worker has the model, or raises with the worker's
        reason (a ModelMismatch names the field); on failure the old model keeps running."""
        self.ensure_started()
        info = self.worker.request("model", path).wait(LOAD_TIMEOUT_S)
        self.model_path, self.model_info = path, info
        self.sent_seq = 0  # the current view again, with the new model
        return info

    def load_scene(self, path: str) -> dict[str, Any]:
        self.ensure_started()
        info = self.worker.request("scene", path).wait(LOAD_TIMEOUT_S)
        self.scene_path = path
        self.sent_seq = 0
        return info

    # -- the control loop's part ---------------------------------------------------------------

    def step(self) -> None:
        """Once per tick: collect what the worker sent, show frames, send the newest view."""
        if self.state in ("idle", "stopped"):
            return
        if self.state == "crashed":
            if time.monotonic() >= self._restart_at:
                self.worker = FrameWorker(self.d.config)
                self.inflight = None
                self.start()
            return
        try:
            msgs = self.worker.receive()
        except (EOFError, OSError):
            msgs = None
        if msgs is None or not self.worker.alive:
            self._crashed()
            return
        for msg in msgs:
            self._handle(msg)
        self._send_next()

    def _handle(self, msg: tuple) -> None:
        kind = msg[0]
        if kind == "ready":
            self.worker.ready = True
            self.state = "running"
        elif kind in ("model", "scene"):
            _, req_id, ok, result = msg
            pending = self.worker.pending.pop(req_id, None)
            if pending is not None:
                pending.ok, pending.result = ok, result
                pending.done.set()
        elif kind == "frame":
            self._show(msg[1], msg[2])
        elif kind == "frame_error":
            seq, message = msg[1], msg[2]
            self.inflight = None
            self.d._error("frame worker", f"view {seq}: {message}")

    def _send_next(self) -> None:
        if self.inflight is not None or not self.worker.ready:
            return
        if self.model_path is None or self.scene_path is None:
            return
        slot = self.d.views
        if slot.view is None or slot.seq <= self.sent_seq:
            return
        seq, view = slot.seq, slot.view
        self.worker.send(("frame", seq, view))
        self.inflight = (seq, time.perf_counter())
        self.sent_seq = seq

    def _show(self, seq: int, payload: dict[str, Any]) -> None:
        sent_at = self.inflight[1] if self.inflight and self.inflight[0] == seq else None
        self.inflight = None
        t0 = time.perf_counter()
        frame = self._panel(payload)
        c = self.d.config.daemon
        frame = panel_for_mode(frame, c.colour_mode, c.single_colour)
        bench = self.d.bench
        if bench.slm is not None and not bench.held:  # held: the capture job shows it after
            try:
                bench.slm.show(frame)
                bench.showing = f"view {seq}"
            except Exception as exc:
                from nhfd.drivers.slm import SLMOutputLost

                self.d._error("slm", f"showing view {seq}: {type(exc).__name__}: {exc}")
                if isinstance(exc, SLMOutputLost):  # the control loop switches lasers off
                    bench.note_slm_lost(str(exc))
                return
        done = time.perf_counter()
        stages = dict(payload["timings_s"])
        stages["output"] = done - t0
        timings = {f"{k}_ms": round(v * 1e3, 3) for k, v in stages.items()}
        if sent_at is not None:
            timings["view_to_slm_ms"] = round((done - sent_at) * 1e3, 3)
        timings.update(seq=seq, cached=payload["cached"],
                       clipped_fraction=list(payload["clipped_fraction"]))
        self.timings = timings
        self.warnings = list(payload["warnings"])
        self.last_rgb, self.last_frame = payload.get("rgb"), frame
        self.shown_seq = seq
        self.frames_shown += 1
        self.d.display = f"view {seq}"
        self.d.views.mark_applied(seq)

    def _panel(self, payload: dict[str, Any]) -> np.ndarray:
        """The full panel: the blank frame (the zero pattern of the coding in use) outside the
        coded region."""
        blank = self.d.bench.blank_frame()
        if self._zero is None or self._zero_of is not blank:
            from nhfd.daemon.frames import PanelBuffer

            self._zero, self._zero_of = PanelBuffer(blank), blank
        top, left = payload["region"][:2]
        return self._zero.frame(top, left, payload["grey"])

    def _crashed(self) -> None:
        code = self.worker.process.exitcode if self.worker.process is not None else None
        self.crashes += 1
        message = f"frame worker (pid {self.worker.pid}) died with exit code {code}"
        log.error("%s; lasers off, SLM blanked, restarting", message)
        # The panel may hold a half-updated or stale frame the daemon no longer controls: the
        # light path is affected, so the lasers go off first.
        try:
            self.d.laser.off()
            message += "; lasers switched off"
        except Exception as exc:
            message += f"; lasers off FAILED: {exc}"
        with contextlib.suppress(Exception):
            self.d.bench.show_blank()
            self.d.display = "blank"
        self.d._error("frame worker", message)
        self.worker.close(timeout_s=0.5)
        self.state = "crashed"
        self.sent_seq = 0
        self._restart_at = time.monotonic() + RESTART_BACKOFF_S

    def status(self) -> dict[str, Any]:
        return {"state": self.state, "pid": self.worker.pid, "alive": self.worker.alive,
                "model": self.model_path, "scene": self.scene_path,
                "sent_seq": self.sent_seq, "shown_seq": self.shown_seq,
                "frames_shown": self.frames_shown, "crashes": self.crashes,
                "pose_warnings": self.warnings}


def _accepted_calibration(config: Any) -> Any:
    """The calibration this process applies, for the worker; None when there is none to keep
    (the worker's own load then says why, with each frame)."""
    from nhfd.calibration import active_calibration

    try:
        return active_calibration(config)
    except ValueError:
        return None


def apply_camera_roi(bench: Any, config: Any) -> None:
    """Give the simulated camera the configured sensor region (daemon.camera_roi_px): the
    camera is rebuilt, because its fixed-pattern noise is drawn for its region at creation."""
    roi = list(config.daemon.camera_roi_px)
    if not roi or bench.camera is None or config.devices.camera != "simulated":
        return
    from types import SimpleNamespace

    from nhfd.drivers import factory

    with contextlib.suppress(Exception):
        bench.camera.close()
    camera = factory.make_camera(config.devices, slm=bench.slm,
                                 laser=SimpleNamespace(twin=bench.laser_twin),
                                 stage=bench.stage, roi=tuple(roi))
    if camera is not None:
        camera.open()
    bench.camera = camera


def default_model_path(base: Path) -> Path:
    return base / "models" / "nhf-donut-512.onnx"
