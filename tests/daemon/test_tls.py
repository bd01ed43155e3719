"""Remote operation (issue 25, part 6): the daemon's TCP port over TLS with a self-signed
certificate made here. A client that trusts the certificate and knows the token is served; one
that does not trust it fails verification before any byte of the token leaves; a wrong token is
refused; arming stays refused over TLS as over any TCP connection, and through an SSH tunnel to
the Unix socket; and a non-loopback address without TLS is refused at the configuration and at
the server."""

from __future__ import annotations

import datetime
import ipaddress
import json
import socket
import ssl
import subprocess
import sys
from pathlib import Path

import pytest

from nhfd.cli import nhfctl
from nhfd.config import ConfigError, ServerSettings, validate
from nhfd.daemon.client import Client, TLSFailure
from nhfd.daemon.protocol import RpcError
from nhfd.daemon.server import LineServer, forwarded_by_ssh, peer_credentials

from .conftest import Running, bench_config, free_port

x509 = pytest.importorskip("cryptography.x509", reason="the dev extra's cryptography makes the "
                           "test certificates")


def self_signed(root: Path, name: str, host: str = "127.0.0.1") -> tuple[Path, Path]:
    """A self-signed P-256 certificate for `host` (its IP address as subjectAltName) and its key,
    as PEM files under root."""
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = datetime.datetime.now(datetime.UTC)
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.SubjectAlternativeName(
                [x509.IPAddress(ipaddress.ip_address(host))]), critical=False)
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .sign(key, hashes.SHA256()))
    cert_path, key_path = root / f"{name}.pem", root / f"{name}.key"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                           serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    key_path.chmod(0o600)
    return cert_path, key_path


def test_tls_with_the_token_is_served_and_arming_is_still_refused(short_dir, mecom_twin,
                                                                   capsys):
    cert, key = self_signed(short_dir, "bench")
    other, _ = self_signed(short_dir, "impostor")
    config = bench_config(short_dir, mecom_twin, server={
        "tcp_port": free_port(), "tls_cert": str(cert), "tls_key": str(key)})
    r = Running(config, short_dir)
    try:
        addr = r.daemon.server.tcp_address
        token = (short_dir / "run" / "tcp.token").read_text().strip()
        with Client(tcp=addr, token=token, tls_ca=cert) as c:
            status = c.status()
            assert status["daemon"]["state"] == "ready"
            assert status["laser"]["armed"] is False
            with pytest.raises(RpcError) as info:
                c.call("laser", action="arm", duration_s=30.0)
            assert info.value.name == "forbidden"
            assert "only over the Unix socket" in info.value.message
        assert r.client().status()["laser"]["armed"] is False
        assert all(not ch["enabled"] for ch in mecom_twin_channels(r))
        with pytest.raises(RpcError) as info:
            Client(tcp=addr, token="guess", tls_ca=cert)
        assert info.value.name == "unauthorized" and info.value.message == "wrong token"
        # Trusting another certificate: the handshake fails, the token is never sent.
        with pytest.raises(TLSFailure) as failure:
            Client(tcp=addr, token=token, tls_ca=other)
        assert "certificate verify failed" in str(failure.value)
        # Plain text to the TLS port gets no JSON-RPC reply: the server drops it.
        with socket.create_connection(addr, timeout=5) as plain:
            plain.sendall(b'{"jsonrpc": "2.0", "id": 1, "method": "status"}\n')
            try:
                answer = plain.recv(4096)
            except ConnectionResetError:
                answer = b""
            assert b"jsonrpc" not in answer
        # And the daemon still serves TLS clients after those failures, nhfctl among them.
        with Client(tcp=addr, token=token, tls_ca=cert) as c:
            assert c.status()["daemon"]["tcp"] == f"{addr[0]}:{addr[1]}"
        remote = ["--tcp", f"{addr[0]}:{addr[1]}", "--tls-ca", str(cert),
                  "--token-file", str(short_dir / "run" / "tcp.token"), "--json"]
        assert nhfctl.main([*remote, "focus", "1.0"]) == 0
        assert nhfctl.main([*remote, "laser", "arm"]) == 1
        err = capsys.readouterr().err
        assert "nhfctl laser: error: forbidden: arming is accepted only over the Unix socket" in err
    finally:
        r.stop()


def mecom_twin_channels(r: Running) -> list[dict]:
    return list(r.client().status()["laser"]["channels"].values())


