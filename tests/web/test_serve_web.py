"""`nhfd serve` with `[daemon.web] enabled = true`, as a real process: the page is served with a
token of its own in <runtime_dir>/web.token (mode 0600; no TCP port, so no TCP token), and a
clean shutdown takes the page and the token file away with the daemon."""

from __future__ import annotations

import base64
import http.client
import socket
import subprocess
import sys

import pytest

from nhfd.daemon.client import Client, DaemonUnavailable
from tests.daemon.conftest import free_port, wait_until

pytest.importorskip("aiohttp", reason="the web view needs the web extra (aiohttp)")


def get(port: int, path: str, headers: dict | None = None) -> http.client.HTTPResponse:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    conn.request("GET", path, headers=headers or {})
    response = conn.getresponse()
    response.read()
    conn.close()
    return response


def test_nhfd_serve_serves_the_page_and_takes_it_away_at_shutdown(short_dir):
    port = free_port()
    run = short_dir / "run"
    config = short_dir / "nhfd.toml"
    config.write_text(f"""
[devices]
laser = "simulated"
slm = "none"
camera = "none"
stage = "none"
[devices.readybeam.guardian]
socket_path = "{short_dir / 'laser.sock'}"
[daemon.server]
runtime_dir = "{run}"
[daemon.paths]
snapshot_dir = "{short_dir / 'snaps'}"
[daemon.web]
enabled = true
port = {port}
""")
    proc = subprocess.Popen([sys.executable, "-m", "nhfd.cli.main", "serve", "--config",
                             str(config)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    try:
        def page_up() -> bool:
            assert proc.poll() is None, proc.stderr.read()
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                return True
            except OSError:
                return False

        wait_until(page_up, 30, "the web view's port")
        token_file = run / "web.token"
        assert token_file.stat().st_mode & 0o777 == 0o600
        assert not (run / "tcp.token").exists()
        token = token_file.read_text().strip()
        assert get(port, "/").status == 401
        signed_in = get(port, f"/?token={token}")
        assert signed_in.status == 303
        cookie = signed_in.getheader("Set-Cookie").split(";")[0]
        assert cookie == f"nhfd_token={token}"
        key = base64.b64encode(b"0123456789abcdef").decode()
        upgrade = {"Upgrade": "websocket", "Connection": "Upgrade", "Cookie": cookie,
                   "Sec-WebSocket-Version": "13", "Sec-WebSocket-Key": key}
        assert get(port, "/ws", upgrade).status == 101

        with Client(run / "control.sock") as c:
            c.call("shutdown")
        assert proc.wait(timeout=15) == 0
        assert "web view at http://127.0.0.1:" in proc.stderr.read()
        assert not token_file.exists()
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
        with pytest.raises(DaemonUnavailable):
            Client(run / "control.sock", timeout_s=1)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
