"""Data safety (issue 12): nothing half-written, nothing stale, nothing overwritten.

Each test reproduces one fault a user met (full disk, overwrites, stale resume files, corrupt
inputs, tracebacks, signals) and checks the documented outcome.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from _helpers import population

from o3dreg import ElasticCriteria, ElasticLevel, RegistrationSettings
from o3dreg.app.model_folder import build_model_folder
from o3dreg.io.mesh import read_triangle_mesh, write_triangle_mesh

ROOT = Path(__file__).resolve().parents[1]


def sphere(n: int = 20) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=n)


def python(code: str, *args: str, cwd: Path | None = None, **kw) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter using this checkout of o3dreg."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd,
        timeout=300,
        **kw,
    )


def cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return python(
        "import sys; from o3dreg.cli import main; sys.exit(main(sys.argv[1:]))", *args, cwd=cwd
    )


def parts(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".part" in p.name)


# -- 1. full disk ------------------------------------------------------------------------------


def _small_tmpfs_works() -> str | None:
    """None when this machine lets us mount a small tmpfs in a private mount namespace."""
    if shutil.which("unshare") is None:
        return "no unshare command"
    if os.geteuid() != 0:
        return "mounting a tmpfs needs root (unshare -m)"
    probe = subprocess.run(
        ["unshare", "-m", "--propagation", "private", "sh", "-c",
         "d=$(mktemp -d) && mount -t tmpfs -o size=40k tmpfs $d && umount $d && rmdir $d"],
        capture_output=True, text=True,
    )  # fmt: skip
    return None if probe.returncode == 0 else f"cannot mount a tmpfs: {probe.stderr.strip()}"


def on_full_disk(
    tmp_path: Path, code: str, size: str = "40k", options: str = ""
) -> subprocess.CompletedProcess:
    """Run ``code`` with ``FULL`` (env) a folder on a ``size`` tmpfs seen by that process only."""
    reason = _small_tmpfs_works()
    if reason:
        pytest.skip(reason)
    full = tmp_path / "full"
    full.mkdir()
    script = tmp_path / "script.py"
    script.write_text(textwrap.dedent(code))
    shell = (
        f"mount -t tmpfs -o size={size}{options} tmpfs {full} && "
        f"{sys.executable} {script}; rc=$?; ls -a {full} > {tmp_path / 'listing.txt'}; exit $rc"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT), "FULL": str(full)}
    return subprocess.run(
        ["unshare", "-m", "--propagation", "private", "sh", "-c", shell],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip


def test_write_on_a_full_disk_leaves_nothing(tmp_path):
    # A 40 kB tmpfs holds about 40 kB of a 65 kB binary PLY: Open3D's writer says success.
    done = on_full_disk(
        tmp_path,
        """
        import os, sys
        import open3d as o3d
        from o3dreg.io.mesh import write_triangle_mesh
        mesh = o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=40)
        try:
            write_triangle_mesh(os.path.join(os.environ["FULL"], "r.ply"), mesh)
        except OSError as exc:
            print("OSError", exc)
            sys.exit(3)
        sys.exit(0)
        """,
    )
    listing = (tmp_path / "listing.txt").read_text().split()
    assert done.returncode == 3, done.stdout + done.stderr
    message = next(line for line in done.stdout.splitlines() if line.startswith("OSError"))
    assert "r.ply" in message and ".part" not in message  # names the output
    assert sorted(listing) == [".", ".."]  # neither the output nor a temporary file


def test_cli_on_a_full_disk_exits_2_and_writes_nothing(tmp_path):
    write_triangle_mesh(tmp_path / "t.ply", sphere(12))
    write_triangle_mesh(tmp_path / "p.ply", sphere(40))
    done = on_full_disk(
        tmp_path,
        f"""
        import os, sys
        from o3dreg.cli import main
        full = os.environ["FULL"]
        sys.exit(main([
            "register", "{tmp_path / "p.ply"}", "{tmp_path / "t.ply"}", "-o", full + "/r.ply",
            "--levels", "2", "--max-iteration", "2", "--report", full + "/r.json", "-q"]))
        """,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert sorted((tmp_path / "listing.txt").read_text().split()) == [".", ".."]


def test_read_only_folder_names_the_output(tmp_path):
    done = on_full_disk(
        tmp_path,
        """
        import os, sys
        import open3d as o3d
        from o3dreg.io.mesh import write_triangle_mesh
        try:
            write_triangle_mesh(os.path.join(os.environ["FULL"], "r.ply"),
                                o3d.geometry.TriangleMesh.create_sphere())
        except OSError as exc:
            print("OSError", exc)
        """,
        options=",ro",
    )
    message = next(line for line in done.stdout.splitlines() if line.startswith("OSError"))
    assert (
        "r.ply" in message
        and ".part" not in message
        and "/tmp" not in message.split("r.ply")[0][-3:]
    )
    assert "Read-only" in message


def test_stale_part_files_of_dead_writers_are_removed(tmp_path):
    # A SIGKILL during a write leaves the hidden temporary file: the next write removes it, and
    # leaves alone the file of a writer still running (here: this process).
    from o3dreg.io import mesh as meshio

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".r.{meshio.HOST}-{dead.pid}.abcd1234.part.ply"
    live = tmp_path / f".r.{meshio.HOST}-{os.getpid()}.abcd1234.part.ply"
    other = tmp_path / f".s.{meshio.HOST}-{dead.pid}.abcd1234.part.ply"
    for p in (stale, live, other):
        p.write_bytes(b"ply\nformat binary_little_endian 1.0\n")
    write_triangle_mesh(tmp_path / "r.ply", sphere())
    assert parts(tmp_path) == sorted([live.name, other.name])
    assert len(read_triangle_mesh(tmp_path / "r.ply").triangles) == len(sphere().triangles)


def test_sigkill_during_a_write_leaves_only_a_hidden_file_cleaned_next_time(tmp_path):
    # Kill the writer while the file is being written (a slow writer).
    code = """
    import sys, time
    from o3dreg.io.mesh import atomic_write
    def slow(tmp):
        with open(tmp, "w") as fh:
            fh.write("partial")
            fh.flush()
            print("writing", flush=True)
            time.sleep(60)
    atomic_write(sys.argv[1], slow)
    """
    proc = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(code), str(tmp_path / "r.ply")],
        stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert proc.stdout is not None and proc.stdout.readline().strip() == "writing"
    proc.kill()
    proc.wait()
    assert not (tmp_path / "r.ply").exists()
    assert len(parts(tmp_path)) == 1 and parts(tmp_path)[0].startswith(".r.")
    write_triangle_mesh(tmp_path / "r.ply", sphere())
    assert parts(tmp_path) == []


# -- 2. overwrites -----------------------------------------------------------------------------


def run_main(capsys, *argv: str) -> tuple[int, str]:
    from o3dreg.cli import main

    try:
        code = main(list(argv))
    except SystemExit as exc:  # argparse
        code = int(exc.code or 0)
    return code, capsys.readouterr().err


@pytest.fixture
def meshes(tmp_path):
    write_triangle_mesh(tmp_path / "t.ply", sphere(8))
    write_triangle_mesh(tmp_path / "p.ply", sphere(10))
    return tmp_path


def test_register_outputs_checked_before_any_work(meshes, capsys):
    # SOURCE does not exist: every output error below is found before reading any input.
    missing, p = str(meshes / "absent.ply"), str(meshes / "p.ply")
    out = str(meshes / "r.ply")
    code, err = run_main(capsys, "register", missing, p, "-o", str(meshes / "r.xyz"))
    assert code == 2 and "--output must end with one of" in err
    code, err = run_main(capsys, "register", missing, p, "-o", out, "--report", out + ".txt")
    assert code == 2 and "--report must end with .json" in err
    code, err = run_main(capsys, "register", missing, p, "-o", out, "--deformation", out)
    assert code == 2 and "--deformation must end with .npz" in err
    (meshes / "o.ply").write_bytes(b"")
    code, err = run_main(capsys, "register", missing, p, "-o", str(meshes / "o.ply"))
    assert code == 2 and "pass --overwrite" in err
    code, err = run_main(capsys, "register", missing, p, "-o", out, "--report", str(meshes))
    assert code == 2 and "must end with .json" in err
    # A folder that exists only once ".." is dropped: the system resolves the path through it.
    through = str(meshes / "absent" / ".." / "r.ply")
    code, err = run_main(capsys, "register", missing, p, "-o", through)
    assert code == 2 and "absent/..' does not exist" in err
    # With --overwrite an output equal to an input is still refused; the input is untouched.
    before = (meshes / "p.ply").read_bytes()
    code, err = run_main(capsys, "register", str(meshes / "t.ply"), p, "-o", p, "--overwrite")
    assert code == 2 and "an output never replaces an input" in err
    assert (meshes / "p.ply").read_bytes() == before
    # Nor may a report replace a landmark file (.mrk.json passes the .json rule).
    marks = meshes / "p.mrk.json"
    marks.write_text("{}")
    code, err = run_main(
        capsys, "register", missing, p, "-o", out, "--landmarks", str(marks), str(marks),
        "--report", str(marks), "--overwrite",
    )  # fmt: skip
    assert code == 2 and "is the input --landmarks TEMPLATE_FILE" in err
    assert marks.read_text() == "{}"
    # All checks pass: now the missing input is reported.
    code, err = run_main(capsys, "register", missing, p, "-o", out, "--report", out + ".json")
    assert code == 2 and "SOURCE" in err


def test_two_outputs_never_share_a_path():
    from o3dreg.cli._common import check_outputs

    with pytest.raises(ValueError, match="--report and --deformation name the same file"):
        check_outputs({"--report": "/tmp/a.x", "--deformation": "/tmp/./a.x"}, True)
    with pytest.raises(ValueError, match="is the input TARGET"):
        check_outputs({"--output": "/tmp/./a.ply"}, True, inputs={"TARGET": "/tmp/a.ply"})


def test_reconstruct_output_never_replaces_its_input(tmp_path, capsys):
    scan = tmp_path / "scan.ply"  # any file: the check comes before reading it
    scan.write_bytes(b"data")
    code, err = run_main(capsys, "reconstruct", str(scan), "-o", str(scan), "--threshold", "1",
                         "--overwrite")  # fmt: skip
    assert code == 2 and "never replaces an input" in err and scan.read_bytes() == b"data"


def test_model_fit_output_rules(tmp_path, capsys):
    landmarks = tmp_path / "lm.mrk.json"
    landmarks.write_text("{}")
    args = ["model", "fit", str(tmp_path / "no-model"), str(tmp_path / "p.ply"),
            "--landmarks", str(landmarks)]  # fmt: skip
    code, err = run_main(capsys, *args, "-o", str(landmarks), "--overwrite")
    assert code == 2 and "--landmarks" in err and landmarks.read_text() == "{}"
    (tmp_path / "pred.csv").write_text("keep")
    code, err = run_main(capsys, *args, "-o", str(tmp_path / "pred.csv"))
    assert code == 2 and "pass --overwrite" in err and (tmp_path / "pred.csv").read_text() == "keep"


@pytest.fixture
def model_dir(tmp_path):
    from o3dreg.shape.build import build_shape_model

    base = sphere(6)
    v = np.asarray(base.vertices)
    rng = np.random.default_rng(0)
    shapes = np.stack(
        [v * (1 + 0.1 * rng.normal()) + 0.3 * rng.normal(size=v.shape) for _ in range(4)]
    )
    model = build_shape_model(shapes, np.asarray(base.triangles))
    folder = tmp_path / "model"
    folder.mkdir()
    model.save(folder / "model.npz")
    write_triangle_mesh(folder / "template.ply", base)
    return folder


def test_model_modes_overwrite_rules_and_finite_sd(model_dir, tmp_path, capsys):
    out = tmp_path / "modes"
    args = ["model", "modes", str(model_dir), "--modes", "1", "-o", str(out)]
    assert run_main(capsys, *args)[0] == 0
    stamp = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    code, err = run_main(capsys, *args)
    assert code == 2 and "pass --overwrite" in err
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == stamp
    assert run_main(capsys, *args, "--overwrite")[0] == 0
    for bad in ("nan", "inf"):
        code, err = run_main(capsys, "model", "modes", str(model_dir), "--sd", bad,
                             "-o", str(tmp_path / "m2"))  # fmt: skip
        assert code == 2 and "finite" in err
    # 1e308 standard deviations wrote meshes of inf coordinates; --modes -1 only the mean.
    # More modes than the model has wrote fewer files, silently (`model fit --modes` refused).
    for option, bad, expected in (
        ("--sd", "1e308", "[-100, 100]"),
        ("--modes", "-1", ">= 1"),
        ("--modes", "100", "--modes must be at most 3 (the model's modes), got 100"),
    ):
        code, err = run_main(capsys, "model", "modes", str(model_dir), option, bad,
                             "-o", str(tmp_path / "m2"))  # fmt: skip
        assert code == 2 and expected in err
    assert not (tmp_path / "m2").exists()


def test_build_model_refuses_one_patient_file_given_twice(model_dir, tmp_path, capsys):
    # It warned "counted twice" and built the model with the patient twice (exit 0).
    template = str(model_dir / "template.ply")
    patients = [template, str(model_dir / ".." / model_dir.name / "template.ply")]
    code, err = run_main(capsys, "build-model", template, *patients, "-o", str(tmp_path / "m"))
    assert code == 2 and "must name each patient file once" in err
    assert not (tmp_path / "m").exists()


def test_build_model_refuses_to_replace_a_model_before_any_work(model_dir, capsys):
    before = (model_dir / "model.npz").read_bytes()
    code, err = run_main(capsys, "build-model", str(model_dir / "absent.ply"),
                         str(model_dir / "p.ply"), "-o", str(model_dir))  # fmt: skip
    assert code == 2 and "already holds a model" in err and "--overwrite" in err
    assert (model_dir / "model.npz").read_bytes() == before


def test_build_model_folder_refuses_to_replace_a_model_and_still_resumes(tmp_path):
    # The Python API follows the command line's rule: an earlier model in the folder is not
    # replaced without overwrite=True; a folder with finished registrations but no model (an
    # interrupted run) is resumed, reusing them.
    (tv, tf), targets, *_ = population(3, seed=5)
    paths = []
    for i, t in enumerate(targets):
        write_triangle_mesh(tmp_path / f"p{i}.ply", t)
        paths.append(str(tmp_path / f"p{i}.ply"))
    template = read_triangle_mesh(write_triangle_mesh(tmp_path / "t.ply", (tv, tf)))
    settings = RegistrationSettings(
        levels=(ElasticLevel(2),), criteria=ElasticCriteria(max_iteration=3)
    )
    out = tmp_path / "model"
    build = functools.partial(build_model_folder, template, paths, str(out), settings=settings)
    first = build()
    assert first.model is not None and not any(r.skipped for r in first.batch.records)
    before = (out / "model.npz").stat().st_mtime_ns, _arrays(out / "model.npz")
    with pytest.raises(FileExistsError, match="already holds a model") as caught:
        build()
    assert repr(str(out)) in str(caught.value) and "overwrite=True" in str(caught.value)
    assert (out / "model.npz").stat().st_mtime_ns == before[0]
    # Any model file counts, not only model.npz (here a run stopped after the statismo file).
    (out / "model.npz").unlink()
    with pytest.raises(FileExistsError, match=r"model\.h5"):
        build()
    again = build(overwrite=True)
    assert all(r.skipped for r in again.batch.records)  # finished registrations reused
    assert _same_arrays(_arrays(out / "model.npz"), before[1])
    # Only finished registrations left: resumed without overwrite.
    for name in ("model.npz", "model.h5", "mean.ply", "variance.txt", "report.json",
                 "explorer.html", "modes", "quality"):  # fmt: skip
        path = out / name
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    resumed = build()
    assert all(r.skipped for r in resumed.batch.records)
    assert _same_arrays(_arrays(out / "model.npz"), before[1])


def test_a_failed_rebuild_keeps_the_earlier_model(tmp_path, monkeypatch):
    # A rebuild with overwrite=True that fails half-way (a full disk, Ctrl-C) leaves the earlier
    # model as it was: the new files are written aside and moved in only once all are written.
    from o3dreg.app import model_folder

    (tv, tf), targets, *_ = population(3, seed=5)
    paths = [str(write_triangle_mesh(tmp_path / f"p{i}.ply", t)) for i, t in enumerate(targets)]
    template = read_triangle_mesh(write_triangle_mesh(tmp_path / "t.ply", (tv, tf)))
    settings = RegistrationSettings(
        levels=(ElasticLevel(2),), criteria=ElasticCriteria(max_iteration=3)
    )
    out = tmp_path / "model"
    build = functools.partial(build_model_folder, template, paths, str(out), settings=settings)
    build()

    def contents() -> dict:
        return {
            p.relative_to(out): p.read_bytes()
            for p in sorted(out.rglob("*"))
            if p.is_file() and "registrations" not in p.parts
        }

    before = contents()
    assert {"model.npz", "model.h5", "explorer.html", "report.json"} <= {str(p) for p in before}

    def full_disk(*args, **kwargs):
        raise OSError("`path`: writing 'model.h5' failed: No space left on device")

    for stage in ("write_statismo", "write_model_explorer"):
        with monkeypatch.context() as patch:
            patch.setattr(model_folder, stage, full_disk)
            with pytest.raises(OSError, match="No space left"):
                build(overwrite=True, force=True)
        assert contents() == before
        assert not [p for p in out.iterdir() if p.name.startswith(".o3dreg-model.")]
    rebuilt = build(overwrite=True, force=True)
    assert rebuilt.model is not None and not [
        p for p in out.iterdir() if p.name.startswith(".o3dreg-model.")
    ]


def _arrays(path) -> dict:
    with np.load(path, allow_pickle=False) as archive:
        return {key: archive[key] for key in archive.files}


def _same_arrays(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


# -- 3. resume keys and names ------------------------------------------------------------------


def _batch(template, targets, out, **options):
    from o3dreg import ElasticCriteria, ElasticLevel, register_batch

    options.setdefault("levels", [ElasticLevel(2)])
    return register_batch(
        template, targets, out, criteria=ElasticCriteria(max_iteration=2), **options
    )


def test_resume_registers_again_when_template_patient_or_options_change(tmp_path, caplog):
    from o3dreg import ElasticLevel

    template = sphere(6)
    write_triangle_mesh(tmp_path / "a.ply", sphere(10))
    targets = [str(tmp_path / "a.ply")]
    out = tmp_path / "reg"
    first = _batch(template, targets, out)
    assert not first.records[0].skipped
    assert _batch(template, targets, out).records[0].skipped  # nothing changed: resumed

    moved = o3d.geometry.TriangleMesh(template)  # same triangles, other vertices
    moved.vertices = o3d.utility.Vector3dVector(np.asarray(template.vertices) * 1.1)
    caplog.clear()
    with caplog.at_level("WARNING", logger="o3dreg"):
        again = _batch(moved, targets, out)
    assert not again.records[0].skipped and "registering again" in caplog.text
    assert _batch(moved, targets, out).records[0].skipped

    write_triangle_mesh(tmp_path / "a.ply", sphere(12), overwrite=True)  # same name, new file
    assert not _batch(moved, targets, out).records[0].skipped
    assert not _batch(moved, targets, out, levels=[ElasticLevel(3)]).records[0].skipped
    assert not _batch(moved, targets, out, init=np.diag([1, 1, 1, 1.0])).records[0].skipped


def test_a_record_never_leads_outside_the_output_folder(tmp_path):
    import json

    from o3dreg.app.batch import BatchResult

    template = sphere(6)
    write_triangle_mesh(tmp_path / "a.ply", sphere(10))
    out = tmp_path / "reg"
    _batch(template, [str(tmp_path / "a.ply")], out)
    write_triangle_mesh(tmp_path / "foreign_shape.ply", sphere(6))  # outside the folder
    record = json.loads((out / "a.json").read_text())
    record["name"] = "../foreign_shape"
    (out / "a.json").write_text(json.dumps(record))
    again = _batch(template, [str(tmp_path / "a.ply")], out)
    assert [r.name for r in again.registered] == ["a"] and not again.records[0].skipped
    with pytest.raises(ValueError, match="not a plain file name"):
        BatchResult((), str(out), np.zeros((0, 3))).mesh_path("../foreign_shape")


# -- 4/5. corrupt archives ---------------------------------------------------------------------


@pytest.fixture
def deformation_file(tmp_path):
    from o3dreg.registration.deformation import LatticeDeformation
    from o3dreg.registration.lattice import TrilinearLattice

    rng = np.random.default_rng(1)
    lattice = TrilinearLattice(
        np.zeros(3), np.ones(3) * 10, (2, 2, 2), rng.normal(size=(3, 3, 3, 3))
    )
    path = tmp_path / "d.npz"
    LatticeDeformation((lattice,)).save(path)
    return path


def _rewrite(path: Path, **changes) -> None:
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update(changes)
    np.savez(path, **arrays)  # uncompressed: byte offsets of the members are simple


def test_deformation_archives_with_nan_or_negative_counts_are_refused(deformation_file):
    from o3dreg import load_deformation

    with np.load(deformation_file) as data:
        displacements = data["level0_displacements"].copy()
    displacements[0, 0, 0, 0] = np.nan
    _rewrite(deformation_file, level0_displacements=displacements)
    with pytest.raises(ValueError, match="level0_displacements holds NaN"):
        load_deformation(deformation_file)
    displacements[0, 0, 0, 0] = 0.0
    _rewrite(deformation_file, level0_displacements=displacements, number_of_levels=np.array(-1))
    with pytest.raises(ValueError, match="number_of_levels is -1"):
        load_deformation(deformation_file)


def _damaged(path: Path, how: str) -> None:
    raw = bytearray(path.read_bytes())
    if how == "empty":
        path.write_bytes(b"")
    elif how == "truncated":
        path.write_bytes(bytes(raw[: len(raw) // 2]))
    else:  # one flipped byte inside the last member's data: a bad CRC
        _rewrite(path)
        raw = bytearray(path.read_bytes())
        central = raw.find(b"PK\x01\x02")  # the central directory follows the data
        raw[central - 20] ^= 0xFF
        path.write_bytes(bytes(raw))


@pytest.mark.parametrize("how", ["empty", "truncated", "bad-crc"])
def test_damaged_archives_raise_a_clear_value_error(deformation_file, how):
    from o3dreg import load_deformation

    _damaged(deformation_file, how)
    with pytest.raises(ValueError, match="d.npz"):
        load_deformation(deformation_file)


@pytest.mark.parametrize("how", ["empty", "truncated", "bad-crc"])
def test_damaged_model_is_one_line_and_exit_2(model_dir, how):
    _damaged(model_dir / "model.npz", how)
    done = cli("model", "info", str(model_dir))
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and "model.npz" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


# -- 4. corrupt volumes ------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_truncated_nifti_is_an_error_not_zeros(tmp_path, suffix):
    import nibabel as nib

    from o3dreg import read_volume

    path = tmp_path / f"ct{suffix}"
    data = np.random.default_rng(0).integers(0, 1000, (20, 30, 40)).astype(np.int16)
    nib.save(nib.Nifti1Image(data, np.eye(4)), path)
    assert read_volume(path).shape == (40, 30, 20)  # the whole file reads
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(OSError, match="truncated"):
        read_volume(path)


@pytest.mark.parametrize("suffix", [".mha", ".mhd"])
def test_truncated_metaimage_is_an_error(tmp_path, suffix):
    import SimpleITK as sitk

    from o3dreg import read_volume

    path = tmp_path / f"ct{suffix}"
    data = np.random.default_rng(0).integers(0, 1000, (20, 30, 40)).astype(np.int16)
    sitk.WriteImage(sitk.GetImageFromArray(data), str(path))
    assert read_volume(path).shape == (20, 30, 40)
    stored = path if suffix == ".mha" else path.with_suffix(".raw")
    raw = stored.read_bytes()
    stored.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(OSError, match="could not read"):
        read_volume(path)


@pytest.mark.parametrize(
    ("header", "message"),
    [
        ({"spacings": [0.0, 1.0, 1.0]}, "spacings"),
        ({"spacings": [np.nan, 1.0, 1.0]}, "spacings"),
        (
            {
                "space": "left-posterior-superior",
                "space directions": np.eye(3),
                "space origin": [np.nan, 0.0, 0.0],
            },
            "space origin",
        ),
        (
            {
                "space": "left-posterior-superior",
                "space directions": np.diag([1.0, 0.0, 1.0]),
                "space origin": [0.0, 0.0, 0.0],
            },
            "zero space direction",
        ),
    ],
)
def test_nrrd_with_unusable_geometry_is_refused(tmp_path, header, message):
    import nrrd

    from o3dreg import read_volume

    path = tmp_path / "mask.nrrd"
    nrrd.write(str(path), np.zeros((4, 5, 6), np.uint8), header)
    with pytest.raises(ValueError, match=message):
        read_volume(path)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        # pynrrd raised a bare KeyError on a type it does not know.
        ((b"type: float", b"type: quaternion"), "unsupported NRRD type 'quaternion'"),
        # SimpleITK 2.5 crashed (SIGSEGV) reading raw bytes under a text encoding.
        ((b"encoding: raw", b"encoding: ascii"), "could not read NRRD data"),
    ],
)
def test_nrrd_whose_header_lies_is_refused(tmp_path, edit, message):
    # Run in a child process: a crash of a reader must fail this test, not end the session.
    import nrrd

    path = tmp_path / "cube.nrrd"
    cube = np.zeros((6, 6, 6), np.float32)
    cube[2:4, 2:4, 2:4] = 1.0
    nrrd.write(str(path), cube, {"encoding": "raw"})
    path.write_bytes(path.read_bytes().replace(*edit))
    done = python(
        """
        import sys
        from o3dreg import read_volume
        try:
            read_volume(sys.argv[1])
        except (OSError, ValueError) as exc:
            print(exc)
        """,
        str(path),
    )
    assert done.returncode == 0 and message in done.stdout, (done.returncode, done.stderr)


def test_dicom_series_with_a_truncated_slice_is_refused(tmp_path):
    from _helpers import write_dicom_series

    from o3dreg import read_volume

    folder = tmp_path / "series"
    stored = np.random.default_rng(0).integers(0, 3000, (4, 32, 32)).astype(np.uint16)
    write_dicom_series(folder, stored, slope=1.0, intercept=0.0, positions_z=[0, 2, 4, 6])
    assert read_volume(folder).shape == (4, 32, 32)
    first = sorted(folder.iterdir())[0]  # an end slice: without it the series still looks whole
    raw = first.read_bytes()
    first.write_bytes(raw[: len(raw) - 32 * 16 * 2])  # half its PixelData
    with pytest.raises(OSError, match=first.name):
        read_volume(folder)


# -- 4/5. corrupt meshes -----------------------------------------------------------------------


def test_ply_header_claiming_2e9_vertices_is_refused_before_allocation(tmp_path):
    path = tmp_path / "huge.ply"
    path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 2000000000\n"
        b"property float x\nproperty float y\nproperty float z\nelement face 1\n"
        b"property list uchar int vertex_indices\nend_header\n" + bytes(64)
    )
    # Under a 3 GB address-space limit: a reader that believed the header would die here.
    done = python(
        """
        import resource, sys
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
        from o3dreg.io.mesh import read_triangle_mesh
        try:
            read_triangle_mesh(sys.argv[1])
        except OSError as exc:
            print("OSError", exc)
        """,
        str(path),
    )
    assert "OSError" in done.stdout and "2000000000 vertex" in done.stdout, done.stderr[-2000:]


@pytest.mark.parametrize("fraction", [0.3, 0.6, 0.9])
def test_truncated_ply_and_obj_are_refused(tmp_path, fraction):
    mesh = sphere(30)
    for suffix, ascii in ((".ply", False), (".ply", True), (".obj", True)):
        path = tmp_path / f"whole{suffix}"
        write_triangle_mesh(path, mesh, write_ascii=ascii, overwrite=True)
        raw = path.read_bytes()
        cut = tmp_path / f"cut{suffix}"
        cut.write_bytes(raw[: int(len(raw) * fraction)])
        with pytest.raises(OSError, match="truncated"):
            read_triangle_mesh(cut)


def test_obj_faces_past_the_vertices_are_refused(tmp_path):
    path = tmp_path / "m.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 4\n")  # no header comments
    with pytest.raises(OSError, match="refers to vertex 4"):
        read_triangle_mesh(path)


def test_ply_faces_past_the_vertices_are_refused(tmp_path):
    # Open3D keeps such a face; computing normals or writing the mesh then reads outside the
    # vertex array (a segmentation fault).
    path = tmp_path / "m.ply"
    header = "ply\nformat ascii 1.0\nelement vertex 3\n" + "".join(
        f"property float {c}\n" for c in "xyz"
    )
    body = "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    path.write_text(header + body + "0 0 0\n1 0 0\n0 1 0\n3 0 1 900000\n")
    with pytest.raises(OSError, match="face 0 refers to vertex 900000, the file holds 3"):
        read_triangle_mesh(path)


def test_an_open3d_mesh_with_faces_past_its_vertices_is_not_written(tmp_path):
    mesh = sphere(8)
    faces = np.asarray(mesh.triangles).copy()
    faces[5, 2] = 100_000
    bad = o3d.geometry.TriangleMesh(mesh.vertices, o3d.utility.Vector3iVector(faces))
    for suffix in (".ply", ".obj", ".stl"):
        with pytest.raises(ValueError, match="got face 5 with vertex 100000; nothing written"):
            write_triangle_mesh(tmp_path / f"m{suffix}", bad)
    empty = o3d.geometry.TriangleMesh(mesh.vertices, o3d.utility.Vector3iVector())
    with pytest.raises(ValueError, match="must have triangles"):
        write_triangle_mesh(tmp_path / "m.ply", empty)
    assert list(tmp_path.iterdir()) == []


def small_model():
    """A model of 4 shapes of the template's triangles."""
    from o3dreg import build_shape_model

    (_, faces), _, truths, _, _ = population(4)
    return build_shape_model(truths, faces)


