"""JSON-RPC 2.0 over lines: framing, validation, and the one table of error codes.

One JSON object (or a batch array) per line, UTF-8, terminated by `\\n`. Numbers are checked
finite *after* parsing: Python's parser accepts `NaN`/`Infinity` and turns `1e400` into
infinity, so both hooks refuse them. Duplicate object keys are refused (which one would win is
parser-dependent). Output never contains NaN or infinity: non-finite floats become null, and
`json.dumps(allow_nan=False)` guards the rest.

Standard library only: the reference client imports this module.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

JSONRPC = "2.0"


@dataclass(frozen=True)
class Code:
    """One row of the error-code table: the JSON-RPC `code`, its `name` (in replies' data and the
    docs) and its `meaning` for a client."""
    code: int
    name: str
    meaning: str


# THE table of error codes. -32768..-32000 is JSON-RPC's reserved range: only its standard codes
# are used there. Application codes are 1000..1099. Keep docs (README, nhfctl) pointing here.
PARSE_ERROR = Code(-32700, "parse_error", "the line is not valid JSON (or holds NaN/Inf)")
INVALID_REQUEST = Code(-32600, "invalid_request", "not a JSON-RPC 2.0 request object, a line "
                       "over the size cap, or a refused batch")
METHOD_NOT_FOUND = Code(-32601, "method_not_found", "no such method")
INVALID_PARAMS = Code(-32602, "invalid_params", "a parameter is missing, of the wrong type or "
                      "out of range; data names the field and what is allowed")
INTERNAL_ERROR = Code(-32603, "internal_error", "a bug in the daemon; the request did not apply")
DEVICE_ERROR = Code(1000, "device_error", "a device refused or failed; data names the device")
BUSY = Code(1001, "busy", "the resource is in use (e.g. the job queue is full)")
LASER_REFUSED = Code(1002, "laser_refused", "the laser (guardian) refused: not armed, latched "
                     "fault, no heartbeat")
FORBIDDEN = Code(1003, "forbidden", "not allowed over this connection (arming needs the Unix "
                 "socket)")
PATH_NOT_ALLOWED = Code(1004, "path_not_allowed", "a file path outside the configured "
                        "directories")
UNAUTHORIZED = Code(1005, "unauthorized", "TCP connection without a valid `auth` token")
NOT_AVAILABLE = Code(1006, "not_available", "the device or feature is not available on this "
                     "bench (e.g. focus with no stage, snapshot with no camera)")
INVALID_FILE = Code(1007, "invalid_file", "the file could not be read or is not valid")
NO_SUCH_JOB = Code(1008, "no_such_job", "no job with that id")
SHUTTING_DOWN = Code(1009, "shutting_down", "the daemon is shutting down")

CODES: tuple[Code, ...] = (
    PARSE_ERROR, INVALID_REQUEST, METHOD_NOT_FOUND, INVALID_PARAMS, INTERNAL_ERROR,
    DEVICE_ERROR, BUSY, LASER_REFUSED, FORBIDDEN, PATH_NOT_ALLOWED, UNAUTHORIZED, NOT_AVAILABLE,
    INVALID_FILE, NO_SUCH_JOB, SHUTTING_DOWN,
)
BY_CODE: dict[int, Code] = {c.code: c for c in CODES}


class RpcError(Exception):
    """An error reply: `code` from the table, a one-line message, optional structured data."""

    def __init__(self, code: Code | int, message: str, data: Mapping[str, Any] | None = None,
                 *, request_id: Any = None) -> None:
        super().__init__(message)
        self.code = code.code if isinstance(code, Code) else int(code)
        self.message = message
        self.data = dict(data) if data else None
        self.request_id = request_id

    @property
    def name(self) -> str:
        """The code's name in the table (the number as text for a code not in it)."""
        known = BY_CODE.get(self.code)
        return known.name if known else str(self.code)

    def to_json(self) -> dict[str, Any]:
        """The reply's `error` object: code, message, and data when there is any."""
        err: dict[str, Any] = {"code": self.code, "message": self.message}
        if self.data:
            err["data"] = self.data
        return err


