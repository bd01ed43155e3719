"""The flat [daemon] keys before the sections: a lab's old file still loads, each old key read
from its old place with one warning naming its new one; `nhfd config check` prints the file
migrated; the one table (`DAEMON_KEYS_MOVED`) is the docs' table."""

from __future__ import annotations

import re
import tomllib
import warnings
from pathlib import Path
from typing import Any

import pytest

from nhfd.cli.main import main
from nhfd.config import (
    DAEMON_KEYS_MOVED,
    Config,
    ConfigError,
    ConfigMigrationWarning,
    DaemonSettings,
    default_text,
    load_config,
    migrate_daemon_keys,
    toml_text,
)

REPO = Path(__file__).resolve().parents[1]

# A valid value other than the default for every key that moved, by its new dotted key under
# [daemon] (the heartbeat within a quarter of the guardian's 0.5 s timeout, the frame window
# inside the 1920 x 1080 panel, a loopback host other than the default one).
NON_DEFAULT: dict[str, Any] = {
    "server.runtime_dir": "/run/lab-nhfd", "server.socket_group": "optics",
    "server.tcp_port": 7700, "server.tcp_token_file": "lab.token", "server.tcp_host": "::1",
    "server.tls_cert": "bench.pem", "server.tls_key": "bench.key",
    "server.max_line_bytes": 4096, "server.max_clients": 8, "server.max_batch": 0,
    "server.max_tcp_clients": 3, "server.max_unauthenticated": 2, "server.auth_timeout_s": 2.5,
    "server.max_buffered_bytes": 65536, "server.lines_per_poll": 7, "server.tick_budget_s": 0.02,
    "arming.users": ["alice"], "arming.groups": ["optics"], "arming.confirm": "serial",
    "arming.confirm_timeout_s": 30.0, "arming.confirm_port": "simulated",
    "arming.confirm_line": "dsr", "arming.remote_emission": True, "arming.guardian": "connect",
    "arming.heartbeat_s": 0.05, "arming.laser_refresh_s": 2.0,
    "frames.model": "models/lab.onnx", "frames.size_px": [800, 600],
    "frames.allow_unchecked_sizes": True, "frames.cache_frames": 3, "frames.worker_threads": 5,
    "frames.worker_threading_layer": "workqueue",
    "frames.onnx_providers": ["CUDAExecutionProvider", "CPUExecutionProvider"],
    "frames.int8": "never", "frames.transport": "pickle", "frames.colour_mode": "single",
    "frames.single_colour": "red", "frames.device": "cpu", "frames.engine_cache_dir": "trt",
    "frames.inference": "torch", "frames.cuda_graphs": False,
    "audit.file": "lab-audit.jsonl", "audit.max_bytes": 8192, "audit.backups": 2,
    "audit.summary_s": 5.0, "audit.log_format": "json", "audit.record": "session.jsonl",
    "paths.scene": "scenes/lab.ply", "paths.scene_dirs": ["lab-scenes"],
    "paths.model_dirs": ["lab-models"], "paths.snapshot_dir": "shots",
    "paths.pattern_dirs": ["patterns"], "paths.max_gaussians": 1000,
    "paths.scene_memory_mb": 512, "paths.model_memory_mb": 256, "paths.jobs_kept": 4,
    "paths.open_files": 1024,
    "bench.stage_at_reference_mm": 10.0, "bench.focus_range_mm": [-4.0, 4.0],
    "bench.navigator_period_s": 0.1, "bench.camera_roi_px": [0, 0, 16, 16],
}
# What a key needs beside it to validate, set at its new place (a certificate needs its key).
COMPANIONS = {"server.tls_cert": {"tls_key": "bench.key"},
              "server.tls_key": {"tls_cert": "bench.pem"}}


def _get(config: Config, dotted: str) -> Any:
    value: Any = config.daemon
    for part in dotted.split("."):
        value = getattr(value, part)
    return value


