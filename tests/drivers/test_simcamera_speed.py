"""The simulated camera's fast imaging (`SimulatedCamera.optical_image`, what every capture uses)
against its plain reference (`optical_image_reference`: every colour in float64 through
`panel_field`, grid_sample over the ROI), at the daemon tests' sizes and at the product's
1920 x 1080 panel on the whole sensor; and the fast raw quantiser against np.interp. Nothing here
is timed (the speed-ups were measured by hand; drivers/simcamera.py's comments give the numbers):
these tests hold the fast path to the same image."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from nhfd.drivers.camera import CameraSettings, ResponseCurve
from nhfd.drivers.simcamera import SimulatedCamera, TrueBench, _RawLevels, camera_response

# What the daemon's citl tests show (tests/daemon/test_frames.py SMALL: 192 x 128).
DAEMON_PANEL_HW = (128, 192)
FULL_PANEL_HW = (1080, 1920)
# The fast path computes in float32 where the reference keeps float64: measured 2.7e-7 to 9.6e-7
# of the image's peak on these benches and sizes (6.8e-7 on the full panel).
REL_TOL = 1e-5
QUIET = dict(read_noise_e=0.0, shot_noise=False, prnu=0.0, dsnu=0.0)
LIT_ALONE = [tuple(i == c for i in range(3)) for c in range(3)]


class Shown:
    """What the camera's callables read: a frame, laser powers and a stage position."""

    def __init__(self, frame: np.ndarray, powers: tuple[float, float, float], stage_mm: float
                 ) -> None:
        self.frame, self.powers, self.stage_mm = frame, powers, stage_mm


def camera(bench: TrueBench, shown: Shown, roi: tuple[int, int, int, int] | None,
           **settings) -> SimulatedCamera:
    return SimulatedCamera(lambda: shown.frame, lambda: shown.powers, lambda: shown.stage_mm,
                           bench, CameraSettings(**settings), roi=roi)


def random_frame(seed: int, panel_hw: tuple[int, int]) -> np.ndarray:
    """Seeded uniform grey levels, [H, W, 3] (a different pattern per colour)."""
    return np.random.default_rng(seed).integers(0, 256, (*panel_hw, 3), dtype=np.uint8)


def assert_same_image(fast: np.ndarray, reference: np.ndarray) -> None:
    assert fast.shape == reference.shape and fast.dtype == reference.dtype
    peak = float(reference.max())
    assert peak > 0
    err = float(np.abs(fast - reference).max())
    assert err <= REL_TOL * peak, f"max |fast - reference| = {err / peak:.2e} of the peak"


# The default bench, three randomised ones (phase sign, mirror, rotation, magnification 0.6 to
# 1.2, focus offsets: seeds 0, 1, 2 as they come), an aberrated relay, and the edge cases of the
# panel's chain (no oversampling, no crosstalk blur).
BENCHES = {
    "default": TrueBench(),
    "randomised-0": TrueBench.randomised(0),
    "randomised-1": TrueBench.randomised(1),
    "randomised-2": TrueBench.randomised(2),
    "aberrated": TrueBench(zernike_rad=(0.3, -0.2, 0.15, 0.1)),
    "plain-pixels": TrueBench(oversample=1, crosstalk_sigma_m=0.0, phase_sign=-1),
    "odd-geometry": TrueBench(rotation_deg=33.0, mirror_x=True, magnification=1.1,
                              oversample=3),
}


@pytest.mark.parametrize("name", list(BENCHES))
def test_the_fast_image_is_the_reference_at_the_daemon_tests_size(name: str) -> None:
    bench = BENCHES[name]
    shown = Shown(random_frame(0, DAEMON_PANEL_HW), (1.0, 1.0, 1.0),
                  bench.stage_at_slm_mm + 0.4)
    # A margin wider than roi_for_panel's: camera pixels that see only the zero padding too.
    cam = camera(bench, shown, bench.roi_for_panel(DAEMON_PANEL_HW, margin_px=24))
    for lit in [*LIT_ALONE, (True, True, True)]:
        assert_same_image(cam.optical_image(lit), cam.optical_image_reference(lit))
        dark = [c for c in range(3) if not lit[c]]
        assert not cam.optical_image(lit)[dark].any()


def test_the_fast_image_follows_the_frame_the_stage_and_the_colour() -> None:
    """What the fast path memoises (fields per frame and colour, the geometry) never hands an
    image of another frame, stage position or colour."""
    bench = BENCHES["randomised-1"]
    shown = Shown(random_frame(1, DAEMON_PANEL_HW), (0.0, 1.0, 0.0), bench.stage_at_slm_mm)
    cam = camera(bench, shown, bench.roi_for_panel(DAEMON_PANEL_HW))
    for frame_seed, stage_mm, lit in [(1, 0.0, LIT_ALONE[1]), (1, 0.3, LIT_ALONE[1]),
                                      (1, 0.3, LIT_ALONE[0]), (2, 0.3, LIT_ALONE[0]),
                                      (2, -0.2, LIT_ALONE[2]), (1, 0.0, LIT_ALONE[1])]:
        shown.frame = random_frame(frame_seed, DAEMON_PANEL_HW)
        shown.stage_mm = bench.stage_at_slm_mm + stage_mm
        assert_same_image(cam.optical_image(lit), cam.optical_image_reference(lit))


def test_the_fast_image_is_the_reference_on_the_full_panel_and_sensor() -> None:
    """The product's sizes: the 1920 x 1080 panel, the default camera's whole 2048 x 2448
    sensor (daemon.bench.camera_roi_px = []), one diode lit as citl lights it."""
    bench = TrueBench()
    shown = Shown(random_frame(0, FULL_PANEL_HW), (0.0, 1.0, 0.0), bench.stage_at_slm_mm + 0.2)
    cam = camera(bench, shown, None)
    lit = LIT_ALONE[1]
    assert_same_image(cam.optical_image(lit), cam.optical_image_reference(lit))


