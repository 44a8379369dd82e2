"""``o3dreg build-model`` and ``o3dreg model info/modes/fit``; the mandible example (slow)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _helpers import population

from o3dreg import write_landmarks, write_triangle_mesh
from o3dreg.cli import main
from o3dreg.io.mesh import read_triangle_mesh
from o3dreg.registration.verdict import STATUSES, worst_status

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli")
    (tv, tf), targets, truths, _, poses = population(6, seed=7)
    write_triangle_mesh(folder / "template.ply", (tv, tf))
    for i, t in enumerate(targets):
        write_triangle_mesh(folder / f"p{i}.ply", t)
    (folder / "broken.ply").write_text("garbage")
    write_landmarks(folder / "lm.mrk.json", ["a", "b"], tv[[0, 100]])
    truth = truths[5][[0, 100]] @ poses[5][:3, :3].T + poses[5][:3, 3]
    write_landmarks(folder / "truth.csv", ["a", "b"], truth)
    return folder


def build_model(files, patients, output, *options: str) -> int:
    """``o3dreg build-model TEMPLATE PATIENTS... -o OUTPUT OPTIONS...`` on the fixture's files."""
    return main(
        ["build-model", str(files / "template.ply"), *patients, "-o", str(output), *options]
    )


def test_build_model_info_modes_fit(files, capsys):
    out = files / "model"
    targets = [str(files / f"p{i}.ply") for i in range(5)] + [str(files / "broken.ply")]
    code = build_model(files, targets, out, "--levels", "2,4,8")
    assert code == 1  # the model is built, but one patient failed
    text = capsys.readouterr().out
    assert "broken" in text and "failed" in text and "Variances %" in text
    for name in (
        "model.npz",
        "model.h5",
        "mean.ply",
        "variance.txt",
        "report.json",
        "template.ply",
    ):
        assert (out / name).is_file(), name
    assert (out / "quality" / "generalization.png").is_file()
    report = json.loads((out / "report.json").read_text())
    assert report["failed"] == ["broken"] and len(report["registered"]) == 5
    # p1, a deformed sphere, has a rigid start that ties with a pose 85 degrees away (its
    # registration ends 4% of its size off, ~1% for the others): flagged, left out of the model.
    assert report["in_model"] == ["p0", "p2", "p3", "p4"]

    assert main(["model", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["points"] > 0 and len(info["variances"]) == 3

    assert (
        main(
            ["model", "modes", str(out), "--modes", "1", "--sd", "-2", "2", "-o", str(files / "m")]
        )
        == 0
    )
    assert sorted(p.name for p in (files / "m").iterdir()) == [
        "mean.ply",
        "mode1_+2sd.ply",
        "mode1_-2sd.ply",
    ]
    capsys.readouterr()

    code = main(
        [
            "model", "fit", str(out), str(files / "p5.ply"),
            "--landmarks", str(files / "lm.mrk.json"), "--truth", str(files / "truth.csv"),
            "-o", str(files / "pred.csv"), "--json",
        ]
    )  # fmt: skip
    result = json.loads(capsys.readouterr().out)
    assert code in (0, 1)  # 1: the fit ran but did not meet its tolerance
    # A 4-mode model of 5 registered shapes: errors of a few mm at most on a 30 mm shape.
    assert result["mean_error"] < 3.0
    assert (files / "pred.csv").is_file()
    # Read through a registration of the instance onto the patient (the default), whose verdict
    # joins the fit's: the exit status follows the worse.
    assert result["onto"] == "registration" and result["registration"]["status"] in STATUSES
    assert result["status"] == worst_status(
        result["fit"]["status"], result["registration"]["status"]
    )
    assert code == (0 if result["status"] == "ok" else 1)
    assert result["registration"]["levels"] == [8, 16]  # the default levels from 8 cells on
    code = main(
        [
            "model", "fit", str(out), str(files / "p5.ply"), "--landmarks",
            str(files / "lm.mrk.json"), "--truth", str(files / "truth.csv"),
            "--registration-levels", "4,8", "--json",
        ]
    )  # fmt: skip
    levels = json.loads(capsys.readouterr().out)
    assert levels["registration"]["levels"] == [4, 8] and levels["mean_error"] < 3.0
    # Levels for a registration that does not run are refused, naming both options.
    fit_closest = ["model", "fit", str(out), str(files / "p5.ply"), "--onto", "closest"]
    assert main([*fit_closest, "--landmarks", str(files / "lm.mrk.json"),
                 "--registration-levels", "8"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "--registration-levels" in err and "--onto closest" in err
    code = main(
        [
            "model", "fit", str(out), str(files / "p5.ply"), "--landmarks",
            str(files / "lm.mrk.json"), "--truth", str(files / "truth.csv"), "--onto", "closest",
            "--json",
        ]
    )  # fmt: skip
    closest = json.loads(capsys.readouterr().out)
    assert closest["registration"] is None and closest["status"] == closest["fit"]["status"]
    assert closest["mean_error"] < 3.0
    # Every landmark format its help lists is written (.fcsv and .pp were refused).
    for suffix in (".fcsv", ".pp"):
        code = main(
            ["model", "fit", str(out), str(files / "p5.ply"), "--landmarks",
             str(files / "lm.mrk.json"), "-o", str(files / f"pred{suffix}"), "-q"]
        )  # fmt: skip
        assert code in (0, 1) and (files / f"pred{suffix}").is_file()
    # Repeated labels make a prediction, or its error, ambiguous: refused before the fit.
    (files / "dup_lm.csv").write_text("label,x,y,z\na,0,0,0\na,1,1,1\n")
    (files / "dup_truth.csv").write_text(
        (files / "truth.csv").read_text() + (files / "truth.csv").read_text().splitlines()[-1]
    )
    fit = ["model", "fit", str(out), str(files / "p5.ply"), "--landmarks"]
    assert main([*fit, str(files / "dup_lm.csv")]) == 2
    assert "repeats landmark labels ['a']" in capsys.readouterr().err
    assert main([*fit, str(files / "lm.mrk.json"), "--truth", str(files / "dup_truth.csv")]) == 2
    assert "--truth repeats landmark labels ['b']" in capsys.readouterr().err
    # Landmarks away from the mean given with the model's .h5 file (no template in it: its
    # mean, in the Procrustes frame, takes landmarks; a template in the patients' frame lies
    # elsewhere): the refusal says where they go.
    tv = np.asarray(read_triangle_mesh(files / "template.ply").vertices)
    write_landmarks(files / "lm_far.mrk.json", ["a", "b"], tv[[0, 100]] + 200.0)
    h5_fit = ["model", "fit", str(out / "model.h5"), str(files / "p5.ply"), "--landmarks"]
    assert main([*h5_fit, str(files / "lm_far.mrk.json")]) == 2
    assert "a .h5 model holds no template: its landmarks go on its mean shape" in (
        capsys.readouterr().err
    )
    # -q: nothing on standard output, for every model action (they printed their tables).
    assert main(["model", "info", str(out), "-q"]) == 0
    assert main(["model", "modes", str(out), "-o", str(files / "mq"), "-q"]) == 0
    assert capsys.readouterr().out == ""
    # The model folder's own page is rewritten; the default page beside a statismo file is
    # anyone's: kept unless --overwrite.
    assert main(["model", "explore", str(out), "-q"]) == 0
    beside = out / "model_explorer.html"
    beside.write_text("my notes")
    assert main(["model", "explore", str(out / "model.h5"), "-q"]) == 2
    assert "--overwrite" in capsys.readouterr().err and beside.read_text() == "my notes"
    assert main(["model", "explore", str(out / "model.h5"), "-q", "--overwrite"]) == 0
    assert beside.read_text() != "my notes"

    # A second run resumes: every patient but the broken one is skipped. The folder holds a
    # model: rebuilding it needs --overwrite (two patients the verdict passes).
    again = [targets[0], targets[2]]
    assert build_model(files, again, out, "--json", "--levels", "2,4,8") == 2
    assert "--overwrite" in capsys.readouterr().err
    assert build_model(files, again, out, "--json", "--levels", "2,4,8", "--overwrite") == 0
    rerun = json.loads(capsys.readouterr().out)
    assert [p["status"] for p in rerun["patients"]] == ["registered", "registered"]


def test_cli_errors(files, tmp_path, capsys):
    assert main(["model", "info", str(tmp_path)]) == 2
    assert "no model.npz" in capsys.readouterr().err
    out = tmp_path / "one"
    code = build_model(files, [str(files / "p0.ply")], out, "--levels", "2")
    # One patient cannot make a model: refused before any work, not after the registrations.
    assert code == 2
    assert "at least 2 distinct patient meshes" in capsys.readouterr().err
    assert not out.exists()
    # A malformed --levels is refused by the argument parser: exit status 2, as for bad input.
    with pytest.raises(SystemExit) as exc:
        build_model(files, [str(files / "p0.ply")], out, "--levels", "x")
    assert exc.value.code == 2
    assert "expected comma-separated integers" in capsys.readouterr().err


def test_too_few_ok_patients_still_print_their_json(files, tmp_path, capsys):
    # One patient registers, one file cannot be read: no model (exit 1), and a script reading
    # --json gets the patients and "model": null rather than nothing.
    out = tmp_path / "few"
    patients = [str(files / "p0.ply"), str(files / "broken.ply")]
    code = build_model(files, patients, out, "--levels", "2", "--json")
    captured = capsys.readouterr()
    assert code == 1
    report = json.loads(captured.out)
    assert report["model"] is None and report["failed"] == ["broken"]
    assert report["registered"] == ["p0"] and "a model needs at least 2" in report["message"]
    assert "a model needs at least 2" in captured.err


def test_quiet_build_model_draws_no_progress_bar_on_a_terminal(files, tmp_path, monkeypatch):
    import o3dreg.cli._model as command

    asked = {}

    def stop(*args, progress, **kwargs):
        asked["progress"] = progress
        raise OSError("stopped here")

    monkeypatch.setattr(command, "build_model_folder", stop)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    patients = [str(files / "p0.ply"), str(files / "p1.ply")]
    for quiet, shown in ((["-q"], False), ([], True)):
        assert build_model(files, patients, tmp_path / "m", *quiet) == 2
        assert asked["progress"] is shown


def test_one_mesh_under_two_names_is_refused_before_any_work(files, tmp_path, capsys):
    # Registered, they would leave model.npz, template.ply and registrations/ behind and end in
    # numpy's "cannot reshape array of size 0": refused before any work.
    twin = tmp_path / "twin.ply"
    twin.write_bytes((files / "p0.ply").read_bytes())
    out = tmp_path / "model"
    code = build_model(files, [str(files / "p0.ply"), str(twin)], out, "--levels", "2")
    err = capsys.readouterr().err
    assert code == 2
    assert "at least 2 distinct patient meshes" in err and "got 2 file(s) with 1 distinct" in err
    assert f"{files / 'p0.ply'} and {twin} hold the same mesh" in err
    assert not out.exists()


def test_a_repeated_patient_beside_others_is_kept_with_a_warning(tmp_path, caplog):
    from o3dreg.app.model_folder import _check_distinct_patients

    _, targets, *_ = population(2, seed=7)
    for name, mesh in (("a", targets[0]), ("b", targets[0]), ("c", targets[1])):
        write_triangle_mesh(tmp_path / f"{name}.ply", mesh)
    paths = [str(tmp_path / f"{name}.ply") for name in "abc"]
    with caplog.at_level("WARNING", logger="o3dreg"):
        _check_distinct_patients(paths)
    assert f"{paths[0]} and {paths[1]} hold the same mesh" in caplog.text
    # An unreadable file counts as distinct (the batch reports it).
    (tmp_path / "broken.ply").write_text("garbage")
    _check_distinct_patients([paths[0], str(tmp_path / "broken.ply")])


@pytest.mark.slow
def test_mandible_example(shared_data, tmp_path):
    if not (shared_data / "mandibles" / "masks").is_dir():
        pytest.skip("mandible masks absent from the shared data")
    run = subprocess.run(
        [
            sys.executable,
            str(ROOT / "examples" / "mandible_model.py"),
            str(tmp_path),
            "--jobs",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert len(report["variances"]) == 6
    assert np.isclose(report["variances"][-1]["cumulative"], 1.0)


def test_build_model_on_a_dask_scheduler_address(files, tmp_path, capsys):
    # `--scheduler ADDRESS` as on a cluster; here the scheduler is a LocalCluster on loopback.
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(
        n_workers=1,
        threads_per_worker=2,
        processes=False,
        dashboard_address=None,
        protocol="tcp://",
        host="127.0.0.1",
    )
    with cluster:
        targets = [str(files / f"p{i}.ply") for i in range(3)]
        code = build_model(
            files, targets, tmp_path / "model", "--levels", "2,4",
            "--scheduler", cluster.scheduler_address, "-q",
        )  # fmt: skip
    report = json.loads((tmp_path / "model" / "report.json").read_text())
    assert len(report["registered"]) == 3
    # Exit 1 for the flagged p1 (see test_build_model_info_modes_fit); the model is built.
    assert code == 1 and report["in_model"] == ["p0", "p2"]


def test_inputs_the_model_folder_would_write_over_are_refused(files, tmp_path, capsys):
    # Before: `build-model w/template.ply w/p0.ply ... -o w` rewrote the user's w/template.ply
    # with the copy the folder keeps (exit 0); a patient named template.ply there was replaced
    # by the template, then registered as a patient.
    work = tmp_path / "w"
    work.mkdir()
    for name in ("template.ply", "p0.ply", "p1.ply"):
        (work / name).write_bytes((files / name).read_bytes())
    before = {p.name: p.read_bytes() for p in work.iterdir()}
    patients = [str(work / "p0.ply"), str(work / "p1.ply")]
    code = main(["build-model", str(work / "template.ply"), *patients, "-o", str(work)])
    assert code == 2
    assert "`TEMPLATE`" in capsys.readouterr().err
    code = build_model(files, [str(work / "template.ply"), *patients], work)
    assert code == 2
    assert "is a file the model folder" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in work.iterdir()} == before  # nothing written


def test_build_model_slides_by_bending_energy(files, tmp_path):
    # --slide: the report names how the semilandmarks were slid (bending energy, the default
    # criterion), and the model is built from the slid shapes, not the registered ones.
    patients = [str(files / f"p{i}.ply") for i in (0, 2, 3)]
    means = {}
    for flag in ([], ["--slide"]):
        out = tmp_path / ("slid" if flag else "plain")
        assert build_model(files, patients, out, "--levels", "2,4", "-q", *flag) == 0
        report = json.loads((out / "report.json").read_text())
        means[bool(flag)] = np.asarray(read_triangle_mesh(out / "mean.ply").vertices)
    assert report["sliding"]["criterion"] == "bending" and report["sliding"]["iterations"] >= 1
    # Both folders register the same patients alike: their means differ by the slides alone
    # (a fraction of a millimetre on this ~30 mm shape).
    moved = np.linalg.norm(means[True] - means[False], axis=1)
    assert 1e-3 < moved.mean() < 3.0


def test_build_model_refuses_a_slide_too_large_before_registering(
    files, tmp_path, capsys, monkeypatch
):
    # Sliding's dense solve has a size limit (BENDING_MAX_POINTS): a template past it is
    # refused before any registration, naming --slide, rather than after all of them.
    import o3dreg.shape.sliding as sliding

    patients = [str(files / f"p{i}.ply") for i in (0, 2, 3)]
    out = tmp_path / "big"
    monkeypatch.setattr(sliding, "BENDING_MAX_POINTS", 10)
    code = build_model(files, patients, out, "--levels", "2", "--slide")
    err = capsys.readouterr().err
    assert code == 2 and "`slide` (--slide)" in err and "at most 10" in err
    assert not (out / "registrations").exists()
