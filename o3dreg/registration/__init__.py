"""Stage 2: a template registered onto each patient (rigid start, trilinear lattices, eq. (3))."""

from typing import Any

from .._validation import moved_name
from .checkers import (
    BoundaryChecker,
    CorrespondenceChecker,
    DistanceChecker,
    NormalAngleChecker,
)
from .deformation import LatticeDeformation, PartitionedDeformation, load_deformation
from .elastic import evaluate_elastic, registration_elastic
from .landmark_start import LandmarkRegistrationResult, registration_landmarks
from .lattice import TrilinearLattice
from .losses import CauchyLoss, HuberLoss, L2Loss, RobustLoss, TukeyLoss
from .options import (
    DistanceEstimation,
    ElasticCriteria,
    ElasticLevel,
    default_levels,
    paper_levels,
)
from .result import (
    ElasticRegistrationResult,
    LevelReport,
    MapQuality,
    RegistrationVerdict,
    RigidStart,
    SurfaceDistances,
)
from .rigid import RigidRegistrationResult, registration_rigid
from .terms import Barycentre, DistanceTerm, PointToSurface
from .verdict import assess_registration, population_outliers

__all__ = [
    "Barycentre",
    "BoundaryChecker",
    "CauchyLoss",
    "CorrespondenceChecker",
    "DistanceChecker",
    "DistanceEstimation",
    "DistanceTerm",
    "ElasticCriteria",
    "ElasticLevel",
    "ElasticRegistrationResult",
    "HuberLoss",
    "L2Loss",
    "LandmarkRegistrationResult",
    "LatticeDeformation",
    "LevelReport",
    "MapQuality",
    "NormalAngleChecker",
    "PartitionedDeformation",
    "PointToSurface",
    "RegistrationVerdict",
    "RigidRegistrationResult",
    "RigidStart",
    "RobustLoss",
    "SurfaceDistances",
    "TrilinearLattice",
    "TukeyLoss",
    "assess_registration",
    "default_levels",
    "evaluate_elastic",
    "load_deformation",
    "paper_levels",
    "population_outliers",
    "registration_elastic",
    "registration_landmarks",
    "registration_rigid",
]

#: Names that moved to the applications (o3dreg.app): batches and their settings.
_MOVED = {
    "BatchResult": "o3dreg.app.batch",
    "PatientRecord": "o3dreg.app.batch",
    "register_batch": "o3dreg.app.batch",
    "RegistrationSettings": "o3dreg.app.settings",
}


def __getattr__(name: str) -> Any:
    if name in _MOVED:
        return moved_name(__name__, name, _MOVED[name])
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
