"""Batch registration: files per patient, failures reported, resume, executors (incl. Dask)."""

from __future__ import annotations

import concurrent.futures as cf
import json
import os

import numpy as np
import pytest
from _helpers import FAST, population

from o3dreg import register_batch, registration_elastic, write_triangle_mesh
from o3dreg.app.batch import resume_key, save_registered


@pytest.fixture(scope="module")
def small():
    (tv, tf), targets, _, _, poses = population(3, seed=2)
    return (tv, tf), targets, np.stack(poses)


def test_batch_writes_each_patient_and_reports_failures(small, tmp_path):
    template, targets, _poses = small
    bad = tmp_path / "broken.ply"
    bad.write_text("not a mesh")
    good = tmp_path / "good.ply"
    write_triangle_mesh(good, targets[0])
    out = tmp_path / "out"
    seen = []
    result = register_batch(
        template, [str(good), str(bad), targets[1]], out, levels=FAST, callback=seen.append
    )
    assert [r.name for r in result.records] == ["good", "broken", "patient002"]
    assert [r.status for r in result.records] == ["registered", "failed", "registered"]
    assert "broken.ply' is not a PLY file" in result.records[1].message
    assert len(seen) == 3
    for name in ("good", "patient002"):
        for suffix in (".ply", ".npz", ".json"):
            assert (out / f"{name}{suffix}").is_file()
        record = json.loads((out / f"{name}.json").read_text())
        assert record["status"] == "registered" and record["distances"]["source_to_target_mean"] < 1
        # How the rigid start was chosen travels with the record (no init given: searched).
        start = record["rigid_start"]
        assert start["candidates"] >= 1 and start["score"] >= 0.0
        assert start["runner_up_score"] is None or start["runner_up_score"] >= start["score"]
    assert result.records[1].rigid_start is None  # a failure has none
    assert json.loads((out / "broken.json").read_text())["status"] == "failed"

    # Strict JSON everywhere (a failure's measures were written as NaN, which JavaScript's
    # JSON.parse rejects): what could not be measured is null, and a rerun reads it back.
    def no_constant(constant):
        raise AssertionError(f"{constant} is not JSON")

    for path in out.glob("*.json"):
        json.loads(path.read_text(), parse_constant=no_constant)
    assert json.loads((out / "broken.json").read_text())["min_jacobian_determinant"] is None
    again = register_batch(template, [str(good), str(bad), targets[1]], out, levels=FAST)
    assert [r.status for r in again.records] == ["registered", "failed", "registered"]
    assert "broken" in again.table()
    assert not [p for p in os.listdir(out) if ".part" in p]  # nothing half-written
    table = result.table()
    assert "broken" in table and "error:" in table and "s->t mean" in table
    names, shapes = result.shapes()
    assert names == ("good", "patient002") and shapes.shape == (2, len(template[0]), 3)


def test_batch_resumes_and_force_reregisters(small, tmp_path):
    template, targets, _ = small
    first = register_batch(template, targets[:2], tmp_path, levels=FAST)
    assert not any(r.skipped for r in first.records)
    again = register_batch(template, targets[:2], tmp_path, levels=FAST)
    assert all(r.skipped for r in again.records)
    assert again.records[0].distances == first.records[0].distances
    assert again.records[0].rigid_start == first.records[0].rigid_start is not None
    forced = register_batch(template, targets[:2], tmp_path, levels=FAST, force=True)
    assert not any(r.skipped for r in forced.records)


def test_a_registration_saved_beforehand_is_not_made_again(small, tmp_path):
    template, targets, _ = small
    made = registration_elastic(template, targets[0], levels=FAST)
    key = resume_key(template, targets[0], levels=FAST)  # what the batch will look for
    saved = save_registered(tmp_path, "patient000", made, 1.0, "<array>", key=key)
    batch = register_batch(template, targets[:2], tmp_path, levels=FAST)
    assert [r.skipped for r in batch.records] == [True, False]
    assert batch.records[0].distances == saved.distances == made.distances.as_dict()
    names, shapes = batch.shapes()
    assert names == ("patient000", "patient001")
    # The PLY holds the vertices to float precision.
    np.testing.assert_allclose(shapes[0], made.vertices, atol=1e-5)


def test_interrupt_keeps_finished_patients(small, tmp_path):
    template, targets, _ = small

    def stop(record):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        register_batch(template, targets, tmp_path, levels=FAST, callback=stop)
    assert (tmp_path / "patient000.json").is_file()
    assert not (tmp_path / "patient001.json").exists()
    resumed = register_batch(template, targets, tmp_path, levels=FAST)
    assert [r.skipped for r in resumed.records] == [True, False, False]


def test_thread_pool_executor_gives_same_records(small, tmp_path):
    template, targets, poses = small
    serial = register_batch(template, targets, tmp_path / "a", levels=FAST, init=poses)
    with cf.ThreadPoolExecutor(2) as pool:
        parallel = register_batch(
            template, targets, tmp_path / "b", levels=FAST, init=poses, executor=pool
        )
    for a, b in zip(serial.records, parallel.records):
        assert a.name == b.name
        np.testing.assert_allclose(
            a.distances["source_to_target_mean"], b.distances["source_to_target_mean"], rtol=1e-9
        )


def test_dask_distributed_executor(small, tmp_path):
    distributed = pytest.importorskip("distributed")
    template, targets, poses = small
    cluster = distributed.LocalCluster(
        n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
    )
    with cluster, distributed.Client(cluster) as client:
        result = register_batch(
            template,
            targets,
            tmp_path,
            levels=FAST,
            init=poses,
            executor=client.get_executor(),
        )
    assert [r.status for r in result.records] == ["registered"] * 3