def test_a_certificate_for_another_host_fails_the_name_check(short_dir, mecom_twin):
    cert, key = self_signed(short_dir, "elsewhere", host="10.1.2.3")
    r = Running(bench_config(short_dir, mecom_twin, server={
        "tcp_port": free_port(), "tls_cert": str(cert), "tls_key": str(key)}), short_dir)
    try:
        with pytest.raises(TLSFailure) as failure:
            Client(tcp=r.daemon.server.tcp_address, tls_ca=cert)
        assert "IP address mismatch" in str(failure.value)
    finally:
        r.stop()


def test_listening_beyond_loopback_needs_tls():
    with pytest.raises(ConfigError) as info:
        validate({"daemon": {"server": {"tcp_port": 7700, "tcp_host": "0.0.0.0"}}}, "lab.toml")
    assert ("daemon.server.tcp_host = '0.0.0.0' is not loopback" in str(info.value)
            and "daemon.server.tls_cert and daemon.server.tls_key" in str(info.value))
    with pytest.raises(ConfigError, match=r"give both daemon\.server\.tls_cert and "
                       r"daemon\.server\.tls_key"):
        validate({"daemon": {"server": {"tls_cert": "bench.pem"}}}, "lab.toml")
    # A copied configuration skips validation: the server refuses the host itself.
    unchecked = ServerSettings.model_construct(tcp_port=7700, tcp_host="0.0.0.0")
    with pytest.raises(ValueError, match=r"daemon\.server\.tls_cert and daemon\.server\.tls_key"):
        LineServer(lambda conn, line: None, unix_path=Path("/nonexistent"), settings=unchecked)


def test_the_client_never_sends_a_token_in_clear_beyond_loopback():
    with pytest.raises(ValueError, match="only over TLS"):
        Client(tcp=("192.0.2.7", 7700), token="secret")


def test_an_unloadable_certificate_names_the_keys(tmp_path):
    from nhfd.daemon.server import server_tls_context

    (tmp_path / "c.pem").write_text("not a certificate")
    with pytest.raises(ValueError, match=r"daemon.server.tls_cert = .*c.pem.*cannot load") as info:
        server_tls_context(tmp_path / "c.pem", tmp_path / "k.pem")
    assert isinstance(info.value, ValueError) and not isinstance(info.value, ssl.SSLError)


def test_arming_through_an_ssh_tunnel_is_refused(short_dir, mecom_twin):
    # `ssh -L local.sock:control.sock bench` makes sshd the socket's peer: the kernel names the
    # process (SO_PEERCRED's pid, /proc/<pid>/comm). Here a client names itself as OpenSSH's
    # session process does, so the daemon sees exactly what a tunnel shows it.
    code = """if True:
        import ctypes, sys
        ctypes.CDLL(None).prctl(15, b"sshd-session", 0, 0, 0)  # PR_SET_NAME
        from nhfd.daemon.client import Client
        from nhfd.daemon.protocol import RpcError
        with Client(sys.argv[1]) as c:
            c.call("laser", action="power", channel="red", power_pct=5.0)
            try:
                c.call("laser", action="arm", duration_s=30.0)
                print("armed")
            except RpcError as exc:
                print(exc.name, exc.message)
    """
    r = Running(bench_config(short_dir, mecom_twin), short_dir)
    try:
        done = subprocess.run([sys.executable, "-c", code, str(r.socket)], capture_output=True,
                              text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        assert done.stdout.strip() == ("forbidden arming is refused through an SSH tunnel: a "
                                       "person arms on the bench's machine")
        assert r.client().status()["laser"]["armed"] is False
        # The same socket from a process at the bench arms (the audit log names the process).
        assert r.client().call("laser", action="arm", duration_s=30.0)["armed"] is True
        audit = [json.loads(line) for line in
                 (short_dir / "run" / "audit.jsonl").read_text().splitlines()]
        refused = [e for e in audit if e.get("outcome", "").startswith("refused")
                   and e["who"].get("process") == "sshd-session"]
        assert refused, audit[-5:]
    finally:
        r.stop()


def test_the_peer_process_is_named_by_the_kernel():
    a, b = socket.socketpair(socket.AF_UNIX)
    try:
        assert peer_credentials(a)["process"] == Path("/proc/self/comm").read_text().strip()
        assert not forwarded_by_ssh(peer_credentials(a))
        assert forwarded_by_ssh({"process": "sshd"}) and forwarded_by_ssh({"process":
                                                                            "sshd-session"})
    finally:
        a.close()
        b.close()
