"""Message types of the mesh: small frozen msgspec Structs, msgpack on the wire.

Every message carries a schema version, a sequence number, a wall-clock stamp (s since the Unix
epoch) and, where it exists, the simulation time (s). Numpy arrays travel as `Array` (dtype,
shape, raw bytes) and images as `Image` (width, height, encoding, raw bytes). A message is a
msgpack map whose `type` field names its class, so any msgpack client can read it.

Validation runs on construction *and* on decoding: a non-finite float anywhere, an array whose
bytes do not match its shape, or a foreign schema version is rejected.
"""

from __future__ import annotations

import functools
import math
import sys
from typing import Annotated, Any, Literal

import lz4.block
import msgspec
import msgspec.inspect
import numpy as np
from msgspec import Meta

from archery.protocol.journal_records import RolloutRecord
from archery.protocol.text import shown

__all__ = [
    "ALLOWED_DTYPES",
    "FLOAT_MAX",
    "MAX_BATCH",
    "MAX_CALLER_WAIT",
    "MAX_LEASE_ID",
    "MESSAGE_TYPES",
    "SCHEMA_VERSION",
    "Array",
    "Describe",
    "Detection",
    "FiniteFloat",
    "Image",
    "JointCommand",
    "JointState",
    "Message",
    "PortInfo",
    "ReplaceRequest",
    "Rollout",
    "RpcReply",
    "RpcRequest",
    "WorldEvent",
    "WorldState",
    "finite_fields",
]

SCHEMA_VERSION = 1
MAX_BATCH = 16  # joint commands started together (one per part)
MAX_LEASE_ID = 64  # characters of a lease id (`JointCommand.lease`)
ALLOWED_DTYPES = ("|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<i8", "<f4", "<f8", "|b1")
#: encoding: channels of its raw pixels in `data` (0: compressed bytes). rgb8_lz4: rgb8 pixels
#: in one LZ4 block, lossless (a rendered 1280x720 frame: 2.7 MB in ~55 kB, 0.5 ms each way).
IMAGE_ENCODINGS = {"rgb8": 3, "bgr8": 3, "mono8": 1, "rgb8_lz4": 0, "jpeg": 0, "png": 0}
_ITEMSIZE = {dtype: np.dtype(dtype).itemsize for dtype in ALLOWED_DTYPES}
_FLOATS = ("<f4", "<f8")


#: The largest finite float: `FiniteFloat`'s bounds.
FLOAT_MAX = sys.float_info.max
#: A float that decoding checks is finite (msgspec's bounds refuse NaN and ±inf) and building a
#: struct does not: a value of this type is checked where it enters a process, not where it is
#: sent (`check_finite_fields` leaves it to the decoder).
FiniteFloat = Annotated[float, Meta(ge=-FLOAT_MAX, le=FLOAT_MAX)]

_NO_FLOATS = (
    msgspec.inspect.IntType,
    msgspec.inspect.StrType,
    msgspec.inspect.BoolType,
    msgspec.inspect.LiteralType,
    msgspec.inspect.NoneType,
    msgspec.inspect.BytesType,
    msgspec.inspect.StructType,  # a nested struct checks itself (Array, Message, Reply)
    msgspec.inspect.RawType,  # undecoded msgpack: checked once decoded (RPC args)
)


def _may_hold_float(info: msgspec.inspect.Type) -> bool:
    inspect = msgspec.inspect
    if isinstance(info, inspect.Metadata):
        return _may_hold_float(info.type)
    if isinstance(info, inspect.FloatType) and info.ge == -FLOAT_MAX and info.le == FLOAT_MAX:
        return False  # a FiniteFloat: its decoder checks it
    if isinstance(info, inspect.UnionType):
        return any(_may_hold_float(t) for t in info.types)
    if isinstance(info, inspect.ListType | inspect.VarTupleType | inspect.SetType):
        return _may_hold_float(info.item_type)
    if isinstance(info, inspect.TupleType):
        return any(_may_hold_float(t) for t in info.item_types)
    if isinstance(info, inspect.DictType):
        return _may_hold_float(info.key_type) or _may_hold_float(info.value_type)
    return not isinstance(info, _NO_FLOATS)


@functools.cache
def finite_fields(cls: type[msgspec.Struct]) -> tuple[str, ...]:
    """The fields of a struct type whose values may hold a float, so `_check_finite` visits
    only those (an int, str or bool field never holds NaN): computed once per type."""
    info = msgspec.inspect.type_info(cls)
    assert isinstance(info, msgspec.inspect.StructType)
    return tuple(f.name for f in info.fields if _may_hold_float(f.type))


