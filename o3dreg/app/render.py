"""Headless pictures of meshes coloured by a scalar (distances, errors), written as PNG.

Two back ends: matplotlib's :class:`~mpl_toolkits.mplot3d.art3d.Poly3DCollection` with shaded
per-face colours (the default: about a second a picture, on any machine), and Open3D's
:class:`open3d.visualization.rendering.OffscreenRenderer` (Filament). Without a GPU, Filament runs
on Mesa's software Vulkan (``llvmpipe``), where it took 3-30 s a picture and sometimes never
returned (killed after 120 s on a 2.5k-vertex mesh), so it runs in a child process under a time
limit; ``backend='auto'`` tries it and falls back to matplotlib.
"""

from __future__ import annotations

import atexit
import logging
import os
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from typing import Any

import numpy as np
import open3d as o3d
from open3d.visualization import rendering

from .._validation import as_mesh_arrays
from ..io.mesh import atomic_write
from ..registration.elastic import vertex_normals

# matplotlib is imported inside the functions that draw: ~1 s to import, for pictures only.

__all__ = [
    "BACKENDS",
    "OPEN3D_TIME_LIMIT",
    "mode_displacements",
    "render_mesh",
    "render_shape_modes",
]

logger = logging.getLogger("o3dreg")

#: Values accepted by ``render_mesh(backend=...)``.
BACKENDS = ("matplotlib", "open3d", "auto")

#: Seconds Open3D's renderer is given (in a child process) before it is stopped.
OPEN3D_TIME_LIMIT = 60.0

# One Filament renderer per process, of a fixed size: creating several in a process is slow and
# unreliable, so it is reused with its scene cleared, and its picture is scaled into the figure.
_CANVAS = (640, 480)
_RENDERER: list[Any] = []
_OPEN3D_FAILED: list[str] = []


def _release_renderer() -> None:
    # Filament aborts at exit when a renderer is destroyed with geometry still in its scene.
    while _RENDERER:
        renderer = _RENDERER.pop()
        renderer.scene.clear_geometry()
        del renderer


def _check_view(view: Any) -> tuple[float, float]:
    try:
        az, el = (float(v) for v in view)
    except (TypeError, ValueError):
        raise ValueError(f"`view` must be (azimuth, elevation) in degrees, got {view!r}") from None
    return az, el


def _check_up(up: Any) -> np.ndarray:
    """``up`` as a unit (3,) vector."""
    up_ = np.asarray(up, dtype=np.float64)
    if up_.shape != (3,) or not np.isfinite(up_).all() or np.linalg.norm(up_) == 0:
        raise ValueError(f"`up` must be a non-zero (3,) vector, got {up!r}")
    return up_ / np.linalg.norm(up_)