def test_an_overwrite_that_is_not_a_bool_never_replaces_a_file(tmp_path):
    # "no" is truthy: read as a bool it would replace the file it was meant to keep.
    from o3dreg import write_landmarks

    path = tmp_path / "m.ply"
    write_triangle_mesh(path, sphere(8))
    marks = tmp_path / "p.mrk.json"
    write_landmarks(marks, ["a"], [[0.0, 0.0, 0.0]])
    model = small_model()
    saved = model.save(tmp_path / "model.npz")
    before = {p: p.read_bytes() for p in tmp_path.iterdir()}
    for write in (
        lambda flag: write_triangle_mesh(path, sphere(12), overwrite=flag),
        lambda flag: write_landmarks(marks, ["b"], [[1.0, 2.0, 3.0]], overwrite=flag),
        lambda flag: model.save(saved, overwrite=flag),
        lambda flag: model.write_meshes(tmp_path / "modes", overwrite=flag),
    ):
        for flag in ("no", "False", 0, None):
            with pytest.raises(TypeError, match="`overwrite` must be True or False"):
                write(flag)
    assert {p: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_a_refused_write_meshes_leaves_the_folder_as_it_was(tmp_path):
    model = small_model()
    folder = tmp_path / "modes"
    with pytest.raises(ValueError, match="`mode` must be in"):
        model.write_meshes(folder, modes=[99])
    with pytest.raises(TypeError, match="`standard_deviations` must be a sequence"):
        model.write_meshes(folder, standard_deviations=3)
    with pytest.raises(TypeError, match="`mode` must be an integer"):
        model.write_meshes(folder, modes=[1.7])
    assert not folder.exists()
    written = model.write_meshes(folder, modes=[0])
    os.remove(written[0])  # mean.ply gone, the mode meshes still there
    with pytest.raises(OSError, match="already holds mode1_-3sd.ply, mode1_"):
        model.write_meshes(folder, modes=[0])
    assert sorted(os.listdir(folder)) == ["mode1_+3sd.ply", "mode1_-3sd.ply"]


# -- 5/6. tracebacks, exit statuses, signals ---------------------------------------------------


def test_levels_too_fine_for_memory_is_one_line_exit_2(meshes):
    # Under a 3 GB address-space limit: a 1000^3 lattice must be refused, not allocated.
    done = python(
        """
        import resource, sys
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
        from o3dreg.cli import main
        sys.exit(main(sys.argv[1:]))
        """,
        "register", str(meshes / "t.ply"), str(meshes / "p.ply"), "-o", str(meshes / "r.ply"),
        "--levels", "1000",
    )  # fmt: skip
    assert done.returncode == 2, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not (meshes / "r.ply").exists() and parts(meshes) == []


def test_memory_error_is_one_line_exit_2(meshes, capsys, monkeypatch):
    from o3dreg.cli import _register

    def exhausted(args):
        raise MemoryError

    monkeypatch.setattr(_register, "run", exhausted)
    code, err = run_main(capsys, "register", str(meshes / "t.ply"), str(meshes / "p.ply"),
                         "-o", str(meshes / "r.ply"))  # fmt: skip
    assert code == 2 and "out of memory" in err and len(err.strip().splitlines()) == 1


def test_sigterm_is_one_line_exit_143_and_nothing_half_written(tmp_path):
    write_triangle_mesh(tmp_path / "t.ply", sphere(40))
    write_triangle_mesh(tmp_path / "p.ply", sphere(80))
    code = "import sys; from o3dreg.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "register", str(tmp_path / "t.ply"), str(tmp_path / "p.ply"),
         "-o", str(tmp_path / "r.ply"), "--report", str(tmp_path / "r.json"),
         "--levels", "2,4,8,16,32"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert proc.stdout is not None
    assert proc.stdout.readline().startswith("source")  # printed before the registration
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-2000:]
    # One line of ours (the progress bar may add its own on stderr).
    assert [line for line in err.splitlines() if "o3dreg" in line] == [
        "o3dreg register: terminated"
    ], err[-2000:]
    assert "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.ply", "t.ply"]


