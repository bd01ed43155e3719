"""The web view's server without a browser: its token rules, its origin check, what reaches the
daemon (never an arm, whatever the page sends), TLS beyond loopback, and the daemon's `preview`
method the thumbnails come from."""

from __future__ import annotations

import asyncio
import base64
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from nhfd.config import ConfigError, WebSettings, validate
from nhfd.daemon.protocol import RpcError
from tests.daemon.conftest import Running, bench_config

aiohttp = pytest.importorskip("aiohttp", reason="the web view needs the web extra (aiohttp)")

from nhfd.web.server import OPERATIONS, WebView, tls_context  # noqa: E402


class FakeDaemon:
    """Records every call the web view makes; answers like the daemon would."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, dict]] = []

    def __call__(self, method: str, **params):
        self.calls.append((method, params))
        if method == "status":
            return {"frames": {"frames_shown": 0}}
        if method == "preview":
            return {"source": params["source"], "available": False}
        return {"ok": True}


def start_view(tmp: Path, **settings) -> tuple[WebView, FakeDaemon]:
    fake = FakeDaemon()
    view = WebView(WebSettings(port=0, **settings), socket_path=tmp / "none.sock", token="t0k3n",
                   snapshot_dir=tmp, base_dir=tmp, call=fake)
    view.start()
    return view, fake


async def session_of(view: WebView, token: str | None, **kw) -> aiohttp.ClientSession:
    jar = aiohttp.CookieJar(unsafe=True)  # cookies for 127.0.0.1 (an IP address)
    session = aiohttp.ClientSession(cookie_jar=jar, **kw)
    if token is not None:
        async with session.get(f"{view.url}?token={token}", allow_redirects=False) as r:
            assert r.status in (303, 401)
    return session


def test_token_rules_and_the_origin_check(tmp_path):
    view, _ = start_view(tmp_path)
    (tmp_path / "snapshot-1.png").write_bytes(b"\x89PNG fake")

    async def run() -> None:
        async with await session_of(view, None) as anon:
            async with anon.get(view.url) as r:
                assert r.status == 401 and "The daemon's token" in await r.text()
                assert r.headers["X-Frame-Options"] == "DENY"
            async with anon.post(f"{view.url}login", data={"token": "nope"}) as r:
                assert r.status == 401 and "Wrong token." in await r.text()
            async with anon.get(f"{view.url}snapshots/snapshot-1.png") as r:
                assert r.status == 401
            with pytest.raises(aiohttp.WSServerHandshakeError) as info:
                await anon.ws_connect(f"{view.url}ws")
            assert info.value.status == 401
            async with anon.post(f"{view.url}login", data={"token": "t0k3n"},
                                 allow_redirects=False) as r:
                assert r.status == 303 and r.headers["Location"] == "/"
                cookie = r.headers["Set-Cookie"]
                assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
                assert "Secure" not in cookie  # plain HTTP on loopback
            async with anon.get(view.url) as r:  # the cookie from the login
                assert r.status == 200 and 'id="focus"' in await r.text()
            async with anon.get(f"{view.url}snapshots/snapshot-1.png") as r:
                assert r.status == 200 and await r.read() == b"\x89PNG fake"
            async with anon.get(f"{view.url}snapshots/..%2Fnone.sock") as r:
                assert r.status == 404
            # Another site's page in the same browser carries the cookie: its origin is refused.
            with pytest.raises(aiohttp.WSServerHandshakeError) as info:
                await anon.ws_connect(f"{view.url}ws", origin="http://evil.example")
            assert info.value.status == 403
            ws = await anon.ws_connect(f"{view.url}ws", origin=view.url.rstrip("/"))
            state = json.loads((await ws.receive()).data)
            assert state["type"] == "state" and state["slm"] is None
            await ws.close()

    try:
        asyncio.run(run())
    finally:
        view.stop()


def test_nothing_the_page_sends_arms_the_lasers(tmp_path):
    view, fake = start_view(tmp_path)
    attempts = [{"op": "laser", "action": "arm", "duration_s": 60},
                {"op": "arm", "duration_s": 60},
                {"op": "lasers_off", "action": "arm"},
                {"op": "focus", "z_mm": 1.0, "action": "arm"},
                {"op": "view", "orbit": {"azimuth_deg": 1, "elevation_deg": 0, "radius": 2},
                 "method": "laser"},
                {"op": "status"}, {"op": "shutdown"}, "not json"]

    async def run() -> list[dict]:
        async with await session_of(view, "t0k3n") as s:
            ws = await s.ws_connect(f"{view.url}ws")
            replies = []
            for i, attempt in enumerate(attempts):
                body = attempt if isinstance(attempt, str) else json.dumps({"id": i, **attempt})
                await ws.send_str(body)
                while (msg := json.loads((await ws.receive()).data))["type"] != "reply":
                    pass
                replies.append(msg)
            await ws.close()
            return replies

    try:
        replies = asyncio.run(run())
    finally:
        view.stop()
    ops = [(m, p) for m, p in fake.calls if m not in ("status", "preview")]
    # What reached the daemon: off, the focus and the view, as given, nothing else.
    assert ops == [("laser", {"action": "off"}), ("focus", {"z_mm": 1.0}),
                   ("set_view", {"orbit": {"azimuth_deg": 1, "elevation_deg": 0, "radius": 2}})]
    assert all(p.get("action") != "arm" for _, p in fake.calls)
    refused = [r for r in replies if not r["ok"]]
    assert [r["error"]["name"] for r in refused] == ["refused"] * 4 + ["invalid_request"]
    assert "arming the lasers is not possible from the web view" in refused[0]["error"]["message"]
    assert refused[2]["error"]["message"] == ("no operation 'status'; the web view offers "
                                              + ", ".join(OPERATIONS))


def test_beyond_loopback_only_with_tls(tmp_path):
    with pytest.raises(ConfigError) as info:
        validate({"daemon": {"web": {"enabled": True, "host": "0.0.0.0"}}}, "lab.toml")
    assert "daemon.web.host = '0.0.0.0' is not loopback" in str(info.value)
    assert "set daemon.web.tls_cert and daemon.web.tls_key" in str(info.value)
    with pytest.raises(ValueError, match=r"set daemon\.web\.tls_cert and daemon\.web\.tls_key"):
        WebView(WebSettings.model_construct(host="0.0.0.0", port=0, tls_cert="", tls_key=""),
                socket_path=tmp_path / "s", token="x")


def test_https_with_a_self_signed_certificate(tmp_path):
    from tests.daemon.test_tls import self_signed

    cert, key = self_signed(tmp_path, "web")
    view, _ = start_view(tmp_path, tls_cert=str(cert), tls_key=str(key))
    import ssl

    async def run() -> None:
        trusted = ssl.create_default_context(cafile=str(cert))
        async with await session_of(view, None) as s:
            async with s.post(f"{view.url}login", data={"token": "t0k3n"}, ssl=trusted,
                              allow_redirects=False) as r:
                assert r.status == 303 and "Secure" in r.headers["Set-Cookie"]
            with pytest.raises(aiohttp.ClientConnectorCertificateError):
                await s.get(view.url)  # the system's CAs do not know this certificate

    try:
        assert view.url.startswith("https://127.0.0.1:")
        asyncio.run(run())
    finally:
        view.stop()


def test_preview_is_the_panel_every_kth_pixel_and_refuses_bad_parameters():
    root = Path(tempfile.mkdtemp(prefix="nhfd-p-", dir="/tmp"))
    (root / "calib").mkdir()
    r = Running(bench_config(root, None, paths={"pattern_dirs": [str(root / "calib")]}), root)
    try:
        c = r.client()
        assert c.call("preview", source="camera") == {"source": "camera", "available": False}
        rng = np.random.default_rng(25)
        frame = rng.integers(0, 256, (3, 36, 64), dtype=np.uint8)
        np.save(root / "calib" / "p.npy", frame)
        c.call("show_pattern", path="p.npy")
        p = c.call("preview", source="slm", max_px=16)
        assert p["step"] == 4 and p["size_hw"] == [36, 64] and p["shape_hwc"] == [9, 16, 3]
        pixels = np.frombuffer(base64.b64decode(p["pixels_b64"]), np.uint8).reshape(9, 16, 3)
        np.testing.assert_array_equal(pixels, frame[:, ::4, ::4].transpose(1, 2, 0))
        assert p["showing"].startswith("pattern ")
        with pytest.raises(RpcError) as info:
            c.call("preview", source="laser")
        assert info.value.data == {"field": "source", "allowed": "one of slm, camera"}
        with pytest.raises(RpcError) as info:
            c.call("preview", source="slm", max_px=8)
        assert info.value.data["field"] == "max_px"
    finally:
        r.stop()
        shutil.rmtree(root, ignore_errors=True)


def test_the_web_view_loads_no_torch():
    code = ("import sys, nhfd.web.server; bad = [m for m in ('torch', 'numba', 'onnxruntime') "
            "if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr


def test_a_certificate_that_cannot_load_names_the_web_views_settings(tmp_path):
    (tmp_path / "junk.pem").write_text("not a certificate\n")
    settings = WebSettings(tls_cert="junk.pem", tls_key="junk.pem")
    with pytest.raises(ValueError, match=r"^daemon\.web\.tls_cert = '.*junk\.pem', "
                                         r"daemon\.web\.tls_key = '.*junk\.pem': cannot load"):
        tls_context(settings, tmp_path)
