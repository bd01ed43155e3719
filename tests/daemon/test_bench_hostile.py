"""`nhfd bench hostile` end to end on its cheap scenarios, each on a real `nhfd serve` with the
lasers lit on the twin: the rows carry `laser off` read back dark on the twin's record, no
guardian disarm during the attack, the flood's drops counted, every hostile scene refused naming
its cause; the JSON and the markdown table are written. Figures are not asserted (a benchmark,
not a timed test); facts are."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from nhfd.benchmarks import hostile
from nhfd.benchmarks.machine import describe
from nhfd.cli.main import build_parser
from nhfd.scene.io import read_scene

TIMEOUT_S = 5.0


def bench(tmp_path: Path, scenarios: str, *extra: str) -> tuple[int, dict[str, Any], str]:
    out = tmp_path / "hostile.json"
    args = build_parser().parse_args(["bench", "hostile", "--scenarios", scenarios,
                                      "--duration-s", "1", "--timeout-s", str(TIMEOUT_S),
                                      "--json", str(out), *extra])
    code = args.handler(args)
    return code, json.loads(out.read_text()), out.with_suffix(".md").read_text()


def assert_safe(row: dict[str, Any]) -> None:
    """The facts every scenario must show: lit through the attack, no guardian disarm, the
    daemon alive, `nhfctl laser off` exit 0 through the daemon and the twin dark after it."""
    assert row["daemon_alive"], row.get("log_tail")
    assert row["lit_until_laser_off"] and row["guardian_disarms"] == 0 \
        and row["starvation_disarms"] == 0, row["disarm_reasons"]
    off = row["laser_off"]
    assert off["rc"] == 0 and off["ok"] and off["lit_before"], off
    assert off["switched_off_by"] == "daemon"
    # dark on the twin's record, after the command started, within the time allowed
    assert 0 < off["ms_to_dark"] < TIMEOUT_S * 1e3
    # the status client ran through the attack (every 20 ms for 1 s) and never failed
    assert row["status"]["n"] >= 10 and row["status_failures"] == 0
    assert row["rss_mb"]["start"] > 0 and row["rss_mb"]["peak"] >= row["rss_mb"]["start"]
    assert row["failed"] == []


def table_row(md: str, title: str) -> str:
    (line,) = [x for x in md.splitlines() if x.startswith(f"| {title} |")]
    return line


def test_idle_and_newline_flood_rows_json_and_table(tmp_path):
    code, data, md = bench(tmp_path, "idle,newline-flood")
    assert code == 0
    idle, flood = data["rows"]
    assert (idle["key"], flood["key"]) == ("idle", "newline-flood")
    for row in (idle, flood):
        assert_safe(row)
    assert idle["refused"] == 0 and idle["attack"] == {}
    # Both peers really flooded, and the daemon's input bounds dropped each of them (a peer
    # past daemon.server.max_buffered_bytes is dropped; the attacker reconnects and counts it).
    for peer in ("tcp", "unix"):
        counts = flood["attack"][peer]
        assert counts["mib_sent"] > 1 and counts["dropped"] >= 1, counts
    assert flood["refused"] == sum(flood["attack"][p]["dropped"] + flood["attack"][p]["stalled"]
                                   for p in ("tcp", "unix"))
    # The markdown: the machine and the command above the table, one row per scenario.
    machine = describe()
    first = md.splitlines()[0]
    assert "nhfd bench hostile --scenarios idle,newline-flood --duration-s 1" in first
    assert f"{machine['cpu']}, {machine['cores']} cores" in first
    assert "| scenario | status median / p99 ms | disarms | RSS start / peak MB " \
           "| laser off ok, ms to dark | notes | goals |" in md
    line = table_row(md, flood["scenario"])
    assert f"yes, {flood['laser_off']['ms_to_dark']:.0f} (daemon)" in line
    assert f"tcp: {flood['attack']['tcp']['mib_sent']} MiB sent" in line
    assert data["machine"] == machine and data["failed"] == []


def test_every_hostile_scene_is_refused_naming_its_cause(tmp_path):
    code, data, md = bench(tmp_path, "hostile-scenes", "--bomb-mib", "16")
    assert code == 0
    (row,) = data["rows"]
    assert_safe(row)
    files = row["attack"]["files"]
    assert set(files) == {"bomb.spz", "zstd-2e28.spz", "bomb.sog", "stride0.glb",
                          "in/escape.gltf", "zero.gltf", "4e9.ply"}
    causes = {
        "bomb.spz": "the .spz gzip stream inflates to more than the 45 bytes its 1 Gaussians "
                    "need",
        "zstd-2e28.spz": "the .spz header declares 268,435,456 Gaussians, more than the limit",
        "bomb.sog": "SOG member means_l.webp declares 16,777,216 bytes, more than the",
        "stride0.glb": "count declares 268,435,456 Gaussians, more than the limit",
        "in/escape.gltf": "uri '../outside.bin' resolves to scenes/outside.bin, outside the "
                          "scene's folder",
        "zero.gltf": "uri '/dev/zero' resolves to /dev/zero, outside the scene's folder",
        "4e9.ply": "PLY element 'vertex' declares 4,000,000,000 Gaussians, more than the limit",
    }
    for name, f in files.items():
        assert f["loads"] >= 1 and f["refused"] == f["cause_named"] == f["loads"], (name, f)
        assert f["error"].startswith(f"SceneFileError: scenes/{name}: "), f["error"]
        assert causes[name] in f["error"], f["error"]
    assert row["refused"] == sum(f["loads"] for f in files.values())
    # each file has its row in the per-file table, with its error
    for name, f in files.items():
        assert f"| {name} ({f['what']}) | {f['refused']} of {f['loads']} |" in md


def test_the_glTF_base_of_the_hostile_files_loads_unchanged(tmp_path):
    """The refusals are the hostile change's: the same document without it is a scene."""
    doc, blob = hostile.splat_gltf(3)
    (tmp_path / "ok.glb").write_bytes(hostile.glb(doc, blob))
    assert len(read_scene(tmp_path / "ok.glb").gaussians) == 3


