"""Landmark files: CSV, 3D Slicer markups (``.mrk.json``, ``.fcsv``) and MeshLab picked points
(``.pp``), with the RAS / LPS conventions of each.

o3dreg's meshes are in **LPS** patient coordinates (x to the patient's left, y posterior, z
superior: DICOM's and ITK's convention, what :func:`o3dreg.read_volume` returns). 3D Slicer's
world is RAS (x right, y anterior); Slicer writes either system and says which. RAS and LPS
differ by the sign of x and y. Reading converts the points to ``coordinate_system`` (LPS by
default) when the file says which system it is in:

=================== ========================================================================
format              how the file says its system
=================== ========================================================================
``.mrk.json``       the point list's ``coordinateSystem`` (``"LPS"`` or ``"RAS"``; absent
                    means LPS, as Slicer reads it)
``.fcsv``           ``# CoordinateSystem = LPS`` / ``RAS`` (or ``1`` / ``0``, Slicer 4.x);
                    absent: Slicer before 4.11 wrote RAS and no line, so RAS is assumed,
                    with a warning
``.csv``            column names ``l,p,s`` or ``r,a,s`` (as Slicer's markups CSV export
                    writes them); ``x,y,z`` or no header (statismo's ``label,x,y,z``
                    rows) says nothing: the points are taken as they are, with a warning
``.pp`` (MeshLab)   never (points are in the picked mesh's coordinates): taken as they are,
                    with a warning
``.json`` (scalismo) never (a list of ``{"id", "coordinates"}``, in the mesh's coordinates):
                    taken as they are, with a warning
=================== ========================================================================

``file_coordinate_system`` tells the system of a file that does not say (and silences the
warning). Writing declares the system wherever the format can: ``.mrk.json`` and ``.fcsv`` in
LPS, CSV as ``label,l,p,s`` (or ``r,a,s``), ``.pp`` in the points' own system.
"""

from __future__ import annotations

import csv
import datetime
import io
import json
import os
import warnings
from collections.abc import Iterable, Sequence
from typing import Any
from xml.etree import ElementTree
from xml.sax.saxutils import quoteattr

import numpy as np

from .._validation import as_points, named_as
from .mesh import atomic_write_text
from .units import millimetres_per_unit

__all__ = ["LANDMARK_SUFFIXES", "check_landmark_suffix", "read_landmarks", "write_landmarks"]

#: Landmark file suffixes read and written.
LANDMARK_SUFFIXES = (".csv", ".mrk.json", ".json", ".fcsv", ".pp")

_SYSTEMS = ("LPS", "RAS")
_FLIP = np.array([-1.0, -1.0, 1.0])  # RAS <-> LPS
_SCHEMA = (
    "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
    "Resources/Schema/markups-schema-v1.0.3.json#"
)
_FCSV_COLUMNS = "id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID"


def check_landmark_suffix(path: str, name: str) -> str:
    """The landmark format suffix of ``path``; ``ValueError`` naming ``name`` otherwise."""
    low = path.lower()
    for suffix in LANDMARK_SUFFIXES:
        if low.endswith(suffix):
            return suffix
    raise ValueError(f"`{name}` must end with one of {', '.join(LANDMARK_SUFFIXES)}, got {path!r}")


