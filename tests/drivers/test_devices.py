"""`nhfd devices`: faked port, HID and USB listings, matched against the configuration."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from nhfd.cli.main import main
from nhfd.config import Config
from nhfd.drivers import discovery


def port(device, vid, pid, serial, product="", manufacturer=""):
    return SimpleNamespace(device=device, vid=vid, pid=pid, serial_number=serial,
                           product=product, manufacturer=manufacturer, description="n/a")


PORTS = [
    port("/dev/ttyUSB1", 0x0403, 0x6001, "FT5LASER", "READYBeam", "FTDI"),
    port("/dev/ttyUSB0", 0x0403, 0xFAF0, "27000123", "Brushed Motor Controller", "Thorlabs"),
    port("/dev/ttyUSB2", 0x0403, 0xFAF0, "83000007", "APT DC Motor Controller", "Thorlabs"),
    port("/dev/ttyS0", None, None, None),
]


@pytest.fixture
def fake_ports(monkeypatch):
    from serial.tools import list_ports

    monkeypatch.setattr(list_ports, "comports", lambda: list(PORTS))


def lab_config(tmp_path, laser_backend="readybeam"):
    path = tmp_path / "lab.toml"
    path.write_text(
        f'[devices]\nlaser = "{laser_backend}"\nstage = "apt"\nnavigator = "spacemouse"\n'
        '[devices.readybeam]\nusb_serial = "FT5LASER"\n'
        '[devices.apt]\nusb_serial = "27000123"\n'
    )
    return path


def test_serial_ports_are_matched_by_usb_serial_number(fake_ports, tmp_path):
    from nhfd.config import check_file

    devices = check_file(lab_config(tmp_path, laser_backend="simulated")).devices
    found = {f.name: f for f in discovery.serial_ports(devices)}
    assert list(found) == ["/dev/ttyS0", "/dev/ttyUSB0", "/dev/ttyUSB1", "/dev/ttyUSB2"]
    assert found["/dev/ttyUSB1"].uses == [
        "devices.readybeam (usb_serial FT5LASER; not in use: devices.laser = 'simulated')"]
    assert found["/dev/ttyUSB1"].usb_id == "0403:6001"
    assert found["/dev/ttyUSB0"].uses == ["devices.apt (usb_serial 27000123; in use)"]
    # A Thorlabs controller nobody names yet: say what to put in the config.
    assert found["/dev/ttyUSB2"].uses == [
        'a Thorlabs APT controller: set devices.apt.usb_serial = "83000007" to use it']
    assert found["/dev/ttyS0"].uses == [] and found["/dev/ttyS0"].usb_id == "-"


def test_a_port_path_in_the_config_matches_too():
    devices = Config().devices.model_copy(update={
        "readybeam": Config().devices.readybeam.model_copy(update={"port": "/dev/ttyUSB1"})})
    assert discovery.uses_of(devices, port="/dev/ttyUSB1", serial_number="X") == [
        "devices.readybeam (port /dev/ttyUSB1; not in use: devices.laser = 'simulated')"]
    assert discovery.uses_of(devices, port="/dev/ttyUSB9") == []


def test_hid_and_usb_listings_match_the_spacemouse_by_vendor_and_product(monkeypatch):
    monkeypatch.setattr(discovery.hid, "enumerate", lambda: [
        {"vendor_id": 0x256F, "product_id": 0xC635, "path": b"/dev/hidraw3",
         "serial_number": "", "manufacturer_string": "3Dconnexion",
         "product_string": "SpaceMouse Compact"},
        {"vendor_id": 0x046D, "product_id": 0xC52B, "path": b"/dev/hidraw1",  # a Logitech mouse
         "serial_number": "", "manufacturer_string": "Logitech", "product_string": "Receiver"},
    ])
    devices = Config().devices
    found = discovery.hid_devices(devices)
    assert found[0].uses == [
        "devices.spacemouse (usb id 256f:c635; not in use: devices.navigator = 'none')"]
    assert found[0].name == "/dev/hidraw3"
    assert found[0].description == "3Dconnexion SpaceMouse Compact"
    assert found[1].uses == []  # Logitech's vendor id alone never matches

    dev = SimpleNamespace(bus=1, address=7, idVendor=0x0403, idProduct=0xFAF0,
                          serial_number="27000123", manufacturer="Thorlabs", product="KDC101")
    backends = []
    monkeypatch.setattr(discovery.usb.core, "find",
                        lambda find_all, backend: backends.append(backend) or iter([dev]))
    found, note = discovery.usb_devices(devices)
    assert note == ""
    assert found[0].name == "bus 1 address 7" and found[0].usb_id == "0403:faf0"
    assert found[0].uses == [
        'a Thorlabs APT controller: set devices.apt.usb_serial = "27000123" to use it']
    # The listing goes through the libusb that libusb-package ships, not a system library.
    assert backends[0] is not None
    assert backends[0].lib._name == str(discovery.libusb_package.get_library_path())


def test_real_hidapi_and_pyusb_list_this_machine():
    """No fakes: hidapi enumerates and pyusb loads libusb-package's libusb (this machine's
    devices, none in a container: what matters is that both listings exist)."""
    listing = discovery.list_devices(Config().devices)
    assert isinstance(listing.hid, list)
    assert isinstance(listing.usb, list), listing.usb_note
    assert listing.usb_note == ""
    assert all(f.kind == "usb" and f.vid is not None for f in listing.usb)


def test_no_libusb_is_named(monkeypatch):
    def find(find_all, backend):
        raise discovery.usb.core.NoBackendError("No backend available")

    monkeypatch.setattr(discovery.usb.core, "find", find)
    assert discovery.usb_devices(Config().devices) == (
        None, "pyusb found no libusb: install the system's libusb-1.0")


def test_nhfd_devices_prints_each_port_and_its_entry(fake_ports, tmp_path, capsys,
                                                     monkeypatch):
    monkeypatch.setattr(discovery.hid, "enumerate", lambda: [])
    monkeypatch.setattr(discovery.usb.core, "find", lambda find_all, backend: iter([]))
    path = lab_config(tmp_path)
    assert main(["devices", "--config", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"config: {path}" in out
    assert ("  /dev/ttyUSB1  0403:6001  serial FT5LASER  FTDI READYBeam\n"
            "      -> devices.readybeam (usb_serial FT5LASER; in use)") in out
    assert "  /dev/ttyS0  -  no serial number\n      -> no config entry would use it" in out
    assert "HID devices:\n  none\nUSB devices:\n  none" in out
    assert main(["devices", "--config", str(path), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    by_name = {f["name"]: f for f in data["serial"]}
    assert by_name["/dev/ttyUSB0"]["uses"] == ["devices.apt (usb_serial 27000123; in use)"]
    assert data["hid"] == [] and data["usb"] == [] and data["usb_note"] == ""


def test_nhfd_devices_with_nothing_connected(monkeypatch, capsys, tmp_path):
    from serial.tools import list_ports

    monkeypatch.setattr(list_ports, "comports", lambda: [])
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("NHFD_CONFIG", raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "config: packaged default only\nSerial ports:\n  none\n" in out
