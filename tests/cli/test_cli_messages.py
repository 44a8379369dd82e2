"""The command line's messages: C++ libraries never on standard output, one-line option errors,
no progress bar in a log file, option values that cannot be meant refused."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import open3d as o3d
import pytest

from o3dreg import read_triangle_mesh, write_triangle_mesh
from o3dreg.cli import main

PITCH = Path(__file__).parents[1] / "data" / "pitch" / "CT_pitch.nii.gz"


def _o3dreg(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``o3dreg ARGS`` in a child process, standard output and error to pipes (no terminal)."""
    return subprocess.run(
        [sys.executable, "-m", "o3dreg", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("messages")
    write_triangle_mesh(folder / "sphere.ply", o3d.geometry.TriangleMesh.create_sphere(5.0, 10))
    (folder / "garbage.ply").write_bytes(b"garbage")
    (folder / "cut.stl").write_text(
        "solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0\n"
    )
    return folder


def test_open3d_messages_never_reach_standard_output(files, capfd):
    # Open3D prints its warnings ("[Open3D WARNING] Read PLY failed ...") on standard output:
    # the library reads quietly and says what is wrong in its exception.
    for name, message in (
        ("garbage.ply", "is not a PLY file"),
        ("cut.stl", "could not be read as a triangle mesh"),
    ):
        with pytest.raises(OSError, match=message):
            read_triangle_mesh(files / name)
    assert capfd.readouterr().out == ""
    done = _o3dreg("register", "garbage.ply", "sphere.ply", "-o", "r.ply", cwd=files)
    assert done.returncode == 2
    assert done.stdout == ""
    assert "o3dreg register: error:" in done.stderr


def test_a_bad_option_value_is_one_line_with_the_hint(files, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["register", "a.ply", "b.ply", "-o", "c.ply", "--levels", "abc"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "usage:" not in err
    assert err.startswith("o3dreg register: error: argument --levels:")
    assert "(see `o3dreg register --help`)" in err


@pytest.mark.parametrize(
    "argv, command",
    [
        (["register", "a.ply", "b.ply", "-o", "c.ply", "--lambda", "3"], "o3dreg register"),
        (["model", "fit", "m/", "p.ply", "--landmarks", "l.csv", "--bogus"], "o3dreg model fit"),
        (["--bogus"], "o3dreg"),
    ],
)
def test_an_unknown_option_names_the_command_it_was_given_to(argv, command, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "usage:" not in err
    assert err.startswith(f"{command}: error: unrecognized arguments: ")
    assert f"(see `{command} --help`)" in err


@pytest.mark.parametrize("value", ["2,,4", "2,4,", ",2"])
def test_a_list_with_an_empty_item_is_refused(value, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["register", "a.ply", "b.ply", "-o", "c.ply", "--levels", value])
    assert exc.value.code == 2
    assert "no empty item" in capsys.readouterr().err


def test_series_uid_on_a_nifti_file_is_refused(tmp_path, capsys):
    code = main(["reconstruct", str(PITCH), "-o", str(tmp_path / "b.ply"), "--threshold", "200",
                 "--series-uid", "1.2.3"])  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err
    assert "--series-uid" in err and "DICOM series in a folder" in err
    assert list(tmp_path.iterdir()) == []


def test_register_writes_no_progress_bar_into_a_log_file(files):
    done = _o3dreg("register", "sphere.ply", "sphere.ply", "-o", "r.ply", "--levels", "2",
                   cwd=files)  # fmt: skip
    assert done.returncode in (0, 1), done.stderr
    # Standard error is a file, not a terminal: no bar, no carriage returns.
    assert "\r" not in done.stderr and "level/s" not in done.stderr
    assert "verdict:" in done.stdout


def test_quiet_and_verbose_together_are_refused(capsys):
    # One before the command and one after it: quiet won, silently.
    with pytest.raises(SystemExit) as exc:
        main(["-q", "model", "info", "m", "-v"])
    assert exc.value.code == 2
    assert "-q/--quiet and -v/--verbose ask for opposite things" in capsys.readouterr().err
