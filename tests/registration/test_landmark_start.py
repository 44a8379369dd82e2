"""A start from landmarks: known transforms recovered, bad pairs refused, the CLI's --landmarks,
and one registration option set shared by `register` and `build-model`."""

import json

import numpy as np
import pytest
from _helpers import similarity_transform

from o3dreg import read_landmarks, registration_landmarks, write_landmarks
from o3dreg.cli import main

LABELS = ["nasion", "left orbit", "right orbit", "chin", "vertex"]
POINTS = np.array(
    [[0.0, -90, 20], [35, -80, 30], [-35, -80, 30], [0, -85, -70], [0, 0, 95]], dtype=float
)


def similarity(scale=1.0, angle=130.0, axis=(0.2, 1.0, -0.4), shift=(12.0, -30.0, 7.0)):
    return similarity_transform(angle, axis, shift, scale)


def test_a_known_similarity_is_recovered_from_labelled_pairs():
    truth = similarity(scale=1.7)
    target = POINTS @ truth[:3, :3].T + truth[:3, 3]
    # Paired by label, whatever the order on each side.
    order = [3, 0, 4, 2, 1]
    result = registration_landmarks(
        (LABELS, POINTS), ([LABELS[k] for k in order], target[order]), with_scaling=True
    )
    np.testing.assert_allclose(result.transformation, truth, atol=1e-9)
    assert result.scale == pytest.approx(1.7)
    assert result.labels == tuple(LABELS) and result.rms < 1e-9


