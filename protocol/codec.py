"""encode / decode: messages to msgpack bytes and back, with size caps and one error type.

Wire layout of a message: one msgpack map ``{"type": str, "version": int, <field>: <value>, …}``
(keys in any order, no duplicates, nothing after the map), either as is or, when that is 1 kB or
more and compression is on, as one zstd frame of it (see `cpslam.protocol.quant`). Arrays are maps
``{"dtype", "shape", "data"}`` (see `cpslam.protocol.arrays`), images maps
``{"codec", "data"}`` (see `cpslam.protocol.images`), optional fields nil when absent.
"""

from __future__ import annotations

import logging
from typing import Any

import msgpack
from pydantic import ValidationError

from cpslam.protocol.base import PROTOCOL_VERSION, Message
from cpslam.protocol.delivery import Refusal, UpdateAck
from cpslam.protocol.errors import ProtocolError
from cpslam.protocol.messages import (
    DecoderWeights,
    FramePoses,
    KeyframeImage,
    KeyframeImageRequest,
    KeyframeMsg,
    SubmapDelta,
)
from cpslam.protocol.quant import compress, decompress, is_compressed
from cpslam.protocol.updates import Ack, Control, ErrorReply, GroupDecoder, ServerUpdate, Status

__all__ = [
    "COMPRESS_MIN_BYTES",
    "DEFAULT_ZSTD_LEVEL",
    "MESSAGE_TYPES",
    "MAX_MESSAGE_BYTES",
    "decode",
    "encode",
    "encoded_size",
    "max_bytes",
]

logger = logging.getLogger(__name__)

MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.type_name(): cls
    for cls in (
        KeyframeMsg,
        SubmapDelta,
        DecoderWeights,
        FramePoses,
        KeyframeImageRequest,
        KeyframeImage,
        ServerUpdate,
        GroupDecoder,
        Ack,
        Status,
        Control,
        ErrorReply,
        UpdateAck,
        Refusal,
    )
}
"""Wire name (the `type` field) -> message class."""

MAX_MESSAGE_BYTES = max(cls.max_bytes for cls in MESSAGE_TYPES.values())
"""Largest size any message may have; longer input is refused before parsing."""

COMPRESS_MIN_BYTES = 1024
"""Smaller messages go uncompressed (zstd's frame overhead eats the gain)."""

DEFAULT_ZSTD_LEVEL = 3
"""zstd level of `encode` unless told otherwise (0 = no compression)."""

# Limits on the msgpack structure itself. Our messages hold few, small containers (arrays
# are single bin objects), so these bound the Python objects hostile input can create.
_MAX_TOP_KEYS = 64
_MAX_CONTAINER_LEN = 1024
_MAX_CONTAINERS = 4096
_MAX_ERRORS_SHOWN = 5


def max_bytes(msg_type: str | type[Message]) -> int:
    """Size cap in bytes of a message type (by wire name or class)."""
    name = msg_type if isinstance(msg_type, str) else msg_type.type_name()
    if name not in MESSAGE_TYPES:
        raise ProtocolError(f"unknown message type {name!r:.60}")
    return MESSAGE_TYPES[name].max_bytes


def encode(msg: Message, zstd_level: int = DEFAULT_ZSTD_LEVEL) -> bytes:
    """msgpack bytes of `msg`, zstd-compressed at `zstd_level` (0: never) when that is shorter
    and the message has at least `COMPRESS_MIN_BYTES`; raises ProtocolError if the msgpack form
    exceeds its type's size cap."""
    if not isinstance(msg, Message) or type(msg).type_name() not in MESSAGE_TYPES:
        raise ProtocolError(f"encode: expected a protocol message, got {type(msg).__name__}")
    name = type(msg).type_name()
    try:
        fields = msg.model_dump()
        wire = {"type": fields.pop("type"), "version": fields.pop("version"), **fields}
        data = msgpack.packb(wire, use_bin_type=True)
    except ProtocolError:
        raise
    except Exception as exc:  # noqa: BLE001 - e.g. a field replaced by model_copy(update=...)
        raise ProtocolError(
            f"encode: {name} message cannot be serialised ({type(exc).__name__}: {exc})", name
        ) from exc
    if len(data) > msg.max_bytes:
        raise ProtocolError(
            f"encode: {name} message is {len(data)} bytes, over its cap of {msg.max_bytes}; "
            "split it",
            name,
        )
    if zstd_level > 0 and len(data) >= COMPRESS_MIN_BYTES:
        packed = compress(data, zstd_level)
        if len(packed) < len(data):
            return packed
    return data


def encoded_size(msg: Message) -> int:
    """Size in bytes of `encode(msg)`."""
    return len(encode(msg))


def decode(
    data: bytes | bytearray | memoryview,
    expected: type[Message] | tuple[type[Message], ...] | None = None,
) -> Message:
    """Message from msgpack bytes, fully validated.

    Args:
        data: the payload.
        expected: a message class (or tuple of classes) the payload must be.

    Raises:
        ProtocolError: on anything wrong (size, version, type, structure, any field). No
            other exception escapes for bad input.
    """
    try:
        return _decode(data, expected)
    except ProtocolError:
        raise
    except UnicodeDecodeError as exc:
        raise ProtocolError(f"decode: a string is not valid UTF-8 ({exc.reason})") from None
    except Exception as exc:  # noqa: BLE001 - the contract is: bad input -> ProtocolError only
        raise ProtocolError(f"decode: malformed message ({type(exc).__name__}: {exc})") from exc


