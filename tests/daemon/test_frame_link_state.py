"""`FrameLink`'s parts (issue 33): its state is a `LinkState`, the view in the worker an
`InFlight`, a frame waiting for its refresh a `WaitingFrame`; it reports through the
`FrameEvents` given at construction; load jobs' threads hand their loads to the control loop
through a queue, so every field is written by one thread. And the frame message it reads
(`nhfd.frame_message`) checks itself.

The worker is this module's `worker_main`, spawned by name as the real one is: instant frames,
loads that succeed unless a file `<path>.refuse` exists, and death on a view at CRASH_DEG.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from nhfd.calibration import CalibrationStore
from nhfd.config import Config, _overlay
from nhfd.daemon import frame_link
from nhfd.daemon.frame_link import FrameEvents, FrameLink, InFlight, LinkState, WaitingFrame
from nhfd.daemon.panel import Panel
from nhfd.daemon.views import ViewSlot
from nhfd.drivers.slm import SimulatedSLM
from nhfd.frame_message import FrameMessage, Region, StageTimes
from nhfd.views import Orbit, View
from nhfd.worker_messages import (
    FrameDone,
    FrameRequest,
    Loaded,
    LoadFailed,
    LoadModel,
    LoadScene,
    Stop,
    WorkerReady,
)

from .conftest import bench_config, wait_until
from .fake_loads import fake_load

CRASH_DEG = -111.0


def worker_main(conn: Any, config_data: dict[str, Any], calibration: Any = None,
                slots: dict[str, Any] | None = None) -> None:
    from multiprocessing import shared_memory

    shms = [shared_memory.SharedMemory(name=n) for n in slots["names"]]
    h, w = config_data["slm"]["height_px"] // 2, config_data["slm"]["width_px"] // 2
    conn.send(WorkerReady(os.getpid()))
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            return
        match msg:
            case Stop():
                return
            case LoadModel(req_id=req_id, path=path) | LoadScene(req_id=req_id, path=path):
                if Path(path + ".refuse").exists():
                    conn.send(LoadFailed(req_id, f"ValueError: {path} refused"))
                else:
                    conn.send(Loaded(req_id, fake_load(msg)))
            case FrameRequest(seq=seq, view=view, slot=slot):
                if view.camera.azimuth_deg == CRASH_DEG:
                    os._exit(3)
                np.ndarray((3, h, w), np.uint8, buffer=shms[slot].buf)[...] = seq % 256
                conn.send(FrameDone(seq, FrameMessage(
                    Region(h // 2, w // 2, h, w, 0, 0), (3, h, w), None,
                    StageTimes(render_s=0.001), (0.0, 0.0, 0.0), slot=slot,
                    ready_s=time.monotonic())))


def orbit(azimuth_deg: float) -> View:
    return View(Orbit(azimuth_deg, 0.0, 1.0))


class Owner:
    """What a daemon gives a frame link: a view slot, a panel, and its events, recorded."""

    def __init__(self, config: Config) -> None:
        self.views = ViewSlot()
        self.slm = SimulatedSLM(config.slm.width_px, config.slm.height_px).open()
        self.calibration = CalibrationStore.of(config)
        self.panel = Panel(config, SimpleNamespace(slm=self.slm, errors={"slm": None}),
                           self.calibration)
        self.shown: list[int] = []
        self.errors: list[tuple[str, str]] = []
        self.crashes: list[str] = []
        self.events = FrameEvents(
            shown=lambda seq: (self.shown.append(seq), self.views.mark_applied(seq)),
            error=lambda source, message: self.errors.append((source, message)),
            crashed=self.crashes.append,
            slm_lost=lambda detail: self.errors.append(("slm lost", detail)))


def make_link(root: Path, link_class: type = FrameLink) -> tuple[Owner, FrameLink]:
    config = Config.model_validate(_overlay(bench_config(root, None).model_dump(),
                                            {"slm": {"refresh_hz": 1000.0}}))
    owner = Owner(config)
    return owner, link_class(config, owner.calibration, owner.views, lambda: owner.panel,
                             owner.events, worker_module=__name__)


def load_in_thread(link: FrameLink, *loads: tuple[str, str]) -> list[Any]:
    """Run `loads` ((kind, path), in order) on a job's thread while this thread steps the link,
    as the daemon's control loop does; the results (or exceptions) in order."""
    results: list[Any] = []

    def job() -> None:
        for kind, path in loads:
            try:
                results.append(getattr(link, f"load_{kind}")(path))
            except Exception as exc:
                results.append(exc)

    thread = threading.Thread(target=job)
    thread.start()
    deadline = time.monotonic() + 20
    while thread.is_alive():
        link.step()
        time.sleep(0.005)
        assert time.monotonic() < deadline, "the loads did not finish"
    return results


def recording(base: type, prefix: str, writers: dict[str, set[int]]) -> type:
    """`base` with every attribute write recorded in `writers` (name -> writing threads)."""

    class Recording(base):  # type: ignore[misc, valid-type]
        def __setattr__(self, name: str, value: Any) -> None:
            writers.setdefault(f"{prefix}{name}", set()).add(threading.get_ident())
            super().__setattr__(name, value)

    return Recording


