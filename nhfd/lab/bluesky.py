"""Ophyd devices for Bluesky over the daemon's JSON-RPC client (`pip install nhfd[bluesky]`).

    from bluesky import RunEngine
    from bluesky.plans import scan
    from nhfd.lab.bluesky import connect

    bench = connect()                  # the daemon's Unix socket, from the configuration's rules
    RE = RunEngine()
    RE(scan([bench.camera], bench.focus, -0.5, 1.5, 5))

- `NhfdFocus` (`focus`): a positioner in the daemon's focus units (mm of hologram depth, the
  `focus` method). `set(z_mm)` starts a focus job and returns a Status that completes when the job
  is done and fails with the daemon's message when the call is refused or the job fails. Its
  readback is the stage's reading from `status`, mapped back to depth.
- `NhfdView` (`view`): `set({"orbit": {...}})` (or `pose`, `relative`, with `refocus_mm`) sends
  `set_view`; the Status completes when the bench shows that view (at once when the daemon has no
  model and scene to render it with). Reads the current view (JSON text) and its sequence numbers.
- `NhfdCamera` (`camera`): a detector. `trigger()` runs a `capture` job (a linear float32 image,
  dark subtracted; `mode = "capture"`, the default) or a `snapshot` job (`mode = "snapshot"`, the
  16-bit PNG read back as linear values in [0, 1]); `read()` gives the image and its exposure,
  gain, frames averaged, saturated fraction and stage position. The daemon writes the files (inside
  its `pattern_dirs` or `snapshot_dir`) and this process reads them: the client runs on the
  bench's machine (the Unix socket, or an SSH tunnel to it with the files shared).
- `NhfdLasers` (`lasers`): the laser channels' powers as the daemon reads them back, and whether
  they are armed; read-only. Nothing here arms, enables or powers a laser: a person does.

One `Client` serves all devices; calls are serialised through `DaemonLink` (a client is one
socket), and a reading of several signals costs one `status` call.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from ophyd import Component as Cpt
from ophyd import Device, Kind, Signal
from ophyd.positioner import PositionerBase
from ophyd.signal import UNSET_VALUE, InternalSignal, SignalRO
from ophyd.status import Status
from PIL import Image

from nhfd.daemon.client import Client
from nhfd.daemon.protocol import RpcError
from nhfd.device_settings import COLOURS

# How often a waiting Status asks the daemon about its job (s), and how long a reading may reuse
# one `status` reply (s): the signals of one `read()` then share it.
POLL_S = 0.02
STATUS_TTL_S = 0.05
JOB_TIMEOUT_S = 300.0
# The daemon's monitor refreshes the stage reading in `status` every 0.2 s: the longest a focus
# Status waits for it after the job (s).
STATUS_LAG_S = 1.0
CAMERA_MODES = ("capture", "snapshot")
PNG16_MAX = 65535.0


class DaemonError(RuntimeError):
    """The daemon refused a request or its job failed; the message is the daemon's."""


