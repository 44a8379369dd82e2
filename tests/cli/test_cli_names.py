"""The command line's errors name what its user typed (``INPUT``, ``TARGET``, ``--landmarks``),
not the library parameter behind it (``path``, ``volume``, ``targets``, ``source``)."""

from __future__ import annotations

import os
from pathlib import Path

import open3d as o3d
import pytest

from o3dreg import write_triangle_mesh
from o3dreg.cli import _numbers_as_values, build_parser, main

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


def test_build_model_records_name_target_for_a_file_that_cannot_be_read(files, tmp_path, capsys):
    # The batch reads each patient in its worker: the failure is a record, not an exception.
    (tmp_path / "bad.ply").write_text("garbage")
    argv = ["build-model", str(files / "a.ply"), str(files / "b.ply"), str(files / "c.ply"),
            str(tmp_path / "bad.ply"), "-o", str(tmp_path / "m"), "--levels", "2"]  # fmt: skip
    assert main(argv) == 1
    out = capsys.readouterr().out
    assert f"`TARGET`: {str(tmp_path / 'bad.ply')!r} is not a PLY file" in out
    assert "`target`" not in out
    record = (tmp_path / "m" / "registrations" / "bad.json").read_text()
    assert "`TARGET`" in record and "`target`" not in record


def test_library_batch_records_still_name_target(files, tmp_path):
    from o3dreg import register_batch

    (tmp_path / "bad.ply").write_text("garbage")
    template = o3d.geometry.TriangleMesh.create_sphere(5.0, 10)
    batch = register_batch(template, [str(tmp_path / "bad.ply")], tmp_path / "out")
    assert batch.records[0].message.startswith("OSError: `target`: ")


def test_build_model_names_a_missing_target_before_any_work(files, tmp_path, capsys):
    missing, other = str(tmp_path / "missing.ply"), str(tmp_path / "other.ply")
    out = tmp_path / "m"
    err = _error(["build-model", str(files / "a.ply"), str(files / "b.ply"), missing,
                  "-o", str(out)], capsys)  # fmt: skip
    assert f"`TARGET`: no such file {missing!r}" in err and "distinct" not in err
    err = _error(["build-model", str(files / "a.ply"), missing, other, "-o", str(out)], capsys)
    assert f"`TARGET`: no such files {missing!r}, {other!r}" in err
    assert not out.exists()


def test_build_model_says_why_the_one_other_target_is_not_a_mesh(files, tmp_path, capsys):
    bad = tmp_path / "bad.ply"
    bad.write_text("garbage")
    err = _error(["build-model", str(files / "a.ply"), str(bad), "-o", str(tmp_path / "m")],
                 capsys)  # fmt: skip
    assert "got 1 file(s) with 0 distinct mesh(es)" in err
    assert f"`TARGET`: {str(bad)!r} is not a PLY file" in err


@pytest.mark.parametrize("action", ["info", "modes", "fit", "explore"])
def test_model_errors_name_the_action(files, action, capsys):
    argv = ["model", action, str(files / "no_model")]
    if action == "fit":
        argv += [str(files / "a.ply"), "--landmarks", str(files / "a.csv")]
    assert main(argv) == 2
    assert capsys.readouterr().err.startswith(f"o3dreg model {action}: error: MODEL: ")


@pytest.mark.parametrize(
    ("option", "expected"),
    [
        (["--crop-box", "1000", "1000", "1000", "2000", "2000", "2000"],
         "`--crop-box` [1000, 1000, 1000]..[2000, 2000, 2000] removed every triangle"),
        (["--crop-plane", "1000", "0", "0", "1", "0", "0"],
         "`--crop-plane` (point [1000, 0, 0], normal [1, 0, 0]) removed every triangle"),
    ],
)  # fmt: skip
def test_reconstruct_names_the_crop_that_removed_everything(files, option, expected, capsys):
    err = _error(["reconstruct", str(PITCH), "-o", str(files / "o.ply"), "--threshold", "100",
                  *option], capsys)  # fmt: skip
    assert expected in err and "the mesh spans" in err and "crop_mesh" not in err


# A folder that exists, passes the checks made before any work (root may write anywhere) and
# refuses new files: writing there fails at write time, as a full disk would.
REFUSING = "/proc/self/fd"
needs_proc = pytest.mark.skipif(not os.path.isdir(REFUSING), reason="needs Linux /proc")


@needs_proc
@pytest.mark.parametrize(
    ("option", "name"), [("--report", "r.json"), ("--deformation", "d.npz"), ("--html", "p.html")]
)
def test_register_outputs_failing_at_write_time_name_their_option(files, option, name, capsys):
    path = f"{REFUSING}/{name}"
    err = _error(["register", str(files / "a.ply"), str(files / "b.ply"), "-o",
                  str(files / "reg.ply"), "--levels", "2", option, path], capsys)  # fmt: skip
    assert f"`{option}`: cannot write {path!r}" in err
    assert "`path`" not in err and "`report`" not in err
    assert not (files / "reg.ply").exists()  # all the outputs or none


STATISMO = DATA / "statismo" / "scalismo-asm-model.h5"


