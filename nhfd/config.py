"""Configuration: the packaged default, the search order, validation and provenance.

The first file found in the search order overlays the packaged default (`nhfd/default.toml`, the
repository's annotated `nhfd.toml`), so a lab's file holds only what it changes. Every value is
validated once here; an unknown key, a wrong type or an out-of-range value raises `ConfigError`
naming the file, the key, the value and what is allowed.

This module imports no torch: control commands read the configuration too.
"""

from __future__ import annotations

import json
import math
import os
import re
import tomllib
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from nhfd.device_settings import (
    CameraSettings,
    LaserSettings,
    NavigatorSettings,
    SLMOutputSettings,
    SlmsuiteSettings,
    StageSettings,
    TriggerSettings,
)
from nhfd.views import QUALITY_TIERS

DEFAULT_NAME = "packaged default"


class ConfigError(ValueError):
    """A configuration file is missing, unreadable or invalid; the message says where and why."""


class ConfigMigrationWarning(UserWarning):
    """A configuration file set a key at a place it has moved from (`DAEMON_KEYS_MOVED`): the
    value was read from there, and the message names the key's new place."""


def _finite(name: str, values: list[float]) -> list[float]:
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} = {values}: not finite")
    return values


class _Section(BaseModel):
    # strict: TOML is typed, so "8" where 8.0 is expected is a mistake worth reporting.
    # TOML also has nan and inf: no setting means either.
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)


PositiveMicrons = Annotated[float, Field(gt=0, lt=1000)]
Radians = Annotated[float, Field(gt=0, le=4 * math.pi)]
Nanometres = Annotated[float, Field(ge=200, le=2000)]
CyclesPerPixel = Annotated[float, Field(gt=0, le=0.5)]
Pixels = Annotated[int, Field(ge=1, le=32768)]


# The fastest refresh slm.refresh_hz may name (benches set it to time the pipeline unpaced).
REFRESH_HZ_MAX = 1000.0


class SLMSettings(_Section):
    """`[slm]`: the panel's size (px), pixel pitch (um), phase stroke per colour (rad, R, G, B),
    phase sign, grey inversion and refresh rate (Hz)."""

    width_px: Pixels = 1920
    height_px: Pixels = 1080
    pitch_um: PositiveMicrons = 8.0
    phase_stroke_rad: Annotated[list[Radians], Field(min_length=3, max_length=3)] = [
        2 * math.pi
    ] * 3
    phase_sign: Literal[1, -1] = 1
    grey_invert: bool = False
    # The panel's refresh rate: the daemon shows at most one view frame per refresh (paced by
    # a timer; a framebuffer that offers FBIO_WAITFORVSYNC also waits for the vertical blank).
    refresh_hz: Annotated[float, Field(ge=1, le=REFRESH_HZ_MAX)] = 60.0

    @property
    def pitch_m(self) -> float:
        """The pixel pitch in metres."""
        return self.pitch_um * 1e-6


class ApertureSettings(_Section):
    """`[optics.aperture]`: the relay's Fourier aperture, its shape and its cutoff per colour in
    cycles per pixel (R, G, B; 0.25 is half the band)."""

    shape: Literal["square", "circle", "diamond"] = "square"
    cutoff_per_px: Annotated[list[CyclesPerPixel], Field(min_length=3, max_length=3)] = [0.25] * 3


class OpticsSettings(_Section):
    """`[optics]`: wavelengths (nm, R, G, B), the hologram window (px), the reference plane's
    distance z0 and the volume about it (mm), propagation's padding, precision and kernel cache."""

    wavelengths_nm: Annotated[list[Nanometres], Field(min_length=3, max_length=3)] = [
        660.0,
        520.0,
        450.0,
    ]
    hologram_width_px: Pixels = 1024
    hologram_height_px: Pixels = 576
    z0_mm: Annotated[float, Field(gt=0, le=1000)] = 6.0
    volume_mm: Annotated[list[float], Field(min_length=2, max_length=2)] = [-3.0, 3.0]
    padding: Literal["none", "2x", "auto"] = "auto"
    precision: Literal["float32", "float64"] = "float32"
    kernel_cache_mb: Annotated[int, Field(ge=0, le=65536)] = 512
    aperture: ApertureSettings = ApertureSettings()

    @model_validator(mode="after")
    def _volume_in_front_of_slm(self) -> OpticsSettings:
        z_min, z_max = _finite("volume_mm", self.volume_mm)
        if not z_min < z_max:
            raise ValueError(f"volume_mm = {self.volume_mm}: needs z_min < z_max")
        if self.z0_mm + z_min <= 0:
            raise ValueError(
                f"z0_mm = {self.z0_mm} with volume_mm = {self.volume_mm} puts the volume's far end "
                f"at {self.z0_mm + z_min:g} mm, on or behind the SLM; needs z0_mm > {-z_min:g}"
            )
        return self

    @property
    def wavelengths_m(self) -> tuple[float, ...]:
        """The three wavelengths in metres, R, G, B."""
        return tuple(w * 1e-9 for w in self.wavelengths_nm)

    @property
    def z0_m(self) -> float:
        """The reference plane's distance from the SLM in metres."""
        return self.z0_mm * 1e-3

    @property
    def volume_m(self) -> tuple[float, float]:
        """The hologram volume `(z_min, z_max)` about the reference plane, in metres."""
        return (self.volume_mm[0] * 1e-3, self.volume_mm[1] * 1e-3)


class CodingSettings(_Section):
    """`[coding]`: double-phase coding's anti-alias low-pass and the amplitude fraction below
    which a pixel codes as the zero pattern."""

    antialias: bool = True
    zero_below: Annotated[float, Field(ge=0, lt=1)] = 0.03


class DeviceSettings(_Section):
    """Which backend drives each device (simulated twins by default) and each device's settings.

    The device settings models live in `nhfd.device_settings` (pydantic only, no nhfd imports),
    so the laser guardian validates them without loading the rest of nhfd.
    """

    slm: Literal["simulated", "framebuffer", "window", "slmsuite", "none"] = "simulated"
    laser: Literal["simulated", "readybeam", "none"] = "simulated"
    stage: Literal["simulated", "apt", "none"] = "simulated"
    camera: Literal["simulated", "opencv", "genicam", "slmsuite", "none"] = "simulated"
    navigator: Literal["none", "simulated", "spacemouse"] = "none"
    slm_output: SLMOutputSettings = SLMOutputSettings()
    readybeam: LaserSettings = LaserSettings()
    apt: StageSettings = StageSettings()
    spacemouse: NavigatorSettings = NavigatorSettings()
    camera_settings: CameraSettings = CameraSettings()
    slmsuite: SlmsuiteSettings = SlmsuiteSettings()
    trigger: TriggerSettings = TriggerSettings()


