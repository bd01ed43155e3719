"""The README's web-view screenshot (docs/figures/web_view.png): the product, not a test panel.

    .venv/bin/python scripts/web_screenshot.py [--out docs/figures/web_view.png]

Starts `nhfd serve` as its own process on the simulated bench (every device simulated, the
guardian spawned in a temporary runtime directory) at the default 1920 x 1080 panel, with the
shipped model (`models/nhf-donut-512.onnx`) and scene (`models/scenes/donut.ply`) loaded at start,
the hologram window at the model's training size as `nhfd demo` has it (`--frame-size` for
another), and `[daemon.web]` enabled on a free loopback port. It opens the page in the system's
headless Chromium (selenium and chromedriver, as tests/web/test_web_view.py does), then drives the
bench over the Unix socket as a person at the bench would: a short orbit of five views inside the
model's pose envelope ending in its middle, the stage homed and focused on the near content
(`--depth-mm`, through the simulated relay's geometry as `nhfd demo` does), the green laser armed
at its power cap. On the page it sets the focus slider to that depth and presses Snapshot, waits
until the page shows the scene, the model, the SLM thumbnail and the new capture's thumbnail,
makes the viewport as tall as the page and saves the screenshot. At the end the lasers go off and
the daemon shuts down (it stops its guardian); the temporary folder is removed (`--keep` keeps
it, with `serve.log`).

Needs the web and dev extras (aiohttp, selenium) and the system's chromium and chromedriver.
About a minute on 2 CPU cores. Not part of the package: a tool for the docs, like the Makefile.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = REPO / "models" / "nhf-donut-512.onnx"
DEFAULT_SCENE = REPO / "models" / "scenes" / "donut.ply"
DEFAULT_OUT = REPO / "docs" / "figures" / "web_view.png"
CHROMIUM = next((p for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser")
                 if os.access(p, os.X_OK)), None)
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--hide-scrollbars")
EXPOSURE_S = 0.05  # as `nhfd demo`
PANEL_WH = (1920, 1080)  # nhfd.toml's [slm] default: the PLUTO-2.1 panel


def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML form for {v!r}")


def toml_text(tables: dict[str, dict[str, Any]]) -> str:
    """A TOML file of flat tables: {"daemon.web": {"enabled": True}, ...}."""
    out = []
    for name, keys in tables.items():
        out.append(f"[{name}]")
        out += [f"{k} = {toml_value(v)}" for k, v in keys.items()]
        out.append("")
    return "\n".join(out)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def model_metadata(path: Path) -> dict[str, Any]:
    """The model file's nhfd metadata (the JSON `nhfd export` writes under the key "nhfd"), read
    from the file as it is; the daemon checks every field when it loads the model."""
    import onnx

    props = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    if "nhfd" not in props:
        raise SystemExit(f"{path}: an ONNX model without nhfd metadata")
    return json.loads(props["nhfd"])


def bench_config(root: Path, model: Path, scene: Path, meta: dict[str, Any],
                 frame_size: list[int], port: int) -> tuple[str, Any]:
    """The daemon's configuration (as `nhfd demo` makes it: the simulated bench, a camera region
    around the hologram window, the simulated relay's focus mapping) plus the web view."""
    from nhfd.drivers.simcamera import TrueBench

    w, h = frame_size or [int(v) for v in reversed(meta["train_size_hw"])]
    truth = TrueBench()
    roi = truth.roi_for_panel((h + 64, w + 64), margin_px=16)
    tables = {
        "slm": {"width_px": PANEL_WH[0], "height_px": PANEL_WH[1]},
        "devices": {"slm": "simulated", "laser": "simulated", "stage": "simulated",
                    "camera": "simulated", "navigator": "none"},
        "devices.readybeam.guardian": {"socket_path": str(root / "laser.sock")},
        "devices.camera_settings": {"exposure_s": EXPOSURE_S, "channels": "mono"},
        "daemon.server": {"runtime_dir": str(root / "run")},
        "daemon.arming": {"guardian": "spawn"},
        "daemon.paths": {"scene_dirs": [str(scene.parent)], "model_dirs": [str(model.parent)],
                         "snapshot_dir": str(root / "snaps"), "scene": str(scene)},
        "daemon.audit": {"file": str(root / "audit.jsonl")},
        "daemon.frames": {"model": str(model), "size_px": frame_size},
        "daemon.bench": {"camera_roi_px": [int(v) for v in roi],
                         "stage_at_reference_mm": round(truth.stage_mm_for(float(meta["z0_m"]),
                                                                           1), 6)},
        "daemon.web": {"enabled": True, "host": "127.0.0.1", "port": port,
                       "push_interval_s": 0.5},
    }
    return toml_text(tables), truth


