"""The Linux framebuffer SLM backend: a memory-mapped /dev/fbN, no desktop needed.

Geometry comes from sysfs (`class/graphics/fbN/{virtual_size,bits_per_pixel,stride}` under the
configured root, so a test can point both the device and sysfs at files). Pixels are 24 or 32 bits
(B, G, R[, X] in memory for the usual BGR order); rows are `stride` bytes apart and the padding
after each row is left alone. 16 bpp is refused: it cannot carry 8-bit grey levels.

Pacing: where the driver offers the FBIO_WAITFORVSYNC ioctl (asked once, at open), each write
waits for the vertical blank first (`_before_write`: before `SLM.show` stamps the frame written
for a trigger line, and outside the camera_exposure line's lock), so frames change between
scans, at most one per refresh (the wait blocks the caller for up to one refresh, as the window
backend's vsync flip does).
Where it does not (ENOTTY, EINVAL: many fbdev drivers), writes go at once and the daemon's
timer at `slm.refresh_hz` paces view frames (`nhfd.daemon.frame_link`); `vsync_detail` says
which, for `status`.

The framebuffer gives no flip feedback and its writes succeed with the cable unplugged,
so health polls the DRM connectors' `status` files: the configured connector must read
"connected", or (none configured) every connector connected at open must still be.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import mmap
import os
import struct
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from nhfd.device_settings import SLMOutputSettings

from .errors import DeviceError
from .slm import SLM, SLMHealth

# <linux/fb.h>: #define FBIO_WAITFORVSYNC _IOW('F', 0x20, __u32): write direction (1 << 30), a
# 4-byte argument (4 << 16), type 'F' (0x46 << 8), number 0x20. The argument is the CRTC, 0.
FBIO_WAITFORVSYNC = 0x40044620


def wait_for_vsync(fd: int) -> None:
    """Block until the next vertical blank of the framebuffer open on `fd` (OSError where the
    driver has no FBIO_WAITFORVSYNC)."""
    fcntl.ioctl(fd, FBIO_WAITFORVSYNC, struct.pack("I", 0))


class FramebufferError(DeviceError):
    """The framebuffer cannot show the SLM's frames as configured."""


def _read(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError as exc:
        raise FramebufferError(f"cannot read {path}: {exc.strerror}") from None


class FramebufferSLM(SLM):
    """The SLM as a memory-mapped /dev/fbN (24 or 32 bpp, geometry from sysfs), paced by
    FBIO_WAITFORVSYNC where the driver has it; health from the DRM connectors' status."""

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
        self._vsync = False  # whether each write waits for the vertical blank
        self.vsync_detail = ""

    @property
    def name(self) -> str:
        """"framebuffer /dev/fbN", for messages."""
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
        self._vsync, self.vsync_detail = self._detect_vsync(fd)

    def _detect_vsync(self, fd: int) -> tuple[bool, str]:
        """Once, at open: does the driver offer FBIO_WAITFORVSYNC? (One wait, at most a
        refresh.)"""
        try:
            wait_for_vsync(fd)
        except OSError as exc:
            name = errno.errorcode.get(exc.errno or 0, str(exc.errno))
            return False, (f"{self.device} has no FBIO_WAITFORVSYNC ({name}): writes are not "
                           "synchronised to the vertical blank")
        return True, f"{self.device}: each write waits for the vertical blank (FBIO_WAITFORVSYNC)"

    def _do_close(self) -> None:
        if self._map is not None:
            self._map.close()
            self._map = None
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None

    def _before_write(self) -> None:
        if self._vsync and self._fd is not None:
            try:
                wait_for_vsync(self._fd)
            except OSError as exc:  # it worked at open: say so once and stop asking
                self._vsync = False
                self.vsync_detail = (f"{self.device}: FBIO_WAITFORVSYNC failed ({exc}); writes "
                                     "are no longer synchronised to the vertical blank")

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