# A profile's width growth per level: 1 keeps the base width, 2 doubles it (the classic U-Net,
# and what every network saved before the key existed was).
GROWTH_RANGE = (1.0, 2.0)

# How a U-Net level's decoder takes its skip: "concat" (the classic U-Net: upsampled features and
# the skip side by side, twice the channels into the first convolution) or "add" (summed: half
# the first convolution's arithmetic). The first is what every network saved before the key
# existed was.
SKIPS = ("concat", "add")

# A profile's largest channel count per level and depth (levels below the first); the network
# (nhfd.models.net.NetSpec) checks the same bounds.
WIDTH_MAX = 512
DEPTH_MAX = 6

# `single_conv_levels`: levels, counted from the first, whose encoder and decoder blocks have one
# 3 x 3 convolution instead of the classic U-Net's two (0, what every network saved before the
# key existed had), at most the network's depth + 1. A thin network spends most of its time at
# its first levels, the largest.

# Adam's learning rate: above the first bound, at most the second (nhfd.toml, `nhfd train --lr`,
# `nhfd bench tradeoff --lr`).
LEARNING_RATE_RANGE = (0.0, 1.0)
LEARNING_RATE_RULE = "must be in ({:g}, {:g}]".format(*LEARNING_RATE_RANGE)


def learning_rate_ok(lr: float) -> bool:
    """Whether `lr` is in `LEARNING_RATE_RANGE` (NaN is not)."""
    return LEARNING_RATE_RANGE[0] < lr <= LEARNING_RATE_RANGE[1]


class ModelProfile(_Section):
    """One network size: U-Net base width (channels at the first level), depth (levels below the
    first, each halving the size), the input pixel-unshuffle factor (the first downsampling) and
    the width's growth per level (2 doubles the channels at each level, 1 keeps them), how
    the decoder joins each skip (`SKIPS`), and how many levels, from the first, have one
    convolution per block instead of two."""

    width: Annotated[int, Field(ge=1, le=WIDTH_MAX)]
    depth: Annotated[int, Field(ge=0, le=DEPTH_MAX)]
    unshuffle: Literal[1, 2, 4, 8]
    # "rgbd" adds the render's mapped depth as a fourth input channel (nhfd.models.inputs).
    inputs: Literal["rgb", "rgbd"] = "rgb"
    growth: Annotated[float, Field(ge=GROWTH_RANGE[0], le=GROWTH_RANGE[1])] = GROWTH_RANGE[1]
    skip: Literal[SKIPS] = SKIPS[0]
    single_conv_levels: Annotated[int, Field(ge=0, le=DEPTH_MAX + 1)] = 0
    # channels of the second level when not width * growth (0); the growth applies below it
    deep_width: Annotated[int, Field(ge=0, le=WIDTH_MAX)] = 0

    @model_validator(mode="after")
    def _levels_exist(self) -> ModelProfile:
        if self.single_conv_levels > self.depth + 1:
            raise ValueError(f"single_conv_levels = {self.single_conv_levels}: the network has "
                             f"{self.depth + 1} levels (depth + 1)")  # fmt: skip
        return self


def _default_profiles() -> dict[str, ModelProfile]:
    return {
        "fast": ModelProfile(width=16, depth=3, unshuffle=2, growth=1, skip="add", inputs="rgbd"),
        "fastest": ModelProfile(width=16, depth=3, unshuffle=2, growth=1, skip="add",
                                single_conv_levels=1, deep_width=8, inputs="rgbd"),
        "balanced": ModelProfile(width=16, depth=3, unshuffle=2, inputs="rgbd"),
        "accurate": ModelProfile(width=32, depth=3, unshuffle=2, inputs="rgbd"),
    }


class TrainSettings(_Section):
    """Defaults of `nhfd train` (each has a command-line flag that overrides it)."""

    steps: Annotated[int, Field(ge=1, le=10_000_000)] = 10_000
    batch: Annotated[int, Field(ge=1, le=256)] = 1
    crop_width_px: Pixels = 384
    crop_height_px: Pixels = 224
    learning_rate: Annotated[float, Field(gt=LEARNING_RATE_RANGE[0],
                                          le=LEARNING_RATE_RANGE[1])] = 1e-3
    seed: Annotated[int, Field(ge=0)] = 0
    plane_mode: Literal["depth", "uniform"] = "depth"
    planes_from_depth: Annotated[int, Field(ge=0, le=64)] = 4
    planes_random: Annotated[int, Field(ge=0, le=64)] = 2
    plane_step_mm: Annotated[float, Field(gt=0, le=10)] = 0.1
    perceptual: Literal["ssim", "vgg", "none"] = "ssim"
    perceptual_weight: Annotated[float, Field(ge=0, le=1000)] = 0.1
    perceptual_planes: Annotated[int, Field(ge=0, le=64)] = 2
    field_weight: Annotated[float, Field(ge=0, le=1000)] = 0.25
    ssim_window_px: Annotated[int, Field(ge=3, le=63)] = 7
    vgg_weights: str = ""
    checkpoint_every: Annotated[int, Field(ge=1)] = 250
    val_views: Annotated[int, Field(ge=1, le=10_000)] = 8
    threads: Annotated[int, Field(ge=0, le=1024)] = 0
    amp: Literal["auto", "off", "bf16", "fp16"] = "auto"


class BuildRecipe(_Section):
    """One `nhfd model build` recipe (nhfd.models.build): the dataset's poses and size, what to
    train, and what to evaluate. A 0 or "" takes the value from [model] / [model.train]."""

    # Poses sampled: train / interpolation / extrapolation in the proportions 100 / 20 / 10.
    views: Annotated[int, Field(ge=3, le=100_000)] = 130
    width_px: Pixels = 512
    height_px: Pixels = 288
    fov_x_deg: Annotated[float, Field(ge=1, le=170)] = 40.0
    azimuth_deg: Annotated[list[float], Field(min_length=2, max_length=2)] = [-30.0, 30.0]
    elevation_deg: Annotated[list[float], Field(min_length=2, max_length=2)] = [10.0, 30.0]
    radius_scale: Annotated[list[float], Field(min_length=2, max_length=2)] = [0.9, 1.1]
    phase: Literal["depth", "zero", "random"] = "depth"
    seed: Annotated[int, Field(ge=0)] = 0
    # [model.profiles] name ("" = [model].profile); optimiser steps and training crop
    # (0 = [model.train]'s).
    network: str = ""
    steps: Annotated[int, Field(ge=0, le=10_000_000)] = 0
    crop_width_px: Annotated[int, Field(ge=0, le=32768)] = 0
    crop_height_px: Annotated[int, Field(ge=0, le=32768)] = 0
    # Held-out views evaluated per split (0 = all); views on the contact sheet; whether to
    # export a static int8 model (kept only within INT8_MAX_LOSS_DB of the float one).
    eval_views: Annotated[int, Field(ge=0, le=100_000)] = 0
    sheet_views: Annotated[int, Field(ge=1, le=6)] = 3
    int8: bool = True
    # export an fp16 candidate too (nhfd.models.half), kept by the same rule as the int8 one
    fp16: bool = True
    # Reduce the scene to what the dataset's views can show before building it, within this
    # many grey levels per pixel (nhfd.scene.cull; 0 still drops the splats no view draws).
    reduce: bool = True
    reduce_grey_levels: Annotated[float, Field(ge=0.0, le=255.0)] = 1.0

    @model_validator(mode="after")
    def _ranges_ordered(self) -> BuildRecipe:
        for name in ("azimuth_deg", "elevation_deg", "radius_scale"):
            lo, hi = _finite(name, getattr(self, name))
            if not lo <= hi:
                raise ValueError(f"{name} = {getattr(self, name)}: needs low <= high")
        if not -89 <= self.elevation_deg[0] <= self.elevation_deg[1] <= 89:
            raise ValueError(f"elevation_deg = {self.elevation_deg}: must lie in [-89, 89]")
        if not self.radius_scale[0] > 0:
            raise ValueError(f"radius_scale = {self.radius_scale}: must be > 0")
        return self