@needs_proc
@pytest.mark.parametrize("action", ["fit", "modes", "explore"])
def test_model_outputs_failing_at_write_time_name_their_option(files, tmp_path, action, capsys):
    argv = ["model", action, str(STATISMO)]
    page = {"fit": "x.csv", "modes": "", "explore": "e.html"}[action]
    written = {"fit": "x.csv", "modes": "mean.ply", "explore": "e.html"}[action]
    if action == "fit":
        from o3dreg.shape.statismo import read_statismo

        mean = read_statismo(STATISMO).mesh()
        write_triangle_mesh(tmp_path / "mean.ply", mean)
        (tmp_path / "lm.csv").write_text(
            "label,x,y,z\n"
            + "".join(f"{k},{','.join(map(str, mean.vertices[i]))}\n" for k, i in
                      (("a", 0), ("b", 10), ("c", 20)))
        )  # fmt: skip
        argv += [str(tmp_path / "mean.ply"), "--landmarks", str(tmp_path / "lm.csv"),
                 "--onto", "closest"]  # fmt: skip
    argv += ["-o", f"{REFUSING}/{page}".rstrip("/")]
    err = _error(argv, capsys)
    assert f"`--output`: cannot write {f'{REFUSING}/{written}'!r}" in err and "`path`" not in err


def test_negative_numbers_in_scientific_notation_or_lists_are_values(files, capsys):
    # argparse reads -1e9 and -1,0,0 as options (its negative numbers are plain ones such as -3):
    # they are values here, checked like any other.
    argv = ["reconstruct", str(PITCH), "-o", str(files / "o.ply"), "--threshold"]
    for value in ("-1e9", "--threshold=-1e9"):
        err = _error([*argv, value] if value == "-1e9" else [*argv[:-1], value], capsys)
        assert "--threshold must lie strictly between" in err and "got -1e+09" in err
    args = build_parser().parse_args(
        _numbers_as_values(["model", "explore", "m/", "--up", "-1,0,0"])
    )
    assert args.up == [-1.0, 0.0, 0.0]
    args = build_parser().parse_args(
        _numbers_as_values([
            "reconstruct", "in.nrrd", "-o", "o.ply", "--threshold", "1", "--crop-box", "-1e2", "-.5", "-3", "1E2", "5", "6",
        ])
    )  # fmt: skip
    assert args.crop_box == [-100.0, -0.5, -3.0, 100.0, 5.0, 6.0]
    with pytest.raises(SystemExit):  # a usage error: argparse exits
        main(["model", "explore", "m/", "--up", "-1,0"])
    assert "expected three numbers X,Y,Z, got '-1,0'" in capsys.readouterr().err  # as typed


def test_a_value_starting_with_a_dash_is_shown_how_to_pass(files, capsys):
    # A file name starting with '-' is an option to argparse: the message says to write it
    # after '=', and tokens after '--' are never taken for numbers.
    argv = ["reconstruct", str(PITCH), "-o", "-out.ply"]
    with pytest.raises(SystemExit) as usage:  # a usage error: argparse exits
        main(argv)
    err = capsys.readouterr().err
    assert usage.value.code == 2 and "expected one argument" in err and "--output=-name" in err
    assert _numbers_as_values(["--up", "-1,0,0", "--", "-1,0,0"]) == [
        "--up", " -1,0,0", "--", "-1,0,0",
    ]  # fmt: skip


def test_a_file_whose_name_holds_the_library_name_keeps_its_name(files, tmp_path, capsys):
    # Only the library's name of the parameter is replaced, never the user's value quoted in the
    # message: --landmarks 'lm`path`.fcsv' read "no such file 'lm`--landmarks`.fcsv'".
    (tmp_path / "lm`path`.csv").write_text("label,l,p,s\np,1,0,0\nq,0,1\n")  # a short row
    for name in ("missing`path`.csv", "lm`path`.csv"):
        err = _error(
            ["register", str(files / "a.ply"), str(files / "b.ply"), "--landmarks",
             str(tmp_path / name), str(files / "b.csv"), "-o", str(tmp_path / "out.ply")],
            capsys,
        )  # fmt: skip
        assert f"{name}'" in err and "`--landmarks TEMPLATE_FILE`" in err, err


def test_named_as_renames_outside_quoted_values_only():
    from o3dreg._validation import named_as

    with pytest.raises(OSError, match=r"^`INPUT`: no such file 'a`path`b' \(the model's\)$"):
        with named_as("INPUT"):
            raise OSError("`path`: no such file 'a`path`b' (the model's)")
    with pytest.raises(ValueError, match='^`X` and "it\'s `path`" and `X`$'):
        with named_as("X"):
            raise ValueError('`path` and "it\'s `path`" and `path`')


def test_a_template_with_a_stray_vertex_is_named_as_typed(files, tmp_path, capsys):
    # The library checks the template as `source` (register) or `template` (build-model).
    import numpy as np

    sphere = o3d.geometry.TriangleMesh.create_sphere(5.0, 10)
    stray = np.vstack([np.asarray(sphere.vertices), [[0.0, 0.0, 0.0]]])
    write_triangle_mesh(tmp_path / "t.ply", (stray, np.asarray(sphere.triangles)))
    t, a, b = str(tmp_path / "t.ply"), str(files / "a.ply"), str(files / "b.ply")
    out = str(tmp_path / "out")
    for argv, typed in (
        (["register", t, a, "-o", f"{out}.ply", "--levels", "2"], "`SOURCE`"),
        (["build-model", t, a, b, "-o", out, "--levels", "2"], "`TEMPLATE`"),
    ):
        err = _error(argv, capsys)
        assert f"{typed} must have every vertex on a triangle" in err, err


def test_a_default_output_failing_names_the_option_that_sets_it(tmp_path, capsys):
    # Without -o the page goes beside a .h5 model (MODEL_explorer.html): a folder of that name
    # there cannot be written over, and the message names the option that chooses another
    # place, not MODEL (which names the model read).
    model = tmp_path / "m.h5"
    model.write_bytes(STATISMO.read_bytes())
    (tmp_path / "m_explorer.html").mkdir()
    err = _error(["model", "explore", str(model)], capsys)
    assert "`--output (its default)`" in err and "MODEL" not in err
