"""The frame link's pacing and subframes: when the newest frame goes to the panel, a
refinement's K subframes shown in turn, and the panels they are built in.

At most one view frame per refresh (`slm.refresh_hz`): a frame back from the worker waits
(`WaitingFrame`) until one refresh after the last one shown (`FramePacer.due_s`; the control
loop wakes for it at `wake_s`), and the next view goes to the worker no earlier than its frame
needs to be ready for the refresh after (`send_at_s`: 1.5 recent frame times plus a margin
before it), so the frame shown is the newest one just before that refresh. A view that asked
for a tier above the network's is refined while it rests (`Refinement`): each better frame's K
subframes are shown one per refresh, straight from the refine slot they came in, and the slot
shown before goes back to the worker. A model of K > 1 subframes sends all K with its frame
(in a refine slot): once the first is shown the K take turns the same way, while the view
moves as while it rests (a `Refinement` of tier "network", which `refine_status` does not
report). Frames are built in `PANELS_REUSED` panels used in turn
(`PanelBuffer`'s `reuse`): the control loop never builds a fresh 6 MB panel per refresh. `status`
counts frames shown, dropped and late (`FrameCounts`).

`FramePacer` knows nothing of the worker process or the daemon: it is built with the refresh
period, the view slot, a getter of the panel, a getter of the worker's slots and the events it
reports (shown, error, SLM lost).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from nhfd.drivers.slm import SLMOutputLost
from nhfd.frame_message import FrameMessage, RefinedFrame, Region, is_interleaved
from nhfd.views import View

# Panels the frame link builds in turn (`PanelBuffer`'s `reuse`): the one shown last stays
# whole (the panel's `resume` after a capture shows it again) while the next is built.
PANELS_REUSED = 2
# A frame is shown when its refresh is due within this (s): the control loop's select may wake
# a little before the time it was given.
DUE_SLACK_S = 0.0005
# A view goes to a worker faster than the panel this long (plus 1.5 frame times) before the
# refresh its frame is for (s).
SEND_MARGIN_S = 0.002


# -- what pacing uses of the daemon and of the worker ------------------------------------------


class PanelView(Protocol):
    """The daemon's panel (`nhfd.daemon.panel.Panel`), as far as view frames go."""

    @property
    def vsync_detail(self) -> str:
        """How the SLM paces frames to its refresh, when it says; "" otherwise."""
        ...

    def show_view(self, frame: np.ndarray, seq: int) -> np.ndarray:
        """Show view `seq`'s full-panel frame (`[3, H, W]` uint8) in the colour mode; returns the
        frame as shown."""
        ...

    def blank_frame(self) -> np.ndarray:
        """The blank of the coding in use, `[3, H, W]` uint8: the panel around every view frame."""
        ...

    def blank(self) -> None:
        """Show the blank."""
        ...


class ViewSource(Protocol):
    """The newest view requested and its sequence number (`nhfd.daemon.views.ViewSlot`)."""

    seq: int
    view: View | None


class WorkerSlots(Protocol):
    """Where a frame's arrays are (`nhfd.daemon.frame_link.FrameWorker`): its shared-memory
    slots, or the message itself with the pickled transport."""

    def arrays(self, message: FrameMessage) -> tuple[np.ndarray, np.ndarray | None]:
        """A frame's grey region `[3, h, w]` and render `[3, H, W]` (or None), uint8: views into
        its slot (copy before releasing it)."""
        ...

    def release(self, slot: int | None) -> None:
        """Give frame slot `slot` back once its frame is shown or refused."""
        ...

    def refined_arrays(self, refined: RefinedFrame) -> np.ndarray:
        """A better frame's subframes `[K, 3, h, w]` uint8 (a view into its refine slot, valid
        until the slot is given back); ValueError when they do not fit it."""
        ...

    def free_refine(self, slot: int | None) -> None:
        """Give refine slot `slot` back to the worker."""
        ...


