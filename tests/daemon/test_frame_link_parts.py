"""The frame link's parts, each alone with fakes (no worker process): the load queue sends loads
from jobs' threads, answers them, and after a crash fails the unanswered ones and loads the
served scene and model again first; the pacer shows a refinement's K subframes in turn, one per
refresh, in panels it reuses (never a fresh one per refresh), and gives refine slots back; the
capture relay hands a current view's request to the bench and its answer back while the worker
waits, and refuses or drops the rest."""

from __future__ import annotations

import math
import threading
import time
from dataclasses import replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from nhfd.daemon.capture_relay import CaptureRelay
from nhfd.daemon.load_queue import LoadQueue, LoadRequest
from nhfd.daemon.pacing import PANELS_REUSED, FramePacer
from nhfd.frame_message import (
    CaptureReply,
    CaptureRequest,
    FrameMessage,
    RefinedFrame,
    Region,
    StageTimes,
)
from nhfd.views import Orbit, View
from nhfd.worker_messages import CaptureAnswer, Loaded, LoadFailed, LoadModel, LoadScene

from .fake_loads import fake_load, fake_model, fake_scene

# -- the load queue -----------------------------------------------------------------------------


class Loop:
    """A control loop for a `LoadQueue`: takes and sends its loads into `sent`, answers each
    with `answer(msg)` (None: not yet)."""

    def __init__(self, q: LoadQueue) -> None:
        self.q = q
        self.sent: list[LoadModel | LoadScene] = []
        self.answered = 0

    def step(self, answer: Any = lambda msg: Loaded(msg.req_id, fake_load(msg))) -> None:
        self.q.take()
        self.q.send(self.sent.append)
        for msg in self.sent[self.answered:]:
            reply = answer(msg)
            if reply is None:
                break
            self.q.answered(reply)
            self.answered += 1


def in_thread(fn: Any) -> tuple[threading.Thread, list[Any]]:
    out: list[Any] = []

    def run() -> None:
        try:
            out.append(fn())
        except Exception as exc:
            out.append(exc)

    t = threading.Thread(target=run)
    t.start()
    return t, out


def step_until(loop: Loop, thread: threading.Thread, **kw: Any) -> None:
    deadline = time.monotonic() + 10
    while thread.is_alive():
        loop.step(**kw)
        time.sleep(0.002)
        assert time.monotonic() < deadline, "the load did not finish"


def test_the_load_queue_answers_loads_and_after_a_crash_loads_what_it_served_first():
    errors: list[tuple[str, str]] = []
    q = LoadQueue(lambda source, message: errors.append((source, message)))
    loop = Loop(q)
    t, out = in_thread(lambda: [q.load(LoadRequest("scene", "s.ply"), 10),
                                q.load(LoadRequest("model", "m.onnx"), 10)])
    step_until(loop, t)
    scene, model = out[0]
    assert (scene, model) == (fake_scene("s.ply"), fake_model("m.onnx"))
    assert (q.scene_path, q.scene, q.model_path, q.model) == ("s.ply", scene, "m.onnx", model)
    assert [type(m) for m in loop.sent] == [LoadScene, LoadModel] and q.pending == {}

    # A load sent but unanswered when the worker dies fails; one queued after waits for the
    # next worker, which gets the served scene and model again first.
    t1, out1 = in_thread(lambda: q.load(LoadRequest("model", "n.onnx"), 10))
    deadline = time.monotonic() + 5
    while not q.pending:
        loop.step(answer=lambda msg: None)
        assert time.monotonic() < deadline
    q.worker_gone()  # the crash
    t1.join(5)
    assert isinstance(out1[0], ValueError) and str(out1[0]) == "the frame worker stopped"
    assert errors == []  # a job's load: its job says why, not status
    t2, out2 = in_thread(lambda: q.load(LoadRequest("scene", "t.ply"), 10))
    while q.take() < 1:
        time.sleep(0.002)
    q.restarted()
    before = len(loop.sent)

    def refuse_model(msg: LoadModel | LoadScene) -> Loaded | LoadFailed:
        if isinstance(msg, LoadModel):
            return LoadFailed(msg.req_id, "ValueError: refused")
        return Loaded(msg.req_id, fake_load(msg))

    loop.answered = before
    step_until(loop, t2, answer=refuse_model)
    assert [(type(m), m.path) for m in loop.sent[before:]] == [
        (LoadScene, "s.ply"), (LoadModel, "m.onnx"), (LoadScene, "t.ply")]
    # The refused reload is an error in status (nobody waits for it); the model stays.
    assert errors == [("frame worker", "reloading model m.onnx: ValueError: refused")]
    assert q.model_path == "m.onnx" and q.scene_path == "t.ply" and out2 == [fake_scene("t.ply")]