def test_rigid_fit_and_residuals_show_a_misplaced_landmark():
    truth = similarity()
    target = POINTS @ truth[:3, :3].T + truth[:3, 3]
    target[3] += (0.0, 0.0, 8.0)  # the chin placed 8 mm off
    result = registration_landmarks(POINTS, target)
    assert result.scale == pytest.approx(1.0)
    assert int(np.argmax(result.residuals)) == 3
    r = result.transformation[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert result.warnings == ()  # 8 mm off among landmarks ~80 mm apart: within reason


def test_swapped_left_and_right_landmarks_are_reported(caplog):
    # Left and right orbits swapped on the patient: no rigid motion fits (before, no word: the
    # registration then started turned and its verdict blamed sliding).
    truth = similarity()
    target = POINTS @ truth[:3, :3].T + truth[:3, 3]
    target[[1, 2]] = target[[2, 1]]
    with caplog.at_level("WARNING", logger="o3dreg"):
        result = registration_landmarks((LABELS, POINTS), (LABELS, target))
    assert len(result.warnings) == 1 and "fit no rigid motion" in result.warnings[0]
    assert "swapped (left and right?)" in result.warnings[0] and "rms" in caplog.text
    # One landmark far off among good ones is named.
    target = POINTS @ truth[:3, :3].T + truth[:3, 3]
    target[4] += (0.0, 40.0, 0.0)
    result = registration_landmarks((LABELS, target), (LABELS, target + 0.0))
    assert result.warnings == ()
    result = registration_landmarks((LABELS, POINTS), (LABELS, target))
    assert len(result.warnings) == 1 and result.warnings[0].startswith("landmark 'vertex' lies 40")


def test_files_are_read(tmp_path):
    truth = similarity(angle=40.0)
    write_landmarks(tmp_path / "t.mrk.json", LABELS, POINTS)
    write_landmarks(tmp_path / "p.csv", LABELS, POINTS @ truth[:3, :3].T + truth[:3, 3])
    result = registration_landmarks(tmp_path / "t.mrk.json", str(tmp_path / "p.csv"))
    np.testing.assert_allclose(result.transformation, truth, atol=1e-9)


def test_bad_pairs_are_refused():
    with pytest.raises(ValueError, match="at least 3 landmark pairs, got 2"):
        registration_landmarks(POINTS[:2], POINTS[:2])
    with pytest.raises(ValueError, match=r"\['vertex'\] only in `source`.*\['tip'\] only in"):
        registration_landmarks((LABELS, POINTS), (LABELS[:4] + ["tip"], POINTS))
    with pytest.raises(ValueError, match="as many landmarks"):
        registration_landmarks(POINTS, POINTS[:4])
    with pytest.raises(ValueError, match="repeats landmark labels"):
        registration_landmarks((["a", "a", "b"], POINTS[:3]), (["a", "b", "c"], POINTS[:3]))
    line = np.outer([0.0, 1.0, 2.0, 5.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="`source` landmarks are degenerate"):
        registration_landmarks(line, POINTS[:4])
    with pytest.raises(ValueError, match="`target` landmarks are degenerate"):
        registration_landmarks(POINTS[:4], np.zeros((4, 3)))
    with pytest.raises(TypeError, match="with_scaling"):
        registration_landmarks(POINTS, POINTS, with_scaling=1)
    # Coordinates whose products overflow: refused (LAPACK's SVD spun without end on them,
    # deaf to SIGTERM: found by a CLI audit with a landmark file of 1e308s).
    with pytest.raises(ValueError, match="`source` landmark coordinates must be finite numbers"):
        registration_landmarks(POINTS * 1e306, POINTS)


def test_labels_choose_the_pairs(tmp_path):
    # A file holding landmarks of anatomy the other side lacks (or placed elsewhere): `labels`
    # pairs only those chosen; each must be on both sides.
    truth = similarity(angle=60.0)
    target = POINTS @ truth[:3, :3].T + truth[:3, 3]
    target[4] += (0.0, 300.0, 0.0)  # 'vertex' placed on something else on the patient
    write_landmarks(tmp_path / "t.fcsv", [*LABELS, "skull"], np.vstack([POINTS, [0, 0, 900]]))
    chosen = ["chin", "nasion", "left orbit", "right orbit"]
    result = registration_landmarks(tmp_path / "t.fcsv", (LABELS, target), labels=chosen)
    assert result.labels == tuple(chosen) and result.rms < 1e-9 and result.warnings == ()
    np.testing.assert_allclose(result.transformation, truth, atol=1e-9)
    with pytest.raises(ValueError, match=r"\['skull'\] only in `source`"):
        registration_landmarks(tmp_path / "t.fcsv", (LABELS, target))
    # A label one side lacks: the side, its labels and what was asked for are named.
    with pytest.raises(
        ValueError,
        match=r"`labels` must name landmarks of `target`, which holds nasion, left orbit, "
        r"right orbit, chin, vertex; got chin, nasion, skull: 'skull' is not in it",
    ):
        registration_landmarks(
            tmp_path / "t.fcsv", (LABELS, target), labels=["chin", "nasion", "skull"]
        )
    with pytest.raises(ValueError, match=r"`source` '.*t.fcsv', which holds .*skull; got tip"):
        registration_landmarks(tmp_path / "t.fcsv", (LABELS, target), labels=["tip"])
    with pytest.raises(ValueError, match=r"at least 3 landmark pairs, got 2 \(`labels` chooses"):
        registration_landmarks((LABELS, POINTS), (LABELS, target), labels=["chin", "nasion"])
    with pytest.raises(ValueError, match="`labels` chooses labelled landmarks, but `target`"):
        registration_landmarks((LABELS, POINTS), target, labels=chosen)
    with pytest.raises(TypeError, match="`labels` must be a sequence of landmark labels, got str"):
        registration_landmarks((LABELS, POINTS), (LABELS, target), labels="chin")
    # A label one side holds twice is ambiguous only where it is chosen.
    twice = ([*LABELS, "chin"], np.vstack([target, target[3]]))
    result = registration_landmarks((LABELS, POINTS), twice, labels=chosen[1:])
    assert result.labels == tuple(chosen[1:]) and result.rms < 1e-9
    with pytest.raises(ValueError, match=r"landmarks `target` holds once; got chin, nasion, .*: "
                       r"'chin' is there twice"):  # fmt: skip
        registration_landmarks((LABELS, POINTS), twice, labels=chosen)


def test_a_landmark_file_with_nan_names_the_file(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("label,x,y,z\nA,nan,0,0\nB,1,0,0\nC,0,1,0\n")
    good = (["A", "B", "C"], POINTS[:3])
    with pytest.raises(ValueError, match=r"bad.csv' holds NaN or infinite coordinates"):
        registration_landmarks(str(path), good)


@pytest.fixture(scope="module")
def turned(tmp_path_factory, bunny_template, bunny_target):
    """The bunny turned by 150 degrees, with landmark files on both sides."""
    folder = tmp_path_factory.mktemp("landmarks")
    template = bunny_template.simplify_quadric_decimation(800)
    template.remove_unreferenced_vertices()
    target = bunny_target.simplify_quadric_decimation(6000)
    target.remove_unreferenced_vertices()
    truth = similarity(angle=150.0, shift=(20.0, 5.0, -10.0))
    target.transform(truth)
    tv = np.asarray(template.vertices)
    picks = tv[[0, 100, 200, 300, 400]]
    write_landmarks(folder / "template.csv", LABELS, picks)
    write_landmarks(folder / "patient.mrk.json", LABELS, picks @ truth[:3, :3].T + truth[:3, 3])
    from o3dreg import write_triangle_mesh

    write_triangle_mesh(folder / "template.ply", template)
    write_triangle_mesh(folder / "patient.ply", target)
    return folder, truth


def test_register_starts_from_landmarks(turned, tmp_path, capsys):
    folder, truth = turned
    code = main(
        [
            "register",
            str(folder / "template.ply"),
            str(folder / "patient.ply"),
            "-o",
            str(tmp_path / "out.ply"),
            "--levels",
            "2,4",
            "--landmarks",
            str(folder / "template.csv"),
            str(folder / "patient.mrk.json"),
            "--report",
            str(tmp_path / "r.json"),
        ]
    )
    printed = capsys.readouterr().out
    assert "start from 5 landmark pairs" in printed
    report = json.loads((tmp_path / "r.json").read_text())
    # The landmarks are exact: the start is the truth, and no search replaced it.
    np.testing.assert_allclose(report["transformation"], truth, atol=1e-6)
    assert code == (0 if report["status"] == "ok" and report["success"] else 1)
    assert report["status"] == "ok"
    # The report says where the start came from (it said rigid_start: null and nothing else).
    start = report["landmark_start"]
    assert len(start["labels"]) == 5 and start["rms"] < 1e-6 and start["warnings"] == []
    # From the exact start the map hardly turns: no rigid search to check the start either.
    assert report["rigid_start"] is None


def test_landmarks_off_the_meshes_are_named(turned, tmp_path):
    # Slicer files often hold landmarks of anatomy the mesh does not show (a mandible's files
    # with landmarks on the skull base): they steer the start all the same, and the report says
    # which they are.
    folder, truth = turned
    labels, points = read_landmarks(folder / "template.csv")
    size = float(np.linalg.norm(np.ptp(points, axis=0)))
    off = points[0] + [0.0, 0.0, 3.0 * size]  # far above the bunny
    write_landmarks(tmp_path / "t.csv", [*labels, "skull"], np.vstack([points, off]))
    moved = np.vstack([points, off]) @ truth[:3, :3].T + truth[:3, 3]
    write_landmarks(tmp_path / "p.csv", [*labels, "skull"], moved)
    main(
        [
            "register", str(folder / "template.ply"), str(folder / "patient.ply"),
            "-o", str(tmp_path / "out.ply"), "--levels", "2", "--report", str(tmp_path / "r.json"),
            "--landmarks", str(tmp_path / "t.csv"), str(tmp_path / "p.csv"), "-q",
        ]
    )  # fmt: skip
    found = json.loads((tmp_path / "r.json").read_text())["landmark_start"]["warnings"]
    assert len(found) == 2  # the template's side and the patient's
    assert all("far from the" in w and "skull (" in w for w in found)
    # Only the far landmark is named far, and the option that leaves it out is given.
    named, hint = zip(*(w.split("; they steer") for w in found))
    assert all(lab not in w for w in named for lab in labels)
    assert all(w.endswith(f"(--labels {','.join(labels)})") for w in hint)
    # With --labels the pairs are those chosen, and nothing is far.
    code = main(
        [
            "register", str(folder / "template.ply"), str(folder / "patient.ply"),
            "-o", str(tmp_path / "out.ply"), "--levels", "2", "--report", str(tmp_path / "r.json"),
            "--landmarks", str(tmp_path / "t.csv"), str(tmp_path / "p.csv"), "-q", "--overwrite",
            "--labels", ",".join(labels[:4]),
        ]
    )  # fmt: skip
    start = json.loads((tmp_path / "r.json").read_text())["landmark_start"]
    assert code in (0, 1) and start["labels"] == list(labels[:4]) and start["warnings"] == []


def test_register_refuses_unknown_labels(turned, tmp_path, capsys):
    folder, _ = turned
    command = [
        "register", str(folder / "template.ply"), str(folder / "patient.ply"),
        "-o", str(tmp_path / "out.ply"), "--levels", "2",
    ]  # fmt: skip
    landmarks = ["--landmarks", str(folder / "template.csv"), str(folder / "patient.mrk.json")]
    assert main([*command, *landmarks, "--labels", "chin,vertex,nose"]) == 2
    err = capsys.readouterr().err
    assert "`labels` (--labels) must name landmarks of `--landmarks TEMPLATE_FILE`" in err
    assert "which holds nasion, left orbit, right orbit, chin, vertex" in err
    assert "got chin, vertex, nose: 'nose' is not in it" in err
    assert not (tmp_path / "out.ply").exists()
    assert main([*command, "--labels", "chin,vertex,nasion"]) == 2
    assert "--labels chooses landmarks of --landmarks: give --landmarks" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse's usage error
        main([*command, *landmarks, "--labels", "chin,,vertex"])
    assert "--labels: expected comma-separated landmark labels with no empty item" in (
        capsys.readouterr().err
    )


SHARED = [
    "--levels",
    "2,4",
    "--regularization",
    "0.2",
    "--max-iteration",
    "7",
    "--with-scaling",
    "--parts",
    "connected",
    "--loss",
    "cauchy",
    "--max-normal-angle",
    "60",
    "--max-distance-factor",
    "3",
    "--min-target-component",
    "0.01",
    "--keep-boundary",
    "--symmetric-weight",
    "0.5",
    "--barycentre-correction",
]


def test_register_and_build_model_share_one_option_set():
    from o3dreg.cli import build_parser
    from o3dreg.cli._registration_options import settings_from_args

    parser = build_parser()
    reg = parser.parse_args(["register", "t.ply", "p.ply", "-o", "o.ply", *SHARED])
    build = parser.parse_args(["build-model", "t.ply", "p.ply", "-o", "model", *SHARED])
    a, b = settings_from_args(reg), settings_from_args(build)
    assert a == b
    assert a.start == "similarity" and a.parts == "connected"
    assert [lev.resolution for lev in a.levels] == [2, 4]
    assert all(lev.regularization == 0.2 for lev in a.levels)
    assert a.criteria.max_iteration == 7
    m = a.estimation_method
    assert (m.symmetric, m.loss, m.max_normal_angle, m.reject_boundary) == (
        True,
        "cauchy",
        60.0,
        False,
    )
    assert (m.max_distance_factor, m.min_target_component, m.symmetric_weight) == (3.0, 0.01, 0.5)
    assert m.barycentre_correction
    paper = settings_from_args(
        parser.parse_args(["build-model", "t.ply", "p.ply", "-o", "m", "--paper"])
    ).estimation_method
    assert (paper.loss, paper.reject_boundary, paper.max_normal_angle) == ("linear", False, None)
    # Nothing given: the library's defaults, not a copy of them.
    plain = settings_from_args(parser.parse_args(["register", "t.ply", "p.ply", "-o", "o.ply"]))
    assert plain.estimation_method is None and plain.levels is None and plain.start == "rigid"


def test_regularization_alone_keeps_the_default_schedule():
    # --regularization without --levels changes the weight of each default level, nothing else
    # (each level's barycentre-term schedule included); --levels gives eq. (3) at every level.
    from dataclasses import replace

    from o3dreg import default_levels
    from o3dreg.cli import build_parser
    from o3dreg.cli._registration_options import settings_from_args

    parser = build_parser()
    args = parser.parse_args(
        ["register", "t.ply", "p.ply", "-o", "o.ply", "--regularization", "0.2"]
    )
    assert list(settings_from_args(args).levels) == [
        replace(lev, regularization=0.2) for lev in default_levels()
    ]
    given = parser.parse_args(["register", "t.ply", "p.ply", "-o", "o.ply", "--levels", "2,4"])
    levels = settings_from_args(given).levels
    assert all(lev.symmetric_scale == 1.0 and lev.barycentre_reach is None for lev in levels)


def test_paper_flag_is_the_published_method():
    # --paper: the paper's plain least squares on eq. (3) at every level (paper_levels), as
    # examples/paper_tables.py reproduces Tables 1-2; --regularization keeps that schedule.
    from dataclasses import replace

    from o3dreg import DistanceEstimation, paper_levels
    from o3dreg.cli import build_parser
    from o3dreg.cli._registration_options import settings_from_args

    parser = build_parser()
    base = ["register", "t.ply", "p.ply", "-o", "o.ply", "--paper"]
    settings = settings_from_args(parser.parse_args(base))
    assert settings.estimation_method == DistanceEstimation.paper()
    assert list(settings.levels) == paper_levels()
    weighted = settings_from_args(parser.parse_args([*base, "--regularization", "0.2"]))
    assert list(weighted.levels) == [replace(lev, regularization=0.2) for lev in paper_levels()]


def test_regularization_alone_reweights_the_templates_default_levels():
    # --regularization without --levels keeps the default hierarchy of the template at hand:
    # five levels for an elongated one (400 x 40 x 40 mm: 1.3 cells across at 16), four else.
    from dataclasses import replace

    from o3dreg import default_levels
    from o3dreg.cli import build_parser
    from o3dreg.cli._registration_options import settings_from_args

    corners = np.array([[x, y, z] for x in (0, 400) for y in (0, 40) for z in (0, 40)], float)
    args = build_parser().parse_args(
        ["register", "t.ply", "p.ply", "-o", "o.ply", "--regularization", "0.05"]
    )
    long = settings_from_args(args, corners)
    assert [lev.resolution for lev in long.levels] == [2, 4, 8, 16, 32]
    assert list(long.levels) == [
        replace(lev, regularization=0.05) for lev in default_levels(corners)
    ]
    compact = settings_from_args(args, corners * [0.1, 1.0, 1.0])
    assert [lev.resolution for lev in compact.levels] == [2, 4, 8, 16]
    assert settings_from_args(args).levels == compact.levels  # no template: the four levels