# -- what pacing holds --------------------------------------------------------------------------


@dataclass(frozen=True)
class WaitingFrame:
    """A frame back from the worker, waiting for its refresh: its view's sequence number, the
    worker's message, and when the view went out (monotonic s; None when it was not the one in
    flight)."""

    seq: int
    message: FrameMessage
    sent_s: float | None
    subframes: RefinedFrame | None = None


@dataclass
class Refinement:
    """The refinement of the view on the panel (the progressive mode): its sequence number,
    the tier the view asked for, the worker's latest report (`nhfd.frame_message.REFINE_KEYS`;
    its "tier" is the stage running: a citl view's sgd steps say "sgd"), the better frame's
    subframes `[K, 3, h, w]` and where they go (shown in turn, one per refresh: each turn pastes
    one into a panel, never all K), the refine slot they are in, the one shown last, the citl
    capture requests so far, and why its emission session ended ("" while it holds)."""

    seq: int
    tier: str
    report: dict[str, Any]
    region: Region | None = None
    greys: np.ndarray | None = None
    slot: int | None = None
    index: int = 0
    swaps: int = 0
    captures: int = 0
    ended: str = ""

    @property
    def subframes(self) -> int:
        """How many subframes take turns on the panel (0: none refined yet)."""
        return 0 if self.greys is None else int(self.greys.shape[0])


@dataclass
class FrameCounts:
    """What `status.frames` counts (docs/frames.md): frames shown; views never computed because
    a newer one overtook them (latest wins), plus a frame waiting for its refresh when the
    worker crashed; of those, the exact frames the worker cut short for a newer view or a load;
    frames shown more than one refresh after the worker finished them; and the ages (s, from
    the frame whole in its slot to the end of the panel write)."""

    shown: int = 0
    dropped: int = 0
    cancelled: int = 0  # also counted in `dropped`
    late: int = 0
    last_age_s: float | None = None
    max_age_s: float = 0.0

    def showed(self, age_s: float | None, refresh_s: float) -> None:
        """One more frame on the panel, `age_s` old (None: its age is unknown)."""
        self.shown += 1
        if age_s is not None:
            self.last_age_s, self.max_age_s = age_s, max(self.max_age_s, age_s)
            self.late += age_s > refresh_s


class PanelBuffer:
    """Full panel frames from the zero pattern and a coded region, built in the SLM's `[H, W, 3]`
    layout: a frame is a fresh copy of the interleaved zero pattern with the region interleaved
    in, returned as its `[3, H, W]` view. `nhfd.drivers.slm.to_rgb` takes that view as it is,
    where a channel-first frame costs a transposing copy of the whole panel (~10 ms at
    1920 x 1080)."""

    def __init__(self, zero: np.ndarray, reuse: int = 0) -> None:
        """`reuse`: 0, every frame is a fresh array; N > 0, frames are built in N arrays reused
        in turn, so a frame stays as it was until N - 1 newer ones (the control loop's: a
        fresh 6 MB panel costs ~500 page faults, 13 ms of CPU on this project's VM, where a
        copy into memory already touched costs 0.5 ms)."""
        self.zero_hwc = np.ascontiguousarray(np.asarray(zero, np.uint8).transpose(1, 2, 0))
        self.reuse = int(reuse)
        self._outs: list[np.ndarray] = []
        self._next = 0

    def _out(self) -> np.ndarray:
        if len(self._outs) < self.reuse:
            self._outs.append(self.zero_hwc.copy())
            return self._outs[-1]
        if not self.reuse:
            return self.zero_hwc.copy()
        out = self._outs[self._next]
        self._next = (self._next + 1) % self.reuse
        np.copyto(out, self.zero_hwc)
        return out

    def frame(self, top: int, left: int, grey: np.ndarray) -> np.ndarray:
        """The panel `[3, H, W]` (a view of its `[H, W, 3]` array) with `grey` `[3, h, w]` at
        (top, left). A grey region in the SLM's layout (`is_interleaved`: a device frame's) is
        pasted row by row; a channel-first one is interleaved plane by plane (at 1920 x 1080 on
        this project's CPU: 0.2 against 1.7 ms)."""
        out = self._out()
        _, h, w = grey.shape
        dst = out[top : top + h, left : left + w]
        if is_interleaved(grey):
            dst[...] = grey.transpose(1, 2, 0)
        else:
            for c in range(grey.shape[0]):
                dst[..., c] = grey[c]
        return out.transpose(2, 0, 1)