def _default_recipes() -> dict[str, BuildRecipe]:
    return {
        "quick": BuildRecipe(views=40, width_px=256, height_px=144, steps=1000,
                             crop_width_px=192, crop_height_px=112, eval_views=4),
        "default": BuildRecipe(),
    }


class BuildSettings(_Section):
    """`nhfd model build`: which recipe runs unless --profile says, and the recipes."""

    profile: str = "default"
    profiles: dict[str, BuildRecipe] = Field(default_factory=_default_recipes)


class ModelSettings(_Section):
    """`[model]`: the network profile used unless a command names one, the profiles, and the
    training and `nhfd model build` defaults."""

    profile: str = "fast"
    profiles: dict[str, ModelProfile] = Field(default_factory=_default_profiles)
    train: TrainSettings = TrainSettings()
    build: BuildSettings = BuildSettings()

    @model_validator(mode="after")
    def _profile_exists(self) -> ModelSettings:
        if self.profile not in self.profiles:
            raise ValueError(
                f"profile = {self.profile!r}: not one of the profiles "
                f"{', '.join(sorted(self.profiles))}"
            )
        if self.build.profile not in self.build.profiles:
            raise ValueError(
                f"build.profile = {self.build.profile!r}: not one of the recipes "
                f"{', '.join(sorted(self.build.profiles))}"
            )
        for name, recipe in self.build.profiles.items():
            if recipe.network and recipe.network not in self.profiles:
                raise ValueError(
                    f"build.profiles.{name}.network = {recipe.network!r}: not one of the "
                    f"profiles {', '.join(sorted(self.profiles))}"
                )
        return self


LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")


def _tls_problem(host: str, tls_cert: str, tls_key: str, prefix: str) -> str | None:
    """Why a listener's host and TLS files do not go together, or None: a certificate needs its
    key (and the reverse), and a host other than loopback needs both (a token must never cross
    a network in clear)."""
    if bool(tls_cert) != bool(tls_key):
        return (f"tls_cert = {tls_cert!r}, tls_key = {tls_key!r}: give both {prefix}tls_cert and "
                f"{prefix}tls_key, or neither")
    if host not in LOOPBACK_HOSTS and not tls_cert:
        return (f"host = {host!r} is not loopback ({', '.join(LOOPBACK_HOSTS)}): listening "
                f"elsewhere needs TLS, set {prefix}tls_cert and {prefix}tls_key")
    return None


class WebSettings(_Section):
    """`[daemon.web]`: the live web view `nhfd serve` serves (the `web` extra, aiohttp)."""

    enabled: bool = False
    # Address and port of the page (0 = any free port, logged at start). Loopback by default; any
    # other address needs tls_cert and tls_key.
    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=0, le=65535)] = 8765
    # PEM certificate (chain) and private key for HTTPS ("" = plain HTTP, loopback only).
    tls_cert: str = ""
    tls_key: str = ""
    # File holding the token the page asks for ("" = the daemon's TCP token when
    # daemon.server.tcp_port is on, else <runtime_dir>/web.token, created mode 0600 at start and
    # removed at stop).
    token_file: str = ""
    # How often the page's state and thumbnails are pushed (s), and the thumbnails' longest side.
    push_interval_s: Annotated[float, Field(ge=0.05, le=10)] = 0.5
    thumbnail_px: Annotated[int, Field(ge=16, le=2048)] = 320
    # Connections at once (page loads and WebSockets); messages a WebSocket may send per second
    # (a burst of as many allowed), and the longest message (bytes).
    max_connections: Annotated[int, Field(ge=1, le=4096)] = 32
    messages_per_s: Annotated[float, Field(gt=0, le=10000)] = 20.0
    max_message_bytes: Annotated[int, Field(ge=256, le=16_777_216)] = 65536

    @model_validator(mode="after")
    def _tls_elsewhere(self) -> WebSettings:
        problem = _tls_problem(self.host, self.tls_cert, self.tls_key, "daemon.web.")
        if problem:
            raise ValueError(problem)
        return self


# The values of daemon settings that benches and commands also take (one place for each list).
INT8_MODES = ("auto", "never", "always")
FRAME_TRANSPORTS = ("shm", "pickle")
INFERENCES = ("auto", "onnxruntime", "torch")

# The device names a setting or flag may take (daemon.frames.device, --device, [model.train]
# device):
# `device_choice` checks one, `nhfd.pipeline.device.resolve_device` turns one into a torch device.
DEVICES = ("auto", "cpu", "cuda", "cuda:N")
DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(:[0-9]+)?")  # matched whole (fullmatch)


def device_choice(value: object, setting: str, *, cuda_count: int | None,
                  allowed: tuple[str, ...] = DEVICES) -> str:
    """`value` (stripped, lower-cased) as a device name: "cpu" or "cuda:N" ("cuda" is "cuda:0";
    "auto" is "cuda:0" when torch sees a CUDA device, else "cpu"). `allowed`: the kinds of
    `DEVICES` `setting` takes. `cuda_count`: how many CUDA devices torch sees (callers pass
    `torch.cuda.device_count() if torch.cuda.is_available() else 0`); None checks the name only:
    "auto" comes back as "auto" and a CUDA index is not checked.

    The one place a device name is checked, so that every setting and flag says the same: a
    ValueError names `setting`, the value, and the allowed values or the CUDA devices torch sees.
    Torch-free (the configuration and control commands use it): the torch version in a message
    is read from the installed package's metadata."""
    text = str(value).strip().lower()
    kind = ("cuda:N" if ":" in text else text) if DEVICE_PATTERN.fullmatch(text) else None
    if kind not in allowed:
        index_note = " (N: a CUDA device index)" if "cuda:N" in allowed else ""
        raise ValueError(f"{setting} = {value!r}: must be one of {', '.join(allowed)}"
                         f"{index_note}")
    if kind == "cpu":
        return "cpu"
    if kind == "auto":
        if cuda_count is None:
            return "auto"
        return "cuda:0" if cuda_count > 0 else "cpu"
    index = int(text.partition(":")[2] or 0)
    if cuda_count is not None and index >= cuda_count:
        fallback = '"auto" or "cpu"' if "auto" in allowed else '"cpu"'
        raise ValueError(f"{setting} = {value!r}: {_torch_sees(cuda_count)}; use {fallback}")
    return f"cuda:{index}"


