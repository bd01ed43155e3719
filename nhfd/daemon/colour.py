"""Colour modes (docs/design.md, "The hardware": Colour timing): what the panel shows per colour,
which diodes a client may switch, and the capture-mode snapshot sequence.

  single   one colour (daemon.frames.single_colour): its pattern in every HDMI channel, and only its
           diode may be enabled or given power. The safe choice for a bench without sync wiring.
  capture  software field-sequential colour, for snapshots only: a MeCom command takes ~5 ms
           plus USB latency and the liquid crystal needs its settle time, so switching diodes per
           colour from software gives a few frames per second at best. Clients set powers and
           arm; the daemon alone enables diodes, one at a time, inside a snapshot: all off ->
           show the colour's pattern -> settle -> that diode on -> capture -> off; the captures
           are combined into one colour image.
  hw-sync  each colour's pattern in its own HDMI channel, the lasers modulated by the SLM's frame
           sync (wired on the bench); software shows frames, sets powers and enables channels.
           Laser commands are not restricted (the wiring decides which diode lights which
           field).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from nhfd.config import FramesSettings
from nhfd.device_settings import COLOURS

from .audit import AuditLog
from .guardian_link import LaserLink
from .jobs import Job
from .png import write_png16, write_preview8
from .protocol import LASER_REFUSED, RpcError

log = logging.getLogger("nhfd.daemon.colour")

COLOUR_MODES = ("single", "capture", "hw-sync")


def panel_for_mode(frame: np.ndarray, mode: str, colour: str) -> np.ndarray:
    """The panel frame a mode shows: in single mode the chosen colour's pattern in all three
    channels (whichever channel the panel reads, it shows that colour's hologram)."""
    if mode != "single":
        return frame
    c = COLOURS.index(colour)
    # Built in the SLM's [H, W, 3] layout and returned as its [3, H, W] view: the SLM takes it
    # without a transposing copy of the whole panel (see nhfd.daemon.frame_link.PanelBuffer).
    out = np.empty((*frame.shape[1:], frame.shape[0]), frame.dtype)
    for k in range(frame.shape[0]):
        out[..., k] = frame[c]
    return out.transpose(2, 0, 1)


def check_laser_command(settings: FramesSettings, action: str, channel: str | None,
                        power_pct: float | None) -> None:
    """Refuse what the colour mode (`daemon.frames.colour_mode`, `single_colour`) forbids, before
    anything reaches the guardian. `settings`: `[daemon.frames]`."""
    c = settings
    mode = c.colour_mode
    if mode == "single" and channel is not None and channel != c.single_colour:
        if action == "enable" or (action == "power" and power_pct):
            raise RpcError(LASER_REFUSED, f"colour_mode 'single' ({c.single_colour}): only the "
                           f"{c.single_colour} diode may be on",
                           {"field": "channel", "allowed": c.single_colour})
    if mode == "capture" and action == "enable":
        raise RpcError(LASER_REFUSED, "colour_mode 'capture': the daemon enables each diode "
                       "itself during a snapshot; set powers and arm only",
                       {"field": "action", "allowed": "arm, disarm, off, power, disable"})


class CapturePanel(Protocol):
    """What the capture sequence uses of the panel (`nhfd.daemon.panel.Panel`)."""

    def blank_frame(self) -> np.ndarray:
        """The blank of the coding in use, the whole panel `[3, H, W]` uint8."""
        ...

    def hold(self) -> AbstractContextManager[None]:
        """Hold the panel for a capture sequence: no view frame replaces the pattern under the
        camera meanwhile."""
        ...

    def show_colour(self, frame: np.ndarray, colour: str) -> None:
        """Show `colour`'s pattern of `frame` (`[3, H, W]` uint8) in every channel, settled."""
        ...

    def resume(self, last_view: np.ndarray | None, seq: int) -> None:
        """Show the last view frame again (`last_view`, view `seq`), or the blank when there is
        none."""
        ...


class CaptureBench(Protocol):
    """What the capture sequence uses of the bench (`nhfd.daemon.bench.Bench`)."""

    slm: Any
    camera: Any

    def capture(self, frames: int | None = None) -> Any:
        """One camera capture, `frames` images averaged (None: the camera's setting)."""
        ...


class ShownViews(Protocol):
    """The last view frame the frame worker delivered, and its view's sequence number."""

    last_frame: np.ndarray | None
    shown_seq: int


@contextlib.contextmanager
def diodes_in_turn(job: Job, what: str, powers_pct: dict[str, float], *, panel: CapturePanel,
                   laser: LaserLink, audit: AuditLog, shown: ShownViews, session: int
                   ) -> Iterator[Callable[[str, bool], None]]:
    """A sequence that lights one diode at a time on a held panel (the capture-mode snapshot,
    citl's captures; `what` names it in the audit log): yields `light(channel, on)`, which
    switches a diode and audits each switch-on with its power from `powers_pct`. A switch-on
    happens only while emission session `session` holds (`LaserLink.enable`: EmissionEnded,
    naming what ended it, once a laser off, disarm or stop has). On every way out every diode
    is switched off (each read back by the guardian), that is audited, and the panel shows the
    control loop's last view again."""
    who = {"who": "daemon", "job": job.id}

    def light(channel: str, on: bool) -> None:
        laser.enable(channel, on, session=session)
        if on:
            audit.write(who, f"laser enable ({what})", channel=channel,
                        power_pct=powers_pct[channel])

    try:
        with panel.hold():
            try:
                yield light
            finally:
                for ch in COLOURS:
                    with contextlib.suppress(Exception):
                        laser.enable(ch, False)
                audit.write(who, f"laser all disabled ({what})")
    finally:
        with contextlib.suppress(Exception):  # back to what the control loop last showed
            panel.resume(shown.last_frame, shown.shown_seq)


def capture_colours(job: Job, path: Path, frames: int | None, *, bench: CaptureBench,
                    panel: CapturePanel, laser: LaserLink, audit: AuditLog,
                    shown: ShownViews, session: int) -> dict[str, Any]:
    """The capture-mode snapshot: one capture per colour that has power, each with only its diode
    on and its own pattern settled on the panel; written as one PNG per colour and their mean.
    `laser` switches the diodes (the guardian reads each back), `audit` records each enable,
    `shown` is the last view frame (what every colour shows, and what the panel shows again).
    `session`: the emission session it was asked in; once that ends (a laser off, disarm or
    stop) nothing more is switched on and it fails saying why (`EmissionEnded`).

    The panel is held meanwhile (`Panel.hold`), so a view arriving during the sequence cannot
    replace the colour's pattern under the camera; afterwards it shows the last view again."""
    if bench.slm is None or bench.camera is None:
        raise RuntimeError("capture mode needs the SLM and the camera")
    laser.check_session(session)
    laser.refresh()
    powers = {ch: float(laser.status()["channels"].get(ch, {}).get("power_pct", 0.0))
              for ch in COLOURS}
    lit = [ch for ch in COLOURS if powers[ch] > 0]
    if not lit:
        raise RuntimeError("no colour has power: set per-channel power (laser power) first")
    # A copy: the frame link builds its panels in arrays it reuses, and views go on arriving
    # (held back from the panel) while the colours are captured.
    base = (shown.last_frame if shown.last_frame is not None else panel.blank_frame()).copy()
    images: dict[str, np.ndarray] = {}
    with diodes_in_turn(job, "capture mode", powers, panel=panel, laser=laser, audit=audit,
                        shown=shown, session=session) as light:
        for ch in lit:
            job.check()
            for other in COLOURS:  # all off, and read back by the guardian
                laser.enable(other, False)
            panel.show_colour(base, ch)
            light(ch, True)
            try:
                images[ch] = bench.capture(frames).image
            finally:
                light(ch, False)
            laser.check_session(session)  # a capture cut short by an off is no capture
    # A colour camera sees each colour in its own channel; a mono one gives [H, W] per colour.
    planes = {ch: img if img.ndim == 2 else img[COLOURS.index(ch)] for ch, img in images.items()}
    zero = np.zeros_like(next(iter(planes.values())))
    combined = np.stack([planes.get(ch, zero) for ch in COLOURS])
    written = {}
    for ch, image in images.items():
        out = path.with_name(f"{path.stem}-{ch}{path.suffix}")
        write_png16(out, image)
        written[ch] = str(out)
    write_png16(path, combined)
    preview = write_preview8(path, combined)
    return {"path": str(path), "preview": str(preview), "colour_mode": "capture",
            "emitting": lit, "colours": written,
            "powers_pct": {ch: powers[ch] for ch in lit},
            "max_linear": {ch: float(img.max()) if img.size else 0.0
                           for ch, img in images.items()}}
