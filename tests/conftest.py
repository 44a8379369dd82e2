"""Shared fixtures: small analytic meshes and the bundled bunny."""

from __future__ import annotations

import os
from pathlib import Path

import open3d as o3d
import pytest

from o3dreg.app.datasets import load_bunny


def shared_data_dir() -> Path | None:
    """``../shared/data`` beside the repository (research data never copied into it)."""
    env = os.environ.get("O3DREG_SHARED_DATA")
    path = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"
    return path if path.is_dir() else None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    path = shared_data_dir()
    if path is None:
        pytest.skip("../shared/data is absent (research data is not part of the repository)")
    return path


@pytest.fixture(scope="session")
def bunny_target() -> o3d.geometry.TriangleMesh:
    """The full bunny (35,947 vertices), millimetres."""
    return load_bunny()


@pytest.fixture(scope="session")
def bunny_template(bunny_target) -> o3d.geometry.TriangleMesh:
    """A ~1.5k-vertex template decimated from the bunny (deterministic)."""
    mesh = bunny_target.simplify_quadric_decimation(3000)
    mesh.remove_unreferenced_vertices()
    return mesh