def _torch_sees(cuda_count: int) -> str:
    """What torch sees, with its version (a "+cpu" build says why there is no GPU)."""
    from importlib import metadata

    try:
        torch = f"torch {metadata.version('torch')}"
    except metadata.PackageNotFoundError:
        torch = "torch"
    if cuda_count <= 0:
        return f"{torch} sees 0 CUDA devices (a CPU-only build, no GPU, or no driver)"
    if cuda_count == 1:
        return f"{torch} sees 1 CUDA device (index 0)"
    return f"{torch} sees {cuda_count} CUDA devices (indices 0..{cuda_count - 1})"


class ServerSettings(_Section):
    """`[daemon.server]`: the control socket, the TCP port (and its TLS), and the bounds on
    what clients may hold of the control loop (connections, lines, buffers, time per pass)."""

    # Runtime directory for the control socket, the lock and the TCP token ("" = systemd's
    # $RUNTIME_DIRECTORY, else $XDG_RUNTIME_DIR/nhfd, else /tmp/nhfd-<uid>).
    runtime_dir: str = ""
    # Group of the control socket (mode 0660); "" = the daemon's own group.
    socket_group: str = ""
    # Loopback TCP port (0 = off). TCP clients must send `auth` with the token first; arming the
    # lasers is refused over TCP whatever the token.
    tcp_port: Annotated[int, Field(ge=0, le=65535)] = 0
    # File holding the TCP token ("" = <runtime_dir>/tcp.token, created mode 0600 at start).
    tcp_token_file: str = ""
    # Address the TCP port listens on. Loopback by default; any other address (remote clients)
    # needs tls_cert and tls_key, and the token is still asked for.
    tcp_host: str = "127.0.0.1"
    # PEM certificate (chain) and private key: the TCP port speaks TLS ("" = plain, loopback only).
    tls_cert: str = ""
    tls_key: str = ""
    # Longest request line accepted (bytes); Unix-socket clients connected at once (remote
    # peers never take these slots); requests in one batch.
    max_line_bytes: Annotated[int, Field(ge=1024, le=16_777_216)] = 65536
    max_clients: Annotated[int, Field(ge=1, le=4096)] = 64
    max_batch: Annotated[int, Field(ge=0, le=1024)] = 32
    # TCP clients connected at once; of them, those still in the TLS handshake or before `auth`,
    # each dropped auth_timeout_s after it connected unless it has authenticated.
    max_tcp_clients: Annotated[int, Field(ge=1, le=4096)] = 16
    max_unauthenticated: Annotated[int, Field(ge=1, le=1024)] = 4
    auth_timeout_s: Annotated[float, Field(ge=0.1, le=600)] = 5.0
    # Per connection: bytes received but not yet handled, and lines handled per control-loop
    # pass (empty lines count). A peer past the first is dropped.
    max_buffered_bytes: Annotated[int, Field(ge=4096, le=1 << 30)] = 1 << 20
    lines_per_poll: Annotated[int, Field(ge=1, le=4096)] = 64
    # The most time one control-loop pass spends serving clients before the heartbeat (s).
    tick_budget_s: Annotated[float, Field(ge=0.005, le=1.0)] = 0.05

    @model_validator(mode="after")
    def _tls_elsewhere(self) -> ServerSettings:
        problem = _tls_problem(self.tcp_host, self.tls_cert, self.tls_key, "daemon.server.")
        if problem:
            raise ValueError(problem.replace("host =", "tcp_host =", 1))
        return self


class ArmingSettings(_Section):
    """`[daemon.arming]`: who may arm the lasers, the bench's confirmation of each arm, whether
    remote peers may start emission, and the laser guardian (how it is found, its heartbeat,
    how often the channels are read back)."""

    # Who may arm the lasers, from the kernel's word on the Unix-socket peer (SO_PEERCRED): user
    # names, and groups whose members may ([] and [] = the daemon's own user only). Never over
    # TCP or the web view.
    users: list[str] = []
    groups: list[str] = []
    # A person at the bench confirms each arm: "none", "spacemouse" (a button of the configured
    # navigator) or "serial" (a key switch on confirm_port's CTS or DSR line; the port
    # "simulated" hosts a twin), within confirm_timeout_s of the request.
    confirm: Literal["none", "spacemouse", "serial"] = "none"
    confirm_timeout_s: Annotated[float, Field(ge=1, le=120)] = 10.0
    confirm_port: str = ""
    confirm_line: Literal["cts", "dsr"] = "cts"
    # Whether a TCP or web-view peer may start what makes a laser emit (a citl view, a
    # capture-mode snapshot, a power change or an enable while armed); off and disarm always.
    remote_emission: bool = False
    # "auto": use a running laser guardian, else start one; "spawn": always start one; "connect":
    # only use a running one (e.g. a separate service).
    guardian: Literal["auto", "spawn", "connect"] = "auto"
    # Heartbeat period (s): the control loop sends the laser guardian's heartbeat this often and
    # sleeps otherwise until an event; at most a quarter of the guardian's heartbeat timeout.
    heartbeat_s: Annotated[float, Field(ge=0.005, le=0.25)] = 0.1
    # How often the laser's channels are read back for `status` (s).
    laser_refresh_s: Annotated[float, Field(ge=0.05, le=60)] = 1.0