#: Interruptions of a registration: during the rigid step (after the command's first line) and
#: at a level boundary (after the first level's line), at varied delays: enough tries that a
#: race between the signal and a library call (threads unwound under a running query, threads
#: at interpreter shutdown) would show as a signal death (a negative return code).
INTERRUPTIONS = [
    (sig, stage, delay)
    for sig in (signal.SIGINT, signal.SIGTERM)
    for stage, delays in (
        ("rigid", (0.0, 0.1, 0.25, 0.4, 0.6)),
        ("level", (0.0, 0.01, 0.05, 0.1, 0.2, 0.4, 0.8)),
    )
    for delay in delays
]


def test_interrupts_during_a_registration_never_kill_by_signal(tmp_path):
    write_triangle_mesh(tmp_path / "t.ply", sphere(40))
    write_triangle_mesh(tmp_path / "p.ply", sphere(80))
    # As from a terminal: a suite started in the background (`cmd &` in a script) inherits
    # SIGINT ignored, which Python and so the CLI then keep ignored, as a background job should.
    code = (
        "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "from o3dreg.cli import console; console()"
    )
    expected = {signal.SIGINT: (130, "interrupted"), signal.SIGTERM: (143, "terminated")}
    outcomes = []
    for k, (sig, stage, delay) in enumerate(INTERRUPTIONS):
        out = tmp_path / f"run{k}"
        out.mkdir()
        proc = subprocess.Popen(
            [sys.executable, "-c", code, "-v", "register", str(tmp_path / "t.ply"),
             str(tmp_path / "p.ply"), "-o", str(out / "r.ply"), "--report", str(out / "r.json"),
             "--levels", "2,4,8,16,24"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )  # fmt: skip
        assert proc.stdout is not None and proc.stderr is not None
        assert proc.stdout.readline().startswith("source")  # printed before the registration
        lines = []
        if stage == "level":
            for line in proc.stderr:  # until the first level's line (logged at -v)
                lines.append(line)
                if "level 1/5" in line:
                    break
        time.sleep(delay)
        proc.send_signal(sig)
        err = "".join(lines) + proc.communicate(timeout=120)[1]
        outcomes.append((sig.name, stage, delay, proc.returncode))
        # A run that finished before the signal arrived exits by its verdict (0 or 1).
        if proc.returncode in (0, 1):
            continue
        code_expected, word = expected[sig]
        assert proc.returncode == code_expected, (outcomes, err[-2000:])
        # One line of ours, the last thing on its line (a progress bar may stand before it,
        # ended by a carriage return on a terminal).
        ours = [line for line in err.splitlines() if "o3dreg register:" in line]
        assert len(ours) == 1 and ours[0].endswith(f"o3dreg register: {word}"), err[-2000:]
        assert "Traceback" not in err
        assert list(out.iterdir()) == [], sorted(p.name for p in out.iterdir())
    # Most tries must land inside the registration, or the test tests nothing.
    assert sum(o[3] in (130, 143) for o in outcomes) >= 20, outcomes


def _seconds_to_run(code: str) -> float:
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, "-c", code], check=True, env={**os.environ, "PYTHONPATH": str(ROOT)}
    )
    return time.perf_counter() - start


