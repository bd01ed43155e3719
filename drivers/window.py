"""The window SLM backend: a borderless full-screen window on the SLM's output, with vsync.

For a bench that runs a desktop session (the framebuffer is hidden while a compositor runs). It
needs pyglet (`pip install pyglet`, not a dependency of nhfd) and runs in the user's desktop
session, not as a system service. The output is chosen by name (`slm_output.drm_connector`, e.g.
"HDMI-A-2", matched against the names pyglet reports for its screens; the "card0-" prefix is
ignored), never by a screen index, which changes with the desktop layout. With no name, the one
screen other than the primary whose size is the panel's is used, and anything ambiguous is
refused.

Each frame is uploaded as an RGB texture the size of the panel and drawn 1:1 (no scaling, no
filtering, dithering off) into the back buffer, then flipped: with vsync the flip waits for the
vertical blank. Check full-range RGB over HDMI with a camera (docs/design.md, "The hardware": SLM).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nhfd.device_settings import SLMOutputSettings

from .errors import DeviceError
from .slm import SLM, SLMHealth


class WindowError(DeviceError):
    """The window backend cannot show frames on the configured output."""


def screen_name(screen: Any) -> str:
    """The output name pyglet knows for a screen ("" where the platform does not say)."""
    for attr in ("get_device_name", "get_monitor_name"):
        getter = getattr(screen, attr, None)
        if callable(getter):
            try:
                name = getter()
            except Exception:
                continue
            if name:
                return str(name)
    return ""


def _bare(name: str) -> str:
    """"card0-HDMI-A-2" -> "hdmi-a-2"; output names are compared without card and case."""
    head, _, tail = name.partition("-")
    return (tail if head.startswith("card") and tail else name).lower()


def pick_screen(screens: Sequence[Any], output_name: str, width_px: int, height_px: int) -> Any:
    """The screen to go full-screen on: by output name, else the one non-primary screen of the
    panel's size. Raises WindowError naming every screen when that is not one screen."""
    described = ", ".join(
        f"#{i} {screen_name(s) or '(unnamed)'} {s.width}x{s.height}" for i, s in enumerate(screens)
    ) or "none"
    if output_name:
        want = _bare(output_name)
        hits = [s for s in screens if screen_name(s) and _bare(screen_name(s)) == want]
        if len(hits) != 1:
            raise WindowError(f"no single screen named {output_name!r}; screens: {described}")
        screen = hits[0]
    else:
        hits = [s for s in list(screens)[1:] if (s.width, s.height) == (width_px, height_px)]
        if len(hits) != 1:
            raise WindowError(
                f"cannot tell which screen is the {width_px}x{height_px} SLM (set "
                f"devices.slm_output.drm_connector to its output name); screens: {described}"
            )
        screen = hits[0]
    if (screen.width, screen.height) != (width_px, height_px):
        raise WindowError(f"screen {screen_name(screen)!r} is {screen.width}x{screen.height}, the "
                          f"SLM is {width_px}x{height_px}: wrong output or wrong mode")
    return screen


class WindowSLM(SLM):
    """The SLM as a borderless full-screen pyglet window on the named output, each frame drawn 1:1
    and flipped with vsync."""

    def __init__(self, width_px: int, height_px: int, settings: SLMOutputSettings | None = None,
                 *, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(width_px, height_px, settings, clock=clock)
        self._pyglet: Any = None
        self._window: Any = None
        self._texture: Any = None

    @property
    def name(self) -> str:
        """"window SLM <connector>" ("(auto)" when none is configured), for messages."""
        return f"window SLM {self.settings.drm_connector or '(auto)'}"

    def _do_open(self) -> None:
        try:
            import pyglet
        except ImportError:
            raise WindowError("the window SLM backend needs pyglet (pip install pyglet) and a "
                              "desktop session; without a desktop use the framebuffer backend"
                              ) from None
        display_module = getattr(pyglet, "display", None) or pyglet.canvas
        screens = display_module.get_display().get_screens()
        screen = pick_screen(screens, self.settings.drm_connector, self.width_px, self.height_px)
        window = pyglet.window.Window(fullscreen=True, screen=screen, vsync=True,
                                      caption="nhfd SLM")
        if tuple(window.get_framebuffer_size()) != (self.width_px, self.height_px):
            size = window.get_framebuffer_size()
            window.close()
            raise WindowError(f"the window's framebuffer is {size}, not the panel's "
                              f"{self.width_px}x{self.height_px} (desktop scaling?)")
        window.set_mouse_visible(False)
        # The flip waits for the vertical blank (vsync=True above): status's pacing says so.
        self.vsync_detail = "the window's flip waits for vsync"
        pyglet.gl.glDisable(pyglet.gl.GL_DITHER)
        self._pyglet, self._window = pyglet, window

    def _do_close(self) -> None:
        if self._window is not None:
            self._window.close()
            self._window = None

    def _write(self, rgb: np.ndarray) -> None:
        pyglet, window = self._pyglet, self._window
        h, w = rgb.shape[:2]
        # Negative pitch: rows are top-down in memory, OpenGL's are bottom-up.
        image = pyglet.image.ImageData(w, h, "RGB", rgb.tobytes(), pitch=-w * 3)
        texture = image.get_texture()
        gl = pyglet.gl
        gl.glBindTexture(texture.target, texture.id)
        gl.glTexParameteri(texture.target, gl.GL_TEXTURE_MIN_FILTER, gl.GL_NEAREST)
        gl.glTexParameteri(texture.target, gl.GL_TEXTURE_MAG_FILTER, gl.GL_NEAREST)
        window.switch_to()
        window.dispatch_events()
        window.clear()
        texture.blit(0, 0)
        window.flip()  # vsync: returns after the vertical blank
        self._texture = texture

    def _health(self) -> SLMHealth:
        if self._window is None or getattr(self._window, "has_exit", False):
            return SLMHealth(False, "window closed")
        connector = self.settings.drm_connector
        if connector:
            matches = sorted((Path(self.settings.sysfs_root) / "class" / "drm").glob(
                f"*{_bare(connector).upper()}/status"))
            states = [p.read_text().strip() for p in matches]
            if states and "connected" not in states:
                return SLMHealth(False, f"{connector} {states[0]}")
        return SLMHealth(True, "window open")
