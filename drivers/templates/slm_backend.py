"""Template: an SLM backend. The base class validates, quantises and keeps the last frame."""

from __future__ import annotations

import numpy as np

from nhfd.drivers.slm import SLM, SLMHealth


class MySLM(SLM):
    """A phase SLM backend to fill in: write one uint8 [H, W, 3] RGB frame, report the output's
    health."""

    def _do_open(self) -> None:
        pass  # find the output (by EDID name, not index), check its geometry

    def _do_close(self) -> None:
        pass

    def _write(self, rgb: np.ndarray) -> None:
        # rgb: uint8 [height_px, width_px, 3], R, G, B: send exactly these values (full range,
        # no scaling, dithering or colour management).
        raise NotImplementedError

    def _health(self) -> SLMHealth:
        # Report whether pixels still reach the panel (cable, output enabled).
        return SLMHealth(True, "not checked")
