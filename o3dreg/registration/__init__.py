"""Stage 2: a template registered onto each patient (rigid start, trilinear lattices, eq. (3))."""

from .batch import BatchResult, PatientRecord, register_batch
from .deformation import LatticeDeformation, PartitionedDeformation, load_deformation
from .elastic import evaluate_elastic, registration_elastic
from .landmarks import LandmarkRegistrationResult, registration_landmarks
from .lattice import TrilinearLattice
from .options import DistanceEstimation, ElasticCriteria, ElasticLevel, default_levels
from .result import ElasticRegistrationResult, LevelReport, RigidStart, SurfaceDistances
from .rigid import RigidRegistrationResult, registration_rigid
from .settings import RegistrationSettings
from .verdict import assess_registration, population_outliers

__all__ = [
    "BatchResult",
    "DistanceEstimation",
    "ElasticCriteria",
    "ElasticLevel",
    "ElasticRegistrationResult",
    "LandmarkRegistrationResult",
    "LatticeDeformation",
    "LevelReport",
    "PartitionedDeformation",
    "PatientRecord",
    "RegistrationSettings",
    "RigidRegistrationResult",
    "RigidStart",
    "SurfaceDistances",
    "TrilinearLattice",
    "assess_registration",
    "default_levels",
    "evaluate_elastic",
    "load_deformation",
    "population_outliers",
    "register_batch",
    "registration_elastic",
    "registration_landmarks",
    "registration_rigid",
]