def select_labels(
    available: Sequence[str], labels: Any, where: str, name: str = "labels"
) -> list[int]:
    """Indices into ``available`` (a file's landmark labels) of the chosen ``labels``, in their
    order; every index when ``labels`` is ``None``.

    ``where`` names the file in the messages (``"'lm.fcsv'"``), ``name`` the parameter.
    ``TypeError`` unless ``labels`` is ``None`` or a sequence of str; ``ValueError`` for no
    label, a repeated label, or a label the file does not hold (naming the file's labels and
    the ones received), or a chosen label the file holds twice.
    """
    if labels is None:
        return list(range(len(available)))
    if isinstance(labels, (str, bytes)) or not isinstance(labels, Iterable):
        raise TypeError(
            f"`{name}` must be a sequence of landmark labels, got {type(labels).__name__}"
            + (f" {labels!r} (write [{labels!r}])" if isinstance(labels, str) else "")
        )
    chosen = list(labels)
    wrong = [type(lab).__name__ for lab in chosen if not isinstance(lab, str)]
    if wrong:
        raise TypeError(f"`{name}` must be landmark labels (str), got {', '.join(wrong)}")
    if not chosen:
        raise ValueError(f"`{name}` must name at least one landmark, got none")
    repeated = sorted({lab for lab in chosen if chosen.count(lab) > 1})
    if repeated:
        raise ValueError(f"`{name}` repeats {repeated}")
    unknown = [lab for lab in chosen if lab not in available]
    if unknown:
        raise ValueError(
            f"`{name}` must name landmarks of {where}, which holds {', '.join(available)}; "
            f"got {', '.join(chosen)}: {', '.join(map(repr, unknown))} "
            f"{'is' if len(unknown) == 1 else 'are'} not in it"
        )
    # A label the file holds twice is ambiguous only where it is chosen.
    twice = sorted({lab for lab in chosen if list(available).count(lab) > 1})
    if twice:
        raise ValueError(
            f"`{name}` must name landmarks {where} holds once; got {', '.join(chosen)}: "
            f"{', '.join(map(repr, twice))} {'is' if len(twice) == 1 else 'are'} there twice"
        )
    index = {lab: k for k, lab in enumerate(available)}
    return [index[lab] for lab in chosen]


def _system(value: Any, name: str, *, allow_none: bool = False) -> str:
    """``'LPS'`` or ``'RAS'`` (any case); ``''`` for ``None`` when ``allow_none``."""
    if value is None and allow_none:
        return ""
    if not isinstance(value, str) or value.upper() not in _SYSTEMS:
        expected = "'LPS' or 'RAS'" + (" or None" if allow_none else "")
        raise ValueError(f"`{name}` must be {expected}, got {value!r}")
    return value.upper()


def read_landmarks(
    path: str | os.PathLike[str],
    *,
    coordinate_system: str = "LPS",
    file_coordinate_system: str | None = None,
    name: str = "path",
) -> tuple[tuple[str, ...], np.ndarray]:
    """Read labelled 3D points from CSV, 3D Slicer (``.mrk.json``, ``.fcsv``) or MeshLab (``.pp``).

    Parameters
    ----------
    path : str or path-like
        ``.csv`` with a header row naming a ``label`` column and the coordinates ``l,p,s``,
        ``r,a,s`` or ``x,y,z`` (other columns ignored), or rows ``label,x,y,z`` without a
        header (statismo's and scalismo's landmark files); a Slicer markups file ``.mrk.json``
        or ``.fcsv`` (the fields its ``# columns`` line names); points Slicer marks undefined,
        preview or missing (not placed; in a CSV, ``defined`` 0) are skipped with a
        ``UserWarning`` naming them; a MeshLab picked-points file ``.pp`` (inactive points
        skipped). A ``.mrk.json`` gives the ``controlPoints`` of its one point list (markup
        ``type`` ``"Fiducial"``; a markup without a type is taken as one), in mm (converted
        from ``coordinateUnits`` ``um``, ``cm`` or ``m``). Other markups beside it (lines,
        angles, curves, planes, ROIs) are ignored with a ``UserWarning``; a file with several
        point lists or none raises ``ValueError`` listing its markups (name, type, number of
        control points): the control points of a line or angle are its ends and vertex, not
        landmarks, and point lists are not merged. A ``.json`` holding a list of
        ``{"id": ..., "coordinates": [x, y, z]}`` is scalismo's landmark file (its
        ``LandmarkIO.writeLandmarksJson``, Scalismo UI's save), which does not say its system.
    coordinate_system : {'LPS', 'RAS'}, optional
        System of the points returned. Default ``'LPS'``, the system of o3dreg's meshes.
    file_coordinate_system : {'LPS', 'RAS'}, optional
        System of a file that does not say which it is in (``x,y,z`` CSV, ``.pp``, scalismo's
        ``.json``, ``.fcsv`` without a ``CoordinateSystem`` line). Default: such a file is
        taken to be in ``coordinate_system`` (an ``.fcsv``: RAS) and a ``UserWarning`` says
        so. A file that says otherwise raises ``ValueError``.

    name : str, optional
        How messages name ``path`` (a command line passes its option). Default ``'path'``.

    Returns
    -------
    labels : tuple of str
    points : (l, 3) ndarray
        In ``coordinate_system``, in the file's units (mm for Slicer's files).
    """
    with named_as(name):
        return _read_landmarks(path, coordinate_system, file_coordinate_system)


