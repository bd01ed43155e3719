"""Driver settings validate once and stand alone; templates subclass the real bases."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest
from pydantic import ValidationError

from nhfd import device_settings as st

SOURCE = Path(st.__file__)


def test_settings_import_nothing_from_nhfd():
    tree = ast.parse(SOURCE.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            assert node.level == 0 and not (node.module or "").startswith("nhfd"), node.module
        if isinstance(node, ast.Import):
            assert not any(a.name.startswith("nhfd") for a in node.names)


def test_safe_defaults():
    laser = st.LaserSettings()
    assert laser.max_power_pct == [10.0, 10.0, 10.0]
    assert laser.cap_pct("green") == 10.0 and laser.instance("blue") == 3
    assert laser.parameter_ids.device_type == 100 and laser.device_type == 1171
    stage = st.StageSettings()
    assert stage.counts_per_mm == 34554.96 and stage.soft_limits_mm == [0.0, 25.0]


@pytest.mark.parametrize(
    ("model", "data", "why"),
    [
        (st.LaserSettings, {"max_power_pct": [10.0, 10.0, 150.0]}, "less than or equal to 100"),
        (st.LaserSettings, {"channel_instances": [1, 1, 2]}, "distinct"),
        (st.LaserSettings, {"power_cap": 5}, "Extra inputs"),
        (st.LaserSettings, {"baud": "57600"}, "valid integer"),
        (st.StageSettings, {"soft_limits_mm": [10.0, 5.0]}, "min < max"),
        (st.StageSettings, {"counts_per_mm": 0.0}, "greater than 0"),
        (st.SLMOutputSettings, {"pixel_order": "GRB"}, "BGR"),
        (st.NavigatorSettings, {"axis_signs": [1, 1, 1, 1, 1, 2]}, "-1"),
        (st.GuardianSettings, {"heartbeat_timeout_s": 60.0}, "less than or equal to 10"),
    ],
)
def test_invalid_settings_are_refused(model, data, why):
    with pytest.raises(ValidationError, match=why):
        model.model_validate(data)


def test_settings_round_trip_through_json_for_the_guardian():
    s = st.LaserSettings(port="/dev/ttyUSB3", max_power_pct=[5.0, 2.0, 1.0])
    assert st.LaserSettings.model_validate_json(s.model_dump_json()) == s


@pytest.mark.parametrize(
    ("module", "cls", "base"),
    [
        ("laser_backend", "MyLaser", "nhfd.drivers.laser:Laser"),
        ("stage_backend", "MyStage", "nhfd.drivers.stage:Stage"),
        ("slm_backend", "MySLM", "nhfd.drivers.slm:SLM"),
        ("navigator_backend", "MyNavigator", "nhfd.drivers.navigator:Navigator"),
    ],
)
def test_templates_are_concrete_subclasses_of_the_bases(module, cls, base):
    template = getattr(importlib.import_module(f"nhfd.drivers.templates.{module}"), cls)
    base_module, base_name = base.split(":")
    assert issubclass(template, getattr(importlib.import_module(base_module), base_name))
    assert not getattr(template, "__abstractmethods__", None)  # every hook is there