def _horizontal_axes(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``e1, e2`` with ``(e1, e2, up)`` orthonormal: the frame both renderers place views in."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def _camera(
    vertices: np.ndarray, view: tuple[float, float], up: np.ndarray, fov: float
) -> tuple[np.ndarray, np.ndarray]:
    """Eye and centre looking at the bounding box from (azimuth, elevation) about ``up``."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre = (lo + hi) / 2.0
    radius = max(float(np.linalg.norm(hi - lo)) / 2.0, 1e-9)
    e1, e2 = _horizontal_axes(up)
    az, el = np.radians(view[0]), np.radians(view[1])
    direction = np.cos(el) * (np.cos(az) * e2 + np.sin(az) * e1) + np.sin(el) * up
    distance = 0.85 * radius / np.sin(np.radians(fov) / 2.0)
    return centre + distance * direction, centre


def view_rotation(view: Sequence[float], up: Sequence[float]) -> list[float]:
    """The world -> camera rotation of ``(azimuth, elevation)`` about ``up``, row-major.

    Rows: the camera's right, up (``up`` as seen on screen) and back (towards the viewer)
    directions, as :func:`render_mesh` places its camera.
    """
    up_ = _check_up(up)
    unit = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    eye, centre = _camera(unit, _check_view(view), up_, 35.0)
    back = (eye - centre) / np.linalg.norm(eye - centre)
    screen_up = up_ - (up_ @ back) * back
    screen_up /= np.linalg.norm(screen_up)
    right = np.cross(screen_up, back)
    return [float(v) for v in np.stack([right, screen_up, back]).ravel()]


def _colours(
    scalars: np.ndarray | None, cmap: str, vmin: float | None, vmax: float | None
) -> tuple[np.ndarray | None, float, float]:
    if scalars is None:
        return None, 0.0, 1.0
    import matplotlib

    finite = scalars[np.isfinite(scalars)]
    lo = float(finite.min()) if vmin is None and finite.size else (vmin or 0.0)
    hi = float(finite.max()) if vmax is None and finite.size else (vmax or 1.0)
    if hi <= lo:
        hi = lo + 1.0
    rgb = matplotlib.colormaps[cmap](np.clip((scalars - lo) / (hi - lo), 0.0, 1.0))[:, :3]
    return rgb, lo, hi


def _render_open3d(
    vertices: np.ndarray,
    faces: np.ndarray,
    face_rgb: np.ndarray | None,
    vertex_rgb: np.ndarray | None,
    view: tuple[float, float],
    up: np.ndarray,
    size: tuple[int, int],
) -> np.ndarray:
    if face_rgb is not None:
        # Per-face colours need unshared vertices.
        vertices, faces = vertices[faces].reshape(-1, 3), np.arange(faces.size).reshape(-1, 3)
        vertex_rgb = np.repeat(face_rgb, 3, axis=0)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces.astype(np.int32))
    )
    mesh.compute_vertex_normals()
    mesh.vertex_colors = o3d.utility.Vector3dVector(
        np.full_like(vertices, 0.75) if vertex_rgb is None else vertex_rgb
    )
    if not _RENDERER:
        _RENDERER.append(rendering.OffscreenRenderer(*_CANVAS))
        atexit.register(_release_renderer)
    renderer = _RENDERER[0]
    scene = renderer.scene
    scene.clear_geometry()
    scene.set_background([1.0, 1.0, 1.0, 1.0])
    material = rendering.MaterialRecord()
    material.shader = "defaultLit"
    scene.add_geometry("mesh", mesh, material)
    eye, centre = _camera(vertices, view, up, 40.0)
    renderer.setup_camera(40.0, centre, eye, up)
    return np.asarray(renderer.render_to_image())[..., :3]


def _open3d_worker(folder: str) -> None:
    """The child process's side of :func:`_render_open3d_limited`: ``args.npz`` -> ``image.npy``."""
    with np.load(os.path.join(folder, "args.npz")) as a:
        rgb = {k: (a[k] if a[k].size else None) for k in ("face_rgb", "vertex_rgb")}
        image = _render_open3d(
            a["vertices"],
            a["faces"],
            rgb["face_rgb"],
            rgb["vertex_rgb"],
            (float(a["view"][0]), float(a["view"][1])),
            a["up"],
            (int(a["size"][0]), int(a["size"][1])),
        )
    np.save(os.path.join(folder, "image.npy"), image)


_WORKER_ARGS = ("vertices", "faces", "face_rgb", "vertex_rgb", "view", "up", "size")