def _read_landmarks(
    path: str | os.PathLike[str], coordinate_system: str, file_coordinate_system: str | None
) -> tuple[tuple[str, ...], np.ndarray]:
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    suffix = check_landmark_suffix(path, "path")
    target = _system(coordinate_system, "coordinate_system")
    assumed = _system(file_coordinate_system, "file_coordinate_system", allow_none=True)
    if not os.path.isfile(path):
        raise OSError(f"`path`: no such file {path!r}")
    try:
        if suffix == ".csv":
            labels, points, declared = _read_csv(path)
        elif suffix == ".fcsv":
            labels, points, declared = _read_fcsv(path)
        elif suffix == ".pp":
            labels, points, declared = _read_pp(path)
        else:
            labels, points, declared = _read_markups(path)
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"`path`: {path!r} is not UTF-8 text (byte {exc.object[exc.start]:#04x} at "
            f"{exc.start}): save it as UTF-8"
        ) from None
    if not points.shape[0]:
        raise ValueError(f"`path`: {path!r} holds no landmarks")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        which = ", ".join(repr(labels[i]) for i in np.flatnonzero(bad)[:5])
        raise ValueError(
            f"`path`: {path!r} holds NaN or infinite coordinates (landmarks {which}"
            f"{' ...' if bad.sum() > 5 else ''})"
        )
    if declared is not None and assumed and declared != assumed:
        raise ValueError(
            f"`file_coordinate_system` is {assumed!r} but {path!r} says its points are in "
            f"{declared}"
        )
    source = declared or assumed
    if not source:
        source = "RAS" if suffix == ".fcsv" else target
        why = (
            "an .fcsv without a CoordinateSystem line was written by Slicer < 4.11, in RAS"
            if suffix == ".fcsv"
            else "the file does not say"
        )
        warnings.warn(
            f"{path!r}: coordinate system not stated; taken as {source} ({why}). Pass "
            "file_coordinate_system='LPS' or 'RAS' to say which.",
            UserWarning,
            stacklevel=3,
        )
    if source != target:
        points = points * _FLIP
    return labels, points


def _numbers(values: list[str], path: str, where: str) -> list[float]:
    try:
        return [float(v) for v in values]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"`path`: {path!r} {where}: coordinates are not numbers") from exc


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _uncommented(lines: Any, *, keep_numbers: bool = True) -> Any:
    """The lines of a CSV file without its comment lines (``#`` first; scalismo's reader skips
    them too): each left empty, so that the rows keep their line numbers, or dropped (for a
    header row, which must come first)."""
    for line in lines:
        if not line.lstrip().startswith("#"):
            yield line
        elif keep_numbers:
            yield "\n"


def _read_headerless_csv(path: str) -> tuple[tuple[str, ...], np.ndarray, str | None]:
    """``label,x,y,z`` (or ``x,y,z``) rows without a header, as statismo and scalismo write
    landmarks; the file does not say its coordinate system."""
    labels: list[str] = []
    points: list[list[float]] = []
    width = 0
    with open(path, newline="", encoding="utf-8-sig") as fh:
        for number, row in enumerate(csv.reader(_uncommented(fh)), start=1):
            if not any(field.strip() for field in row):
                continue
            width = width or len(row)
            if len(row) != width:
                expected = "label,x,y,z" if width == 4 else "x,y,z"
                raise ValueError(
                    f"`path`: {path!r} line {number}: {expected} expected (a file without a "
                    f"header), got {len(row)} fields {row}"
                )
            points.append(_numbers(row[-3:], path, f"line {number}"))
            labels.append(
                row[0].strip() if len(row) == 4 and row[0].strip() else f"L{len(labels) + 1}"
            )
    return tuple(labels), np.array(points, dtype=np.float64).reshape(-1, 3), None


