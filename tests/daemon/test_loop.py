"""The control loop's scheduling: idle, it sleeps in select until the next heartbeat (one per
`daemon.arming.heartbeat_s`, however many requests woke it); a request or the frame worker's pipe
wakes it at once. Facts about the schedule, not CPU figures (those are `nhfd bench load`'s idle
phase)."""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import socket
import threading
import time
from types import SimpleNamespace

import pytest

from nhfd.daemon.service import Daemon
from nhfd.worker_messages import FrameFailed

from .conftest import bench_config

STATUS = b'{"jsonrpc":"2.0","method":"status","id":1}\n'


@pytest.fixture
def stepped(short_dir, mecom_twin):
    """A started daemon whose loop the test steps by hand; heartbeats and poll timeouts
    recorded."""
    d = Daemon(bench_config(short_dir, mecom_twin), base_dir=short_dir, env={},
               handle_signals=False)
    d.start()
    beats: list[float] = []
    timeouts: list[float] = []
    real_beat, real_poll = d.laser.heartbeat, d.server.poll

    def beat(now: float) -> None:
        beats.append(now)
        real_beat(now)

    def poll(timeout_s: float):
        timeouts.append(timeout_s)
        return real_poll(timeout_s)

    d.laser.heartbeat, d.server.poll = beat, poll
    try:
        yield SimpleNamespace(d=d, beats=beats, timeouts=timeouts)
    finally:
        d.request_shutdown("test over")
        d.close()


def test_idle_the_loop_sleeps_until_the_next_heartbeat(stepped):
    d, beats = stepped.d, stepped.beats
    tick = d.config.daemon.arming.heartbeat_s
    d.step(d.wait_s(time.monotonic()))  # the first heartbeat is due at once
    assert len(beats) == 1
    now = time.monotonic()
    wait = d.wait_s(now)
    # Nothing due but the heartbeat: the select timeout is exactly the time left to it.
    assert wait == pytest.approx(beats[0] + tick - now, abs=1e-9)
    assert 0 < wait <= tick
    d.step(wait)  # nothing wakes it: it sleeps through to the deadline
    assert len(beats) == 2
    assert stepped.timeouts[-1] == wait
    assert beats[1] - beats[0] >= tick


def test_a_request_is_answered_at_once_and_sends_no_extra_heartbeat(stepped):
    d, beats = stepped.d, stepped.beats
    tick = d.config.daemon.arming.heartbeat_s
    d.step(0.0)
    assert len(beats) == 1
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(5)
        s.connect(str(d.socket_path))
        d.step(d.wait_s(time.monotonic()))  # the connection wakes it: accepted
        s.sendall(STATUS)
        t0 = time.monotonic()
        d.step(30.0)  # a long sleep, woken by the request
        took = time.monotonic() - t0
        assert b'"result"' in s.recv(1 << 20)
    assert took < 15  # not the 30 s it would sleep if the socket did not wake it
    # Request wake-ups are not heartbeats: still one (the old loop beat on every wake-up).
    assert len(beats) == 1
    now = time.monotonic()
    assert d.wait_s(now) == pytest.approx(max(0.0, beats[0] + tick - now), abs=1e-9)


def test_the_frame_workers_pipe_wakes_the_loop_and_leaves_the_selector_when_not_drained(
        stepped):
    d = stepped.d
    here, there = mp.Pipe(duplex=True)
    frames = d.frames
    frames.worker.conn = here
    frames.worker.process = SimpleNamespace(is_alive=lambda: True, exitcode=None, pid=1)
    frames.state = "running"
    d.step(0.0)
    fd = here.fileno()
    assert fd in d.server.selector.get_map()
    there.send(FrameFailed(7, "a message from the worker"))
    t0 = time.monotonic()
    d.step(30.0)  # woken by the pipe, and the message collected in the same step
    assert time.monotonic() - t0 < 15
    assert d.errors.entries()[-1]["message"] == "view 7: a message from the worker"
    # A crashed worker's pipe (end of file nobody drains) leaves the selector, or every
    # select would return at once.
    frames.state = "crashed"
    frames._restart_at = time.monotonic() + 3600
    d.step(0.0)
    assert fd not in d.server.selector.get_map()
    there.close()
    frames.state, frames.worker.process = "idle", None
    here.close()


def test_a_signal_wakes_the_sleeping_loop(short_dir, mecom_twin):
    """Python retries a select a signal interrupted: without the wake-up socket, SIGTERM would
    wait for the next heartbeat (or a whole tick before)."""
    d = Daemon(bench_config(short_dir, mecom_twin), base_dir=short_dir, env={},
               handle_signals=True)  # this test runs in the main thread, as `nhfd serve` does
    old = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    try:
        d.start()
        d.step(0.0)
        killer = threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGTERM))
        killer.start()
        t0 = time.monotonic()
        d.step(20.0)
        assert time.monotonic() - t0 < 10  # not the 20 s it would sleep
        assert d.stopping and d._shutdown_reason == "signal SIGTERM"
        killer.join()
    finally:
        d.close()
        signal.signal(signal.SIGTERM, old[0])
        signal.signal(signal.SIGINT, old[1])
    assert signal.set_wakeup_fd(-1) == -1  # close() gave the wake-up fd back
