"""`o3dreg register`: outputs, refusals, exit codes."""

import json
import subprocess
import sys

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from o3dreg import registration_rigid
from o3dreg.app.synthetic import SmoothWarp, synthetic_form
from o3dreg.cli import main


@pytest.fixture(scope="module")
def pair(tmp_path_factory, bunny_template, bunny_target):
    # The bunny: no symmetry, so the rigid start is not ambiguous and the verdict is 'ok' (a
    # cube's is: 24 poses fit it equally well, and the warped cube folds at its edges).
    folder = tmp_path_factory.mktemp("pair")
    template = bunny_template.simplify_quadric_decimation(800)
    dense = bunny_target.simplify_quadric_decimation(6000)
    dense.remove_unreferenced_vertices()
    template.remove_unreferenced_vertices()
    warp = SmoothWarp.random(np.asarray(dense.vertices), magnitude=0.03, seed=2)
    dense.vertices = o3d.utility.Vector3dVector(warp(np.asarray(dense.vertices)))
    o3d.io.write_triangle_mesh(str(folder / "template.ply"), template)
    o3d.io.write_triangle_mesh(str(folder / "patient.ply"), dense)
    return folder


def register(pair, output, *options: str, target: str = "patient.ply") -> int:
    """``o3dreg register TEMPLATE TARGET -o OUTPUT OPTIONS...`` on the fixture's pair."""
    template, patient = str(pair / "template.ply"), str(pair / target)
    return main(["register", template, patient, "-o", str(output), *options])


def test_register_writes_all_outputs(pair, tmp_path, capsys):
    out = tmp_path / "out.ply"
    code = register(
        pair, out, "--levels", "2,4,8",
        "--deformation", str(tmp_path / "d.npz"), "--report", str(tmp_path / "r.json"),
    )  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "source -> target" in printed and "target -> source" in printed
    mesh = o3d.io.read_triangle_mesh(str(out))
    assert len(mesh.vertices) == len(o3d.io.read_triangle_mesh(str(pair / "template.ply")).vertices)
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["success"] is True and len(report["levels"]) == 3
    assert report["distances"]["source_to_target_mean"] < 1.0
    assert (tmp_path / "d.npz").is_file()


def test_json_output_and_no_symmetric(pair, tmp_path, capsys):
    code = register(pair, tmp_path / "o.ply", "--json", "--no-symmetric", "--levels", "2,4")
    single = json.loads(capsys.readouterr().out)
    assert code == 0 and single["levels"][0]["resolution"] == 2
    assert register(pair, tmp_path / "s.ply", "--json", "--levels", "2,4") == 0
    symmetric = json.loads(capsys.readouterr().out)
    # Same rigid start, same first level: the symmetric cost adds the barycentre term's
    # (positive) share to the same point-to-surface and regulariser terms, so --no-symmetric
    # must show a smaller starting cost.
    assert single["transformation"] == symmetric["transformation"]
    assert single["levels"][0]["initial_cost"] < symmetric["levels"][0]["initial_cost"]


def test_refusals_leave_nothing(pair, tmp_path, capsys):
    out = tmp_path / "exists.ply"
    out.write_text("keep me")
    assert register(pair, out) == 2
    assert out.read_text() == "keep me"
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert register(pair, tmp_path / "x.ply", target="missing.ply") == 2
    assert "no such file" in capsys.readouterr().err
    assert register(pair, tmp_path / "y.ply", "--levels", "2,4", "--regularization", "1,2,3") == 2
    assert "--regularization must give 1 or 2 values" in capsys.readouterr().err
    assert register(pair, tmp_path / "z.ply", "--levels", "4,2") == 2
    assert "--levels must go from coarse to fine" in capsys.readouterr().err
    for option in (["--symmetric-weight", "2"], ["--barycentre-correction"]):
        assert register(pair, tmp_path / "w.ply", "--no-symmetric", *option) == 2
        assert "which --no-symmetric drops" in capsys.readouterr().err
    assert register(pair, tmp_path / "v.ply", "--levels", "1000") == 2
    assert "`resolution` (--levels) must be at most 128" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists.ply"]


def test_the_exit_status_follows_the_verdict_not_the_iteration_limit(pair, tmp_path, capsys):
    # A level stopped at --max-iteration: a note on the stopping-criteria line; the exit
    # status is the verdict's (a good result never stops a `set -e` script).
    code = register(pair, tmp_path / "o.ply", "--levels", "2", "--max-iteration", "1", "--json")
    report = json.loads(capsys.readouterr().out)
    assert report["success"] is False  # the level did stop at its limit
    assert code == (0 if report["status"] == "ok" else 1)
    assert (tmp_path / "o.ply").is_file()
    code = register(pair, tmp_path / "p.ply", "--levels", "2", "--max-iteration", "1")
    out = capsys.readouterr().out
    assert "stopping criteria:" in out and "max" in out.split("stopping criteria:")[1]
    assert code == (0 if "verdict: ok" in out else 1)


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert "o3dreg" in capsys.readouterr().out
    assert main([]) == 2


def test_robust_options_reach_the_registration(pair, tmp_path, capsys):
    code = register(
        pair, tmp_path / "o.ply", "--levels", "2,4",
        "--loss", "cauchy", "--max-normal-angle", "60", "--parts", "connected", "--json",
    )  # fmt: skip
    data = json.loads(capsys.readouterr().out)
    assert code in (0, 1)
    assert data["supported_vertices"] is not None and data["supported_vertices"] > 0
    with pytest.raises(SystemExit) as exc:  # argparse refuses an unknown choice
        main(["register", "a.ply", "b.ply", "-o", "c.ply", "--loss", "l1"])
    assert exc.value.code == 2


