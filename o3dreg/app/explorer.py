"""Interactive explorers in the browser: a shape model's modes, and registrations with verdicts.

Each page is one self-contained HTML file (no network, no CDN): the data as JSON with base64
float32 arrays, drawn by a small WebGL viewer (``explorer.html`` beside this module). The model
page shows the mean shape with a slider per mode (-3 to +3 standard deviations; the shape is
recomputed in the page as ``mean + sum_k modes[k] * sqrt(variances[k]) * slider[k]``) coloured
by the displacement from the mean along the normal, the variance table, and each patient's
registered template coloured by its distance to the patient, with the record's verdict. The URL
hash selects the view (``#view=model&mode1=2.5``, ``#view=NAME``).
"""

from __future__ import annotations

import base64
import html
import json
import logging
import os
from collections.abc import Mapping, Sequence
from importlib import resources
from typing import Any

import numpy as np
import open3d as o3d

from .._geometry import apply_transformation
from .._validation import as_mesh_arrays
from ..io.mesh import atomic_write_text, read_triangle_mesh
from ..registration.distance import SurfaceDistanceQuery
from ..registration.result import ElasticRegistrationResult
from ..shape.model import ShapeModel
from .batch import resolve_record_source
from .render import mode_displacements, view_rotation

__all__ = ["write_model_explorer", "write_registration_explorer"]

logger = logging.getLogger("o3dreg")

#: Patient surfaces larger than this are decimated for display (the distances are measured on the
#: full surface first).
MAX_DISPLAY_TRIANGLES = 4000

# Fields of a registration record shown as its verdict (``status``/``warnings`` where the record
# has them).
_VERDICT_KEYS = (
    "verdict",
    "status",
    "success",
    "message",
    "warnings",
    "distances",
    "min_jacobian_determinant",
    "flipped_triangles",
)


def _b64(array: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def _colormap(name: str, count: int = 33) -> list[list[float]]:
    import matplotlib

    table = matplotlib.colormaps[name](np.linspace(0.0, 1.0, count))[:, :3]
    return np.round(table, 4).tolist()


def _finite(value: Any) -> Any:
    """``value`` as JSON: NaN and infinities as ``None`` (JSON has neither), objects as text."""
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, Mapping):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, np.generic):
        return _finite(value.item())
    if value is None or isinstance(value, (str, int, float)):
        return value
    return str(value)  # a warning object, say: its text


def _verdict(record: Mapping[str, Any]) -> dict[str, Any]:
    out = {k: _finite(record[k]) for k in _VERDICT_KEYS if k in record}
    if isinstance(out.get("distances"), Mapping):
        out["distances"] = {
            k: v for k, v in out["distances"].items() if k.endswith(("_mean", "_max"))
        }
    return out


def _display_mesh(vertices: np.ndarray, faces: np.ndarray, max_triangles: int) -> dict[str, Any]:
    note = ""
    if faces.shape[0] > max_triangles:
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces.astype(np.int32))
        )
        small = mesh.simplify_quadric_decimation(int(max_triangles))
        note = f"decimated for display from {faces.shape[0]} to {len(small.triangles)} triangles"
        vertices, faces = np.asarray(small.vertices), np.asarray(small.triangles)
    return {
        "vertices": _b64(vertices, "<f4"),
        "faces": _b64(faces, "<u4"),
        "note": note,
    }