def _read_csv(path: str) -> tuple[tuple[str, ...], np.ndarray, str | None]:
    with open(path, newline="", encoding="utf-8-sig") as fh:
        rows = (row for row in csv.reader(_uncommented(fh)) if any(f.strip() for f in row))
        first = next(rows, [])
    if len(first) in (3, 4) and all(_is_number(v) for v in first[-3:]):
        return _read_headerless_csv(path)
    with open(path, newline="", encoding="utf-8-sig") as fh:
        reader = csv.DictReader(_uncommented(fh, keep_numbers=False))
        fields = [f.strip().lower() for f in (reader.fieldnames or [])]
        declared: str | None = None
        columns: tuple[str, ...] = ("x", "y", "z")
        for system in _SYSTEMS:
            if set(system.lower()) <= set(fields):
                declared, columns = system, tuple(system.lower())
                break
        else:
            if not set(columns) <= set(fields):
                raise ValueError(
                    f"`path`: {path!r} must have a header with columns l,p,s or r,a,s or x,y,z, "
                    f"got {fields}"
                )
        labels, points, skipped = [], [], []
        for k, row in enumerate(reader):
            row = {key.strip().lower(): value for key, value in row.items() if key}
            label = str(row.get("label") or "").strip() or f"L{k + 1}"
            # Slicer's control point export writes defined = 0 for a point not placed (its
            # coordinates are zeros, not a position), and its import takes 0 as undefined.
            if _is_false(row.get("defined")):
                skipped.append((label, "undefined"))
                continue
            points.append(_numbers([row[c] for c in columns], path, f"row {k + 2}"))
            labels.append(label)
    _skip_unplaced(path, skipped, 5)
    return tuple(labels), np.array(points, dtype=np.float64).reshape(-1, 3), declared


def _is_false(value: str | None) -> bool:
    """Whether a CSV flag (``1``/``0``, ``true``/``false``) is set to false; empty is not."""
    text = (value or "").strip().lower()
    if text in ("false", "no"):
        return True
    try:
        return float(text) == 0.0
    except ValueError:
        return False


def _fcsv_system(value: str, path: str) -> str:
    value = value.strip().upper()
    # Slicer 4.x wrote the enum: 0 = RAS, 1 = LPS.
    system = {"0": "RAS", "1": "LPS"}.get(value, value)
    if system not in _SYSTEMS:
        raise ValueError(f"`path`: {path!r} has CoordinateSystem {value!r}; LPS or RAS expected")
    return system


#: Slicer's control point states (``vtkMRMLMarkupsNode``: 0 undefined, 1 preview, 2 defined,
#: 3 missing); only defined points are placed landmarks.
_UNPLACED = {"0": "undefined", "1": "preview", "3": "missing"}


def _skip_unplaced(path: str, skipped: list[tuple[str, str]], stacklevel: int) -> None:
    if skipped:
        names = ", ".join(f"{label!r} ({status})" for label, status in skipped)
        warnings.warn(
            f"{path!r}: {len(skipped)} control point(s) not placed, skipped: {names}",
            UserWarning,
            stacklevel=stacklevel,
        )


def _read_fcsv(path: str) -> tuple[tuple[str, ...], np.ndarray, str | None]:
    """Slicer fiducials: the ``# columns`` line names the fields (Slicer 4-5:
    ``id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID``; Slicer 3:
    ``label,x,y,z,sel,vis``); Slicer 5 rows carry two more, ``positionStatus`` and
    ``autoCreated``, that the line does not name. Without the line, Slicer 4's columns."""
    declared = None
    columns: list[str] | None = None
    rows: list[tuple[int, str]] = []
    with open(path, newline="", encoding="utf-8-sig") as fh:
        for number, line in enumerate(fh, start=1):
            text = line.strip()
            if text.startswith("#"):
                key, _, value = text.lstrip("# ").partition("=")
                key = key.strip().lower()
                if key == "coordinatesystem":
                    declared = _fcsv_system(value, path)
                elif key == "columns":
                    columns = [c.strip().lower() for c in value.split(",")]
            elif text:
                rows.append((number, text))
    named = columns if columns is not None else _FCSV_COLUMNS.lower().split(",")
    missing = [c for c in ("x", "y", "z") if c not in named]
    if missing:
        raise ValueError(
            f"`path`: {path!r} has a columns line without {', '.join(missing)}: {columns}"
        )
    where = {c: named.index(c) for c in named}
    status_at = where.get("positionstatus")
    if status_at is None and named[-1:] == ["associatednodeid"]:
        status_at = len(named)  # Slicer 5: the first field after the named ones
    labels, points, skipped = [], [], []
    parsed = csv.reader(text for _, text in rows)
    for k, ((number, text), row) in enumerate(zip(rows, parsed)):
        # A row that ends before its last named column is cut (a file truncated inside its
        # last row): its numbers and its label cannot be trusted.
        if len(row) < len(named):
            raise ValueError(
                f"`path`: {path!r} line {number} is short: {len(named)} fields expected "
                f"({','.join(named)}), got {len(row)}: {text!r} (the file may be truncated)"
            )
        label = row[where["label"]].strip() if "label" in where else ""
        label = label or f"L{k + 1}"
        status = (
            row[status_at].strip().lower() if status_at is not None and status_at < len(row) else ""
        )
        status = _UNPLACED.get(status, status)
        if status in ("undefined", "preview", "missing"):
            skipped.append((label, status))
            continue
        points.append(_numbers([row[where[c]] for c in ("x", "y", "z")], path, f"line {number}"))
        labels.append(label)
    _skip_unplaced(path, skipped, 5)
    return tuple(labels), np.array(points, dtype=np.float64).reshape(-1, 3), declared


