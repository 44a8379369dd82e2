"""``o3dreg view MESH...``: look at meshes in Open3D's viewer (or write a picture, headless)."""

from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np
import open3d as o3d

from .._validation import named_as
from ..app.render import BACKENDS, OPEN3D_TIME_LIMIT, render_mesh
from ..io.mesh import read_triangle_mesh
from ..registration.distance import SurfaceDistanceQuery
from ._common import add_overwrite_option, check_outputs, emit, int_list

EPILOG = """examples:
  o3dreg view template.ply patient.ply
  o3dreg view registered.ply --distance-to patient.ply            # colour by distance (mm)
  o3dreg view registered.ply --distance-to patient.ply --screenshot registered.png  # headless"""

_PALETTE = [(0.85, 0.55, 0.2), (0.3, 0.55, 0.85), (0.5, 0.75, 0.4), (0.8, 0.4, 0.6)]


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "view",
        help="show meshes in Open3D's interactive viewer",
        description="Open meshes in Open3D's viewer where a display exists; --screenshot renders "
        "one mesh to a PNG instead (works without a display or GPU: matplotlib by default, "
        "about a second; --backend open3d uses Filament, under --time-limit).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "meshes",
        metavar="MESH",
        nargs="+",
        help="mesh files (.ply, .obj, .stl, .off, .gltf, .glb, .vtk, .vtp, .vtu)",
    )
    p.add_argument(
        "--distance-to",
        metavar="TARGET",
        help="colour the first mesh by its point-to-surface distance to TARGET",
    )
    p.add_argument(
        "--screenshot", metavar="PNG", help="write a picture instead of opening a window"
    )
    add_overwrite_option(p, "an existing --screenshot file")
    p.add_argument(
        "--backend",
        choices=BACKENDS,
        default="matplotlib",
        help="--screenshot renderer: matplotlib (default; any machine), open3d (Filament: needs a "
        "Vulkan/EGL driver, slow or hanging on software Vulkan), auto (open3d, else matplotlib)",
    )
    p.add_argument(
        "--time-limit",
        type=float,
        default=OPEN3D_TIME_LIMIT,
        metavar="SECONDS",
        help=f"stop the open3d renderer after SECONDS (default {OPEN3D_TIME_LIMIT:g})",
    )
    p.add_argument(
        "--size",
        type=int_list,
        default=[1000, 800],
        metavar="W,H",
        help="--screenshot size in pixels (default 1000,800)",
    )
    p.set_defaults(func=run)


def _colours(values: np.ndarray) -> np.ndarray:
    import matplotlib  # deferred: ~0.3 s to import, needed only with --distance-to

    top = float(np.percentile(values, 98)) or 1.0
    return np.asarray(matplotlib.colormaps["viridis"](np.clip(values / top, 0, 1)))[:, :3]


def run(args: argparse.Namespace) -> int:
    if args.screenshot:  # before any work: reading the meshes, the distances
        check_outputs(
            {"--screenshot": args.screenshot},
            args.overwrite,
            inputs={f"MESH {k + 1}": m for k, m in enumerate(args.meshes)}
            | {"--distance-to": args.distance_to},
            suffixes={"--screenshot": (".png",)},
        )
        if len(args.size) != 2:
            raise ValueError(f"--size must be W,H, got {args.size}")
        if len(args.meshes) > 1:
            # Drawing only the first would silently leave the others out of the picture.
            raise ValueError(
                f"--screenshot renders one MESH, got {len(args.meshes)}: write one picture per "
                "mesh, or open them together in a window (without --screenshot)"
            )
    meshes = [read_triangle_mesh(path, name="MESH") for path in args.meshes]
    scalars = None
    if args.distance_to:
        target = read_triangle_mesh(args.distance_to, name="--distance-to")
        query = SurfaceDistanceQuery(np.asarray(target.vertices), np.asarray(target.triangles))
        scalars = query.distance(np.asarray(meshes[0].vertices))
        emit(
            f"{args.meshes[0]} -> {args.distance_to}: mean {scalars.mean():.3f}, "
            f"max {scalars.max():.3f} (mm)",
            args,
        )
    if args.screenshot:
        with named_as("--screenshot"):
            render_mesh(
                meshes[0],
                args.screenshot,
                scalars=scalars,
                title=os.path.basename(args.meshes[0])
                + (
                    f": distance to {os.path.basename(args.distance_to)}"
                    if scalars is not None
                    else ""
                ),
                label="mm" if scalars is not None else None,
                size=(args.size[0], args.size[1]),
                backend=args.backend,
                time_limit=args.time_limit,
                overwrite=args.overwrite,
            )
        emit(f"wrote {args.screenshot}", args)
        return 0
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise RuntimeError(
            "no display to open a window on (DISPLAY is not set); use --screenshot PNG to render "
            "a picture instead"
        )
    for k, mesh in enumerate(meshes):
        mesh.compute_vertex_normals()
        if k == 0 and scalars is not None:
            mesh.vertex_colors = o3d.utility.Vector3dVector(_colours(scalars))
        elif not mesh.has_vertex_colors():
            mesh.paint_uniform_color(_PALETTE[k % len(_PALETTE)])
    o3d.visualization.draw_geometries(meshes, window_name="o3dreg view")
    return 0
