"""The live web view (issue 25, part 1) in a real headless Chromium (the system's package, driven
by Selenium): against a daemon on the simulated bench, the page shows the SLM's frame pixel for
pixel, a focus change on the slider moves the stage twin to the daemon's focus mapping, the orbit
slider sets the daemon's view, the snapshot button saves a capture, an arming attempt through the
page's WebSocket is refused (the lasers stay disarmed), and a wrong or missing token is refused
by the page and by the WebSocket.

The README's picture of the page comes from scripts/web_screenshot.py (the demo bench at the
whole panel with a scene and a model loaded), not from this test's small bench."""

from __future__ import annotations

import base64
import http.client
import os
import shutil
import tempfile
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest

pytest.importorskip("aiohttp", reason="the web view needs the web extra (aiohttp)")
pytest.importorskip("selenium", reason="the browser test needs selenium (the dev extra)")

from PIL import Image
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

from nhfd.daemon.bench import stage_mm_for_focus
from tests.daemon.conftest import Running, bench_config, wait_until

REPO = Path(__file__).resolve().parents[2]
CHROMIUM = next((p for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser")
                 if os.access(p, os.X_OK)), None)
CHROMEDRIVER = shutil.which("chromedriver")
needs_browser = pytest.mark.skipif(
    CHROMIUM is None or CHROMEDRIVER is None,
    reason="no Chromium and chromedriver from the system's packages (as root, `make test` "
           "installs them: apt-get install chromium chromium-driver); the browser test skips")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--window-size=1400,1000")


def rings(h: int, w: int) -> np.ndarray:
    """A Fresnel-lens-like calibration frame, uint8 [3, H, W]: each colour's own ring pitch."""
    y, x = np.mgrid[:h, :w].astype(np.float64)
    r2 = (x - w / 2) ** 2 + (y - h / 2) ** 2
    return np.stack([np.mod(r2 * k, 256.0) for k in (0.9, 1.3, 1.7)]).astype(np.uint8)


@pytest.fixture
def bench():
    root = Path(tempfile.mkdtemp(prefix="nhfd-w-", dir="/tmp"))
    (root / "calib").mkdir()
    config = bench_config(root, None, paths={"pattern_dirs": [str(root / "calib")]},
                          bench={"camera_roi_px": [1000, 1200, 24, 32],
                                 "stage_at_reference_mm": 0.0},
                          web={"port": 0, "push_interval_s": 0.2})
    config = config.model_copy(update={"devices": config.devices.model_copy(
        update={"camera": "simulated"})})
    r = Running(config, root)
    view = None
    try:
        # Homing (from 7 mm at 2 mm/s) runs while the browser starts; focus needs a homed stage.
        r.client().call("stage_move", position_mm=0.0, home=True)
        view = r.web_view()
        yield r, view, root
    finally:
        if view is not None:
            view.stop()
        r.stop()
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture
def browser():
    profile = tempfile.mkdtemp(prefix="nhfd-chromium-")
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in (*FLAGS, f"--user-data-dir={profile}"):
        opts.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def decoded_pixels(driver, element_id: str) -> np.ndarray:
    """The image as the browser decoded it (drawn on a canvas and read back), uint8 [H, W, 4]."""
    w, h, data = driver.execute_script("""
        const img = document.getElementById(arguments[0]);
        const c = document.createElement("canvas");
        c.width = img.naturalWidth; c.height = img.naturalHeight;
        const ctx = c.getContext("2d");
        ctx.drawImage(img, 0, 0);
        const px = ctx.getImageData(0, 0, c.width, c.height).data;
        let s = ""; for (let i = 0; i < px.length; i++) s += String.fromCharCode(px[i]);
        return [c.width, c.height, btoa(s)];""", element_id)
    return np.frombuffer(base64.b64decode(data), np.uint8).reshape(h, w, 4)


def upgrade_status(url: str, cookie: str | None) -> int:
    """The HTTP status of a WebSocket upgrade of /ws with this cookie."""
    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=5)
    headers = {"Upgrade": "websocket", "Connection": "Upgrade", "Sec-WebSocket-Version": "13",
               "Sec-WebSocket-Key": base64.b64encode(b"0123456789abcdef").decode()}
    if cookie is not None:
        headers["Cookie"] = f"nhfd_token={cookie}"
    conn.request("GET", "/ws", headers=headers)
    status = conn.getresponse().status
    conn.close()
    return status