def _render_open3d_limited(args: tuple[Any, ...], time_limit: float | None) -> np.ndarray:
    """``_render_open3d(*args)``, in a child process stopped after ``time_limit`` seconds."""
    if time_limit is None:
        return _render_open3d(*args)
    # A fresh interpreter running only the renderer: a hung Filament cannot block this process,
    # and (unlike multiprocessing's "spawn") the caller's main script is not run again there.
    package_root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH")) if p)
    with tempfile.TemporaryDirectory(prefix="o3dreg-render-") as folder:
        arrays = {
            k: np.zeros(0) if v is None else np.asarray(v) for k, v in zip(_WORKER_ARGS, args)
        }
        np.savez(os.path.join(folder, "args.npz"), **arrays)  # type: ignore[arg-type]
        code = "import sys; from o3dreg.app import render; render._open3d_worker(sys.argv[1])"
        try:
            done = subprocess.run(
                [sys.executable, "-c", code, folder],
                env=env,
                capture_output=True,
                text=True,
                timeout=time_limit,
            )
        except subprocess.TimeoutExpired:  # the child has been killed
            raise RuntimeError(
                f"Open3D did not render within the time limit of {time_limit:g} s (no GPU? "
                "Filament on software Vulkan can hang); use backend='matplotlib'"
            ) from None
        out = os.path.join(folder, "image.npy")
        if done.returncode != 0 or not os.path.exists(out):
            tail = done.stderr.strip().splitlines()[-1:] or [""]
            raise RuntimeError(f"Open3D's renderer exited with status {done.returncode}: {tail[0]}")
        return np.load(out)


