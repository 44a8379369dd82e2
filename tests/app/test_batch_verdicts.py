"""Verdicts in batches: the population check, and flagged patients kept out of the model."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _helpers import population

from o3dreg import (
    read_triangle_mesh,
    registration_landmarks,
    write_landmarks,
    write_triangle_mesh,
)
from o3dreg.app.model_folder import build_model_folder, patient_landmark_file
from o3dreg.app.population import population_findings
from o3dreg.app.settings import RegistrationSettings
from o3dreg.cli import main
from o3dreg.registration.options import ElasticLevel


def test_population_findings_mark_the_outlier():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(200, 3)) * 30.0
    shapes = np.stack([base + rng.normal(size=base.shape) * 0.5 for _ in range(7)])
    shapes[4] = base + rng.normal(size=base.shape) * 6.0  # one shape far from the others
    names = [f"p{k}" for k in range(7)]
    distances = [{"source_to_target_mean": 0.3, "target_to_source_mean": 0.4}] * 7
    distances[2] = {"source_to_target_mean": 2.5, "target_to_source_mean": 0.41}
    found = population_findings(names, distances, shapes)
    assert sorted(found) == ["p2", "p4"]
    assert "mean template->patient distance" in found["p2"][0]
    assert "Procrustes residual" in found["p4"][0] and "robust z-score" in found["p4"][0]


def test_landmark_file_naming_rule(tmp_path):
    mesh = tmp_path / "case01.ply"
    mesh.write_text("")
    with pytest.raises(OSError, match=r"case01\.mrk\.json or .*case01\.fcsv or .*case01\.csv"):
        patient_landmark_file(mesh)
    (tmp_path / "case01.csv").write_text("label,x,y,z\n")
    assert patient_landmark_file(mesh) == str(tmp_path / "case01.csv")
    (tmp_path / "case01.fcsv").write_text("# Markups fiducial file version = 4.11\n")
    assert patient_landmark_file(mesh) == str(tmp_path / "case01.fcsv")  # Slicer's own
    (tmp_path / "case01.mrk.json").write_text("{}")
    assert patient_landmark_file(str(mesh)) == str(tmp_path / "case01.mrk.json")


def test_landmark_labels_choose_the_pairs_of_every_patient(tmp_path):
    # The template's file also holds a landmark the patients' files lack: the labels chosen are
    # paired, in every file; one the template's file lacks is refused before any work.
    (tv, tf), targets, truths, _, poses = population(2, seed=3)
    picks = [0, 40, 80]
    write_triangle_mesh(tmp_path / "template.ply", (tv, tf))
    template = read_triangle_mesh(tmp_path / "template.ply")
    write_landmarks(tmp_path / "template.csv", ["a", "b", "c", "skull"], tv[[*picks, 120]])
    paths = []
    for i, target in enumerate(targets):
        write_triangle_mesh(tmp_path / f"p{i}.ply", target)
        truth = truths[i][picks] @ poses[i][:3, :3].T + poses[i][:3, 3]
        write_landmarks(tmp_path / f"p{i}.csv", ["a", "b", "c"], truth)
        paths.append(str(tmp_path / f"p{i}.ply"))
    settings = RegistrationSettings(levels=(ElasticLevel(2),))
    start = settings.landmark_start(
        tmp_path / "template.csv", tmp_path / "p0.csv", labels=["a", "b", "c"]
    )
    own = registration_landmarks((["a", "b", "c"], tv[picks]), tmp_path / "p0.csv")
    np.testing.assert_allclose(start, own.transformation)  # the 3 pairs chosen, no more
    with pytest.raises(ValueError, match=r"\['skull'\] only in `source`"):
        settings.landmark_start(tmp_path / "template.csv", tmp_path / "p0.csv")
    with pytest.raises(
        ValueError,
        match=r"`landmark_labels` must name landmarks of '.*template.csv', which holds a, b, c, "
        r"skull; got a, nose: 'nose' is not in it",
    ):
        build_model_folder(
            template, paths, str(tmp_path / "bad"), settings=settings,
            landmarks=tmp_path / "template.csv", landmark_labels=["a", "nose"],
        )  # fmt: skip
    assert not (tmp_path / "bad").exists()
    with pytest.raises(ValueError, match="`landmark_labels` chooses landmarks of `landmarks`"):
        build_model_folder(template, paths, str(tmp_path / "bad"), landmark_labels=["a"])
    folder = build_model_folder(
        template,
        paths,
        str(tmp_path / "model"),
        settings=settings,
        landmarks=tmp_path / "template.csv",
        landmark_labels=["a", "b", "c"],
    )
    assert len(folder.batch.registered) == 2


def test_a_patient_in_other_units_is_flagged_and_left_out(tmp_path, capsys):
    # Six patients started from landmarks; patient p5's landmark file is in centimetres, so the
    # similarity start shrinks the template tenfold: verdict 'failed', not in the model.
    (tv, tf), targets, truths, _, poses = population(6, seed=3)
    write_triangle_mesh(tmp_path / "template.ply", (tv, tf))
    picks = [0, 40, 80, 120, 160]
    labels = [f"L{k}" for k in picks]
    write_landmarks(tmp_path / "template.csv", labels, tv[picks])
    paths = []
    for i, target in enumerate(targets):
        write_triangle_mesh(tmp_path / f"p{i}.ply", target)
        truth = truths[i][picks] @ poses[i][:3, :3].T + poses[i][:3, 3]
        if i == 5:
            truth = truth / 10.0
        write_landmarks(tmp_path / f"p{i}.csv", labels, truth)
        paths.append(str(tmp_path / f"p{i}.ply"))
    settings = RegistrationSettings(levels=(ElasticLevel(2), ElasticLevel(4)), start="similarity")
    folder = build_model_folder(
        read_triangle_mesh(tmp_path / "template.ply"),
        paths,
        str(tmp_path / "model"),
        settings=settings,
        landmarks=tmp_path / "template.csv",
    )
    record = {r.name: r for r in folder.batch.records}["p5"]
    assert record.verdict == "failed"
    assert any("times the template's size" in w for w in record.warnings)
    # The model holds exactly the patients whose verdict (with the population check) is 'ok'.
    assert "p5" not in folder.model.names
    assert set(folder.model.names) == {r.name for r in folder.batch.accepted}
    assert len(folder.model.names) >= 4
    report = json.loads((tmp_path / "model" / "report.json").read_text())
    assert report["flagged"]["p5"]["verdict"] == "failed" and "p5" not in report["in_model"]
    assert report["settings"]["start"] == "similarity"
    assert "failed" in folder.batch.table() and "times the template's size" in folder.batch.table()
    # The command line: the same, with --keep-flagged putting p5 back into the model.
    code = main(
        ["build-model", str(tmp_path / "template.ply"), *paths, "-o", str(tmp_path / "cli"),
         "--levels", "2,4", "--with-scaling", "--landmarks", str(tmp_path / "template.csv"),
         "--keep-flagged", "-q"]
    )  # fmt: skip
    assert code == 1
    assert "p5 (failed" in capsys.readouterr().err
    report = json.loads((tmp_path / "cli" / "report.json").read_text())
    assert "p5" in report["in_model"] and report["keep_flagged"]


def test_an_interrupted_model_leaves_no_model_files(tmp_path, monkeypatch):
    # Ctrl-C while the model's files were written left model.npz, model.h5, mean.ply, ... and
    # no report: a rerun was refused ("already holds a model") and `model info` read it. Now
    # the model's files go together; the registrations stay, and the rerun builds the model.
    import o3dreg.app.model_folder as model_folder

    (tv, tf), targets, _, _, _ = population(3, seed=5)
    write_triangle_mesh(tmp_path / "template.ply", (tv, tf))
    template = read_triangle_mesh(tmp_path / "template.ply")
    paths = []
    for i, target in enumerate(targets):
        write_triangle_mesh(tmp_path / f"p{i}.ply", target)
        paths.append(str(tmp_path / f"p{i}.ply"))
    out = tmp_path / "model"
    levels = [ElasticLevel(2)]

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(model_folder, "write_model_explorer", interrupted)
        with pytest.raises(KeyboardInterrupt):
            build_model_folder(template, paths, str(out), levels=levels)
    assert model_folder.existing_model_files(out) == []
    assert sorted(p.name for p in out.iterdir()) == ["registrations", "template.ply"]
    folder = build_model_folder(template, paths, str(out), levels=levels)
    assert all(r.skipped for r in folder.batch.records)  # resumed, not registered again
    assert (out / "report.json").is_file() and (out / "explorer.html").is_file()


def test_a_second_build_into_the_same_folder_is_refused_while_one_runs(tmp_path):
    # Two `build-model` runs into one new folder both exited 0 and the last one's model won.
    import fcntl

    import o3dreg.app.model_folder as model_folder

    (tv, tf), targets, _, _, _ = population(3, seed=5)
    write_triangle_mesh(tmp_path / "template.ply", (tv, tf))
    paths = []
    for i, target in enumerate(targets):
        write_triangle_mesh(tmp_path / f"p{i}.ply", target)
        paths.append(str(tmp_path / f"p{i}.ply"))
    out = tmp_path / "model"
    out.mkdir()
    template = read_triangle_mesh(tmp_path / "template.ply")
    with open(out / model_folder.LOCK_FILE, "a") as held:  # another build, holding the folder
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(OSError, match="another model build is writing"):
            build_model_folder(template, paths, str(out), levels=[ElasticLevel(2)])
    assert not (out / "registrations").exists()
    folder = build_model_folder(template, paths, str(out), levels=[ElasticLevel(2)])
    assert folder.model is not None
    assert not (out / model_folder.LOCK_FILE).exists()  # a finished build leaves no lock file


def test_the_summary_and_the_report_agree_on_a_population_outlier(tmp_path):
    # Two coarse levels from the identity leave p0 with a mean distance 4.5 times the others':
    # its own verdict is 'ok', the population check makes it 'suspect'. The batch's
    # summary.json said 'ok' while report.json said 'suspect'; and report.json stored sources
    # relative to where the command ran, each record relative to its own folder.
    (tv, tf), targets, _, _, poses = population(6, seed=3)
    write_triangle_mesh(tmp_path / "template.ply", (tv, tf))
    paths = []
    for i, (v, f) in enumerate(targets):
        unposed = (v - poses[i][:3, 3]) @ poses[i][:3, :3]  # in the template's frame
        write_triangle_mesh(tmp_path / f"p{i}.ply", (unposed, f))
        paths.append(str(tmp_path / f"p{i}.ply"))
    settings = RegistrationSettings(levels=(ElasticLevel(2), ElasticLevel(4)), start="identity")
    out = tmp_path / "model"
    folder = build_model_folder(
        read_triangle_mesh(tmp_path / "template.ply"), paths, str(out), settings=settings
    )
    checked = {r.name: r.verdict for r in folder.batch.records}
    outliers = [r.name for r in folder.batch.records if any("outlier" in w for w in r.warnings)]
    assert outliers and all(checked[name] == "suspect" for name in outliers), checked
    summary = json.loads((out / "registrations" / "summary.json").read_text())
    report = json.loads((out / "report.json").read_text())
    assert {d["name"]: d["verdict"] for d in summary} == checked
    assert {d["name"]: d["verdict"] for d in report["patients"]} == checked
    assert {d["source"] for d in report["patients"]} == {f"../p{i}.ply" for i in range(6)}


def test_a_folded_mode_is_found():
    # Semilandmarks that slid differently from patient to patient fold a mode's shape at 3 SD
    # (14% of a mandible model's triangles turned at -3 SD with --slide). Six copies of one
    # shape with 0.05 mm of noise: no fold; the same with the vertices of a patch shuffled in
    # three of them (moved along the surface past each other): folded modes.
    from o3dreg import build_shape_model
    from o3dreg.app.model_folder import folded_modes

    (tv, tf), _, truths, _, _ = population(6, seed=3)
    rng = np.random.default_rng(0)
    shapes = truths[0] + rng.normal(size=truths.shape) * 0.05
    assert folded_modes(build_shape_model(shapes, tf)) == []
    for k in (1, 2, 3):
        patch = rng.choice(len(tv), 60, replace=False)
        order = np.arange(len(tv))
        order[patch] = rng.permutation(patch)
        shapes[k] = shapes[k][order]
    folded = folded_modes(build_shape_model(shapes, tf))
    assert folded and all(f > 0.01 for _, _, f in folded)