def test_the_load_queue_refuses_an_answer_of_the_wrong_kind_and_fails_all_on_close():
    q = LoadQueue(lambda source, message: None)
    loop = Loop(q)
    t, out = in_thread(lambda: q.load(LoadRequest("model", "m.onnx"), 10))
    step_until(loop, t, answer=lambda msg: Loaded(msg.req_id, fake_scene(msg.path)))
    assert isinstance(out[0], ValueError)
    assert str(out[0]) == ("the frame worker answered a model load with SceneLoaded, not "
                           "ModelLoaded")
    assert q.model is None and q.scene is None  # nothing served changed
    assert not q.answered(Loaded(999, fake_model("x.onnx")))  # no such load: ignored
    waiting = [in_thread(lambda: q.load(LoadRequest("scene", "s.ply"), 10)) for _ in range(2)]
    while q.take() < 2:
        time.sleep(0.002)
    q.close()
    for thread, result in waiting:
        thread.join(5)
        assert isinstance(result[0], ValueError) and str(result[0]) == "the frame worker stopped"


# -- the pacer -----------------------------------------------------------------------------------

H, W, K = 12, 16, 3
REGION = Region(4, 6, 4, 6, 0, 0)
REPORT = {"tier": "sgd", "iterations": 10, "seconds": 0.1, "loss": 0.5, "psnr_db": 30.0,
          "start_psnr_db": 28.0, "stop": ""}


class FakePanel:
    """The panel: keeps a copy of what it was shown (as the SLM does), and which array it was
    (its memory's address)."""

    vsync_detail = ""

    def __init__(self) -> None:
        self.blank_ = np.full((3, H, W), 128, np.uint8)
        self.shown: list[tuple[int, np.ndarray]] = []
        self.buffers: list[int] = []

    def show_view(self, frame: np.ndarray, seq: int) -> np.ndarray:
        self.shown.append((seq, frame.copy()))
        self.buffers.append(frame.__array_interface__["data"][0])
        return frame

    def blank_frame(self) -> np.ndarray:
        return self.blank_

    def blank(self) -> None:
        pass


class FakeSlots:
    """The worker's slots: three refine slots of K subframes each, in memory."""

    def __init__(self) -> None:
        rng = np.random.default_rng(3)
        self.refine = [rng.integers(0, 256, (K, 3, REGION.height, REGION.width), np.uint8)
                       for _ in range(3)]
        self.freed: list[int | None] = []
        self.released: list[int | None] = []

    def arrays(self, message: FrameMessage) -> tuple[np.ndarray, np.ndarray | None]:
        assert message.grey is not None
        return message.grey, message.rgb

    def release(self, slot: int | None) -> None:
        self.released.append(slot)

    def refined_arrays(self, refined: RefinedFrame) -> np.ndarray:
        assert refined.slot is not None and refined.grey_shape is not None
        return self.refine[refined.slot][: refined.grey_shape[0]]

    def free_refine(self, slot: int | None) -> None:
        self.freed.append(slot)