def _render_matplotlib(
    vertices: np.ndarray,
    faces: np.ndarray,
    face_rgb: np.ndarray | None,
    view: tuple[float, float],
    up: np.ndarray,
    size: tuple[int, int],
    frame: np.ndarray | None = None,
) -> np.ndarray:
    """Draw with matplotlib; ``frame`` (points) sets the box framed (default ``vertices``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    # Rotate so that ``up`` is matplotlib's z axis.
    e1, e2 = _horizontal_axes(up)
    # A right-handed frame (e2, -e1, up): (e2, e1, up) would mirror every picture.
    # The camera direction cos(az) e2 + sin(az) e1 of _camera is azimuth -az in this frame.
    basis = np.stack([e2, -e1, up], axis=1)
    pts = vertices @ basis
    tris = pts[faces]
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    az, el = np.radians(view[0]), np.radians(view[1])
    light = np.array([np.cos(el) * np.cos(az), -np.cos(el) * np.sin(az), np.sin(el)])
    shade = 0.35 + 0.65 * np.abs(normals @ light)
    base = np.full((faces.shape[0], 3), 0.75) if face_rgb is None else face_rgb
    dpi = 100
    fig = Figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    ax: Any = fig.add_axes((0.0, 0.0, 1.0, 1.0), projection="3d")
    ax.add_collection3d(Poly3DCollection(tris, facecolors=base * shade[:, None], linewidths=0))
    framed = pts if frame is None else frame @ basis
    lo, hi = framed.min(axis=0), framed.max(axis=0)
    half = (hi - lo).max() / 2.0
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), (lo + hi) / 2.0):
        setter(c - half, c + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=view[1], azim=-view[0])
    ax.set_axis_off()
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()  # type: ignore[attr-defined]
    return image


def render_mesh(
    mesh: Any,
    path: str | os.PathLike[str],
    *,
    scalars: Any = None,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
    view: Sequence[float] = (30.0, 20.0),
    up: Sequence[float] = (0.0, 0.0, 1.0),
    size: tuple[int, int] = (800, 600),
    title: str | None = None,
    label: str | None = None,
    backend: str = "matplotlib",
    time_limit: float | None = OPEN3D_TIME_LIMIT,
    overwrite: bool = True,
) -> str:
    """Render ``mesh``, optionally coloured by ``scalars``, to a PNG file, headless.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh or (vertices, faces)
        Not modified.
    path : str or os.PathLike
        The PNG to write (atomically: nothing is left there if rendering fails).
    scalars : (n,) or (m,) array_like, optional
        One value per vertex (``n``) or per face (``m``), mapped through ``cmap``; NaN is drawn
        at the bottom of the scale. Default: a uniform grey surface.
    cmap : str
        A matplotlib colormap name. Default ``'viridis'``.
    vmin, vmax : float, optional
        Colour scale limits. Default: the range of ``scalars``.
    view : (azimuth, elevation)
        Camera direction in degrees, about ``up``. Default ``(30, 20)``.
    up : (3,) array_like
        The world direction shown upwards. Default ``(0, 0, 1)`` (``(0, 1, 0)`` suits the bunny).
    size : (width, height)
        Image size in pixels. Default ``(800, 600)``.
    title : str, optional
        Drawn above the picture.
    label : str, optional
        Colour-bar label (a colour bar is drawn when ``scalars`` is given).
    backend : {'matplotlib', 'open3d', 'auto'}
        ``'matplotlib'`` (default) works on any machine in about a second. ``'open3d'`` uses
        Open3D's offscreen renderer (Filament: smoother shading, needs a Vulkan or EGL driver);
        ``'auto'`` tries Open3D and falls back to matplotlib when it fails or runs out of time
        (the fallback is logged, and later calls in the process go straight to matplotlib).
    time_limit : float or None
        Seconds Open3D's renderer may take, in a child process that is stopped after them
        (default :data:`OPEN3D_TIME_LIMIT`); ``None`` renders in this process with no limit
        (faster for many pictures, but a hung driver hangs the caller). Unused by matplotlib.
    overwrite : bool
        Replace an existing file. Default ``True``.

    Returns
    -------
    str
        The path written.

    Raises
    ------
    ValueError
        For a wrong ``scalars`` length, ``size``, ``view``, ``up`` or ``backend``.
    RuntimeError
        When ``backend='open3d'`` is requested and Open3D cannot render within ``time_limit``.
    """
    vertices, faces = as_mesh_arrays(mesh, "mesh")
    if backend not in BACKENDS:
        raise ValueError(f"`backend` must be one of {BACKENDS}, got {backend!r}")
    try:
        width, height = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"`size` must be (width, height) in pixels, got {size!r}") from None
    if width < 16 or height < 16:
        raise ValueError(f"`size` must be at least (16, 16) pixels, got {size!r}")
    view_ = _check_view(view)
    up_ = _check_up(up)
    if time_limit is not None and not (np.isfinite(time_limit) and time_limit > 0):
        raise ValueError(f"`time_limit` must be a positive number of seconds, got {time_limit!r}")
    values = None
    if scalars is not None:
        values = np.asarray(scalars, dtype=np.float64).ravel()
        if values.size not in (vertices.shape[0], faces.shape[0]):
            raise ValueError(
                f"`scalars` must have one value per vertex ({vertices.shape[0]}) or per face "
                f"({faces.shape[0]}), got {values.size}"
            )
    rgb, lo, hi = _colours(values, cmap, vmin, vmax)
    face_rgb = vertex_rgb = None
    if rgb is not None and values is not None:
        if values.size == vertices.shape[0]:
            vertex_rgb = rgb
        else:
            face_rgb = rgb
    decorate = title is not None or values is not None
    # Leave room for the title and colour bar.
    inner = (width - (110 if values is not None else 0), height - (40 if title else 0))
    inner = (max(inner[0], 16), max(inner[1], 16))

    image: np.ndarray | None = None
    if backend in ("auto", "open3d") and not (backend == "auto" and _OPEN3D_FAILED):
        try:
            image = _render_open3d_limited(
                (vertices, faces, face_rgb, vertex_rgb, view_, up_, inner), time_limit
            )
        except Exception as error:  # any driver failure: fall back
            if backend == "open3d":
                raise RuntimeError(f"Open3D offscreen rendering failed: {error}") from error
            _OPEN3D_FAILED.append(str(error))
            logger.warning("Open3D offscreen rendering failed (%s); using matplotlib", error)
    if image is None:
        if face_rgb is None and vertex_rgb is not None:
            face_rgb = vertex_rgb[faces].mean(axis=1)
        image = _render_matplotlib(vertices, faces, face_rgb, view_, up_, inner)

    def write(tmp: str) -> None:
        import matplotlib
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        dpi = 100
        fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
        FigureCanvasAgg(fig)
        top = 1.0 - (40 / height if title else 0.0)
        ax = fig.add_axes((0.0, 0.0, inner[0] / width, top))
        ax.imshow(image, interpolation="antialiased")
        ax.set_axis_off()
        if decorate:
            if title:
                fig.suptitle(title, y=1.0 - 8 / height, va="top", fontsize=11)
            if values is not None:
                cax = fig.add_axes((1.0 - 80 / width, 0.1, 18 / width, 0.75 * top))
                mappable = matplotlib.cm.ScalarMappable(
                    norm=matplotlib.colors.Normalize(lo, hi), cmap=cmap
                )
                fig.colorbar(mappable, cax=cax, label=label, extend=colorbar_extend(values, lo, hi))
                _keep_inside(fig, cax)
        fig.savefig(tmp, format="png", dpi=dpi)

    return atomic_write(path, write, overwrite=overwrite, name="path")


def colorbar_extend(values: np.ndarray, lo: float, hi: float) -> str:
    """Matplotlib's ``extend`` for a colour bar from ``lo`` to ``hi``: values beyond the scale
    take its end colour, and the bar's pointed ends say that some do."""
    finite = values[np.isfinite(values)]
    over = finite.size > 0 and float(finite.max()) > hi
    under = finite.size > 0 and float(finite.min()) < lo
    return {(True, True): "both", (True, False): "max", (False, True): "min"}.get(
        (over, under), "neither"
    )