def test_a_signal_while_the_command_starts_up_ends_it_cleanly(tmp_path):
    # The libraries load for a second or two before the command line is read; a signal then
    # must end `python -m o3dreg` as one during the command does. The delays spread over that
    # load, measured here, after the interpreter's own start (which no package can guard).
    write_triangle_mesh(tmp_path / "t.ply", sphere(40))
    write_triangle_mesh(tmp_path / "p.ply", sphere(80))
    bare = _seconds_to_run("pass")
    # The shorter of two loads: the first may read the libraries from a cold disk cache.
    loading = min(_seconds_to_run("import o3dreg") for _ in range(2)) - bare
    assert loading > 0.2, loading  # else the tries below would not land inside the load
    expected = {signal.SIGINT: (130, "interrupted"), signal.SIGTERM: (143, "terminated")}
    outcomes = []
    for k, (sig, share) in enumerate(
        (sig, share) for sig in expected for share in (0.1, 0.25, 0.4, 0.55, 0.7)
    ):
        out = tmp_path / f"run{k}"
        out.mkdir()
        proc = subprocess.Popen(
            [sys.executable, "-m", "o3dreg", "register", str(tmp_path / "t.ply"),
             str(tmp_path / "p.ply"), "-o", str(out / "r.ply"), "--report", str(out / "r.json")],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
            # As from a terminal: SIGINT not ignored, whatever the suite was started from.
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )  # fmt: skip
        time.sleep(2 * bare + share * loading)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
        outcomes.append((sig.name, share, proc.returncode))
        if proc.returncode in (0, 1):  # a load faster than measured: done before the signal
            continue
        status, word = expected[sig]
        assert proc.returncode == status, (outcomes, err[-2000:])
        assert [line for line in err.splitlines() if "o3dreg" in line] == [
            f"o3dreg register: {word}"
        ], err[-2000:]
        assert list(out.iterdir()) == []
    assert sum(o[2] in (130, 143) for o in outcomes) >= 8, outcomes