# -- the pacer ----------------------------------------------------------------------------------


class FramePacer:
    """When frames from the worker go to the panel, and what the panel shows of a refinement.

    `refresh_s`: the panel's refresh period (1 / slm.refresh_hz). `views`: the newest view
    requested (read only). `panel`: the panel in use now (a getter, asked each time).
    `slots`: the worker's slots in use now (a getter: a restarted worker has new ones).
    `shown(seq)`, `error(source, message)`, `slm_lost(detail)`: the owner's events
    (`nhfd.daemon.frame_link.FrameEvents`). The control loop's thread alone calls it."""

    def __init__(self, refresh_s: float, views: ViewSource, panel: Callable[[], PanelView],
                 slots: Callable[[], WorkerSlots], *, shown: Callable[[int], None],
                 error: Callable[[str, str], None], slm_lost: Callable[[str], None]) -> None:
        self.refresh_s = float(refresh_s)
        self.views = views
        self.panel = panel
        self.slots = slots
        self.shown = shown
        self.error = error
        self.slm_lost = slm_lost
        self.waiting: WaitingFrame | None = None
        self.refinement: Refinement | None = None  # of the view on the panel, if it asked
        self.shown_seq = 0
        self.timings: dict[str, Any] | None = None
        self.warnings: list[str] = []
        self.last_rgb: np.ndarray | None = None
        self.last_frame: np.ndarray | None = None
        self.counts = FrameCounts()
        self.last_show_s = -math.inf  # monotonic, when the last view frame went to the panel
        self.compute_s: float | None = None  # the worker's recent frame time, request to ready
        self._zero: PanelBuffer | None = None  # of the blank frame `_zero_of`, built on use
        self._zero_of: np.ndarray | None = None

    # -- when ---------------------------------------------------------------------------------

    @property
    def due_s(self) -> float:
        """When the next view frame may go to the panel (monotonic): one refresh after the
        last."""
        return self.last_show_s + self.refresh_s

    @property
    def send_at_s(self) -> float:
        """When the next view may go to the worker (monotonic): early enough that its frame is
        ready for the next refresh (1.5 x the worker's recent frame time plus a margin before
        it), no earlier, so a worker faster than the panel computes the view that is newest
        just before the refresh instead of one a refresh old."""
        if self.compute_s is None:
            return -math.inf
        return self.due_s - 1.5 * self.compute_s - SEND_MARGIN_S

    @property
    def cycling(self) -> bool:
        """Whether the panel shows time-multiplexed subframes, one per refresh."""
        r = self.refinement
        return r is not None and r.subframes > 1 and self.views.seq == r.seq

    @property
    def wake_s(self) -> float:
        """When the control loop must step again for the panel (monotonic; inf: nothing is
        due): a frame waiting for its refresh, or the next subframe."""
        if self.waiting is not None or self.cycling:
            return self.due_s
        return math.inf

    # -- frames from the worker ----------------------------------------------------------------

    def arrived(self, seq: int, message: FrameMessage, sent_s: float | None,
                subframes: RefinedFrame | None = None) -> None:
        """View `seq`'s frame is back (`sent_s`: when the view went out, None when it was not
        the one in flight; `subframes`: a K-subframe model's K): it waits for its refresh, and
        the worker's frame time is learnt. A frame it overtakes gives its subframes' refine
        slot back."""
        if sent_s is not None and message.ready_s is not None:
            took = max(0.0, message.ready_s - sent_s)
            self.compute_s = took if self.compute_s is None else (
                0.7 * self.compute_s + 0.3 * took)
        if self.waiting is not None and self.waiting.subframes is not None:
            self.slots().free_refine(self.waiting.subframes.slot)
        self.waiting = WaitingFrame(seq, message, sent_s, subframes)  # one frame at a time

    def show_due(self) -> None:
        """Show the waiting frame, or the refinement's next subframe, when its refresh is due."""
        if self.waiting is not None and time.monotonic() >= self.due_s - DUE_SLACK_S:
            waiting, self.waiting = self.waiting, None
            self._show(waiting)
        elif self.cycling and time.monotonic() >= self.due_s - DUE_SLACK_S:
            self._show_subframe()

    def refined(self, seq: int, refined: Any) -> None:
        """A better frame for view `seq`: shown only while `seq` is the view on the panel and no
        newer one was asked for (a refinement the worker had not yet seen cancelled is
        stale); its subframes then take turns, one per refresh. A stale frame's refine slot,
        and the one the frame before it was in, go back to the worker."""
        current = self.refinement
        if not isinstance(refined, RefinedFrame):
            self.error("frame worker", f"view {seq}: not a refined frame: "
                                       f"{type(refined).__name__}")
            return
        slots = self.slots()
        if (current is None or current.seq != seq or self.shown_seq != seq
                or self.views.seq != seq or self.waiting is not None):
            slots.free_refine(refined.slot)
            return
        current.report = dict(refined.report)
        if not refined.subframes:
            return
        greys = self._slot_arrays(slots, refined, f"view {seq}'s refined frame")
        if greys is None:
            return
        previous = current.slot
        current.region, current.greys, current.slot = refined.region, greys, refined.slot
        if previous is not None and previous != refined.slot:
            slots.free_refine(previous)
        current.index, current.swaps = -1, current.swaps + 1
        self._show_subframe()

    def refine_failed(self, seq: int, error: str) -> None:
        """View `seq`'s refinement failed: an error in status, and its report says so."""
        self.error("frame worker", f"view {seq}: refinement failed: {error}")
        if self.refinement is not None and self.refinement.seq == seq:
            self.refinement.report = {**self.refinement.report, "stop": f"error: {error}"}

    def counted_capture(self, seq: int) -> None:
        """A citl step of view `seq` asked the bench for captures (handed on)."""
        if self.refinement is not None and self.refinement.seq == seq:
            self.refinement.captures += 1

    def emission_ended(self, seq: int, reason: str) -> None:
        """An emission session ended while `seq` was the newest view: the citl run of the view
        on the panel (if it is `seq` or older) ends with it, and status says why."""
        r = self.refinement
        if r is not None and r.tier == "citl" and r.seq <= seq and not r.ended:
            r.ended = reason

    def forget(self, *, crashed: bool = False) -> None:
        """The worker is gone (its slots with it): the frame waiting (counted dropped after a
        crash) and the refinement go too; the panel keeps what it shows (a crash blanks it)."""
        if crashed and self.waiting is not None:
            self.counts.dropped += 1
        self.waiting = self.refinement = None

    # -- the panel -------------------------------------------------------------------------------

    def _show(self, waiting: WaitingFrame) -> None:
        seq, message = waiting.seq, waiting.message
        # One clock (monotonic) for all: the worker's ready_s is CLOCK_MONOTONIC, as is sent_s.
        t0 = self.last_show_s = time.monotonic()
        # A frame that cannot be shown (a region off the panel, arrays that do not fit the
        # slot, the SLM refusing it) is an error in status, not an exception out of the control
        # loop: the panel keeps the frame before it and the daemon keeps running.
        try:
            try:
                panel, rgb = self._panel(message)
            finally:  # copied out (or refused): the worker may write the slot again
                self.slots().release(message.slot)
            # The panel applies the colour mode, and holds the frame back during a capture.
            frame = self.panel().show_view(panel, seq)
        except Exception as exc:
            if waiting.subframes is not None:
                self.slots().free_refine(waiting.subframes.slot)
            self.error("slm", f"showing view {seq}: {type(exc).__name__}: {exc}")
            if isinstance(exc, SLMOutputLost):  # the control loop switches lasers off
                self.slm_lost(str(exc))
            return
        done = time.monotonic()
        self.counts.showed(None if message.ready_s is None else done - message.ready_s,
                           self.refresh_s)
        stages = {**message.timings.seconds(), "output": done - t0}
        timings: dict[str, Any] = {f"{k}_ms": round(v * 1e3, 3) for k, v in stages.items()}
        if waiting.sent_s is not None:
            timings["view_to_slm_ms"] = round((done - waiting.sent_s) * 1e3, 3)
        timings.update(seq=seq, cached=message.cached,
                       clipped_fraction=list(message.clipped_fraction),
                       subframes=1 if waiting.subframes is None else waiting.subframes.subframes)
        self.timings = timings
        self.warnings = list(message.warnings)
        self.last_rgb, self.last_frame = rgb, frame
        self.shown_seq = seq
        view = self.views.view if self.views.seq == seq else None
        quality = view.quality if view is not None else "network"
        self._drop_refinement()
        if quality != "network":
            # A scene's exact frame with no model is the exact tier already: nothing follows.
            done = "exact" if message.tier == quality else ""
            self.refinement = Refinement(seq, quality, {
                "tier": message.tier if done else quality, "iterations": 0, "seconds": 0.0,
                "loss": None, "psnr_db": None, "start_psnr_db": None, "stop": done})
        if waiting.subframes is not None:
            self._cycle_network(seq, waiting.subframes)
        self.shown(seq)

    def _cycle_network(self, seq: int, subframes: RefinedFrame) -> None:
        """View `seq`'s network frame has K subframes: the first is on the panel, the K take
        turns from the next refresh (in the view's refinement when it asked for one, until a
        better frame replaces them)."""
        slots = self.slots()
        greys = self._slot_arrays(slots, subframes, f"view {seq}'s subframes")
        if greys is None:
            return
        if self.refinement is None:
            self.refinement = Refinement(seq, "network", dict(subframes.report))
        r = self.refinement
        r.region, r.greys, r.slot, r.index = subframes.region, greys, subframes.slot, 0

    def _slot_arrays(self, slots: Any, refined: RefinedFrame, what: str) -> np.ndarray | None:
        """`refined`'s subframes (`refined_arrays`), or None with the error reported and its
        slot given back when they cannot be read."""
        try:
            return slots.refined_arrays(refined)
        except ValueError as exc:
            self.error("frame worker", f"{what}: {exc}")
            slots.free_refine(refined.slot)
            return None

    def _panel(self, message: FrameMessage) -> tuple[np.ndarray, np.ndarray | None]:
        """The full panel: the blank frame (the zero pattern of the coding in use) outside the
        coded region; and a copy of the render. Both copied out of the frame's slot."""
        grey, rgb = self.slots().arrays(message)
        panel = self._zero_buffer().frame(message.region.top, message.region.left, grey)
        rgb = None if rgb is None else rgb.copy()
        del grey  # no view into the slot outlives this call
        return panel, rgb

    def _show_subframe(self) -> None:
        """The refinement's next subframe on the panel (the control loop paces them, one per
        refresh): one subframe pasted into a panel of the buffer, straight from its refine
        slot, so a turn of the loop costs one frame whatever K. A panel that refuses it is an
        error in status; the frame before stays."""
        r = self.refinement
        assert r is not None and r.greys is not None and r.region is not None
        r.index = (r.index + 1) % r.subframes
        self.last_show_s = time.monotonic()
        try:
            panel = self._zero_buffer().frame(r.region.top, r.region.left, r.greys[r.index])
            self.last_frame = self.panel().show_view(panel, r.seq)
        except Exception as exc:
            self.error("slm", f"showing view {r.seq}'s refined frame: "
                              f"{type(exc).__name__}: {exc}")
            self._drop_subframes(r)
            if isinstance(exc, SLMOutputLost):
                self.slm_lost(str(exc))

    def _zero_buffer(self) -> PanelBuffer:
        """The panel buffer of the blank frame in use now (rebuilt when the blank changes)."""
        blank = self.panel().blank_frame()
        if self._zero is None or self._zero_of is not blank:
            self._zero, self._zero_of = PanelBuffer(blank, reuse=PANELS_REUSED), blank
        return self._zero

    def _drop_subframes(self, r: Refinement) -> None:
        """Stop showing `r`'s subframes, and give their refine slot back."""
        self.slots().free_refine(r.slot)
        r.greys, r.slot = None, None

    def _drop_refinement(self) -> None:
        """The refinement of the view on the panel is over (a newer view's frame is shown)."""
        if self.refinement is not None:
            self._drop_subframes(self.refinement)
            self.refinement = None

    # -- status ---------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """`status.frames`' counts and pacing: frames shown, dropped and late, the ages, the
        refresh and how the panel keeps to it."""
        c = self.counts
        pacing = f"timer: one frame per refresh at {1 / self.refresh_s:g} Hz (slm.refresh_hz)"
        vsync = self.panel().vsync_detail  # the framebuffer's FBIO_WAITFORVSYNC, or why not
        if vsync:
            pacing += f"; {vsync}"
        return {"frames_shown": c.shown, "frames_dropped": c.dropped,
                "frames_cancelled": c.cancelled, "frames_late": c.late,
                "last_frame_age_ms": (None if c.last_age_s is None
                                      else round(c.last_age_s * 1e3, 3)),
                "max_frame_age_ms": round(c.max_age_s * 1e3, 3),
                "refresh_hz": round(1 / self.refresh_s, 6), "pacing": pacing}

    def refine_status(self, capture: str | None = None) -> dict[str, Any] | None:
        """`status.frames.refine`: the refinement of the view on the panel (None: it asked for
        the network's frame): the worker's report, the tier asked for and the stage running
        (`stage`: a citl view's first steps are sgd's), what it is doing now (`phase`: "sgd
        through the bench model", "citl step 3: capturing green at plane 2 of 3"), the view's
        sequence number, the better frames swapped in and the subframes shown in turn. A citl
        run whose emission session ended says so in `stop` at once ("stopped: lasers off ...").
        `capture`: what the bench does for the capture the worker waits for (None: it waits
        for none; `CaptureRelay.waiting_phase`)."""
        r = self.refinement
        if r is None or r.tier == "network":  # a K-subframe network frame: no refinement
            return None
        out = {**r.report, "tier": r.tier, "stage": r.report.get("tier", r.tier),
               "seq": r.seq, "swaps": r.swaps, "subframes": r.subframes,
               "capture_steps": r.captures}
        if r.ended:
            out["stop"] = f"stopped: {r.ended}"
        out["phase"] = _phase(r, out, capture)
        return out


def _phase(r: Refinement, shown: dict[str, Any], capture: str | None) -> str:
    """What the refinement `r` does now, in a few words ("" once it stopped)."""
    if shown.get("stop"):
        return ""
    if r.tier == "citl" and capture is not None:
        return f"citl step {r.captures}: {capture}"
    stage = shown["stage"]
    if stage == "citl":
        return f"citl step {r.captures}: fitting the captures"
    if shown.get("iterations"):
        return f"{stage} through the bench model"
    return "the view's light-field inversion (its exact target)"
