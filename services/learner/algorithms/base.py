"""The ask/tell protocol every learner follows, its errors and plain-state helpers.

A learner searches θ (m) in a `protocol.theta.ThetaBox`, by default `THETA_BOX` (the
controller's posture box)."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any, ClassVar

import msgspec
import numpy as np

from archery.protocol.text import shown
from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.protocol.vectors import finite_vector

__all__ = [
    "MAX_STD",
    "STATE_VERSION",
    "Learner",
    "LearnerConfigError",
    "LearnerError",
    "ObservationError",
    "RestoreError",
    "in_range",
    "rng_from_state",
    "rng_state",
    "scalar_return",
    "with_history",
]

STATE_VERSION = 1
_INT64_MAX = 2**63 - 1
MAX_STD = 1.0  # m: the largest exploration std or step a learner takes (θ spans ~0.1-0.3 m)
# A saved generator's state (`rng_state`): numpy's bit generators, their integers of at most
# 128 bits (PCG64's state and increment) and arrays of at most 1,024 (MT19937's 624-word key).
_BIT_GENERATORS = ("PCG64", "PCG64DXSM", "MT19937", "Philox", "SFC64")
_RNG_INT_BITS = 128
_RNG_ARRAY = 1024
_RNG_DEPTH = 3


class LearnerError(ValueError):
    """Base of every learner error."""


class LearnerConfigError(LearnerError):
    """An invalid learner option, θ box, θ0 or algorithm name."""


class ObservationError(LearnerError):
    """A reward vector given to `tell` with the wrong shape or a non-finite value, or a θ that
    is not numbers."""


class RestoreError(LearnerError):
    """A saved state that cannot be restored into this learner."""


def scalar_return(r: np.ndarray) -> float:
    """The paper's scalar return R = exp(−‖r‖) (Eq. 1) for a reward vector r in metres."""
    r = np.asarray(r, dtype=float)
    return math.exp(-math.sqrt(float(np.dot(r, r))))


def _finite_option(name: str, value: float, *, low: float, high: float = math.inf) -> float:
    """Validate a numeric option in [low, high] and return it as float."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise LearnerConfigError(f"{name} must be a finite number, got {shown(value)}")
    if not low <= value <= high:
        raise LearnerConfigError(f"{name} must be in [{low}, {high}], got {shown(value)}")
    return float(value)


def _std_option(name: str, value: float | Sequence[float], dim: int) -> np.ndarray:
    """Validate a standard deviation (m) in [0, `MAX_STD`], one for all components or one per
    component."""
    try:
        array = np.broadcast_to(np.asarray(value, dtype=float), (dim,)).copy()
    except (TypeError, ValueError) as exc:
        raise LearnerConfigError(
            f"{name} must be one number or {dim} numbers, got {shown(value)}"
        ) from exc
    if not in_range(array, 0.0, MAX_STD):
        raise LearnerConfigError(f"{name} must be finite and in [0, {MAX_STD}], got {shown(value)}")
    return array


def in_range(values: np.ndarray, low: float | np.ndarray, high: float | np.ndarray) -> bool:
    """True if every value is finite and in [low, high] (per component for arrays)."""
    return bool(np.all(np.isfinite(values)) and np.all((values >= low) & (values <= high)))


def _count_option(name: str, value: int, *, low: int) -> int:
    """Validate an integer option >= low."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise LearnerConfigError(f"{name} must be an integer >= {low}, got {shown(value)}")
    return int(value)


def _plain(value: Any) -> Any:
    """Bit-generator state → msgpack/JSON-friendly values (big ints and arrays tagged)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return {"__array__": [_plain(int(x)) for x in value.ravel()], "dtype": str(value.dtype)}
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        value = int(value)
        return value if -_INT64_MAX <= value <= _INT64_MAX else {"__int__": hex(value)}
    if isinstance(value, float | np.floating):
        return float(value)
    if isinstance(value, str):
        return value
    raise RestoreError(f"cannot store a value of type {type(value).__name__} in a learner state")


def _unplain(value: Any) -> Any:
    """Inverse of `_plain`."""
    if isinstance(value, dict):
        if "__int__" in value:
            return int(value["__int__"], 16)
        if "__array__" in value:
            return np.array([_unplain(x) for x in value["__array__"]], dtype=value["dtype"])
        return {k: _unplain(v) for k, v in value.items()}
    return value


def with_history(
    checkpoint: dict[str, Any],
    thetas: Sequence[Sequence[float]],
    rewards: Sequence[Sequence[float]],
) -> dict[str, Any]:
    """A whole state (`Learner.state_dict`) from a `checkpoint_state` and the θ (m) and r (m)
    of the rollouts it was told, in order; a whole state is returned as it is.

    Raises:
        RestoreError: the checkpoint is not a dict, or counts another number of rollouts.
    """
    if not isinstance(checkpoint, dict):
        raise RestoreError(f"a learner state must be a dict, got {type(checkpoint).__name__}")
    if "told" not in checkpoint:
        return checkpoint
    told = checkpoint["told"]
    if isinstance(told, bool) or not isinstance(told, int) or told != len(thetas):
        raise RestoreError(f"the checkpoint counts {shown(told)} rollouts told, not {len(thetas)}")
    state = {k: v for k, v in checkpoint.items() if k != "told"}
    return state | {"thetas": list(thetas), "rewards": list(rewards)}


def rng_state(rng: np.random.Generator) -> dict[str, Any]:
    """A Generator's bit_generator.state as plain values (128-bit ints become hex strings)."""
    result: dict[str, Any] = _plain(rng.bit_generator.state)
    return result


