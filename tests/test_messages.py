"""Messages: round trips, plain-msgpack readability, and rejection of every kind of bad payload."""

from __future__ import annotations

import contextlib
import math

import msgpack
import msgspec
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from archery.protocol.codec import decode, encode, from_jsonable, to_jsonable
from archery.protocol.errors import DecodeError
from archery.protocol.journal_records import AbortedRecord, DoneRecord, ProposedRecord
from archery.protocol.messages import (
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    Array,
    Describe,
    Detection,
    Image,
    JointCommand,
    JointState,
    Message,
    PortInfo,
    ReplaceRequest,
    Rollout,
    RpcReply,
    RpcRequest,
    WorldEvent,
    WorldState,
    finite_fields,
)

SAMPLES: list[Message] = [
    JointState(part="torso", names=["a", "b"], position=[0.1, -0.2], velocity=[0.0, 1.5]),
    JointCommand(part="left_arm", position=[0.3], names=["l_elbow"], sim_time=1.25),
    WorldState(qpos=Array.from_numpy(np.linspace(0, 1, 7)), phase="flying", shot=3),
    WorldEvent(kind="landed", shot=2, impact_m=[0.01, -0.02]),
    Image.from_numpy(np.arange(24, dtype=np.uint8).reshape(2, 4, 3), frame=9),
    Detection(
        frame_stamp=3.5,
        status="ok",
        target_px=[640.0, 360.0],
        arrow_px=[600, 380],
        target_confidence=0.9,
        arrow_confidence=0.8,
        r_m=[0.1, 0.05],
    ),
    Rollout(
        record=DoneRecord(
            session="s1",
            t=1.5,
            index=4,
            rollout=3,
            theta=[0.2, 0.0, 0.01],
            r_m=[0.0, 0.1],
            ret=0.9,
            distance_m=0.1,
            hit=False,
        )
    ),
    RpcRequest(verb="posture", args={"theta": [0.1, 0.2, 0.3]}),
    RpcReply(ok=False, code="unreachable", message="too far"),
    Describe(service="robot", ports=[PortInfo(key="k", kind="pub", message="JointState")]),
    ReplaceRequest(service="robot", host="lab-pc", pid=4242),
]


def test_every_message_type_has_a_sample() -> None:
    assert {type(m).__name__ for m in SAMPLES} == set(MESSAGE_TYPES)


