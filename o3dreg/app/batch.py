"""Registration of one template onto many patients: parallel, resumable, failure-tolerant.

Each finished patient is written to the output folder as soon as it completes (atomic writes):

* ``NAME.ply``: the semilandmark mesh (template triangles on the registered vertices);
* ``NAME.npz``: the elastic deformation (read it with :func:`~o3dreg.load_deformation`);
* ``NAME.json``: the record (status, distances both ways, convergence, time, rigid
  transformation), written last, so its presence with ``"status": "registered"`` marks the
  patient as done.

Interrupting a batch (Ctrl-C) loses only the patients in progress; running it again skips the
finished ones (unless ``force``). A finished patient is recognised by its record's resume key, a
hash of the template, the patient's content, the initial transformation and the registration
options (:func:`resume_key`): when any of them changed since, the patient is registered again
(with a log line). A record whose name is not its file's stem is ignored, so a record never
makes the batch read a file outside its folder. A patient that fails to load or to register is recorded with
its error (``"status": "failed"``) and the batch goes on; a rerun retries it.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import functools
import hashlib
import json
import logging
import os
import re
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._validation import as_mesh_arrays, as_transformation, check_bool, check_referenced
from ..io import json_text
from ..io.mesh import atomic_write_text, read_triangle_mesh, write_triangle_mesh
from ..registration.options import DistanceEstimation, ElasticCriteria, default_levels
from ..registration.verdict import STATUSES
from .progress import Progress
from .settings import RegistrationSettings, resolve_settings

__all__ = ["BatchResult", "PatientRecord", "register_batch", "resume_key"]

logger = logging.getLogger("o3dreg")

_STATUS = ("registered", "failed")


@dataclass(frozen=True)
class PatientRecord:
    """What happened to one patient of a batch.

    Attributes
    ----------
    name : str
    status : {'registered', 'failed'}
    success : bool
        Registration converged at every level (``False`` for a usable but unconverged result
        and for failures).
    message : str
        The registration message, or the error for a failure.
    seconds : float
        Wall time of the registration.
    distances : dict of str to float
        ``SurfaceDistances.as_dict()`` (empty for a failure).
    min_jacobian_determinant : float
    transformation : tuple of 16 float
        The rigid pre-alignment, row-major (empty for a failure).
    source : str
        The target file, or ``"<array>"``. ``NAME.json`` stores it relative to its own folder
        (read back as a path that works from any working folder).
    verdict : {'ok', 'suspect', 'failed', 'unknown'}
        The registration's verdict (:func:`~o3dreg.assess_registration`), made worse by a
        population check (:func:`o3dreg.app.population.check_population`) where one was run;
        ``'failed'`` for an error, ``'unknown'`` for a record written before verdicts existed
        (registered again on the next run).
    warnings : tuple of str
        The reasons behind ``verdict``, one plain sentence each.
    rigid_start : dict or None
        How the rigid start was chosen (``RigidStart.as_dict()``: the winner's and runner-up's
        scores, candidates, ICP figures, ambiguity warnings), or with a given ``init`` the
        search that checked the registration against it (``ElasticRegistrationResult``'s
        ``rigid_start``); ``None`` for a failure, or where no search ran.
    skipped : bool
        ``True`` when the record was read back from an earlier run.
    """

    name: str
    status: str
    success: bool
    message: str
    seconds: float = 0.0
    distances: dict[str, float] = field(default_factory=dict)
    min_jacobian_determinant: float = float("nan")
    transformation: tuple[float, ...] = ()
    source: str = ""
    verdict: str = "unknown"
    warnings: tuple[str, ...] = ()
    rigid_start: dict[str, Any] | None = None
    skipped: bool = False

    def __repr__(self) -> str:
        d = self.distances
        extra = (
            f", source->target mean={d['source_to_target_mean']:.4g}"
            f", target->source mean={d['target_to_source_mean']:.4g}"
            if d
            else ""
        )
        return (
            f"PatientRecord({self.name!r}, {self.status}, verdict={self.verdict}, "
            f"success={self.success}{extra}, "
            f"seconds={self.seconds:.2f})"
        )

    def as_dict(self) -> dict[str, Any]:
        out = dict(self.__dict__)
        out["transformation"] = list(self.transformation)
        out["warnings"] = list(self.warnings)
        out.pop("skipped")
        return out


@dataclass(frozen=True, eq=False)
class BatchResult:
    """The outcome of :func:`register_batch`.

    Attributes
    ----------
    records : tuple of PatientRecord
        In the order of the targets.
    output_dir : str
    faces : (m, 3) ndarray
        The template triangles (shared by every semilandmark mesh).
    """

    records: tuple[PatientRecord, ...]
    output_dir: str
    faces: np.ndarray = field(repr=False)

    def __repr__(self) -> str:
        ok = sum(r.status == "registered" for r in self.records)
        return (
            f"BatchResult({len(self.records)} patients: {ok} registered, "
            f"{len(self.records) - ok} failed, output_dir={self.output_dir!r})"
        )

    @property
    def registered(self) -> tuple[PatientRecord, ...]:
        return tuple(r for r in self.records if r.status == "registered")

    @property
    def failed(self) -> tuple[PatientRecord, ...]:
        return tuple(r for r in self.records if r.status == "failed")

    @property
    def accepted(self) -> tuple[PatientRecord, ...]:
        """Registered patients whose verdict is ``'ok'``: what a model is built from."""
        return tuple(r for r in self.registered if r.verdict == "ok")

    @property
    def flagged(self) -> tuple[PatientRecord, ...]:
        """Registered patients whose verdict is not ``'ok'`` (left out of a model by default)."""
        return tuple(r for r in self.registered if r.verdict != "ok")

    def mesh_path(self, name: str) -> str:
        return os.path.join(self.output_dir, f"{_checked_name(name)}.ply")

    def deformation_path(self, name: str) -> str:
        return os.path.join(self.output_dir, f"{_checked_name(name)}.npz")

    def shapes(self, *, accepted_only: bool = False) -> tuple[tuple[str, ...], np.ndarray]:
        """Names and semilandmark vertices ``(s, n, 3)`` of the registered patients (only those
        whose verdict is ``'ok'`` with ``accepted_only``)."""
        chosen = self.accepted if accepted_only else self.registered
        names = tuple(r.name for r in chosen)
        shapes = [np.asarray(read_triangle_mesh(self.mesh_path(n)).vertices) for n in names]
        return names, (np.stack(shapes) if shapes else np.zeros((0, 0, 3)))

    def table(self, unit: str = "mm") -> str:
        """Summary: verdict, distances both ways (mean / max), whether every level met its
        stopping criteria, and time per patient; the reasons under each flagged patient."""
        head = (
            f"{'patient':<24}{'verdict':<9}{'s->t mean':>10}{'s->t max':>10}"
            f"{'t->s mean':>10}{'t->s max':>10}{'criteria met':>13}{'seconds':>9}"
        )
        lines = [f"distances in {unit}", head]
        for r in self.records:
            d = r.distances
            if d:
                nums = "".join(
                    f"{d[k]:>10.3g}"
                    for k in (
                        "source_to_target_mean",
                        "source_to_target_max",
                        "target_to_source_mean",
                        "target_to_source_max",
                    )
                )
            else:
                nums = f"{'-':>10}" * 4
            met = ("yes" if r.success else "no") if r.status == "registered" else "-"
            lines.append(f"{r.name[:23]:<24}{r.verdict:<9}{nums}{met:>13}{r.seconds:>9.1f}")
            if r.status == "failed":
                lines.append(f"{'':<24}error: {r.message}")
            else:
                lines += [f"{'':<24}- {w}" for w in r.warnings]
        return "\n".join(lines)

    def as_dicts(self) -> list[dict[str, Any]]:
        return [r.as_dict() for r in self.records]


#: Names a patient cannot have: the batch's own files in its folder (compared ignoring case, as
#: some file systems do).
RESERVED_NAMES = ("summary",)


def _safe_name(name: str) -> str:
    cleaned = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")
    return cleaned or "patient"


def _checked_name(name: str) -> str:
    """``name`` when it is a plain file stem (no folder, no ``..``); ``ValueError`` otherwise."""
    if not isinstance(name, str) or name != _safe_name(name):
        raise ValueError(f"patient name {name!r} is not a plain file name")
    return name


def _canonical(value: Any) -> Any:
    """A JSON-able form of registration options that changes whenever a value does."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            "type": type(value).__name__,
            **{
                f.name: _canonical(getattr(value, f.name))
                for f in dataclasses.fields(value)
                if not (f.metadata.get("keyed_when_set") and getattr(value, f.name) == f.default)
            },
        }
    if isinstance(value, np.ndarray):
        return {"array": _digest(value)}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, (float, np.floating)):
        return repr(float(value))  # exact
    return repr(value)