def _write(tmp_path: Path, text: str, name: str = "lab.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _load(path: Path) -> tuple[Any, list[warnings.WarningMessage]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded = load_config(path, env={})
    return loaded, [w for w in caught if issubclass(w.category, ConfigMigrationWarning)]


def _old_file(old: str, value: Any) -> str:
    """A file setting `old` under [daemon], with what its new key needs beside it."""
    section = DAEMON_KEYS_MOVED[old].split(".")[0]
    extra = COMPANIONS.get(DAEMON_KEYS_MOVED[old], {})
    return toml_text({"daemon": {old: value, **({section: extra} if extra else {})}})


# Keys that came after the flat [daemon] layout: no old place to migrate from.
ADDED_SINCE = {"frames.allow_other_bench"}


def test_the_table_maps_every_old_key_once_onto_a_field_of_its_section():
    sections = {name for name in DaemonSettings.model_fields if name != "web"}
    assert len(set(DAEMON_KEYS_MOVED.values())) == len(DAEMON_KEYS_MOVED) == 61
    for old, new in DAEMON_KEYS_MOVED.items():
        section, name = new.split(".")
        assert section in sections, new
        assert name in DaemonSettings.model_fields[section].annotation.model_fields, new
        assert old not in DaemonSettings.model_fields, old  # no old key is a section's name
    # every field of every section came from the flat layout, but those added since it
    every = {f"{s}.{f}" for s in sections
             for f in DaemonSettings.model_fields[s].annotation.model_fields} - ADDED_SINCE
    assert every == set(DAEMON_KEYS_MOVED.values())
    # the test's own values are what they claim: one per key, none the default
    assert set(NON_DEFAULT) == every
    for new, value in NON_DEFAULT.items():
        assert _get(Config(), new) != value, new


@pytest.mark.parametrize("old", sorted(DAEMON_KEYS_MOVED))
def test_an_old_key_loads_into_its_new_place_with_one_warning_naming_both(tmp_path, old):
    new = DAEMON_KEYS_MOVED[old]
    path = _write(tmp_path, _old_file(old, NON_DEFAULT[new]))
    loaded, caught = _load(path)
    assert _get(loaded.config, new) == NON_DEFAULT[new]
    assert [str(w.message) for w in caught] == [
        f"{path}: daemon.{old} is now daemon.{new}; read from its old place (nhfd config check "
        "prints the file migrated)"]
    assert loaded.migrations == ((f"daemon.{old}", f"daemon.{new}"),)
    # where the value came from, under its new key; the old key is no key of the configuration
    assert loaded.sources[f"daemon.{new}"] == str(path)
    assert f"daemon.{old}" not in loaded.sources
    # the same configuration as the file written with the new key
    section, name = new.split(".")
    extra = COMPANIONS.get(new, {})
    modern = _write(tmp_path, toml_text({"daemon": {section: {name: NON_DEFAULT[new], **extra}}}),
                    "modern.toml")
    again, none = _load(modern)
    assert again.config == loaded.config and not none and again.migrations == ()


def test_a_file_of_every_old_key_warns_for_each_and_sources_name_only_new_keys(tmp_path):
    text = toml_text({"daemon": {old: NON_DEFAULT[new] for old, new in DAEMON_KEYS_MOVED.items()}})
    path = _write(tmp_path, text)
    loaded, caught = _load(path)
    assert len(caught) == len(loaded.migrations) == len(DAEMON_KEYS_MOVED)
    assert {k for k, v in loaded.sources.items() if v == str(path)} == {
        f"daemon.{new}" for new in DAEMON_KEYS_MOVED.values()}
    for old, new in DAEMON_KEYS_MOVED.items():
        assert _get(loaded.config, new) == NON_DEFAULT[new]
        assert f"daemon.{old}" not in loaded.sources


def _leaf_keys(data: dict[str, Any], prefix: str = "") -> list[str]:
    out = []
    for key, value in data.items():
        if isinstance(value, dict) and value:
            out += _leaf_keys(value, f"{prefix}{key}.")
        else:
            out.append(f"{prefix}{key}")
    return out


@pytest.mark.parametrize("old", sorted(DAEMON_KEYS_MOVED))
def test_a_key_at_both_its_old_and_its_new_place_is_refused_naming_both(tmp_path, old):
    new = DAEMON_KEYS_MOVED[old]
    section, name = new.split(".")
    value = NON_DEFAULT[new]
    path = _write(tmp_path, toml_text({"daemon": {old: value, section: {name: value}}}))
    with pytest.raises(ConfigError) as info:
        load_config(path, env={})
    message = str(info.value)
    assert message.startswith(f"{path}: daemon.{old} = ")
    assert f" and daemon.{new} = " in message and f"keep only daemon.{new}" in message


def test_an_unknown_key_under_daemon_is_refused_listing_the_sections(tmp_path):
    allowed = "arming, audit, bench, frames, paths, server, web"
    for key in ("tick_ms", "heartbeat_s", "size_px"):  # a typo, and new keys at the old level
        path = _write(tmp_path, f"[daemon]\n{key} = 1\n")
        with pytest.raises(ConfigError) as info:
            load_config(path, env={})
        assert str(info.value) == f"{path}: daemon.{key}: unknown key; allowed here: {allowed}"
    # inside a section, the section's own keys are listed
    path = _write(tmp_path, "[daemon.arming]\ntick_s = 0.05\n")
    with pytest.raises(ConfigError, match=r"daemon\.arming\.tick_s: unknown key; allowed here: "
                       r"confirm, confirm_line, .*heartbeat_s"):
        load_config(path, env={})


def test_an_old_key_with_a_bad_value_is_refused_at_its_new_place(tmp_path):
    path = _write(tmp_path, "[daemon]\ntick_s = 0.2\n")
    with pytest.raises(ConfigError, match=r": daemon\.arming\.heartbeat_s = 0\.2 s: must be at "
                       r"most 1/4 of devices\.readybeam\.guardian\.heartbeat_timeout_s"):
        _load(path)


LAB = """\
# A lab's file from before the sections.
[slm]
width_px = 1920

[daemon]
tcp_port = 7700
tick_s = 0.05
arm_users = ["alice", "bob"]
frame_size_px = [1024, 576]
audit_log = "/var/log/nhfd/audit.jsonl"
stage_at_reference_mm = 11.25

[daemon.frames]
int8 = "never"

[daemon.web]
enabled = true
port = 0
"""


def test_config_check_prints_the_file_migrated_and_it_loads_alike_without_a_warning(
        tmp_path, capsys):
    old = _write(tmp_path, LAB)
    before, warned = _load(old)
    assert len(warned) == 6
    assert main(["config", "check", str(old)]) == 0
    out, err = capsys.readouterr()
    first, moved, *rest = out.splitlines(keepends=True)
    assert first == f"{old}: ok\n"
    assert moved.startswith(f"# {old} sets 6 keys at their old places (daemon.tcp_port -> "
                            "daemon.server.tcp_port, daemon.tick_s -> daemon.arming.heartbeat_s")
    # one line per move on stderr, as the command's warning
    assert err.count("nhfd config: warning: ") == 6
    assert f"nhfd config: warning: {old}: daemon.tick_s is now daemon.arming.heartbeat_s" in err
    printed = "".join(rest)
    # the lab's own keys only, in their new places, values kept: not the whole default
    assert tomllib.loads(printed) == {
        "slm": {"width_px": 1920},
        "daemon": {"server": {"tcp_port": 7700}, "arming": {"heartbeat_s": 0.05,
                                                            "users": ["alice", "bob"]},
                   "frames": {"int8": "never", "size_px": [1024, 576]},
                   "audit": {"file": "/var/log/nhfd/audit.jsonl"},
                   "bench": {"stage_at_reference_mm": 11.25},
                   "web": {"enabled": True, "port": 0}}}
    # pasted over the old file (the comment line included: it is TOML too)
    new = _write(tmp_path, moved + printed, "pasted.toml")
    after, none = _load(new)
    assert after.config == before.config and not none and after.migrations == ()
    # and checked again: nothing moved, nothing more printed
    assert main(["config", "check", str(new)]) == 0
    assert capsys.readouterr() == (f"{new}: ok\n", "")


def test_config_show_names_the_new_keys_and_the_file_as_their_source(tmp_path, capsys):
    old = _write(tmp_path, LAB)
    assert main(["config", "show", "--config", str(old)]) == 0
    out = capsys.readouterr().out
    assert re.search(rf"^daemon\.arming\.heartbeat_s += 0\.05 +# {re.escape(str(old))}$", out,
                     re.MULTILINE), out
    assert re.search(r"^daemon\.frames\.size_px += \[1024, 576\] +# ", out, re.MULTILINE)
    assert not re.search(r"^daemon\.(tick_s|frame_size_px|tcp_port) ", out, re.MULTILINE)


def test_migration_changes_nothing_but_the_old_keys_and_leaves_its_input_alone():
    user = {"slm": {"width_px": 1000}, "daemon": {"tcp_port": 1, "web": {"port": 2},
                                                  "server": {"tcp_host": "::1"}}}
    snapshot = repr(user)
    moved, moves = migrate_daemon_keys(user, "lab.toml")
    assert repr(user) == snapshot
    assert moved == {"slm": {"width_px": 1000},
                     "daemon": {"web": {"port": 2},
                                "server": {"tcp_host": "::1", "tcp_port": 1}}}
    assert moves == [("daemon.tcp_port", "daemon.server.tcp_port")]
    modern = {"daemon": {"server": {"tcp_port": 1}}}
    assert migrate_daemon_keys(modern, "x") == (modern, [])


def test_the_packaged_default_documents_every_daemon_key_at_its_new_place():
    default = tomllib.loads(default_text())["daemon"]
    assert not set(default) & set(DAEMON_KEYS_MOVED)  # nothing at an old place
    assert set(_leaf_keys(default)) == set(_leaf_keys(DaemonSettings().model_dump()))
    assert Config.model_validate(tomllib.loads(default_text())).daemon == DaemonSettings()
    assert (REPO / "nhfd.toml").read_bytes() == (REPO / "nhfd" / "default.toml").read_bytes()


def test_the_docs_table_is_the_table():
    """docs/daemon.md, "Settings moved in this release": one row per old key, in the table's
    order, naming the old and the new dotted key."""
    text = (REPO / "docs" / "daemon.md").read_text()
    section = text.split("## Settings moved in this release", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `daemon\.(\w+)` \| `daemon\.([\w.]+)` \|$", section, re.MULTILINE)
    assert rows == list(DAEMON_KEYS_MOVED.items())


def test_the_toml_writer_reads_back_equal():
    """What config check prints is read back as it was: the whole packaged default (tables of
    tables, empty tables, lists of lists), and strings TOML wants escaped."""
    default = tomllib.loads(default_text())
    assert tomllib.loads(toml_text(default)) == default
    odd = {"s": 'q"\\\n\t\x01\x7fé', "t": {"a.b": {"k": [1, 2.5, True, "x"]}, "e": {}}}
    assert tomllib.loads(toml_text(odd)) == odd
    with pytest.raises(ValueError, match="nan: not finite"):
        toml_text({"x": float("nan")})
