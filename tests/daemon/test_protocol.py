"""Protocol unit facts: strict finite JSON in, no NaN out, requests checked, params named."""

from __future__ import annotations

import json
import math

import pytest

from nhfd.daemon import protocol
from nhfd.daemon.protocol import Params, RpcError


@pytest.mark.parametrize("line", [
    b'{"jsonrpc":"2.0","method":"status","id":1',        # truncated
    b'{"jsonrpc":"2.0","method":"status","id":NaN}',      # NaN literal
    b'{"a": Infinity}', b'{"a": -Infinity}',
    b'{"a": 1e400}', b'{"a": -1e400}',                    # overflow to +-inf
    b'{"a": 1, "a": 2}',                                  # duplicate key
    b'\xff\xfe{}',                                        # not UTF-8
    b"[" * 100000 + b"]" * 100000,                        # nested too deeply
])
def test_non_finite_or_malformed_json_is_a_parse_error(line):
    with pytest.raises(RpcError) as info:
        protocol.loads(line)
    assert info.value.code == -32700


def test_finite_numbers_and_huge_integers_parse():
    assert protocol.loads(b'{"a": 1e300, "b": -2.5, "c": 7}') == {"a": 1e300, "b": -2.5, "c": 7}
    big = protocol.loads(b'{"a": 1' + b"0" * 400 + b"}")["a"]
    with pytest.raises(RpcError, match="number too large") as info:
        Params({"z_mm": big}).number("z_mm", -5, 5)
    assert info.value.data == {"field": "z_mm", "allowed": "a finite number in [-5, 5]"}


@pytest.mark.parametrize(("msg", "code"), [
    ([], -32600), ("status", -32600), (3, -32600),
    ({"method": "status", "id": 1}, -32600),                     # no jsonrpc
    ({"jsonrpc": "1.0", "method": "status", "id": 1}, -32600),
    ({"jsonrpc": "2.0", "id": 1}, -32600),                       # no method
    ({"jsonrpc": "2.0", "method": 5, "id": 1}, -32600),
    ({"jsonrpc": "2.0", "method": "status", "id": True}, -32600),
    ({"jsonrpc": "2.0", "method": "status", "id": [1]}, -32600),
    ({"jsonrpc": "2.0", "method": "status", "id": 1, "extra": 1}, -32600),
    ({"jsonrpc": "2.0", "method": "status", "params": 3, "id": 1}, -32600),
    ({"jsonrpc": "2.0", "method": "status", "params": [1], "id": 1}, -32602),
])
def test_invalid_requests(msg, code):
    with pytest.raises(RpcError) as info:
        protocol.to_request(msg)
    assert info.value.code == code


def test_notifications_and_ids():
    assert protocol.to_request({"jsonrpc": "2.0", "method": "status"}).notification
    req = protocol.to_request({"jsonrpc": "2.0", "method": "status", "id": None})
    assert not req.notification and req.id is None


def test_output_never_contains_nan_or_infinity():
    line = protocol.dumps({"a": math.nan, "b": [math.inf, -math.inf, 1.5], "c": {"d": math.nan}})
    assert b"NaN" not in line and b"Infinity" not in line and line.endswith(b"\n")
    assert json.loads(line) == {"a": None, "b": [None, None, 1.5], "c": {"d": None}}


def test_params_errors_name_the_field_and_the_allowed_range():
    cases = [
        (lambda p: p.number("z_mm", -5, 5), {"z_mm": 9}, "z_mm", "a finite number in [-5, 5]"),
        (lambda p: p.number("z_mm", -5, 5), {"z_mm": "1"}, "z_mm", "a finite number in [-5, 5]"),
        (lambda p: p.number("z_mm", -5, 5), {"z_mm": True}, "z_mm", "a finite number in [-5, 5]"),
        (lambda p: p.number("z_mm", -5, 5), {}, "z_mm", "a finite number in [-5, 5]"),
        (lambda p: p.integer("n", 1, 9), {"n": 2.0}, "n", "an integer in [1, 9]"),
        (lambda p: p.choice("c", ("red", "blue")), {"c": "x"}, "c", "one of red, blue"),
        (lambda p: p.vector("v", 3, 0, 1), {"v": [0, 1]}, "v",
         "a list of 3 finite numbers in [0, 1]"),
        (lambda p: p.vector("v", 2, 0, 1), {"v": [0, 2]}, "v[1]", "a finite number in [0, 1]"),
    ]
    for read, params, field, allowed in cases:
        with pytest.raises(RpcError) as info:
            read(Params(params))
        assert info.value.code == -32602
        assert info.value.data == {"field": field, "allowed": allowed}, params
        assert field in info.value.message and allowed in info.value.message
    p = Params({"z_mm": 1.0, "zz": 2})
    p.number("z_mm", -5, 5)
    with pytest.raises(RpcError, match="zz: unknown parameter; allowed: z_mm"):
        p.done()


def test_application_codes_stay_outside_the_reserved_range():
    for c in protocol.CODES:
        standard = c.name in ("parse_error", "invalid_request", "method_not_found",
                              "invalid_params", "internal_error")
        assert (-32768 <= c.code <= -32000) == standard
    assert len({c.code for c in protocol.CODES}) == len(protocol.CODES)
