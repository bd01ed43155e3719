"""Cameras: the base class's linearisation, bursts and dark frames; the real backends' clear
errors; and the simulated camera's physics against what the true bench predicts."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from nhfd.drivers.camera import (
    Camera,
    CameraSettings,
    CameraTimeout,
    CameraUnavailable,
    Capture,
    GenICamCamera,
    OpenCVCamera,
    ResponseCurve,
    colour_planes,
)
from nhfd.drivers.errors import DeviceError
from nhfd.drivers.simcamera import SimulatedCamera, TrueBench, slm_frame_source
from nhfd.drivers.slm import SimulatedSLM
from nhfd.optics import Aperture, apply_aperture, double_phase, phase_to_grey, propagate

N = 128  # simulated panel (pixels per side): 1 mm at 8 um
GREEN = 1
# A small sensor keeps every test fast; the panel's image (0.77 mm at M = 0.75) fits on it.
SMALL = TrueBench(sensor_hw_px=(256, 256))
# No noise or fixed pattern: for tests that compare exact levels.
QUIET = dict(read_noise_e=0.0, shot_noise=False, prnu=0.0, dsnu=0.0)


class Stage:
    """A stand-in for the simulated stage: a position the test sets."""

    def __init__(self, mm: float = 10.0) -> None:
        self.mm = mm

    def __call__(self) -> float:
        return self.mm


def sim(bench: TrueBench, frame: np.ndarray, powers=(0.0, 1.0, 0.0), stage: Stage | None = None,
        **settings) -> SimulatedCamera:
    frames = {"now": frame}
    cam = SimulatedCamera(lambda: frames["now"], lambda: powers,
                          stage or Stage(bench.stage_at_slm_mm), bench,
                          CameraSettings(**settings), roi=bench.roi_for_panel((N, N)))
    cam.frames = frames  # type: ignore[attr-defined]  (lets a test change what is shown)
    return cam


def pi_checkerboard(bench: TrueBench, colour: int = GREEN) -> np.ndarray:
    """Grey 0 and the level whose true phase is pi further, on a pixel checkerboard: light the
    aperture blocks entirely (no DC), whatever the table's shape."""
    table = np.asarray(bench.phase_tables[colour])
    g_pi = int(np.argmin(np.abs(table - table[0] - np.pi)))
    rows, cols = np.indices((N, N))
    return np.where((rows + cols) % 2 == 0, 0, g_pi).astype(np.uint8)


# ------------------------------------------------------------------------------- base class


class FakeCamera(Camera):
    """A backend returning scripted raw frames."""

    def __init__(self, frames, settings=None, **kw):
        super().__init__(settings, **kw)
        self.frames = list(frames)
        self.applied: list[tuple[str, float]] = []
        self.opened = 0

    def _do_open(self):
        self.opened += 1

    def _do_close(self):
        pass

    def _apply_exposure(self, exposure_s):
        self.applied.append(("exposure", exposure_s))
        return round(exposure_s, 4)  # a camera quantises

    def _apply_gain(self, gain_db):
        self.applied.append(("gain", gain_db))
        return gain_db

    def _grab(self):
        return self.frames.pop(0)


def test_settings_are_validated_once_and_applied_explicitly_on_open():
    with pytest.raises(ValidationError):
        CameraSettings(exposure_s=-1.0)
    with pytest.raises(ValidationError):
        CameraSettings(channels="bayer")
    cam = FakeCamera([], CameraSettings(exposure_s=0.01234, gain_db=3.0))
    with cam:
        assert cam.applied == [("exposure", 0.01234), ("gain", 3.0)]
        assert cam.exposure_s == 0.0123  # the value read back, not the one asked for
        with pytest.raises(ValueError, match="exposure_s"):
            cam.set_exposure(100.0)
        with pytest.raises(ValueError, match="gain_db"):
            cam.set_gain(-1.0)
    with pytest.raises(DeviceError, match="not open"):
        cam.capture()


