"""Frame pacing and the frame counts in status, with a fake frame worker much faster than the
panel's refresh; the framebuffer's FBIO_WAITFORVSYNC; shared-memory slots after a crash.

The fake worker is this module's `worker_main`: the daemon spawns it by name as it spawns the
real one (`FrameLink(worker_module=...)`), so it speaks the real protocol through the real pipe
and slots, without torch. Its frames are instant and filled with their view's sequence number.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from nhfd.calibration import CalibrationStore
from nhfd.config import Config, _overlay
from nhfd.daemon import frame_link, pacing
from nhfd.daemon.frame_link import FrameEvents, FrameLink, LinkState
from nhfd.daemon.panel import Panel
from nhfd.daemon.views import ViewSlot
from nhfd.device_settings import SLMOutputSettings
from nhfd.drivers import framebuffer
from nhfd.drivers.framebuffer import FBIO_WAITFORVSYNC, FramebufferSLM
from nhfd.drivers.slm import SimulatedSLM
from nhfd.frame_message import FrameMessage, Region, StageTimes
from nhfd.views import Orbit, View
from nhfd.worker_messages import (
    FrameDone,
    FrameRequest,
    Loaded,
    LoadModel,
    LoadScene,
    Stop,
    WorkerReady,
)

from .conftest import bench_config, wait_until
from .fake_loads import fake_load

REFRESH_HZ = 10.0  # a slow panel: a loaded test machine keeps to its refreshes with room
# Views the fake worker treats otherwise, by their azimuth: it dies (exit code 3); its frame's
# region runs off the panel (the paste fails); its frame is larger than the slot.
CRASH_DEG, OFF_PANEL_DEG, TOO_BIG_DEG = -111.0, -112.0, -113.0


def orbit(azimuth_deg: float) -> View:
    return View(Orbit(azimuth_deg, 0.0, 1.0))


def worker_main(conn: Any, config_data: dict[str, Any], calibration: Any = None,
                slots: dict[str, Any] | None = None) -> None:
    """A frame worker whose frames take no time: grey = the view's seq (mod 256) in a region of
    half the panel, centred; the azimuths CRASH_DEG, OFF_PANEL_DEG and TOO_BIG_DEG make it die or
    send a frame that cannot be shown."""
    from multiprocessing import shared_memory

    shms = [shared_memory.SharedMemory(name=n) for n in slots["names"]]
    panel_h, panel_w = config_data["slm"]["height_px"], config_data["slm"]["width_px"]
    h, w = panel_h // 2, panel_w // 2
    conn.send(WorkerReady(os.getpid()))
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            return
        if isinstance(msg, Stop):
            return
        if isinstance(msg, LoadModel | LoadScene):
            conn.send(Loaded(msg.req_id, fake_load(msg)))
            continue
        assert isinstance(msg, FrameRequest)
        seq, view, slot = msg.seq, msg.view, msg.slot
        azimuth = view.camera.azimuth_deg
        if azimuth == CRASH_DEG:
            os._exit(3)
        np.ndarray((3, h, w), np.uint8, buffer=shms[slot].buf)[...] = seq % 256
        region = Region(h // 2, w // 2, h, w, 0, 0)
        if azimuth == OFF_PANEL_DEG:
            region = Region(panel_h - 2, panel_w - 2, h, w, 0, 0)
        elif azimuth == TOO_BIG_DEG:
            region = Region(0, 0, 4 * panel_h, 4 * panel_w, 0, 0)
        message = FrameMessage(region, (3, region.height, region.width), None, StageTimes(),
                               (0.0, 0.0, 0.0), slot=slot, ready_s=time.monotonic())
        conn.send(FrameDone(seq, message))


class Host:
    """The slice of the daemon a FrameLink uses, on a simulated SLM that keeps its write times."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.views = ViewSlot()
        self.slm = SimulatedSLM(config.slm.width_px, config.slm.height_px,
                                SLMOutputSettings(history_frames=10000)).open()
        self.calibration = CalibrationStore.of(config)
        self.panel = Panel(config, SimpleNamespace(slm=self.slm, errors={"slm": None}),
                           self.calibration)
        self.errors: list[str] = []

    def error(self, source: str, message: str) -> None:
        self.errors.append(f"{source}: {message}")

    def events(self) -> FrameEvents:
        return FrameEvents(shown=self.views.mark_applied, error=self.error,
                           crashed=lambda message: self.error("frame worker", message),
                           slm_lost=lambda detail: self.error("slm", detail))


