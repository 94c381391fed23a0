"""Wire format of the daemon: versioned msgpack messages (never pickle), validated before use.

Control (client DEALER or REQ -> daemon ROUTER), one msgpack map per message::

    request  {"v": 1, "id": <int|str>, "op": <str>, "token": <str>, "args": {...}}
    reply    {"v": 1, "id": <same>, "ok": true,  "result": {...}}
             {"v": 1, "id": <same>, "ok": false, "error": {"code": <str>, "message": <str>}}

Frame stream (daemon PUSH -> client PULL), multipart ``[header, buffer]``; the header is a msgpack
map ``{"v": 1, "type": "frame", "job", "seq", "name", "dtype", "shape", "timestamp_ns", "exposure",
"meta"}`` and the buffer the raw C-ordered pixels (sent zero-copy). The last message of a job is
``[{"v": 1, "type": "end", "job", "ok", "frames", "error"}]``. See PROTOCOL.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

PROTOCOL_VERSION = 1
SUPPORTED_VERSIONS = (1,)
DEFAULT_MAX_MESSAGE_BYTES = 64 * 2**20

OPS = (
    "hello", "ping", "heartbeat", "devices", "plugins", "status", "open_rig", "close_rig", "move",
    "capture", "stream", "job", "cancel", "shutdown",
)
# error codes
BAD_MESSAGE, BAD_VERSION, UNAUTHENTICATED, UNKNOWN_OP, BAD_ARGS = "bad_message", "bad_version", "unauthenticated", "unknown_op", "bad_args"
DEVICE, BUSY, NOT_FOUND, INTERNAL = "device", "busy", "not_found", "internal"
CLIENT_TIMEOUT = "client_timeout"  # a job cancelled because its client's heartbeats stopped


class ProtocolError(Exception):
    """A message that breaks the protocol; ``code`` is one of the error codes above."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Request:
    id: int | str
    op: str
    token: str
    args: dict[str, Any]


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def unpack(data: bytes, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> Any:
    """Decode one msgpack object; refuse trailing bytes and anything larger than ``max_bytes``."""
    if len(data) > max_bytes:
        raise ProtocolError(BAD_MESSAGE, f"message of {len(data)} bytes exceeds the {max_bytes}-byte limit")
    try:
        return msgpack.unpackb(data, raw=False, strict_map_key=True)
    except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, RecursionError) as exc:
        raise ProtocolError(BAD_MESSAGE, f"not a msgpack message: {type(exc).__name__}") from None


def parse_request(data: bytes, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> Request:
    """Validate a control request (structure, version, op); authentication is checked by the server."""
    msg = unpack(data, max_bytes)
    if not isinstance(msg, dict):
        raise ProtocolError(BAD_MESSAGE, "a request must be a map")
    rid, op, token, args = msg.get("id"), msg.get("op"), msg.get("token", ""), msg.get("args", {})
    if not isinstance(rid, int | str) or isinstance(rid, bool):
        raise ProtocolError(BAD_MESSAGE, "request id must be an int or a string")

    def refused(code: str, message: str) -> ProtocolError:  # answered with the request's id (it said id: None)
        error = ProtocolError(code, message)
        error.rid = rid  # type: ignore[attr-defined]
        return error

    version = msg.get("v")
    if version not in SUPPORTED_VERSIONS or isinstance(version, bool):
        raise refused(BAD_VERSION, f"protocol version {str(version)[:20]!r} not supported (daemon speaks "
                                   f"{SUPPORTED_VERSIONS})")
    if not isinstance(op, str) or not isinstance(token, str) or not isinstance(args, dict):
        raise refused(BAD_MESSAGE, "op and token must be strings and args a map")
    if op not in OPS:
        raise refused(UNKNOWN_OP, f"unknown op {op[:40]!r}")
    return Request(rid, op, token, args)


def request(rid: int | str, op: str, token: str, **args: Any) -> bytes:
    return pack({"v": PROTOCOL_VERSION, "id": rid, "op": op, "token": token, "args": args})


def reply_ok(rid: Any, result: Any) -> bytes:
    return pack({"v": PROTOCOL_VERSION, "id": rid, "ok": True, "result": result})


def reply_error(rid: Any, code: str, message: str) -> bytes:
    return pack({"v": PROTOCOL_VERSION, "id": rid, "ok": False, "error": {"code": code, "message": message}})


def frame_header(job: str, seq: int, name: str, data: np.ndarray, timestamp_ns: int, exposure: float,
                 meta: dict[str, Any]) -> bytes:
    if data.dtype.kind not in "biuf":  # an object array's bytes are pointers into this process: never sent
        raise ProtocolError(BAD_MESSAGE, f"frame {name!r} has dtype {data.dtype.str}: numeric types only")
    return pack({"v": PROTOCOL_VERSION, "type": "frame", "job": job, "seq": seq, "name": name,
                 "dtype": data.dtype.str, "shape": list(data.shape), "timestamp_ns": int(timestamp_ns),
                 "exposure": float(exposure), "meta": meta})


def end_header(job: str, frames: int, error: dict[str, str] | None = None) -> bytes:
    return pack({"v": PROTOCOL_VERSION, "type": "end", "job": job, "ok": error is None, "frames": frames, "error": error})


def decode_frame(header: dict[str, Any], buffer: Any) -> np.ndarray:
    """The frame array viewed on the received buffer (no copy); checks size against the header."""
    dtype = np.dtype(header["dtype"])
    shape = tuple(int(s) for s in header["shape"])
    if dtype.kind not in "biuf":  # numbers only: no objects (pointers), no void or string records
        raise ProtocolError(BAD_MESSAGE, f"frame dtype {dtype.str} is not allowed: numeric types only")
    arr = np.frombuffer(buffer, dtype=dtype)
    if arr.size != int(np.prod(shape)):
        raise ProtocolError(BAD_MESSAGE, f"frame buffer of {arr.nbytes} bytes does not match shape {shape} {dtype}")
    return arr.reshape(shape)