def test_importing_o3dreg_keeps_the_programs_signal_handlers():
    # SIGINT as the interpreter set it up: its default handler, or ignored where the suite runs
    # as a background job (the shell ignores SIGINT there, and Python keeps that).
    code = (
        "import signal; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
        "before = signal.getsignal(signal.SIGINT); import o3dreg; "
        "assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN; "
        "assert signal.getsignal(signal.SIGINT) is before"
    )
    subprocess.run(
        [sys.executable, "-c", code], check=True, env={**os.environ, "PYTHONPATH": str(ROOT)}
    )


def test_closed_standard_streams_keep_the_exit_status(model_dir, tmp_path):
    # With stdout closed (`>&-`) the command ended in a traceback and status 1; with stderr
    # closed its error line went to stdout, status 1 instead of 2.
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    command = f'"{sys.executable}" -m o3dreg model info'

    def shell(line: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            ["sh", "-c", line], capture_output=True, text=True, env=env, timeout=300
        )

    done = shell(f'{command} "{model_dir}" >&-')
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    done = shell(f'{command} "{tmp_path / "missing"}" 2>&-')
    assert done.returncode == 2 and done.stdout == "", done.stdout


def test_native_output_stays_off_stdout_so_json_is_valid(tmp_path):
    # Open3D and RPly print on file descriptor 1; inside the CLI that goes to stderr.
    done = python(
        """
        import json, os, sys
        from o3dreg.cli import _signals_and_streams
        with _signals_and_streams():
            os.write(1, b"[Open3D WARNING] from C++\\n")
            print(json.dumps({"ok": True}))
        """
    )
    assert json.loads(done.stdout) == {"ok": True}
    assert "[Open3D WARNING] from C++" in done.stderr