class DaemonLink:
    """The client the devices share: one call at a time, and a short-lived `status` cache."""

    def __init__(self, client: Client, *, poll_s: float = POLL_S,
                 status_ttl_s: float = STATUS_TTL_S, job_timeout_s: float = JOB_TIMEOUT_S) -> None:
        self.client = client
        self.poll_s = poll_s
        self.status_ttl_s = status_ttl_s
        self.job_timeout_s = job_timeout_s
        self._lock = threading.Lock()
        self._status: tuple[float, dict[str, Any]] | None = None

    def call(self, method: str, **params: Any) -> Any:
        with self._lock:
            return self.client.call(method, **params)

    def status(self, *, fresh: bool = False) -> dict[str, Any]:
        now = time.monotonic()
        cached = self._status
        if fresh or cached is None or now - cached[0] > self.status_ttl_s:
            cached = (now, self.call("status"))
            self._status = cached
        return cached[1]

    def start_job(self, what: str, method: str, params: dict[str, Any], status: Status,
                  on_done: Callable[[dict[str, Any]], None]) -> dict[str, Any] | None:
        """Send `method` (which answers with a job id) and finish `status` when the job ends:
        `on_done(result)` then success, or the daemon's error. A refused call fails `status` at
        once. Returns the daemon's reply (None when refused)."""
        try:
            reply = self.call(method, **params)
        except RpcError as exc:
            _fail(status, DaemonError(f"{what}: the daemon refused {method}: {exc}"))
            return None
        except Exception as exc:  # the daemon went away: the status says so, not a thread
            _fail(status, DaemonError(f"{what}: {type(exc).__name__}: {exc}"))
            return None
        job_id = int(reply["job"])
        threading.Thread(target=self._follow, args=(what, job_id, status, on_done),
                         name=f"nhfd-bluesky-job-{job_id}", daemon=True).start()
        return reply

    def _follow(self, what: str, job_id: int, status: Status,
                on_done: Callable[[dict[str, Any]], None]) -> None:
        end = time.monotonic() + self.job_timeout_s
        try:
            while not status.done:
                job = self.call("job", id=job_id)
                if job["state"] == "done":
                    on_done(job["result"])
                    self._status = None  # the bench changed: the next reading asks again
                    status.set_finished()
                    return
                if job["state"] in ("failed", "cancelled"):
                    self._status = None
                    _fail(status, DaemonError(f"{what}: {job['kind']} job {job_id} "
                                              f"{job['state']}: {job['error']}"))
                    return
                if time.monotonic() > end:
                    _fail(status, DaemonError(f"{what}: {job['kind']} job {job_id} still "
                                              f"{job['state']} after {self.job_timeout_s:g} s"))
                    return
                time.sleep(self.poll_s)
        except Exception as exc:
            _fail(status, DaemonError(f"{what}: {type(exc).__name__}: {exc}"))


def _fail(status: Status, exc: Exception) -> None:
    if not status.done:  # a Status that timed out on its own stays as it is
        try:
            status.set_exception(exc)
        except Exception:  # finished meanwhile (its own timeout): nothing left to report
            pass


class StatusSignal(SignalRO):
    """A read-only signal read from the daemon's `status` at every `get()`: `pick(status,
    device)` takes the value out (`device` is the signal's root device, which holds the link)."""

    def __init__(self, *args: Any, pick: Callable[[dict[str, Any], Any], Any],
                 **kwargs: Any) -> None:
        self._pick = pick
        super().__init__(*args, **kwargs)

    def get(self, **kwargs: Any) -> Any:
        root = self.root
        value = self._pick(root.link.status(), root)
        old, self._readback = self._readback, value
        now = time.time()
        self._metadata["timestamp"] = now
        self._run_subs(sub_type=self.SUB_VALUE, old_value=old, value=value, timestamp=now)
        return value


class ImageSignal(InternalSignal):
    """The last image (float32 [H, W], or [C, H, W] for a colour camera); its description names
    the numpy dtype and the shape of the image read."""

    def describe(self) -> dict[str, Any]:
        if self._readback is UNSET_VALUE:  # the shape is the camera region's, known once read
            raise RuntimeError(f"{self.name}: no image yet: trigger the camera before describe()")
        desc = super().describe()
        desc[self.name]["dtype_numpy"] = np.dtype(np.float32).str
        return desc


# --- focus ---------------------------------------------------------------------------------


def _stage_mm(status: dict[str, Any]) -> float:
    stage = status["devices"]["stage"]
    if stage.get("position_mm") is None:
        raise DaemonError(f"no stage reading: {stage.get('error') or 'no stage configured'}")
    return float(stage["position_mm"])


def _focus_readback(status: dict[str, Any], focus: NhfdFocus) -> float:
    return focus.depth_mm(_stage_mm(status), status)


