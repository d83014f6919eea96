"""The hand postures of a YARP robot's shot (`--hand-postures FILE`): JSON {verb: {axis:
degrees}} for grasp, nock and reset, and "operator": the verbs whose posture waits for the
operator's hand first; read and checked before any work (`yarp_shot` moves them)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from archery.protocol.text import shown
from archery.services.robot.yarp_parts import BodyError

__all__ = ["HAND_VERBS", "read_postures"]

HAND_VERBS = ("grasp", "nock", "reset")


def read_postures(path: str) -> tuple[dict[str, dict[str, float]], tuple[str, ...]]:
    """The hand postures of `path` (JSON {verb: {axis: degrees}}, verb among `HAND_VERBS`;
    "operator": [verb, …], the verbs whose posture waits for the operator's hand first, e.g.
    an arrow put on the string before the fingers close on it) and those verbs.

    Raises:
        BodyError: the file does not read, is not that shape, or names another verb.
    """
    where = f"--hand-postures {shown(path)}"
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise BodyError(f"{where}: {exc}") from None
    if not isinstance(raw, dict):
        raise BodyError(f"{where}: not a JSON object {{verb: {{axis: deg}}}}")
    first = raw.pop("operator", [])
    if not isinstance(first, list) or not all(verb in HAND_VERBS for verb in first):
        raise BodyError(f'{where}: "operator" lists verbs among {", ".join(HAND_VERBS)}')
    out: dict[str, dict[str, float]] = {}
    for verb, angles in raw.items():
        if verb not in HAND_VERBS:
            raise BodyError(f"{where}: {shown(verb)} is not one of {', '.join(HAND_VERBS)}")
        if (
            not isinstance(angles, dict)
            or not angles
            or not all(
                isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                for v in angles.values()
            )
        ):
            raise BodyError(f"{where}: {verb} must map axis names to degrees")
        out[verb] = {str(k): float(v) for k, v in angles.items()}
    return out, tuple(first)
