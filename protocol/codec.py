"""Encoding and validated decoding of messages (msgpack via msgspec; never pickle)."""

from __future__ import annotations

from typing import Any, TypeVar, Union

import msgspec

from archery.protocol.errors import DecodeError
from archery.protocol.messages import FLOAT_MAX, MESSAGE_TYPES, Array, Image, Message
from archery.protocol.text import SHOWN_LIMIT, cut, shown

__all__ = [
    "FINITE_EXPECTED",
    "MAX_PAYLOAD_BYTES",
    "NESTED_TOO_DEEP",
    "ImageView",
    "decode",
    "encode",
    "encode_into",
    "from_jsonable",
    "to_jsonable",
    "validation_text",
]

M = TypeVar("M", bound=Message)

MAX_PAYLOAD_BYTES = 64 * 1024 * 1024  # a 4K RGB frame is 25 MB; nothing legitimate is bigger
NESTED_TOO_DEEP = "the payload nests too deep to decode (no message nests more than a few levels)"

_encoder = msgspec.msgpack.Encoder()
_any_decoder = msgspec.msgpack.Decoder(Union[tuple(MESSAGE_TYPES.values())])  # noqa: UP007
_decoders: dict[type, msgspec.msgpack.Decoder[Any]] = {
    cls: msgspec.msgpack.Decoder(cls) for cls in MESSAGE_TYPES.values()
}


class ImageView(Image, frozen=True, tag="Image"):
    """An `Image` decoded without copying its pixels: `data` is a read-only view of the
    received payload (which it keeps alive). What subscribers get: a 1280×720 frame is then
    copied once on receipt (out of Zenoh), not twice. Validated as an `Image` is."""

    data: memoryview  # type: ignore[assignment]  # Image's bytes, as a zero-copy view


_view_decoders: dict[type, msgspec.msgpack.Decoder[Any]] = {
    Image: msgspec.msgpack.Decoder(ImageView)
}


#: msgspec's words for a `FiniteFloat` it refused (NaN or ±inf), and ours for them
_FINITE_BOUNDS = (f"Expected `float` >= {-FLOAT_MAX!r}", f"Expected `float` <= {FLOAT_MAX!r}")
FINITE_EXPECTED = "Expected a finite number"


def validation_text(exc: msgspec.ValidationError) -> str:
    """msgspec's "what - at `path`", each part cut short: what may quote the payload (an
    unknown field's name, a bad enum value), and a long one must not push the path out; a
    `FiniteFloat` refused reads `FINITE_EXPECTED`."""
    what, at, path = str(exc).partition(" - at `")
    if what.startswith(_FINITE_BOUNDS):
        what = FINITE_EXPECTED
    return cut(what, 2 * SHOWN_LIMIT) + at + cut(path, SHOWN_LIMIT)


def encode(message: Message) -> bytes:
    """Serialize a message to msgpack bytes."""
    return _encoder.encode(message)


def encode_into(message: Message, buffer: bytearray) -> None:
    """Serialize a message into `buffer` (resized to fit), reusing its memory: no new
    allocation per message for a publisher that keeps one buffer."""
    _encoder.encode_into(message, buffer)


def decode(
    payload: bytes,
    expected: type[M] | None = None,
    *,
    max_bytes: int = MAX_PAYLOAD_BYTES,
    view: bool = False,
) -> M:
    """Decode and validate a payload, optionally requiring one message type; with `view`, an
    `Image` comes as an `ImageView` (its pixels a view of `payload`, not a copy).

    Nesting is bounded: msgspec decodes nested arrays and maps by recursion, and a payload
    nesting deeper than the interpreter's recursion limit allows (about 1,000 levels on Python
    3.11, about 10,000 on 3.13; no message of ours nests more than 5) is refused like any other bad
    payload, not raised as a `RecursionError`. Whatever the error quotes of the payload (an
    unknown field's name, a bad enum value) is cut short (`protocol.text.cut`).

    Raises:
        DecodeError: oversized, not msgpack, not a message (or not `expected`), a foreign schema
            version, a NaN where a number is required, nested too deep; the message says which.
    """
    if len(payload) > max_bytes:
        raise DecodeError(f"payload of {len(payload)} bytes exceeds the limit of {max_bytes} bytes")
    decoder = _any_decoder
    if expected is not None:
        decoder = (view and _view_decoders.get(expected)) or _decoders.get(expected, _any_decoder)
    try:
        message: M = decoder.decode(payload)
        return message
    except msgspec.ValidationError as exc:
        wanted = expected.__name__ if expected is not None else "message"
        raise DecodeError(f"invalid {wanted}: {validation_text(exc)}") from None
    except msgspec.DecodeError as exc:
        raise DecodeError(f"payload is not msgpack: {cut(str(exc))}") from None
    except RecursionError:
        raise DecodeError(NESTED_TOO_DEEP) from None


def _jsonable(value: Any) -> Any:
    if isinstance(value, Array):
        return value.to_numpy().tolist()
    if isinstance(value, bytes | memoryview):
        return f"<{len(value)} bytes>"
    if isinstance(value, msgspec.Struct):
        out = {"type": type(value).__name__} if isinstance(value, Message) else {}
        out.update({f: _jsonable(getattr(value, f)) for f in value.__struct_fields__})
        return out
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def to_jsonable(message: Message) -> dict[str, Any]:
    """A JSON-friendly dict of a message: arrays as nested lists, raw bytes summarised."""
    jsonable: dict[str, Any] = _jsonable(message)
    return jsonable


def from_jsonable(obj: Any, message_type: type[M]) -> M:
    """Build a message of `message_type` from JSON-like data (the `type` field is optional).

    Raises:
        DecodeError: the data does not fit the type; the message names the field.
    """
    if not isinstance(obj, dict):
        raise DecodeError(f"a {message_type.__name__} must be a JSON object, got {shown(obj)}")
    data = {k: v for k, v in obj.items() if k != "type"}
    try:
        return msgspec.convert(data, message_type)
    except msgspec.ValidationError as exc:
        raise DecodeError(f"invalid {message_type.__name__}: {validation_text(exc)}") from None
    except RecursionError:
        raise DecodeError(NESTED_TOO_DEEP) from None