def test_register_json_is_valid_json(meshes):
    done = cli("register", str(meshes / "t.ply"), str(meshes / "p.ply"), "-o",
               str(meshes / "r.ply"), "--levels", "2", "--json")  # fmt: skip
    assert done.returncode in (0, 1), done.stderr[-2000:]
    assert json.loads(done.stdout)["output"] == str(meshes / "r.ply")


def test_unreachable_scheduler_is_found_before_any_work(meshes):
    pytest.importorskip("distributed")
    out = meshes / "model"
    done = cli("build-model", str(meshes / "t.ply"), str(meshes / "p.ply"), str(meshes / "p.ply"),
               "-o", str(out), "--scheduler", "tcp://127.0.0.1:9")  # fmt: skip
    assert done.returncode == 2 and "cannot reach" in done.stderr, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and not out.exists()


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(p) for p in path.read_text().split()] if path.exists() else []


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
def test_workers_end_with_a_killed_parent(tmp_path):
    write_triangle_mesh(tmp_path / "t.ply", sphere(30))
    for i in range(4):
        write_triangle_mesh(tmp_path / f"p{i}.ply", sphere(60 + i))
    code = "import sys; from o3dreg.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "build-model", str(tmp_path / "t.ply"),
         *[str(tmp_path / f"p{i}.ply") for i in range(4)], "-o", str(tmp_path / "model"),
         "--jobs", "2", "--levels", "2,4,8,16,32"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    deadline = time.monotonic() + 60
    workers: list[int] = []
    while time.monotonic() < deadline and len(workers) < 2:
        time.sleep(0.2)
        workers = [c for c in _children(proc.pid) if _alive(c)]
    assert len(workers) >= 2, "the workers did not start"
    time.sleep(1.0)
    proc.kill()  # SIGKILL: no Python code runs in the parent
    proc.wait()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.2)
    assert not any(_alive(w) for w in workers)


