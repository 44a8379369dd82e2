"""Builders shared by the tests (import as ``from _helpers import ...``; pytest puts tests/ on the
path). Test modules never import each other: what two of them share lives here or, for fixtures,
in ``conftest.py``.

The synthetic population (shape model, batch, sliding, landmark, quality, statismo and CLI tests)
is generated from a known linear model: a mean surface (an asymmetric egg with a nose, ~30 mm)
deformed by three known smooth displacement fields with standard deviations 4, 2 and 1 mm (RMS
over the template), then put in a random pose. Each subject's *target* surface is an independent,
finer remeshing (a randomly rotated sphere tessellation) of that subject, so a registration must
find the correspondences; the *truth* is the template's vertices moved by the same fields.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from pydicom.dataset import FileDataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid
from scipy.spatial.transform import Rotation

from o3dreg import Barycentre, ElasticLevel, PointToSurface
from o3dreg.registration._cost import LevelProblem
from o3dreg.registration.distance import SurfaceDistanceQuery
from o3dreg.registration.lattice import TrilinearLattice


@lru_cache(maxsize=1)
def warped_blob() -> tuple[o3d.geometry.TriangleMesh, tuple[np.ndarray, np.ndarray], np.ndarray]:
    """The asymmetric blob (``o3dreg.app.synthetic.asymmetric_blob``) under a 3% warp (seed 1):
    its 1,500-vertex quadric template, the warped surface ``(vertices, faces)`` and the
    template's true positions on it. Built once per session; the arrays are read-only."""
    from o3dreg import decimate
    from o3dreg.app.synthetic import SmoothWarp, asymmetric_blob

    dense = asymmetric_blob()
    template = decimate(dense, 1500)
    vertices, faces = np.asarray(dense.vertices), np.asarray(dense.triangles)
    warp = SmoothWarp.random(vertices, magnitude=0.03, seed=1)
    arrays = warp(vertices), faces.copy(), warp(np.asarray(template.vertices))
    for array in arrays:
        array.setflags(write=False)
    return template, arrays[:2], arrays[2]


#: Three quick levels (2, 4, 8 cells per axis; regularisation 0.1) for tests of the pipeline, not
#: of the accuracy of a full hierarchy.
FAST = [ElasticLevel(2, 0.1), ElasticLevel(4, 0.1), ElasticLevel(8, 0.1)]


def mesh_of(vertices: np.ndarray, faces: np.ndarray) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.asarray(faces, dtype=np.int32)),
    )