class FramesSettings(_Section):
    """`[daemon.frames]`: the model served and the frame window, the frame worker (threads,
    device, inference, cache, transport) and the colour timing of what it shows. (Not
    `nhfd.pipeline.settings.FrameSettings`, one frame's settings built from several sections.)"""

    # Model loaded at start ("" = none; then `load_model`). Its metadata must match [optics].
    model: str = ""
    # Hologram window rendered and propagated per frame, [width, height] in pixels ([] = the
    # model's training size). The trained fx is kept, so another size shows more or less of the
    # scene at the same scale.
    size_px: Annotated[list[Pixels], Field(max_length=2)] = []
    # Serve a frame window whose size (padded to the model's input multiple) is not among the
    # model's checked_sizes (`nhfd model check-sizes`); false: such a model load is refused.
    allow_unchecked_sizes: bool = False
    # Serve a model tuned for another bench's calibration (its metadata's tuned_for names it,
    # `nhfd model tune`), or one tuned for a bench while none is configured; false: such a model
    # load is refused, naming both, and the model in service stays. `status` says when it is on.
    allow_other_bench: bool = False
    # Frames kept by the frame worker, keyed by view and settings (a revisited view is instant).
    cache_frames: Annotated[int, Field(ge=0, le=1024)] = 16
    # Threads of the frame worker process for torch (intra-op; inter-op is 1), numba and
    # onnxruntime (intra-op; inter-op 1, spinning off), and numba's threading layer.
    worker_threads: Annotated[int, Field(ge=1, le=256)] = 2
    worker_threading_layer: Literal["omp", "tbb", "workqueue"] = "omp"
    # onnxruntime execution providers of the frame worker's session, in order of preference
    # (e.g. ["CUDAExecutionProvider", "CPUExecutionProvider"]). One this onnxruntime lacks makes
    # load_model fail with the list of those available (the previous model keeps running).
    onnx_providers: Annotated[list[str], Field(min_length=1)] = ["CPUExecutionProvider"]
    # The model's int8 sibling (<stem>-int8.onnx beside it) on the CPU path: "auto" serves it
    # where its metadata records a held-out loss within 0.5 dB of this float model, "never"
    # serves the float model, "always" the int8 one whenever it exists.
    int8: Literal[INT8_MODES] = "auto"
    # How frames cross from the frame worker: "shm" (shared-memory slots, only a small message
    # on the pipe) or "pickle" (the arrays pickled through the pipe; for comparison).
    transport: Literal[FRAME_TRANSPORTS] = "shm"
    # Colour timing (docs/design.md, "The hardware"): "single" (daemon.frames.single_colour's
    # pattern in every channel, only that diode may be on), "capture" (snapshots step through
    # the colours: all off, the colour's pattern, settle, that diode on, capture, off; clients
    # only set powers) or "hw-sync" (each colour's pattern in its own channel, lasers modulated
    # by the SLM's sync).
    colour_mode: Literal["single", "capture", "hw-sync"] = "hw-sync"
    single_colour: Literal["red", "green", "blue"] = "green"
    # Where the frame worker computes frames: "auto" (the first CUDA device when torch sees one
    # and gsplat is installed, else the CPU), "cpu", "cuda" or "cuda:N". On CUDA every stage runs
    # on the GPU (gsplat, the network as daemon.frames.inference says, propagation, coding) and
    # only the uint8 panel region crosses to the host; a CUDA device torch does not see fails the
    # load.
    device: str = "auto"
    # TensorRT engines built for the frame worker, one folder per model hash, input shape and GPU
    # ("" = $XDG_CACHE_HOME/nhfd/tensorrt, else ~/.cache/nhfd/tensorrt).
    engine_cache_dir: str = ""
    # What runs the network (`nhfd.pipeline.device.inference_backend`): "onnxruntime", "torch"
    # (the model file's network rebuilt as a torch module, `nhfd.models.torch_model`), or
    # "auto": onnxruntime, except on a CUDA device whose onnxruntime has no CUDA provider.
    inference: Literal[INFERENCES] = "auto"
    # On CUDA, each frame stage after the render (network in torch, propagation, coding) is
    # replayed as one CUDA graph (`nhfd.pipeline.device.CudaGraphs`); false launches every
    # kernel from the host. No effect on the CPU.
    cuda_graphs: bool = True

    @model_validator(mode="after")
    def _device_named(self) -> FramesSettings:
        device_choice(self.device, "device", cuda_count=None)  # the name; torch sees at load
        return self

    @model_validator(mode="after")
    def _size_is_width_and_height(self) -> FramesSettings:
        if len(self.size_px) not in (0, 2):
            raise ValueError(f"size_px = {self.size_px}: give [width, height] or []")
        return self


class AuditSettings(_Section):
    """`[daemon.audit]`: the audit log (where, its rotation, its summaries), the log lines'
    format, and the session recording."""

    # Audit log, JSON lines ("" = $LOGS_DIRECTORY/audit.jsonl under systemd, else
    # <runtime_dir>/audit.jsonl).
    file: str = ""
    # The audit log is rotated when it would pass max_bytes (audit.jsonl -> .1 -> ..., backups
    # kept), so it never holds more than max_bytes * (backups + 1).
    max_bytes: Annotated[int, Field(ge=4096, le=2**40)] = 10_485_760
    backups: Annotated[int, Field(ge=1, le=100)] = 5
    # Repeated set_view from one caller, and repeated refusals of one method with one error
    # code from anyone, are written once per window of this length (s) plus "N more like this".
    summary_s: Annotated[float, Field(ge=0.1, le=3600)] = 1.0
    # Log lines on stderr: "logfmt" (key=value) or "json".
    log_format: Literal["logfmt", "json"] = "logfmt"
    # Session recording: every bench-changing request, timed, as JSON lines ("" = off;
    # `nhfd serve --record FILE` sets it); `nhfd replay FILE` plays it against a daemon.
    record: str = ""


class PathSettings(_Section):
    """`[daemon.paths]`: the scene loaded at start, the directories requests may read from and
    write into, and the budgets of what they load and keep (Gaussians, memory, jobs, files)."""

    # Scene loaded at start ("" = none); directories load_scene may read from.
    scene: str = ""
    scene_dirs: list[str] = ["scenes"]
    # Directories load_model may read from; directory snapshots are written into.
    model_dirs: list[str] = ["models"]
    snapshot_dir: str = "out/snapshots"
    # Directories show_pattern may read calibration frames (.npy) from and capture may write
    # images (.npy) into (`nhfd calib capture` through the daemon: its --out lies inside one).
    pattern_dirs: list[str] = ["calib"]
    # Scenes: the most Gaussians a scene may declare, and the memory a scene load may take (MB).
    max_gaussians: Annotated[int, Field(ge=1, le=1_000_000_000)] = 20_000_000
    scene_memory_mb: Annotated[int, Field(ge=64, le=1 << 20)] = 8192
    # Models: the memory a candidate model's first session may take (MB); more is refused and
    # the serving model stays.
    model_memory_mb: Annotated[int, Field(ge=64, le=1 << 20)] = 4096
    # Finished jobs kept for `status`.
    jobs_kept: Annotated[int, Field(ge=1, le=10000)] = 32
    # The soft limit on open files is raised to this at start (or to the hard limit, if lower).
    open_files: Annotated[int, Field(ge=256, le=1 << 20)] = 8192


