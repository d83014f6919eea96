"""Transfer: a new session (another distance, another bow) starts from a previous session's
learned model; the journal header records where it came from; bad sources are refused."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import msgspec
import numpy as np
import pytest

from archery.apps.experiment.config import ExperimentConfig, Transfer
from archery.apps.experiment.experiment import run_algorithm
from archery.protocol.errors import BadRequest
from archery.protocol.journal_records import HeaderRecord
from archery.services.learner.algorithms.base import LearnerConfigError, RestoreError
from archery.services.learner.algorithms.registry import (
    TRANSFER_ALGORITHMS,
    check_transfer,
    make_learner,
    restore_learner,
    transferred_learner,
)
from archery.services.learner.config import SessionConfig
from archery.services.learner.journal import JournalError, read_records
from archery.services.learner.session import Session
from archery.services.learner.transfer import load_source
from archery.sim.ballistic import BallisticWorld, Scenario
from tests.test_learner_service_session import FakeRig

STIFF = Scenario(bow_stiffness=420.0)  # the learner's nominal model is a 300 N/m bow
# archer-prior with its model's physical parameters held at the nominal ones: all it learns is
# the residual (c, D).
RESIDUAL_ONLY = {
    "model_distance_std": 0.0,
    "model_drag_std": 0.0,
    "model_wind_std": 0.0,
    "model_stiffness_std": 0.0,
}


def _learned(name: str, scenario: Scenario, rollouts: int = 12, seed: int = 1, **options: float):
    """A learner of `name` after `rollouts` rollouts in `scenario` (no observation noise)."""
    world = BallisticWorld(scenario)
    learner = make_learner(
        name, np.array(scenario.start), rng=np.random.default_rng(seed), **options
    )
    for _ in range(rollouts):
        theta = learner.ask()
        learner.tell(theta, world.impacts(theta.reshape(1, -1)).r[0])
    return learner


def _miss(scenario: Scenario, theta: np.ndarray) -> float:
    return float(np.linalg.norm(BallisticWorld(scenario).impacts(theta.reshape(1, -1)).r[0]))


def _fresh(**options: float):
    return make_learner(
        "archer-prior", np.array(STIFF.start), rng=np.random.default_rng(0), **options
    )


def test_prior_transfer_aims_with_the_learned_residual() -> None:
    source = _learned("archer-prior", STIFF, **RESIDUAL_ONLY)
    fresh = _fresh(**RESIDUAL_ONLY)
    seeded = transferred_learner(_fresh(**RESIDUAL_ONLY), source.state_dict())
    c, _ = source.correction()
    assert np.linalg.norm(c) > 0.02  # the stiffer bow shoots well off the nominal model
    theta_fresh, theta_seeded = fresh.ask(), seeded.ask()
    # Fresh: the model's own aim (model r = 0); seeded: the aim whose model r cancels c.
    r_model = seeded.model_jacobian(theta_seeded)[0]
    assert np.linalg.norm(r_model + c) < 0.2 * np.linalg.norm(c)
    assert np.linalg.norm(fresh.model_jacobian(theta_fresh)[0]) < 1e-3
    assert _miss(STIFF, theta_seeded) < 0.5 * _miss(STIFF, theta_fresh)


def test_prior_transfer_aims_with_the_learned_physics() -> None:
    # The stiffer bow's arrows fly higher: the fitted physics explains them (a nearer target),
    # and a session started from it aims with that world.
    source = _learned("archer-prior", STIFF)
    assert source.params is not None and not np.allclose(source.params, source.params_mean)
    seeded = transferred_learner(_fresh(), source.state_dict())
    assert np.array_equal(seeded.params_mean, source.params)
    assert _miss(STIFF, seeded.ask()) < 0.2 * _miss(STIFF, _fresh().ask())


def test_prior_transfer_is_widened_so_new_data_override_it() -> None:
    source = _learned("archer-prior", STIFF, **RESIDUAL_ONLY)
    seeded = transferred_learner(_fresh(**RESIDUAL_ONLY), source.state_dict())
    # The residual's variance where the source aimed: tight there, widened here.
    phi = np.concatenate([[1.0], source.best()[0] - source.theta0])
    assert phi @ seeded.posterior()[1] @ phi > 10 * phi @ source.posterior()[1] @ phi
    # The nominal world: one rollout there pulls the predicted residual at its θ most of the way
    # back to that world's own, 0.
    theta = seeded.ask()
    phi = np.concatenate([[1.0], theta - seeded.theta0])
    before = np.linalg.norm(phi @ seeded.posterior()[0])
    seeded.tell(theta, BallisticWorld(Scenario()).impacts(theta.reshape(1, -1)).r[0])
    assert before > 0.03
    assert np.linalg.norm(phi @ seeded.posterior()[0]) < 0.1 * before


def test_archer_transfer_starts_at_the_source_best() -> None:
    source = _learned("archer", Scenario(), rollouts=20)
    fresh = make_learner("archer", np.array(STIFF.start), rng=np.random.default_rng(0))
    seeded = transferred_learner(
        make_learner("archer", np.array(STIFF.start), rng=np.random.default_rng(0)),
        source.state_dict(),
    )
    assert np.allclose(seeded.ask(), source.best()[0])
    assert not np.allclose(fresh.ask(), source.best()[0])
    assert seeded.exploration_rollouts == 1 and fresh.exploration_rollouts == 3


@pytest.mark.parametrize("name", ["archer", "archer-prior"])
def test_transferred_state_restores_exactly(name: str) -> None:
    source = _learned(name, STIFF)
    seeded = transferred_learner(
        make_learner(name, np.array(STIFF.start), rng=np.random.default_rng(3)),
        source.state_dict(),
    )
    world = BallisticWorld(Scenario(distance=3.0))
    for _ in range(2):
        theta = seeded.ask()
        seeded.tell(theta, world.impacts(theta.reshape(1, -1)).r[0])
    copy = restore_learner(json.loads(json.dumps(seeded.state_dict())))
    for _ in range(3):
        theta = seeded.ask()
        assert np.array_equal(copy.ask(), theta)
        r = world.impacts(theta.reshape(1, -1)).r[0]
        seeded.tell(theta, r)
        copy.tell(theta, r)


@pytest.mark.parametrize(
    ("name", "source", "target"),
    [
        ("archer-prior", STIFF, STIFF),  # a learned model error carries over
        ("archer", Scenario(), STIFF),  # the nominal world's aim is a good start for the stiff bow
        ("archer", Scenario(), Scenario(distance=3.0)),
    ],
)
def test_transfer_hits_faster_on_a_mismatched_world(
    name: str, source: Scenario, target: Scenario
) -> None:
    sessions = 8
    learned = run_algorithm(ExperimentConfig((name,), sessions, 60, scenario=source), name)
    transfer = Transfer("source", {name: learned.states})
    scratch = run_algorithm(ExperimentConfig((name,), sessions, 30, scenario=target), name)
    seeded = run_algorithm(
        ExperimentConfig((name,), sessions, 30, scenario=target, transfer=transfer), name
    )
    assert np.median(seeded.rollouts_to_hit()) < np.median(scratch.rollouts_to_hit())
    assert np.median(seeded.distances[:, 0]) < np.median(scratch.distances[:, 0])


def test_unsupported_algorithms_are_refused() -> None:
    with pytest.raises(LearnerConfigError, match=r"power cannot start.*archer-prior"):
        check_transfer("power")
    assert set(TRANSFER_ALGORITHMS) >= {"archer", "archer-prior", "archer-recent"}
    assert "cma" not in TRANSFER_ALGORITHMS
    power = make_learner("power", np.array(STIFF.start), rng=np.random.default_rng(0))
    with pytest.raises(LearnerConfigError, match="cannot start from another session"):
        power.seed_from(_learned("power", STIFF, rollouts=3))
    archer = make_learner("archer", np.array(STIFF.start), rng=np.random.default_rng(0))
    with pytest.raises(RestoreError, match="'archer-prior', not 'archer'"):
        transferred_learner(archer, _learned("archer-prior", STIFF, rollouts=3).state_dict())
    with pytest.raises(RestoreError, match="seeds need N = 3"):
        transferred_learner(archer, _learned("archer", STIFF, rollouts=2).state_dict())
    used = make_learner("archer-prior", np.array(STIFF.start), rng=np.random.default_rng(0))
    used.ask()
    with pytest.raises(LearnerConfigError, match="fresh learner"):
        used.seed_from(_learned("archer-prior", STIFF, rollouts=3))


def _session(tmp_path: Path, algo: str, name: str, **kw) -> Session:
    config = SessionConfig(algorithm=algo, rollouts=6, until_hit=False, seed=2)
    session = Session.create(config, FakeRig(), tmp_path, session_id=name, **kw)
    session.run(threading.Event())
    return session


@pytest.mark.parametrize("algo", ["archer", "archer-prior"])
def test_session_from_journal_records_its_source(tmp_path: Path, algo: str) -> None:
    first = _session(tmp_path, algo, "first")
    source = load_source("first", algo, tmp_path)  # a session id under the runs directory
    assert source.session == "first" and source.journal == first.journal.path.resolve()
    second = Session.create(
        SessionConfig(algorithm=algo), FakeRig(), tmp_path, "second", source=source
    )
    header = read_records(second.journal.path)[0][0]
    assert isinstance(header, HeaderRecord)
    assert header.from_ == {"session": "first", "journal": str(source.journal), "algo": algo}
    fresh = make_learner(algo, np.array(SessionConfig().theta0), rng=np.random.default_rng(0))
    assert not np.allclose(second.learner.ask(), fresh.ask())
    # Resuming the new session restores the seeded learner.
    second.journal.close()
    resumed = Session.resume(second.journal.path, FakeRig())
    assert np.array_equal(resumed.learner.ask(), second.learner.ask())


def test_bad_source_journals_are_refused(tmp_path: Path) -> None:
    first = _session(tmp_path, "archer", "first")
    with pytest.raises(JournalError, match="ran archer, not archer-prior") as info:
        load_source(str(first.journal.path), "archer-prior")
    assert info.value.code == "bad_journal"
    with pytest.raises(JournalError, match="no such journal"):
        load_source("nosuch", "archer", tmp_path)
    with pytest.raises(BadRequest, match="power cannot start"):
        load_source(str(first.journal.path), "power")
    records = [msgspec.to_builtins(r) for r in read_records(first.journal.path)[0]]  # to edit
    old = tmp_path / "old.jsonl"
    old.write_text("".join(json.dumps(r | {"version": 0}) + "\n" for r in records[:1]))
    with pytest.raises(JournalError, match="journal version 0"):
        load_source(str(old), "archer")
    empty = tmp_path / "empty"
    Session.create(SessionConfig(), FakeRig(), tmp_path, "empty").journal.close()
    with pytest.raises(JournalError, match="no done rollout"):
        load_source(str(empty), "archer")
    stale = tmp_path / "stale.jsonl"  # no state of it restores: the header's, the checkpoints'
    records = [
        r | {"learner_state": r["learner_state"] | {"version": 9}} if "learner_state" in r else r
        for r in records
    ]
    stale.write_text("".join(json.dumps(r) + "\n" for r in records))
    with pytest.raises(JournalError, match=r"no learner state of session first restores: .*9"):
        load_source(str(stale), "archer")