def _case(
    name: str,
    verdict: Mapping[str, Any],
    *,
    registered: np.ndarray | None = None,
    faces: np.ndarray | None = None,
    target: tuple[np.ndarray, np.ndarray] | None = None,
    template: np.ndarray | None = None,
    max_triangles: int = MAX_DISPLAY_TRIANGLES,
    notes: Sequence[str] = (),
    shared_faces: bool = False,
) -> dict[str, Any]:
    """One registration's view: the registered template coloured by its distance to ``target``.

    With ``shared_faces`` the page takes the triangles from its model (the same template).
    """
    case: dict[str, Any] = {"name": name, "verdict": dict(verdict), "notes": list(notes)}
    if registered is not None and faces is not None:
        case["registered"] = _b64(registered, "<f4")
        if not shared_faces:
            case["faces"] = _b64(faces, "<u4")
        if template is not None:
            case["template"] = _b64(template, "<f4")
    if target is not None:
        if registered is not None:
            distance = SurfaceDistanceQuery(*target).distance(registered)
            case["distance"] = _b64(distance, "<f4")
            case["distance_mean"] = float(distance.mean())
            # The colour scale ends at the 98th percentile, so that one far vertex does not
            # flatten the picture; the legend says where.
            case["vmax"] = float(np.percentile(distance, 98)) or 1.0
        case["patient"] = _display_mesh(target[0], target[1], max_triangles)
    return case


def _page(data: dict[str, Any]) -> str:
    template = resources.files("o3dreg.app").joinpath("explorer.html").read_text("utf-8")
    data = {**data, "colormaps": {name: _colormap(name) for name in ("coolwarm", "viridis")}}
    # "</" cannot appear inside a <script> element; JSON allows "<\/".
    payload = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    return template.replace("__TITLE__", html.escape(data["title"])).replace("__DATA__", payload)