def _decode(data: Any, expected: Any) -> Message:
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ProtocolError(f"decode: expected bytes, got {type(data).__name__}")
    data = bytes(data)
    if not data:
        raise ProtocolError("decode: empty payload")
    if len(data) > MAX_MESSAGE_BYTES:
        raise ProtocolError(
            f"decode: payload of {len(data)} bytes exceeds the largest cap {MAX_MESSAGE_BYTES}"
        )
    if is_compressed(data):
        data = decompress(data, MAX_MESSAGE_BYTES)
    name, version = _peek(data)
    if version != PROTOCOL_VERSION:
        raise ProtocolError(
            f"decode: {name!r:.60} message has protocol version {version!r:.20}, "
            f"this build speaks version {PROTOCOL_VERSION} only (peers of different versions "
            "cannot talk: upgrade both)",
            name,
        )
    cls = MESSAGE_TYPES.get(name)
    if cls is None:
        raise ProtocolError(
            f"decode: unknown message type {name!r:.60} (known: {sorted(MESSAGE_TYPES)})"
        )
    if expected is not None:
        allowed = expected if isinstance(expected, tuple) else (expected,)
        if cls not in allowed:
            want = " or ".join(repr(c.type_name()) for c in allowed)
            raise ProtocolError(f"decode: expected a {want} message, got {name!r}", name)
    if len(data) > cls.max_bytes:
        raise ProtocolError(
            f"decode: {name} message of {len(data)} bytes exceeds its cap of {cls.max_bytes}",
            name,
        )
    obj = msgpack.unpackb(data, **_unpack_options())
    try:
        return cls.model_validate(obj, strict=True)
    except ValidationError as exc:
        raise ProtocolError(_describe(name, exc), name) from None


def _peek(data: bytes) -> tuple[Any, Any]:
    """(type, version) of a payload without building its other values."""
    unpacker = msgpack.Unpacker(max_buffer_size=len(data), **_unpack_options())
    unpacker.feed(data)
    try:
        n = unpacker.read_map_header()
    except Exception as exc:  # noqa: BLE001 - the first byte is not a map (or truncated)
        raise ProtocolError(f"decode: payload is not a msgpack map ({exc})") from None
    if n > _MAX_TOP_KEYS:
        raise ProtocolError(f"decode: message map has {n} keys, at most {_MAX_TOP_KEYS} allowed")
    try:
        head = _read_head(unpacker, n)
    except msgpack.OutOfData:
        raise ProtocolError("decode: payload is truncated") from None
    if unpacker.tell() != len(data):
        raise ProtocolError(f"decode: {len(data) - unpacker.tell()} bytes after the message map")
    for key in ("type", "version"):
        if key not in head:
            raise ProtocolError(f"decode: message has no {key!r} field")
    if not isinstance(head["type"], str):
        raise ProtocolError(f"decode: 'type' must be a str, got {type(head['type']).__name__}")
    version = head["version"]
    if type(version) is not int:
        raise ProtocolError(f"decode: 'version' must be an int, got {type(version).__name__}")
    return head["type"], version


def _read_head(unpacker: msgpack.Unpacker, n: int) -> dict[str, Any]:
    """Values of the top-level "type" and "version" keys; the other values are skipped."""
    seen: set[str] = set()
    head: dict[str, Any] = {}
    for _ in range(n):
        key = unpacker.unpack()
        if not isinstance(key, str):
            raise ProtocolError(f"decode: message keys must be str, got {type(key).__name__}")
        if key in seen:
            raise ProtocolError(f"decode: duplicate key {key!r:.60}")
        seen.add(key)
        if key in ("type", "version"):
            head[key] = unpacker.unpack()
        else:
            unpacker.skip()
    return head


def _unpack_options() -> dict[str, Any]:
    count = [0]

    def counted(container: Any) -> Any:
        count[0] += 1
        if count[0] > _MAX_CONTAINERS:
            raise ProtocolError(f"decode: more than {_MAX_CONTAINERS} nested containers")
        return container

    return {
        "raw": False,
        "strict_map_key": True,
        "max_array_len": _MAX_CONTAINER_LEN,
        "max_map_len": _MAX_CONTAINER_LEN,
        "list_hook": counted,
        "object_hook": counted,
        "ext_hook": _refuse_ext,
    }


def _refuse_ext(code: int, data: bytes) -> Any:
    raise ProtocolError(f"decode: msgpack extension types are not used (got ext {code})")


def _describe(name: str, exc: ValidationError) -> str:
    errors = exc.errors(include_url=False, include_input=False)
    parts = []
    for err in errors[:_MAX_ERRORS_SHOWN]:
        field = ".".join(str(p) for p in err["loc"]) or "<message>"
        parts.append(f"field {field!r}: {err['msg']}")
    more = len(errors) - _MAX_ERRORS_SHOWN
    suffix = f"; and {more} more" if more > 0 else ""
    return f"decode: invalid {name} message: " + "; ".join(parts) + suffix