def _read_pp(path: str) -> tuple[tuple[str, ...], np.ndarray, str | None]:
    try:
        root = ElementTree.parse(path).getroot()
    except ElementTree.ParseError as exc:
        raise ValueError(f"`path`: {path!r} is not a MeshLab picked-points file ({exc})") from exc
    if root.tag != "PickedPoints":
        raise ValueError(f"`path`: {path!r} is not a MeshLab picked-points file (root {root.tag})")
    labels, points, skipped = [], [], 0
    for k, point in enumerate(root.iter("point")):
        if point.get("active", "1").strip() == "0":
            skipped += 1  # a template point not placed
            continue
        xyz = [point.get(c) for c in ("x", "y", "z")]
        points.append(_numbers([v if v is not None else "" for v in xyz], path, f"point {k + 1}"))
        labels.append(str(point.get("name") or "").strip() or f"L{k + 1}")
    if skipped:
        warnings.warn(f"{path!r}: {skipped} inactive point(s) skipped", UserWarning, stacklevel=4)
    return tuple(labels), np.array(points, dtype=np.float64).reshape(-1, 3), None


def _markup_summary(index: int, markup: Any) -> str:
    """``markups[i] 'name' (Type, n control points)``, for messages."""
    if not isinstance(markup, dict):
        return f"markups[{index}] ({type(markup).__name__}, not a markup)"
    name = markup.get("name")
    named = f" {str(name)!r}" if name else ""
    control = markup.get("controlPoints")
    count = len(control) if isinstance(control, list) else 0
    kind = markup.get("type", "no type")
    return f"markups[{index}]{named} ({kind}, {count} control point(s))"


def _is_point_list(markup: Any) -> bool:
    # Slicer writes "Fiducial" for a point list. A markup without a type (Slicer requires one)
    # names no other kind: its points are taken as landmarks (hand-written files omit it).
    return isinstance(markup, dict) and str(markup.get("type", "Fiducial")).lower() == "fiducial"


def _choose_point_list(doc: Any, path: str) -> dict[str, Any]:
    """The one point list of a markups file; other markups beside it ignored with a warning."""
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list) or not markups:
        got = "an empty list" if markups == [] else type(markups).__name__
        raise ValueError(
            f"`path`: {path!r} is not a 3D Slicer markups file (a non-empty `markups` list "
            f"expected, got {got if markups is not None else 'none'})"
        )
    lists = [k for k, m in enumerate(markups) if _is_point_list(m)]
    held = ", ".join(_markup_summary(k, m) for k, m in enumerate(markups))
    if not lists:
        raise ValueError(
            f"`path`: {path!r} holds {held} and no point list (markup type 'Fiducial'): the "
            "control points of a line, angle, curve, plane or ROI are not landmarks; place the "
            "landmarks in a Slicer point list and save that"
        )
    if len(lists) > 1:
        raise ValueError(
            f"`path`: {path!r} holds {len(lists)} point lists: {held}; one point list per file "
            "is read (mixing them would pair landmarks of different lists): save the one "
            "wanted in a file of its own (Slicer saves each markups node to its own .mrk.json)"
        )
    if len(markups) > 1:
        others = ", ".join(_markup_summary(k, m) for k, m in enumerate(markups) if k != lists[0])
        warnings.warn(
            f"{path!r}: read the point list {_markup_summary(lists[0], markups[lists[0]])}; "
            f"ignored {others} (not point lists)",
            UserWarning,
            stacklevel=5,
        )
    return markups[lists[0]]


