"""Driver settings: validated once, units in the key names, safe defaults.

This module imports nothing from nhfd: the guardian process and `nhfd laser-off` validate laser
settings without loading the rest of the package, and `nhfd.config` nests these models in its
`Config`. Like `nhfd.config`, models are strict (TOML is typed) and frozen.

Protocol facts that a real unit might not share (MeCom parameter ids, channel instances, APT
scaling) are settings, because docs/design.md ("The hardware") marks them unverified or
model-dependent.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

# Colour order everywhere in nhfd: R, G, B. Lists of per-colour values follow it.
COLOURS: tuple[str, str, str] = ("red", "green", "blue")


class _Settings(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)


Seconds = Annotated[float, Field(gt=0, le=3600)]
Percent = Annotated[float, Field(ge=0, le=100)]
ParamId = Annotated[int, Field(ge=0, le=0xFFFF)]


# Why the camera in the loop (`citl`, and the learned bench's captures) cannot capture with these
# lasers; it never arms and never sets a power, so the remedy is always a person's.
NEVER_ARMS = ("{who} never arms: arm the lasers (nhfctl laser arm) and set each colour's "
              "power (nhfctl laser power COLOUR PCT), then ask again")


def citl_laser_refusal(fault: str | None, armed: bool, armed_remaining_s: float,
                       powers_pct: dict[str, float], who: str = "citl") -> str | None:
    """Why citl (or `who` else captures with citl's sequence) may not switch the diodes on
    (None: it may): a fault, the arming absent or expired, or a colour at 0 % power (it fits
    every colour). One rule for the daemon's capture job (`nhfd.daemon.citl`), the offline loop
    (`nhfd.calib.citl.CameraLoop`) and `nhfd calib learn`'s check before it starts."""
    never = NEVER_ARMS.format(who=who)
    if fault:
        return f"laser fault: {fault}"
    if not armed or armed_remaining_s <= 0:
        return f"the lasers are not armed; {never}"
    dark = [ch for ch in COLOURS if powers_pct.get(ch, 0.0) <= 0]
    if dark:
        return f"{', '.join(dark)} at 0% power: {who} fits every colour; {never}"
    return None


def _finite(values: list[float]) -> list[float]:
    if not all(math.isfinite(v) for v in values):
        raise ValueError("must be finite")
    return values


# ---------------------------------------------------------------------------------------- lasers


class MecomParameterIds(_Settings):
    """READYBeam parameter ids as used by the open-source driver, unverified against FISBA's list:
    every write is read back and a mismatch is a fault."""

    device_type: ParamId = 100
    status: ParamId = 104
    # Meerstetter's common parameter "serial number" (ids 100-109 are common to its devices, as
    # in Meerstetter's MeCom C API: 100 device type, 101 hardware version, 102 serial number,
    # 103 firmware version, 104 status). Read-only; a unit that lacks it reports no serial.
    serial_number: ParamId = 102
    digital_control: ParamId = 7000
    channel_enable: ParamId = 7006
    channel_power: ParamId = 7013
    # "Any laser on": read after all-off as a third confirmation (see check_any_laser_on).
    any_laser_on: ParamId = 7010


class GuardianSettings(_Settings):
    """`[devices.readybeam.guardian]`: the laser guardian process's socket, heartbeat timeout
    and tick (s), and how long the daemon waits for it to start and to answer (s)."""

    # Unix socket the daemon and `nhfd laser-off` talk to. "" = laser.sock in the daemon's runtime
    # directory (so two daemons with two runtime directories have two guardians).
    socket_path: str = ""
    # All channels off when no heartbeat arrives for this long (the daemon sends one per loop).
    heartbeat_timeout_s: Annotated[float, Field(ge=0.05, le=10)] = 0.5
    # How often the guardian checks heartbeats and arming expiry.
    tick_s: Annotated[float, Field(ge=0.005, le=0.5)] = 0.05
    # How long a spawner waits for the guardian to identify the laser and listen.
    start_timeout_s: Seconds = 15.0
    # The daemon's bound on a heartbeat's answer; a guardian it started that misses it is hung:
    # SIGKILLed and replaced by one that switches every channel off (well inside 1 s in all).
    heartbeat_reply_timeout_s: Annotated[float, Field(ge=0.01, le=5)] = 0.25


class LaserSettings(_Settings):
    """`[devices.readybeam]`: the READYBeam's port or USB serial, MeCom address and device type,
    channel instances and power caps (% per colour, R, G, B), arming limit, timeouts (s) and
    reconnection."""

    # Port path (/dev/ttyUSB0); "" = find the port by usb_serial.
    port: str = ""
    # USB serial number of the controller's FTDI chip (`nhfd devices` lists them).
    usb_serial: str = ""
    baud: Annotated[int, Field(ge=1200, le=3_000_000)] = 57600
    # MeCom address (0 reaches the unit at any address; 255 is broadcast, which never answers).
    address: Annotated[int, Field(ge=0, le=254)] = 0
    # `?VR 100` must answer this before anything is written (1171: the RGB READYBeam).
    device_type: int = 1171
    # MeCom instances of the R, G, B diodes.
    channel_instances: Annotated[list[Annotated[int, Field(ge=1, le=255)]],
                                 Field(min_length=3, max_length=3)] = [1, 2, 3]
    # Power cap per channel, R, G, B, in percent of the diode's full power. No command exceeds
    # it: the driver clamps whatever the caller asks.
    max_power_pct: Annotated[list[Percent], Field(min_length=3, max_length=3)] = [10.0] * 3
    # Write digital control = 1 (take) on open, so the host, not the front panel, sets enables.
    take_control: bool = True
    # After all-off, also read "any laser on" (the least certain id: false skips it).
    check_any_laser_on: bool = True
    # Longest arming a person may ask for; arming expires and is never restored automatically.
    arm_max_s: Seconds = 900.0
    reply_timeout_s: Annotated[float, Field(gt=0, le=10)] = 0.25
    # Resends (with a new sequence number) after a timeout or a corrupt reply.
    retries: Annotated[int, Field(ge=0, le=10)] = 2
    # A read-back further than this from the value written is a fault.
    readback_tolerance_pct: Annotated[float, Field(ge=0, le=1)] = 0.01
    reconnect_attempts: Annotated[int, Field(ge=1, le=100)] = 5
    reconnect_backoff_s: Annotated[float, Field(ge=0, le=60)] = 0.2
    reconnect_backoff_max_s: Annotated[float, Field(ge=0, le=600)] = 5.0
    # FTDI latency timer set on open (the default 16 ms adds to every reply); 0 leaves it.
    latency_timer_ms: Annotated[int, Field(ge=0, le=255)] = 1
    parameter_ids: MecomParameterIds = MecomParameterIds()
    guardian: GuardianSettings = GuardianSettings()

    @field_validator("channel_instances")
    @classmethod
    def _distinct(cls, v: list[int]) -> list[int]:
        if len(set(v)) != len(v):
            raise ValueError(f"channel instances must be distinct, got {v}")
        return v

    def cap_pct(self, channel: str) -> float:
        """The power cap (% of full power) of `channel` ("red", "green" or "blue")."""
        return self.max_power_pct[COLOURS.index(channel)]

    def instance(self, channel: str) -> int:
        """The MeCom instance of `channel`'s diode ("red", "green" or "blue")."""
        return self.channel_instances[COLOURS.index(channel)]


# ----------------------------------------------------------------------------------------- stage


class StageSettings(_Settings):
    """`[devices.apt]`: the Thorlabs controller's port or USB serial, channel, allowed models,
    encoder scaling (counts/mm), velocity (mm/s), acceleration (mm/s^2), soft limits (mm) and
    timeouts (s)."""

    # Port path; "" = find by usb_serial (27xxxxxx KDC101, 83xxxxxx TDC001).
    port: str = ""
    usb_serial: str = ""
    baud: Annotated[int, Field(ge=1200, le=3_000_000)] = 115200
    rtscts: bool = True
    # Pulse RTS and purge the buffers after open (Thorlabs' APT initialisation). An adapter
    # without modem-control lines refuses it ("Inappropriate ioctl for device"): false skips it.
    rts_reset: bool = True
    # APT channel ident of the motor (1 on single-channel controllers).
    channel: Annotated[int, Field(ge=1, le=16)] = 1
    # HW_GET_INFO's model must start with one of these; anything else is refused.
    allowed_models: Annotated[list[str], Field(min_length=1)] = ["KDC101", "TDC001"]
    # Encoder counts per mm: 34554.96 for Z8-series actuators in current documents (older code
    # uses 34304).
    counts_per_mm: Annotated[float, Field(gt=0, le=1e9)] = 34554.96
    # APT velocity time unit T: velocity units = counts/mm * T * 65536 * v (mm/s),
    # acceleration units = counts/mm * T^2 * 65536 * a (mm/s^2). 2048 / 6e6 s on KDC101/TDC001.
    time_unit_s: Annotated[float, Field(gt=0, le=1)] = 2048 / 6e6
    velocity_mm_s: Annotated[float, Field(gt=0, le=50)] = 2.0
    acceleration_mm_s2: Annotated[float, Field(gt=0, le=100)] = 1.5
    # Targets outside [min, max] are refused before any byte is sent.
    soft_limits_mm: Annotated[list[float], Field(min_length=2, max_length=2)] = [0.0, 25.0]
    # A move that ends within this distance of its target has arrived, even with a limit switch
    # pressed there (a target at either end of the travel); short of it, a switch is an error.
    arrival_tolerance_mm: Annotated[float, Field(ge=0, le=0.1)] = 0.001
    # Refuse moves until the stage has been homed (position means nothing before).
    require_homed: bool = True
    home_timeout_s: Seconds = 60.0
    move_timeout_s: Seconds = 60.0
    reply_timeout_s: Annotated[float, Field(gt=0, le=30)] = 1.0
    # Status updates stop unless acknowledged about once a second.
    keepalive_period_s: Annotated[float, Field(ge=0.01, le=5)] = 1.0
    # A TDC001 can lock up when homed right after its channel is enabled: wait this long.
    enable_settle_s: Annotated[float, Field(ge=0, le=10)] = 1.0
    reconnect_attempts: Annotated[int, Field(ge=1, le=100)] = 5
    reconnect_backoff_s: Annotated[float, Field(ge=0, le=60)] = 0.2
    reconnect_backoff_max_s: Annotated[float, Field(ge=0, le=600)] = 5.0
    latency_timer_ms: Annotated[int, Field(ge=0, le=255)] = 1

    @model_validator(mode="after")
    def _limits_ordered(self) -> StageSettings:
        low, high = _finite(self.soft_limits_mm)
        if not low < high:
            raise ValueError(f"soft_limits_mm = {self.soft_limits_mm}: needs min < max")
        return self

    @property
    def velocity_units(self) -> int:
        """`velocity_mm_s` in APT velocity units (counts/mm * T * 65536 * v)."""
        return round(self.counts_per_mm * self.time_unit_s * 65536 * self.velocity_mm_s)

    @property
    def acceleration_units(self) -> int:
        """`acceleration_mm_s2` in APT acceleration units (counts/mm * T^2 * 65536 * a)."""
        return round(self.counts_per_mm * self.time_unit_s**2 * 65536 * self.acceleration_mm_s2)


# ------------------------------------------------------------------------------------------- SLM


class SLMOutputSettings(_Settings):
    """How frames reach the panel. Geometry (width_px, height_px) stays in nhfd's [slm]."""

    # Liquid-crystal settle time after a frame before a capture means anything.
    settle_ms: Annotated[float, Field(ge=0, le=2000)] = 50.0
    # Framebuffer backend: device node and the sysfs root its geometry is read under.
    framebuffer_device: str = "/dev/fb1"
    sysfs_root: str = "/sys"
    # DRM connector that feeds the SLM (a name under /sys/class/drm, e.g. "card0-HDMI-A-2").
    # "" = every connector that was connected at open must stay connected.
    drm_connector: str = ""
    # Byte order of the colour channels in a framebuffer pixel (BGR = BGRX in memory).
    pixel_order: Literal["BGR", "RGB"] = "BGR"
    # Simulated SLM: write each shown frame as PNG here ("" = keep frames in memory only).
    png_dir: str = ""
    # Simulated SLM: how many recent frames to keep.
    history_frames: Annotated[int, Field(ge=1, le=10000)] = 8
    # Simulated SLM: time from the host's write to the panel flipping to the frame (an HDMI
    # panel shows a frame one or more refreshes after it was sent). settle_ms must cover it plus
    # the liquid crystal's response when captures are not triggered (drivers/trigger.py).
    flip_latency_ms: Annotated[float, Field(ge=0, le=1000)] = 0.0


# ------------------------------------------------------------------------------------- navigator

# 3Dconnexion devices, (vendor id, product id). Vendor 0x046d is Logitech's, so a product id must
# match too. From public device lists (spacenavd and others).
SPACEMOUSE_IDS: list[list[int]] = [
    [0x046D, 0xC603],  # SpaceMouse Plus XT (USB)
    [0x046D, 0xC605],  # CADman
    [0x046D, 0xC606],  # SpaceMouse Classic
    [0x046D, 0xC621],  # SpaceBall 5000
    [0x046D, 0xC623],  # SpaceTraveler
    [0x046D, 0xC625],  # SpacePilot
    [0x046D, 0xC626],  # SpaceNavigator
    [0x046D, 0xC627],  # SpaceExplorer
    [0x046D, 0xC628],  # SpaceNavigator for Notebooks
    [0x046D, 0xC629],  # SpacePilot Pro
    [0x046D, 0xC62B],  # SpaceMouse Pro
    [0x256F, 0xC62E],  # SpaceMouse Wireless (cable)
    [0x256F, 0xC62F],  # SpaceMouse Wireless (receiver)
    [0x256F, 0xC631],  # SpaceMouse Pro Wireless (cable)
    [0x256F, 0xC632],  # SpaceMouse Pro Wireless (receiver)
    [0x256F, 0xC633],  # SpaceMouse Enterprise
    [0x256F, 0xC635],  # SpaceMouse Compact
    [0x256F, 0xC636],  # SpaceMouse Module
    [0x256F, 0xC652],  # Universal Receiver
]


class NavigatorSettings(_Settings):
    """`[devices.spacemouse]`: the SpaceMouse's USB ids, dead zone and full scale (raw counts),
    the view's velocity at full deflection (m/s, deg/s), axis signs and read timeout (ms)."""

    usb_ids: Annotated[
        list[Annotated[list[Annotated[int, Field(ge=0, le=0xFFFF)]],
                       Field(min_length=2, max_length=2)]],
        Field(min_length=1),
    ] = SPACEMOUSE_IDS
    # Raw axis values at or below this magnitude read as zero (the puck never rests at exactly 0).
    dead_zone_counts: Annotated[int, Field(ge=0, le=1000)] = 15
    # Raw value of a full deflection (about 350 on current models).
    full_scale_counts: Annotated[int, Field(ge=1, le=32767)] = 350
    # Velocity at full deflection: view translation (scene metres per second) and rotation.
    max_translation_m_s: Annotated[float, Field(gt=0, le=100)] = 0.1
    max_rotation_deg_s: Annotated[float, Field(gt=0, le=3600)] = 45.0
    # +1 or -1 per axis: x, y, z, rx, ry, rz.
    axis_signs: Annotated[list[Literal[1, -1]], Field(min_length=6, max_length=6)] = [1] * 6
    read_timeout_ms: Annotated[int, Field(ge=0, le=1000)] = 10


# ---------------------------------------------------------------------------------------- camera


class CameraSettings(_Settings):
    """Camera settings, validated once (strict and frozen, like every driver's settings)."""

    # Exposure time, applied on open with auto exposure off.
    exposure_s: Annotated[float, Field(gt=0, le=60)] = 0.005
    # Analogue gain with auto gain off: dB for GenICam and the simulated camera; V4L2 drivers
    # take CAP_PROP_GAIN in their own units, so OpenCVCamera passes this number through.
    gain_db: Annotated[float, Field(ge=0, le=48)] = 0.0
    # Frames averaged by a capture unless the call says otherwise.
    burst_frames: Annotated[int, Field(ge=1, le=10000)] = 1
    # "mono": [H, W]; "rgb": [3, H, W] (R, G, B).
    channels: Literal["mono", "rgb"] = "mono"
    # ADC bits of the raw frames (8 for most V4L2 cameras; 10/12/16 for Mono12-style formats).
    bit_depth: Annotated[int, Field(ge=1, le=16)] = 8
    # Sensor pixel pitch (um): calibration turns pixels per SLM metre into magnification with it.
    pixel_pitch_um: Annotated[float, Field(gt=0, le=100)] = 3.45
    # Response curve: raw/full = linear ** (1 / response_gamma); 1.0 = linear (raw machine-vision
    # formats). Consumer webcams apply ~2.2. A measured table can be given to the class instead.
    response_gamma: Annotated[float, Field(ge=0.1, le=5)] = 1.0
    # OpenCV: device path or index ("/dev/video0", "0"); GenICam: ignored.
    device: str = "/dev/video0"
    # OpenCV: frames dropped after a settings change or before a burst (V4L2 queues old frames).
    discard_frames: Annotated[int, Field(ge=0, le=100)] = 2
    # GenICam: the vendor's GenTL producer and the camera's serial number ("" = the first).
    cti_path: str = ""
    serial_number: str = ""
    # GenICam PixelFormat to set on open ("" = leave the camera's), e.g. "Mono12", "RGB8".
    pixel_format: str = ""
    # Longest wait for one frame beyond the exposure itself.
    frame_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0


# -------------------------------------------------------------------------------------- slmsuite


# A TOML value a vendor class's keyword argument may take (strict: TOML is typed).
SlmsuiteArg = int | float | str | bool | list[int] | list[float] | list[str]


class SlmsuiteSettings(_Settings):
    """Vendor hardware through slmsuite (`[devices] slm = "slmsuite"` and/or `camera =
    "slmsuite"`): any slmsuite SLM or camera class as "module:Class" and its keyword arguments.
    nhfd's grey frames go to the SLM as they are (slmsuite's phase-to-grey conversion is
    bypassed: nhfd's calibrated curves stay authoritative)."""

    slm_class: str = "slmsuite.hardware.slms.simulated:SimulatedSLM"
    # e.g. {resolution = [1920, 1080], pitch_um = [8.0, 8.0]}: the panel's size and pitch must
    # match [slm]'s width_px, height_px and pitch_um (checked on open).
    slm_kwargs: dict[str, SlmsuiteArg] = {}
    camera_class: str = "slmsuite.hardware.cameras.simulated:SimulatedCamera"
    camera_kwargs: dict[str, SlmsuiteArg] = {}
    # The frame's channel a (monochrome) slmsuite SLM shows: the colour its laser is. In
    # colour_mode = "single" every channel holds the single colour's pattern.
    channel: Literal["red", "green", "blue"] = "green"

    @field_validator("slm_class", "camera_class")
    @classmethod
    def _module_colon_class(cls, v: str) -> str:
        module, _, name = v.partition(":")
        if not module or not name.isidentifier():
            raise ValueError(f"{v!r}: expected 'module:Class', e.g. "
                             "'slmsuite.hardware.slms.simulated:SimulatedSLM'")
        return v


# -------------------------------------------------------------------------------------- triggers


# The trigger wirings ("none" first: no line) and the ranges of their settings (ms): the one
# place for drivers.trigger's TriggerLine and for `nhfd bench triggers`.
TRIGGER_SOURCES = ("none", "slm_flip", "camera_exposure")
TRIGGER_DELAY_MS = (0.0, 1000.0)  # closed
TRIGGER_TIMEOUT_MS = (0.0, 60000.0)  # (low, high]


class TriggerSettings(_Settings):
    """Hardware triggering of captures (drivers/trigger.py). "none": a capture waits out the SLM's
    settle_ms after each frame. "slm_flip": the SLM's frame-flip output is wired to the camera's
    trigger input; the camera arms, the frame flips, and the exposure starts delay_ms after the
    edge, with no settle sleep on the host. "camera_exposure": the camera's exposure-active output
    is wired to the host; a frame is written only once the line is low (no frame changes during
    an exposure, none waits for the image's readout), the settle sleep stays."""

    source: Literal[TRIGGER_SOURCES] = "none"
    # The camera's trigger delay after the edge: the liquid crystal's response to a new frame.
    delay_ms: Annotated[float, Field(ge=TRIGGER_DELAY_MS[0], le=TRIGGER_DELAY_MS[1])] = 10.0
    # No edge within this long after a frame was written: the capture fails (TriggerTimeout);
    # camera_exposure: the line high this long when a frame is to be written: the write fails.
    timeout_ms: Annotated[float, Field(gt=TRIGGER_TIMEOUT_MS[0], le=TRIGGER_TIMEOUT_MS[1])] = 500.0