@needs_browser
def test_the_page_shows_the_bench_and_steers_it_but_never_arms(bench, browser):
    r, view, root = bench
    c = r.client()
    stage = r.daemon.bench.stage.twin
    slm = r.daemon.bench.slm
    frame = rings(36, 64)
    np.save(root / "calib" / "rings.npy", frame)
    c.call("show_pattern", path="rings.npy")

    # A wrong token: the login page again, no bench; the WebSocket refuses before upgrading.
    browser.get(f"{view.url}?token=not-{view.token}")
    assert "Wrong token." in browser.find_element(By.ID, "message").text
    assert not browser.find_elements(By.ID, "slm")
    assert upgrade_status(view.url, None) == 401
    assert upgrade_status(view.url, "guess") == 401
    assert upgrade_status(view.url, view.token) == 101  # the same request with the token

    browser.get(f"{view.url}?token={view.token}")
    assert browser.current_url == view.url  # the token went into a cookie, out of the address
    wait = WebDriverWait(browser, 10)
    wait.until(lambda d: d.find_element(By.ID, "connection").text == "live")
    wait.until(lambda d: d.execute_script(
        "const i = document.getElementById('slm'); return i.complete && i.naturalWidth > 0"))
    # The thumbnail is the panel's frame, pixel for pixel (64 x 36 < thumbnail_px: no step).
    shown = decoded_pixels(browser, "slm")
    assert shown.shape == (36, 64, 4)
    np.testing.assert_array_equal(shown[..., :3], slm.last_frame.transpose(1, 2, 0))
    np.testing.assert_array_equal(shown[..., :3], frame.transpose(1, 2, 0))
    assert "calibration pattern" in browser.find_element(By.ID, "display").text

    # The focus slider: the daemon's focus job moves the stage twin to its focus mapping.
    wait_until(lambda: c.status()["devices"]["stage"].get("homed"), 10, "the stage homed")
    z_mm = 0.4
    browser.execute_script("""
        const s = document.getElementById('focus'); s.value = arguments[0];
        s.dispatchEvent(new Event('input')); s.dispatchEvent(new Event('change'));""", z_mm)
    target_mm = stage_mm_for_focus(r.daemon.config, r.daemon.calibration, z_mm)
    assert target_mm == pytest.approx(0.4)
    wait_until(lambda: abs(stage.position_mm - target_mm) < 1e-3, 10, "the stage twin at focus")
    wait.until(lambda d: d.find_element(By.ID, "stage").text.startswith("0.400 mm"))

    # The orbit slider sets the daemon's view.
    browser.execute_script("""
        document.getElementById('radius').value = 3;
        const s = document.getElementById('azimuth'); s.value = 35;
        s.dispatchEvent(new Event('input'));""")
    wait_until(lambda: (c.status()["view"]["requested"] or {}).get("azimuth_deg") == 35.0, 5,
               "the view from the orbit slider")
    assert c.status()["view"]["requested"]["radius"] == 3.0

    # Arming through the page's own WebSocket (its cookie) is refused; nothing is armed.
    reply = browser.execute_async_script("""
        const done = arguments[arguments.length - 1];
        const ws = new WebSocket(`ws://${location.host}/ws`);
        ws.onopen = () => ws.send(JSON.stringify(
            {id: 7, op: "laser", action: "arm", duration_s: 60}));
        ws.onmessage = (e) => { const m = JSON.parse(e.data);
            if (m.type === "reply") { ws.close(); done(m); } };""")
    assert reply["ok"] is False and reply["error"]["name"] == "refused"
    assert "arming the lasers is not possible from the web view" in reply["error"]["message"]
    assert c.status()["laser"]["armed"] is False

    # A person at the bench arms and lights green (the Unix socket); the page shows it.
    c.call("laser", action="arm", duration_s=120.0)
    c.call("laser", action="power", channel="green", power_pct=20.0)
    c.call("laser", action="enable", channel="green")
    wait.until(lambda d: "ARMED" in d.find_element(By.ID, "armed").text)
    assert " s left" in browser.find_element(By.ID, "armed").text

    # The snapshot button: a capture saved in daemon.paths.snapshot_dir, offered for download, and
    # the page's camera thumbnail is that capture.
    browser.find_element(By.ID, "snapshot").click()
    link = wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, "#snapshot-result a"))[0]
    name = link.text
    assert (root / "snaps" / name).stat().st_size > 0
    wait.until(lambda d: d.execute_script(
        "const i = document.getElementById('camera'); return i.complete && i.naturalWidth > 0"))
    camera = decoded_pixels(browser, "camera")
    assert camera.shape == (24, 32, 4)
    assert camera[..., 0].max() == 255  # scaled to its own peak
    # It is that capture: the saved 16-bit PNG scaled to its own peak, to a grey level.
    saved = np.asarray(Image.open(root / "snaps" / name)).astype(np.float64)
    assert saved.shape == (24, 32) and saved.max() > 0
    expected = np.round(saved / saved.max() * 255)
    assert np.abs(camera[..., 0] - expected).max() <= 1
    assert (camera[..., 0] == camera[..., 1]).all()  # grey

    c.call("laser", action="off")
    wait.until(lambda d: d.find_element(By.ID, "armed").text == "not armed")