def wait_for(what: str, check: Callable[[], Any], timeout_s: float, proc: Any = None,
             log: Path | None = None) -> Any:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if proc is not None and proc.poll() is not None:
            tail = log.read_text()[-1500:] if log else ""
            raise RuntimeError(f"nhfd serve exited with {proc.returncode} while waiting for "
                               f"{what}:\n{tail}")
        with contextlib.suppress(Exception):
            got = check()
            if got:
                return got
        time.sleep(0.2)
    raise TimeoutError(f"{what}: not within {timeout_s:g} s")


def run_job(client: Any, job: int, timeout_s: float) -> dict[str, Any]:
    j = client.wait_job(job, timeout_s)
    if j["state"] != "done":
        raise RuntimeError(f"{j.get('kind')} job {job} {j['state']}: {j.get('error')}")
    return j


def screenshot(args: argparse.Namespace) -> dict[str, Any]:
    from PIL import Image
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    from nhfd.daemon.client import Client

    driver_path = shutil.which("chromedriver")
    if CHROMIUM is None or driver_path is None:
        raise SystemExit("needs the system's chromium and chromedriver "
                         "(apt-get install chromium chromium-driver)")
    model, scene = args.model.resolve(), args.scene.resolve()
    if not scene.is_file():
        raise SystemExit(f"{scene}: no such scene file")
    meta = model_metadata(model)
    root = Path(tempfile.mkdtemp(prefix="nhfd-shot-", dir="/tmp"))
    port = free_port()
    text, truth = bench_config(root, model, scene, meta, args.frame_size, port)
    (root / "nhfd.toml").write_text(text)
    log_path = root / "serve.log"
    log = log_path.open("w")
    proc = subprocess.Popen([sys.executable, "-m", "nhfd.cli.main", "serve", "--config",
                             str(root / "nhfd.toml")], cwd=root, stdout=subprocess.DEVNULL,
                            stderr=log)
    profile = tempfile.mkdtemp(prefix="nhfd-chromium-")
    browser = None
    c = None
    try:
        sock = root / "run" / "control.sock"

        def ready() -> bool:
            st = Client(sock, timeout_s=30).status()
            if st.get("errors"):
                print("daemon errors:", st["errors"], file=sys.stderr)
            return (st["frames"]["state"] == "running" and st["model"] != "none loaded"
                    and bool(st["scene"]))
        wait_for("the daemon with the model and the scene", ready, 240, proc, log_path)
        c = Client(sock, timeout_s=60)
        token = (root / "run" / "web.token").read_text().strip()
        url = f"http://127.0.0.1:{port}/"
        opts = webdriver.ChromeOptions()
        opts.binary_location = CHROMIUM
        for flag in (*FLAGS, f"--window-size={args.width},{args.height}",
                     f"--user-data-dir={profile}"):
            opts.add_argument(flag)
        browser = webdriver.Chrome(service=Service(driver_path), options=opts)
        browser.get(f"{url}?token={token}")
        wait = WebDriverWait(browser, 120, poll_frequency=0.2)
        wait.until(lambda d: d.find_element(By.ID, "connection").text == "live")

        # A short orbit inside the model's pose envelope, as `nhfd demo` drives it, ending in
        # the middle view: the page follows each frame.
        env = meta.get("pose_envelope") or {}
        az = env.get("azimuth_deg") or [-20.0, 20.0]
        el = env.get("elevation_deg") or [20.0, 20.0]
        dist = env.get("distance") or [2.0, 2.0]
        mid = 0.5 * (az[0] + az[1]) + args.azimuth_offset_deg
        quarter = 0.25 * (az[1] - az[0])
        orbit = {}
        for a in (mid - quarter, mid - 0.5 * quarter, mid + 0.5 * quarter, mid + quarter, mid):
            orbit = {"azimuth_deg": round(a, 1), "elevation_deg": round(0.5 * (el[0] + el[1]), 1),
                     "radius": round(0.5 * (dist[0] + dist[1]), 3)}
            seq = c.call("set_view", orbit=orbit)["seq"]
            wait_for(f"view {seq}", lambda seq=seq: c.status()["view"]["applied_seq"] == seq,
                     120, proc, log_path)
        # The camera focused on the near content: the daemon's (uncalibrated) focus in the
        # focus slider's 0.05 mm steps, the stage homed first.
        # As `nhfd demo` (focus_command_mm): stage travel is M^2 times the hologram depth.
        z_mm = round(round(args.depth_mm / truth.stage_scale / 0.05) * 0.05, 2)
        run_job(c, c.call("focus", z_mm=z_mm, home=True)["job"], 120)
        c.call("laser", action="arm", duration_s=600.0)
        # The driver clamps the request to devices.readybeam.max_power_pct (10 % by default).
        c.call("laser", action="power", channel="green", power_pct=args.power_pct)
        c.call("laser", action="enable", channel="green")

        def shown(img: str) -> bool:
            return browser.execute_script(
                "const i = document.getElementById(arguments[0]);"
                "return i.complete && i.naturalWidth > 0", img)
        wait.until(lambda d: shown("slm"))
        wait.until(lambda d: "Gaussians" in d.find_element(By.ID, "scene").text)
        wait.until(lambda d: d.find_element(By.ID, "model").text != "none loaded")
        wait.until(lambda d: "ARMED" in d.find_element(By.ID, "armed").text)
        # The page's controls where the bench is: the focus slider at the stage's depth (the
        # daemon's focus job, already there), the orbit sliders at the view.
        browser.execute_script("""
            const s = document.getElementById('focus'); s.value = arguments[0];
            s.dispatchEvent(new Event('input')); s.dispatchEvent(new Event('change'));""", z_mm)
        browser.execute_script("""
            const v = arguments[0];
            document.getElementById('azimuth').value = v.azimuth_deg;
            document.getElementById('az-value').textContent = Math.round(v.azimuth_deg);
            document.getElementById('elevation').value = v.elevation_deg;
            document.getElementById('el-value').textContent = Math.round(v.elevation_deg);
            document.getElementById('radius').value = v.radius;""", orbit)
        browser.find_element(By.ID, "snapshot").click()
        wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, "#snapshot-result a"))
        wait.until(lambda d: shown("camera"))
        time.sleep(2 * 0.5 + 0.3)  # two pushes: every thumbnail and the status current
        # The whole page in one picture: the viewport as tall as the page.
        height = browser.execute_script("return document.documentElement.scrollHeight")
        browser.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", {
            "width": args.width, "height": int(height), "deviceScaleFactor": 1,
            "mobile": False})
        time.sleep(0.3)
        png = browser.get_screenshot_as_png()
        args.out.parent.mkdir(parents=True, exist_ok=True)
        Image.open(io.BytesIO(png)).save(args.out, optimize=True)
        st = c.status()
        summary = {"out": str(args.out), "size_px": list(Image.open(args.out).size),
                   "orbit": orbit, "focus_z_mm": z_mm, "panel": st.get("panel"),
                   "model": st["model"] if isinstance(st["model"], str) else
                   {k: st["model"].get(k) for k in ("path", "profile", "frame_hw", "window_hw")},
                   "scene": {k: (st["scene"] or {}).get(k) for k in ("path", "gaussians")},
                   "timings": st.get("timings"),
                   "frames_shown": st["frames"].get("frames_shown")}
        return summary
    finally:
        if browser is not None:
            with contextlib.suppress(Exception):
                browser.quit()
        shutil.rmtree(profile, ignore_errors=True)
        if c is not None:
            with contextlib.suppress(Exception):
                c.call("laser", action="off")
            with contextlib.suppress(Exception):
                c.call("shutdown")
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(30)
        if proc.poll() is None:
            proc.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(10)
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        log.close()
        if args.keep:
            print(f"kept {root}", file=sys.stderr)
        else:
            shutil.rmtree(root, ignore_errors=True)


def size(text: str) -> list[int]:
    w, h = (int(v) for v in text.lower().split("x"))
    return [w, h]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    p.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="the PNG to write")
    p.add_argument("--frame-size", type=size, default=[],
                   help="hologram window WxH (daemon.frames.size_px; default: the model's "
                        "training size, as `nhfd demo`)")
    p.add_argument("--depth-mm", type=float, default=1.0,
                   help="hologram depth the camera is focused on (mm from the reference plane)")
    p.add_argument("--power-pct", type=float, default=10.0,
                   help="green laser power asked for (clamped to the configured cap)")
    p.add_argument("--azimuth-offset-deg", type=float, default=0.0,
                   help="the view's azimuth from the middle of the model's pose envelope")
    p.add_argument("--width", type=int, default=1400, help="browser window width (px)")
    p.add_argument("--height", type=int, default=900, help="browser window height (px)")
    p.add_argument("--keep", action="store_true", help="keep the temporary folder (logs)")
    args = p.parse_args(argv)
    print(json.dumps(screenshot(args), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