def running_link(root: Path) -> tuple[Host, FrameLink]:
    base = bench_config(root, None)
    config = Config.model_validate(_overlay(base.model_dump(), {"slm": {"refresh_hz": REFRESH_HZ}}))
    host = Host(config)
    link = FrameLink(config, host.calibration, host.views, lambda: host.panel, host.events(),
                     worker_module=__name__)
    link.loads.model_path, link.loads.scene_path = "fake.onnx", "fake.ply"
    link.start()
    deadline = time.monotonic() + 20
    while link.state != LinkState.RUNNING:
        link.step()
        time.sleep(0.01)
        assert time.monotonic() < deadline, "the fake worker did not start"
    return host, link




def step_until(link: FrameLink, until_s: float, submit: Any = None) -> None:
    """The daemon's loop: step, then sleep until the link's wake time (or the next request)."""
    while time.monotonic() < until_s:
        if submit is not None:
            submit()
        link.step()
        time.sleep(max(0.0, min(0.002, link.wake_s - time.monotonic())))


def test_frames_faster_than_the_refresh_are_paced_fresh_and_counted(short_dir, our_segments):
    host, link = running_link(short_dir)
    period_s = 1 / REFRESH_HZ
    sent: list[tuple[int, int | None]] = []  # (slot named in a request, slot the daemon holds)
    send = link.worker.send

    def spy(msg: Any) -> None:
        if isinstance(msg, FrameRequest):
            sent.append((msg.slot, None if link.waiting is None else link.waiting.message.slot))
        send(msg)

    link.worker.send = spy
    show_starts: list[float] = []  # when each frame began to go out (what pacing schedules)
    show = link.pacer._show

    def timed_show(*args: Any) -> None:
        show(*args)
        show_starts.append(link.last_show_s)

    link.pacer._show = timed_show
    try:
        start = time.monotonic()
        views = iter(range(1, 100000))
        step_until(link, start + 1.2,
                   lambda: host.views.submit(orbit(float(next(views) % 360))))
        last = host.views.seq
        step_until(link, time.monotonic() + 3 * period_s)
        elapsed = time.monotonic() - start
        s = link.status()
        written = np.array(host.slm.written_s)
        # The last view requested is the one on the panel, its seq in every grey level.
        assert link.shown_seq == last
        top, left, h, w = 36 // 4, 64 // 4, 36 // 2, 64 // 2
        assert np.all(host.slm.last_frame[:, top:top + h, left:left + w] == last % 256)
        # At most one frame per refresh: the shown count is bounded by the refreshes, and no two
        # frames begin to go out closer than a refresh (less the loop's wake-up slack). The
        # panel write follows after the region is pasted into the panel, whose time varies
        # (0.7 ms once on an idle 2-core machine), so the writes are only checked to be far
        # from back to back: unpaced, these requests would write every few ms.
        assert s["frames_shown"] == len(written) == len(show_starts) >= 5
        assert s["frames_shown"] <= elapsed / period_s + 1
        assert np.diff(show_starts).min() >= period_s - pacing.DUE_SLACK_S
        assert np.diff(written).min() >= 0.9 * period_s
        # Every view is shown or dropped by latest wins (overtaken before it was computed):
        # views were requested ~500 times faster than the panel shows them.
        assert s["frames_shown"] + s["frames_dropped"] == last
        assert s["frames_dropped"] > 10 * s["frames_shown"]
        # No frame shown is older than one refresh: the view goes out just in time for its
        # refresh, not a refresh early.
        assert s["frames_late"] == 0 and s["max_frame_age_ms"] <= period_s * 1e3
        assert s["refresh_hz"] == REFRESH_HZ and "10 Hz" in s["pacing"]
        # The daemon never names a slot it still holds.
        assert sent and all(named != held for named, held in sent)
    finally:
        link.close()
    assert our_segments() == []