def _digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _file_digest(path: str) -> str:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError:
        # Not readable here (e.g. only the Dask workers see it): the path stands for the file.
        return f"path:{os.path.abspath(path)}"
    return h.hexdigest()


def _options_key(settings: RegistrationSettings) -> dict[str, Any]:
    """The settings with the defaults of :func:`registration_elastic` filled in, canonical."""
    filled = {k: v for k, v in settings.elastic_options().items() if v is not None}
    filled["start"] = settings.start
    filled.setdefault("levels", default_levels())
    filled.setdefault("estimation_method", DistanceEstimation())
    filled.setdefault("criteria", ElasticCriteria())
    filled.setdefault("padding", 0.1)
    return _canonical(filled)


def _key(template_digest: str, target: Any, init: Any, options_key: Any) -> str:
    target_digest = _file_digest(target) if isinstance(target, str) else _digest(*target)
    payload = {
        "template": template_digest,
        "target": target_digest,
        "init": None if init is None else _digest(np.asarray(init, dtype=np.float64)),
        "options": options_key,
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def resume_key(
    template: Any,
    target: Any,
    *,
    init: Any = None,
    settings: RegistrationSettings | None = None,
    **options: Any,
) -> str:
    """The key :func:`register_batch` stores with a finished registration.

    A hash of the template's vertices and triangles, the target (a file's bytes, or a mesh's
    arrays), ``init`` and the registration settings (``settings``, or its fields as keywords)
    with their defaults filled in: a finished patient whose key differs from the current one is
    registered again. Pass it to
    :func:`save_registered` for a registration made outside a batch.
    """
    tv, tf = as_mesh_arrays(template, "template")
    if isinstance(target, (str, os.PathLike)):
        target = os.fspath(target)
    else:
        target = as_mesh_arrays(target, "target", drop_degenerate=True)
    if init is not None:
        init = as_transformation(init, "init", similarity=True)
    return _key(_digest(tv, tf), target, init, _options_key(resolve_settings(settings, options)))


def _default_name(target: Any, index: int) -> str:
    if isinstance(target, (str, os.PathLike)):
        base = os.path.basename(os.fspath(target))
        for suffix in (".nii.gz",):
            if base.lower().endswith(suffix):
                return base[: -len(suffix)]
        return os.path.splitext(base)[0]
    return f"patient{index:03d}"


def _default_names(targets: Sequence[Any]) -> list[str]:
    """A distinct name per target: the file stem; where stems repeat, the fewest folders in
    front that tell those files apart (``a/bone.ply``, ``b/bone.ply`` -> ``a_bone``,
    ``b_bone``), else a number (``bone_1``, ``bone_2``). Names are made of ASCII letters,
    digits, ``.``, ``_`` and ``-``."""
    names = [_safe_name(_default_name(t, i)) for i, t in enumerate(targets)]
    groups: dict[str, list[int]] = {}
    for i, name in enumerate(names):
        groups.setdefault(name.lower(), []).append(i)  # one file where case is ignored
    for members in groups.values():
        if len(members) == 1:
            continue
        renamed = [f"{names[i]}_{k}" for k, i in enumerate(members, start=1)]
        if all(isinstance(targets[i], (str, os.PathLike)) for i in members):
            parts = [os.path.abspath(os.fspath(targets[i])).split(os.sep)[:-1] for i in members]
            for depth in range(1, min(len(p) for p in parts) + 1):
                candidate = [
                    _safe_name("_".join([*p[-depth:], names[i]])) for p, i in zip(parts, members)
                ]
                if len({c.lower() for c in candidate}) == len(candidate):
                    renamed = candidate
                    break
        for i, new in zip(members, renamed):
            names[i] = new
    # A folder-made name may still meet another file's stem (a/p.ply and a_p.ply), and the
    # batch's own summary.json takes one name: number what would collide.
    seen = {n.lower() for n in RESERVED_NAMES}
    for i, name in enumerate(names):
        unique, k = name, 1
        while unique.lower() in seen:
            k += 1
            unique = f"{name}_{k}"
        names[i] = unique
        seen.add(unique.lower())
    return names


def _register_one(
    template: tuple[np.ndarray, np.ndarray],
    target: Any,
    init: Any,
    settings: RegistrationSettings,
    name: str = "target",
) -> tuple[Any, float]:
    """Worker: load (when a path; errors name it ``name``) and register; returns (result,
    seconds). Runs anywhere."""
    start = time.perf_counter()
    if isinstance(target, (str, os.PathLike)):
        target = read_triangle_mesh(target, name=name)
    result = settings.register(template, target, init=init)
    return result, time.perf_counter() - start


def _read_record(path: str, name: str, key: str) -> PatientRecord | None:
    """The finished record of patient ``name`` at ``path``, or None (missing, stale, foreign)."""
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
        stored_key = data.pop("resume_key", None)
        if isinstance(data.get("source"), str):
            data["source"] = resolve_record_source(data["source"], os.path.dirname(path))
        data["transformation"] = tuple(data.get("transformation", ()))
        data["warnings"] = tuple(data.get("warnings", ()))
        # A measure that could not be taken is written as null (JSON has no NaN).
        for field in ("seconds", "min_jacobian_determinant"):
            if field in data and data[field] is None:
                data[field] = float("nan")
        if isinstance(data.get("distances"), dict):
            data["distances"] = {
                k: float("nan") if v is None else v for k, v in data["distances"].items()
            }
        record = PatientRecord(**data, skipped=True)
    except FileNotFoundError:
        return None
    except (OSError, ValueError, TypeError, AttributeError) as exc:
        logger.warning("batch: %s: unreadable record %s (%s); registering again", name, path, exc)
        return None
    if record.name != name:
        logger.warning(
            "batch: %s: record %s names %r; ignored, registering again", name, path, record.name
        )
        return None
    if record.status == "registered" and stored_key != key:
        logger.warning(
            "batch: %s: the template, the patient or the options changed since it was "
            "registered; registering again",
            name,
        )
        return None
    return record


def _write_json(path: str, data: Any) -> None:
    folder = os.path.dirname(os.path.abspath(path))

    def relative(item: Any) -> Any:
        if isinstance(item, dict) and isinstance(item.get("source"), str):
            return {**item, "source": stored_source(item["source"], folder)}
        return item

    data = [relative(d) for d in data] if isinstance(data, list) else relative(data)
    atomic_write_text(path, json_text.dumps(data, indent=2) + "\n", overwrite=True)


def stored_source(source: str, folder: str) -> str:
    """``source`` as a record in ``folder`` stores it: relative to ``folder`` (the records stay
    valid when the command that reads them runs elsewhere, or when the model folder moves with
    its patients). ``"<array>"`` (a mesh given in memory) is kept."""
    if not source or source.startswith("<"):
        return source
    try:
        return os.path.relpath(os.path.abspath(source), os.path.abspath(folder))
    except ValueError:  # another drive (Windows): no relative path
        return os.path.abspath(source)


def resolve_record_source(source: str, folder: str) -> str:
    """The path of a record's ``source`` (see :func:`stored_source`): relative to ``folder``
    (the record's folder); a record written with a path relative to where its command ran is
    found there when it is not found beside ``folder``."""
    if not source or source.startswith("<") or os.path.isabs(source):
        return source
    beside = os.path.normpath(os.path.join(folder, source))
    return beside if os.path.exists(beside) or not os.path.exists(source) else source


def save_registered(
    output_dir: str | os.PathLike[str],
    name: str,
    result: Any,
    seconds: float,
    source: str = "",
    *,
    key: str = "",
) -> PatientRecord:
    """Write one registered patient as :func:`register_batch` does (mesh, deformation, then the
    record), so that a batch run on ``output_dir`` skips it: a registration already made
    elsewhere (e.g. a comparison) is not made twice. ``key`` is its :func:`resume_key`; a
    record without the batch's key is registered again."""
    output_dir = os.fspath(output_dir)
    name = _safe_name(name)
    write_triangle_mesh(
        os.path.join(output_dir, f"{name}.ply"), result.semilandmark_mesh(), overwrite=True
    )
    result.deformation.save(os.path.join(output_dir, f"{name}.npz"), overwrite=True)
    record = PatientRecord(
        name=name,
        status="registered",
        success=bool(result.success),
        message=str(result.message),
        seconds=float(seconds),
        distances=result.distances.as_dict(),
        min_jacobian_determinant=float(result.min_jacobian_determinant),
        transformation=tuple(float(v) for v in np.asarray(result.transformation).ravel()),
        source=source,
        verdict=str(result.status),
        warnings=tuple(result.warnings),
        rigid_start=None if result.rigid_start is None else result.rigid_start.as_dict(),
    )
    logger.info(
        "batch: %s registered in %.1f s (mean distances %.3g / %.3g)",
        name,
        seconds,
        record.distances["source_to_target_mean"],
        record.distances["target_to_source_mean"],
    )
    _write_json(os.path.join(output_dir, f"{name}.json"), {**record.as_dict(), "resume_key": key})
    return record


def register_batch(
    template: Any,
    targets: Sequence[Any],
    output_dir: str | os.PathLike[str],
    *,
    names: Sequence[str] | None = None,
    executor: cf.Executor | None = None,
    force: bool = False,
    progress: bool = False,
    callback: Callable[[PatientRecord], Any] | None = None,
    settings: RegistrationSettings | None = None,
    target_name: str = "target",
    **options: Any,
) -> BatchResult:
    """Register ``template`` elastically onto every target; save each patient as it finishes.

    Parameters
    ----------
    template : open3d.geometry.TriangleMesh or (vertices, faces)
        The template (source). Not modified.
    targets : sequence of path or mesh
        Patient surfaces: mesh files (read by the worker, so a file that fails to load is a
        failed patient, not a failed batch) or meshes / ``(vertices, faces)`` pairs.
    output_dir : str or path-like
        Created if missing. Holds ``NAME.ply``, ``NAME.npz``, ``NAME.json`` per patient and
        ``summary.json``.
    names : sequence of str, optional
        Patient names (file stems), distinct ignoring case, not ``summary``. Default: the
        target file stems, or ``patient000``, ...; where stems repeat ignoring case
        (``case01/bone.ply``, ``case02/bone.ply``), the fewest folders that tell the files apart
        lead (``case01_bone``, ``case02_bone``), else a number; a name that would still meet
        another, or the batch's ``summary``, gets a number (``summary_2``).
    executor : concurrent.futures.Executor, optional
        Runs the registrations, e.g. ``ProcessPoolExecutor(2)`` or a Dask client's
        ``client.get_executor()``. Workers receive arrays and paths and return the result; all
        files are written by this process, so workers need not share its disk (but file targets
        must be readable by the workers). Default: one after the other in this process.
    force : bool, optional
        Register again patients already finished in ``output_dir``. Default ``False``.
    progress : bool, optional
        Report progress on stderr: a tqdm bar (patients done, current patient, elapsed and
        remaining time) on a terminal or in a notebook, elsewhere (a log, a CI job) a line per
        finished patient. Default ``False``.
    callback : callable, optional
        Called with each :class:`PatientRecord` as it is saved (also for skipped ones).
    settings : RegistrationSettings, optional
        How each patient is registered (the same settings ``o3dreg register`` and
        ``o3dreg build-model`` take). Default ``RegistrationSettings()``.
    target_name : str, optional
        What the failure of a target file that cannot be read calls it (its record's message
        and log line), e.g. the command-line argument that gave the files. Default
        ``"target"``.
    **options
        ``init``: one ``(4, 4)`` transformation for every target, or one per target, shape
        ``(len(targets), 4, 4)`` (e.g. from landmarks, see
        :meth:`RegistrationSettings.landmark_start`); it replaces the settings' ``start``.
        Instead of ``settings``, its fields may be given as keywords (``levels``,
        ``estimation_method``, ``criteria``, ``padding``, ``parts``, ``start``).

    Returns
    -------
    BatchResult
        Every record carries its registration's ``verdict`` and ``warnings``
        (:func:`o3dreg.app.population.check_population` adds the comparison with the other
        patients, as ``build_model_folder`` does). Failures are records with ``status='failed'`` and the error
        message; nothing is raised for a failing patient. ``KeyboardInterrupt`` cancels pending work and propagates, after
        which every finished patient is on disk.
    """
    tv, tf = as_mesh_arrays(template, "template")
    check_referenced(tv, tf, "template")
    if isinstance(targets, (str, os.PathLike)) or not isinstance(targets, Sequence):
        raise TypeError(
            f"`targets` must be a sequence of paths or meshes, got {type(targets).__name__}"
        )
    if len(targets) == 0:
        raise ValueError("`targets` must hold at least one patient, got 0")
    if not isinstance(output_dir, (str, os.PathLike)):
        raise TypeError(f"`output_dir` must be a path, got {type(output_dir).__name__}")
    output_dir = os.fspath(output_dir)
    if (
        executor is not None
        and not isinstance(executor, cf.Executor)
        and not hasattr(executor, "submit")
    ):
        raise TypeError(
            f"`executor` must be a concurrent.futures.Executor, got {type(executor).__name__}"
        )
    if callback is not None and not callable(callback):
        raise TypeError(f"`callback` must be callable, got {type(callback).__name__}")
    force = check_bool(force, "force")
    progress = check_bool(progress, "progress")
    if not isinstance(target_name, str):
        raise TypeError(f"`target_name` must be a str, got {type(target_name).__name__}")
    settings_ = resolve_settings(settings, {k: v for k, v in options.items() if k != "init"})
    if names is None:
        names_ = _default_names(targets)
    else:
        names_ = [str(n) for n in names]
        if len(names_) != len(targets):
            raise ValueError(f"`names` must hold {len(targets)} names, got {len(names_)}")
    if options.get("init") is not None:
        init = np.asarray(options["init"], dtype=np.float64)
        if init.shape == (len(targets), 4, 4):
            inits: list[Any] = [
                as_transformation(t, f"init[{i}]", similarity=True) for i, t in enumerate(init)
            ]
        elif init.shape == (4, 4):
            inits = [as_transformation(init, "init", similarity=True)] * len(targets)
        else:
            raise ValueError(
                f"`init` must have shape (4, 4) or ({len(targets)}, 4, 4), got {init.shape}"
            )
    else:
        inits = [None] * len(targets)
    names_ = [_safe_name(n) for n in names_]
    seen: dict[str, int] = {}
    for i, n in enumerate(names_):
        if n.lower() in RESERVED_NAMES:
            raise ValueError(
                f"`names`: {n!r} (target {i}) names the batch's own {n.lower()}.json; choose "
                "another name"
            )
        if n.lower() in seen:
            raise ValueError(
                f"`names` must be unique (ignoring case), got {n!r} for targets "
                f"{seen[n.lower()]} and {i}"
            )
        seen[n.lower()] = i
    prepared: list[Any] = []
    for i, t in enumerate(targets):
        if isinstance(t, (str, os.PathLike)):
            prepared.append(os.fspath(t))
        else:
            prepared.append(as_mesh_arrays(t, f"targets[{i}]", drop_degenerate=True))
    if os.path.exists(output_dir) and not os.path.isdir(output_dir):
        raise OSError(f"`output_dir`: {os.fspath(output_dir)!r} is a file, not a folder")
    os.makedirs(output_dir, exist_ok=True)
    return _run_batch(
        (tv, tf),
        prepared,
        names_,
        inits,
        output_dir,
        executor,
        force,
        progress,
        callback,
        settings_,
        target_name,
    )


def _run_batch(
    template: tuple[np.ndarray, np.ndarray],
    targets: list[Any],
    names: list[str],
    inits: list[Any],
    output_dir: str,
    executor: cf.Executor | None,
    force: bool,
    progress: bool,
    callback: Callable[[PatientRecord], Any] | None,
    settings: RegistrationSettings,
    target_name: str,
) -> BatchResult:
    records: dict[str, PatientRecord] = {}
    todo: list[int] = []
    template_digest, options_key = _digest(*template), _options_key(settings)
    keys = [_key(template_digest, t, init, options_key) for t, init in zip(targets, inits)]
    for i, name in enumerate(names):
        path = os.path.join(output_dir, f"{name}.json")
        record = None if force else _read_record(path, name, keys[i])
        if (
            record is not None
            and record.status == "registered"
            and record.verdict in STATUSES
            and os.path.isfile(os.path.join(output_dir, f"{name}.ply"))
        ):
            current = targets[i]
            if isinstance(current, str) and os.path.abspath(record.source) != os.path.abspath(
                current
            ):
                # The same patient (its content is in the key) read from elsewhere: a folder
                # moved with its patients, or patients moved. The record names where it is now.
                record = dataclasses.replace(record, source=os.path.abspath(current))
                _write_json(path, {**record.as_dict(), "resume_key": keys[i]})
            records[name] = record
            logger.info("batch: %s already registered, skipped", name)
            if callback is not None:
                callback(record)
        else:
            todo.append(i)

    bar = Progress(
        len(names), len(names) - len(todo), "patients", "patient", enabled=bool(progress)
    )

    def source_of(i: int) -> str:
        return targets[i] if isinstance(targets[i], str) else "<array>"

    def finish(i: int, outcome: tuple[Any, float] | None, error: BaseException | None) -> None:
        name = names[i]
        if error is not None:
            msg = f"{type(error).__name__}: {error}"
            logger.warning("batch: %s failed: %s", name, msg)
            logger.debug("".join(traceback.format_exception(error)))
            record = PatientRecord(
                name, "failed", False, msg, source=source_of(i), verdict="failed"
            )
        else:
            assert outcome is not None
            record = save_registered(output_dir, name, *outcome, source=source_of(i), key=keys[i])
        if record.status == "failed":
            _write_json(os.path.join(output_dir, f"{name}.json"), record.as_dict())
        records[name] = record
        bar.done(f"{name} ({record.verdict or record.status})")
        if callback is not None:
            callback(record)

    def settle(i: int, outcome_of: Callable[[], tuple[Any, float]]) -> None:
        """Record patient ``i`` from its registration (an interruption is not a failure)."""
        try:
            outcome = outcome_of()
        except KeyboardInterrupt:
            raise
        except Exception as exc:
            finish(i, None, exc)
        else:
            finish(i, outcome, None)

    try:
        if executor is None:
            for i in todo:
                bar.current(names[i])
                work = functools.partial(
                    _register_one, template, targets[i], inits[i], settings, target_name
                )
                settle(i, work)
        else:
            futures = {
                executor.submit(
                    _register_one, template, targets[i], inits[i], settings, target_name
                ): i
                for i in todo
            }
            try:
                for future in cf.as_completed(futures):
                    settle(futures[future], future.result)
            except BaseException:
                for future in futures:
                    future.cancel()
                raise
    finally:
        bar.close()
        done = [records[n].as_dict() for n in names if n in records]
        if done:
            _write_json(os.path.join(output_dir, "summary.json"), done)
    return BatchResult(tuple(records[n] for n in names), output_dir, template[1])


def write_summary(batch: BatchResult) -> None:
    """Write ``summary.json`` of ``batch`` (its records as they are now: after a population
    check, with the verdicts it gave) into its output folder."""
    if batch.records:
        _write_json(os.path.join(batch.output_dir, "summary.json"), batch.as_dicts())
