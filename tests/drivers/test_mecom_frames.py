"""MeCom frames byte by byte, against CRCs computed here from the XMODEM definition."""

from __future__ import annotations

import pytest

from nhfd.drivers import mecom
from nhfd.drivers.errors import ProtocolError


def crc_by_definition(data: bytes) -> int:
    """CRC-16/XMODEM as polynomial division: remainder of M(x) * x^16 by
    x^16 + x^12 + x^5 + 1 over GF(2) (init 0, no reflection, no final xor)."""
    m = int.from_bytes(data, "big") << 16
    for bit in range(len(data) * 8 + 15, 15, -1):
        if m >> bit & 1:
            m ^= 0x11021 << (bit - 16)
    return m


def frame(body: str) -> bytes:
    return body.encode() + f"{crc_by_definition(body.encode()):04X}".encode() + b"\r"


def test_crc_matches_the_catalogue_check_value_and_the_definition():
    assert mecom.crc16_xmodem(b"123456789") == 0x31C3 == crc_by_definition(b"123456789")
    for data in (b"", b"#", b"#000001?VR006401", bytes(range(256))):
        assert mecom.crc16_xmodem(data) == crc_by_definition(data)


def test_query_device_type_is_the_hand_computed_frame():
    req = mecom.query(0, 1, 100, 1)
    assert req.frame == b"#000001?VR006401C657\r" == frame("#000001?VR006401")
    assert req.crc == 0xC657


def test_set_frames_for_int_and_float_values():
    enable = mecom.set_value(1, 2, 7006, 1, mecom.int_bits(1))
    assert enable.frame == b"#010002VS1B5E010000000161B7\r" == frame("#010002VS1B5E0100000001")
    power = mecom.set_value(0, 10, 7013, 1, mecom.float_bits(10.0))
    # 10.0 as an IEEE-754 single is 0x41200000; 7013 is 0x1B65.
    assert power.frame == frame("#00000AVS1B650141200000")
    minus_one = mecom.set_value(0, 3, 7000, 2, mecom.int_bits(-1))
    assert minus_one.frame == frame("#000003VS1B5802FFFFFFFF")
    assert minus_one.value_bits == 0xFFFFFFFF and minus_one.parameter == (7000, 2)


def test_value_reply_decodes_with_its_own_crc():
    req = mecom.query(0, 1, 100, 1)
    reply = mecom.decode_reply(frame("!00000100000493"), req)
    assert isinstance(reply, mecom.ValueReply) and reply.as_int == 1171
    power = mecom.decode_reply(frame("!00000141200000"), req)
    assert power.as_float == 10.0
    bad = b"!00000100000493" + b"0000\r"
    with pytest.raises(ProtocolError, match="bad CRC"):
        mecom.decode_reply(bad, req)


def test_acknowledgement_echoes_the_request_crc():
    req = mecom.set_value(0, 7, 7006, 1, 1)
    ack = f"!000007{req.crc:04X}\r".encode()
    assert isinstance(mecom.decode_reply(ack, req), mecom.Ack)
    # The device's CRC of its own 7 characters is NOT what an acknowledgement carries.
    own = frame("!000007")
    assert own != ack
    with pytest.raises(ProtocolError, match="echoes CRC"):
        mecom.decode_reply(own, req)


@pytest.mark.parametrize(
    ("code_text", "code", "meaning"),
    [
        ("01", 1, "command not available"),
        ("05", 5, "parameter not available"),
        ("07", 7, "value out of range"),
        ("09", 9, "parameter internal failure"),
        ("20", 0x20, "set timeout"),  # "20" parsed as hex, as public code does
        ("14", 20, "set timeout"),  # decimal 20 sent in hex
        ("21", 0x21, "query timeout"),
        ("15", 21, "query timeout"),
        ("0A", 10, "unknown error code"),
    ],
)
def test_error_replies_carry_hex_codes(code_text, code, meaning):
    req = mecom.set_value(0, 5, 7013, 1, mecom.float_bits(5.0))
    reply = mecom.decode_reply(frame(f"!000005+{code_text}"), req)
    assert reply == mecom.ErrorReply(code, code_text)
    assert reply.meaning == meaning
    err = mecom.MecomDeviceError(reply, req, "laser /dev/ttyUSB0")
    assert f"+{code_text}" in str(err) and meaning in str(err) and err.code == code


def test_device_frames_the_twin_sends_are_the_same_bytes():
    req = mecom.set_value(0, 5, 7013, 1, 0)
    assert mecom.error_frame(0, 5, "07") == frame("!000005+07") == b"!000005+073BC3\r"
    assert mecom.value_frame(0, 1, 1171) == frame("!00000100000493")
    assert mecom.ack_frame(req) == f"!000005{req.crc:04X}\r".encode()


def test_stale_wrong_address_and_garbage_replies_are_rejected():
    req = mecom.query(0, 9, 100, 1)
    with pytest.raises(mecom.StaleReply):
        mecom.decode_reply(frame("!00000800000493"), req)
    with pytest.raises(ProtocolError, match="address"):
        mecom.decode_reply(frame("!02000900000493"), req)
    for junk in (b"\x00\xff\r", b"!zz\r", b"!0000\r", frame("!000009+7")):
        with pytest.raises(ProtocolError):
            mecom.decode_reply(junk, req)


def test_host_frames_parse_and_a_bad_crc_is_refused():
    req = mecom.parse_request(frame("#000001?VR006401"))
    assert (req.address, req.sequence, req.payload, req.is_query) == (0, 1, "?VR006401", True)
    with pytest.raises(ProtocolError, match="bad CRC"):
        mecom.parse_request(b"#000001?VR0064010000\r")


def test_values_that_do_not_fit_are_refused():
    with pytest.raises(ValueError):
        mecom.int_bits(2**32)
    with pytest.raises(ValueError):
        mecom.query(0, 0x10000, 100, 1)
    with pytest.raises(ValueError):
        mecom.error_frame(0, 1, "7")