@dataclass(frozen=True)
class Request:
    """A request as parsed: `method`, `params` (named: {} when absent), `id` (None for a
    notification) and whether it is a notification (no `id`: no reply)."""
    method: str
    params: dict[str, Any]
    id: Any
    notification: bool


# ----------------------------------------------------------------------------------- parsing


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number JSON allows")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text[:40]} overflows to {value}")
    return value


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"duplicate key {key!r}")
        out[key] = value
    return out


# Deepest nesting of arrays and objects a message may have. Requests need a handful of levels;
# the parser itself stops near the interpreter's recursion limit, but what handles a message
# afterwards (sanitising, the audit log's compact copy) recurses with fewer frames to spare, so
# a line of a few hundred brackets would otherwise raise RecursionError after parsing.
MAX_NESTING = 32


def _nesting(value: Any) -> int:
    """How deeply arrays and objects nest in `value` (a scalar: 0), without recursion."""
    deepest = 0
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        children = (item.values() if isinstance(item, dict)
                    else item if isinstance(item, list) else None)
        if children is None:
            continue
        deepest = max(deepest, depth)
        if depth <= MAX_NESTING:  # one level past the cap is enough to refuse it
            stack.extend((child, depth + 1) for child in children)
    return deepest


def loads(line: bytes | str) -> Any:
    """Parse one line; RpcError(PARSE_ERROR) on anything that is not finite, strict JSON, or
    nests arrays and objects more than MAX_NESTING deep."""
    try:
        text = line.decode("utf-8") if isinstance(line, bytes) else line
        value = json.loads(text, parse_constant=_refuse_constant, parse_float=_finite_float,
                           object_pairs_hook=_no_duplicates)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeError are these
        reason = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise RpcError(PARSE_ERROR, f"parse error: {reason[:200]}") from None
    if _nesting(value) > MAX_NESTING:
        raise RpcError(PARSE_ERROR, f"parse error: nested too deeply (more than {MAX_NESTING} "
                       "levels of arrays and objects)")
    return value


def _valid_id(value: Any) -> bool:
    if isinstance(value, bool):
        return False
    return value is None or isinstance(value, str | int)


def to_request(obj: Any) -> Request:
    """Check one parsed message as a JSON-RPC 2.0 request."""
    if not isinstance(obj, dict):
        raise RpcError(INVALID_REQUEST, "a request is a JSON object")
    rid = obj.get("id")
    if "id" in obj and not _valid_id(rid):
        raise RpcError(INVALID_REQUEST, "id must be a string, an integer or null")
    reply_id = rid if "id" in obj else None
    if obj.get("jsonrpc") != JSONRPC:
        raise RpcError(INVALID_REQUEST, 'jsonrpc must be "2.0"', request_id=reply_id)
    unknown = set(obj) - {"jsonrpc", "method", "params", "id"}
    if unknown:
        raise RpcError(INVALID_REQUEST, f"unknown member(s): {', '.join(sorted(unknown))}",
                       request_id=reply_id)
    method = obj.get("method")
    if not isinstance(method, str) or not method:
        raise RpcError(INVALID_REQUEST, "method must be a non-empty string", request_id=reply_id)
    params = obj.get("params", {})
    if isinstance(params, list):
        raise RpcError(INVALID_PARAMS, "params must be an object (named parameters)",
                       {"field": "params", "allowed": "object"}, request_id=reply_id)
    if not isinstance(params, dict):
        raise RpcError(INVALID_REQUEST, "params must be an object", request_id=reply_id)
    return Request(method, params, reply_id, notification="id" not in obj)


# ---------------------------------------------------------------------------------- encoding