@pytest.mark.parametrize("message", SAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip(message: Message) -> None:
    payload = encode(message)
    assert decode(payload) == message
    assert decode(payload, type(message)) == message


@pytest.mark.parametrize("message", SAMPLES, ids=lambda m: type(m).__name__)
def test_plain_msgpack_reads_every_message(message: Message) -> None:
    plain = msgpack.unpackb(encode(message), raw=False)
    assert plain["type"] == type(message).__name__
    assert plain["schema"] == SCHEMA_VERSION
    for field in message.__struct_fields__:
        assert field in plain


def test_arrays_and_images_travel_as_typed_binary() -> None:
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    plain = msgpack.unpackb(encode(WorldState(qpos=Array.from_numpy(a))), raw=False)
    assert plain["qpos"]["dtype"] == "<f4" and plain["qpos"]["shape"] == [3, 4]
    assert isinstance(plain["qpos"]["data"], bytes)
    assert np.array_equal(np.frombuffer(plain["qpos"]["data"], "<f4").reshape(3, 4), a)
    rgb = np.random.default_rng(0).integers(0, 255, (4, 5, 3), dtype=np.uint8)
    image = decode(encode(Image.from_numpy(rgb)), Image)
    assert np.array_equal(image.to_numpy(), rgb)


def test_an_lz4_image_carries_the_same_pixels_in_fewer_bytes() -> None:
    rgb = np.zeros((72, 128, 3), np.uint8)  # a rendered frame's flat colours
    rgb[20:50, 30:90] = (210, 40, 30)
    rgb[::7, ::5] = np.random.default_rng(1).integers(0, 255, (11, 26, 3), dtype=np.uint8)
    packed = Image.from_numpy(rgb, "rgb8_lz4", frame=2)
    assert len(packed.data) < rgb.nbytes / 4
    image = decode(encode(packed), Image)
    assert image.encoding == "rgb8_lz4" and np.array_equal(image.to_numpy(), rgb)
    raw = image.unpacked()
    assert raw.encoding == "rgb8" and raw.data == rgb.tobytes() and raw.frame == 2
    plain = Image.from_numpy(rgb)
    assert plain.unpacked() is plain
    with pytest.raises(ValueError, match=r"rgb8_lz4 packs HxWx3 pixels, got shape \(72, 128\)"):
        Image.from_numpy(rgb[:, :, 0], "rgb8_lz4")
    # a block that is not LZ4, or decodes to another size than width × height × 3
    for data, match in (
        (b"\xff" * 40, "rgb8_lz4 image data does not decode"),
        (
            Image.from_numpy(rgb[:36], "rgb8_lz4").data,
            "of 128x72 decodes to 13824 bytes, not 27648",
        ),
    ):
        bad = decode(encode(msgspec.structs.replace(packed, data=data)), Image)
        with pytest.raises(ValueError, match=match):
            bad.to_numpy()


def test_wrong_type_is_rejected_with_the_expected_name() -> None:
    with pytest.raises(DecodeError, match="invalid JointState"):
        decode(encode(RpcRequest(verb="x")), JointState)


def test_foreign_schema_version_is_rejected() -> None:
    plain = msgpack.unpackb(encode(SAMPLES[0]), raw=False)
    plain["schema"] = SCHEMA_VERSION + 1
    with pytest.raises(DecodeError, match="schema version 2; this node speaks version 1"):
        decode(msgpack.packb(plain))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_numbers_are_rejected(bad: float) -> None:
    plain = msgpack.unpackb(encode(SAMPLES[0]), raw=False)
    plain["position"][1] = bad
    with pytest.raises(DecodeError, match=r"position\[1\]"):
        decode(msgpack.packb(plain))
    request = {"type": "RpcRequest", "verb": "posture", "args": {"theta": [0.1, bad, 0.0]}}
    with pytest.raises(DecodeError, match="finite"):
        decode(msgpack.packb(request))
    with pytest.raises(ValueError, match="finite"):
        Array.from_numpy(np.array([0.0, bad]))
    rollout = msgpack.unpackb(encode(SAMPLES[6]), raw=False)
    rollout["record"]["r_m"][1] = bad  # a journal record inside a message checks its floats too
    with pytest.raises(DecodeError, match=r"record\.r_m\[1\]"):
        decode(msgpack.packb(rollout))


def test_a_rollout_carries_its_journal_record() -> None:
    plain = msgpack.unpackb(encode(SAMPLES[6]), raw=False)
    assert plain["record"]["record"] == "done" and "learner_state" not in plain["record"]
    for record in (
        ProposedRecord(session="s1", index=5, theta=[0.2, 0.0, 0.01]),
        AbortedRecord(
            session="s1", index=5, theta=[0.2, 0.0, 0.01], code="x", cause="y", retry_theta=[0.2]
        ),
    ):
        assert decode(encode(Rollout(record=record)), Rollout).record == record
    plain["record"]["index"] = 0  # attempts count from 1
    with pytest.raises(DecodeError, match=r"index"):
        decode(msgpack.packb(plain))


def test_inconsistent_arrays_and_images_are_rejected() -> None:
    with pytest.raises(DecodeError, match="needs 24 bytes"):
        decode(
            msgpack.packb(
                {"type": "WorldState", "qpos": {"dtype": "<f8", "shape": [3], "data": b"\0" * 10}}
            )
        )
    with pytest.raises(DecodeError, match="dtype"):
        decode(
            msgpack.packb({"type": "WorldState", "qpos": {"dtype": "O", "shape": [0], "data": b""}})
        )
    with pytest.raises(DecodeError, match="needs 36 bytes"):
        decode(
            msgpack.packb(
                {"type": "Image", "width": 3, "height": 4, "encoding": "rgb8", "data": b"\0" * 35}
            )
        )
    with pytest.raises(DecodeError, match="encoding"):
        decode(
            msgpack.packb(
                {"type": "Image", "width": 1, "height": 1, "encoding": "yuv9", "data": b"\0"}
            )
        )
    with pytest.raises(DecodeError, match="3 names, 2 positions"):
        decode(
            msgpack.packb(
                {
                    "type": "JointState",
                    "part": "torso",
                    "names": ["a", "b", "c"],
                    "position": [0.0, 0.0],
                    "velocity": [0.0, 0.0, 0.0],
                }
            )
        )


def test_oversized_payloads_are_rejected_before_parsing() -> None:
    with pytest.raises(DecodeError, match="exceeds the limit of 100 bytes"):
        decode(encode(SAMPLES[4]) + b"\0" * 100, max_bytes=100)


def test_garbage_is_not_msgpack() -> None:
    with pytest.raises(DecodeError, match="not msgpack"):
        decode(b"\xc1\xc1\xc1")
    with pytest.raises(DecodeError):
        decode(msgpack.packb({"type": "Pickle", "x": 1}))
    with pytest.raises(DecodeError):
        decode(msgpack.packb([1, 2, 3]))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=512))
