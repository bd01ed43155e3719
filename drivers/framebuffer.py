"""The Linux framebuffer SLM backend: a memory-mapped /dev/fbN, no desktop needed.

Geometry comes from sysfs (`class/graphics/fbN/{virtual_size,bits_per_pixel,stride}` under the
configured root, so a test can point both the device and sysfs at files). Pixels are 24 or 32 bits
(B, G, R[, X] in memory for the usual BGR order); rows are `stride` bytes apart and the padding
after each row is left alone. 16 bpp is refused: it cannot carry 8-bit grey levels.

The framebuffer gives no vsync or flip feedback and its writes succeed with the cable unplugged,
so health polls the DRM connectors' `status` files: the configured connector must read
"connected", or (none configured) every connector connected at open must still be.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from nhfd.device_settings import SLMOutputSettings

from .errors import DeviceError
from .slm import SLM, SLMHealth


class FramebufferError(DeviceError):
    """The framebuffer cannot show the SLM's frames as configured."""


def _read(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError as exc:
        raise FramebufferError(f"cannot read {path}: {exc.strerror}") from None


class FramebufferSLM(SLM):
    def __init__(self, width_px: int, height_px: int, settings: SLMOutputSettings | None = None,
                 *, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(width_px, height_px, settings, clock=clock)
        s = self.settings
        self.device = Path(s.framebuffer_device)
        self.sysfs_root = Path(s.sysfs_root)
        self.bits_per_pixel = 0
        self.stride_bytes = 0
        self._fd: int | None = None
        self._map: mmap.mmap | None = None
        self._watched: list[Path] = []

    @property
    def name(self) -> str:
        return f"framebuffer {self.device}"

    def _do_open(self) -> None:
        sysfs = self.sysfs_root / "class" / "graphics" / self.device.name
        virtual = _read(sysfs / "virtual_size")
        try:
            width, height = (int(v) for v in virtual.split(","))
            bpp = int(_read(sysfs / "bits_per_pixel"))
            stride = int(_read(sysfs / "stride"))
        except ValueError:
            raise FramebufferError(f"{sysfs}: unreadable geometry") from None
        if bpp == 16:
            raise FramebufferError(
                f"{self.device} is 16 bpp, which cannot carry 8-bit grey levels; set the "
                "framebuffer to 24 or 32 bpp (e.g. fbset -depth 32, or video=...-32 on the "
                "kernel command line)"
            )
        if bpp not in (24, 32):
            raise FramebufferError(f"{self.device}: {bpp} bpp is not supported (24 or 32)")
        if width != self.width_px or height < self.height_px:
            raise FramebufferError(
                f"{self.device} is {width} x {height}, the SLM is {self.width_px} x "
                f"{self.height_px}: wrong output, or the mode is not the panel's"
            )
        if stride < width * bpp // 8:
            raise FramebufferError(f"{self.device}: stride {stride} < {width} pixels x {bpp} bpp")
        self.bits_per_pixel, self.stride_bytes = bpp, stride
        self._watched = self._connectors_to_watch()
        size = stride * self.height_px
        try:
            fd = os.open(self.device, os.O_RDWR)
        except OSError as exc:
            raise FramebufferError(f"cannot open {self.device}: {exc.strerror} (is the user in "
                                   "the video group?)") from None
        try:
            self._map = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        except (OSError, ValueError) as exc:
            os.close(fd)
            raise FramebufferError(f"cannot map {size} bytes of {self.device}: {exc}") from None
        self._fd = fd

    def _do_close(self) -> None:
        if self._map is not None:
            self._map.close()
            self._map = None
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None

    def _write(self, rgb: np.ndarray) -> None:
        assert self._map is not None
        bytes_pp = self.bits_per_pixel // 8
        rows = np.ndarray((self.height_px, self.stride_bytes), np.uint8, buffer=self._map)
        pixels = rows[:, : self.width_px * bytes_pp].reshape(self.height_px, self.width_px,
                                                             bytes_pp)
        order = (2, 1, 0) if self.settings.pixel_order == "BGR" else (0, 1, 2)
        for byte, channel in enumerate(order):
            pixels[..., byte] = rgb[..., channel]
        if bytes_pp == 4:
            # X byte: ignored by XRGB formats; opaque where a driver reads it as alpha.
            pixels[..., 3] = 0xFF

    # -- health --------------------------------------------------------------------------------

    def _drm(self) -> Path:
        return self.sysfs_root / "class" / "drm"

    def _connectors_to_watch(self) -> list[Path]:
        if self.settings.drm_connector:
            status = self._drm() / self.settings.drm_connector / "status"
            if not status.exists():
                raise FramebufferError(f"DRM connector {self.settings.drm_connector!r} not found "
                                       f"({status} missing)")
            return [status]
        return [p for p in sorted(self._drm().glob("*/status"))
                if p.read_text().strip() == "connected"]

    def _health(self) -> SLMHealth:
        if not self._watched:
            return SLMHealth(True, "no DRM connector to watch (unplugging goes unnoticed)")
        lost = []
        for status in self._watched:
            try:
                state = status.read_text().strip()
            except OSError:
                state = "gone"
            if state != "connected":
                lost.append(f"{status.parent.name} {state}")
        if lost:
            return SLMHealth(False, ", ".join(lost))
        return SLMHealth(True, ", ".join(p.parent.name for p in self._watched) + " connected")