def _check_triangles(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 4:
        raise ValueError(f"`max_display_triangles` must be an integer >= 4, got {value!r}")
    return int(value)


def _folder_records(folder: str) -> list[tuple[str, dict[str, Any]]]:
    """``(name, record)`` of every ``NAME.json`` record of a batch folder."""
    records = []
    for entry in sorted(os.listdir(folder)):
        if not entry.endswith(".json") or entry.startswith("."):
            continue
        try:
            with open(os.path.join(folder, entry), encoding="utf-8") as f:
                record = json.load(f)
        except (OSError, ValueError) as error:
            logger.warning("explorer: skipping unreadable record %s: %s", entry, error)
            continue
        if isinstance(record, dict):
            records.append((entry[: -len(".json")], record))
    return records


def _registration_cases(
    folder: str,
    records: list[tuple[str, dict[str, Any]]],
    faces: np.ndarray,
    max_triangles: int,
    targets: Mapping[str, Any],
) -> list[dict]:
    """One case per record (see :func:`~o3dreg.register_batch`), its mesh read from ``folder``."""
    cases = []
    for name, record in records:
        notes: list[str] = []
        registered = target = None
        mesh_path = os.path.join(folder, f"{name}.ply")
        if record.get("status", "registered") != "failed" and os.path.isfile(mesh_path):
            vertices = np.asarray(read_triangle_mesh(mesh_path).vertices)
            if vertices.shape[0] == int(faces.max()) + 1:
                registered = vertices
            else:
                notes.append(f"{name}.ply does not have the model's template vertices; not shown")
        source = resolve_record_source(str(record.get("source", "")), folder)
        if registered is not None:
            try:
                given = targets.get(name)
                if given is None:
                    target = as_mesh_arrays(read_triangle_mesh(source), "target")
                elif isinstance(given, (str, os.PathLike)):
                    target = as_mesh_arrays(read_triangle_mesh(given), f"targets[{name!r}]")
                else:
                    target = as_mesh_arrays(given, f"targets[{name!r}]")
            except (OSError, TypeError, ValueError) as error:
                notes.append(f"patient surface not shown, no distances: {error}")
                logger.warning(
                    "explorer: %s: patient surface not shown, no distances: %s", name, error
                )
        cases.append(
            _case(
                str(record.get("name", name)),
                _verdict(record),
                registered=registered,
                faces=faces,
                target=target,
                max_triangles=max_triangles,
                notes=notes,
                shared_faces=True,
            )
        )
    return cases


def write_model_explorer(
    path: str | os.PathLike[str],
    model: Any,
    *,
    registrations: Any = None,
    targets: Mapping[str, Any] | None = None,
    view: Sequence[float] = (30.0, 20.0),
    up: Sequence[float] = (0.0, 0.0, 1.0),
    max_display_triangles: int = MAX_DISPLAY_TRIANGLES,
    title: str | None = None,
    overwrite: bool = True,
) -> str:
    """Write an interactive, self-contained HTML explorer of a shape model and its patients.

    The page works offline in any browser with WebGL. It shows the mean shape with a slider per
    mode (-3 to +3 standard deviations; the shape is ``mean + sum_k modes[k] sqrt(variances[k])
    slider[k]``, recomputed in the page), coloured by the displacement from the mean along the
    mean's normal, and the variance table. With ``registrations``, each patient's registered
    template is shown coloured by its distance to the patient (measured on the full patient
    surface), over the patient surface, with the record's verdict (``status``, ``success``,
    ``message``, ``warnings`` where present, distances). The URL hash selects what is shown:
    ``#view=model&mode1=2.5`` or ``#view=NAME``.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.html`` file to write (atomically).
    model : ShapeModel
        Every mode gets a slider.
    registrations : str, os.PathLike or BatchResult, optional
        A :func:`~o3dreg.register_batch` output folder (``NAME.json`` records and ``NAME.ply``
        semilandmark meshes: every record in it is shown), or its result (its patients only,
        with its records' verdicts, a population check's included). Patients whose file (the
        record's ``source``) is gone are shown without distances.
    targets : mapping of str to mesh or path, optional
        Patient surfaces by name (``open3d.geometry.TriangleMesh``, ``(vertices, faces)`` or a
        file), for records that do not name a readable file (patients registered from arrays).
    view : (azimuth, elevation)
        Initial camera direction in degrees about ``up``. Default ``(30, 20)``.
    up : (3,) array_like
        The world direction shown upwards at first. Default ``(0, 0, 1)``.
    max_display_triangles : int
        Patient surfaces with more triangles are decimated for display (the page says so), to
        keep the page small. Default :data:`MAX_DISPLAY_TRIANGLES`.
    title : str, optional
        Page title. Default: a summary of the model.
    overwrite : bool
        Replace an existing file. Default ``True``.

    Returns
    -------
    str
        The path written.

    Raises
    ------
    TypeError
        If ``model`` is not a shape model.
    ValueError
        For a bad ``view``, ``up`` or ``max_display_triangles``.
    OSError
        If ``registrations`` is not a folder, or ``path`` exists and ``overwrite`` is false.

    Examples
    --------
    >>> write_model_explorer("explorer.html", model, registrations="model/registrations")
    ... # doctest: +SKIP
    """
    if not isinstance(model, ShapeModel):
        raise TypeError(f"`model` must be a ShapeModel, got {type(model).__name__}")
    max_triangles = _check_triangles(max_display_triangles)
    rotation = view_rotation(view, up)
    folder = getattr(registrations, "output_dir", registrations)
    if folder is not None and not os.path.isdir(folder):
        raise OSError(f"`registrations`: no folder {os.fspath(folder)!r}")
    faces = np.asarray(model.faces)
    k = model.number_of_modes
    # Colour scale: the largest normal displacement of the first mode at 3 SD.
    scale = float(np.abs(mode_displacements(model, 0, 3.0)).max()) if k else 0.0
    summary = (
        f"{model.number_of_shapes} shapes, {model.number_of_points} points, "
        f"{faces.shape[0]} triangles, {k} modes; "
        f"{'similarity' if model.scaling else 'rigid'} Procrustes alignment."
    )
    data: dict[str, Any] = {
        "title": title or f"o3dreg shape model ({model.number_of_shapes} shapes)",
        "rotation": rotation,
        "model": {
            "mean": _b64(model.mean, "<f4"),
            "faces": _b64(faces, "<u4"),
            "modes": [_b64(model.modes[i], "<f4") for i in range(k)],
            "standard_deviations": model.standard_deviations.tolist(),
            "variances": model.variance_records(),
            "scale": scale or 1.0,
            "summary": summary,
        },
        "cases": [],
        "notes": [
            "Shapes in mm, in the Procrustes frame of the model; patients in their own frames.",
        ],
    }
    if folder is not None:
        folder = os.fspath(folder)
        batch = getattr(registrations, "records", None)
        # A BatchResult's own records: its patients only, with the verdicts it holds (a
        # population check's included, which the files on disk do not carry).
        records = (
            [(r.name, r.as_dict()) for r in batch] if batch is not None else _folder_records(folder)
        )
        data["cases"] = _registration_cases(
            folder, records, faces, max_triangles, dict(targets or {})
        )
    return atomic_write_text(path, _page(data), overwrite=overwrite)


def write_registration_explorer(
    path: str | os.PathLike[str],
    source: Any,
    target: Any,
    result: Any,
    *,
    verdict: Mapping[str, Any] | None = None,
    name: str = "registration",
    view: Sequence[float] = (30.0, 20.0),
    up: Sequence[float] = (0.0, 0.0, 1.0),
    max_display_triangles: int = MAX_DISPLAY_TRIANGLES,
    title: str | None = None,
    overwrite: bool = True,
) -> str:
    """Write an interactive, self-contained HTML page of one elastic registration.

    Layers: the registered template coloured by its point-to-surface distance to the target
    (mm), the target surface (decimated for display when large), and the template after the
    rigid pre-alignment only (hidden at first); with the verdict (converged, message,
    distances both ways, smallest Jacobian determinant, and ``status``/``warnings`` when
    ``verdict`` has them).

    Parameters
    ----------
    path : str or os.PathLike
        The ``.html`` file to write (atomically).
    source : open3d.geometry.TriangleMesh or (vertices, faces)
        The template that was registered (in its own frame). Not modified.
    target : open3d.geometry.TriangleMesh or (vertices, faces)
        The patient surface. Not modified.
    result : ElasticRegistrationResult
        What :func:`~o3dreg.registration_elastic` returned for ``source`` onto ``target``.
    verdict : mapping, optional
        The fields shown as the verdict (a registration report); default: from ``result``.
    name : str
        Name of the registration in the page. Default ``'registration'``.
    view, up, max_display_triangles, title, overwrite :
        As in :func:`write_model_explorer`.

    Returns
    -------
    str
        The path written.

    Raises
    ------
    TypeError
        If ``result`` is not an elastic registration result.
    ValueError
        If ``result`` does not have ``source``'s vertices, or for a bad ``view``, ``up`` or
        ``max_display_triangles``.
    """
    if not isinstance(result, ElasticRegistrationResult):
        raise TypeError(
            f"`result` must be an ElasticRegistrationResult, got {type(result).__name__}"
        )
    vertices, faces = as_mesh_arrays(source, "source")
    target_arrays = as_mesh_arrays(target, "target")
    max_triangles = _check_triangles(max_display_triangles)
    registered = np.asarray(result.vertices)
    if registered.shape != vertices.shape:
        raise ValueError(
            f"`result` must hold the {vertices.shape[0]} vertices of `source`, got "
            f"{registered.shape[0]}"
        )
    if verdict is None:
        verdict = {
            "success": result.success,
            "message": result.message,
            "distances": result.distances.as_dict(),
            "min_jacobian_determinant": result.min_jacobian_determinant,
            "flipped_triangles": result.flipped_triangles,
        }
        # A verdict of the result's own, where it has one.
        for key in ("status", "warnings"):
            if getattr(result, key, None) is not None:
                verdict[key] = getattr(result, key)
    rigid = apply_transformation(np.asarray(result.transformation), vertices)
    case = _case(
        name,
        _verdict(verdict),
        registered=registered,
        faces=faces,
        target=target_arrays,
        template=rigid,
        max_triangles=max_triangles,
    )
    data = {
        "title": title or f"o3dreg registration: {name}",
        "rotation": view_rotation(view, up),
        "model": None,
        "cases": [case],
        "notes": ["Distances in the input's units (mm), in the target's frame."],
    }
    return atomic_write_text(path, _page(data), overwrite=overwrite)
