"""Isosurfaces of volumes: marching cubes to an Open3D triangle mesh in world millimetres."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import open3d as o3d
from skimage.measure import marching_cubes

from .._validation import check_bool, check_positive
from ..io.mesh import to_open3d
from .volume import Volume

__all__ = ["isosurface"]

logger = logging.getLogger("o3dreg")

# Planes scanned at once when computing the data range and the crop box: bounds the temporary
# boolean masks to a few megabytes whatever the volume size.
_CHUNK_VOXELS = 1 << 22


def isosurface(
    volume: Volume,
    level: float,
    *,
    step_size: int = 1,
    crop: bool = True,
    close_boundary: bool = True,
) -> o3d.geometry.TriangleMesh:
    """Extract the surface ``volume == level`` with marching cubes, in world millimetres.

    The inside of the surface is where ``volume >= level`` (bone above a Hounsfield threshold,
    1 in a 0/1 mask at level 0.5). Triangles are oriented outwards: the normals point from high
    to low values and the signed volume of a closed surface is positive.

    Parameters
    ----------
    volume : Volume
        The scan or mask; spacing, origin and direction are honoured (see :class:`Volume`).
    level : float
        The iso-value, in the volume's units (HU for CT, e.g. 300-400 for bone; 0.5 for masks).
    step_size : int, optional
        Marching-cubes step in voxels; larger is coarser and faster. Default 1.
    crop : bool, optional
        Run marching cubes only on the bounding box of the voxels ``>= level`` plus a margin of
        ``step_size`` voxels (time and memory scale with the object, not the scan). With
        ``step_size=1`` the result is the same; with a larger step the samples start elsewhere,
        so the coarse surface differs slightly (both closed).
        Default ``True``.
    close_boundary : bool, optional
        Pad the (cropped) volume below ``level`` (one voxel before, ``step_size`` after) so
        that an object cut by the border of the scan gives a closed surface, capped at the
        border. Default ``True``.

    Returns
    -------
    mesh : open3d.geometry.TriangleMesh
        Vertices ``(n, 3)`` in world (x, y, z) millimetres, triangles ``(m, 3)``.

    Raises
    ------
    TypeError
        ``volume`` is not a :class:`Volume`, or ``level`` is not a number.
    ValueError
        ``level`` or the data is not finite; the volume has fewer than 2 voxels along an axis
        (a 2D image has no surface).
    RuntimeError
        ``level`` is outside the data range: no surface found.

    Notes
    -----
    Memory: the volume is never copied as a whole. The data range and the crop box are computed
    a few planes at a time; marching cubes then converts only the cropped box to float32 (as
    scikit-image does). Uses :func:`skimage.measure.marching_cubes` (Lewiner et al., 2003,
    doi:10.1080/10867651.2003.10487582).

    Examples
    --------
    >>> import numpy as np
    >>> z, y, x = np.mgrid[:20, :20, :20]
    >>> ball = ((x - 10) ** 2 + (y - 10) ** 2 + (z - 10) ** 2 < 36).astype(np.uint8)
    >>> mesh = isosurface(Volume(ball, spacing=(1, 1, 1)), 0.5)
    >>> mesh.is_watertight()
    True
    """
    if not isinstance(volume, Volume):
        raise TypeError(f"`volume` must be an o3dreg.Volume, got {type(volume).__name__}")
    if isinstance(level, bool) or not isinstance(level, (int, float, np.integer, np.floating)):
        raise TypeError(f"`level` must be a number, got {type(level).__name__}")
    if not np.isfinite(level):
        raise ValueError(f"`level` must be finite, got {level!r}")
    step = check_positive(step_size, "step_size", integer=True)
    if min(volume.shape) < 2:
        raise ValueError(
            f"`volume` must have at least 2 voxels along every axis, got shape {volume.shape}: "
            "a 2D image has no surface"
        )
    crop = check_bool(crop, "crop")
    close_boundary = check_bool(close_boundary, "close_boundary")
    return _isosurface(volume, float(level), step, crop, close_boundary)


def _isosurface(
    volume: Volume, level: float, step: int, crop: bool, close_boundary: bool
) -> o3d.geometry.TriangleMesh:
    array = volume.array
    low, high, lo, hi = _scan(array, level)
    if not low < level < high or lo is None or hi is None:
        raise RuntimeError(
            f"no surface found at level {level:g}: data range is [{_fmt(low)}, {_fmt(high)}] "
            "(the level must lie strictly between the lowest and the highest value)"
        )
    limit = float(np.finfo(np.float32).max)
    if max(abs(low), abs(high)) > limit:
        # Marching cubes works in float32: such values become inf and the surface NaN.
        raise ValueError(
            f"`volume` values must fit in float32 (|x| <= {limit:.3g}) for marching cubes, got "
            f"a range [{_fmt(low)}, {_fmt(high)}]: rescale the volume"
        )
    if crop:
        # A sample below the level on each side: marching cubes with a step samples every
        # step-th voxel from the box's first one, so the far side needs a margin of a step
        # (with one voxel, a step of 3 left a ball's far side open).
        start = np.maximum(lo - step, 0)
        stop = np.minimum(hi + 1 + step, array.shape)
    else:
        start = np.zeros(3, dtype=np.int64)
        stop = np.asarray(array.shape)
    sub = array[start[0] : stop[0], start[1] : stop[1], start[2] : stop[2]]
    offset = start.astype(np.float64)
    if close_boundary:
        touches = (start == 0) | (stop == np.asarray(array.shape))
        # The first sample is the low pad; the last falls within a step of the end.
        pad = [(int(t), int(t) * step) for t in touches]
        if any(touches):
            # One voxel below the level around the box closes objects cut by the scan border.
            fill = np.float32(low)
            sub = np.pad(sub.astype(np.float32, copy=False), pad, constant_values=fill)
            offset -= np.array([p[0] for p in pad], dtype=np.float64)
    if min(sub.shape) < 2:
        raise RuntimeError(
            f"no surface found at level {level:g}: the voxels >= level form a single layer "
            f"of shape {sub.shape} at the border of the volume (try close_boundary=True)"
        )
    try:
        verts, faces, _, _ = marching_cubes(
            sub, level, step_size=step, allow_degenerate=False, method="lewiner"
        )
    except (ValueError, RuntimeError) as exc:
        if step > 1 and step >= int(min(hi - lo + 1)) // 2 + 1:
            # The step, not the level, leaves marching cubes too few samples.
            raise RuntimeError(
                f"no surface found with step_size={step}: the object spans "
                f"{tuple(int(n) for n in hi - lo + 1)} "
                "voxels, too few for that step; use a smaller step"
            ) from exc
        raise RuntimeError(f"no surface found at level {level:g}: {exc}") from exc
    del sub
    index = verts.astype(np.float64) + offset
    points = volume.index_to_world(index)
    faces = np.asarray(faces, dtype=np.int64)
    # scikit-image winds triangles inward in (plane, row, column) index space for bright
    # objects; the index -> world map may preserve or reverse orientation.
    linear = (volume.direction * volume.spacing[::-1])[:, ::-1]  # acting on (p, r, c)
    if np.linalg.det(linear) > 0:
        faces = faces[:, ::-1]
    mesh = to_open3d(points, faces)
    logger.info(
        "isosurface at level %g: %d vertices, %d triangles (box %s..%s of %s)",
        level,
        len(points),
        len(faces),
        start.tolist(),
        stop.tolist(),
        list(array.shape),
    )
    return mesh


def _fmt(value: float) -> str:
    return f"{value:g}"


def _scan(array: np.ndarray, level: float) -> tuple[float, float, Any, Any]:
    """Data range, and the index bounding box ``[lo, hi]`` of voxels ``>= level``, chunkwise.

    Raises ``ValueError`` on NaN or infinite values.
    """
    planes = max(1, _CHUNK_VOXELS // max(1, array.shape[1] * array.shape[2]))
    low, high = np.inf, -np.inf
    any_p = np.zeros(array.shape[0], dtype=bool)
    any_r = np.zeros(array.shape[1], dtype=bool)
    any_c = np.zeros(array.shape[2], dtype=bool)
    floating = np.issubdtype(array.dtype, np.floating)
    for p0 in range(0, array.shape[0], planes):
        chunk = array[p0 : p0 + planes]
        if floating:
            finite = np.isfinite(chunk)
            if not finite.all():
                bad = int(chunk.size - np.count_nonzero(finite))
                raise ValueError(
                    f"`volume` must hold finite values, got {bad} NaN or infinite voxel(s) "
                    f"in planes {p0}..{p0 + chunk.shape[0] - 1}"
                )
        low = min(low, float(chunk.min()))
        high = max(high, float(chunk.max()))
        inside = chunk >= level
        any_p[p0 : p0 + chunk.shape[0]] = inside.any(axis=(1, 2))
        any_r |= inside.any(axis=(0, 2))
        any_c |= inside.any(axis=(0, 1))
    if not any_p.any():
        return low, high, None, None
    bounds = [np.flatnonzero(a) for a in (any_p, any_r, any_c)]
    lo = np.array([b[0] for b in bounds], dtype=np.int64)
    hi = np.array([b[-1] for b in bounds], dtype=np.int64)
    return low, high, lo, hi