class BenchSettings(_Section):
    """`[daemon.bench]`: the focus mapping without a calibration, the navigator's period and the
    simulated camera's sensor region."""

    # Focus without a calibration file: stage_mm = stage_at_reference_mm + z_mm, with z_mm (the
    # hologram depth from the reference plane) limited to focus_range_mm.
    stage_at_reference_mm: Annotated[float, Field(ge=-1000, le=1000)] = 12.5
    focus_range_mm: Annotated[list[float], Field(min_length=2, max_length=2)] = [-5.0, 5.0]
    # How often the control loop reads the navigator (devices.navigator) and moves the view (s).
    navigator_period_s: Annotated[float, Field(ge=0.005, le=1.0)] = 0.05
    # The simulated camera's sensor region, [top, left, height, width] in sensor pixels ([] =
    # the whole sensor). A small region keeps simulated captures fast; real cameras ignore it.
    camera_roi_px: Annotated[list[Annotated[int, Field(ge=0, le=65536)]],
                             Field(max_length=4)] = []

    @model_validator(mode="after")
    def _focus_range_ordered(self) -> BenchSettings:
        low, high = _finite("focus_range_mm", self.focus_range_mm)
        if not low < high:
            raise ValueError(f"focus_range_mm = {self.focus_range_mm}: needs min < max")
        return self

    @model_validator(mode="after")
    def _camera_roi_is_a_region(self) -> BenchSettings:
        if len(self.camera_roi_px) not in (0, 4) or (
                self.camera_roi_px and min(self.camera_roi_px[2:]) < 1):
            raise ValueError(f"camera_roi_px = {self.camera_roi_px}: give [top, left, height, "
                             "width] (height and width >= 1) or []")
        return self


class DaemonSettings(_Section):
    """`nhfd serve`: one section per part of the daemon, each part handed its own.

    Relative paths are taken from the daemon's working directory (the unit's WorkingDirectory).
    """

    # The sockets, TCP and TLS, and the control loop's serving budget.
    server: ServerSettings = ServerSettings()
    # Arming, its confirmation, and the laser guardian.
    arming: ArmingSettings = ArmingSettings()
    # The model, the frame worker and the colour timing.
    frames: FramesSettings = FramesSettings()
    # The audit log, log lines and the session recording.
    audit: AuditSettings = AuditSettings()
    # Paths requests may use, and the budgets of loads and jobs.
    paths: PathSettings = PathSettings()
    # The focus mapping, the navigator and the simulated camera's region.
    bench: BenchSettings = BenchSettings()
    # The live web view (nhfd.web), off by default.
    web: WebSettings = WebSettings()


# Where each key of the flat `[daemon]` table before the sections went: old key -> its dotted
# key under [daemon] now. The one place the mapping lives: `migrate_daemon_keys` moves a file's
# old keys with it, `nhfd config check` prints the moved file, the docs' table
# (docs/daemon.md, "Settings moved in this release") is tested against it.
DAEMON_KEYS_MOVED: dict[str, str] = {
    **{key: f"server.{key}" for key in (
        "runtime_dir", "socket_group", "tcp_port", "tcp_token_file", "tcp_host", "tls_cert",
        "tls_key", "max_line_bytes", "max_clients", "max_batch", "max_tcp_clients",
        "max_unauthenticated", "auth_timeout_s", "max_buffered_bytes", "lines_per_poll",
        "tick_budget_s")},
    "arm_users": "arming.users",
    "arm_groups": "arming.groups",
    "arm_confirm": "arming.confirm",
    "arm_confirm_timeout_s": "arming.confirm_timeout_s",
    "arm_confirm_port": "arming.confirm_port",
    "arm_confirm_line": "arming.confirm_line",
    "remote_emission": "arming.remote_emission",
    "guardian": "arming.guardian",
    "tick_s": "arming.heartbeat_s",
    "laser_refresh_s": "arming.laser_refresh_s",
    "model": "frames.model",
    "frame_size_px": "frames.size_px",
    "allow_unchecked_sizes": "frames.allow_unchecked_sizes",
    "frame_cache_frames": "frames.cache_frames",
    "worker_threads": "frames.worker_threads",
    "worker_threading_layer": "frames.worker_threading_layer",
    "onnx_providers": "frames.onnx_providers",
    "int8": "frames.int8",
    "frame_transport": "frames.transport",
    "colour_mode": "frames.colour_mode",
    "single_colour": "frames.single_colour",
    "device": "frames.device",
    "engine_cache_dir": "frames.engine_cache_dir",
    "inference": "frames.inference",
    "cuda_graphs": "frames.cuda_graphs",
    "audit_log": "audit.file",
    "audit_max_bytes": "audit.max_bytes",
    "audit_backups": "audit.backups",
    "audit_summary_s": "audit.summary_s",
    "log_format": "audit.log_format",
    "record": "audit.record",
    **{key: f"paths.{key}" for key in (
        "scene", "scene_dirs", "model_dirs", "snapshot_dir", "pattern_dirs", "max_gaussians",
        "scene_memory_mb", "model_memory_mb", "jobs_kept", "open_files")},
    **{key: f"bench.{key}" for key in (
        "stage_at_reference_mm", "focus_range_mm", "navigator_period_s", "camera_roi_px")},
}


class CalibrationSettings(_Section):
    """`[calibration]`: the calibration.toml the daemon applies ("" = none)."""

    # calibration.toml written by `nhfd calib fit` ("" = none: the configured phase curves, sign
    # and daemon.bench.stage_at_reference_mm focus mapping apply). The daemon applies its phase
    # curves and sign, and maps focus through its depth -> stage fit.
    file: str = ""


# The frame tiers (`nhfd.views.QUALITY_TIERS`, where they are defined and described).
Quality = Literal[QUALITY_TIERS]  # type: ignore[valid-type]
# The most subframes a frame has and the most planes a refinement fits or a focal stack holds.
MAX_SUBFRAMES = 16
MAX_PLANES = 16