@pytest.mark.parametrize("channels", ["mono", "rgb"])
def test_a_noise_free_raw_frame_is_the_reference_chains(channels: str) -> None:
    """_expose's mixing of the lit colours and its raw quantiser against the chain written out
    plainly on the reference image: at most one level apart (a value on a rounding boundary),
    and almost everywhere equal."""
    bench = replace(BENCHES["randomised-2"], **QUIET)
    powers = (0.6, 0.0, 0.9)
    shown = Shown(random_frame(3, DAEMON_PANEL_HW), powers, bench.stage_at_slm_mm + 0.1)
    cam = camera(bench, shown, bench.roi_for_panel(DAEMON_PANEL_HW), channels=channels,
                 exposure_s=0.004, gain_db=6.0)
    raw = cam.open()._grab()
    per_colour = cam.optical_image_reference([p > 0 for p in powers])
    rate = np.asarray(powers) * np.asarray(bench.electrons_per_s)
    mix = np.asarray(bench.colour_matrix) * rate[None, :] if channels == "rgb" else rate[None, :]
    t = cam.exposure_s
    electrons = np.tensordot(mix, per_colour, axes=1) * t * cam._prnu
    electrons = np.clip(electrons + bench.dark_current_e_per_s * t, 0.0, bench.full_well_e)
    signal = bench.dark_level + cam._dsnu + \
        (1 - bench.dark_level) * bench.gain(cam.gain_db) * electrons / bench.full_well_e
    want = np.rint(bench.response().to_raw(np.clip(signal, 0.0, 1.0))).astype(np.uint16)
    want = want[0] if channels == "mono" else want.transpose(1, 2, 0)
    assert raw.shape == want.shape
    diff = np.abs(raw.astype(np.int64) - want)
    assert diff.max() <= 1
    assert (diff == 0).mean() > 0.999
    # The scene is bright enough for the check to mean something.
    assert want.max() > 0.5 * cam.response.max_level


@pytest.mark.parametrize("channels", ["mono", "rgb"])
def test_the_noisy_chain_is_the_plain_one_level_for_level(channels: str) -> None:
    """On the same optical image, _expose (the lit colour alone mixed in, the signal in place,
    the fast quantiser) draws the same noise and gives the same raw levels as the plain chain
    (the one written before the fast path: a tensordot over all colours, np.interp)."""
    bench = BENCHES["randomised-0"]
    powers = (0.0, 0.8, 0.0)
    shown = Shown(random_frame(4, DAEMON_PANEL_HW), powers, bench.stage_at_slm_mm)
    cam = camera(bench, shown, bench.roi_for_panel(DAEMON_PANEL_HW), channels=channels,
                 exposure_s=0.003, gain_db=3.0)
    image = cam.optical_image((False, True, False)).copy()
    cam.open()
    raws = [cam._grab() for _ in range(2)]
    rng = np.random.default_rng(bench.noise_seed)
    rate = np.asarray(powers) * np.asarray(bench.electrons_per_s)
    mix = np.asarray(bench.colour_matrix) * rate[None, :] if channels == "rgb" else rate[None, :]
    t = cam.exposure_s
    for raw in raws:
        electrons = np.tensordot(mix, image, axes=1) * t * cam._prnu
        electrons = electrons + bench.dark_current_e_per_s * t
        electrons = rng.poisson(electrons).astype(np.float64)
        electrons = electrons + rng.normal(0.0, bench.read_noise_e, electrons.shape)
        electrons = np.clip(electrons, 0.0, bench.full_well_e)
        signal = bench.dark_level + cam._dsnu + \
            (1 - bench.dark_level) * bench.gain(cam.gain_db) * electrons / bench.full_well_e
        want = np.rint(bench.response().to_raw(np.clip(signal, 0.0, 1.0))).astype(np.uint16)
        want = want[0] if channels == "mono" else want.transpose(1, 2, 0)
        assert np.array_equal(raw, want)


RESPONSES = {
    "true-bench": camera_response(1.06, 0.01, 12),
    "linear-8-bit": camera_response(1.0, 0.0, 8),
    "gamma-2.2": camera_response(2.2, 0.0, 12),
    # Steps finer than the quantiser's bins: it falls back to np.interp.
    "16-bit": camera_response(1.06, 0.01, 16),
    # A table that starts above 0: below it np.interp gives level 0.
    "offset": ResponseCurve(np.linspace(0.02, 1.0, 4096)),
}


@pytest.mark.parametrize("name", list(RESPONSES))
def test_the_raw_quantiser_is_np_interps(name: str) -> None:
    """Level for level what rint(ResponseCurve.to_raw) gives, on random signals and at and
    beside every table entry and every rounding boundary."""
    response = RESPONSES[name]
    table = response.linear
    mids = (table[1:] + table[:-1]) / 2
    signal = np.concatenate([
        np.random.default_rng(0).random(200_000), table, mids,
        np.nextafter(table, 0.0), np.nextafter(table, 1.0),
        np.nextafter(mids, 0.0), np.nextafter(mids, 1.0),
        np.arange(_RawLevels.BINS + 1) / _RawLevels.BINS,
    ])
    signal = np.clip(signal, 0.0, 1.0)
    want = np.rint(response.to_raw(signal)).astype(np.uint16)
    got = _RawLevels(response)(signal.copy())
    assert got.dtype == np.uint16
    assert np.array_equal(got, want)
