"""The mandible benchmark and example on PDDCA-like folders they have not seen: which patients
serve, the line that names each one left out, the choice of templates and the offset fit.

Tiny synthetic masks (boxes written as NRRD) and Slicer ``.fcsv`` files made in ``tmp_path``: no
research data.
"""

from __future__ import annotations

import importlib.util
import logging
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

import o3dreg

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import _mandibles  # noqa: E402
import bench_landmarks  # noqa: E402
from _mandibles import (  # noqa: E402
    Unusable,
    load_patient,
    load_patients,
    patient_files,
    patient_id,
)

LABELS = bench_landmarks.LABELS
TEMPLATE_VERTICES = 200
#: The "mandible" of the synthetic masks: index ranges (z, y, x) of a box, 1 mm voxels, origin 0.
BONE = ((10, 30), (10, 40), (10, 50))


def _example():
    spec = importlib.util.spec_from_file_location(
        "mandible_model", ROOT / "examples" / "mandible_model.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


mandible_model = _example()


@pytest.fixture(autouse=True)
def _o3dreg_log_level():
    # The benchmark quietens o3dreg's logger for its run: give the other tests theirs back.
    logger = logging.getLogger("o3dreg")
    level = logger.level
    yield
    logger.setLevel(level)


def write_mask(path: Path, boxes=(BONE,), shape=(40, 50, 60)) -> Path:
    """A 0/1 mask holding ``boxes`` (index ranges z, y, x), 1 mm voxels, LPS origin 0."""
    array = np.zeros(shape, dtype=np.uint8)
    for (z0, z1), (y0, y1), (x0, x1) in boxes:
        array[z0:z1, y0:y1, x0:x1] = 1
    path.parent.mkdir(parents=True, exist_ok=True)
    sitk.WriteImage(sitk.GetImageFromArray(array), str(path), True)
    return path


def on_box(box=BONE) -> np.ndarray:
    """``chin``, ``mand_r``, ``mand_l`` (LPS, mm), 1 mm inside the box's faces (the marching-cubes
    surface lies half a voxel outside the voxel centres), like PDDCA's annotations."""
    (z0, z1), (y0, y1), (x0, x1) = box
    z, y, x = (z0 + z1) / 2, (y0 + y1) / 2, (x0 + x1) / 2
    return np.array([[x, y0 + 0.5, z], [x0 + 0.5, y, z], [x1 - 1.5, y, z]])


def write_fcsv(
    path: Path,
    points: np.ndarray,
    labels=LABELS,
    *,
    system: str = "0",
    in_lps: bool = False,
    status: list[str] | None = None,
) -> Path:
    """A Slicer fiducial file as PDDCA's (version 4.3, ``CoordinateSystem = 0``: RAS); the points
    (LPS) are written in RAS unless ``in_lps``; ``status``: Slicer 5's position status per row."""
    rows = [
        "# Markups fiducial file version = 4.3",
        f"# CoordinateSystem = {system}",
        "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID",
    ]
    written = points if in_lps else points * [-1.0, -1.0, 1.0]
    for k, (label, (x, y, z)) in enumerate(zip(labels, written)):
        extra = f",{status[k]},0" if status else ""
        rows.append(f"vtkMRMLMarkupsFiducialNode_{k},{x},{y},{z},0,0,0,1,1,1,0,{label},,vol{extra}")
    rows.append(f"vtkMRMLMarkupsFiducialNode_9,1,2,3,0,0,0,1,1,1,0,occ_bone,,vol{extra}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(rows) + "\n")
    return path


def patient(folder: Path, pid: str, *, mask=True, points=None, box=BONE, **fcsv) -> None:
    if mask:
        write_mask(folder / "masks" / f"{pid}_Mandible.nrrd", boxes=(box,))
    if points is not False:
        landmarks = on_box(box) if points is None else points
        write_fcsv(folder / "landmarks" / f"{pid}_Landmarks.fcsv", landmarks, **fcsv)


def load(folder: Path, pid: str = "p1"):
    mask = folder / "masks" / f"{pid}_Mandible.nrrd"
    landmarks = folder / "landmarks" / f"{pid}_Landmarks.fcsv"
    return load_patient(
        pid, mask, landmarks if landmarks.exists() else None, LABELS, TEMPLATE_VERTICES
    )


# -- which files are patients ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "pid"),
    [
        ("0522c0001_Mandible.nrrd", "0522c0001"),
        ("0522c00123_Mandible.nrrd", "0522c00123"),  # 10 characters
        ("HN_CHUM_001_Mandible.nrrd", "HN_CHUM_001"),  # underscores in the id
        ("p7_mandible.NRRD", "p7"),
        ("_Mandible.nrrd", None),
        ("0522c0001_BrainStem.nrrd", None),
        ("0522c0001.nrrd", None),
    ],
)
def test_the_patient_id_is_all_before_the_suffix(name, pid):
    assert patient_id(Path(name), _mandibles.MASK_SUFFIX) == pid


def test_patient_files_pair_masks_and_landmarks_and_name_the_rest(tmp_path):
    for name in ("HN_CHUM_001_Mandible.nrrd", "0522c00123_Mandible.nrrd", "notes.txt"):
        (tmp_path / "masks").mkdir(exist_ok=True)
        (tmp_path / "masks" / name).write_bytes(b"")
    (tmp_path / "masks" / ".DS_Store").write_bytes(b"")
    (tmp_path / "landmarks").mkdir()
    for name in ("HN_CHUM_001_Landmarks.fcsv", "0522c0999_Landmarks.fcsv"):
        (tmp_path / "landmarks" / name).write_text("")
    files, lines = patient_files(tmp_path)
    assert list(files) == ["0522c00123", "HN_CHUM_001"]
    assert files["0522c00123"][1] is None
    assert files["HN_CHUM_001"][1].name == "HN_CHUM_001_Landmarks.fcsv"
    assert lines == [
        "ignored masks/notes.txt: not named <id>_Mandible.nrrd",
        "left out 0522c0999: landmarks/0522c0999_Landmarks.fcsv has no "
        "masks/0522c0999_Mandible.nrrd",
    ]


# -- one patient -------------------------------------------------------------------------------


def test_a_patient_serves_with_its_annotations_in_lps(tmp_path):
    patient(tmp_path, "p1")
    data, notes = load(tmp_path)
    assert notes == []
    np.testing.assert_allclose(data["landmarks"], on_box())
    assert len(data["template"][0]) <= TEMPLATE_VERTICES + 10
    np.testing.assert_allclose(np.ptp(data["surface"][0], axis=0), [40, 30, 20], atol=1.5)
    np.testing.assert_allclose(data["spacing"], [1, 1, 1])


@pytest.mark.parametrize("system", ["LPS", "1"])  # Slicer >= 4.11 and Slicer 4's enum
def test_a_landmark_file_in_lps_gives_the_same_points(tmp_path, system):
    patient(tmp_path, "p1", system=system, in_lps=True)
    data, _ = load(tmp_path)
    np.testing.assert_allclose(data["landmarks"], on_box())


def test_a_file_without_a_coordinate_system_is_taken_as_ras_with_a_note(tmp_path):
    path = write_fcsv(tmp_path / "landmarks" / "p1_Landmarks.fcsv", on_box())
    path.write_text("".join(line for line in path.open() if "CoordinateSystem" not in line))
    write_mask(tmp_path / "masks" / "p1_Mandible.nrrd")
    data, notes = load(tmp_path)
    np.testing.assert_allclose(data["landmarks"], on_box())
    assert len(notes) == 1 and "coordinate system not stated" in notes[0]


LANDMARK_PROBLEMS = {
    "no file": (dict(points=False), r"^no landmark file landmarks/p1_Landmarks\.fcsv$"),
    "a label absent": (
        dict(points=on_box()[:2], labels=LABELS[:2]),
        r"p1_Landmarks\.fcsv lacks 'mand_l' \(chin, mand_r, mand_l expected; it holds chin, "
        r"mand_r, occ_bone\)",
    ),
    "a label twice": (
        dict(points=np.vstack([on_box(), on_box()[:1] + 1]), labels=(*LABELS, "chin")),
        r"p1_Landmarks\.fcsv holds 'chin' 2 times \(each label once expected",
    ),
    "a label not placed": (
        dict(status=["2", "0", "2"]),  # Slicer 5: 0 = undefined
        r"p1_Landmarks\.fcsv holds 'mand_r' not placed",
    ),
    "the other system than the file says": (
        dict(system="LPS"),  # RAS points under an LPS header
        r"its landmarks lie off its mandible surface \('chin' .* mm.*\) and on it with x and y "
        r"negated: its landmark file's CoordinateSystem \(RAS or LPS\) does not match",
    ),
    "a landmark off the bone": (
        dict(points=on_box() + [[0, 0, 0], [0, 0, 0], [0, 0, 25]]),
        r"^landmarks off its mandible surface: 'mand_l' \d+\.\d mm \(within \d\.\d mm expected",
    ),
}


@pytest.mark.parametrize("problem", list(LANDMARK_PROBLEMS))
def test_a_landmark_file_that_cannot_serve_says_why(tmp_path, problem):
    fcsv, message = LANDMARK_PROBLEMS[problem]
    patient(tmp_path, "p1", **fcsv)
    with pytest.raises(Unusable, match=message):
        load(tmp_path)


def test_an_empty_mask_says_so(tmp_path):
    patient(tmp_path, "p1")
    write_mask(tmp_path / "masks" / "p1_Mandible.nrrd", boxes=())
    with pytest.raises(Unusable, match=r"^p1_Mandible\.nrrd holds no voxel above 0\.5"):
        load(tmp_path)


def test_an_unreadable_mask_says_so(tmp_path):
    patient(tmp_path, "p1")
    (tmp_path / "masks" / "p1_Mandible.nrrd").write_bytes(b"not a volume")
    with pytest.raises(Unusable, match=r"^p1_Mandible\.nrrd cannot be read"):
        load(tmp_path)


def test_a_mask_in_pieces_says_so(tmp_path):
    patient(tmp_path, "p1")
    halves = (((10, 30), (10, 40), (5, 25)), ((10, 30), (10, 40), (35, 55)))
    write_mask(tmp_path / "masks" / "p1_Mandible.nrrd", boxes=halves)
    with pytest.raises(Unusable, match=r"is in pieces: its largest component holds 50% of"):
        load(tmp_path)


def test_a_largest_component_that_is_not_the_mandible_says_so(tmp_path):
    # A small "mandible" carrying the annotations and a block more than 9 times its surface.
    small = ((5, 17), (5, 21), (5, 25))
    block = ((5, 61), (5, 61), (40, 96))
    write_mask(tmp_path / "masks" / "p1_Mandible.nrrd", (small, block), shape=(70, 70, 100))
    write_fcsv(tmp_path / "landmarks" / "p1_Landmarks.fcsv", on_box(small))
    with pytest.raises(
        Unusable,
        match=r"^its mask's largest component \(5\d x 5\d x 5\d mm\) does not hold 'chin' .* they "
        r"lie on another component of the mask .* so its largest component is not the mandible",
    ):
        load(tmp_path)


# -- a folder ----------------------------------------------------------------------------------


def test_load_patients_names_each_patient_left_out(tmp_path):
    for pid in ("a", "b_1", "c"):
        patient(tmp_path, pid)
    patient(tmp_path, "d", points=on_box()[:2], labels=LABELS[:2])
    patient(tmp_path, "e", points=False)
    lines: list[str] = []
    data = load_patients(tmp_path, LABELS, TEMPLATE_VERTICES, say=lines.append)
    assert list(data) == ["a", "b_1", "c"]
    assert lines == [
        "left out d: d_Landmarks.fcsv lacks 'mand_l' (chin, mand_r, mand_l expected; it holds "
        "chin, mand_r, occ_bone)",
        "left out e: no landmark file landmarks/e_Landmarks.fcsv",
    ]


def test_the_benchmark_skips_with_fewer_than_3_patients(tmp_path, capsys):
    patient(tmp_path, "a")
    patient(tmp_path, "b")
    patient(tmp_path, "c", points=False)
    assert bench_landmarks.main(["--data", str(tmp_path), "--template-vertices", "200"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "left out c: no landmark file landmarks/c_Landmarks.fcsv"
    assert out[1].startswith("skip: 2 patient(s) of ") and "at least 3 needed" in out[1]


def test_the_benchmark_runs_on_3_patients_and_says_what_3_cannot_give(tmp_path, capsys):
    for pid in ("a", "b", "c"):
        patient(tmp_path, pid)
    args = ["--data", str(tmp_path), "--template-vertices", "200", "--skip-peer", "--decompose"]
    assert bench_landmarks.main([*args, "--templates", "0"]) == 0
    out = capsys.readouterr().out
    assert "transfer: 1 templates x 2 patients = 2 pairs" in out
    assert "\no3dreg consensus " in out and "\n  a: " in out
    # One template: as many pair errors as free offsets.
    assert (
        "offsets o_a - o_b and rest r_ab not fitted, underdetermined (1 template x 2 patients): "
        "2 pair errors for 2 free offsets" in out
    )
    assert (
        "\nprediction skipped: its model is built of the patients other than the template " in out
    )


@pytest.mark.slow
def test_the_benchmark_counts_its_patients_in_the_prediction_table(tmp_path, capsys):
    for k, pid in enumerate(("a", "b", "c", "d")):
        patient(tmp_path, pid, box=((10, 30 - k), (10, 40 + k), (10, 50 - 2 * k)))
    args = ["--data", str(tmp_path), "--template-vertices", "200", "--skip-peer"]
    assert bench_landmarks.main([*args, "--templates", "a,1", "--decompose"]) == 0
    out = capsys.readouterr().out
    assert "transfer: 2 templates x 3 patients = 6 pairs" in out
    assert "\nrest r_ab " in out
    assert (
        "prediction: model of 2 patients' semilandmark meshes, predict_landmarks on the 3rd" in out
    )
    assert "\nrigid       3 annotations  registered " in out
    assert "the mean of the template's and the 2 model patients' annotations" in out


def test_the_benchmark_refuses_a_data_folder_without_masks(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        bench_landmarks.main(["--data", str(tmp_path / "absent")])
    assert exit_.value.code == 2
    assert "must hold masks/ (<id>_Mandible.nrrd) and landmarks/" in capsys.readouterr().err


# -- templates, tables, the offset fit ---------------------------------------------------------

IDS = ["0522c0001", "0522c0002", "HN_3", "p4", "p5"]


@pytest.mark.parametrize(
    ("spec", "chosen"),
    [
        (None, IDS),
        ("0,2", ["0522c0001", "HN_3"]),
        ("p5, 0", ["p5", "0522c0001"]),
        ("HN_3", ["HN_3"]),
    ],
)
def test_templates_are_indices_or_ids(spec, chosen):
    assert bench_landmarks.chosen_templates(spec, IDS) == chosen


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("5", r"indices 0-4 or ids of the 5 patients that serve \(0522c0001, .*\), got '5'"),
        ("0,,1", r"got '' in '0,,1'"),
        ("-1", r"got '-1'"),
        ("0522c0009", r"got '0522c0009'"),
        ("1,0522c0002", r"each template once, got 0522c0002 twice"),
    ],
)
def test_templates_outside_the_patients_are_refused(spec, message):
    with pytest.raises(ValueError, match=message):
        bench_landmarks.chosen_templates(spec, IDS)


@pytest.mark.parametrize(
    ("n", "text"),
    [(1, "1st"), (2, "2nd"), (3, "3rd"), (4, "4th"), (7, "7th"), (11, "11th"), (22, "22nd")],
)
def test_ordinal(n, text):
    assert bench_landmarks.ordinal(n) == text


def pairs_of(templates: list[int], count: int) -> list[tuple[int, int]]:
    return [(a, b) for a in templates for b in range(count) if b != a]


def test_the_offset_fit_splits_errors_into_offsets_and_rest():
    rng = np.random.default_rng(0)
    count = 5
    offsets = rng.normal(size=(count, 3, 3))
    offsets -= offsets.mean(axis=0)
    pairs = pairs_of([0, 1], count)
    errors = np.stack([offsets[a] - offsets[b] for a, b in pairs])
    explained, rest = bench_landmarks.offset_fit(pairs, errors, count)
    np.testing.assert_allclose(explained, errors, atol=1e-12)
    np.testing.assert_allclose(rest, 0, atol=1e-12)
    noisy = errors + rng.normal(scale=0.1, size=errors.shape)
    explained, rest = bench_landmarks.offset_fit(pairs, noisy, count)
    assert 0 < np.abs(rest).max() < 0.5
    np.testing.assert_allclose(explained + rest, noisy)


def test_the_offset_fit_says_when_it_is_underdetermined():
    errors = np.ones((4, 3, 3))
    with pytest.raises(bench_landmarks.Underdetermined, match="4 pair errors for 4 free offsets"):
        bench_landmarks.offset_fit(pairs_of([0], 5), errors, 5)
    with pytest.raises(bench_landmarks.Underdetermined, match="tie only 2 of the 3 annotations"):
        bench_landmarks.offset_fit([(0, 1), (1, 0)], errors[:2], 3)


# -- examples/mandible_model.py ----------------------------------------------------------------


def test_the_example_reads_ids_of_any_length_and_names_other_files(tmp_path):
    for name in (
        "HN_CHUM_001_Mandible.nrrd",
        "0522c0001_Mandible.nrrd",
        "img.nrrd",
        "a b_Mandible.nrrd",
    ):
        (tmp_path / name).write_bytes(b"")
    masks, lines = mandible_model.patient_masks(tmp_path)
    assert [pid for pid, _ in masks] == ["0522c0001", "HN_CHUM_001"]
    assert lines == [
        "left out 'a b': its id is not a plain file name (letters, digits, . _ -)",
        "ignored img.nrrd: not named <id>_Mandible.nrrd",
    ]


def test_the_example_leaves_out_masks_without_one_mandible(tmp_path):
    Unusable_ = mandible_model.Unusable
    empty = write_mask(tmp_path / "empty_Mandible.nrrd", boxes=())
    with pytest.raises(Unusable_, match=r"^empty_Mandible\.nrrd holds no voxel above 0\.5"):
        mandible_model.reconstruct(empty)
    halves = (((10, 30), (10, 40), (5, 25)), ((10, 30), (10, 40), (35, 55)))
    pieces = write_mask(tmp_path / "pieces_Mandible.nrrd", boxes=halves)
    with pytest.raises(Unusable_, match=r"in pieces: its largest component holds 50%"):
        mandible_model.reconstruct(pieces)
    mesh = mandible_model.reconstruct(write_mask(tmp_path / "ok_Mandible.nrrd"))
    assert len(mesh.vertices) > 100
    outliers = mandible_model.size_outliers({"a": 170.0, "b": 160.0, "c": 180.0, "d": 340.0})
    assert list(outliers) == ["d"]
    assert "340 mm across" in outliers["d"] and "median 175 mm" in outliers["d"]


def test_the_example_stops_with_fewer_than_3_masks(tmp_path, capsys):
    write_mask(tmp_path / "data" / "masks" / "a_Mandible.nrrd")
    write_mask(tmp_path / "data" / "masks" / "b_Mandible.nrrd")
    assert mandible_model.main([str(tmp_path / "out"), "--data", str(tmp_path / "data")]) == 0
    assert "2 mandible mask(s) <id>_Mandible.nrrd under" in capsys.readouterr().out
    assert not (tmp_path / "out").exists()


def test_the_example_makes_a_cached_surface_again_from_another_mask_or_count(tmp_path):
    small = write_mask(tmp_path / "a_Mandible.nrrd")
    large = write_mask(tmp_path / "b_Mandible.nrrd", boxes=(((5, 35), (5, 45), (5, 55)),))
    path = tmp_path / "out" / "a.ply"
    path.parent.mkdir()

    def extent():
        return float(np.ptp(np.asarray(o3dreg.read_triangle_mesh(path).vertices), axis=0).max())

    mandible_model.cached_surface(path, small, None)
    first, written = extent(), path.stat().st_mtime_ns
    mandible_model.cached_surface(path, small, None)
    assert path.stat().st_mtime_ns == written  # the same mask and count: reused
    mandible_model.cached_surface(path, large, None)
    # The larger box's extent (50 voxels of 1 mm against 40): a stale mesh would keep the first.
    assert extent() > first + 5.0
    mandible_model.cached_surface(path, large, 200)
    assert len(o3dreg.read_triangle_mesh(path).vertices) <= 200