class RefineSettings(_Section):
    """`[refine]`: frames better than the network's (`nhfd.pipeline.refine`), at the display
    (`nhfctl set-view --quality`) and offline (`nhfd refine`): the tier, the optimisation's
    budget and stopping rule, and time multiplexing."""

    # The tier a view gets unless it asks for another ("network" = open loop, as before).
    quality: Quality = "network"
    # The budget: refinement stops at whichever comes first.
    iterations: Annotated[int, Field(ge=1, le=100_000)] = 200
    seconds: Annotated[float, Field(gt=0, le=3600)] = 60.0
    # Converged: the best loss fell by less than this fraction over the last `patience`
    # iterations (0 = never stop early).
    tolerance: Annotated[float, Field(ge=0, le=0.5)] = 1e-3
    patience: Annotated[int, Field(ge=1, le=10_000)] = 25
    # Adam's step on the SLM phase (rad): a few grey levels (2 pi / 256 = 0.025 rad each).
    learning_rate_rad: Annotated[float, Field(gt=0, le=1.0)] = 0.05
    # citl's step: smaller, since each step's loss is a noisy capture (with 0.05 the camera's
    # loss was best after 3 or 4 steps and then grew; 0.02 still gained at 8, docs/refine.md).
    citl_learning_rate_rad: Annotated[float, Field(gt=0, le=1.0)] = 0.02
    # Time multiplexing: K subframes optimised jointly on their mean intensity and shown in
    # turn (one camera exposure spans the K flips).
    subframes: Annotated[int, Field(ge=1, le=MAX_SUBFRAMES)] = 1
    # The planes fitted: this many depth quantiles of the view's content.
    planes: Annotated[int, Field(ge=1, le=MAX_PLANES)] = 3
    # Progressive mode: a better frame replaces the one shown every this many iterations.
    swap_every: Annotated[int, Field(ge=1, le=10_000)] = 10
    # The bench model sgd and citl refine through: "learned" uses the calibration's learned
    # bench when it has one (`nhfd calib learn`, docs/learned_bench.md) and the parametric
    # model otherwise; "parametric" always the parametric model.
    bench_model: Literal["learned", "parametric"] = "learned"


def _bounds(name: str) -> str:
    """RefineSettings' allowed range of `name`, e.g. "1 <= iterations <= 100000"."""
    lo = hi = ""
    for m in RefineSettings.model_fields[name].metadata:
        for attr, sym in (("ge", "<="), ("gt", "<")):
            if getattr(m, attr, None) is not None:
                lo = f"{getattr(m, attr):g} {sym} "
        for attr, sym in (("le", "<="), ("lt", "<")):
            if getattr(m, attr, None) is not None:
                hi = f" {sym} {getattr(m, attr):g}"
    return f"{lo}{name}{hi}"


def refine_settings(base: RefineSettings, overrides: Mapping[str, Any]) -> RefineSettings:
    """`base` (a configuration's `[refine]`) with `overrides` (None: keep), validated as
    RefineSettings: a ValueError naming `refine.<key>`, the value and the allowed range."""
    given = {k: v for k, v in overrides.items() if v is not None}
    try:
        return RefineSettings.model_validate({**base.model_dump(), **given})
    except ValidationError as exc:
        problems = []
        for e in exc.errors():
            key = ".".join(str(p) for p in e["loc"])
            allowed = _bounds(key) if key in RefineSettings.model_fields else ""
            problems.append(f"refine.{key} = {e.get('input')!r}: "
                            + (f"must be {allowed}" if allowed else str(e["msg"])))
        raise ValueError("; ".join(problems)) from None


class Config(_Section):
    """The whole validated configuration, one typed section per TOML table; the rules joining
    sections (`cross_field_problems`) apply at construction."""

    slm: SLMSettings = SLMSettings()
    optics: OpticsSettings = OpticsSettings()
    coding: CodingSettings = CodingSettings()
    devices: DeviceSettings = DeviceSettings()
    model: ModelSettings = ModelSettings()

    daemon: DaemonSettings = DaemonSettings()
    calibration: CalibrationSettings = CalibrationSettings()
    refine: RefineSettings = RefineSettings()

    @model_validator(mode="after")
    def _cross_field(self) -> Config:
        problems = cross_field_problems(self)
        if problems:
            raise ValueError("; ".join(problems))
        return self


def cross_field_problems(config: Config) -> list[str]:
    """The rules that join sections, each problem naming its keys (`Config` validation applies
    them; `nhfd serve` and `nhfd config check` both see them there)."""
    o, s = config.optics, config.slm
    frames, arming = config.daemon.frames, config.daemon.arming
    panel = f"the panel {s.width_px} x {s.height_px} (slm.width_px x height_px)"
    problems = []
    if o.hologram_width_px > s.width_px or o.hologram_height_px > s.height_px:
        problems.append(f"optics.hologram_width_px x hologram_height_px = {o.hologram_width_px} "
                        f"x {o.hologram_height_px} does not fit {panel}")
    size = frames.size_px
    if size and (size[0] > s.width_px or size[1] > s.height_px):
        problems.append(f"daemon.frames.size_px = {size} does not fit {panel}")
    # The control loop sends the guardian's heartbeat once per heartbeat_s: a late beat or two
    # must not let the guardian switch the lasers off under a healthy daemon.
    timeout_s = config.devices.readybeam.guardian.heartbeat_timeout_s
    if arming.heartbeat_s * HEARTBEATS_PER_TIMEOUT > timeout_s:
        problems.append(f"daemon.arming.heartbeat_s = {arming.heartbeat_s:g} s: must be at most 1/"
                        f"{HEARTBEATS_PER_TIMEOUT} of devices.readybeam.guardian."
                        f"heartbeat_timeout_s = {timeout_s:g} s")
    return problems


# Heartbeats the control loop sends within one guardian heartbeat timeout, at least.
HEARTBEATS_PER_TIMEOUT = 4


@dataclass(frozen=True)
class LoadedConfig:
    """A validated configuration, the file it came from (None: the packaged default), for
    every dotted key where its value came from, and the keys the file set at an old place that
    were moved to their new one, as (old, new) dotted keys (`migrate_daemon_keys`)."""

    config: Config
    path: Path | None
    sources: dict[str, str]
    migrations: tuple[tuple[str, str], ...] = ()


def default_text() -> str:
    """The packaged default configuration's text (`nhfd/default.toml`)."""
    return resources.files("nhfd").joinpath("default.toml").read_text(encoding="utf-8")


def search_paths(env: Mapping[str, str] | None = None, cwd: Path | None = None) -> list[Path]:
    """Optional locations after --config and $NHFD_CONFIG, in the order they are tried."""
    env = os.environ if env is None else env
    cwd = Path.cwd() if cwd is None else cwd
    xdg = env.get("XDG_CONFIG_HOME") or str(Path(env.get("HOME", "~")).expanduser() / ".config")
    return [cwd / "nhfd.toml", Path(xdg) / "nhfd" / "nhfd.toml", Path("/etc/nhfd/nhfd.toml")]


def find_config(
    explicit: str | os.PathLike[str] | None = None,
    env: Mapping[str, str] | None = None,
    cwd: Path | None = None,
) -> Path | None:
    """The file to use, or None for the packaged default alone.

    A file named explicitly (--config or $NHFD_CONFIG) must exist: silently falling back to the
    default would drive the bench with settings nobody chose.
    """
    env = os.environ if env is None else env
    for origin, named in (("--config", explicit), ("$NHFD_CONFIG", env.get("NHFD_CONFIG"))):
        if named:
            path = Path(named).expanduser()
            if not path.is_file():
                raise ConfigError(f"{origin} names {path}, which is not a readable file")
            return path
    for path in search_paths(env, cwd):
        if path.is_file():
            return path
    return None