def test_a_crashed_worker_leaves_no_shared_memory_and_its_successor_gets_new_slots(
        short_dir, monkeypatch, our_segments):
    monkeypatch.setattr(frame_link, "RESTART_BACKOFF_S", 0.0)
    host, link = running_link(short_dir)
    try:
        first = our_segments()
        # One frame slot: the link holds one frame at a time (in the worker or waiting for its
        # refresh), so a second would never be needed (each is the panel's size); and the three
        # refine slots a refinement's better frames and a K-subframe model's take turns in.
        assert len(first) == frame_link.SLOTS + frame_link.REFINE_SLOTS == 4
        host.views.submit(orbit(CRASH_DEG))
        wait_until(lambda: (link.step(), link.state == LinkState.CRASHED)[1], 10, "the crash")
        assert our_segments() == []  # unlinked with the crashed worker
        assert any("died with exit code 3" in e for e in host.errors)
        wait_until(lambda: (link.step(), link.state == LinkState.RUNNING)[1], 20, "the restart")
        second = our_segments()
        assert len(second) == len(first) and not set(second) & set(first)
        seq = host.views.submit(orbit(0.0))
        wait_until(lambda: (link.step(), link.shown_seq == seq)[1], 10, "a frame after it")
    finally:
        link.close()
    assert our_segments() == []


def test_a_frame_that_cannot_be_shown_is_an_error_and_the_next_one_is_shown(short_dir,
                                                                          our_segments):
    # Each bad frame reaches `_show` through the real pipe and slot: its region runs off the
    # panel (PanelBuffer's paste raises ValueError), or its arrays are larger than the slot
    # (reading them out raises TypeError). Either must land in status as an "slm" error naming
    # the view, give the slot back and leave the panel as it was, with the control loop's step
    # returning normally.
    host, link = running_link(short_dir)
    panel_h, panel_w = host.config.slm.height_px, host.config.slm.width_px
    try:
        good = host.views.submit(orbit(1.0))
        wait_until(lambda: (link.step(), link.shown_seq == good)[1], 10, "the first frame")
        before = host.slm.last_frame
        count = host.slm.count
        for bad, raised in ((OFF_PANEL_DEG, "ValueError"), (TOO_BIG_DEG, "TypeError")):
            bad_seq = host.views.submit(orbit(bad))
            wait_until(lambda s=bad_seq: (link.step(), link.sent_seq == s
                                          and link.inflight is None and link.waiting is None)[1],
                       10, f"view {bad_seq} tried")
            errors = [e for e in host.errors if f"view {bad_seq}" in e]
            assert len(errors) == 1 and errors[0].startswith(
                f"slm: showing view {bad_seq}: {raised}"), host.errors
            assert link.worker.free_slots == list(range(frame_link.SLOTS))
            assert link.shown_seq == good and host.slm.count == count
            assert np.array_equal(host.slm.last_frame, before)
            assert link.state == LinkState.RUNNING
            good = host.views.submit(orbit(3.0))
            wait_until(lambda s=good: (link.step(), link.shown_seq == s)[1], 10, "a good frame")
            top, left = panel_h // 4, panel_w // 4
            assert np.all(host.slm.last_frame[:, top, left] == good % 256)
            before, count = host.slm.last_frame, host.slm.count
    finally:
        link.close()
    assert our_segments() == []