def _units_to_mm(markup: dict[str, Any], path: str) -> float:
    """The factor from a markup's ``coordinateUnits`` (absent: mm) to millimetres."""
    units = markup.get("coordinateUnits", "mm")
    # A coded entry [code, coding scheme, meaning], e.g. ["mm", "UCUM", "millimeter"].
    code = units[0] if isinstance(units, list) and units else units
    factor = millimetres_per_unit(code)
    if factor is None:
        raise ValueError(
            f"`path`: {path!r} has coordinateUnits {units!r}; a length unit (mm, um, cm, m) "
            "expected"
        )
    return factor


def _read_markups(path: str) -> tuple[tuple[str, ...], np.ndarray, str | None]:
    try:
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
    except json.JSONDecodeError as exc:
        raise ValueError(f"`path`: {path!r} is not a 3D Slicer markups file: {exc}") from exc
    if isinstance(doc, list):
        return _read_scalismo_json(doc, path)
    markup = _choose_point_list(doc, path)
    scale = _units_to_mm(markup, path)
    try:
        control = markup.get("controlPoints") or []
        # Slicer reads a markup without coordinateSystem as LPS.
        declared = str(markup.get("coordinateSystem") or "LPS").upper()
        labels, points, skipped = [], [], []
        for k, p in enumerate(control):
            label = str(p.get("label") or "").strip() or f"L{k + 1}"
            status = str(p.get("positionStatus", "defined")).lower()
            # An unplaced point: "position" absent or "" (Slicer writes "" with
            # positionStatus "undefined"), or a status other than defined.
            if status in ("undefined", "preview", "missing") or p.get("position") in (None, ""):
                skipped.append((label, status if status != "defined" else "no position"))
                continue
            position = [float(c) for c in p["position"]]
            if len(position) != 3:
                raise ValueError(f"control point {k + 1} has {len(position)} coordinates")
            points.append(position)
            labels.append(label)
        points_arr = np.array(points, dtype=np.float64).reshape(-1, 3)
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
        raise ValueError(
            f"`path`: {path!r} is not a 3D Slicer markups file "
            f"(controlPoints[i].position expected): {exc}"
        ) from exc
    if declared not in _SYSTEMS:
        raise ValueError(f"`path`: {path!r} has coordinateSystem {declared!r}; LPS or RAS expected")
    _skip_unplaced(path, skipped, 5)
    if scale != 1.0:
        points_arr = points_arr * scale
    return tuple(labels), points_arr, declared


def _read_scalismo_json(doc: list[Any], path: str) -> tuple[tuple[str, ...], np.ndarray, None]:
    """scalismo's landmark file (``LandmarkIO.writeLandmarksJson``, what Scalismo UI saves): a
    list of ``{"id": ..., "coordinates": [x, y, z]}`` (``description`` and ``uncertainty``
    ignored), in the coordinates of the mesh it was placed on; the file does not say which
    system that is."""
    labels, points = [], []
    for k, entry in enumerate(doc):
        coordinates = entry.get("coordinates") if isinstance(entry, dict) else None
        try:
            position = [float(c) for c in coordinates]  # type: ignore[union-attr]
        except (TypeError, ValueError):
            position = []
        if len(position) != 3:
            raise ValueError(
                f"`path`: {path!r} is a list, read as a scalismo landmark file; its entry {k + 1} "
                f"is not {{'id': ..., 'coordinates': [x, y, z]}}: {str(entry)[:80]}"
            )
        points.append(position)
        labels.append(str(entry.get("id") or "").strip() or f"L{k + 1}")
    return tuple(labels), np.array(points, dtype=np.float64).reshape(-1, 3), None