class NhfdFocus(Device, PositionerBase):
    """The daemon's focus (mm of hologram depth from the reference plane) as a positioner."""

    readback = Cpt(StatusSignal, pick=_focus_readback, kind=Kind.hinted)
    setpoint = Cpt(InternalSignal, value=0.0, kind=Kind.normal)
    stage_mm = Cpt(StatusSignal, pick=lambda s, _: _stage_mm(s), kind=Kind.normal)

    def __init__(self, link: DaemonLink, *, name: str, home_first: bool = False,
                 **kwargs: Any) -> None:
        self.link = link
        self._home = home_first
        # (z_mm, stage_mm) of the last focus the daemon accepted: where the calibrated mapping
        # puts z = 0 is not in `status`, only its slope.
        self._anchor: tuple[float, float] | None = None
        self._job: int | None = None
        super().__init__("", name=name, **kwargs)
        self.readback.name = self.name  # the scan's column is the device's name

    @property
    def egu(self) -> str:
        return "mm"

    @property
    def limits(self) -> tuple[float, float]:
        low, high = self.link.status()["calibration"]["focus_range_mm"]
        return float(low), float(high)

    @property
    def position(self) -> float:
        return float(self.readback.get())

    def depth_mm(self, stage_mm: float, status: dict[str, Any]) -> float:
        """The focus depth (mm) at which the stage reads `stage_mm`, by the daemon's mapping:
        `stage = stage_at_reference_mm + z` uncalibrated, a slope of `1 / stage_scale` with a
        calibration (anchored at the last focus accepted, or the last focus job in `status`)."""
        cal = status["calibration"]
        if not cal.get("loaded"):
            return stage_mm - float(cal["stage_at_reference_mm"])
        anchor = self._anchor or _last_focus(status)
        if anchor is None:
            raise DaemonError("the calibrated focus mapping's zero is known after the first "
                              "focus move: no focus job yet")
        z_mm, stage_at = anchor
        return z_mm + (stage_mm - stage_at) * float(cal["stage_scale"])

    def check_value(self, value: Any) -> None:
        """The daemon checks the range (one place); a non-number fails here."""
        float(value)

    def move(self, position: Any, wait: bool = False, timeout: float | None = None,
             moved_cb: Any = None) -> Status:
        z_mm = float(position)
        status = Status(obj=self, timeout=timeout or self.link.job_timeout_s)
        self._moving = True

        def finished(st: Status) -> None:
            self._moving = False
            self._job = None
            if st.success:
                self._set_position(z_mm)
                self._done_moving(success=True)

        self.setpoint.put(z_mm, internal=True)
        params: dict[str, Any] = {"z_mm": z_mm}
        if self._home:
            params["home"] = True
        status.add_callback(finished)
        reply = self.link.start_job(f"focus to z_mm = {z_mm:g}", "focus", params, status,
                                    self._until_status_shows)
        if reply is not None:
            self._home = False
            if not status.done:  # a fast job may have finished already
                self._job = int(reply["job"])
            self._anchor = (z_mm, float(reply["stage_mm"]))  # the stage target of z_mm
        if wait:
            status.wait()
        return status

    def _until_status_shows(self, result: dict[str, Any]) -> None:
        """Waits (at most `STATUS_LAG_S`) until `status` reads the stage where the job left it:
        the daemon refreshes its stage reading on a monitor thread, so a readback taken at once
        could still be the old position."""
        end = time.monotonic() + STATUS_LAG_S
        while time.monotonic() < end:
            stage = self.link.status(fresh=True)["devices"]["stage"].get("position_mm")
            if stage is not None and abs(float(stage) - float(result["stage_mm"])) <= 1e-6:
                return
            time.sleep(self.link.poll_s)

    def stop(self, *, success: bool = False) -> None:
        """Stops the stage only while this device's focus job runs: the daemon's `stop` cancels
        every bench job, other clients' included."""
        if self._job is not None and not success:
            self.link.call("stop")
        super().stop(success=success)


def _last_focus(status: dict[str, Any]) -> tuple[float, float] | None:
    for job in reversed(status.get("jobs") or []):
        if job["kind"] == "focus" and job["state"] == "done" and job.get("result"):
            return float(job["result"]["z_mm"]), float(job["result"]["stage_mm"])
    return None


# --- view ----------------------------------------------------------------------------------


def _view_params(target: Any) -> dict[str, Any]:
    """`set_view`'s parameters from `{"orbit"|"pose"|"relative": {...}, "refocus_mm"?}`, or from
    a view as `read()` gives it (`{"kind": "orbit", ...}`)."""
    if isinstance(target, str):
        target = json.loads(target)
    if not isinstance(target, dict):
        raise ValueError(f"view = {target!r}: expected a dict such as "
                         "{'orbit': {'azimuth_deg': 0, 'elevation_deg': 10, 'radius': 2}}")
    if "kind" in target:  # a normalised view, as read back
        view = dict(target)
        kind = view.pop("kind")
        params = {"refocus_mm": view.pop("refocus_mm")} if "refocus_mm" in view else {}
        return {kind: view, **params}
    return dict(target)