def pacer_on_fakes(refresh_s: float = 1 / 60) -> tuple[FramePacer, Any]:
    host = SimpleNamespace(panel=FakePanel(), slots=FakeSlots(), shown=[], errors=[],
                           views=SimpleNamespace(seq=0, view=None))
    pacer = FramePacer(refresh_s, host.views, lambda: host.panel, lambda: host.slots,
                       shown=host.shown.append,
                       error=lambda source, message: host.errors.append((source, message)),
                       slm_lost=lambda detail: host.errors.append(("slm lost", detail)))
    return pacer, host


def network_frame(seq: int) -> FrameMessage:
    grey = np.full((3, REGION.height, REGION.width), seq, np.uint8)
    return FrameMessage.of_arrays(REGION, grey, None, StageTimes(render_s=0.001))


def due(pacer: FramePacer) -> None:
    """Make the next refresh due now (as one refresh period passing would)."""
    pacer.last_show_s = -math.inf


def test_the_pacer_shows_one_frame_per_refresh_and_k_subframes_in_turn_in_reused_panels():
    pacer, host = pacer_on_fakes()
    host.views.seq, host.views.view = 1, View(Orbit(0.0, 0.0, 1.0), quality="sgd")
    pacer.arrived(1, network_frame(1), sent_s=None)
    pacer.show_due()  # the first frame: due at once
    assert [s for s, _ in host.panel.shown] == [1] and host.shown == [1]
    assert host.slots.released == [None]  # its slot (none: arrays in the message) given back
    assert pacer.refinement is not None and pacer.refinement.tier == "sgd"
    # A frame back before the next refresh waits for it.
    pacer.arrived(1, network_frame(1), sent_s=None)
    pacer.show_due()
    assert len(host.panel.shown) == 1 and pacer.wake_s == pytest.approx(pacer.due_s)
    pacer.waiting = None

    # A better frame of K subframes in refine slot 0: shown at once, then one per refresh.
    pacer.refined(1, RefinedFrame(REGION, None, REPORT, slot=0, grey_shape=(K, 3, 4, 6)))
    assert pacer.cycling and pacer.refinement.swaps == 1 and pacer.refinement.report == REPORT
    for _ in range(2 * K):
        pacer.show_due()  # not due yet: nothing
        due(pacer)
        pacer.show_due()
    shown = host.panel.shown[1:]
    assert len(shown) == 1 + 2 * K
    r = REGION
    for i, (seq, frame) in enumerate(shown):
        assert seq == 1
        assert np.array_equal(frame[:, r.rows, r.cols], host.slots.refine[0][i % K])
        outside = frame.copy()
        outside[:, r.rows, r.cols] = 128
        assert np.all(outside == 128)  # the blank around it
    # Never a fresh panel per refresh: every frame is one of PANELS_REUSED buffers.
    assert len(set(host.panel.buffers)) == PANELS_REUSED
    assert pacer.refine_status()["subframes"] == K

    # The next better frame comes in slot 1: slot 0 goes back; a stale one (the view moved on)
    # is never shown and its slot goes back at once.
    pacer.refined(1, RefinedFrame(REGION, None, REPORT, slot=1, grey_shape=(K, 3, 4, 6)))
    assert host.slots.freed == [0] and pacer.refinement.swaps == 2
    host.views.seq, host.views.view = 2, View(Orbit(1.0, 0.0, 1.0))  # a network view
    assert not pacer.cycling and pacer.wake_s == math.inf
    count = len(host.panel.shown)
    pacer.refined(1, RefinedFrame(REGION, None, REPORT, slot=0, grey_shape=(K, 3, 4, 6)))
    assert host.slots.freed == [0, 0] and len(host.panel.shown) == count
    # The newer view's frame ends the refinement: its slot goes back too.
    pacer.arrived(2, network_frame(2), sent_s=None)
    due(pacer)
    pacer.show_due()
    assert host.slots.freed == [0, 0, 1] and pacer.refinement is None
    assert pacer.counts.shown == 2 and host.errors == []


NETWORK_REPORT = {**REPORT, "tier": "network", "iterations": 0, "stop": "subframes"}


