"""The job runner publishes a job's end state only after its finish hook has recorded it."""

from __future__ import annotations

import time

from nhfd.daemon.jobs import Job, JobRunner


def _fail(_job: Job) -> None:
    raise ValueError("bad file")


def test_a_failed_state_is_seen_only_after_the_hook_recorded_it():
    recorded: list[tuple[str, str | None]] = []

    def hook(job: Job, state: str, error: str | None) -> None:
        time.sleep(0.2)  # a slow audit write: a client polls meanwhile
        recorded.append((state, error))

    runner = JobRunner("test", on_finish=hook)
    job = runner.submit(Job("load", {}, _fail))
    deadline = time.monotonic() + 5
    while job.state not in ("done", "failed", "cancelled") and time.monotonic() < deadline:
        time.sleep(0.005)
    assert job.state == "failed"
    assert recorded == [("failed", "ValueError: bad file")]  # already there when state is seen
    assert job.error == "ValueError: bad file" and job.done.wait(1)
    assert runner.get(job.id) is job
    runner.close()


def test_a_hook_that_raises_still_ends_the_job():
    def hook(job: Job, state: str, error: str | None) -> None:
        raise RuntimeError("audit disk full")

    runner = JobRunner("test", on_finish=hook)
    job = runner.submit(Job("load", {}, lambda _j: 42))
    assert job.done.wait(5)
    assert job.state == "done" and job.result == 42 and job.error is None
    runner.close()
