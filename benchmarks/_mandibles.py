"""The patients of a PDDCA mandible folder, for the landmark benchmarks: each mask's surface and
its 3D Slicer annotations, checked, and a line naming each patient that cannot serve and why.

A folder holds ``masks/<id>_Mandible.nrrd`` and ``landmarks/<id>_Landmarks.fcsv`` (PDDCA's
naming; the id is whatever precedes the suffix). A patient serves when its mask gives one
mandible surface and its landmark file places each label used once, on that surface.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))

# The mask checks are the mandible example's: a patient serves the benchmarks when its mask
# gives the example's surface.
from mandible_model import (
    LARGEST_SHARE,
    MASK_SUFFIX,
    SMOOTHING,
    Unusable,
    mask_isosurface,
)

__all__ = ["LARGEST_SHARE", "MASK_SUFFIX", "SMOOTHING", "Unusable"]

LANDMARK_SUFFIX = "_Landmarks.fcsv"


def patient_id(path: Path, suffix: str) -> str | None:
    """The id of a file named ``<id><suffix>`` (the suffix in any case); ``None`` otherwise.

    Parameters
    ----------
    path : Path
    suffix : str
        :data:`MASK_SUFFIX` or :data:`LANDMARK_SUFFIX`.

    Returns
    -------
    str or None
        Everything before the suffix: ids hold any characters, underscores included.
    """
    name = path.name
    if len(name) > len(suffix) and name.lower().endswith(suffix.lower()):
        return name[: -len(suffix)]
    return None


def patient_files(folder: Path) -> tuple[dict[str, tuple[Path, Path | None]], list[str]]:
    """Each patient's mask and landmark file in ``folder``, by id.

    Parameters
    ----------
    folder : Path
        Holding ``masks/`` and ``landmarks/``.

    Returns
    -------
    files : dict
        ``{id: (mask, landmark file or None)}``, sorted by id.
    lines : list of str
        One per file that names no patient, and per landmark file without its mask.
    """
    lines: list[str] = []

    def by_id(sub: str, suffix: str) -> dict[str, Path]:
        found: dict[str, Path] = {}
        where = folder / sub
        for path in sorted(where.iterdir()) if where.is_dir() else []:
            if path.name.startswith("."):  # system files (.DS_Store, ._ resource forks)
                continue
            pid = patient_id(path, suffix)
            if pid is None:
                lines.append(f"ignored {sub}/{path.name}: not named <id>{suffix}")
            elif pid in found:
                lines.append(
                    f"ignored {sub}/{path.name}: patient {pid} has {found[pid].name} already"
                )
            else:
                found[pid] = path
        return found

    masks = by_id("masks", MASK_SUFFIX)
    landmarks = by_id("landmarks", LANDMARK_SUFFIX)
    for pid in sorted(set(landmarks) - set(masks)):
        lines.append(
            f"left out {pid}: landmarks/{landmarks[pid].name} has no masks/{pid}{MASK_SUFFIX}"
        )
    return {pid: (masks[pid], landmarks.get(pid)) for pid in sorted(masks)}, lines


def mask_surfaces(path: Path):
    """The surface of a mask (marching cubes at 0.5), its largest component smoothed, and the
    voxel size.

    Parameters
    ----------
    path : Path
        A mask volume (voxels above 0.5 are the bone).

    Returns
    -------
    whole : open3d.geometry.TriangleMesh
        Every component, unsmoothed (to tell where landmarks off the largest one lie).
    surface : open3d.geometry.TriangleMesh
        The largest component after :data:`SMOOTHING` Taubin iterations.
    spacing : (3,) ndarray
        Voxel size along x, y, z (mm).

    Raises
    ------
    Unusable
        The file cannot be read, holds no voxel above 0.5 or no surface there, or its largest
        component holds less than :data:`LARGEST_SHARE` of the surface.
    """
    import o3dreg

    whole, volume = mask_isosurface(path)
    surface = o3dreg.smooth_taubin(o3dreg.keep_largest_components(whole, 1), SMOOTHING)
    return whole, surface, np.asarray(volume.spacing, dtype=float)[::-1]


def annotations(path: Path | None, labels: Sequence[str], pid: str) -> tuple[np.ndarray, list[str]]:
    """The points of ``labels`` in a landmark file, LPS (o3dreg's meshes' system).

    Parameters
    ----------
    path : Path or None
        A 3D Slicer ``.fcsv`` (RAS or LPS, as its ``CoordinateSystem`` line says); ``None``
        when the patient has none.
    labels : sequence of str
    pid : str
        The patient, for the messages.

    Returns
    -------
    points : (len(labels), 3) ndarray
    notes : list of str
        What the reader warned of (a coordinate system not stated, unplaced points of other
        labels).

    Raises
    ------
    Unusable
        No file, a file that cannot be read, or a label absent, unplaced or there twice.
    """
    import o3dreg

    if path is None:
        raise Unusable(f"no landmark file landmarks/{pid}{LANDMARK_SUFFIX}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            found, points = o3dreg.read_landmarks(str(path))
        except (OSError, ValueError) as exc:
            raise Unusable(f"{path.name} cannot be read: {exc}") from None
    notes = [str(w.message) for w in caught]
    missing = [lab for lab in labels if lab not in found]
    # The reader skips an unplaced point with a warning naming it: say so rather than "lacks".
    unplaced = [
        lab for lab in missing if any("not placed" in n and f"{lab!r} (" in n for n in notes)
    ]
    if unplaced:
        raise Unusable(
            f"{path.name} holds {', '.join(map(repr, unplaced))} not placed (a Slicer control "
            f"point without a position; {', '.join(labels)} placed expected)"
        )
    if missing:
        raise Unusable(
            f"{path.name} lacks {', '.join(map(repr, missing))} ({', '.join(labels)} expected; "
            f"it holds {', '.join(found)})"
        )
    twice = [f"{lab!r} {found.count(lab)} times" for lab in labels if found.count(lab) > 1]
    if twice:
        raise Unusable(
            f"{path.name} holds {', '.join(twice)} (each label once expected: which one is the "
            "annotation is not known)"
        )
    return points[[found.index(lab) for lab in labels]], notes


def _size(vertices: np.ndarray) -> str:
    return " x ".join(f"{x:.0f}" for x in np.ptp(vertices, axis=0)) + " mm"


def check_on_surface(
    template: tuple[np.ndarray, np.ndarray],
    points: np.ndarray,
    labels: Sequence[str],
    whole,
) -> None:
    """Refuse annotations that do not lie on the template, as the benchmark attaches them
    (:meth:`~o3dreg.TemplateLandmarks.from_points`: within ``LANDMARK_REACH``, 5 % of the
    template's size), saying why.

    Parameters
    ----------
    template : (vertices, faces)
        The template decimated from the mask's largest component.
    points : (l, 3) ndarray
        The annotations, LPS.
    labels : sequence of str
    whole : open3d.geometry.TriangleMesh
        Every component of the mask's surface.

    Raises
    ------
    Unusable
        Naming the landmarks off the surface, how far, and the likely cause: a file in the other
        coordinate system (the points lie on the surface with x and y negated), a largest
        component that is not the mandible (they lie on another component), or the placement.
    """
    import igl

    from o3dreg import TemplateLandmarks
    from o3dreg.shape.landmark_transfer import LANDMARK_REACH, OffTemplateError

    def attach(at: np.ndarray) -> OffTemplateError | None:
        try:
            TemplateLandmarks.from_points(template, at, labels)
        except OffTemplateError as exc:
            return exc
        return None

    off = attach(points)
    if off is None:
        return
    far = ", ".join(f"{lab!r} {d:.1f} mm" for lab, d in zip(off.far, off.distances))
    reach = f"within {off.max_distance:.1f} mm expected, {LANDMARK_REACH:.0%} of the surface's size"
    if attach(points * np.array([-1.0, -1.0, 1.0])) is None:
        raise Unusable(
            f"its landmarks lie off its mandible surface ({far}; {reach}) and on it with x and y "
            "negated: its landmark file's CoordinateSystem (RAS or LPS) does not match its points"
        )
    vertices = np.asarray(whole.vertices, dtype=np.float64)
    faces = np.asarray(whole.triangles, dtype=np.int64)
    picked = points[[list(labels).index(lab) for lab in off.far]]
    anywhere = np.sqrt(igl.point_mesh_squared_distance(picked, vertices, faces)[0])
    if (anywhere <= off.max_distance).all():
        raise Unusable(
            f"its mask's largest component ({_size(template[0])}) does not hold {far} ({reach}): "
            f"they lie on another component of the mask ({anywhere.max():.1f} mm from it at "
            "most), so its largest component is not the mandible"
        )
    raise Unusable(
        f"landmarks off its mandible surface: {far} ({reach}; the surface {_size(template[0])})"
    )


def load_patient(
    pid: str,
    mask: Path,
    landmarks: Path | None,
    labels: Sequence[str],
    template_vertices: int,
) -> tuple[dict, list[str]]:
    """One patient's surface, template and annotations, checked.

    Parameters
    ----------
    pid : str
    mask, landmarks : Path
        Its files (``landmarks`` ``None`` when it has none).
    labels : sequence of str
        The labels used, each to be placed once, on the surface.
    template_vertices : int
        The template: the surface decimated to about this many vertices.

    Returns
    -------
    patient : dict
        ``spacing`` (voxel size x, y, z, mm), ``surface`` and ``template`` (vertices, faces),
        ``landmarks`` ((len(labels), 3), LPS, in the order of ``labels``).
    notes : list of str
        What the landmark reader warned of.

    Raises
    ------
    Unusable
        The reason the patient cannot serve.
    """
    import o3dreg

    points, notes = annotations(landmarks, labels, pid)
    whole, surface, spacing = mask_surfaces(mask)
    template = o3dreg.decimate(surface, template_vertices)
    template_arrays = (np.asarray(template.vertices), np.asarray(template.triangles))
    check_on_surface(template_arrays, points, labels, whole)
    patient = {
        "spacing": spacing,
        "surface": (np.asarray(surface.vertices), np.asarray(surface.triangles)),
        "template": template_arrays,
        "landmarks": points,
    }
    return patient, notes


def load_patients(
    folder: Path,
    labels: Sequence[str],
    template_vertices: int,
    say: Callable[[str], None] = print,
) -> dict[str, dict]:
    """Every patient of ``folder`` that can serve (:func:`load_patient`), by id.

    Parameters
    ----------
    folder : Path
        Holding ``masks/`` and ``landmarks/``.
    labels : sequence of str
    template_vertices : int
    say : callable, optional
        Given one line per patient left out (``left out <id>: <why>``), per file ignored and
        per note of the landmark reader. Default :func:`print`.

    Returns
    -------
    dict
        ``{id: patient}`` sorted by id, the patients as :func:`load_patient` returns them.
    """
    files, lines = patient_files(folder)
    for line in lines:
        say(line)
    out = {}
    for pid, (mask, landmarks) in files.items():
        try:
            out[pid], notes = load_patient(pid, mask, landmarks, labels, template_vertices)
        except Unusable as exc:
            say(f"left out {pid}: {exc}")
            continue
        for note in notes:
            say(f"note {pid}: {note}")
    return out