class NhfdView(Device):
    """The daemon's view: `set(...)` sends `set_view`; reads give the requested view (JSON text),
    its sequence number and the last one the bench showed (0: none yet)."""

    current = Cpt(StatusSignal,
                  pick=lambda s, _: json.dumps((s["view"] or {}).get("requested")),
                  kind=Kind.hinted)
    seq = Cpt(StatusSignal, pick=lambda s, _: int((s["view"] or {}).get("seq") or 0),
              kind=Kind.normal)
    applied_seq = Cpt(StatusSignal,
                      pick=lambda s, _: int((s["view"] or {}).get("applied_seq") or 0),
                      kind=Kind.normal)

    def __init__(self, link: DaemonLink, *, name: str, **kwargs: Any) -> None:
        self.link = link
        super().__init__("", name=name, **kwargs)
        self.current.name = self.name  # the reading's key is the device's name

    def set(self, value: Any, *, timeout: float | None = None) -> Status:
        status = Status(obj=self, timeout=timeout or self.link.job_timeout_s)
        try:
            seq = int(self.link.call("set_view", **_view_params(value))["seq"])
        except RpcError as exc:
            _fail(status, DaemonError(f"view: the daemon refused set_view: {exc}"))
            return status
        except ValueError as exc:
            _fail(status, exc)
            return status
        threading.Thread(target=self._follow, args=(seq, status), daemon=True,
                         name=f"nhfd-bluesky-view-{seq}").start()
        return status

    def _follow(self, seq: int, status: Status) -> None:
        try:
            while not status.done:
                s = self.link.status(fresh=True)
                if (s["view"].get("applied_seq") or 0) >= seq or not _renders(s):
                    # Shown (or overtaken by a newer view that was); with no model and scene
                    # the daemon holds the view until it can render it.
                    status.set_finished()
                    return
                time.sleep(self.link.poll_s)
        except Exception as exc:
            _fail(status, DaemonError(f"view {seq}: {type(exc).__name__}: {exc}"))


def _renders(status: dict[str, Any]) -> bool:
    """Whether the daemon's frame worker can render a view now (a model and a scene loaded)."""
    return (status["frames"].get("state") == "running" and status["model"] != "none loaded"
            and bool(status.get("scene")))


# --- camera --------------------------------------------------------------------------------


class NhfdCamera(Device):
    """The daemon's camera as a detector. `mode` (configuration): "capture" (a linear float32
    .npy, dark subtracted) or "snapshot" (a 16-bit PNG, linear values clipped to [0, 1]; no gain
    in its reading). `exposure_request_s` and `frames_request` (configuration; 0 = the camera's
    own) go with each capture."""

    image = Cpt(ImageSignal, kind=Kind.normal)
    exposure_s = Cpt(InternalSignal, value=0.0, kind=Kind.normal)
    gain_db = Cpt(InternalSignal, value=0.0, kind=Kind.normal)
    frames = Cpt(InternalSignal, value=0, kind=Kind.normal)
    saturated_fraction = Cpt(InternalSignal, value=0.0, kind=Kind.normal)
    max_linear = Cpt(InternalSignal, value=0.0, kind=Kind.hinted)
    stage_mm = Cpt(InternalSignal, value=0.0, kind=Kind.normal)
    path = Cpt(InternalSignal, value="", kind=Kind.normal)
    mode = Cpt(Signal, value="capture", kind=Kind.config)
    exposure_request_s = Cpt(Signal, value=0.0, kind=Kind.config)
    frames_request = Cpt(Signal, value=0, kind=Kind.config)

    def __init__(self, link: DaemonLink, *, name: str, mode: str = "capture",
                 exposure_s: float = 0.0, frames: int = 0, subdir: str = "bluesky",
                 **kwargs: Any) -> None:
        self.link = link
        # Relative names land in the daemon's first pattern_dir (capture) or its snapshot_dir.
        self._stem = f"{subdir}/{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
        self._count = 0
        super().__init__("", name=name, **kwargs)
        self.mode.put(mode)
        self.exposure_request_s.put(float(exposure_s))
        self.frames_request.put(int(frames))

    def trigger(self) -> Status:
        mode = self.mode.get()
        status = Status(obj=self, timeout=self.link.job_timeout_s)
        if mode not in CAMERA_MODES:
            _fail(status, ValueError(f"{self.name}.mode = {mode!r}: one of {CAMERA_MODES}"))
            return status
        # The snapshot's PNG carries no gain: its reading leaves it out.
        self.gain_db.kind = Kind.normal if mode == "capture" else Kind.omitted
        self._count += 1
        params: dict[str, Any] = {
            "path": f"{self._stem}-{self._count:05d}.{'npy' if mode == 'capture' else 'png'}"}
        if int(self.frames_request.get()) > 0:
            params["frames"] = int(self.frames_request.get())
        if mode == "capture" and float(self.exposure_request_s.get()) > 0:
            params["exposure_s"] = float(self.exposure_request_s.get())
        self.link.start_job(f"{self.name} {mode}", mode, params, status, self._store)
        return status

    def _store(self, result: dict[str, Any]) -> None:
        path = Path(result["path"])
        if path.suffix == ".npy":
            image = np.load(path, allow_pickle=False).astype(np.float32)
            stage = result.get("stage_mm")
            self.gain_db.put(float(result["gain_db"]), internal=True)
        else:  # write_png16's linear values, scaled to 16 bits
            with Image.open(path) as png:
                image = (np.asarray(png, dtype=np.float64) / PNG16_MAX).astype(np.float32)
            stage = self.link.status(fresh=True)["devices"]["stage"].get("position_mm")
        self.image.put(image, internal=True)
        self.exposure_s.put(float(result["exposure_s"]), internal=True)
        self.frames.put(int(result["frames"]), internal=True)
        self.saturated_fraction.put(float(result["saturated_fraction"]), internal=True)
        self.max_linear.put(float(result["max_linear"]), internal=True)
        self.stage_mm.put(float(stage) if stage is not None else 0.0, internal=True)
        self.path.put(str(path), internal=True)


