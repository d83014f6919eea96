"""Camera frames of the first recording format (read only): Foxglove's image schemas as JSON,
pixels in base64, the fields of `Image` Foxglove has no place for in an `archery` object.

Recordings written since store frames as protobuf (`apps.topics.image_records`); this module lets
a replay still read the older files.
"""

from __future__ import annotations

from typing import Any

import msgspec

from archery.apps.topics.image_records import COMPRESSED, RAW, checked_image
from archery.protocol.errors import DecodeError
from archery.protocol.messages import Image

__all__ = ["json_image_from_record"]


class _Time(msgspec.Struct, frozen=True):
    sec: int
    nsec: int


class _ImageMeta(msgspec.Struct, frozen=True):
    schema: int
    seq: int
    stamp: float
    sim_time: float | None
    frame: int
    width: int = 0  # compressed images only: their size
    height: int = 0
    encoding: str = ""


class _RawImage(msgspec.Struct, frozen=True):
    timestamp: _Time
    frame_id: str
    width: int
    height: int
    encoding: str
    step: int
    data: bytes
    archery: _ImageMeta


class _CompressedImage(msgspec.Struct, frozen=True):
    timestamp: _Time
    frame_id: str
    data: bytes
    format: str
    archery: _ImageMeta


_decoders: dict[str, msgspec.json.Decoder[Any]] = {
    RAW: msgspec.json.Decoder(_RawImage),
    COMPRESSED: msgspec.json.Decoder(_CompressedImage),
}


def json_image_from_record(name: str, data: bytes) -> Image:
    """The `Image` a JSON record of `RAW` or `COMPRESSED` holds (validated).

    Raises:
        DecodeError: data that does not fit the schema, or an invalid image.
    """
    try:
        record = _decoders[name].decode(data)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise DecodeError(f"invalid {name} record: {exc}") from None
    meta = record.archery
    if isinstance(record, _RawImage):
        size = (record.width, record.height, record.encoding)
    else:
        size = (meta.width, meta.height, record.format)
    stamps = (meta.schema, meta.seq, meta.stamp, meta.sim_time, meta.frame)
    return checked_image(name, stamps, size, record.data)
