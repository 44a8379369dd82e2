"""o3dreg: elastic registration of 3D surface meshes and statistical shape models of anatomy.

A plugin for the Open3D / libigl ecosystem implementing the multi-resolution trilinear
("octree-spline") registration with a symmetric distance of Berar et al. (2005).
"""

from __future__ import annotations

import logging

__version__ = "0.1.0"

logging.getLogger("o3dreg").addHandler(logging.NullHandler())

from .io.mesh import read_triangle_mesh, write_triangle_mesh  # noqa: E402

__all__ = ["__version__", "read_triangle_mesh", "write_triangle_mesh"]

# --- elastic registration -----------------------------------------------------------------------
from .registration.deformation import (  # noqa: E402
    LatticeDeformation,
    PartitionedDeformation,
    load_deformation,
)
from .registration.elastic import evaluate_elastic, registration_elastic  # noqa: E402
from .registration.landmarks import LandmarkRegistrationResult, registration_landmarks  # noqa: E402
from .registration.lattice import TrilinearLattice  # noqa: E402
from .registration.options import (  # noqa: E402
    DistanceEstimation,
    ElasticCriteria,
    ElasticLevel,
    default_levels,
)
from .registration.result import (  # noqa: E402
    ElasticRegistrationResult,
    LevelReport,
    RigidStart,
    SurfaceDistances,
)
from .registration.rigid import RigidRegistrationResult, registration_rigid  # noqa: E402
from .registration.settings import RegistrationSettings  # noqa: E402
from .registration.verdict import assess_registration, population_outliers  # noqa: E402

__all__ += [
    "DistanceEstimation",
    "ElasticCriteria",
    "ElasticLevel",
    "ElasticRegistrationResult",
    "LandmarkRegistrationResult",
    "LatticeDeformation",
    "LevelReport",
    "PartitionedDeformation",
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
    "registration_elastic",
    "registration_landmarks",
    "registration_rigid",
]

# --- CT reconstruction (volume, isosurface, cleaning) ---
from .volume.cleaning import (  # noqa: E402
    Components,
    connected_components,
    crop_mesh,
    decimate,
    keep_largest_components,
    remove_small_components,
    smooth_taubin,
)
from .volume.isosurface import isosurface  # noqa: E402
from .volume.readers import read_raw_slices, read_volume  # noqa: E402
from .volume.volume import Volume  # noqa: E402

__all__ += [
    "Components",
    "Volume",
    "connected_components",
    "crop_mesh",
    "decimate",
    "isosurface",
    "keep_largest_components",
    "read_raw_slices",
    "read_volume",
    "remove_small_components",
    "smooth_taubin",
]

# --- shape models ---
from .registration.batch import BatchResult, PatientRecord, register_batch  # noqa: E402
from .shape.build import build_shape_model  # noqa: E402
from .shape.fit import ModelFit, fit_shape_model  # noqa: E402
from .shape.landmarks import (  # noqa: E402
    LandmarkPrediction,
    TemplateLandmarks,
    landmark_errors,
    load_template_landmarks,
    predict_landmarks,
    read_landmarks,
    write_landmarks,
)
from .shape.model import ShapeModel, ShapeProjection  # noqa: E402
from .shape.procrustes import ProcrustesResult, generalized_procrustes, procrustes_transform  # noqa: E402
from .shape.quality import QualityCurve, compactness, generalization, specificity  # noqa: E402
from .shape.sliding import SlidingResult, slide_semilandmarks  # noqa: E402
from .shape.statismo import read_statismo, write_statismo  # noqa: E402

__all__ += [
    "BatchResult",
    "LandmarkPrediction",
    "ModelFit",
    "PatientRecord",
    "ProcrustesResult",
    "QualityCurve",
    "ShapeModel",
    "ShapeProjection",
    "SlidingResult",
    "TemplateLandmarks",
    "build_shape_model",
    "compactness",
    "fit_shape_model",
    "generalization",
    "generalized_procrustes",
    "landmark_errors",
    "load_template_landmarks",
    "predict_landmarks",
    "procrustes_transform",
    "read_landmarks",
    "read_statismo",
    "register_batch",
    "slide_semilandmarks",
    "specificity",
    "write_landmarks",
    "write_statismo",
]
