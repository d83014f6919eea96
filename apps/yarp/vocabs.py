"""The YARP vocabularies the bridge speaks (`yarp::os::Vocab32`: up to four characters packed
into an int, the first in the lowest byte), those of YARP 3.5's control board protocol among
them (`ControlBoardVocabs.h`, protocol version 1.9.0)."""

from __future__ import annotations

__all__ = [
    "AXES",
    "DONE",
    "DONES",
    "ENCODER",
    "ENCODERS",
    "FAIL",
    "GET",
    "INFO_NAME",
    "IS",
    "LIMITS",
    "MOTION_DONE_GROUP",
    "OK",
    "POSITION_DIRECT",
    "POSITION_DIRECTS",
    "POSITION_MOVE",
    "POSITION_MOVES",
    "POSITION_MOVE_GROUP",
    "PROTOCOL",
    "PROTOCOL_VERSION",
    "REF_SPEED",
    "REF_SPEEDS",
    "REF_SPEED_GROUP",
    "SET",
    "TIMESTAMP",
    "vocab",
    "vocab_text",
]


def vocab(text: str) -> int:
    """The 32-bit vocabulary of `text` (1 to 4 ASCII characters), as YARP encodes it."""
    raw = text.encode("ascii")
    if not 1 <= len(raw) <= 4:
        raise ValueError(f"a vocabulary has 1 to 4 characters, got {text!r}")
    return sum(byte << (8 * i) for i, byte in enumerate(raw))


def vocab_text(code: int) -> str:
    """The characters of a vocabulary (a received one may hold anything: not checked)."""
    raw = bytes((code >> (8 * i)) & 0xFF for i in range(4)).rstrip(b"\0")
    return raw.decode("latin-1")


GET, SET, IS = vocab("get"), vocab("set"), vocab("is")
OK, FAIL = vocab("ok"), vocab("fail")
TIMESTAMP = vocab("tsta")
PROTOCOL = vocab("prot")
PROTOCOL_VERSION = (1, 9, 0)  # what YARP 3.5's remote_controlboard expects (major, minor, tweak)
AXES = vocab("axes")
ENCODER, ENCODERS = vocab("enc"), vocab("encs")
LIMITS = vocab("llim")
POSITION_MOVE, POSITION_MOVES, POSITION_MOVE_GROUP = vocab("pos"), vocab("poss"), vocab("posg")
DONE, DONES, MOTION_DONE_GROUP = vocab("don"), vocab("dons"), vocab("dong")
REF_SPEED, REF_SPEEDS, REF_SPEED_GROUP = vocab("vel"), vocab("vels"), vocab("velg")
INFO_NAME = vocab("name")
POSITION_DIRECT, POSITION_DIRECTS = vocab("dpo"), vocab("dpos")  # streamed (command:i)