def test_response_is_inverted_bursts_average_linear_values_and_saturation_is_flagged():
    # An 8-bit gamma-2.2 camera: raw 128 is linear (128/255)^2.2, not 0.5.
    raw = [np.array([[0, 128], [255, 64]], np.uint8), np.array([[0, 128], [200, 64]], np.uint8)]
    cam = FakeCamera(raw, CameraSettings(response_gamma=2.2, bit_depth=8))
    with cam:
        cap = cam.capture(2)
    lin = (np.array([[0, 128], [227.5, 64]]) / 255) ** 2.2
    lin[1, 0] = ((255 / 255) ** 2.2 + (200 / 255) ** 2.2) / 2  # averaged after linearising
    assert cap.image.dtype == np.float32 and cap.frames == 2
    np.testing.assert_allclose(cap.image, lin, rtol=1e-6)
    assert cap.saturated.tolist() == [[False, False], [True, False]]  # saturated in one frame


def test_dark_frame_is_subtracted_and_dropped_when_exposure_changes():
    frames = [np.full((2, 2), 10, np.uint16), np.full((2, 2), 50, np.uint16),
              np.full((2, 2), 50, np.uint16)]
    cam = FakeCamera(frames, CameraSettings(bit_depth=12))
    with cam:
        dark = cam.capture_dark(1)
        np.testing.assert_allclose(dark, 10 / 4095)
        cap = cam.capture(1)
        assert cap.dark_subtracted
        np.testing.assert_allclose(cap.image, 40 / 4095, rtol=1e-5)
        cam.set_exposure(0.02)
        assert cam.dark_frame is None and not cam.capture(1).dark_subtracted


def test_raw_frames_are_checked():
    with FakeCamera([np.full((2, 2), 300, np.uint16)]) as cam:  # 8-bit camera, level 300
        with pytest.raises(DeviceError, match="bit_depth"):
            cam.capture()
    with FakeCamera([np.zeros((2, 2, 3), np.uint8)]) as cam:  # colour frame, mono settings
        with pytest.raises(DeviceError, match="shape"):
            cam.capture()
    with pytest.raises(ValueError, match="end at 1"):
        ResponseCurve([0.0, 0.5])


def test_real_backends_say_what_is_missing(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "cv2", None)  # as if OpenCV were not installed
    with pytest.raises(CameraUnavailable, match="opencv"):
        OpenCVCamera()
    with pytest.raises(CameraUnavailable, match="cti_path"):
        GenICamCamera()
    with pytest.raises(CameraUnavailable, match="not a file"):
        GenICamCamera(CameraSettings(cti_path=str(tmp_path / "missing.cti")))
    cti = tmp_path / "producer.cti"
    cti.write_bytes(b"")
    monkeypatch.setitem(sys.modules, "harvesters", None)
    monkeypatch.setitem(sys.modules, "harvesters.core", None)
    with pytest.raises(CameraUnavailable, match="pip install harvesters"):
        GenICamCamera(CameraSettings(cti_path=str(cti)))


def test_camera_module_imports_no_torch():
    code = "import sys, nhfd.drivers.camera; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# -------------------------------------------------------------------------- simulated camera


def coded_target(bench: TrueBench, z_m: float) -> tuple[np.ndarray, torch.Tensor]:
    """A bar target at distance z_m from the SLM, double-phase coded for the green laser with
    the bench's own (perfectly calibrated) table and sign -> (grey frame, target field)."""
    lam, pitch = bench.wavelengths_m[GREEN], bench.pitch_m
    aperture = Aperture("square", (0.25,))
    amp = torch.zeros(1, N, N)
    amp[0, 40:88, 44:52] = 1
    amp[0, 40:88, 60:68] = 1
    amp[0, 40:48, 76:90] = 1
    amp[0, 70:88, 76:90] = 1
    # A random phase within the aperture spreads every point over the cone, so defocus blurs.
    noise = torch.randn(1, N, N, dtype=torch.complex64, generator=torch.Generator().manual_seed(3))
    phase = torch.angle(apply_aperture(noise, Aperture("square", (0.2,))))
    target = apply_aperture(torch.polar(amp, phase), aperture)
    slm = propagate(target, -z_m, pitch, [lam], aperture=aperture)
    a = slm.abs()
    scale = float(torch.quantile(a[a > 0.01 * a.max()], 0.995))
    coded = double_phase(slm, scale, antialias=aperture)
    grey = phase_to_grey(coded.phase_rad, [bench.phase_curves()[GREEN]], sign=bench.phase_sign)
    return grey[0].numpy(), target


def psnr_db(image: np.ndarray, reference: np.ndarray) -> float:
    """PSNR after the best scale of the image (the camera's units are arbitrary)."""
    k = (image * reference).sum() / (image * image).sum()
    return float(10 * np.log10(reference.max() ** 2 / ((k * image - reference) ** 2).mean()))


