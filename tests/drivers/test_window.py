"""The window SLM backend: choosing the output by name, and a clear error without pyglet."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import pytest

from nhfd.device_settings import SLMOutputSettings
from nhfd.drivers.window import WindowError, WindowSLM, pick_screen


def screen(name, width, height):
    return SimpleNamespace(width=width, height=height, get_device_name=lambda: name)


SCREENS = [screen("DP-1", 2560, 1440), screen("HDMI-A-2", 1920, 1080),
           screen("HDMI-A-1", 1920, 1080)]


def test_the_output_is_chosen_by_name_not_index():
    assert pick_screen(SCREENS, "HDMI-A-2", 1920, 1080) is SCREENS[1]
    assert pick_screen(SCREENS, "card0-HDMI-A-1", 1920, 1080) is SCREENS[2]  # sysfs spelling
    with pytest.raises(WindowError, match=r"no single screen named 'HDMI-A-3'; screens: "
                                          r"#0 DP-1 2560x1440, #1 HDMI-A-2 1920x1080"):
        pick_screen(SCREENS, "HDMI-A-3", 1920, 1080)
    with pytest.raises(WindowError, match="is 2560x1440, the SLM is 1920x1080"):
        pick_screen(SCREENS, "DP-1", 1920, 1080)


def test_without_a_name_only_an_unambiguous_panel_sized_screen_is_used():
    assert pick_screen(SCREENS[:2], "", 1920, 1080) is SCREENS[1]
    with pytest.raises(WindowError, match="cannot tell which screen"):
        pick_screen(SCREENS, "", 1920, 1080)  # two candidates
    with pytest.raises(WindowError, match="cannot tell which screen"):
        pick_screen(SCREENS[:1], "", 1920, 1080)  # the primary is never guessed


def test_without_pyglet_the_backend_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyglet", None)
    slm = WindowSLM(1920, 1080, SLMOutputSettings(drm_connector="HDMI-A-2"))
    with pytest.raises(WindowError, match="needs pyglet"):
        slm.open()
    assert not slm.health().ok
