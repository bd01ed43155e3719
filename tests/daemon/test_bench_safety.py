"""`nhfd bench safety` end to end on one fault: a real `nhfd serve`, SIGTERM, the time to dark
taken from the laser twin's record; the table and the JSON carry it; the fuzz figure counts
every reply."""

from __future__ import annotations

import json

from nhfd.benchmarks import safety
from nhfd.cli.main import build_parser


def test_sigterm_trial_table_json_and_fuzz(tmp_path, capsys):
    out = tmp_path / "safety.json"
    args = build_parser().parse_args(["bench", "safety", "--faults", "SIGTERM daemon",
                                      "--repeats", "1", "--timeout-s", "5", "--fuzz", "300",
                                      "--json", str(out)])
    assert args.handler(args) == 0
    data = json.loads(out.read_text())
    (row,) = data["faults"]
    assert row["fault"] == "SIGTERM daemon" and row["all_off"] is True
    (ms,) = row["times_ms"]
    # A real measurement: dark after the signal was sent, well inside the 5 s allowed.
    assert 0 < ms < 5000 and row["median_ms"] == row["max_ms"] == ms
    printed = capsys.readouterr().out
    assert f"| SIGTERM daemon | 1 | {ms:.1f} | {ms:.1f} | yes |" in printed
    fuzz = data["fuzz"]
    lines, expected = safety.bad_requests(300, 7, 65536)
    assert fuzz["requests"] == len(lines) and fuzz["replies"] == fuzz["replies_expected"] \
        == expected
    assert fuzz["all_errors"] and fuzz["state_unchanged"] and fuzz["max_emitted_pct"] == 0.0


def test_a_channel_never_dark_is_a_failure_row():
    rows = [{"fault": "SIGSTOP guardian", "times_ms": [None, 812.5], "timeout_s": 5.0,
             "all_off": False, "median_ms": 812.5, "max_ms": None}]
    assert safety.table(rows).splitlines()[-1] == \
        "| SIGSTOP guardian | 2 | 812.5 | - | no: 1 not off within 5 s |"