def check_finite_fields(struct: msgspec.Struct, prefix: str = "") -> None:
    """Raise ValueError naming the field (`prefix` + its name) where a non-finite float hides in
    `struct`; a field that is None or a finite float costs no call (the common case of every
    message's stamps, on every send and receive)."""
    for name in finite_fields(type(struct)):
        value = getattr(struct, name)
        if value is None or (type(value) is float and math.isfinite(value)):
            continue
        _check_finite(value, prefix + name)


def _check_finite(value: Any, where: str) -> None:
    """Raise ValueError if a non-finite float hides anywhere in `value`."""
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{where} is {value!r}; a finite number is required")
    elif isinstance(value, list | tuple):
        try:
            if all(map(math.isfinite, value)):  # a list of numbers: one pass, no call per item
                return
        except (TypeError, OverflowError):
            pass  # not all numbers (or an int too large for a float): item by item
        for i, item in enumerate(value):
            _check_finite(item, f"{where}[{i}]")
    elif isinstance(value, dict):
        for k, item in value.items():
            _check_finite(item, f"{where}.{k}")
    elif isinstance(value, Array):
        pass  # validated by its own __post_init__


class Array(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A numpy array as typed binary: dtype string (numpy `dtype.str`), shape, C-order bytes."""

    dtype: str
    shape: tuple[int, ...]
    data: bytes

    def __post_init__(self) -> None:
        if self.dtype not in ALLOWED_DTYPES:
            raise ValueError(f"array dtype {shown(self.dtype, 60)} is not one of {ALLOWED_DTYPES}")
        if any(n < 0 for n in self.shape) or len(self.shape) > 8:
            raise ValueError(
                f"array shape {shown(self.shape, 60)} must have ≤ 8 non-negative sizes"
            )
        expected = math.prod(self.shape) * _ITEMSIZE[self.dtype]
        if expected != len(self.data):
            raise ValueError(
                f"array of dtype {self.dtype} and shape {self.shape} needs {expected} bytes, "
                f"got {len(self.data)}"
            )
        # one vectorised pass over a flat view of the bytes (no copy, no reshape)
        if self.dtype in _FLOATS and not np.isfinite(np.frombuffer(self.data, self.dtype)).all():
            raise ValueError("array holds NaN or infinite values; finite numbers are required")

    @classmethod
    def from_numpy(cls, array: np.ndarray) -> Array:
        """Wrap a numpy array (converted to little-endian, C order)."""
        a = np.ascontiguousarray(array)
        a = a.astype(a.dtype.newbyteorder("<"), copy=False)
        return cls(dtype=a.dtype.str, shape=tuple(int(n) for n in a.shape), data=a.tobytes())

    def to_numpy(self) -> np.ndarray:
        """A read-only numpy view of the bytes."""
        return np.frombuffer(self.data, dtype=np.dtype(self.dtype)).reshape(self.shape)


class Message(msgspec.Struct, frozen=True, kw_only=True, tag=True, tag_field="type"):
    """Base of every message: schema version, sequence number, stamps (s)."""

    schema: int = SCHEMA_VERSION
    seq: int = 0
    stamp: float = 0.0
    sim_time: float | None = None

    def __post_init__(self) -> None:
        if self.schema != SCHEMA_VERSION:
            raise ValueError(
                f"{type(self).__name__} has schema version {self.schema}; this node speaks "
                f"version {SCHEMA_VERSION} (update the sender or this node)"
            )
        check_finite_fields(self)
        self.validate()

    def validate(self) -> None:
        """Type-specific checks beyond the field types; raise ValueError when invalid."""


class JointState(Message, frozen=True):
    """Joint positions (rad) and velocities (rad/s) of one controlboard part."""

    part: str
    names: list[str]
    position: list[float]
    velocity: list[float]
    motion_done: bool = True

    def validate(self) -> None:
        if not len(self.names) == len(self.position) == len(self.velocity):
            raise ValueError(
                f"joint state of {shown(self.part, 60)}: {len(self.names)} names, "
                f"{len(self.position)} positions and {len(self.velocity)} velocities differ"
            )


class JointCommand(Message, frozen=True):
    """Joint position targets (rad) for a part; `names` selects a subset (default: all).

    `batch`: how many commands, this one included and one per part, the sender publishes back
    to back to start together: a robot at rest waits for all of them (at most its batch window)
    and starts them at one simulated time. 1 (default): start this one at once.

    `lease`: the lease id the part's `claim` verb gave the sender ("" for none, the default, so
    recordings made before leases still decode). While a client holds the part's lease the robot
    obeys only commands that carry it; with no lease held it takes commands from anyone.
    """

    part: str
    position: list[float]
    names: list[str] | None = None
    batch: int = 1
    lease: str = ""

    def validate(self) -> None:
        if not 1 <= self.batch <= MAX_BATCH:
            raise ValueError(
                f"joint command for {shown(self.part, 60)}: batch must be in 1..{MAX_BATCH}, "
                f"got {self.batch}"
            )
        if len(self.lease) > MAX_LEASE_ID:
            raise ValueError(
                f"joint command for {self.part!r}: a lease id has at most {MAX_LEASE_ID} "
                f"characters, got {len(self.lease)}"
            )
        if self.names is not None and len(self.names) != len(self.position):
            raise ValueError(
                f"joint command for {shown(self.part, 60)}: {len(self.names)} names but "
                f"{len(self.position)} positions"
            )


class WorldState(Message, frozen=True):
    """What a renderer needs to draw the scene: generalized positions and the shot phase."""

    qpos: Array
    phase: str = "idle"  # idle | nocked | flying | stuck | missed
    shot: int = 0


class WorldEvent(Message, frozen=True):
    """A shot event, or a `watchdog` hold (`reason` names the part). `impact_m` is the
    ground-truth r (m) on the target plane: tests/plots only."""

    kind: Literal["grasped", "nocked", "released", "landed", "missed", "reset", "watchdog"]
    shot: int = 0
    impact_m: list[float] | None = None
    reason: str = ""


class Image(Message, frozen=True):
    """An image: raw pixels (rgb8, bgr8, mono8; row-major), rgb8 pixels in an LZ4 block
    (rgb8_lz4: lossless, the camera's default) or compressed bytes (jpeg, png)."""

    width: int
    height: int
    encoding: str
    data: bytes
    frame: int = 0

    def validate(self) -> None:
        if self.encoding not in IMAGE_ENCODINGS:
            raise ValueError(
                f"image encoding {shown(self.encoding, 60)} is not one of {sorted(IMAGE_ENCODINGS)}"
            )
        if not (0 < self.width <= 16384 and 0 < self.height <= 16384):
            raise ValueError(f"image size {self.width}x{self.height} is outside 1..16384 px")
        channels = IMAGE_ENCODINGS[self.encoding]
        if channels and len(self.data) != self.width * self.height * channels:
            raise ValueError(
                f"{self.encoding} image of {self.width}x{self.height} needs "
                f"{self.width * self.height * channels} bytes, got {len(self.data)}"
            )

    @classmethod
    def from_numpy(cls, pixels: np.ndarray, encoding: str = "rgb8", **fields: Any) -> Image:
        """Wrap an HxWx3 (rgb8/bgr8/rgb8_lz4) or HxW (mono8) uint8 array; rgb8_lz4 compresses
        the rgb8 pixels into one LZ4 block."""
        if pixels.dtype != np.uint8 or pixels.ndim not in (2, 3):
            raise ValueError(f"pixels must be a uint8 HxW or HxWx3 array, got {pixels.dtype}")
        height, width = pixels.shape[:2]
        if encoding == "rgb8_lz4":
            if pixels.shape[2:] != (3,):
                raise ValueError(f"rgb8_lz4 packs HxWx3 pixels, got shape {pixels.shape}")
            data = lz4.block.compress(np.ascontiguousarray(pixels), store_size=False)
        else:
            data = np.ascontiguousarray(pixels).tobytes()
        return cls(width=width, height=height, encoding=encoding, data=data, **fields)

    def unpacked(self) -> Image:
        """This image with raw pixels: an rgb8_lz4 image as rgb8 (the same pixels), any other
        as it is.

        Raises:
            ValueError: the LZ4 block does not decode to width × height × 3 bytes.
        """
        if self.encoding != "rgb8_lz4":
            return self
        size = self.width * self.height * 3
        try:
            data = lz4.block.decompress(self.data, uncompressed_size=size)
        except lz4.block.LZ4BlockError as exc:
            raise ValueError(f"rgb8_lz4 image data does not decode: {exc}") from None
        if len(data) != size:
            raise ValueError(
                f"rgb8_lz4 image of {self.width}x{self.height} decodes to {len(data)} bytes, "
                f"not {size}"
            )
        return msgspec.structs.replace(self, encoding="rgb8", data=data)

    def to_numpy(self) -> np.ndarray:
        """Pixels as uint8: HxWx3 in RGB order for colour encodings, HxW for mono8.

        Raises:
            ValueError: compressed data that does not decode."""
        if self.encoding == "rgb8_lz4":
            return self.unpacked().to_numpy()
        if self.encoding in ("jpeg", "png"):
            import cv2

            bgr = cv2.imdecode(np.frombuffer(self.data, np.uint8), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ValueError(f"{self.encoding} image data does not decode")
            return bgr[:, :, ::-1]
        channels = IMAGE_ENCODINGS[self.encoding]
        shape = (self.height, self.width, channels) if channels == 3 else (self.height, self.width)
        pixels = np.frombuffer(self.data, np.uint8).reshape(shape)
        return pixels[:, :, ::-1] if self.encoding == "bgr8" else pixels


class Detection(Message, frozen=True):
    """Target centre and arrow tip in an image (px: column, row) and the reward vector r (m):
    arrow − centre on the target plane, r[0] to the robot's right, r[1] up (the paper's
    r = m_T − m_A in pixels, re-expressed in metres); `status` "ok" when both were found;
    `rings` the target's fitted ring ellipses (px), inner to outer, for viewers."""

    frame_stamp: float
    status: Literal["ok", "no_target", "no_arrow"]
    target_px: list[float] | None = None
    arrow_px: list[float] | None = None
    target_confidence: float = 0.0
    arrow_confidence: float = 0.0
    r_m: list[float] | None = None
    rings: (
        list[
            Annotated[
                list[float],
                Meta(
                    min_length=5,
                    max_length=5,
                    description="a fitted ring ellipse: centre column, centre row, full axis "
                    "lengths (px) and angle (degrees, OpenCV's convention)",
                ),
            ]
        ]
        | None
    ) = None


class Rollout(Message, frozen=True):
    """One rollout as the learner journaled it: its proposed, done or aborted journal record
    (`protocol.journal_records`; a done record travels without the learner's state, which only
    the journal keeps). θ, r and the distances are in m."""

    record: RolloutRecord

    def validate(self) -> None:
        # the record is a nested struct: its floats are checked here
        for name in finite_fields(type(self.record)):
            _check_finite(getattr(self.record, name), f"record.{name}")


MAX_CALLER_WAIT = 3600.0  # s: the longest a caller may say it waits for a reply


class RpcRequest(Message, frozen=True):
    """A request to an `rpc:i` port: a verb, its arguments and how long its caller waits for the
    reply (s; None: not said). A server never works on a request after its caller has given up
    (`mesh.rpc_server`)."""

    verb: str
    args: dict[str, Any] = {}
    wait: Annotated[float, Meta(gt=0.0, le=MAX_CALLER_WAIT)] | None = None


class RpcReply(Message, frozen=True):
    """`ok` with a result, or an error with a code and a message saying what was wrong;
    `service` names the lost upstream service of an `upstream_lost` error."""

    ok: bool
    result: Any = None
    code: str = ""
    message: str = ""
    service: str = ""


class PortInfo(msgspec.Struct, frozen=True):
    """One port of a service: key, kind (pub, events, sub, rpc), message type name and, for a
    pub or events port, how many messages the service has sent on it since it started (its
    rate is the count's rise between two describes: nobody need subscribe to measure it)."""

    key: str
    kind: str
    message: str
    count: int = 0


class Describe(Message, frozen=True):
    """A service's self-description (like `yarp name list` plus port types); `interfaces` holds
    each typed rpc:i key's verbs as {doc, args, reply} (JSON schemas, `protocol.verbs`)."""

    service: str
    ports: list[PortInfo]
    pid: int = 0
    host: str = ""
    verbs: dict[str, list[str]] = {}
    interfaces: dict[str, dict[str, Any]] = {}  # rpc key -> verb -> {doc, args, reply} schemas


class ReplaceRequest(Message, frozen=True):
    """A new instance of a service, started with `--replace`, asks the live one to stop. The
    live one stops only for a process of its own host that runs `archery NAME … --replace`
    (`pid` must be alive there and its command line say so) and that read the live one's token
    from its runtime folder (`proof`, `mesh.runtime`: only the same user can)."""

    service: str
    host: str
    pid: int
    proof: Annotated[str, Meta(max_length=128)] = ""


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.__name__: cls
    for cls in (
        JointState,
        JointCommand,
        WorldState,
        WorldEvent,
        Image,
        Detection,
        Rollout,
        RpcRequest,
        RpcReply,
        Describe,
        ReplaceRequest,
    )
}
