"""``--labels``: the landmarks of a file to use, for ``model fit`` and ``build-model`` (register's
are in tests/registration/test_landmark_start.py)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from _helpers import population

from o3dreg import build_shape_model, write_landmarks, write_triangle_mesh
from o3dreg.cli import main

#: Template vertices of the landmarks on the bone (a, b, c); "skull" lies far off it.
PICKS = [0, 100, 200]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A model folder (a model of 5 shapes, its template) and a patient, with a landmark file
    holding the template's 3 landmarks and one far off it (a Slicer file of a mandible with a
    landmark on the skull)."""
    folder = tmp_path_factory.mktemp("labels")
    (tv, tf), targets, truths, _, poses = population(6, seed=7)
    model = folder / "model"
    model.mkdir()
    build_shape_model(truths[:5], tf).save(model / "model.npz")
    write_triangle_mesh(model / "template.ply", (tv, tf))
    write_triangle_mesh(folder / "patient.ply", targets[5])
    size = float(np.linalg.norm(np.ptp(tv, axis=0)))
    skull = tv[0] + [0.0, 0.0, 2.0 * size]
    write_landmarks(
        folder / "lm.fcsv", ["a", "skull", "b", "c"], np.vstack([tv[0], skull, tv[PICKS[1:]]])
    )
    truth = truths[5][PICKS] @ poses[5][:3, :3].T + poses[5][:3, 3]
    write_landmarks(folder / "truth.csv", ["a", "b", "c"], truth)  # no "skull" on the patient
    return folder


def fit(files, *options: str) -> list[str]:
    return [
        "model", "fit", str(files / "model"), str(files / "patient.ply"),
        "--landmarks", str(files / "lm.fcsv"), "--onto", "closest", *options,
    ]  # fmt: skip


def test_fit_refuses_landmarks_off_the_template_and_names_the_labels_to_choose(files, capsys):
    assert main(fit(files, "--json")) == 2
    err = capsys.readouterr().err
    assert "landmarks off the template" in err and "skull (" in err
    assert err.rstrip().endswith("choose the landmarks on it with --labels a,b,c")


def test_fit_predicts_the_labels_chosen_only(files, capsys):
    code = main(fit(files, "--labels", "c,a", "--truth", str(files / "truth.csv"), "--json"))
    result = json.loads(capsys.readouterr().out)
    assert code in (0, 1)
    # Only the chosen landmarks, in their order; --truth needs only those.
    assert list(result["landmarks"]) == ["c", "a"] and list(result["errors"]) == ["c", "a"]
    assert result["mean_error"] < 3.0


def test_fit_refuses_a_label_the_file_lacks(files, capsys):
    assert main(fit(files, "--labels", "a,b,nose")) == 2
    err = capsys.readouterr().err
    assert "`labels` (--labels) must name landmarks of" in err and "lm.fcsv" in err
    assert "which holds a, skull, b, c; got a, b, nose: 'nose' is not in it" in err


def test_build_model_pairs_the_labels_chosen(files, tmp_path, capsys, caplog):
    # The patients' files lack the template file's "skull": without --labels the labels do not
    # match; with them the registrations start from the 3 pairs chosen.
    (tv, tf), targets, truths, _, poses = population(3, seed=3)
    write_triangle_mesh(tmp_path / "template.ply", (tv, tf))
    size = float(np.linalg.norm(np.ptp(tv, axis=0)))
    write_landmarks(
        tmp_path / "template.csv",
        ["a", "b", "c", "skull"],
        np.vstack([tv[PICKS], tv[0] + [0.0, 0.0, 2.0 * size]]),
    )
    patients = []
    for i in range(2):
        write_triangle_mesh(tmp_path / f"p{i}.ply", targets[i])
        pts = truths[i][PICKS] @ poses[i][:3, :3].T + poses[i][:3, 3]
        write_landmarks(tmp_path / f"p{i}.fcsv", ["c", "b", "a"], pts[::-1])
        patients.append(str(tmp_path / f"p{i}.ply"))
    command = [
        "build-model", str(tmp_path / "template.ply"), *patients, "--levels", "2",
        "--landmarks", str(tmp_path / "template.csv"), "--json",
    ]  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="o3dreg"):
        assert main([*command, "-o", str(tmp_path / "m0")]) == 2
    err = capsys.readouterr().err
    assert "['skull'] only in `--landmarks`" in err
    # The template's landmark off its surface is named, with the --labels that leave it out.
    assert "template landmarks far from the template surface" in caplog.text
    assert "skull (" in caplog.text and "(--labels a,b,c)" in caplog.text
    assert main([*command, "-o", str(tmp_path / "m1"), "--labels", "a,b,nose"]) == 2
    err = capsys.readouterr().err
    assert "`labels` (--labels) must name landmarks of" in err
    assert "which holds a, b, c, skull; got a, b, nose: 'nose' is not in it" in err
    assert not (tmp_path / "m1" / "registrations").exists()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="o3dreg"):
        code = main([*command, "-o", str(tmp_path / "m2"), "--labels", "a,b,c"])
    report = json.loads(capsys.readouterr().out)
    assert code in (0, 1) and len(report["registered"]) == 2
    assert "far from the template surface" not in caplog.text


def test_build_model_names_a_patient_whose_landmarks_are_off_its_surface(tmp_path, caplog):
    # p1's file holds its landmarks with x and y negated (RAS written against an LPS mesh): a
    # rotation by 180 degrees, which the landmark start fits exactly and places wrongly.
    (tv, tf), targets, truths, _, poses = population(3, seed=3)
    write_triangle_mesh(tmp_path / "template.ply", (tv, tf))
    write_landmarks(tmp_path / "template.csv", ["a", "b", "c"], tv[PICKS])
    for i in range(2):
        write_triangle_mesh(tmp_path / f"p{i}.ply", targets[i])
        pts = truths[i][PICKS] @ poses[i][:3, :3].T + poses[i][:3, 3]
        write_landmarks(tmp_path / f"p{i}.fcsv", ["a", "b", "c"], pts * [1 - 2 * i, 1 - 2 * i, 1])
    with caplog.at_level(logging.WARNING, logger="o3dreg"):
        main([
            "build-model", str(tmp_path / "template.ply"), str(tmp_path / "p0.ply"),
            str(tmp_path / "p1.ply"), "--levels", "2", "--landmarks", str(tmp_path / "template.csv"),
            "-o", str(tmp_path / "m"), "--json",
        ])  # fmt: skip
    far = [r.getMessage() for r in caplog.records if "lie far from its surface" in r.getMessage()]
    assert len(far) == 1 and "p1.ply" in far[0] and "of its 3 landmarks" in far[0]
    assert "in the mesh's coordinates" in far[0]


def test_build_model_labels_need_landmarks(files, tmp_path, capsys):
    patient = str(files / "patient.ply")
    template = str(files / "model" / "template.ply")
    command = ["build-model", template, patient, patient, "-o", str(tmp_path / "m")]
    assert main([*command, "--labels", "a,b,c"]) == 2
    err = capsys.readouterr().err
    assert "--labels chooses landmarks of --landmarks: give --landmarks" in err