@pytest.mark.parametrize("quality", ["network", "sgd"])
def test_a_k_subframe_models_frames_take_turns_while_the_view_moves(quality):
    """A model of K subframes sends its K with each frame (in a refine slot): the frame's own
    (the first) is shown, then the K in turn, one per refresh, for a moving view as for one at
    rest; a frame overtaken while it waits gives its slot back, and so does the frame shown once
    a newer one replaces it. A network view's cycle is no refinement in status."""
    pacer, host = pacer_on_fakes()
    r = REGION
    subframes = RefinedFrame(REGION, None, NETWORK_REPORT, slot=0, grey_shape=(K, 3, 4, 6))
    host.views.seq, host.views.view = 1, View(Orbit(0.0, 0.0, 1.0), quality=quality)
    pacer.arrived(1, network_frame(1), None, subframes)
    pacer.show_due()
    assert pacer.cycling and pacer.timings["subframes"] == K
    for _ in range(2 * K):
        due(pacer)
        pacer.show_due()
    shown = [frame[:, r.rows, r.cols] for _, frame in host.panel.shown]
    assert np.array_equal(shown[0], network_frame(1).grey)
    for i, grey in enumerate(shown[1:], start=1):  # subframe 1, 2, ..., K - 1, 0, 1, ...
        assert np.array_equal(grey, host.slots.refine[0][i % K]), i
    assert len({g.tobytes() for g in shown[1:]}) == K  # K distinct frames in turn
    if quality == "network":
        assert pacer.refine_status() is None
    else:  # the refinement starts from the network's K; its better frames replace them
        assert pacer.refine_status()["tier"] == "sgd"
        pacer.refined(1, RefinedFrame(REGION, None, REPORT, slot=1, grey_shape=(K, 3, 4, 6)))
        assert host.slots.freed == [0] and pacer.refinement.swaps == 1
        host.slots.freed.clear()

    # The view moves: view 2's frame waits, view 3's overtakes it (its slot goes back at once).
    on_panel = pacer.refinement.slot
    two, three = (slot for slot in range(3) if slot != on_panel)
    host.views.seq, host.views.view = 3, View(Orbit(2.0, 0.0, 1.0), quality=quality)
    pacer.arrived(2, network_frame(2), None, replace(subframes, slot=two))
    pacer.arrived(3, network_frame(3), None, replace(subframes, slot=three))
    assert host.slots.freed == [two]
    due(pacer)
    pacer.show_due()  # view 3 on the panel: the slot view 1 cycled from goes back
    assert host.slots.freed == [two, on_panel] and pacer.cycling
    assert pacer.refinement.seq == 3 and pacer.refinement.slot == three
    assert pacer.counts.shown == 2 and host.errors == []


def test_a_capture_says_what_its_exposure_spans_of_the_subframes_taking_turns():
    """At 60 Hz, 4 subframes cycle in 66.7 ms: an exposure of one or two cycles holds each
    equally; 10 ms (0.15 cycles) or 100 ms (1.5) weighs them unequally, and the warning says
    so with the exposure to set. A still frame adds nothing to the capture's result."""
    from nhfd.daemon.methods import exposure_over_cycle

    assert exposure_over_cycle(0.01, 1, 1 / 60) == {}
    for exposure_s in (4 / 60, 8 / 60, 4.1 / 60):
        got = exposure_over_cycle(exposure_s, 4, 1 / 60)
        assert "warning" not in got and got["subframes"] == 4
        assert got["cycle_s"] == pytest.approx(4 / 60, abs=1e-6)
    short = exposure_over_cycle(0.01, 4, 1 / 60)
    assert short["exposure_cycles"] == 0.15
    assert short["warning"] == ("exposure 10 ms spans 0.15 cycles of the 4 subframes shown in "
                                "turn (66.6667 ms at 60 Hz): the image weighs them unequally; "
                                "set exposure_s to a whole number of cycles (0.0666667 s)")
    assert "(0.133333 s)" in exposure_over_cycle(0.1, 4, 1 / 60)["warning"]