def signed_volume(mesh: Any) -> float:
    """Volume enclosed by a closed mesh (Open3D or ``(vertices, faces)``): positive when its
    triangles wind outward (divergence theorem: a sum of signed tetrahedra from the origin)."""
    if isinstance(mesh, o3d.geometry.TriangleMesh):
        mesh = (np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    v, f = mesh
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def snapshot(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """Copies of a mesh's arrays, to assert later that a call left it untouched."""
    return np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles).copy()


def assert_untouched(mesh: o3d.geometry.TriangleMesh, snap: tuple[np.ndarray, np.ndarray]) -> None:
    np.testing.assert_array_equal(np.asarray(mesh.vertices), snap[0])
    np.testing.assert_array_equal(np.asarray(mesh.triangles), snap[1])


def point_jacobian(f: Any, points: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central differences of a map ``f`` of ``(n, 3)`` points: ``(n, 3, 3)``, row = output,
    column = input (the layout of ``LatticeDeformation.jacobian``)."""
    return np.stack([(f(points + h * e) - f(points - h * e)) / (2 * h) for e in np.eye(3)], axis=2)


def similarity_transform(angle_deg: float, axis: Any, shift: Any, scale: float = 1.0) -> np.ndarray:
    """The 4x4 map ``x -> scale * R x + shift``, ``R`` a rotation by ``angle_deg`` about ``axis``."""
    t = np.eye(4)
    axis = np.asarray(axis, dtype=float)
    t[:3, :3] = (
        scale
        * Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
    )
    t[:3, 3] = shift
    return t


def level_problem(
    points: np.ndarray,
    target: tuple[np.ndarray, np.ndarray],
    lattice: TrilinearLattice,
    *,
    symmetric_weight: float = 1.0,
    regularization: float = 0.3,
    energy: str = "bending",
    terms: Any = None,
    **options: Any,
) -> LevelProblem:
    """One level's problem from the identity: every point free (active), no earlier displacement,
    the whole target as the barycentre term's points; ``terms`` default point-to-surface and a
    barycentre term of ``symmetric_weight`` with uniform rows; ``options`` as LevelProblem's."""
    if terms is None:
        terms = [PointToSurface()]
        if symmetric_weight > 0:
            terms.append(Barycentre(symmetric_weight, weighting="uniform"))
    return LevelProblem(
        points=points,
        previous=np.zeros_like(points),
        lattice=lattice,
        active=np.ones(points.shape[0], dtype=bool),
        target=SurfaceDistanceQuery(*target),
        terms=terms,
        regularization=regularization,
        energy=energy,
        **options,
    )


#: Standard deviations (mm, RMS over the template) of the three modes of the population.
SD = np.array([4.0, 2.0, 1.0])


def _base_map(p: np.ndarray) -> np.ndarray:
    q = p * [39.0, 30.0, 24.0]
    nose = np.exp(-((p - [0.0, 1.0, 0.3]) ** 2).sum(1) / 0.15)
    q += 10.0 * nose[:, None] * [0.0, 1.0, 0.0]
    q[:, 0] += 6.0 * np.clip(p[:, 2], 0, None) ** 2
    return q


def unit_sphere(
    resolution: int, rotation: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    v = np.asarray(m.vertices).copy()
    if rotation is not None:
        v = v @ rotation.T
    return v, np.asarray(m.triangles).astype(np.int64)


def _fields(x: np.ndarray) -> list[np.ndarray]:
    zero = np.zeros(len(x))
    stretch = np.stack([x[:, 0] / 39.0, zero, zero], 1)
    top = np.exp(-((x - [0, 0, 24]) ** 2).sum(1) / (2 * 12.0**2))[:, None] * [0.0, 0.0, 1.0]
    side = np.exp(-((x - [30, 0, 0]) ** 2).sum(1) / (2 * 12.0**2))[:, None] * [0.0, 1.0, 0.0]
    return [stretch, top, side]


def unit_fields(x: np.ndarray, template: np.ndarray) -> list[np.ndarray]:
    """The three fields at ``x``, each scaled to unit RMS over the template vertices."""
    norms = [np.sqrt((f**2).sum(1).mean()) for f in _fields(template)]
    return [f / n for f, n in zip(_fields(x), norms)]


def population(
    count: int, seed: int = 0, template_resolution: int = 12, target_resolution: int = 30
):
    """``(template (V, F), targets [(V, F)], truths (count, n, 3), coefficients, poses)``."""
    rng = np.random.default_rng(seed)
    tv, tf = unit_sphere(template_resolution)
    template = _base_map(tv)
    b = rng.standard_normal((count, 3)) * SD
    truths, targets, poses = [], [], []
    for i in range(count):

        def phi(x: np.ndarray, i: int = i) -> np.ndarray:
            return x + sum(b[i, k] * f for k, f in enumerate(unit_fields(x, template)))

        sv, sf = unit_sphere(
            target_resolution, Rotation.random(random_state=seed * 1000 + i).as_matrix()
        )
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.15).as_matrix()
        pose[:3, 3] = rng.normal(size=3) * 5
        targets.append((phi(_base_map(sv)) @ pose[:3, :3].T + pose[:3, 3], sf))
        truths.append(phi(template))
        poses.append(pose)
    return (template, tf), targets, np.stack(truths), b, poses


def write_dicom_series(
    folder: Path,
    stored: np.ndarray,
    *,
    slope: float,
    intercept: float,
    positions_z: list[float],
    series_uid: str | None = None,
    prefix: str = "img",
    edit: Any = None,
) -> str:
    """Write ``stored`` (planes, rows, columns) uint16 as a CT series with pydicom
    (``edit(n, dataset)``: a change to slice ``n`` before it is saved)."""
    folder.mkdir(exist_ok=True)
    series_uid = series_uid or generate_uid()
    study_uid = generate_uid()
    frame_uid = generate_uid()
    for n, (plane, z) in enumerate(zip(stored, positions_z, strict=True)):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = FileDataset(None, {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.StudyInstanceUID = study_uid
        ds.SeriesInstanceUID = series_uid
        ds.FrameOfReferenceUID = frame_uid
        ds.Modality = "CT"
        ds.PatientName = "Phantom^Test"
        ds.PatientID = "0"
        ds.InstanceNumber = n + 1
        ds.ImagePositionPatient = [-10.0, 20.0, float(z)]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing = [0.75, 0.5]  # row spacing (y), column spacing (x)
        ds.SliceThickness = 2.0
        ds.Rows, ds.Columns = plane.shape
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated = 16
        ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 0
        ds.RescaleSlope = slope
        ds.RescaleIntercept = intercept
        ds.PixelData = np.ascontiguousarray(plane, dtype="<u2").tobytes()
        if edit is not None:
            edit(n, ds)
        # Files named in reverse order of position: the reader must sort by position.
        ds.save_as(folder / f"{prefix}{len(stored) - n:03d}.dcm", enforce_file_format=True)
    return series_uid


def ct_mandible_masks(shared_data: Path) -> list[Path]:
    """The PDDCA mandible masks of the shared data, sorted (the test is skipped without them)."""
    import pytest

    masks = shared_data / "mandibles" / "masks"
    if not masks.is_dir():
        pytest.skip("mandible masks absent from the shared data")
    return sorted(masks.glob("*.nrrd"))


def ct_mandible(mask: Path, vertices: int | None = None) -> o3d.geometry.TriangleMesh:
    """The bone surface of a mandible mask, as ``examples/mandible_model.py`` makes it
    (decimated to ``vertices`` when given)."""
    import sys

    examples = str(Path(__file__).resolve().parents[1] / "examples")
    if examples not in sys.path:
        sys.path.insert(0, examples)
    from mandible_model import reconstruct

    return reconstruct(str(mask)) if vertices is None else reconstruct(str(mask), vertices)


def morton_code(cells: np.ndarray) -> np.ndarray:
    """The Morton code of integer cells ``(n, 3)`` of a 1024^3 grid: their bits interleaved
    x, y, z from the least significant, one bit at a time (the definition, not o3dreg's)."""
    code = np.zeros(cells.shape[0], dtype=np.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cells[:, axis] >> bit) & 1) << (3 * bit + axis)
    return code
