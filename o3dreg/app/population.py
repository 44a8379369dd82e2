"""The population check of a batch: patients that stand out among the others become suspect.

A registration can be wrong and still locally tidy (no fold, small distances: a template
wrapped onto the wrong part of the anatomy). Among patients of one kind it stands out: its mean
distances or its Procrustes residual (RMS distance of its aligned semilandmarks to the
Procrustes mean) are outliers by :func:`~o3dreg.population_outliers` (a robust z-score above
3.5 and more than twice the median; five patients or more).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from ..registration.verdict import OUTLIER_Z, population_outliers, worst_status
from ..shape.procrustes import generalized_procrustes
from .batch import BatchResult

__all__ = ["check_population", "population_findings"]


def population_findings(
    names: Sequence[str], distances: Sequence[Mapping[str, float]], shapes: np.ndarray
) -> dict[str, list[str]]:
    """Per patient, the sentences of the population check (most patients get none).

    Parameters
    ----------
    names : sequence of str
        The registered patients.
    distances : sequence of mapping
        Their ``SurfaceDistances.as_dict()``, in the same order.
    shapes : (s, n, 3) ndarray
        Their semilandmark vertices, in the same order.

    Returns
    -------
    dict of str to list of str
        For each patient whose mean distance either way, or whose Procrustes residual (rigid
        generalised Procrustes), is an outlier by :func:`~o3dreg.population_outliers`.
    """
    measures: dict[str, dict[str, float]] = {
        "mean template->patient distance": {
            n: float(d.get("source_to_target_mean", np.nan)) for n, d in zip(names, distances)
        },
        "mean patient->template distance": {
            n: float(d.get("target_to_source_mean", np.nan)) for n, d in zip(names, distances)
        },
    }
    if len(names) >= 3 and shapes.ndim == 3 and shapes.shape[0] == len(names):
        residuals = generalized_procrustes(shapes).residuals
        measures["Procrustes residual"] = dict(zip(names, (float(r) for r in residuals)))
    out: dict[str, list[str]] = {}
    for what, values in measures.items():
        median = float(np.nanmedian(list(values.values())))
        for name, z in population_outliers(values).items():
            out.setdefault(name, []).append(
                f"its {what} ({values[name]:.3g}) is an outlier among the {len(values)} "
                f"registered patients (median {median:.3g}, robust z-score {z:.1f} > "
                f"{OUTLIER_Z:g}): look at this registration"
            )
    return out


def check_population(batch: BatchResult) -> BatchResult:
    """The batch with outlier patients made ``'suspect'`` (the reasons added to theirs).

    Parameters
    ----------
    batch : BatchResult
        As :func:`~o3dreg.register_batch` returns it.

    Returns
    -------
    BatchResult
        The same records, where :func:`population_findings` found something: ``verdict`` at
        least ``'suspect'`` and the sentences appended to ``warnings``. The per-patient files
        on disk keep the registration's own verdict (the check depends on the whole batch).
    """
    registered = batch.registered
    if not registered:
        return batch
    names, shapes = batch.shapes()
    findings = population_findings(names, [r.distances for r in registered], shapes)
    records = []
    for record in batch.records:
        extra = tuple(findings.get(record.name, ()))
        if extra:
            record = dataclasses.replace(
                record,
                verdict=worst_status(record.verdict, "suspect"),
                warnings=record.warnings + extra,
            )
        records.append(record)
    return dataclasses.replace(batch, records=tuple(records))