def test_demo_deletes_only_what_it_wrote(tmp_path):
    from o3dreg.cli._demo import _write_marker, prepare_output

    folder = tmp_path / "demo"
    (folder / "images").mkdir(parents=True)
    (folder / "report.md").write_text("old report")
    (folder / "images" / "a.png").write_bytes(b"png")
    _write_marker(str(folder), {"report.md", os.path.join("images", "a.png")})
    (folder / "notes.txt").write_text("mine")  # added by the user since
    with pytest.raises(OSError, match="notes.txt"):
        prepare_output(str(folder))
    assert (folder / "report.md").exists() and (folder / "notes.txt").read_text() == "mine"
    (folder / "notes.txt").unlink()
    # The earlier demo's files stay until a new run has finished and replaces them.
    assert prepare_output(str(folder)) == (
        str(folder),
        {"report.md", os.path.join("images", "a.png")},
    )
    assert (folder / "report.md").read_text() == "old report"


def test_an_interrupted_demo_leaves_the_earlier_one(tmp_path, monkeypatch, capsys):
    # Ctrl-C (or a full disk) in a second run deleted the first run's report and meshes.
    from o3dreg.cli import _demo

    folder = tmp_path / "demo"
    folder.mkdir()
    (folder / "report.md").write_text("old report")
    _demo._write_marker(str(folder), {"report.md"})

    def interrupted(output, **kwargs):
        (Path(output) / "report.md").write_text("half a new report")
        raise KeyboardInterrupt

    monkeypatch.setattr(_demo, "run_demo", interrupted)
    code, _ = run_main(capsys, "demo", "-o", str(folder))
    assert code == 130
    assert sorted(p.name for p in folder.iterdir()) == [_demo.MARKER, "report.md"]
    assert (folder / "report.md").read_text() == "old report"


