"""Applications built on the three stages: batches of registrations (settings, resume, Dask),
the model-folder pipeline, the demo, reports, pictures and the explorer page."""

from .batch import BatchResult, PatientRecord, register_batch
from .settings import RegistrationSettings

__all__ = ["BatchResult", "PatientRecord", "RegistrationSettings", "register_batch"]