def test_decoder_fuzz_raw_bytes(payload: bytes) -> None:
    with contextlib.suppress(DecodeError):
        decode(payload)


json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=8)
    | st.binary(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=12,
)


@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from(sorted(MESSAGE_TYPES)),
    st.dictionaries(
        st.sampled_from(
            [
                "part",
                "names",
                "position",
                "velocity",
                "qpos",
                "kind",
                "width",
                "height",
                "encoding",
                "data",
                "verb",
                "args",
                "ok",
                "schema",
                "seq",
                "stamp",
                "theta",
                "status",
                "record",
                "frame_stamp",
                "ports",
                "service",
            ]
        ),
        json_values,
        max_size=8,
    ),
)
def test_decoder_fuzz_structured(type_name: str, fields: dict) -> None:
    """Structured but wrong payloads: only DecodeError ever escapes, never another exception."""
    try:
        message = decode(msgpack.packb({"type": type_name, **fields}, use_bin_type=True))
    except DecodeError:
        return
    assert isinstance(message, MESSAGE_TYPES[type_name])


def test_json_forms_for_the_cli() -> None:
    command = from_jsonable({"part": "torso", "position": [0.1, 0.2, 0.3]}, JointCommand)
    assert command.position == [0.1, 0.2, 0.3]
    with pytest.raises(DecodeError, match="invalid JointCommand"):
        from_jsonable({"part": "torso", "position": "high"}, JointCommand)
    with pytest.raises(DecodeError, match="must be a JSON object"):
        from_jsonable([1, 2], JointCommand)
    shown = to_jsonable(SAMPLES[2])
    assert shown["type"] == "WorldState" and len(shown["qpos"]) == 7
    assert to_jsonable(SAMPLES[4])["data"] == "<24 bytes>"


def test_messages_are_frozen() -> None:
    with pytest.raises(AttributeError):
        SAMPLES[0].part = "other"  # type: ignore[attr-defined]  # a Message list; the write fails on purpose
    assert msgspec.structs.replace(SAMPLES[0], seq=5).seq == 5


def test_an_image_view_holds_the_payload_not_a_copy() -> None:
    image = Image.from_numpy(np.arange(48 * 64 * 3, dtype=np.uint8).reshape(48, 64, 3), seq=3)
    payload = encode(image)
    view = decode(payload, Image, view=True)
    assert isinstance(view, Image) and isinstance(view.data, memoryview)
    assert view.data.obj is payload and view.data.readonly
    assert encode(view) == payload and view.to_numpy().tobytes() == image.data
    short = encode(Image(width=2, height=2, encoding="rgb8", data=bytes(12)))
    with pytest.raises(DecodeError, match="needs 12 bytes, got 11"):
        decode(short.replace(b"\xc4\x0c" + bytes(12), b"\xc4\x0b" + bytes(11)), Image, view=True)
    assert to_jsonable(view)["data"] == f"<{len(image.data)} bytes>"


def test_only_fields_that_may_hold_a_float_are_checked_for_finiteness() -> None:
    assert finite_fields(JointState) == ("position", "velocity", "stamp", "sim_time")
    assert finite_fields(Image) == ("stamp", "sim_time")
    with pytest.raises(ValueError, match="velocity"):
        JointState(part="torso", names=["a"], position=[0.0], velocity=[math.nan])


def test_a_non_finite_number_in_a_list_is_named_by_its_index() -> None:
    with pytest.raises(ValueError, match=r"position\[2\] is inf"):
        JointCommand(part="torso", position=[0.1, 0.2, math.inf])
    with pytest.raises(ValueError, match=r"args.x\[1\] is nan"):
        RpcRequest(verb="v", args={"x": ["a", math.nan]})
    assert RpcRequest(verb="v", args={"x": [10**400, "a", [1.5]]}).args["x"][0] == 10**400


@pytest.mark.parametrize("batch", [0, -1, 17])
def test_a_joint_command_batch_outside_1_to_16_is_refused(batch: int) -> None:
    with pytest.raises(ValueError, match=r"batch must be in 1\.\.16, got"):
        JointCommand(part="torso", position=[0.0, 0.0, 0.0], batch=batch)