def test_build_model_quiet_prints_nothing(meshes, capsys):
    from o3dreg.cli import main

    # Two distinct patients, so the registrations run and their table would be printed (the
    # same file twice is refused at once, before anything could be printed).
    write_triangle_mesh(meshes / "q.ply", sphere(12))
    code = main(["build-model", str(meshes / "t.ply"), str(meshes / "p.ply"),
                 str(meshes / "q.ply"), "-o", str(meshes / "m"), "--levels", "2", "-q"])  # fmt: skip
    captured = capsys.readouterr()
    assert code in (0, 1) and (meshes / "m" / "registrations").is_dir()  # both registered
    assert captured.out == ""


def test_every_output_option_follows_the_rule(meshes, capsys, model_dir):
    from o3dreg.shape.model import ShapeModel

    missing, p = str(meshes / "absent.ply"), str(meshes / "p.ply")
    code, err = run_main(capsys, "register", missing, p, "-o", str(meshes / "r.ply"),
                         "--html", str(meshes / "page.txt"))  # fmt: skip
    assert code == 2 and "--html must end with one of .html" in err
    code, err = run_main(capsys, "view", p, "--screenshot", str(meshes / "shot.jpg"))
    assert code == 2 and "--screenshot must end with .png" in err
    with pytest.raises(ValueError, match="`standard_deviations` must be finite"):
        ShapeModel.load(model_dir / "model.npz").mode_shape(0, float("nan"))


def test_a_concurrent_writer_is_never_overwritten(tmp_path):
    from o3dreg.io.mesh import atomic_write

    target = tmp_path / "r.txt"

    def writer(tmp):  # another process finishes the same output while this one writes
        target.write_text("the other writer's result")
        Path(tmp).write_text("mine")

    with pytest.raises(OSError, match="another writer"):
        atomic_write(target, writer)
    assert target.read_text() == "the other writer's result" and parts(tmp_path) == []


def test_a_failing_later_output_removes_the_earlier_ones(meshes, capsys, monkeypatch):
    from o3dreg.cli import _register

    def disk_full(path, data, *, overwrite, name="path"):
        raise OSError(f"--report: writing {path!r} failed: No space left on device")

    monkeypatch.setattr(_register, "write_json", disk_full)
    out = meshes / "r.ply"
    code, err = run_main(capsys, "register", str(meshes / "t.ply"), str(meshes / "p.ply"),
                         "-o", str(out), "--deformation", str(meshes / "d.npz"),
                         "--report", str(meshes / "r.json"), "--levels", "2")  # fmt: skip
    assert code == 2 and "No space left" in err
    assert sorted(p.name for p in meshes.iterdir()) == ["p.ply", "t.ply"]


def test_a_failed_overwrite_puts_the_earlier_outputs_back(meshes, capsys, monkeypatch):
    # With --overwrite, the outputs written before the failing one had replaced the earlier
    # run's: the command ended with a mix of new and old files.
    from o3dreg.cli import _register

    args = ["register", str(meshes / "t.ply"), str(meshes / "p.ply"), "-o", str(meshes / "r.ply"),
            "--deformation", str(meshes / "d.npz"), "--report", str(meshes / "r.json"),
            "--levels", "2"]  # fmt: skip
    assert run_main(capsys, *args)[0] in (0, 1)
    before = {p.name: p.read_bytes() for p in meshes.iterdir()}

    def disk_full(path, data, *, overwrite, name="path"):
        raise OSError(f"--report: writing {path!r} failed: No space left on device")

    monkeypatch.setattr(_register, "write_json", disk_full)
    code, err = run_main(capsys, *args, "--levels", "2,4", "--overwrite")
    assert code == 2 and "No space left" in err
    assert {p.name: p.read_bytes() for p in meshes.iterdir()} == before  # no hidden file either


def test_model_modes_on_a_full_disk_writes_no_mesh(model_dir, tmp_path):
    # A full disk in the middle of `model modes` left mean.ply behind an exit status 2, and
    # the message said only "writing ... failed".
    done = on_full_disk(
        tmp_path,
        f"""
        import os, sys
        from o3dreg.cli import main
        out = os.path.join(os.environ["FULL"], "modes")
        code = main(["model", "modes", "{model_dir}", "--modes", "1", "--sd", "-3", "-2",
                     "-1", "1", "2", "3", "-o", out])
        print("LEFT", sorted(os.listdir(out)))
        sys.exit(code)
        """,
        size="24k",
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "no space left" in done.stderr.lower(), done.stderr
    assert "LEFT []" in done.stdout, done.stdout