def test_batch_bad_input(small, tmp_path):
    template, targets, _ = small
    with pytest.raises(ValueError, match="at least one"):
        register_batch(template, [], tmp_path)
    with pytest.raises(ValueError, match="unique"):
        register_batch(template, targets[:2], tmp_path, names=["a", "a"])
    with pytest.raises(TypeError, match="sequence"):
        register_batch(template, "patient.ply", tmp_path)
    with pytest.raises(TypeError, match="unexpected registration option"):
        register_batch(template, targets, tmp_path, level=[])
    with pytest.raises(ValueError, match="init"):
        register_batch(template, targets, tmp_path, init=np.zeros((2, 4, 4)))
    # Refused before any patient is registered (each would fail the same way), nothing written.
    tv, tf = template
    stray = (np.vstack([tv, tv[:1] + 100.0]), tf)
    with pytest.raises(ValueError, match="`template` must have every vertex on a triangle"):
        register_batch(stray, targets, tmp_path / "stray")
    assert not (tmp_path / "stray").exists()


def test_patients_of_one_file_name_in_several_folders_get_distinct_names(small, tmp_path):
    # The common layout patients/<id>/bone.ply was refused ("`names` must be unique", an API
    # parameter the command line does not have). The fewest folders that tell them apart lead.
    template, targets, _ = small
    paths = []
    for case, target in zip(("case01", "case02"), targets[:2]):
        (tmp_path / case).mkdir()
        write_triangle_mesh(tmp_path / case / "bone.ply", target)
        paths.append(str(tmp_path / case / "bone.ply"))
    result = register_batch(template, paths, tmp_path / "out", levels=FAST)
    assert [r.name for r in result.records] == ["case01_bone", "case02_bone"]
    assert (tmp_path / "out" / "case02_bone.ply").is_file()


def test_default_names_never_meet_each_other_or_the_summary():
    # a/p.ply and b/p.ply are told apart as a_p and b_p, which met the stem of a_p.ply ("`names`
    # must be unique" after the template was written); a patient file summary.ply wrote its
    # record over the batch's summary.json.
    from o3dreg.app.batch import _default_names

    assert _default_names(["a/p.ply", "b/p.ply", "a_p.ply"]) == ["a_p", "b_p", "a_p_2"]
    assert _default_names(["x/summary.ply", "y/Summary.ply"]) == ["x_summary", "y_Summary"]
    assert _default_names(["summary.ply", "q.ply"]) == ["summary_2", "q"]
    assert _default_names(["A.ply", "a.ply"]) == ["A_1", "a_2"]  # one file on some systems


def test_given_names_are_refused_where_they_would_meet(small, tmp_path):
    template, targets, _ = small
    for names, message in (
        (["summary", "q"], "names the batch's own summary.json"),
        (["P", "p"], r"must be unique \(ignoring case\), got 'p' for targets 0 and 1"),
    ):
        with pytest.raises(ValueError, match=message):
            register_batch(template, targets[:2], tmp_path / "out", names=names, levels=FAST)
    assert not (tmp_path / "out").exists()


def test_resume_keys_leave_out_the_extra_terms_until_there_are_some(small):
    # A batch folder made before DistanceEstimation had `more_terms` keeps its keys (no patient
    # registered again for nothing); an extra term, when there is one, changes the key.
    from dataclasses import dataclass

    from o3dreg import DistanceEstimation, DistanceTerm
    from o3dreg.app.batch import _canonical

    assert "more_terms" not in _canonical(DistanceEstimation())

    @dataclass(frozen=True)
    class Nothing(DistanceTerm):
        def bind(self, context):
            return None

    template, target = small[0], small[1][0]
    plain = resume_key(template, target, estimation_method=DistanceEstimation())
    extra = resume_key(
        template, target, estimation_method=DistanceEstimation(more_terms=(Nothing(),))
    )
    assert plain == resume_key(template, target)
    assert extra != plain


def test_settings_with_a_term_holding_arrays_describe_themselves_as_json():
    # A model folder's report holds the settings: a term of one's own in `more_terms` whose
    # fields are arrays (landmark pairs) must not make the report unwritable.
    from dataclasses import dataclass

    from o3dreg import DistanceEstimation, DistanceTerm, RegistrationSettings

    @dataclass(frozen=True, eq=False)
    class Pairs(DistanceTerm):
        vertices: np.ndarray
        points: np.ndarray

        def bind(self, context):
            return None

    term = Pairs(np.array([1, 2]), np.zeros((2, 3)))
    settings = RegistrationSettings(estimation_method=DistanceEstimation(more_terms=(term,)))
    text = json.dumps(settings.as_dict())
    described = json.loads(text)["estimation_method"]["more_terms"][0]
    assert described == {"vertices": [1, 2], "points": [[0.0, 0.0, 0.0]] * 2}


def test_progress_off_a_terminal_is_a_line_per_patient(small, tmp_path, capsys):
    # A bar redraws with carriage returns: in a log or a CI job it reads as nothing until the
    # end. There each finished patient is a line (skipped ones count as done from the start).
    template, targets, _poses = small
    out = tmp_path / "out"
    register_batch(template, targets[:1], out, levels=FAST)
    capsys.readouterr()  # pytest's capture is no terminal
    result = register_batch(template, targets[:2], out, levels=FAST, progress=True)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("patients")]
    assert len(lines) == 1 and "\r" not in lines[0]
    assert lines[0].startswith(f"patients 2/2: patient001 ({result.records[1].verdict}) (")