def test_a_bad_registration_prints_its_verdict_and_exits_1(pair, tmp_path, capsys):
    # The patient shrunk fivefold and no rigid step to find the scale: the registration cannot be
    # right, and the verdict says why (sizes in other units).
    small = o3d.io.read_triangle_mesh(str(pair / "patient.ply"))
    small.scale(0.2, center=small.get_center())
    o3d.io.write_triangle_mesh(str(tmp_path / "small.ply"), small)
    args = ["register", str(pair / "template.ply"), str(tmp_path / "small.ply")]
    code = main([*args, "-o", str(tmp_path / "o.ply"), "--levels", "2", "--no-rigid"])
    out = capsys.readouterr().out
    assert code == 1
    assert "verdict: failed" in out and "times the template's size" in out
    assert "converged: yes" not in out
    # Without --no-rigid the rigid start refuses the size mismatch, naming the fix; nothing is
    # written.
    code = main([*args, "-o", str(tmp_path / "p.ply"), "--levels", "2"])
    assert code == 2
    assert "--with-scaling" in capsys.readouterr().err
    assert not (tmp_path / "p.ply").exists()


def test_the_report_carries_the_rigid_start(pair, tmp_path, capsys):
    # The bunny: the rigid start's scores are in the report, as registration_rigid finds them
    # (deterministic: same inputs, same candidates), and no ambiguity.
    code = register(pair, tmp_path / "o.ply", "--levels", "2", "--report", str(tmp_path / "r.json"))
    report = json.loads((tmp_path / "r.json").read_text())
    rigid = registration_rigid(
        o3d.io.read_triangle_mesh(str(pair / "template.ply")),
        o3d.io.read_triangle_mesh(str(pair / "patient.ply")),
    )
    start = report["rigid_start"]
    assert start["score"] == pytest.approx(rigid.score, rel=1e-9)
    assert start["candidates"] == rigid.candidates > 1
    assert start["runner_up_score"] == (
        None if rigid.runner_up_score is None else pytest.approx(rigid.runner_up_score, rel=1e-9)
    )
    assert start["warnings"] == [] and code == 0
    # A start given by the user (the identity, near the pair's pose: the map hardly turns): no
    # search, nothing to report.
    register(pair, tmp_path / "i.ply", "--levels", "2", "--no-rigid", "--report",
             str(tmp_path / "i.json"))  # fmt: skip
    assert json.loads((tmp_path / "i.json").read_text())["rigid_start"] is None


def test_an_ambiguous_rigid_start_is_in_the_report_and_the_verdict(tmp_path, capsys):
    # A cube turned 45 degrees about z and 30 about x: 24 rotations fit it and none is near the
    # input pose, so the rigid start is ambiguous (see test_rigid); the report says so with
    # both scores, and the verdict carries the same warning.
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("zx", [45.0, 30.0], degrees=True).as_matrix()
    target = synthetic_form("cube", 3000)
    target.transform(turn)
    o3d.io.write_triangle_mesh(str(tmp_path / "t.ply"), synthetic_form("cube", 600))
    o3d.io.write_triangle_mesh(str(tmp_path / "p.ply"), target)
    code = main(["register", str(tmp_path / "t.ply"), str(tmp_path / "p.ply"), "-o",
                 str(tmp_path / "o.ply"), "--levels", "2", "--json"])  # fmt: skip
    report = json.loads(capsys.readouterr().out)
    start = report["rigid_start"]
    assert code == 1 and report["status"] != "ok"
    assert start["runner_up_score"] < 1.2 * start["score"]  # the near tie behind the warning
    assert len(start["warnings"]) == 1 and "ambiguous" in start["warnings"][0]
    assert start["warnings"][0] in report["warnings"]


def test_library_warnings_are_one_log_line_and_quiet_hides_them(pair, tmp_path):
    # CSV landmark files that do not say their coordinate system: the reader warns. On the
    # command line that is one "WARNING o3dreg:" line (no source line that reads as a
    # traceback), and --quiet means errors only. A process of its own: pytest owns the logging
    # and warnings of this one.
    vertices = np.asarray(o3d.io.read_triangle_mesh(str(pair / "template.ply")).vertices)
    rows = "\n".join(f"{x},{y},{z}" for x, y, z in vertices[[0, 100, 200, 300, 400]])
    for name in ("t.csv", "p.csv"):
        (tmp_path / name).write_text("x,y,z\n" + rows + "\n")
    command = [
        sys.executable, "-m", "o3dreg", "register", str(pair / "template.ply"),
        str(pair / "patient.ply"), "--landmarks", str(tmp_path / "t.csv"), str(tmp_path / "p.csv"),
        "--levels", "2", "--max-iteration", "3",
    ]  # fmt: skip
    loud = subprocess.run([*command, "-o", str(tmp_path / "l.ply")], capture_output=True, text=True)
    said = [line for line in loud.stderr.splitlines() if "coordinate system not stated" in line]
    assert len(said) == 2, loud.stderr
    assert all(line.startswith("WARNING o3dreg: ") for line in said), loud.stderr
    assert "UserWarning" not in loud.stderr and "read_landmarks(" not in loud.stderr
    quiet = subprocess.run(
        [*command, "-o", str(tmp_path / "q.ply"), "-q"], capture_output=True, text=True
    )
    assert "coordinate system" not in quiet.stderr, quiet.stderr
