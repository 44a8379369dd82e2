"""Build a model folder: batch registration, Procrustes, PCA, quality curves and the files.

A model folder holds ``template.ply`` (the template the model is defined on), ``model.npz``
(:meth:`~o3dreg.ShapeModel.save`), ``model.h5`` (statismo layout), ``mean.ply`` and ``modes/``,
``variance.txt`` (the paper's Table 4), ``quality/`` (tables and PNG plots), ``registrations/``
(one semilandmark mesh, deformation and record per patient), ``report.json`` and
``explorer.html`` (:func:`~o3dreg.app.explorer.write_model_explorer`).
``o3dreg build-model`` is a thin adapter over :func:`build_model_folder`.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np
import open3d as o3d

from .._geometry import turned_triangles
from .._validation import check_bool
from ..io import json_text
from ..io.landmark_files import read_landmarks, select_labels
from ..io.mesh import atomic_write_text, make_folder, read_triangle_mesh, write_triangle_mesh
from ..registration.options import ElasticLevel
from ..shape.build import build_shape_model
from ..shape.model import ShapeModel
from ..shape.quality import QualityCurve, compactness, generalization, specificity
from ..shape.sliding import SlidingResult, check_bending_size, slide_semilandmarks
from ..shape.statismo import write_statismo
from .batch import BatchResult, register_batch, stored_source, write_summary
from .explorer import write_model_explorer
from .population import check_population
from .progress import announce
from .settings import RegistrationSettings

logger = logging.getLogger("o3dreg")


@dataclass(frozen=True, repr=False)
class ModelFolder:
    """What :func:`build_model_folder` wrote.

    Attributes
    ----------
    path : str
        The model folder.
    batch : BatchResult
        One record per patient (registered, skipped as finished, or failed).
    model : ShapeModel or None
        The shape model; ``None`` when fewer than two patients were registered.
    curves : list of QualityCurve
        Compactness, specificity and (three patients or more) generalisation.
    sliding : SlidingResult or None
        The semilandmark sliding, when asked for.
    report : dict
        The content of ``report.json`` (empty when no model was built).
    """

    path: str
    batch: BatchResult
    model: ShapeModel | None
    curves: list[QualityCurve]
    sliding: SlidingResult | None
    report: dict[str, Any]

    def __repr__(self) -> str:
        shapes = 0 if self.model is None else len(self.model.names)
        return (
            f"ModelFolder(path={self.path!r}, patients={len(self.batch.records)}, "
            f"shapes={shapes}, failed={len(self.batch.failed)})"
        )


#: What a built model consists of in its folder: none is replaced without ``overwrite``.
#: The hidden file a model build holds locked in its folder (see ``_folder_lock``).
LOCK_FILE = ".o3dreg-build.lock"

MODEL_FILES = (
    "model.npz",
    "model.h5",
    "mean.ply",
    "variance.txt",
    "report.json",
    "explorer.html",
    "modes",
    "quality",
)


def existing_model_files(folder: str | os.PathLike[str]) -> list[str]:
    """The names of :data:`MODEL_FILES` present in ``folder`` (a folder counts when not empty).

    Finished registrations (``registrations/``) and ``template.ply`` are not model files: a
    folder holding only those is resumed without ``overwrite``.
    """
    found = []
    for name in MODEL_FILES:
        path = os.path.join(folder, name)
        if os.path.isfile(path) or (os.path.isdir(path) and os.listdir(path)):
            found.append(name)
    return found


@contextlib.contextmanager
def _folder_lock(folder: str | os.PathLike[str]) -> Iterator[None]:
    """Hold ``folder/.o3dreg-build.lock`` while a model is built there: a second build into the
    same folder is refused at once (two runs both exited 0 and the last one's model won). The
    kernel releases the lock when the process ends, however it ends. No lock where ``fcntl`` is
    missing (Windows)."""
    try:
        import fcntl  # POSIX only: absent on Windows, where no lock is taken
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    with open(os.path.join(folder, LOCK_FILE), "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise OSError(
                f"`output`: another model build is writing {os.fspath(folder)!r}; wait for it to "
                "end or choose another folder"
            ) from None
        try:
            yield
        finally:
            with contextlib.suppress(OSError):
                os.remove(os.path.join(folder, LOCK_FILE))  # a finished build leaves no trace
            fcntl.flock(handle, fcntl.LOCK_UN)


def _refuse_a_model(output: str | os.PathLike[str], overwrite: bool) -> None:
    """``FileExistsError`` when ``output`` holds a model and ``overwrite`` is false."""
    present = existing_model_files(output)
    if present and not overwrite:
        raise FileExistsError(
            f"`output`: {os.fspath(output)!r} already holds a model ({', '.join(present)}); pass "
            "overwrite=True to rebuild it (finished registrations are reused) or choose another "
            "folder"
        )


#: The hidden folders a model build writes its files into before moving them into place, and
#: moves the files they replace into before removing them.
STAGING_PREFIX = ".o3dreg-model."


def _replace_model_files(folder: str, staging: str) -> None:
    """Move the :data:`MODEL_FILES` written in ``staging`` into ``folder``, in place of those
    there: the old ones are first moved aside (renames within one folder), and moved back if
    the swap is interrupted, so the folder holds one model or the other."""
    old = tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=folder)
    moved_aside: list[str] = []
    placed: list[str] = []
    try:
        for name in MODEL_FILES:
            if os.path.lexists(os.path.join(folder, name)):
                os.replace(os.path.join(folder, name), os.path.join(old, name))
                moved_aside.append(name)
        for name in MODEL_FILES:
            if os.path.lexists(os.path.join(staging, name)):
                os.replace(os.path.join(staging, name), os.path.join(folder, name))
                placed.append(name)
    except BaseException:
        for name in placed:
            with contextlib.suppress(OSError):
                os.replace(os.path.join(folder, name), os.path.join(staging, name))
        for name in moved_aside:
            with contextlib.suppress(OSError):
                os.replace(os.path.join(old, name), os.path.join(folder, name))
        raise
    finally:
        shutil.rmtree(old, ignore_errors=True)


def check_inputs_outside(
    folder: str | os.PathLike[str], inputs: Sequence[Any], name: str = "targets"
) -> None:
    """Refuse input files that the model folder ``folder`` would write over: its
    ``template.ply``, the :data:`MODEL_FILES` and anything in ``registrations/``, ``modes/`` or
    ``quality/`` (inputs that are not paths are skipped). Before any work."""
    out = os.path.realpath(folder)
    written = {os.path.join(out, n) for n in ("template.ply", *MODEL_FILES)}
    trees = [os.path.join(out, n) for n in ("registrations", "modes", "quality")]
    for item in inputs:
        if not isinstance(item, (str, os.PathLike)):
            continue
        path = os.path.realpath(item)
        if path in written or any(path.startswith(t + os.sep) for t in trees):
            raise ValueError(
                f"`{name}`: {os.fspath(item)!r} is a file the model folder "
                f"{os.fspath(folder)!r} writes; it would be replaced. Move it out of the folder "
                "or choose another output folder"
            )


#: Suffixes tried, in order, for a patient's landmark file beside its mesh.
LANDMARK_SUFFIXES = (".mrk.json", ".fcsv", ".csv")


#: A mode whose shape at +-3 standard deviations turns more than this fraction of the
#: triangles over (relative to the mean) is folded (the 8 mandibles' model: 0.02% at most; a
#: linear model of very large variations may fold at 3 SD too, and is said to).
FOLDED_MODE_FRACTION = 0.01


def folded_modes(model: ShapeModel, modes: int = 3) -> list[tuple[int, float, float]]:
    """``(mode, standard deviations, fraction)`` of the first ``modes`` modes whose shape at
    -3 or +3 standard deviations turns more than :data:`FOLDED_MODE_FRACTION` of the triangles
    over relative to the mean (normals at 90 degrees or more)."""
    faces, mean = np.asarray(model.faces), np.asarray(model.mean)
    out = []
    for mode in range(min(modes, model.number_of_modes)):
        for sd in (-3.0, 3.0):
            turned = turned_triangles(mean, model.mode_shape(mode, sd), faces)
            if turned.mean() > FOLDED_MODE_FRACTION:
                out.append((mode, sd, float(turned.mean())))
    return out


def patient_landmark_file(mesh_path: str | os.PathLike[str]) -> str:
    """The landmark file of a patient mesh: ``PATH/NAME.mrk.json``, else ``PATH/NAME.fcsv``,
    else ``PATH/NAME.csv``.

    ``NAME`` is the mesh file name without its suffix (``.nii.gz`` counted as one).

    Raises
    ------
    OSError
        When neither exists (naming both).
    """
    path = os.fspath(mesh_path)
    folder, base = os.path.split(path)
    stem = (
        base[: -len(".nii.gz")] if base.lower().endswith(".nii.gz") else os.path.splitext(base)[0]
    )
    tried = [os.path.join(folder, stem + suffix) for suffix in LANDMARK_SUFFIXES]
    for candidate in tried:
        if os.path.isfile(candidate):
            return candidate
    raise OSError(f"no landmark file for patient {path!r}: expected {' or '.join(tried)}")


def _check_distinct_patients(targets: Sequence[str], name: str = "target") -> None:
    """Before any work: the patient files hold at least 2 distinct meshes. Identical meshes give
    identical registrations, so a model of no variance. Files that cannot be read here are
    counted as distinct (the batch reports them, or reads them where it runs); when too few are
    left, the refusal gives the reader's reason for each (``name``: how it calls one file)."""
    given: dict[str, str] = {}
    for path in targets:
        real = os.path.realpath(path)
        if real in given:
            raise ValueError(
                f"`targets` must name each patient file once, got {given[real]!r} and "
                f"{os.fspath(path)!r}: one file"
            )
        given[real] = os.fspath(path)
    groups: dict[str, list[str]] = {}
    unread: list[str] = []
    for path in targets:
        try:
            mesh = read_triangle_mesh(path, name=name)
        except (OSError, ValueError, RuntimeError) as exc:
            unread.append(str(exc))
            continue
        digest = hashlib.sha256(np.asarray(mesh.vertices).tobytes())
        digest.update(np.asarray(mesh.triangles).tobytes())
        groups.setdefault(digest.hexdigest(), []).append(os.fspath(path))
    repeated = [" and ".join(paths) for paths in groups.values() if len(paths) > 1]
    if len(groups) + len(unread) < 2:
        same = "".join(f"; {paths} hold the same mesh" for paths in repeated)
        # The reader's message names the file and why it was not read (a typo, not a mesh).
        why = "".join(f"; {text}" for text in unread)
        raise ValueError(
            f"`targets` must hold at least 2 distinct patient meshes to build a model, got "
            f"{len(targets)} file(s) with {len(groups)} distinct mesh(es){same}{why}"
        )
    for paths in repeated:
        logger.warning("build_model_folder: %s hold the same mesh (counted twice)", paths)


def build_model_folder(
    template: o3d.geometry.TriangleMesh,
    targets: Sequence[str],
    output: str,
    *,
    executor: Executor | None = None,
    force: bool = False,
    overwrite: bool = False,
    progress: bool = False,
    settings: RegistrationSettings | None = None,
    landmarks: str | os.PathLike[str] | None = None,
    landmark_labels: Sequence[str] | None = None,
    keep_flagged: bool = False,
    levels: Sequence[ElasticLevel] | None = None,
    scaling: bool = False,
    slide: bool = False,
    target_name: str = "target",
) -> ModelFolder:
    """Register ``template`` onto every patient file and write a model folder (resumable).

    Parameters
    ----------
    template : open3d.geometry.TriangleMesh
        The template (moves; ~1k-4k vertices).
    targets : sequence of str
        Patient mesh files.
    output : str
        The model folder (created). A folder holding a model of another template (other
        triangles) is refused unless ``force``.
    executor : concurrent.futures.Executor, optional
        Runs the registrations (a process pool, a Dask client's executor); serial by default.
    force : bool, optional
        Register finished patients again.
    overwrite : bool, optional
        Replace the model of an earlier run in ``output`` (any of :data:`MODEL_FILES`).
        Without it such a folder is refused before any work; a folder holding only finished
        registrations (an interrupted run) is resumed either way.
    progress : bool, optional
        Report progress on stderr: the patients (a bar on a terminal, a line per patient
        elsewhere) and the steps after them.
    settings : RegistrationSettings, optional
        How each patient is registered: the same settings as ``o3dreg register`` (levels,
        regularisation, single/symmetric distance, robust settings, start). Default
        ``RegistrationSettings()``.
    landmarks : str or path-like, optional
        The template's landmark file. Each patient ``PATH/NAME.EXT`` is then started from the
        landmarks of :func:`patient_landmark_file` (``PATH/NAME.mrk.json``, ``.fcsv`` or
        ``.csv``), paired by label: a rigid fit, or a similarity when
        ``settings.start == 'similarity'``. A patient without one raises before any work.
    landmark_labels : sequence of str, optional
        The landmarks of ``landmarks`` (and of each patient's file) to pair, e.g. those of the
        anatomy the meshes show; each must be in every file. Default: every landmark, the
        same labels in every file.
    keep_flagged : bool, optional
        Put patients whose verdict is ``'suspect'`` or ``'failed'`` in the model too. Default
        ``False``: only ``'ok'`` patients; the others are listed in ``report.json`` with their
        reasons.
    levels : sequence of ElasticLevel, optional
        Shorthand for ``settings=RegistrationSettings(levels=levels)``.
    scaling : bool, optional
        Similarity Procrustes (size removed).
    slide : bool, optional
        Slide the semilandmarks before the PCA.
    target_name : str, optional
        What the messages about a patient file that cannot be read call it (see
        :func:`~o3dreg.app.batch.register_batch`). Default ``"target"``.

    Returns
    -------
    ModelFolder
        What was written; ``model`` is ``None`` when fewer than two patients were registered.

    Raises
    ------
    FileExistsError
        When ``output`` already holds a model and ``overwrite`` is false (naming the folder).
    ValueError
        Before any work, when ``targets`` hold fewer than 2 distinct meshes (one patient, or
        one mesh under several names: a model of no variance); after the registrations (kept,
        no model file written), when the registered shapes do not differ.
    """
    for flag, label in (
        (force, "force"),
        (overwrite, "overwrite"),
        (progress, "progress"),
        (keep_flagged, "keep_flagged"),
        (scaling, "scaling"),
        (slide, "slide"),
    ):
        check_bool(flag, label)
    if levels is not None:
        if settings is not None:
            raise TypeError("pass `levels` inside `settings`, not both")
        settings = RegistrationSettings(levels=tuple(levels))
    settings = settings if settings is not None else RegistrationSettings()
    if not isinstance(settings, RegistrationSettings):
        raise TypeError(f"`settings` must be a RegistrationSettings, got {type(settings).__name__}")
    _refuse_a_model(output, overwrite)
    check_inputs_outside(output, targets)
    if landmarks is not None:
        check_inputs_outside(output, [landmarks], "landmarks")
        if landmark_labels is not None:  # the template's file named, before any patient's
            available = read_landmarks(landmarks)[0]
            select_labels(available, landmark_labels, repr(os.fspath(landmarks)), "landmark_labels")
    elif landmark_labels is not None:
        raise ValueError("`landmark_labels` chooses landmarks of `landmarks`: give `landmarks`")
    if slide:  # before any registration: the sliding's dense solve has a size limit
        check_bending_size(len(np.asarray(template.vertices)), name="slide")
    _check_distinct_patients(targets, target_name)
    inits = None
    if landmarks is not None:
        starts = []
        for t in targets:
            marks = patient_landmark_file(t)
            try:
                starts.append(settings.landmark_start(landmarks, marks, labels=landmark_labels))
            except ValueError as exc:  # name the patient: the message names only the roles
                raise ValueError(f"patient {os.fspath(t)!r} ({marks!r}): {exc}") from exc
        inits = np.stack(starts)
    out = output
    make_folder(out, "output")
    with _folder_lock(out):
        _refuse_a_model(output, overwrite)  # again: a build may have ended since
        # Staging folders of a build killed outright (SIGKILL, power loss): this build holds
        # the folder's lock, so no other build is writing them.
        for entry in os.listdir(out):
            if entry.startswith(STAGING_PREFIX):
                shutil.rmtree(os.path.join(out, entry), ignore_errors=True)
        template_path = os.path.join(out, "template.ply")
        if os.path.exists(template_path):
            previous = read_triangle_mesh(template_path)
            same = np.array_equal(np.asarray(previous.triangles), np.asarray(template.triangles))
            if not same and not force:
                raise ValueError(
                    f"{out!r} holds a model of another template; use another folder or --force"
                )
        write_triangle_mesh(template_path, template, overwrite=True)
        batch = register_batch(
            template,
            list(targets),
            os.path.join(out, "registrations"),
            executor=executor,
            force=force,
            progress=progress,
            settings=settings,
            target_name=target_name,
            init=inits,
        )
        batch = check_population(batch)
        # The batch's summary says what the check found, as report.json does.
        write_summary(batch)
        names, shapes = batch.shapes(accepted_only=not keep_flagged)
        if len(names) < 2:
            return ModelFolder(out, batch, None, [], None, {})
        faces = np.asarray(template.triangles)
        slid = None
        if slide:
            if progress:
                announce(f"sliding the semilandmarks of {len(names)} patients")
            used = set(names)
            surfaces = [read_triangle_mesh(r.source) for r in batch.registered if r.name in used]
            slid = slide_semilandmarks(shapes, surfaces, scaling=scaling, faces=faces)
            shapes = slid.shapes
            if not slid.success:
                logger.warning("build-model: sliding semilandmarks %s", slid.message)
        try:
            model = build_shape_model(shapes, faces, names=names, scaling=scaling)
        except ValueError as exc:  # the patients' shapes do not differ: no model file is written
            raise ValueError(
                f"{exc}; no model written, the registrations in "
                f"{os.path.join(out, 'registrations')!r} are kept"
            ) from exc
        folded = folded_modes(model)
        for mode, sd, fraction in folded:
            logger.warning(
                "build-model: mode %d at %+g SD turns %.1f%% of the triangles over (a folded "
                "shape)%s",
                mode + 1,
                sd,
                100 * fraction,
                ": the slid semilandmarks moved differently from patient to patient; build "
                "without --slide"
                if slide
                else "",
            )
        # The model's files are written together or not at all: they are written into a hidden
        # folder beside the model's and moved into place once all are written, so a failed or
        # interrupted run (a full disk, Ctrl-C) leaves the folder's earlier model as it was and
        # never a half-built one. The registrations stay for the rerun.
        if progress:
            announce(f"model of {len(names)} patients: files, quality curves and the explorer")
        staging = tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=out)
        try:
            model.save(os.path.join(staging, "model.npz"), overwrite=True)
            write_statismo(os.path.join(staging, "model.h5"), model, overwrite=True)
            model.write_meshes(os.path.join(staging, "modes"), overwrite=True)
            write_triangle_mesh(os.path.join(staging, "mean.ply"), model.mesh(), overwrite=True)
            atomic_write_text(
                os.path.join(staging, "variance.txt"), model.variance_table() + "\n", overwrite=True
            )
            quality_dir = os.path.join(staging, "quality")
            os.makedirs(quality_dir, exist_ok=True)
            curves = [compactness(model), specificity(model, shapes, number_of_samples=100, seed=0)]
            if len(names) >= 3:
                curves.append(generalization(shapes, faces, scaling=scaling))
            for curve in curves:
                curve.plot(os.path.join(quality_dir, f"{curve.name}.png"), overwrite=True)
                atomic_write_text(
                    os.path.join(quality_dir, f"{curve.name}.txt"),
                    curve.table() + "\n",
                    overwrite=True,
                )
            report = {
                "model_dir": out,
                # Sources relative to the model folder, as each record stores them.
                "patients": [
                    {**d, "source": stored_source(d["source"], out)} for d in batch.as_dicts()
                ],
                "settings": settings.as_dict(),
                "in_model": list(names),
                "registered": [r.name for r in batch.registered],
                "failed": [r.name for r in batch.failed],
                "flagged": {
                    r.name: {"verdict": r.verdict, "warnings": list(r.warnings)}
                    for r in batch.flagged
                },
                "keep_flagged": keep_flagged,
                "variances": model.variance_records(),
                "quality": {c.name: c.as_dict() for c in curves},
                "folded_modes": [
                    {"mode": m + 1, "standard_deviations": sd, "turned_fraction": f}
                    for m, sd, f in folded
                ],
                "sliding": None
                if slid is None
                else {
                    "criterion": slid.criterion,
                    "iterations": slid.iterations,
                    "message": slid.message,
                },
            }
            atomic_write_text(
                os.path.join(staging, "report.json"),
                json_text.dumps(report, indent=2) + "\n",
                overwrite=True,
            )
            write_model_explorer(os.path.join(staging, "explorer.html"), model, registrations=batch)
            _replace_model_files(out, staging)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        return ModelFolder(out, batch, model, curves, slid, report)