def write_landmarks(
    path: str | os.PathLike[str],
    labels: Any,
    points: Any,
    *,
    overwrite: bool = False,
    coordinate_system: str = "LPS",
) -> str:
    """Write labelled points, atomically, saying their coordinate system where the format can.

    Parameters
    ----------
    path : str or path-like
        ``.csv`` (``label,l,p,s`` or ``label,r,a,s``), ``.mrk.json`` (a Slicer point list, LPS),
        ``.fcsv`` (Slicer fiducials, ``# CoordinateSystem = LPS``) or ``.pp`` (MeshLab picked
        points, in the points' system: the format cannot say).
    labels : sequence of str or None
        Default ``L1, L2, ...``.
    points : (l, 3) array_like
    overwrite : bool, optional
    coordinate_system : {'LPS', 'RAS'}, optional
        System of ``points``. Default ``'LPS'`` (o3dreg's meshes).

    Returns
    -------
    str
        The path written.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`path` must be a path, got {type(path).__name__}")
    path = os.fspath(path)
    suffix = check_landmark_suffix(path, "path")
    system = _system(coordinate_system, "coordinate_system")
    pts = as_points(points, "points")
    if labels is None:
        labels_ = tuple(f"L{i + 1}" for i in range(pts.shape[0]))
    else:
        if isinstance(labels, (str, bytes)) or not isinstance(labels, (list, tuple, np.ndarray)):
            raise TypeError(
                f"`labels` must be a sequence of {pts.shape[0]} labels, got {type(labels).__name__}"
            )
        labels_ = tuple(str(x) for x in labels)
        broken = [lab for lab in labels_ if "\n" in lab or "\r" in lab]
        if broken and suffix == ".fcsv":  # Slicer's reader takes a line per point
            raise ValueError(f"`labels` must be single lines in an .fcsv, got {broken[0]!r}")
        if len(labels_) != pts.shape[0]:
            raise ValueError(f"`labels` must hold {pts.shape[0]} labels, got {len(labels_)}")
    lps = pts if system == "LPS" else pts * _FLIP
    if suffix == ".csv":
        text = _csv_text(labels_, pts, system)
    elif suffix == ".fcsv":
        text = _fcsv_text(labels_, lps)
    elif suffix == ".pp":
        text = _pp_text(labels_, pts)
    else:
        text = _markups_text(labels_, lps)
    return atomic_write_text(path, text, overwrite=overwrite)


def _csv_text(labels: tuple[str, ...], points: np.ndarray, system: str) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["label", *system.lower()])
    for label, p in zip(labels, points):
        writer.writerow([label, *(repr(float(c)) for c in p)])
    return buf.getvalue()


def _fcsv_text(labels: tuple[str, ...], lps: np.ndarray) -> str:
    buf = io.StringIO()
    buf.write("# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n")
    buf.write(f"# columns = {_FCSV_COLUMNS}\n")
    writer = csv.writer(buf, lineterminator="\n")
    for k, (label, p) in enumerate(zip(labels, lps)):
        xyz = [repr(float(c)) for c in p]
        writer.writerow([str(k + 1), *xyz, 0, 0, 0, 1, 1, 1, 0, label, "", ""])
    return buf.getvalue()


def _pp_text(labels: tuple[str, ...], points: np.ndarray) -> str:
    now = datetime.datetime.now()
    lines = [
        "<!DOCTYPE PickedPoints>",
        "<PickedPoints>",
        " <DocumentData>",
        f'  <DateTime time="{now:%H:%M:%S}" date="{now:%Y-%m-%d}"/>',
        '  <User name="o3dreg"/>',
        '  <DataFileName name=""/>',
        '  <templateName name=""/>',
        " </DocumentData>",
    ]
    for label, p in zip(labels, points):
        x, y, z = (repr(float(c)) for c in p)
        lines.append(f' <point x="{x}" y="{y}" z="{z}" active="1" name={quoteattr(label)}/>')
    lines.append("</PickedPoints>")
    return "\n".join(lines) + "\n"


def _markups_text(labels: tuple[str, ...], lps: np.ndarray) -> str:
    doc = {
        "@schema": _SCHEMA,
        "markups": [
            {
                "type": "Fiducial",
                "coordinateSystem": "LPS",
                "coordinateUnits": "mm",
                "controlPoints": [
                    {
                        "id": str(k + 1),
                        "label": label,
                        "position": [float(c) for c in p],
                        "positionStatus": "defined",
                    }
                    for k, (label, p) in enumerate(zip(labels, lps))
                ],
            }
        ],
    }
    return json.dumps(doc, indent=2) + "\n"
