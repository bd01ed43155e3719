"""APT messages byte by byte, as docs/design.md ("The hardware") lays them out (little-endian,
dest 0x50, source 1)."""

from __future__ import annotations

import pytest

from nhfd.device_settings import StageSettings
from nhfd.drivers import apt
from nhfd.drivers.stage import AptDeviceError


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def test_move_absolute_is_the_example_in_hardware_md():
    assert apt.move_absolute(1, 2048) == h("53 04 06 00 D0 01 01 00 00 08 00 00")


@pytest.mark.parametrize(
    ("encoded", "expected"),
    [
        (apt.req_info(), "05 00 00 00 50 01"),
        (apt.start_update_msgs(), "11 00 00 00 50 01"),
        (apt.stop_update_msgs(), "12 00 00 00 50 01"),
        (apt.disconnect(), "02 00 00 00 50 01"),
        (apt.set_channel_enable(1, True), "10 02 01 01 50 01"),
        (apt.set_channel_enable(1, False), "10 02 01 02 50 01"),
        (apt.move_home(1), "43 04 01 00 50 01"),
        (apt.move_relative(1, -2048), "48 04 06 00 D0 01 01 00 00 F8 FF FF"),
        (apt.move_absolute(1, 864874), "53 04 06 00 D0 01 01 00 6A 32 0D 00"),
        (apt.move_stop(1, immediate=True), "65 04 01 01 50 01"),
        (apt.move_stop(1, immediate=False), "65 04 01 02 50 01"),
        (apt.req_status_bits(1), "29 04 01 00 50 01"),
        (apt.req_dc_status(1), "90 04 01 00 50 01"),
        (apt.ack_dc_status(), "92 04 00 00 50 01"),
        (apt.req_vel_params(1), "14 04 01 00 50 01"),
        (apt.set_vel_params(1, 0, 396, 1545963),
         "13 04 0E 00 D0 01 01 00 00 00 00 00 8C 01 00 00 EB 96 17 00"),
    ],
)
def test_every_host_message_is_the_hand_computed_frame(encoded, expected):
    assert encoded == h(expected)


def test_scaling_follows_the_documented_formulas():
    s = StageSettings(velocity_mm_s=2.0, acceleration_mm_s2=1.5)
    # 34554.96 counts/mm * (2048 / 6e6 s) * 65536 * 2 mm/s = 1545962.74
    assert s.velocity_units == 1545963
    # 34554.96 * (2048 / 6e6)^2 * 65536 * 1.5 = 395.77
    assert s.acceleration_units == 396
    old = StageSettings(counts_per_mm=34304.0, velocity_mm_s=1.0)
    assert old.velocity_units == round(34304 * 2048 / 6e6 * 65536)


def test_status_block_velocity_is_signed_and_bits_unsigned():
    # channel 1, position -1000, velocity -5, reserved 0, bits 0x80000401 (enabled, homed, CW)
    data = h("01 00 18 FC FF FF FB FF 00 00 01 04 00 80")
    st = apt.DcStatus.decode(data)
    assert (st.channel, st.position_counts, st.velocity_raw) == (1, -1000, -5)
    assert int(st.status) == 0x80000401
    assert st.enabled and st.homed and apt.Status.LIMIT_CW in st.status
    assert not st.moving and not st.motion_error
    assert st.encode() == data
    moving = apt.DcStatus.decode(h("01 00 00 00 00 00 10 00 00 00 20 42 00 00"))
    assert moving.moving and moving.homing and moving.motion_error


def test_hw_get_info_decodes_serial_model_and_firmware():
    data = (
        (27000123).to_bytes(4, "little")
        + b"KDC101\x00\x00"
        + (27).to_bytes(2, "little")
        + bytes([10, 0, 3, 0])  # minor, interim, major, unused
        + b"Brushed DC Controller".ljust(48, b"\x00")
        + bytes(12)
        + (1).to_bytes(2, "little") + (0).to_bytes(2, "little") + (1).to_bytes(2, "little")
    )
    assert len(data) == 84
    info = apt.HwInfo.decode(data)
    assert (info.serial_number, info.model, info.firmware) == (27000123, "KDC101", (3, 0, 10))
    assert info.notes == "Brushed DC Controller" and info.n_channels == 1
    assert info.encode() == data


def test_a_controller_stream_decodes_every_reply_kind_and_resynchronises():
    stream = apt.AptStream(from_unit=True)
    status = h("01 00 00 08 00 00 00 00 00 00 00 04 00 80")
    completed = h("64 04 0E 00 81 50") + status
    homed = h("44 04 01 00 01 50")
    rich = h("81 00 44 00 81 50") + apt.RichResponse(0x0453, 43, "bad move").encode()
    bits = h("2A 04 06 00 81 50 01 00 00 04 00 80")
    garbage = b"\x13\x37\x00\xff\x50\x01"  # includes a host-direction address pair
    messages = []
    for byte in garbage + completed + homed + garbage[:3] + rich + bits:
        messages += stream.feed(bytes([byte]))  # byte by byte: partial headers wait
    names = [m.name for m in messages]
    assert names == ["MOT_MOVE_COMPLETED", "MOT_MOVE_HOMED", "HW_RICHRESPONSE",
                     "MOT_GET_STATUSBITS"]
    assert stream.discarded == len(garbage) + 3
    assert apt.DcStatus.decode(messages[0].data).position_counts == 2048
    err = AptDeviceError("stage /dev/ttyUSB0", **{
        "code": (r := apt.RichResponse.decode(messages[2].data)).code,
        "notes": r.notes, "msg_ident": r.msg_ident})
    assert "controller error 43 about MOT_MOVE_ABSOLUTE: bad move" in str(err)


def test_a_host_stream_refuses_messages_from_the_controller():
    stream = apt.AptStream(from_unit=False)
    got = stream.feed(h("44 04 01 00 01 50") + apt.move_home(1))
    assert [m.name for m in got] == ["MOT_MOVE_HOME"] and stream.discarded == 6