def _rng_int(value: Any) -> bool:
    """True for an int of at most `_RNG_INT_BITS` bits, plain or tagged by `_plain`."""
    if isinstance(value, dict):
        text = value.get("__int__")
        return len(value) == 1 and isinstance(text, str) and len(text) <= 3 + _RNG_INT_BITS // 4
    return (
        isinstance(value, int)
        and not isinstance(value, bool)
        and value.bit_length() <= _RNG_INT_BITS
    )


def _rng_form(value: Any, depth: int = 0) -> bool:
    """True if `value` has the form and the sizes of a saved generator's state (`rng_state`):
    nested dicts of strings, ints of at most `_RNG_INT_BITS` bits (plain or tagged) and short
    tagged arrays, checked before anything is converted."""
    if isinstance(value, bool | float | str):
        return not isinstance(value, str) or len(value) <= 64
    if isinstance(value, int):
        return _rng_int(value)
    if not isinstance(value, dict) or depth > _RNG_DEPTH:
        return False
    if "__int__" in value:
        return _rng_int(value)
    if "__array__" in value:
        items = value["__array__"]
        return (
            set(value) == {"__array__", "dtype"}
            and isinstance(items, list)
            and len(items) <= _RNG_ARRAY
            and isinstance(value["dtype"], str)
            and len(value["dtype"]) <= 16
            and all(_rng_int(x) for x in items)
        )
    return len(value) <= 8 and all(
        isinstance(k, str) and _rng_form(v, depth + 1) for k, v in value.items()
    )


def rng_from_state(state: dict[str, Any]) -> np.random.Generator:
    """A Generator that continues exactly where the one saved by `rng_state` stopped.

    Raises:
        RestoreError: not a state `rng_state` writes: another form, a bit generator numpy does
            not have, an integer or an array bigger than any of theirs (the value quoted,
            `protocol.text`).
    """
    refused = f"not a saved random generator state: {shown(state)}"
    if not _rng_form(state) or not isinstance(state, dict):
        raise RestoreError(refused)
    if state.get("bit_generator") not in _BIT_GENERATORS:
        raise RestoreError(refused)
    try:
        raw = _unplain(state)
        bit_generator = getattr(np.random, raw["bit_generator"])()
        bit_generator.state = raw
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
        raise RestoreError(refused) from exc
    return np.random.Generator(bit_generator)


class _Rows:
    """Rows of floats appended one at a time into an array that doubles when full (amortised
    O(1) per row), read as one array without rebuilding it from the rows."""

    def __init__(self, width: int) -> None:
        self._data = np.empty((16, width))
        self._n = 0

    def append(self, row: np.ndarray) -> None:
        if self._n == len(self._data):
            self._data = np.concatenate([self._data, np.empty_like(self._data)])
        self._data[self._n] = row
        self._n += 1

    def array(self) -> np.ndarray:
        """The rows so far, (n, width): a read-only view, no copy (a row never changes once
        appended)."""
        view = self._data[: self._n]
        view.flags.writeable = False
        return view