def mode_displacements(model: Any, mode: int, standard_deviations: float) -> np.ndarray:
    """Signed normal displacement (mm, outward positive) of each vertex of a mode shape.

    ``(mode_shape(mode, c) - mean) . n`` with ``n`` the mean shape's area-weighted unit vertex
    normals: positive where the shape grows outwards, negative where it moves in.
    """
    normals = vertex_normals(np.asarray(model.mean), np.asarray(model.faces))
    moved = model.mode_shape(mode, standard_deviations) - model.mean
    return np.asarray((moved * normals).sum(axis=1))


def _keep_inside(fig: Any, cax: Any, margin: float = 4.0) -> None:
    """Move a colour bar left until its ticks and label fit in the figure: long tick labels
    ("-0.75") pushed the label's second line past the right edge."""
    width = fig.get_figwidth() * fig.dpi
    overflow = cax.get_tightbbox(fig.canvas.get_renderer()).x1 - (width - margin)
    if overflow > 0:
        box = cax.get_position()
        cax.set_position((box.x0 - overflow / width, box.y0, box.width, box.height))


def render_shape_modes(
    model: Any,
    path: str | os.PathLike[str],
    *,
    modes: Sequence[int] = (0, 1),
    standard_deviations: Sequence[float] = (-3.0, 0.0, 3.0),
    view: Sequence[float] = (30.0, 20.0),
    up: Sequence[float] = (0.0, 0.0, 1.0),
    panel: tuple[int, int] = (420, 360),
    cmap: str = "coolwarm",
    overwrite: bool = True,
) -> str:
    """One PNG of a shape model's modes (paper Figure 6), coloured by displacement from the mean.

    A grid with one row per mode and one column per multiple of the standard deviation; every
    panel is coloured by :func:`mode_displacements` on one colour scale, symmetric about 0 (the
    mean is the neutral colour), with a colour bar in mm. Drawn with matplotlib (headless, any
    machine).

    Parameters
    ----------
    model : ShapeModel
    path : str or os.PathLike
        The PNG to write (atomically).
    modes : sequence of int
        0-based modes, one row each (modes the model lacks are left out). Default the first two.
    standard_deviations : sequence of float
        Multiples of each mode's standard deviation, one column each. Default ``(-3, 0, 3)``.
    view, up :
        Camera as in :func:`render_mesh`.
    panel : (width, height)
        Size of one panel in pixels. Default ``(420, 360)``.
    cmap : str
        A diverging matplotlib colormap. Default ``'coolwarm'``.
    overwrite : bool
        Replace an existing file. Default ``True``.

    Returns
    -------
    str
        The path written.

    Raises
    ------
    ValueError
        For an empty ``modes`` or ``standard_deviations``, or a bad ``view``/``up``/``panel``.
    """
    import matplotlib

    rows = [int(m) for m in modes if 0 <= int(m) < model.number_of_modes]
    sds = [float(c) for c in standard_deviations]
    if not rows:
        raise ValueError(
            f"`modes` must name at least one of the model's {model.number_of_modes} modes, "
            f"got {list(modes)!r}"
        )
    if not sds:
        raise ValueError("`standard_deviations` must not be empty")
    try:
        width, height = (int(s) for s in panel)
    except (TypeError, ValueError):
        raise ValueError(f"`panel` must be (width, height) in pixels, got {panel!r}") from None
    if width < 64 or height < 64:
        raise ValueError(f"`panel` must be at least (64, 64) pixels, got {panel!r}")
    view_ = _check_view(view)
    up_ = _check_up(up)
    faces = np.asarray(model.faces)
    values = {(m, c): mode_displacements(model, m, c) for m in rows for c in sds}
    top = max(float(np.abs(v).max()) for v in values.values()) or 1.0
    norm = matplotlib.colors.Normalize(-top, top)
    colormap = matplotlib.colormaps[cmap]
    shapes = {(m, c): model.mode_shape(m, c) for m in rows for c in sds}
    # One frame for every panel, so that changes of size and position show.
    frame = np.concatenate(list(shapes.values()))
    pictures = {}
    for (m, c), value in values.items():
        face_rgb = colormap(norm(value[faces].mean(axis=1)))[:, :3]
        # Drawn larger, then cropped: matplotlib's 3-D axes leave wide margins.
        pictures[(m, c)] = _render_matplotlib(
            shapes[(m, c)], faces, face_rgb, view_, up_, (2 * width, 2 * height), frame
        )
    # One crop for every panel (the box holding every drawn pixel), so the scale stays common.
    drawn = np.any(np.stack(list(pictures.values())) < 250, axis=(0, 3))
    rows_, cols_ = np.flatnonzero(drawn.any(axis=1)), np.flatnonzero(drawn.any(axis=0))
    if rows_.size and cols_.size:
        pad = 6
        top_, bottom = max(rows_[0] - pad, 0), min(rows_[-1] + pad + 1, drawn.shape[0])
        left, right = max(cols_[0] - pad, 0), min(cols_[-1] + pad + 1, drawn.shape[1])
        pictures = {k: v[top_:bottom, left:right] for k, v in pictures.items()}

    def write(tmp: str) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        dpi = 100
        bar, head = 130, 30
        fig_w, fig_h = width * len(sds) + bar, (height + head) * len(rows)
        fig = Figure(figsize=(fig_w / dpi, fig_h / dpi), dpi=dpi)
        FigureCanvasAgg(fig)
        for i, m in enumerate(rows):
            for j, c in enumerate(sds):
                ax = fig.add_axes(
                    (
                        j * width / fig_w,
                        1.0 - (i + 1) * (height + head) / fig_h,
                        width / fig_w,
                        height / fig_h,
                    )
                )
                ax.imshow(pictures[(m, c)], interpolation="antialiased")
                ax.set_axis_off()
                name = "mean" if c == 0 else f"{c:+g} SD"
                ax.set_title(f"mode {m + 1}: {name}", fontsize=12)
        cax = fig.add_axes((1.0 - 105 / fig_w, 0.15, 18 / fig_w, 0.7))
        mappable = matplotlib.cm.ScalarMappable(norm=norm, cmap=colormap)
        fig.colorbar(mappable, cax=cax, label="displacement from the mean\nalong the normal (mm)")
        _keep_inside(fig, cax)
        fig.savefig(tmp, format="png", dpi=dpi)

    return atomic_write(path, write, overwrite=overwrite, name="path")