def _parse(text: str, origin: str) -> dict[str, Any]:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{origin}: not valid TOML: {exc}") from None


def _overlay(base: dict[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in top.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), dict):
            merged[key] = _overlay(merged[key], value)
        else:
            merged[key] = value
    return merged


def migrate_daemon_keys(user: Mapping[str, Any], origin: str
                        ) -> tuple[dict[str, Any], list[tuple[str, str]]]:
    """One parsed file (`user`, before the overlay on the default) with every old flat key
    under `[daemon]` moved to its section (`DAEMON_KEYS_MOVED`), and the moves as (old, new)
    dotted keys in the file's order. Nothing else changes; nothing is warned here
    (`load_config` warns once per move).

    A file that sets a key at both its old and its new place raises `ConfigError` naming both:
    which one it meant is not ours to guess."""
    out = dict(user)
    daemon = user.get("daemon")
    if not isinstance(daemon, Mapping) or not any(k in DAEMON_KEYS_MOVED for k in daemon):
        return out, []
    kept: dict[str, Any] = {}
    moves: list[tuple[str, str]] = []
    clashes: list[str] = []
    for key, value in daemon.items():
        if key not in DAEMON_KEYS_MOVED:
            # a section the file already has is copied, so moving into it changes no input
            kept[key] = dict(value) if isinstance(value, Mapping) else value
    for old, value in daemon.items():
        if old not in DAEMON_KEYS_MOVED:
            continue
        section, name = DAEMON_KEYS_MOVED[old].split(".")
        new = f"daemon.{section}.{name}"
        target = kept.setdefault(section, {})
        if not isinstance(target, dict):
            raise ConfigError(f"{origin}: daemon.{old} moves to {new}, but daemon.{section} = "
                              f"{target!r} is not a table")
        if name in target:
            clashes.append(f"daemon.{old} = {value!r} and {new} = {target[name]!r} are both set "
                           f"({new} is daemon.{old}'s new place): keep only {new}")
            continue
        target[name] = value
        moves.append((f"daemon.{old}", new))
    if clashes:
        raise ConfigError(f"{origin}: " + "; ".join(clashes))
    out["daemon"] = kept
    return out, moves


def _toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else json.dumps(key)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):  # validation refuses these before anything is printed
            raise ValueError(f"{value!r}: not finite")
        return repr(value)
    if isinstance(value, str):
        # a JSON string is a TOML basic string, but for DEL, which TOML wants escaped
        return json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}"
                               for k, v in value.items()) + "}"
    # dates and times: tomllib reads them; no setting takes one
    raise ValueError(f"{value!r}: a {type(value).__name__}, which no setting takes")


def toml_text(data: Mapping[str, Any], prefix: str = "") -> str:
    """`data` (a parsed configuration, or part of one) as TOML that `tomllib` reads back equal:
    each table's own values first, then its subtables under their dotted headers."""
    lines = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in data.items()
             if not isinstance(v, Mapping)]
    out = "\n".join(lines) + ("\n" if lines else "")
    for key, value in data.items():
        if isinstance(value, Mapping):
            name = f"{prefix}{_toml_key(key)}"
            body = toml_text(value, f"{name}.")
            own = any(not isinstance(v, Mapping) for v in value.values())
            # a table of tables needs no header of its own; an empty one does, to exist
            chunk = (f"[{name}]\n" if own or not value else "") + body
            out += ("\n" if out else "") + chunk
    return out


def migrated_text(path: str | os.PathLike[str]) -> tuple[str, list[tuple[str, str]]]:
    """The file at `path` as TOML with its old keys in their new places (only what the file
    itself sets, values as they were; its comments are not kept), and the moves."""
    user = _parse(_read(Path(path)), str(path))
    migrated, moves = migrate_daemon_keys(user, str(path))
    return toml_text(migrated), moves


def _leaves(data: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(_leaves(value, name + "."))
        else:
            out[name] = value
    return out


def _describe(error: Mapping[str, Any], model: type[BaseModel]) -> str:
    loc = [str(p) for p in error["loc"]]
    key = ".".join(loc)
    value = error.get("input")
    message = str(error["msg"]).removeprefix("Value error, ")
    if error["type"] == "extra_forbidden":
        allowed = _allowed_keys(model, loc[:-1])
        return f"{key}: unknown key; allowed here: {', '.join(allowed)}"
    if error["type"] == "value_error" and (not loc or isinstance(value, Mapping)):
        # a section's own rule: its message starts with the key inside the section
        return f"{key}.{message}" if loc else message
    if error["type"] == "finite_number" or (isinstance(value, float) and not math.isfinite(value)):
        return f"{key} = {value!r}: not finite"
    return f"{key} = {value!r}: {message}"


def _allowed_keys(model: type[BaseModel], path: list[str]) -> list[str]:
    for part in path:
        field = model.model_fields.get(part)
        annotation = field.annotation if field else None
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            return []
        model = annotation
    return sorted(model.model_fields)


def validate(data: Mapping[str, Any], origin: str) -> Config:
    """Validate a parsed TOML mapping (already overlaid on the default) as a `Config`."""
    try:
        return Config.model_validate(dict(data))
    except ValidationError as exc:
        lines = [_describe(e, Config) for e in exc.errors()]
        raise ConfigError(f"{origin}: " + "; ".join(lines)) from None


def load_config(
    explicit: str | os.PathLike[str] | None = None,
    env: Mapping[str, str] | None = None,
    cwd: Path | None = None,
) -> LoadedConfig:
    """Find, read, overlay on the packaged default and validate the configuration."""
    default = _parse(default_text(), DEFAULT_NAME)
    path = find_config(explicit, env, cwd)
    sources = dict.fromkeys(_leaves(default), DEFAULT_NAME)
    data = default
    moves: list[tuple[str, str]] = []
    if path is not None:
        user, moves = migrate_daemon_keys(_parse(_read(path), str(path)), str(path))
        for old, new in moves:
            warnings.warn(f"{path}: {old} is now {new}; read from its old place (nhfd config "
                          "check prints the file migrated)", ConfigMigrationWarning,
                          stacklevel=2)
        data = _overlay(default, user)
        sources.update(dict.fromkeys(_leaves(user), str(path)))  # the keys' new places
    config = validate(data, str(path) if path else DEFAULT_NAME)
    return LoadedConfig(config=config, path=path, sources=sources, migrations=tuple(moves))


def _read(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None


def check_file(path: str | os.PathLike[str]) -> Config:
    """Validate one file as a lab would use it (overlaid on the packaged default). The files it
    names are opened by `nhfd.calibration.check_calibration_file`."""
    return load_config(explicit=path, env={}).config