def test_the_pacer_sends_a_view_just_in_time_and_counts_late_frames():
    pacer, host = pacer_on_fakes(refresh_s=0.1)
    assert pacer.send_at_s == -math.inf  # no frame time learnt yet: at once
    now = time.monotonic()
    pacer.arrived(1, FrameMessage(REGION, (3, 4, 6), None, StageTimes(),
                                  ready_s=now - 0.02), sent_s=now - 0.03)
    assert pacer.compute_s == pytest.approx(0.01)
    host.views.seq = 1
    pacer.arrived(1, network_frame(1), sent_s=None)  # (arrays in the message this time)
    pacer.show_due()
    assert pacer.send_at_s == pytest.approx(pacer.due_s - 1.5 * 0.01 - 0.002)
    old = FrameMessage.of_arrays(REGION, np.zeros((3, 4, 6), np.uint8), None, StageTimes())
    pacer.arrived(2, FrameMessage(REGION, (3, 4, 6), None, StageTimes(), grey=old.grey,
                                  ready_s=time.monotonic() - 0.5), sent_s=None)
    due(pacer)
    pacer.show_due()
    assert pacer.counts.late == 1 and pacer.counts.max_age_s >= 0.5
    pacer.arrived(3, network_frame(3), sent_s=None)
    pacer.forget(crashed=True)  # the frame waiting goes with the worker: dropped
    assert pacer.counts.dropped == 1 and pacer.waiting is None


# -- the capture relay ----------------------------------------------------------------------------


def test_the_capture_relay_hands_on_answers_back_and_refuses_or_drops_the_rest():
    grey = np.zeros((2, 3, REGION.height, REGION.width), np.uint8)
    request = CaptureRequest(REGION, grey, (0.006,))
    reply = CaptureReply(np.ones((1, 3, 2, 2), np.float32), np.zeros((1, 3, 2, 2), bool))
    handed: list[tuple[int, CaptureRequest]] = []
    relay = CaptureRelay(lambda req_id, req: handed.append((req_id, req)))
    sent: list[CaptureAnswer] = []
    assert relay.waiting_phase() is None
    assert relay.asked(3, 1, request, True, sent.append)
    assert handed == [(1, request)] and sent == [] and relay.wanted(1)
    assert relay.waiting_phase() is None  # its bench job has not said where it is yet
    relay.phase(1, "")  # the bench job's thread
    assert relay.waiting_phase() == "waiting for the bench"
    relay.phase(1, "capturing green at plane 1 of 1")
    assert relay.waiting_phase() == "capturing green at plane 1 of 1"
    t = threading.Thread(target=relay.answer, args=(1, reply))  # from the bench job's thread
    t.start()
    t.join()
    relay.send_answers(sent.append)
    assert len(sent) == 1 and sent[0].req_id == 1 and sent[0].reply is reply
    assert not relay.wanted(1) and relay.waiting_phase() is None

    # Not the view shown, or nobody to capture: refused at once, naming why.
    assert not relay.asked(2, 2, request, False, sent.append)
    assert sent[-1].req_id == 2 and sent[-1].reply.error == "view 2 is no longer the one shown"
    assert not CaptureRelay(None).asked(3, 3, request, True, sent.append)
    assert sent[-1].reply.error == "this daemon has no camera loop"
    assert not relay.asked(3, 4, "not one", True, sent.append)
    assert sent[-1].reply.error == "not a capture request: str"
    # The worker cancelled the refinement that asked: a late answer is dropped.
    assert relay.asked(3, 5, request, True, sent.append)
    relay.cancelled()
    relay.answer(5, reply)
    n = len(sent)
    relay.send_answers(sent.append)
    assert len(sent) == n and not relay.wanted(5)
    # Emission sessions' ends, from any thread, in order, once.
    relay.emission_ended(3, "lasers off")
    relay.emission_ended(4, "disarmed")
    assert list(relay.emission_ends()) == [(3, "lasers off"), (4, "disarmed")]
    assert list(relay.emission_ends()) == []