def test_closing_forgets_a_frame_waiting_for_its_refresh(short_dir, monkeypatch, our_segments):
    # A view sent well before its refresh (a wide send margin): its frame waits as `waiting`.
    # Its slot is unlinked with the worker on close, so the link must not keep it, nor wake
    # the loop for it.
    monkeypatch.setattr(pacing, "SEND_MARGIN_S", 0.08)
    host, link = running_link(short_dir)
    try:
        first = host.views.submit(orbit(1.0))
        wait_until(lambda: (link.step(), link.shown_seq == first)[1], 10, "the first frame")
        waiting = host.views.submit(orbit(2.0))
        wait_until(lambda: (link.step(), link.waiting is not None)[1], 10, "a waiting frame")
        assert link.waiting.seq == waiting and link.wake_s < math.inf
    finally:
        link.close()
    assert link.waiting is None and link.wake_s == math.inf
    assert our_segments() == []


# -- the framebuffer's vertical blank ------------------------------------------------------------


def fake_framebuffer(root: Path, width: int, height: int) -> SLMOutputSettings:
    fb = root / "sys" / "class" / "graphics" / "fb1"
    fb.mkdir(parents=True)
    (fb / "virtual_size").write_text(f"{width},{height}\n")
    (fb / "bits_per_pixel").write_text("32\n")
    (fb / "stride").write_text(f"{width * 4}\n")
    (root / "dev").mkdir()
    (root / "dev" / "fb1").write_bytes(b"\0" * width * 4 * height)
    return SLMOutputSettings(framebuffer_device=str(root / "dev" / "fb1"),
                             sysfs_root=str(root / "sys"))


def test_fbio_waitforvsync_is_the_linux_ioctl_number():
    # _IOW('F', 0x20, __u32): direction write (1) << 30 | size 4 << 16 | 'F' << 8 | 0x20.
    assert FBIO_WAITFORVSYNC == (1 << 30) | (4 << 16) | (ord("F") << 8) | 0x20 == 0x40044620


def test_framebuffer_waits_for_the_vertical_blank_before_each_write_where_offered(tmp_path,
                                                                               monkeypatch):
    fb = tmp_path / "dev" / "fb1"
    waits: list[tuple[int, bytes, int]] = []  # (request, argument, first byte when it waited)

    def ioctl(fd: int, request: int, arg: bytes) -> bytes:
        waits.append((request, arg, fb.read_bytes()[0]))
        return arg

    monkeypatch.setattr(framebuffer.fcntl, "ioctl", ioctl)
    settings = fake_framebuffer(tmp_path, 4, 2)
    with FramebufferSLM(4, 2, settings) as slm:
        assert "waits for the vertical blank" in slm.vsync_detail
        slm.show(np.full((2, 4), 7, np.uint8))
        slm.show(np.full((2, 4), 9, np.uint8))
    # Asked once at open, then before each write (the panel still showing the previous frame),
    # always FBIO_WAITFORVSYNC on CRTC 0.
    assert [w[2] for w in waits] == [0, 0, 7]
    assert all(w[:2] == (0x40044620, b"\0\0\0\0") for w in waits)
    assert fb.read_bytes()[:4] == bytes([9, 9, 9, 0xFF])


def test_a_framebuffer_without_fbio_waitforvsync_falls_back_and_says_so(tmp_path, monkeypatch):
    # A regular file stands in for /dev/fb1: the ioctl fails with ENOTTY, as on fbdev drivers
    # that do not implement it.
    asked: list[int] = []
    ioctl = framebuffer.fcntl.ioctl
    monkeypatch.setattr(framebuffer.fcntl, "ioctl",
                        lambda fd, request, arg: (asked.append(request), ioctl(fd, request, arg)))
    settings = fake_framebuffer(tmp_path, 4, 2)
    with FramebufferSLM(4, 2, settings) as slm:
        assert "has no FBIO_WAITFORVSYNC (ENOTTY)" in slm.vsync_detail
        slm.show(np.full((2, 4), 5, np.uint8))
        slm.show(np.full((2, 4), 5, np.uint8))
    assert asked == [FBIO_WAITFORVSYNC]  # once, at open: the writes do not ask again
    assert (tmp_path / "dev" / "fb1").read_bytes()[:4] == bytes([5, 5, 5, 0xFF])