def test_web_scenarios_are_skipped_with_the_reason_without_aiohttp(monkeypatch, tmp_path):
    real = hostile.importlib.util.find_spec
    monkeypatch.setattr(hostile.importlib.util, "find_spec",
                        lambda name, *a: None if name == "aiohttp" else real(name, *a))
    code, data, md = bench(tmp_path, "web-flood")
    (row,) = data["rows"]
    assert code == 0 and row["skipped"].startswith("aiohttp is not installed")
    assert "| web message flood (one token holder) | skipped: aiohttp is not installed" in md


def test_a_failed_row_says_what_failed_in_the_table():
    row = {"scenario": "x", "status": {"n": 50, "median_ms": 0.5, "p99_ms": 250.0,
                                       "max_ms": 300.0},
           "status_failures": 0, "guardian_disarms": 1,
           "disarm_reasons": ["no heartbeat for 0.5 s"], "starvation_disarms": 1,
           "late_heartbeats": 3, "max_heartbeat_gap_ms": 612.0, "lit_until_laser_off": False,
           "rss_mb": {"start": 60.0, "peak": 300.0}, "daemon_alive": True,
           "laser_off": {"rc": 0, "ok": True, "lit_before": False, "switched_off_by": "daemon",
                         "ms_to_dark": 0.0, "stderr": ""},
           "audit_bytes_added": 0, "log_lines_added": 2, "refused": 0, "notes": ""}
    row["failed"] = hostile.safety_failures(row, [])
    row["goals_missed"] = hostile.goals(row, flood=True)
    assert row["failed"] == ["the light went off during the attack (1 guardian disarms: no "
                             "heartbeat for 0.5 s)"]
    # a flood that nothing refused does not waive the p99 goal
    assert row["goals_missed"] == ["disarmed during the attack", "RSS +240 MB",
                                   "status p99 250 ms"]
    line = hostile.table([row]).splitlines()[-1]
    assert line.startswith("| x | 0.5 / 250.0 | 1 (no heartbeat for 0.5 s); 3 late beats, max "
                           "gap 612 ms | 60 / 300 | yes, 0 (daemon), already dark |")
    assert "FAILED: the light went off" in line
    assert line.endswith("| missed: disarmed during the attack, RSS +240 MB, status p99 250 ms |")


@pytest.mark.parametrize("bad", ["frobnicate", ""])
def test_unknown_scenarios_are_refused_naming_the_choices(tmp_path, bad):
    args = build_parser().parse_args(["bench", "hostile", "--scenarios", bad, "--json",
                                      str(tmp_path / "h.json")])
    with pytest.raises(SystemExit, match=r"--scenarios: no scenario .*; one of: idle, "
                                         r"tcp-lockout, newline-flood"):
        args.handler(args)
