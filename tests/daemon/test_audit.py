"""The audit log under a flood of refused requests: compact, summarised with exact counts,
rotated by size; accepted laser changes still written in full."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from nhfd.daemon.audit import PARAMS_CHARS, AuditLog
from nhfd.daemon.server import Connection

from .conftest import Running, bench_config


def _lines(run_dir: Path) -> list[dict]:
    files = sorted(run_dir.glob("audit.jsonl*"), key=lambda p: -len(p.suffixes[-1]))
    return [json.loads(x) for f in files for x in f.read_text().splitlines()]


def test_twenty_thousand_refusals_stay_under_the_limit_with_exact_counts(short_dir, mecom_twin):
    max_bytes, backups = 65536, 1
    r = Running(bench_config(short_dir, mecom_twin,
                             audit={"max_bytes": max_bytes, "backups": backups}), short_dir)
    sent = {("focus", -32602): 0, ("laser", -32602): 0}
    pad = "x" * 2000  # what a client sends to fill the disk
    try:
        for i in range(20_000):
            # a different caller each time: summaries must not be per connection
            conn = Connection(None, "unix", {"uid": 1000, "pid": 10_000 + i})  # type: ignore[arg-type]
            if i % 4:
                msg = {"jsonrpc": "2.0", "id": i, "method": "focus",
                       "params": {"z_mm": 1e9, "pad": pad}}
            else:
                msg = {"jsonrpc": "2.0", "id": i, "method": "laser",
                       "params": {"action": "blast", "pad": pad}}
            reply = r.daemon.dispatcher.handle_message(conn, msg)
            assert reply["error"]["code"] == -32602
            sent[(msg["method"], -32602)] += 1
        conn = Connection(None, "unix", {"uid": 1000, "pid": 1})  # type: ignore[arg-type]
        reply = r.daemon.dispatcher.handle_message(conn, {"jsonrpc": "2.0", "id": 0,
                                                          "method": "laser",
                                                          "params": {"action": "off"}})
        assert reply["result"] == {"armed": False, "all_off": True}
    finally:
        r.stop()
    run_dir = short_dir / "run"
    assert sum(p.stat().st_size for p in run_dir.glob("audit.jsonl*")) <= max_bytes * (1 + backups)
    audit = _lines(run_dir)
    counted = dict.fromkeys(sent, 0)
    for a in audit:
        method = a["what"].removesuffix(" (refusals summary)")
        if "code" not in a or (method, a["code"]) not in counted:
            continue
        if a["what"].endswith("(refusals summary)"):
            assert a["outcome"] == f"{a['count']} more like this"
            counted[(method, a["code"])] += a["count"]
        else:
            assert a["outcome"].startswith("refused: invalid_params")
            assert isinstance(a["params"], str) and len(a["params"]) < PARAMS_CHARS + 40
            counted[(method, a["code"])] += 1
    assert counted == sent == {("focus", -32602): 15_000, ("laser", -32602): 5_000}
    off = [a for a in audit if a["what"] == "laser" and a.get("outcome") == "ok"]
    assert len(off) == 1 and off[0]["params"] == {"action": "off"}
    assert off[0]["result"] == {"armed": False, "all_off": True}
    assert off[0]["who"] == {"transport": "unix", "uid": 1000, "pid": 1}


def test_rotation_by_size_keeps_every_line_whole_and_the_newest(tmp_path):
    path = tmp_path / "audit.jsonl"
    log = AuditLog(path, summary_s=1.0, max_bytes=4096, backups=2)
    for i in range(300):
        log.write({"who": "test"}, "laser", params={"action": "off", "n": i}, outcome="ok")
    log.close()
    files = [path.with_name("audit.jsonl.2"), path.with_name("audit.jsonl.1"), path]
    assert sorted(tmp_path.iterdir()) == sorted(files)
    assert all(0 < f.stat().st_size <= 4096 for f in files)
    numbers = [json.loads(x)["params"]["n"] for f in files for x in f.read_text().splitlines()]
    assert numbers == list(range(numbers[0], 300))  # contiguous, ending on the last write
    assert numbers[0] > 0  # the oldest were dropped, not the newest


def test_a_short_refusal_keeps_its_params_and_repeats_count_after_the_window(tmp_path):
    path = tmp_path / "audit.jsonl"
    log = AuditLog(path, summary_s=3600, max_bytes=2**20, backups=1)
    who = {"transport": "tcp", "peer": "127.0.0.1:5"}
    for _ in range(5):
        log.refused(who, "laser", 1003, "forbidden", "arming is accepted only over the Unix "
                    "socket", {"action": "arm", "duration_s": 30.0})
    log.close()
    first, summary = (json.loads(x) for x in path.read_text().splitlines())
    assert first["params"] == {"action": "arm", "duration_s": 30.0}
    assert first["outcome"] == ("refused: forbidden: arming is accepted only over the Unix "
                                "socket")
    assert summary["what"] == "laser (refusals summary)" and summary["count"] == 4
    assert summary["outcome"] == "4 more like this" and summary["code"] == 1003


def test_an_internal_error_is_audited_with_its_params_cut_short(running, monkeypatch):
    from nhfd.daemon.methods import METHODS, Method

    def boom(d, conn, p):
        raise RuntimeError("bug")

    monkeypatch.setitem(METHODS, "focus", Method(boom, audited=True))
    conn = Connection(None, "unix", {"uid": 1000, "pid": 7})  # type: ignore[arg-type]
    reply = running.daemon.dispatcher.handle_message(conn, {"jsonrpc": "2.0", "id": 1,
                                                            "method": "focus",
                                                            "params": {"pad": "y" * 100_000}})
    assert reply["error"]["code"] == -32603
    running.stop()
    lines = _lines(running.daemon.runtime_dir)
    (line,) = [a for a in lines if a["what"] == "focus"]
    assert line["outcome"] == "internal error: bug"
    assert line["params"].startswith('{"pad": "yyy') and line["params"].endswith("(100011 chars)")


def test_a_line_over_the_limit_keeps_the_history_and_a_failed_write_raises(tmp_path):
    # Why the rotation is not logging.handlers.RotatingFileHandler (nhfd.daemon.audit): on
    # Python 3.11 that handler rotates an empty file for such a line (here: a daemon starting on
    # an emptied audit.jsonl), pushing the oldest backup out, and it swallows a failed write.
    path = tmp_path / "audit.jsonl"
    path.with_name("audit.jsonl.1").write_text('{"what": "old"}\n')
    path.write_text("")
    log = AuditLog(path, summary_s=1.0, max_bytes=4096, backups=2)
    log.write({"who": "test"}, "big", pad="x" * 5000)
    log.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["audit.jsonl", "audit.jsonl.1"]
    assert path.with_name("audit.jsonl.1").read_text() == '{"what": "old"}\n'
    assert [json.loads(x)["what"] for x in path.read_text().splitlines()] == ["big"]

    class Full:
        def write(self, text: str) -> int:
            raise OSError(28, "No space left on device")

    log = AuditLog(tmp_path / "b.jsonl", summary_s=1.0, max_bytes=4096, backups=1)
    log._file = Full()  # type: ignore[assignment]
    with pytest.raises(OSError, match="No space left"):
        log.write({"who": "test"}, "laser", outcome="ok")
