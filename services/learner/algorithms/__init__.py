"""The learning algorithms: PoWER, ARCHER and baselines behind one ask/tell protocol."""

from archery.services.learner.algorithms.archer import Archer
from archery.services.learner.algorithms.base import (
    Learner,
    LearnerConfigError,
    LearnerError,
    ObservationError,
    RestoreError,
    scalar_return,
)
from archery.services.learner.algorithms.baselines import CmaEs, HillClimber, RandomSearch
from archery.services.learner.algorithms.impact_model import (
    BallisticModel,
    ImpactModel,
    PhysicalModel,
)
from archery.services.learner.algorithms.power import Power
from archery.services.learner.algorithms.prior import ArcherPrior
from archery.services.learner.algorithms.registry import ALGORITHMS, make_learner, restore_learner

__all__ = [
    "ALGORITHMS",
    "Archer",
    "ArcherPrior",
    "BallisticModel",
    "CmaEs",
    "HillClimber",
    "ImpactModel",
    "Learner",
    "LearnerConfigError",
    "LearnerError",
    "ObservationError",
    "PhysicalModel",
    "Power",
    "RandomSearch",
    "RestoreError",
    "make_learner",
    "restore_learner",
    "scalar_return",
]