def test_a_coded_target_is_sharpest_at_the_stage_position_of_its_depth():
    bench = replace(SMALL, phase_sign=-1)  # a conjugating bench: the coder must follow it
    z_target = 4e-3
    grey, target = coded_target(bench, z_target)
    stage = Stage()
    cam = sim(bench, grey, stage=stage, exposure_s=0.002)
    reference = cam.project_to_camera(target.abs().square(), bench.pitch_m)[0]
    psnr = {}
    with cam:
        for dz in (-2e-3, 0.0, 2e-3, 3e-3):
            stage.mm = bench.stage_mm_for(z_target + dz, GREEN)
            cap = cam.capture()
            psnr[dz] = psnr_db(cap.image - bench.dark_level_at(cam.exposure_s), reference)
    assert psnr[0.0] > 25, psnr
    for dz in (-2e-3, 2e-3, 3e-3):
        assert psnr[0.0] > psnr[dz] + 3, psnr
    # With the wrong sign the volume is mirrored about the SLM: nothing is in focus at +z...
    wrong, _ = coded_target(replace(bench, phase_sign=1), z_target)
    cam.frames["now"] = wrong
    with cam:
        stage.mm = bench.stage_mm_for(z_target, GREEN)
        bad = psnr_db(cam.capture().image - bench.dark_level_at(cam.exposure_s), reference)
        stage.mm = bench.stage_mm_for(-z_target, GREEN)
        mirrored = psnr_db(cam.capture().image - bench.dark_level_at(cam.exposure_s), reference)
    assert bad < psnr[0.0] - 6, (bad, psnr)
    assert mirrored > bad + 6, (mirrored, bad)  # ... but at -z, the mirror image


def test_zero_order_leaks_where_and_as_much_as_the_bench_says():
    # Only the leak may pass: no crosstalk or gap light, and a frame the aperture blocks.
    base = replace(SMALL, crosstalk_sigma_m=0.0, fill_factor=1.0, source_waist_m=0.25e-3,
                   source_offset_m=(0.12e-3, -0.08e-3))
    frame = pi_checkerboard(base)
    energy, peak = {}, {}
    for leak in (0.0, 0.01, 0.04):
        bench = replace(base, zero_order_fraction=leak)
        powers = [0.0, 0.0, 0.0]
        cam = sim(bench, frame, powers=powers, exposure_s=0.005)
        with cam:
            cam.capture_dark(4)  # lasers off
            powers[GREEN] = 1.0
            img = cam.capture(4).image.astype(np.float64)
        energy[leak] = img.sum()
        rows, cols = np.indices(img.shape)
        top, left = cam.roi[:2]
        if leak:
            # Centroid of the leaked light (above the noise): where the beam's centre is imaged.
            w = np.where(img > 0.2 * img.max(), img, 0.0)
            centroid = ((w * (cols + left)).sum() / w.sum(), (w * (rows + top)).sum() / w.sum())
            expect = bench.slm_to_camera_px(*bench.source_offset_m)
            assert np.hypot(centroid[0] - expect[0], centroid[1] - expect[1]) < 1.5, \
                (centroid, expect)
            # Its level: the unmodulated fraction of the beam's peak irradiance.
            r, c = round(expect[1]) - top, round(expect[0]) - left
            peak[leak] = img[r - 1 : r + 2, c - 1 : c + 2].mean()
            predicted = leak * 1.0e6 * 0.005 / bench.full_well_e * (1 - bench.dark_level)
            assert peak[leak] == pytest.approx(predicted, rel=0.1)
    assert energy[0.04] / energy[0.01] == pytest.approx(4.0, rel=0.05)
    assert abs(energy[0.0]) < 0.01 * energy[0.01]  # no leak: nothing there


