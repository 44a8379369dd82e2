"""Stage 3: semilandmark meshes to shape models (Procrustes, sliding, PCA, fitting, quality)."""

from .build import build_shape_model
from .fit import ModelFit, assess_model_fit, fit_shape_model
from .landmark_transfer import (
    LandmarkPrediction,
    TemplateLandmarks,
    landmark_errors,
    load_template_landmarks,
    predict_landmarks,
    read_landmarks,
    write_landmarks,
)
from .model import ShapeModel, ShapeProjection
from .procrustes import ProcrustesResult, generalized_procrustes, procrustes_transform
from .quality import QualityCurve, compactness, generalization, specificity
from .sliding import SlidingResult, slide_semilandmarks
from .statismo import read_statismo, write_statismo

__all__ = [
    "LandmarkPrediction",
    "ModelFit",
    "ProcrustesResult",
    "QualityCurve",
    "ShapeModel",
    "ShapeProjection",
    "SlidingResult",
    "TemplateLandmarks",
    "assess_model_fit",
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
    "slide_semilandmarks",
    "specificity",
    "write_landmarks",
    "write_statismo",
]