class Learner(ABC):
    """The ask/tell protocol: `ask()` proposes θ (m), `tell(θ, r)` records the reward vector r (m).

    θ is the string hand's position relative to the bow hand; r the arrow's offset from the target
    centre on the target plane (r[0] to the robot's right, r[1] up); the scalar return is
    R = exp(−‖r‖) (the paper's Eq. 1). `ask()` is idempotent until the next `tell`, and every
    proposal is finite and inside `bounds`. `state_dict()` returns the whole state as plain values
    (lists, floats, ints, strings); `load_state_dict()` puts it back, after which the learner
    proposes exactly what the saved one would have.

    Subclasses implement `_propose`, `_update`, `options`, and, if they keep more state than the
    history, `_extra_state` and `_load_extra_state`.
    """

    algorithm: ClassVar[str]
    exploration_rollouts: int = 1
    # `seed_from` can start it from another session: set for the classes that define
    # `_seed_from(source)`, which takes over what a checked source of the same class learned
    transferable: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.transferable = callable(getattr(cls, "_seed_from", None))

    def __init__(
        self, theta0: np.ndarray, *, rng: np.random.Generator, bounds: ThetaBox = THETA_BOX
    ) -> None:
        if not isinstance(rng, np.random.Generator):
            raise LearnerConfigError(
                f"rng must be a numpy.random.Generator (e.g. numpy.random.default_rng(seed)), "
                f"got {type(rng).__name__}"
            )
        if not isinstance(bounds, ThetaBox):
            raise LearnerConfigError(f"bounds must be a ThetaBox, got {type(bounds).__name__}")
        theta0 = finite_vector("theta0", theta0, LearnerConfigError)
        if not bounds.contains(theta0):
            raise LearnerConfigError(bounds.outside("theta0", theta0))
        self.theta0 = theta0.copy()
        self.bounds = bounds
        self.rng = rng
        self._thetas: list[np.ndarray] = []
        self._rewards: list[np.ndarray] = []
        self._returns: list[float] = []
        # The same history as arrays, grown in place: reading it costs no rebuild from the lists
        self._rows = _Rows(self.theta0.size + 3)  # θ (m), r (m), R per rollout
        self._pending: np.ndarray | None = None

    # -- the protocol ---------------------------------------------------------------------------

    def redraw(self, key: Sequence[int]) -> np.ndarray | None:
        """A θ (m) to run instead of one that put no arrow on the target, for a learner whose
        proposals ignore the rewards; None (the default): the session backs off towards the
        best θ instead (`abort_policy`). `key` (session seed, attempt index) makes the draw
        reproducible from the journal alone, without touching the learner's generator."""
        return None

    def ask(self) -> np.ndarray:
        """The next θ to try (m): finite and inside the bounds; the same until the next `tell`."""
        if self._pending is None:
            theta = np.asarray(self._propose(), dtype=float)
            if theta.shape != self.theta0.shape or not np.all(np.isfinite(theta)):
                # A numerical failure never reaches the robot: fall back to the best θ so far.
                theta = self.best()[0] if self._thetas else self.theta0
            self._pending = self.bounds.clip(theta)
        return self._pending.copy()

    def tell(self, theta: np.ndarray, r: np.ndarray) -> float:
        """Record that θ (m) gave the reward vector r (m); returns R = exp(−‖r‖) (Eq. 1).

        θ is the parameter actually used (it may differ from the last `ask()`): one `ask`
        proposed, one a journal or a world's checked action holds (3 finite numbers, not
        checked again here). r is measured, and checked here.

        Raises:
            ObservationError: θ or r is not numbers; r has the wrong shape or a non-finite value.
        """
        try:
            theta = np.array(theta, dtype=float)
            r = np.asarray(r, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ObservationError(
                f"θ and r must be numeric vectors (m), got {theta!r}, {r!r}"
            ) from exc
        theta.setflags(write=False)
        r = finite_vector(
            "r", r, ObservationError, size=2, unit="m, arrow − centre on the target plane"
        )
        big_return = scalar_return(r)
        self._thetas.append(theta)
        self._rewards.append(r)
        self._returns.append(big_return)
        self._rows.append(np.concatenate([theta, r, [big_return]]))
        self._pending = None
        self._update(theta, r, big_return)
        return big_return

    # -- history --------------------------------------------------------------------------------

    @property
    def n_rollouts(self) -> int:
        """Number of rollouts told so far."""
        return len(self._thetas)

    @property
    def thetas(self) -> np.ndarray:
        """(n, d) θ of every rollout told so far (m)."""
        return self._rows.array()[:, : self.theta0.size]

    @property
    def rewards(self) -> np.ndarray:
        """(n, 2) reward vectors r of every rollout (m)."""
        d = self.theta0.size
        return self._rows.array()[:, d : d + 2]

    @property
    def returns(self) -> np.ndarray:
        """(n,) scalar returns R = exp(−‖r‖)."""
        return self._rows.array()[:, -1]

    def ranked(self) -> np.ndarray:
        """Rollout indices sorted by return, best first (ties: earlier first); Eq. 4's ind(k)."""
        return np.argsort(-self.returns, kind="stable")

    def best(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(θ, r, R) of the best rollout so far.

        Raises:
            LearnerError: nothing has been told yet.
        """
        if not self._thetas:
            raise LearnerError("no rollout told yet: call tell(θ, r) before best()")
        i = int(self.ranked()[0])
        return self._thetas[i].copy(), self._rewards[i].copy(), self._returns[i]

    # -- state ----------------------------------------------------------------------------------

    @abstractmethod
    def options(self) -> dict[str, Any]:
        """The constructor options (plain values), enough to rebuild an equal fresh learner."""

    def state_dict(self) -> dict[str, Any]:
        """The whole state as plain values (JSON and msgpack friendly)."""
        return self._state() | {
            "thetas": [t.tolist() for t in self._thetas],
            "rewards": [r.tolist() for r in self._rewards],
        }

    def checkpoint_state(self) -> dict[str, Any]:
        """The state without its history, whose size does not grow with it: `told` counts the
        rollouts told, whose θ and r a journal's done records hold (`with_history` puts them
        back)."""
        return self._state() | {"told": self.n_rollouts}

    def _state(self) -> dict[str, Any]:
        return {
            "version": STATE_VERSION,
            "algorithm": self.algorithm,
            "options": self.options(),
            "theta0": self.theta0.tolist(),
            "bounds": msgspec.to_builtins(self.bounds),
            "rng": rng_state(self.rng),
            "pending": None if self._pending is None else self._pending.tolist(),
            "extra": self._extra_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Replace this learner's state by a saved one (from `state_dict`).

        Raises:
            RestoreError: the state is malformed, from another algorithm or another θ dimension.
        """
        if not isinstance(state, dict):
            raise RestoreError(f"a learner state must be a dict, got {type(state).__name__}")
        missing = {"version", "algorithm", "rng", "thetas", "rewards", "pending", "extra"} - set(
            state
        )
        if missing:
            raise RestoreError(f"learner state lacks {sorted(missing)}")
        if state["version"] != STATE_VERSION:
            raise RestoreError(
                f"learner state version {state['version']!r} is not supported; "
                f"this code reads version {STATE_VERSION}"
            )
        if state["algorithm"] != self.algorithm:
            raise RestoreError(
                f"state of algorithm {state['algorithm']!r} cannot be loaded into a "
                f"{self.algorithm!r} learner"
            )
        d = self.theta0.size
        try:
            thetas = [np.array(t, dtype=float) for t in state["thetas"]]
            rewards = [np.array(r, dtype=float) for r in state["rewards"]]
            pending = None if state["pending"] is None else np.array(state["pending"], dtype=float)
        except (TypeError, ValueError) as exc:
            raise RestoreError(f"learner state has non-numeric history: {exc}") from exc
        if len(thetas) != len(rewards) or any(t.shape != (d,) for t in thetas):
            raise RestoreError(f"learner state history must pair {d}-vectors θ with 2-vectors r")
        if any(r.shape != (2,) for r in rewards) or (pending is not None and pending.shape != (d,)):
            raise RestoreError(f"learner state history must pair {d}-vectors θ with 2-vectors r")
        if not all(in_range(v, -math.inf, math.inf) for v in (*thetas, *rewards)):
            raise RestoreError("learner state history holds a number that is not finite")
        if pending is not None and not self.bounds.contains(pending):
            raise RestoreError(f"learner state's {self.bounds.outside('pending θ', pending)}")
        self.rng = rng_from_state(state["rng"])
        self._thetas = thetas
        self._rewards = rewards
        self._returns = [scalar_return(r) for r in rewards]
        self._rows = _Rows(d + 3)
        for theta, r, big_return in zip(thetas, rewards, self._returns, strict=True):
            self._rows.append(np.concatenate([theta, r, [big_return]]))
        self._pending = pending
        self._load_extra_state(state["extra"])

    def _extra_state(self) -> dict[str, Any]:
        """Algorithm state beyond the history (plain values)."""
        return {}

    def _load_extra_state(self, extra: dict[str, Any]) -> None:  # noqa: B027 (optional hook)
        """Inverse of `_extra_state`."""

    # -- transfer -------------------------------------------------------------------------------

    def seed_from(self, source: Learner) -> None:
        """Start this fresh learner from what `source`, a session in another world (another
        distance, another bow), learned (learners that define `_seed_from`).

        Raises:
            LearnerConfigError: this learner cannot transfer, or `source` is of another algorithm
                or θ dimension, or this learner has been asked or told already.
        """
        if not self.transferable:
            raise LearnerConfigError(f"{self.algorithm} cannot start from another session")
        if type(source) is not type(self) or source.theta0.size != self.theta0.size:
            raise LearnerConfigError(
                f"a {self.algorithm} learner can start only from a {self.algorithm} session "
                f"with {self.theta0.size}-vectors θ, not from a {source.algorithm} one"
            )
        if self._thetas or self._pending is not None:
            raise LearnerConfigError("seed_from needs a fresh learner (nothing asked or told)")
        if source.n_rollouts == 0:
            raise LearnerConfigError("the source session has no rollout to learn from")
        self._seed_from(source)  # type: ignore[attr-defined]  # defined where transferable

    # -- the algorithm --------------------------------------------------------------------------

    @abstractmethod
    def _propose(self) -> np.ndarray:
        """A new θ (m); the base class clips it into the bounds."""

    @abstractmethod
    def _update(self, theta: np.ndarray, r: np.ndarray, big_return: float) -> None:
        """Learn from the rollout just appended to the history."""