def test_mirror_and_rotation_put_an_off_centre_feature_at_the_predicted_pixel():
    frame = pi_checkerboard(SMALL)
    r0, c0 = 30, 84  # a flat 6 x 6 patch (it passes the aperture) off the centre
    frame[r0 : r0 + 6, c0 : c0 + 6] = 0
    x = (c0 + 2.5 - (N - 1) / 2) * SMALL.pitch_m
    y = (r0 + 2.5 - (N - 1) / 2) * SMALL.pitch_m
    seen = []
    for mirror, rotation in ((False, 0.0), (True, 0.0), (False, 90.0), (True, 210.0)):
        bench = replace(SMALL, mirror_x=mirror, rotation_deg=rotation)
        cam = sim(bench, frame, exposure_s=0.002)
        with cam:
            img = cam.capture().image - bench.dark_level_at(cam.exposure_s)
        rows, cols = np.indices(img.shape)
        w = np.where(img > 0.5 * img.max(), img, 0)
        top, left = cam.roi[:2]
        found = ((w * (cols + left)).sum() / w.sum(), (w * (rows + top)).sum() / w.sum())
        expect = bench.slm_to_camera_px(x, y)
        assert np.hypot(found[0] - expect[0], found[1] - expect[1]) < 1.0, (mirror, rotation)
        seen.append(found)
    # The flip moves the feature to the other side of the image's centre, not nowhere.
    assert abs(seen[0][0] - seen[1][0]) > 20


def test_saturation_clips_at_full_well_and_is_flagged():
    bench = replace(SMALL, source_waist_m=0.4e-3, source_offset_m=(0.0, 0.0))
    flat = np.zeros((N, N), np.uint8)
    cam = sim(bench, flat, exposure_s=0.02)  # the beam's centre collects 2x the full well
    with cam:
        cap = cam.capture()
        assert 0.01 < cap.saturated_fraction < 0.9
        assert cap.image.max() == 1.0  # full well = full scale at 0 dB
        assert (cap.image[cap.saturated] == 1.0).all()
        assert cap.image[~cap.saturated].max() < 1.0
        cam.set_gain(12.0)  # with gain, the ADC clips first, still flagged
        assert cam.capture().saturated_fraction > cap.saturated_fraction


def test_noise_is_reproducible_with_the_seed():
    frame = np.zeros((N, N), np.uint8)
    a, b = sim(SMALL, frame), sim(SMALL, frame)
    c = sim(replace(SMALL, noise_seed=1), frame)
    with a, b, c:
        first = a.capture().image
        assert np.array_equal(first, b.capture().image)
        assert not np.array_equal(first, c.capture().image)
        a.reseed(SMALL.noise_seed)
        assert np.array_equal(first, a.capture().image)


def test_lasers_off_give_the_dark_level_and_the_dark_frame_removes_its_pattern():
    frame = np.zeros((N, N), np.uint8)
    quiet = replace(SMALL, **QUIET)
    with sim(quiet, frame, powers=(0.0, 0.0, 0.0), exposure_s=0.01) as cam:
        img = cam.capture().image
        np.testing.assert_allclose(img, quiet.dark_level_at(0.01), atol=2e-4)
    with sim(SMALL, frame, powers=(0.0, 0.0, 0.0), exposure_s=0.01,
             channels="rgb") as cam:
        raw = cam.capture(subtract_dark=False).image
        assert raw.shape[0] == 3
        assert raw.mean() == pytest.approx(SMALL.dark_level_at(0.01), abs=2e-4)
        cam.capture_dark(16)
        dark_subtracted = cam.capture().image
        assert abs(dark_subtracted.mean()) < 1e-4
        assert dark_subtracted.std() < raw.std()  # DSNU gone, read noise remains


def test_burst_average_reduces_noise_by_sqrt_n():
    flat = np.zeros((N, N), np.uint8)
    with sim(SMALL, flat, powers=(0.0, 0.5, 0.0), exposure_s=0.01) as cam:
        def noise(frames: int) -> float:
            # The difference of two captures cancels the scene and the fixed patterns.
            d = cam.capture(frames).image - cam.capture(frames).image
            lit = cam.optical_image((False, True, False))[GREEN] > 0.5
            return float(d[lit].std() / np.sqrt(2))
        ratio = noise(1) / noise(16)
    assert ratio == pytest.approx(4.0, rel=0.15)


def test_it_images_what_the_simulated_slm_shows():
    slm = SimulatedSLM(N, N)
    source = slm_frame_source(slm)
    assert source().shape == (N, N) and source().max() == 0  # nothing shown yet: grey 0
    cam = SimulatedCamera(source, lambda: (0.0, 0.3, 0.0), Stage(SMALL.stage_at_slm_mm), SMALL,
                          roi=SMALL.roi_for_panel((N, N)))
    with slm, cam:
        flat = cam.capture().image.mean()
        slm.show(pi_checkerboard(SMALL))  # blocked by the aperture: (nearly) dark
        assert cam.capture().image.mean() < 0.3 * flat
    with pytest.raises(DeviceError, match="laser powers"):
        with SimulatedCamera(source, lambda: (0.0, 2.0), Stage(), SMALL, roi=(0, 0, 8, 8)) as c:
            c.capture()