def test_every_field_is_written_by_the_control_loops_thread(short_dir, monkeypatch):
    # Before: the load job's thread started the worker and wrote model_path, model_info,
    # scene_path, state and sent_seq = 0 ("resend") while the control loop read them. The link
    # and each of its parts (the load queue, the pacer, the capture relay) are watched.
    writers: dict[str, set[int]] = {}
    for module, name, prefix in ((frame_link, "FrameWorker", "worker."),
                                 (frame_link, "LoadQueue", "loads."),
                                 (frame_link, "FramePacer", "pacer."),
                                 (frame_link, "CaptureRelay", "relay.")):
        monkeypatch.setattr(module, name, recording(getattr(module, name), prefix, writers))
    owner, link = make_link(short_dir, recording(FrameLink, "", writers))
    (short_dir / "bad.onnx.refuse").touch()
    try:
        assert link.state == LinkState.IDLE and link.worker.pid is None
        results = load_in_thread(link, ("scene", "a.ply"), ("model", "a.onnx"),
                                 ("model", str(short_dir / "bad.onnx")))
        assert [r.path for r in results[:2]] == ["a.ply", "a.onnx"]
        assert link.model is results[1] and link.model.variant == "float"
        assert link.scene is results[0] and link.scene.center == (0.0, 0.0, 0.0)
        assert isinstance(results[2], ValueError) and "bad.onnx refused" in str(results[2])
        # the refused model changed nothing: the one before it serves
        assert (link.model_path, link.scene_path) == ("a.onnx", "a.ply")
        seq = owner.views.submit(orbit(1.0))
        wait_until(lambda: (link.step(), link.shown_seq == seq)[1], 10, "a frame")
    finally:
        link.close()
    main = {threading.get_ident()}
    assert {"state", "loads.model_path", "loads.scene_path", "loads.model", "loads.scene",
            "sent_seq", "worker.pid", "pacer.shown_seq", "pacer.waiting"} <= set(writers)
    assert {name: ids for name, ids in writers.items() if ids != main} == {}


def test_states_in_flight_and_events_through_a_crash_and_a_refused_reload(short_dir,
                                                                          monkeypatch):
    monkeypatch.setattr(frame_link, "RESTART_BACKOFF_S", 0.0)
    owner, link = make_link(short_dir)
    model = str(short_dir / "m.onnx")
    try:
        load_in_thread(link, ("scene", "s.ply"), ("model", model))
        assert link.state == LinkState.RUNNING and link.status()["state"] == "running"
        seq = owner.views.submit(orbit(1.0))
        link.step()
        assert isinstance(link.inflight, InFlight) and link.inflight.seq == seq
        assert link.inflight.slot == 0  # the shared-memory slot named to the worker
        wait_until(lambda: (link.step(), link.shown_seq == seq)[1], 10, "the frame")
        assert owner.shown == [seq] and owner.views.applied_seq == seq
        assert link.timings["render_ms"] == 1.0 and link.timings["coding_ms"] == 0.0

        # The worker dies: the owner hears of it (and would switch the lasers off); once the
        # reload is refused, that too is an error the owner records.
        Path(model + ".refuse").touch()
        owner.views.submit(orbit(CRASH_DEG))
        wait_until(lambda: (link.step(), link.state == LinkState.CRASHED)[1], 10, "the crash")
        assert len(owner.crashes) == 1 and "died with exit code 3" in owner.crashes[0]
        wait_until(lambda: (link.step(), any("reloading model" in m for _, m in owner.errors))[1],
                   20, "the refused reload")
        assert ("frame worker", f"reloading model {model}: ValueError: {model} refused") in (
            owner.errors)
        assert link.state == LinkState.RUNNING and link.model_path == model  # tried again later
        after = owner.views.submit(orbit(2.0))
        wait_until(lambda: (link.step(), link.shown_seq == after)[1], 10, "a frame after it")
    finally:
        link.close()
    assert link.state == LinkState.STOPPED and link.inflight is None and link.waiting is None
    with pytest.raises(ValueError, match="the frame worker stopped"):
        link.load_model(model)  # at once: no control loop will answer


def test_a_waiting_frame_is_a_value_with_its_message():
    message = FrameMessage(Region(0, 0, 2, 3, 0, 0), (3, 2, 3), None, StageTimes())
    waiting = WaitingFrame(7, message, None)
    assert waiting.message.region.width == 3 and waiting.seq == 7
    with pytest.raises(AttributeError):
        waiting.seq = 8  # type: ignore[misc]


def test_the_frame_message_checks_itself_and_carries_arrays_only_when_asked():
    grey = np.zeros((3, 4, 6), np.uint8)
    with pytest.raises(ValueError, match=r"frame grey_shape = \[3, 4, 6\]: expected \[C, 5, 6\]"):
        FrameMessage(Region(0, 0, 5, 6, 0, 0), grey.shape, None, StageTimes())
    with pytest.raises(ValueError, match=r"region top = -2: expected an integer >= 0"):
        Region(-2, 0, 4, 6, 0, 0)
    with pytest.raises(ValueError, match=r"stage times \['decode'\]"):
        StageTimes.from_seconds({"render": 0.1, "decode": 0.2})
    with pytest.raises(ValueError, match=r"stage time coding_s = -1"):
        StageTimes(coding_s=-1)
    times = StageTimes.from_seconds({"render": 0.1, "coding": 0.2})
    assert times.seconds() == {"render": 0.1, "inference": 0.0, "propagation": 0.0,
                               "coding": 0.2}
    full = FrameMessage.of_arrays(Region(2, 4, 4, 6, 1, 1), grey, None, times, (0.1,) * 3,
                                  ["outside"])
    assert full.grey is grey and full.grey_shape == (3, 4, 6) and full.warnings == ("outside",)
    slotted = full.in_slot(0)
    assert slotted.grey is None and slotted.rgb is None and slotted.slot == 0
    assert slotted.region == full.region and slotted.grey_shape == full.grey_shape
    hit = full.from_cache()
    assert hit.cached and hit.timings == StageTimes() and hit.grey is grey
    assert full.ready(5.0).ready_s == 5.0 and full.ready_s is None