def sanitise(value: Any) -> Any:
    """`value` with every non-finite float as None and tuples as lists: what JSON may carry
    (the replies, the audit log and the session recording all write through it)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): sanitise(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [sanitise(v) for v in value]
    return value


def dumps(obj: Any) -> bytes:
    """One line of JSON; never NaN or Infinity (they become null)."""
    return json.dumps(sanitise(obj), allow_nan=False, separators=(",", ":")).encode() + b"\n"


def result_reply(request_id: Any, result: Any) -> dict[str, Any]:
    """The reply carrying `result` to request `request_id`."""
    return {"jsonrpc": JSONRPC, "id": request_id, "result": result}


def error_reply(request_id: Any, error: RpcError) -> dict[str, Any]:
    """The reply carrying `error` to request `request_id`."""
    return {"jsonrpc": JSONRPC, "id": request_id, "error": error.to_json()}


def request(method: str, params: Mapping[str, Any] | None = None,
            request_id: Any = None) -> dict[str, Any]:
    """A request object for `method` with named `params`; without `request_id` a notification (no
    reply)."""
    msg: dict[str, Any] = {"jsonrpc": JSONRPC, "method": method}
    if params:
        msg["params"] = dict(params)
    if request_id is not None:
        msg["id"] = request_id
    return msg


# ------------------------------------------------------------------------- parameter checking


def bad_param(name: str, message: str, allowed: str) -> RpcError:
    """The `invalid_params` error for parameter `name`: "NAME: MESSAGE; allowed: ALLOWED", with
    `field` and `allowed` in its data."""
    return RpcError(INVALID_PARAMS, f"{name}: {message}; allowed: {allowed}",
                    {"field": name, "allowed": allowed})


class Params:
    """Read a request's params by name, each checked, then `done()` refuses unknown names.

    Handlers read everything first and act after `done()`, so a bad request changes nothing.
    """

    _MISSING = object()

    def __init__(self, params: Mapping[str, Any], prefix: str = "") -> None:
        self._p = params
        self._used: set[str] = set()
        self._prefix = prefix

    def _get(self, name: str, default: Any, allowed: str) -> Any:
        self._used.add(name)
        if name in self._p:
            return self._p[name]
        if default is self._MISSING:
            raise bad_param(self._prefix + name, "missing", allowed)
        return default

    def has(self, name: str) -> bool:
        """Whether the request gives `name` (it is not marked read)."""
        return name in self._p

    def number(self, name: str, low: float, high: float, default: Any = _MISSING, *,
               low_open: bool = False) -> float:
        """`name` as a finite float in [low, high] ((low, high] with `low_open`). Absent: `default`,
        or None when the default is None; without a default it is required."""
        left = "(" if low_open else "["
        allowed = f"a finite number in {left}{low:g}, {high:g}]"
        value = self._get(name, default, allowed)
        if default is None and name not in self._p:
            return None  # type: ignore[return-value]  # optional, absent
        return check_number(self._prefix + name, value, low, high, low_open=low_open)

    def integer(self, name: str, low: int, high: int, default: Any = _MISSING) -> int:
        """`name` as an int in [low, high] (a bool is not an int); absent: as `number`."""
        allowed = f"an integer in [{low}, {high}]"
        value = self._get(name, default, allowed)
        if default is None and name not in self._p:
            return None  # type: ignore[return-value]  # optional, absent
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise bad_param(self._prefix + name, f"got {_show(value)}", allowed)
        return value

    def boolean(self, name: str, default: Any = _MISSING) -> bool:
        """`name` as true or false; absent: as `number`."""
        value = self._get(name, default, "true or false")
        if default is None and name not in self._p:
            return None  # type: ignore[return-value]  # optional, absent
        if not isinstance(value, bool):
            raise bad_param(self._prefix + name, f"got {_show(value)}", "true or false")
        return value

    def string(self, name: str, default: Any = _MISSING, *, max_len: int = 4096) -> str:
        """`name` as a string of 1 to `max_len` characters without NUL; absent: as `number`."""
        allowed = f"a string of 1 to {max_len} characters"
        value = self._get(name, default, allowed)
        if default is None and name not in self._p:
            return None  # type: ignore[return-value]  # optional, absent
        if not isinstance(value, str) or not 0 < len(value) <= max_len or "\x00" in value:
            raise bad_param(self._prefix + name, f"got {_show(value)}", allowed)
        return value

    def choice(self, name: str, options: Sequence[str], default: Any = _MISSING) -> str:
        """`name` as one of `options`; absent: as `number`."""
        allowed = "one of " + ", ".join(options)
        value = self._get(name, default, allowed)
        if default is None and name not in self._p:
            return None  # type: ignore[return-value]  # optional, absent
        if not isinstance(value, str) or value not in options:
            raise bad_param(self._prefix + name, f"got {_show(value)}", allowed)
        return value

    def vector(self, name: str, length: int, low: float, high: float,
               default: Any = _MISSING) -> list[float]:
        """`name` as a list of `length` finite floats in [low, high]; absent: as `number`."""
        allowed = f"a list of {length} finite numbers in [{low:g}, {high:g}]"
        value = self._get(name, default, allowed)
        if default is None and name not in self._p:
            return None  # type: ignore[return-value]  # optional, absent
        if not isinstance(value, list) or len(value) != length:
            raise bad_param(self._prefix + name, f"got {_show(value)}", allowed)
        return [check_number(f"{self._prefix}{name}[{i}]", v, low, high)
                for i, v in enumerate(value)]

    def numbers(self, name: str, low: float, high: float, max_len: int) -> list[float]:
        """`name` as a list of 1 to `max_len` finite floats in [low, high] (required)."""
        allowed = f"a list of 1 to {max_len} finite numbers in [{low:g}, {high:g}]"
        value = self._get(name, self._MISSING, allowed)
        if not isinstance(value, list) or not 0 < len(value) <= max_len:
            raise bad_param(self._prefix + name, f"got {_show(value)}", allowed)
        return [check_number(f"{self._prefix}{name}[{i}]", v, low, high)
                for i, v in enumerate(value)]

    def obj(self, name: str, default: Any = _MISSING) -> Params | None:
        """`name` as a nested object, read by its own Params (its errors name `name.field`); absent:
        as `number`."""
        value = self._get(name, default, "an object")
        if value is None and default is None:
            return None
        if not isinstance(value, dict):
            raise bad_param(self._prefix + name, f"got {_show(value)}", "an object")
        return Params(value, prefix=f"{self._prefix}{name}.")

    def done(self) -> None:
        """Refuse the first parameter not read (`invalid_params`, allowing the names read)."""
        unknown = [k for k in self._p if k not in self._used]
        if unknown:
            known = ", ".join(sorted(self._used)) or "none"
            raise bad_param(self._prefix + str(unknown[0]), "unknown parameter", known)


def check_number(name: str, value: Any, low: float, high: float, *,
                 low_open: bool = False) -> float:
    """`value` as a float when it is a finite number in [low, high] ((low, high] with `low_open`; a
    bool is not a number), else the `invalid_params` error for `name`."""
    left = "(" if low_open else "["
    allowed = f"a finite number in {left}{low:g}, {high:g}]"
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise bad_param(name, f"got {_show(value)}", allowed)
    try:
        number = float(value)
    except OverflowError:  # a huge integer literal: finite in JSON, not as a float
        raise bad_param(name, "number too large", allowed) from None
    in_range = (low < number if low_open else low <= number) and number <= high
    if not (math.isfinite(number) and in_range):
        raise bad_param(name, f"got {_show(value)}", allowed)
    return number


def _show(value: Any) -> str:
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 128:
        return "a huge integer"
    try:
        text = json.dumps(value, default=str)
    except (ValueError, RecursionError):
        text = type(value).__name__
    return text if len(text) <= 60 else text[:57] + "..."


def describe_codes(codes: Iterable[Code] = CODES) -> str:
    """The table as text (nhfctl --codes, docs)."""
    return "\n".join(f"{c.code:>7}  {c.name:<17} {c.meaning}" for c in codes)
