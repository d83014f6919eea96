"""Camera frames in a recording: Foxglove's image schemas as protobuf, pixels as raw bytes.

A frame is stored as `foxglove.RawImage` (rgb8, bgr8, mono8) or `foxglove.CompressedImage`
(jpeg, png), protobuf-encoded, so Foxglove's Image panel shows it and the pixels are written as
they are (no base64, no per-pixel work). The schemas are Foxglove's own (from the
`foxglove-schemas-protobuf` package) with the fields of `Image` that they have no place for
added at field numbers 100 and up: the message schema version, seq, stamp (wall s), sim time
(s, absent when the frame has none) and frame number; and for a compressed image its width,
height and encoding. Foxglove decodes with the descriptor the file carries and reads the
fields it knows by name; the replay reads them all back, so a replayed frame is the very
message that was published.
"""

from __future__ import annotations

from typing import Any

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage as _FoxCompressed
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage as _FoxRaw
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory, timestamp_pb2
from google.protobuf.message import DecodeError as ProtobufDecodeError

from archery.protocol.errors import DecodeError
from archery.protocol.messages import Image

__all__ = [
    "COMPRESSED",
    "RAW",
    "checked_image",
    "image_from_record",
    "image_record",
    "image_schema",
]

RAW = "foxglove.RawImage"
COMPRESSED = "foxglove.CompressedImage"
FRAME_ID = "target_camera"

_F = descriptor_pb2.FieldDescriptorProto
_COMMON = (  # name, number, type: the fields of `Image` Foxglove has no place for
    ("archery_schema", 100, _F.TYPE_UINT32),
    ("seq", 101, _F.TYPE_UINT64),
    ("stamp", 102, _F.TYPE_DOUBLE),
    ("sim_time", 103, _F.TYPE_DOUBLE),  # proto3 optional: absent = None
    ("frame", 104, _F.TYPE_UINT64),
)
_COMPRESSED_EXTRA = (
    ("image_width", 105, _F.TYPE_UINT32),
    ("image_height", 106, _F.TYPE_UINT32),
)


def _file(
    fox: Any, name: str, extra: tuple[tuple[str, int, int], ...]
) -> descriptor_pb2.FileDescriptorProto:
    """Foxglove's file descriptor of `fox`, its message extended with `extra` fields."""
    proto = descriptor_pb2.FileDescriptorProto()
    fox.DESCRIPTOR.file.CopyToProto(proto)
    proto.name = f"archery/{name}.proto"
    message = proto.message_type[0]
    for field_name, number, kind in _COMMON + extra:
        field = message.field.add(
            name=field_name, number=number, type=kind, label=_F.LABEL_OPTIONAL
        )
        if field_name == "sim_time":
            field.proto3_optional = True
            field.oneof_index = len(message.oneof_decl)
            message.oneof_decl.add(name="_sim_time")
    return proto


def _build() -> tuple[dict[str, Any], dict[str, bytes]]:
    pool = descriptor_pool.DescriptorPool()
    stamp_file = descriptor_pb2.FileDescriptorProto()
    timestamp_pb2.DESCRIPTOR.CopyToProto(stamp_file)
    pool.Add(stamp_file)
    classes, schemas = {}, {}
    for full, fox, extra in ((RAW, _FoxRaw, ()), (COMPRESSED, _FoxCompressed, _COMPRESSED_EXTRA)):
        proto = _file(fox, full.split(".")[1], extra)
        pool.Add(proto)
        classes[full] = message_factory.GetMessageClass(pool.FindMessageTypeByName(full))
        files = descriptor_pb2.FileDescriptorSet(file=[stamp_file, proto])
        schemas[full] = files.SerializeToString()
    return classes, schemas


_CLASSES, _SCHEMAS = _build()


def image_schema(name: str) -> bytes:
    """The schema data (a serialized protobuf `FileDescriptorSet`) of `RAW` or `COMPRESSED`."""
    return _SCHEMAS[name]


def image_record(image: Image) -> tuple[str, bytes]:
    """(schema name, protobuf bytes) of a frame: the pixels copied once, as they are (an
    rgb8_lz4 frame's as rgb8: Foxglove's raw image knows no LZ4, the recording's chunks are
    compressed anyway).

    Raises:
        ValueError: an rgb8_lz4 frame whose data does not decode."""
    image = image.unpacked()
    sec = max(0, int(image.stamp))
    nsec = min(999_999_999, max(0, round((image.stamp - sec) * 1e9)))
    common: dict[str, Any] = {
        "frame_id": FRAME_ID,
        "data": image.data,
        "archery_schema": image.schema,
        "seq": image.seq,
        "stamp": image.stamp,
        "frame": image.frame,
    }
    if image.sim_time is not None:
        common["sim_time"] = image.sim_time
    if image.encoding in ("jpeg", "png"):
        name = COMPRESSED
        common |= {
            "format": image.encoding,
            "image_width": image.width,
            "image_height": image.height,
        }
    else:
        name = RAW
        common |= {
            "width": image.width,
            "height": image.height,
            "encoding": image.encoding,
            "step": len(image.data) // image.height,
        }
    record = _CLASSES[name](**common)
    record.timestamp.seconds, record.timestamp.nanos = sec, nsec
    return name, record.SerializeToString()


def image_from_record(name: str, data: bytes) -> Image:
    """The `Image` a protobuf record of `RAW` or `COMPRESSED` holds (validated).

    Raises:
        DecodeError: not protobuf of that schema, or an invalid image.
    """
    try:
        record = _CLASSES[name].FromString(data)
    except ProtobufDecodeError as exc:
        raise DecodeError(f"invalid {name} record: {exc}") from None
    if name == COMPRESSED:
        size = (record.image_width, record.image_height, record.format)
    else:
        size = (record.width, record.height, record.encoding)
    sim_time = record.sim_time if record.HasField("sim_time") else None
    stamps = (record.archery_schema, record.seq, record.stamp, sim_time, record.frame)
    return checked_image(name, stamps, size, record.data)


def checked_image(
    name: str,
    stamps: tuple[int, int, float, float | None, int],
    size: tuple[int, int, str],
    data: bytes,
) -> Image:
    """The `Image` of a record of schema `name`: `stamps` (schema version, seq, stamp s, sim
    time s, frame), `size` (width px, height px, encoding) and its pixels.

    Raises:
        DecodeError: an invalid image; names the schema.
    """
    schema, seq, stamp, sim_time, frame = stamps
    width, height, encoding = size
    try:
        return Image(
            schema=schema,
            seq=seq,
            stamp=stamp,
            sim_time=sim_time,
            frame=frame,
            width=width,
            height=height,
            encoding=encoding,
            data=data,
        )
    except ValueError as exc:
        raise DecodeError(f"invalid {name} record: {exc}") from None
