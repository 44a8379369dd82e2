"""A model folder's records name their patients relative to the records' folder: the explorer
finds the patients from any working folder, and says when one is missing."""

from __future__ import annotations

import json
import logging
import os
import re

import pytest
from _helpers import population

from o3dreg import ElasticCriteria, ElasticLevel, read_triangle_mesh, write_triangle_mesh
from o3dreg.app.model_folder import build_model_folder
from o3dreg.cli import main


def _cases(path):
    text = open(path, encoding="utf-8").read()
    found = re.search(
        r'<script id="o3dreg-data" type="application/json">(.*?)</script>', text, re.S
    )
    assert found is not None
    return json.loads(found.group(1))["cases"]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("relative")
    (tv, tf), targets, *_ = population(3, seed=7)
    (root / "patients").mkdir()
    write_triangle_mesh(root / "template.ply", (tv, tf))
    for i, t in enumerate(targets):
        write_triangle_mesh(root / "patients" / f"p{i}.ply", t)
    template = read_triangle_mesh(root / "template.ply")
    level = ElasticLevel(2, criteria=ElasticCriteria(max_iteration=50))
    here = os.getcwd()
    os.chdir(root)  # the patients given relative to where build-model runs
    try:
        build_model_folder(
            template, [f"patients/p{i}.ply" for i in range(3)], "model", levels=[level]
        )
    finally:
        os.chdir(here)
    return root


def test_records_name_patients_relative_to_their_folder(built):
    record = json.loads((built / "model" / "registrations" / "p0.json").read_text())
    assert record["source"] == os.path.join("..", "..", "patients", "p0.ply")


def test_model_explore_from_another_folder_finds_every_patient(built, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    page = tmp_path / "e.html"
    assert main(["model", "explore", str(built / "model"), "-o", str(page)]) == 0
    cases = _cases(page)
    assert [c["name"] for c in cases] == ["p0", "p1", "p2"]
    for case in cases:
        assert "patient" in case and case["patient"]["note"] == "", case.get("notes")


def test_a_missing_patient_is_named(built, tmp_path, monkeypatch, caplog):
    monkeypatch.chdir(tmp_path)
    moved = built / "patients" / "p1.ply"
    hidden = built / "p1.hidden"
    moved.rename(hidden)
    try:
        with caplog.at_level(logging.WARNING, logger="o3dreg"):
            assert (
                main(["model", "explore", str(built / "model"), "-o", str(tmp_path / "e.html")])
                == 0
            )
    finally:
        hidden.rename(moved)
    assert "p1: patient surface not shown" in caplog.text
    assert "p0" not in caplog.text


def test_a_rebuild_after_the_patients_moved_names_where_they_are(tmp_path):
    # The records reused by a rebuild kept the old paths: the explorer then showed no patient
    # surface ("no such file") although every patient was given where it now lies.
    (tv, tf), targets, *_ = population(3, seed=7)
    (tmp_path / "old").mkdir()
    paths = [str(write_triangle_mesh(tmp_path / "old" / f"p{i}.ply", t)) for i, t in
             enumerate(targets)]  # fmt: skip
    template = read_triangle_mesh(write_triangle_mesh(tmp_path / "template.ply", (tv, tf)))
    level = ElasticLevel(2, criteria=ElasticCriteria(max_iteration=50))
    build_model_folder(template, paths, str(tmp_path / "model"), levels=[level])
    (tmp_path / "old").rename(tmp_path / "new")
    moved = [str(tmp_path / "new" / f"p{i}.ply") for i in range(3)]
    again = build_model_folder(
        template, moved, str(tmp_path / "model"), levels=[level], overwrite=True
    )
    assert all(r.skipped for r in again.batch.records)  # the same patients: not registered again
    assert [r.source for r in again.batch.records] == moved
    record = json.loads((tmp_path / "model" / "registrations" / "p0.json").read_text())
    assert record["source"] == os.path.join("..", "..", "new", "p0.ply")
    cases = _cases(tmp_path / "model" / "explorer.html")
    assert all(case["patient"]["note"] == "" for case in cases)
