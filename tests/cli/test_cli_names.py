"""The command line's errors name what its user typed (``INPUT``, ``TARGET``, ``--landmarks``),
not the library parameter behind it (``path``, ``volume``, ``targets``, ``source``)."""

from __future__ import annotations

from pathlib import Path

import open3d as o3d
import pytest

from o3dreg import write_triangle_mesh
from o3dreg.cli import main

DATA = Path(__file__).resolve().parents[1] / "data"
PITCH = DATA / "pitch" / "CT_pitch.nii.gz"  # values 0-255


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("names")
    write_triangle_mesh(folder / "a.ply", o3d.geometry.TriangleMesh.create_sphere(5.0, 10))
    write_triangle_mesh(folder / "b.ply", o3d.geometry.TriangleMesh.create_sphere(5.5, 12))
    write_triangle_mesh(folder / "c.ply", o3d.geometry.TriangleMesh.create_sphere(6.0, 12))
    for name in ("a", "b", "c"):
        (folder / f"{name}.csv").write_text("label,l,p,s\np,1,0,0\nq,0,1,0\nr,0,0,1\n")
    (folder / "bad.csv").write_text("hello world\n")
    (folder / "garbage.h5").write_bytes(b"garbage")
    return folder


def _error(argv: list[str], capsys) -> str:
    assert main(argv) == 2
    return capsys.readouterr().err


@pytest.mark.parametrize("which", [0, 1])
def test_register_names_the_landmark_file_of_landmarks(files, which, capsys):
    pair = [str(files / "a.csv"), str(files / "b.csv")]
    pair[which] = str(files / "missing.csv")
    out = str(files / "out.ply")
    err = _error(["register", str(files / "a.ply"), str(files / "b.ply"), "-o", out,
                  "--landmarks", *pair], capsys)  # fmt: skip
    name = ("--landmarks TEMPLATE_FILE", "--landmarks PATIENT_FILE")[which]
    assert f"`{name}`: no such file {pair[which]!r}" in err
    assert "`path`" not in err and "`source`" not in err and "`target`" not in err


def test_reconstruct_names_input(files, capsys):
    for given, expected in (
        (files / "missing.nii.gz", "`INPUT`: no such file or folder"),
        (files / "bad.csv", "`INPUT` must be a folder of DICOM slices"),
    ):
        err = _error(["reconstruct", str(given), "-o", str(files / "o.ply"), "--threshold", "1"],
                     capsys)  # fmt: skip
        assert expected in err and repr(str(given)) in err and "`path`" not in err


def test_reconstruct_names_input_for_a_2d_image(files, capsys):
    slice_ = DATA / "dicom_slice"
    err = _error(["reconstruct", str(slice_), "-o", str(files / "o.ply"), "--threshold", "100"],
                 capsys)  # fmt: skip
    assert "`INPUT` must have at least 2 voxels along every axis, got shape (1, 128, 128)" in err
    assert "`volume`" not in err


@pytest.mark.parametrize("level", ["1000", "-5"])
def test_reconstruct_says_a_threshold_outside_the_values_in_the_files_units(files, level, capsys):
    err = _error(["reconstruct", str(PITCH), "-o", str(files / "o.ply"), f"--threshold={level}"],
                 capsys)  # fmt: skip
    assert "--threshold must lie strictly between" in err
    assert "[0, 255] (the file's own units)" in err and f"got {level}" in err


def test_reconstruct_refuses_a_threshold_that_is_not_finite(files, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["reconstruct", str(PITCH), "-o", str(files / "o.ply"), "--threshold", "nan"])
    assert exc.value.code == 2
    assert "argument --threshold: expected a finite number, got 'nan'" in capsys.readouterr().err


def test_reconstruct_help_says_the_level_is_in_the_files_units(capsys):
    with pytest.raises(SystemExit):
        main(["reconstruct", "--help"])
    assert "file's own units" in " ".join(capsys.readouterr().out.split())


def test_build_model_names_target(files, capsys):
    err = _error(["build-model", str(files / "a.ply"), str(files / "b.ply"),
                  "-o", str(files / "m1")], capsys)  # fmt: skip
    assert "`TARGET` must hold at least 2 distinct patient meshes" in err
    assert "got 1 file(s)" in err and "`targets`" not in err


def test_build_model_names_its_landmarks(files, capsys):
    missing = str(files / "missing.csv")
    err = _error(["build-model", str(files / "a.ply"), str(files / "b.ply"), str(files / "c.ply"),
                  "-o", str(files / "m2"), "--landmarks", missing], capsys)  # fmt: skip
    assert f"`--landmarks`: no such file {missing!r}" in err
    assert "`source`" not in err and "`path`" not in err


def test_model_names_model_and_landmarks(files, capsys):
    garbage = str(files / "garbage.h5")
    err = _error(["model", "info", garbage], capsys)
    assert f"`MODEL`: {garbage!r} is not a readable HDF5 file" in err and "`path`" not in err
    model = str(DATA / "statismo" / "scalismo-asm-model.h5")
    bad = str(files / "bad.csv")
    err = _error(["model", "fit", model, str(files / "a.ply"), "--landmarks", bad], capsys)
    assert f"`--landmarks`: {bad!r} must have a header" in err and "`path`" not in err