def test_colour_camera_sees_each_laser_through_its_filters_and_focus_is_per_colour():
    bench = replace(SMALL, **QUIET)
    flat = np.zeros((N, N), np.uint8)
    with sim(bench, flat, powers=(0.5, 0.0, 0.0), channels="rgb", exposure_s=0.005) as cam:
        img = cam.capture().image - bench.dark_level_at(0.005)
    lit = cam.optical_image((True, False, False))[0] > 0.5
    r, g, b = (float(img[k][lit].mean()) for k in range(3))
    m = bench.colour_matrix
    assert g / r == pytest.approx(m[1][0] / m[0][0], rel=0.05)
    assert b / r == pytest.approx(m[2][0] / m[0][0], rel=0.1)
    # Chromatic focal shift: one stage position is a slightly different depth per colour, and
    # the stage scale is 1 / M^2.
    z = 4e-3
    assert bench.stage_mm_for(z, 0) != bench.stage_mm_for(z, GREEN)
    assert bench.z_m(bench.stage_mm_for(z, 2), 2) == pytest.approx(z)
    assert (bench.z_m(11.0, GREEN) - bench.z_m(10.0, GREEN)) == pytest.approx(
        1e-3 / bench.magnification**2)


def test_a_randomised_bench_is_reproducible_and_plausible():
    a, b = TrueBench.randomised(5), TrueBench.randomised(5)
    assert a == b and a.phase_tables == b.phase_tables
    assert {TrueBench.randomised(s).phase_sign for s in range(12)} == {1, -1}
    for table in a.phase_tables:
        assert np.all(np.diff(table) > 0)  # monotone, however wiggly


def _colour_capture(value: float) -> Capture:
    """A colour camera's capture `[3, 4, 5]` channel-first: channel c holds value + c, and
    channel 2 saturates."""
    image = np.stack([np.full((4, 5), value + c, np.float32) for c in range(3)])
    saturated = np.zeros((3, 4, 5), bool)
    saturated[2, 0, 0] = True
    return Capture(image, saturated, 0.01, 0.0, 1, True)


def test_colour_planes_reads_each_colours_own_channel_and_lights_after_the_pattern() -> None:
    """citl's capture sequence (the daemon's job and the offline loop share it): a colour
    camera's frame is channel-first, so colour c is channel c (not column c); the K subframes
    average; each diode goes on only once its pattern is up, and off after its captures."""
    log: list[tuple] = []
    shots = iter(range(100))

    def capture() -> Capture:
        n = next(shots)
        log.append(("capture", n))
        return _colour_capture(10.0 * n)

    images, saturated = colour_planes(
        2, 2, at_plane=lambda i: log.append(("plane", i)),
        before_colour=lambda name: log.append(("check", name)),
        show=lambda k, name: log.append(("show", k, name)),
        light=lambda name, on: log.append(("light", name, on)), capture=capture)
    assert images.shape == (2, 3, 4, 5) and images.dtype == np.float32
    # plane 0: red shots 0, 1 (channel 0), green 2, 3 (channel 1), blue 4, 5 (channel 2)
    assert images[0, :, 0, 0].tolist() == [5.0, 26.0, 47.0]
    assert images[1, :, 0, 0].tolist() == [65.0, 86.0, 107.0]
    assert saturated[:, 2, 0, 0].all() and not saturated[:, :2].any()
    assert log[:8] == [("plane", 0), ("check", "red"), ("show", 0, "red"), ("light", "red", True),
                       ("capture", 0), ("show", 1, "red"), ("capture", 1),
                       ("light", "red", False)]


def test_colour_planes_switches_the_diode_off_when_a_capture_fails() -> None:
    log: list[tuple] = []

    def capture() -> Capture:
        raise CameraTimeout("no frame in 2 s")

    with pytest.raises(CameraTimeout, match="no frame"):
        colour_planes(1, 1, at_plane=lambda i: None, before_colour=lambda name: None,
                      show=lambda k, name: None,
                      light=lambda name, on: log.append((name, on)), capture=capture)
    assert log == [("red", True), ("red", False)]