# --- lasers --------------------------------------------------------------------------------


def _power(colour: str) -> Callable[[dict[str, Any], Any], float]:
    return lambda s, _: float(s["laser"]["channels"][colour]["power_pct"])


class NhfdLasers(Device):
    """The laser channels' powers (%) as the daemon reads them back, and the armed state.
    Read-only: arming and powers are a person's acts (`nhfctl laser ...`)."""

    red_power_pct = Cpt(StatusSignal, pick=_power(COLOURS[0]), kind=Kind.normal)
    green_power_pct = Cpt(StatusSignal, pick=_power(COLOURS[1]), kind=Kind.normal)
    blue_power_pct = Cpt(StatusSignal, pick=_power(COLOURS[2]), kind=Kind.normal)
    armed = Cpt(StatusSignal, pick=lambda s, _: bool(s["laser"]["armed"]), kind=Kind.normal)

    def __init__(self, link: DaemonLink, *, name: str, **kwargs: Any) -> None:
        self.link = link
        super().__init__("", name=name, **kwargs)


# --- connect -------------------------------------------------------------------------------


@dataclass
class NhfdBench:
    """The devices of one daemon, sharing one link."""

    focus: NhfdFocus
    view: NhfdView
    camera: NhfdCamera
    lasers: NhfdLasers
    link: DaemonLink

    def close(self) -> None:
        self.link.client.close()


def connect(target: str | os.PathLike[str] | Client | None = None, *, prefix: str = "",
            timeout_s: float = 10.0, home_first: bool = False,
            **camera: Any) -> NhfdBench:
    """The bench's devices over a `Client`, or over a new one on the socket `target` (None: the
    configuration's socket). Device names are `prefix` + focus, view, camera, lasers.
    `home_first`: the first focus move homes the stage; `camera`: `NhfdCamera`'s options
    (mode, exposure_s, frames, subdir)."""
    client = target if isinstance(target, Client) else Client(target, timeout_s=timeout_s)
    link = DaemonLink(client)
    link.status(fresh=True)  # a daemon that answers, or DaemonUnavailable now
    return NhfdBench(focus=NhfdFocus(link, name=f"{prefix}focus", home_first=home_first),
                     view=NhfdView(link, name=f"{prefix}view"),
                     camera=NhfdCamera(link, name=f"{prefix}camera", **camera),
                     lasers=NhfdLasers(link, name=f"{prefix}lasers"), link=link)
