"""Correspondence judged on real annotated anatomy: landmark transfer and prediction on mandibles.

The PDDCA CT masks of ``--data`` (default: the 8 development mandibles, research data in
``../shared/data/mandibles``) come with 3D Slicer annotations: ``chin`` and the two condyles
``mand_r`` / ``mand_l`` on the bone, placed on voxel centres 0.6-4 mm inside the marching-cubes
surface. Each mask becomes a surface (marching cubes at 0.5, largest component, 30 Taubin
iterations for the 2.5-3 mm slice staircase); a template is that surface decimated to
``--template-vertices``. A patient serves when its mask gives one mandible surface and its
landmark file places each of the three labels once, on it (``_mandibles.py``); any other is left
out with a line naming it and why. Below, N is the number of patients that serve (at least 3).

* **Transfer**: every template (N) onto every other patient (N - 1): o3dreg with its default
  settings (rigid start, default levels), the template's annotations carried by the
  deformation's map of space (``result.transform``); trimesh's ``nricp_amberg`` (default steps,
  unit-diagonal coordinates) from o3dreg's rigid start, the annotations attached to the template
  surface with their depth (``TemplateLandmarks.from_points``) and read off its moved vertices.
  The error is the distance to the patient's own annotation. Its **systematic** part is, per
  template and landmark, the length of the mean error vector over the N - 1 patients (the
  template's own annotation differing from the others'); the rest is the **random** part. Each
  method also carries **consensus** landmarks: for a pair, the mean of the template's annotation
  and those of the N - 2 patients outside the pair, read back onto the template through the
  method's own registrations onto them (``TemplateLandmarks.from_annotated_shapes``); the
  patient's own annotation is never used. It averages out the template annotator's placement,
  most of the systematic part. Averaging over templates the other way: each patient's landmarks
  estimated as the mean of what the templates carry there (per patient, with every template
  chosen).
* **Prediction** (the paper's goal): for every template and every held-out patient, a shape model
  of the other N - 2 patients' semilandmark meshes (the transfer's registrations),
  :func:`~o3dreg.predict_landmarks` of the template's annotations (with their depth) on the
  held-out patient, read on the fitted instance registered onto the patient surface (the
  default), on it with every vertex moved to its closest patient point (``onto='closest'``) and
  on the instance itself; the same fit read with the landmarks snapped onto the surface, and with the
  landmarks averaged from the annotations of the template and the model's N - 2 patients
  (``TemplateLandmarks.from_annotated_shapes``); with a rigid model (size kept, the paper) and a
  similarity model (``build_shape_model(scaling=True)``). With ``--cut f`` the held-out
  patient's surface loses its top ``f`` of its height (z) first: a partial patient, whose
  missing part (both condyles for ``f = 0.2``) the model infers.
* **Decomposition** of o3dreg's transfer error (``--decompose``): along the CT slice axis z and
  in the slice plane; along the patient surface's normal at the annotation and tangential to
  it; the difference of the two annotations' depths below the surface; the error the voxel
  grid alone would leave (both annotations uniform in their voxel, each axis its spacing); the
  floor of a registration that is exact up to the annotations (their depth difference along
  the normal plus that voxel error in the tangent plane); and a fit of ``e_ab = o_a - o_b +
  r_ab``, one offset ``o`` per annotation (the same whichever patient it is carried to or from),
  which splits the error into what the annotations explain and what is left to each
  registration (it needs 2 or more templates: with one, the offsets explain every error and
  the fit says so instead).
* **Inverse-consistent transfer** (``--inverse-consistent``): the pair's registration the other
  way round as well (the patient's surface decimated like a template, registered onto the
  template's surface; with every template it is another pair's forward registration), the
  template's annotation carried backwards through it (``result.inverse_transform``: the point
  that map sends onto the annotation), and the mean of the forward and backward estimates. A
  bias that both directions make the same way (a protrusion the map does not quite reach) has
  opposite signs in the two estimates and cancels in the mean. Its time per pair counts both
  registrations.

    python benchmarks/bench_landmarks.py                       # N x (N - 1) pairs, both methods
    python benchmarks/bench_landmarks.py --templates 2 --skip-peer --skip-prediction
    python benchmarks/bench_landmarks.py --data OTHER/mandibles --templates 0522c0001,0522c0002
    python benchmarks/bench_landmarks.py --skip-peer --barycentre-weighting uniform
    python benchmarks/bench_landmarks.py --skip-peer --skip-prediction --decompose
    python benchmarks/bench_landmarks.py --skip-peer --skip-prediction --inverse-consistent
    python benchmarks/bench_landmarks.py --skip-peer --cut 0.2     # predict on partial patients

Prints the figures and the ratios against the peer measured in the same run; skips with a message
where the data are absent or fewer than 3 patients serve. Nothing derived from the masks is
written.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

ROOT = Path(__file__).resolve().parents[1]
LABELS = ("chin", "mand_r", "mand_l")
#: Patients the benchmark needs: a template and 2 patients, so that its error over them has a
#: systematic and a random part.
MIN_PATIENTS = 3


def data_dir() -> Path:
    """The default mandible folder: ``$O3DREG_SHARED_DATA/mandibles``, else
    ``../shared/data/mandibles`` beside the repository."""
    env = os.environ.get("O3DREG_SHARED_DATA")
    base = Path(env) if env else ROOT.parent / "shared" / "data"
    return base / "mandibles"


def load(template_vertices: int, folder: Path | None = None) -> dict:
    """Per patient that serves: the surface, the template decimated from it and the 3
    annotations (LPS); a line printed for each patient left out (``_mandibles.load_patients``).

    Parameters
    ----------
    template_vertices : int
    folder : Path, optional
        Holding ``masks/`` and ``landmarks/``. Default :func:`data_dir`.
    """
    from _mandibles import load_patients

    return load_patients(folder or data_dir(), LABELS, template_vertices)


def chosen_templates(spec: str | None, ids: Sequence[str]) -> list[str]:
    """The patients ``--templates`` chooses as templates.

    Parameters
    ----------
    spec : str or None
        Comma-separated entries, each a patient id or an index into ``ids`` (an id first);
        ``None`` chooses every patient.
    ids : sequence of str
        The patients that serve, sorted.

    Returns
    -------
    list of str
        The ids, in the order given.

    Raises
    ------
    ValueError
        An entry that names no patient of ``ids``, or a patient named twice.
    """
    if spec is None:
        return list(ids)
    chosen: list[str] = []
    for entry in (part.strip() for part in spec.split(",")):
        if entry in ids:
            pid = entry
        elif entry.isdigit() and int(entry) < len(ids):
            pid = ids[int(entry)]
        else:
            raise ValueError(
                f"`--templates` must list indices 0-{len(ids) - 1} or ids of the {len(ids)} "
                f"patients that serve ({', '.join(ids)}), got {entry!r} in {spec!r}"
            )
        if pid in chosen:
            raise ValueError(
                f"`--templates` must name each template once, got {pid} twice in {spec!r}"
            )
        chosen.append(pid)
    return chosen


def ordinal(n: int) -> str:
    """``1st``, ``2nd``, ``3rd``, ``4th``, ..., ``11th``, ``21st``."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def amberg(template: tuple, rigid: np.ndarray, surface: tuple) -> np.ndarray:
    """Template vertices moved by trimesh's nricp_amberg from the rigid start ``rigid``."""
    import trimesh
    import trimesh.registration as treg

    sv = template[0] @ rigid[:3, :3].T + rigid[:3, 3]
    centre = surface[0].mean(axis=0)
    scale = float(np.linalg.norm(np.ptp(surface[0], axis=0)))
    source = trimesh.Trimesh((sv - centre) / scale, template[1], process=False)
    target = trimesh.Trimesh((surface[0] - centre) / scale, surface[1], process=False)
    return np.asarray(treg.nricp_amberg(source, target)) * scale + centre


def without_top(surface: tuple, fraction: float) -> tuple:
    """The surface without its triangles above ``1 - fraction`` of its height (z)."""
    if fraction <= 0:
        return surface
    v, f = surface
    top = v[:, 2].max() - fraction * np.ptp(v[:, 2])
    return v, f[(v[f][:, :, 2] < top).all(axis=1)]


def consensus_landmarks(
    data: dict, tid: str, moved: dict[tuple[str, str], np.ndarray], patients: list[str]
):
    """Template ``tid``'s landmarks as the mean of its annotation and those of ``patients``,
    each read back through a method's registration onto that patient (``moved[tid, p]``: the
    registered template vertices)."""
    from o3dreg import TemplateLandmarks

    # An annotation is read back however far its registered surface stayed from it (a part the
    # registration did not reach): 50 mm, half a mandible.
    return TemplateLandmarks.from_annotated_shapes(
        data[tid]["template"],
        [data[tid]["template"][0]] + [moved[tid, p] for p in patients],
        [data[tid]["landmarks"]] + [data[p]["landmarks"] for p in patients],
        max_distance=50.0,
    )


class Underdetermined(ValueError):
    """The offset fit cannot split the error: too few pairs for the offsets."""


def offset_fit(
    pairs: Sequence[tuple[int, int]], errors: np.ndarray, count: int
) -> tuple[np.ndarray, np.ndarray]:
    """Fit ``e_ab = o_a - o_b + r_ab``: one offset per annotation, least squares with sum(o) = 0.

    Parameters
    ----------
    pairs : sequence of (a, b)
        Each pair's template and patient, as indices of their annotations.
    errors : (p, l, 3) ndarray
        Each pair's error vectors ``e_ab``.
    count : int
        The number of annotations.

    Returns
    -------
    explained : (p, l, 3) ndarray
        ``o_a - o_b`` of each pair.
    rest : (p, l, 3) ndarray
        ``r_ab``.

    Raises
    ------
    Underdetermined
        When an annotation is in no pair with the others (its offset is not fitted), or there
        are no more pair errors than free offsets (one template: the offsets explain every
        error and leave no rest).
    """
    design = np.zeros((len(pairs), count))
    for k, (a, b) in enumerate(pairs):
        design[k, a], design[k, b] = 1.0, -1.0
    # The pairs fix the offsets up to a common shift (the sum fixes it): the differences they
    # determine are the rank of their rows, count - 1 when every annotation is tied in.
    free = int(np.linalg.matrix_rank(design)) if len(pairs) else 0
    if free < count - 1:
        raise Underdetermined(
            f"the {len(pairs)} pairs tie only {free + 1} of the {count} annotations together; "
            "the others' offsets are not determined"
        )
    if len(pairs) <= free:
        raise Underdetermined(
            f"{len(pairs)} pair errors for {free} free offsets: the offsets would explain every "
            "error exactly and leave no rest"
        )
    stacked = np.vstack([errors.reshape(len(pairs), -1), np.zeros((1, errors[0].size))])
    full = np.vstack([design, np.ones((1, count))])
    offsets = np.linalg.lstsq(full, stacked, rcond=None)[0].reshape(count, *errors.shape[1:])
    explained = np.stack([offsets[a] - offsets[b] for a, b in pairs])
    return explained, errors - explained


def decompose(vectors: np.ndarray) -> tuple[float, float]:
    """Systematic and random parts of error vectors ``(templates, patients, landmarks, 3)``."""
    mean = vectors.mean(axis=1, keepdims=True)
    return float(np.linalg.norm(mean, axis=-1).mean()), float(
        np.linalg.norm(vectors - mean, axis=-1).mean()
    )


def decomposition(
    data: dict, vectors: np.ndarray, chosen: list[str], peer: np.ndarray | None = None
) -> None:
    """Print where the transfer error lies (see the module docstring), per landmark and overall.

    With ``peer`` (the same pairs' error vectors by another method), the offsets are fitted to
    its errors as well: offsets that the two methods find alike belong to the annotations (or
    the surfaces both read), not to either method's registration.
    """
    from o3dreg import TemplateLandmarks

    ids = sorted(data)
    rng = np.random.default_rng(0)
    # The annotation's foot point, outward normal and signed depth on its own patient's surface.
    own = {}
    for pid in ids:
        attached = TemplateLandmarks.from_points(
            data[pid]["surface"], data[pid]["landmarks"], max_distance=50.0
        )
        _, frames = attached.frames(data[pid]["surface"][0])
        own[pid] = (frames[:, 2], attached.depths)
    rows: dict[str, list[np.ndarray]] = {
        "total": [],
        "along z (slice axis)": [],
        "in the slice plane": [],
        "along the normal": [],
        "tangential": [],
        "|depth difference|": [],
        "voxel grid alone": [],
        "floor: depth + voxel": [],
    }
    pairs: list[tuple[int, int]] = []
    errors: list[np.ndarray] = []
    for a, tid in enumerate(chosen):
        for b, pid in enumerate(p for p in ids if p != tid):
            e = vectors[a, b]
            normal, depth = own[pid]
            along = (e * normal).sum(axis=1)
            rows["total"].append(np.linalg.norm(e, axis=1))
            rows["along z (slice axis)"].append(np.abs(e[:, 2]))
            rows["in the slice plane"].append(np.linalg.norm(e[:, :2], axis=1))
            rows["along the normal"].append(np.abs(along))
            rows["tangential"].append(np.linalg.norm(e - along[:, None] * normal, axis=1))
            gap = own[tid][1] - depth
            rows["|depth difference|"].append(np.abs(gap))
            # Each annotation uniform in its voxel (a voxel centre stands for the whole voxel).
            grid = (
                rng.uniform(-0.5, 0.5, (4000, 1, 3)) * data[tid]["spacing"]
                - rng.uniform(-0.5, 0.5, (4000, 1, 3)) * data[pid]["spacing"]
            )
            voxel = float(np.linalg.norm(grid, axis=-1).mean())
            rows["voxel grid alone"].append(np.full(len(LABELS), voxel))
            flat = grid - (grid * normal).sum(axis=-1, keepdims=True) * normal
            floor = np.linalg.norm(gap[:, None] * normal + flat, axis=-1).mean(axis=0)
            rows["floor: depth + voxel"].append(floor)
            pairs.append((ids.index(tid), ids.index(pid)))
            errors.append(e)
    try:
        explained, rest = offset_fit(pairs, np.stack(errors), len(ids))
    except Underdetermined as exc:
        unfitted = (
            f"offsets o_a - o_b and rest r_ab not fitted, underdetermined ({len(chosen)} "
            f"template{'s' if len(chosen) != 1 else ''} x {len(ids) - 1} patients): {exc}; "
            "2 or more templates give the fit more pair errors than offsets"
        )
    else:
        unfitted = ""
        rows["offsets o_a - o_b"] = list(np.linalg.norm(explained, axis=-1))
        rows["rest r_ab"] = list(np.linalg.norm(rest, axis=-1))
        if peer is not None:
            other = np.stack([peer[a, b] for a in range(len(chosen)) for b in range(len(ids) - 1)])
            peer_explained, _ = offset_fit(pairs, other, len(ids))
            rows["peer's offsets"] = list(np.linalg.norm(peer_explained, axis=-1))
            rows["|offsets - peer's|"] = list(np.linalg.norm(explained - peer_explained, axis=-1))
    print("\ndecomposition of o3dreg's transfer error (mean of |.|, mm)")
    print(f"{'part':<26}{'all':>7}" + "".join(f"{lab:>8}" for lab in LABELS))
    for name, found in rows.items():
        x = np.array(found)
        print(f"{name:<26}{x.mean():>7.2f}" + "".join(f"{c:>8.2f}" for c in x.mean(axis=0)))
    if unfitted:
        print(unfitted)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--data",
        metavar="FOLDER",
        help="the mandible folder: masks/<id>_Mandible.nrrd and landmarks/<id>_Landmarks.fcsv "
        "(default: $O3DREG_SHARED_DATA/mandibles, else ../shared/data/mandibles)",
    )
    parser.add_argument("--template-vertices", type=int, default=3000)
    parser.add_argument(
        "--templates",
        help="comma-separated templates: patient ids, or indices into the patients that serve, "
        "sorted by id (default all)",
    )
    parser.add_argument("--skip-peer", action="store_true")
    parser.add_argument("--skip-prediction", action="store_true")
    parser.add_argument(
        "--decompose", action="store_true", help="where o3dreg's transfer error lies (see above)"
    )
    parser.add_argument(
        "--barycentre-weighting",
        choices=["count", "uniform"],
        help="o3dreg's DistanceEstimation.barycentre_weighting (default: the library default)",
    )
    parser.add_argument(
        "--cut",
        type=float,
        default=0.0,
        help="predict on the held-out patient's surface without its top CUT of its height "
        "(z; 0.2 removes both condyles): a partial patient (see above)",
    )
    parser.add_argument(
        "--inverse-consistent",
        action="store_true",
        help="also carry each annotation backwards through the patient-onto-template "
        "registration, and average the two estimates (see above)",
    )
    args = parser.parse_args(argv)
    folder = Path(args.data) if args.data else data_dir()
    if not (folder / "masks").is_dir() or not (folder / "landmarks").is_dir():
        if args.data:
            parser.error(
                f"--data {folder} must hold masks/ (<id>_Mandible.nrrd) and landmarks/ "
                "(<id>_Landmarks.fcsv)"
            )
        print(f"skip: no mandible masks and landmarks in {folder} (research data, not shipped)")
        return 0
    import igl

    import o3dreg
    from o3dreg import TemplateLandmarks, build_shape_model, predict_landmarks

    logging.getLogger("o3dreg").setLevel(logging.ERROR)
    data = load(args.template_vertices, folder)
    if len(data) < MIN_PATIENTS:
        print(
            f"skip: {len(data)} patient(s) of {folder} serve, at least {MIN_PATIENTS} needed (a "
            "template and 2 patients to carry its landmarks to)"
        )
        return 0
    estimation = (
        None
        if args.barycentre_weighting is None
        else o3dreg.DistanceEstimation(barycentre_weighting=args.barycentre_weighting)
    )
    ids = sorted(data)
    try:
        chosen = chosen_templates(args.templates, ids)
    except ValueError as exc:
        parser.error(str(exc))
    both = ["o3dreg backward", "o3dreg mean"] if args.inverse_consistent else []
    methods = ["o3dreg"] + both + ([] if args.skip_peer else ["nricp_amberg"])
    vectors = {m: np.zeros((len(chosen), len(ids) - 1, len(LABELS), 3)) for m in methods}
    seconds = dict.fromkeys(methods, 0.0)
    statuses: list[str] = []
    shapes: dict[tuple[str, str], np.ndarray] = {}
    peer_shapes: dict[tuple[str, str], np.ndarray] = {}
    results: dict[tuple[str, str], o3dreg.ElasticRegistrationResult] = {}
    took: dict[tuple[str, str], float] = {}
    for a, tid in enumerate(chosen):
        template = data[tid]["template"]
        attached = TemplateLandmarks.from_points(template, data[tid]["landmarks"])
        for b, pid in enumerate(p for p in ids if p != tid):
            surface, truth = data[pid]["surface"], data[pid]["landmarks"]
            start = time.perf_counter()
            result = o3dreg.registration_elastic(template, surface, estimation_method=estimation)
            took[tid, pid] = time.perf_counter() - start
            seconds["o3dreg"] += took[tid, pid]
            statuses.append(result.status)
            vectors["o3dreg"][a, b] = result.transform(data[tid]["landmarks"]) - truth
            shapes[tid, pid] = result.vertices
            if args.inverse_consistent:
                results[tid, pid] = result
            if "nricp_amberg" in methods:
                start = time.perf_counter()
                moved = amberg(template, result.transformation, surface)
                seconds["nricp_amberg"] += time.perf_counter() - start
                peer_shapes[tid, pid] = moved
                vectors["nricp_amberg"][a, b] = attached.positions(moved) - truth
        print(f"template {tid}: done", file=sys.stderr, flush=True)
    for a, tid in enumerate(chosen if args.inverse_consistent else []):
        for b, pid in enumerate(p for p in ids if p != tid):
            if (pid, tid) not in results:  # the reverse pair, unless it was a forward one
                start = time.perf_counter()
                results[pid, tid] = o3dreg.registration_elastic(
                    data[pid]["template"], data[tid]["surface"], estimation_method=estimation
                )
                took[pid, tid] = time.perf_counter() - start
                statuses.append(results[pid, tid].status)
            start = time.perf_counter()
            forward = results[tid, pid].transform(data[tid]["landmarks"])
            backward = results[pid, tid].inverse_transform(data[tid]["landmarks"])
            # Every backward estimate pays for its registration, done here or as a forward pair.
            seconds["o3dreg backward"] += took[pid, tid] + time.perf_counter() - start
            truth = data[pid]["landmarks"]
            vectors["o3dreg backward"][a, b] = backward - truth
            vectors["o3dreg mean"][a, b] = 0.5 * (forward + backward) - truth
    if args.inverse_consistent:
        seconds["o3dreg mean"] = seconds["o3dreg"] + seconds["o3dreg backward"]
    # The template annotator's placement averaged out: for every pair, the template's landmarks
    # from its own annotation and those of the N - 2 patients other than the pair's (read back
    # through the method's registrations onto them), carried by the pair's registered vertices.
    # No registration is added; the patient's own annotation is not used.
    for m, moved in (("o3dreg", shapes), ("nricp_amberg", peer_shapes)):
        if m not in methods:
            continue
        name = f"{m} consensus"
        methods.append(name)
        vectors[name] = np.zeros_like(vectors[m])
        seconds[name] = seconds[m]
        for a, tid in enumerate(chosen):
            for b, pid in enumerate(p for p in ids if p != tid):
                others = [p for p in ids if p not in (tid, pid)]
                consensus = consensus_landmarks(data, tid, moved, others)
                found = consensus.positions(moved[tid, pid])
                vectors[name][a, b] = found - data[pid]["landmarks"]

    pairs = len(chosen) * (len(ids) - 1)
    print(
        f"transfer: {len(chosen)} templates x {len(ids) - 1} patients = {pairs} pairs, "
        f"template {args.template_vertices} vertices; error = distance to the patient's own "
        "annotation, mm"
    )
    counts = ", ".join(f"{s} {statuses.count(s)}" for s in sorted(set(statuses)))
    print(f"o3dreg verdicts (every registration run): {counts}")
    width = max(len(m) for m in methods) + 2
    head = (
        f"{'method':<{width}}{'mean':>7}"
        + "".join(f"{lab:>8}" for lab in LABELS)
        + f"{'max':>7}{'system.':>9}{'random':>8}{'s/pair':>8}"
    )
    print(head)
    means = {}
    for m in methods:
        err = np.linalg.norm(vectors[m], axis=-1)
        systematic, random = decompose(vectors[m])
        means[m] = float(err.mean())
        print(
            f"{m:<{width}}{err.mean():>7.2f}"
            + "".join(f"{e:>8.2f}" for e in err.mean(axis=(0, 1)))
            + f"{err.max():>7.2f}{systematic:>9.2f}{random:>8.2f}{seconds[m] / pairs:>8.2f}"
        )
    if "nricp_amberg" in means:
        print(
            f"o3dreg / nricp_amberg mean transfer error: {means['o3dreg'] / means['nricp_amberg']:.2f}"
            f" (time {seconds['o3dreg'] / seconds['nricp_amberg']:.2f})"
        )
        if "o3dreg consensus" in means:
            ratio = means["o3dreg consensus"] / means["nricp_amberg consensus"]
            print(f"the same with consensus landmarks: {ratio:.2f}")
    if len(chosen) > 1:
        # Averaging over templates: each patient's landmarks estimated as the mean of what every
        # chosen template other than the patient carries there (each template annotator's
        # placement averages out; the patient annotator's stays).
        print(
            f"mean of the templates' transfers, per patient ({len(ids)} patients; each the mean "
            "of the estimates of the chosen templates other than the patient):"
        )
        for m in [m for m in methods if m in ("o3dreg", "nricp_amberg")]:
            per_patient = []
            for pid in ids:
                found = [
                    vectors[m][a, [p for p in ids if p != tid].index(pid)]
                    for a, tid in enumerate(chosen)
                    if tid != pid
                ]
                per_patient.append(np.mean(found, axis=0))
            err = np.linalg.norm(np.array(per_patient), axis=-1)
            print(
                f"{m:<{width}}{err.mean():>7.2f}"
                + "".join(f"{e:>8.2f}" for e in err.mean(axis=0))
                + f"{err.max():>7.2f}"
            )
    if args.inverse_consistent:
        # No annotation of the patient's in it: how far the two maps disagree on one point.
        gap = np.linalg.norm(vectors["o3dreg"] - vectors["o3dreg backward"], axis=-1)
        print(
            "|forward - backward| (mean, chin, mand_r, mand_l): "
            + "  ".join(f"{x:.2f}" for x in (gap.mean(), *gap.mean(axis=(0, 1))))
        )
    for m in ["o3dreg"] + both:
        print(f"per template ({m}: mean, chin, mand_r, mand_l):")
        err = np.linalg.norm(vectors[m], axis=-1)
        for a, tid in enumerate(chosen):
            row = err[a].mean(axis=0)
            print(f"  {tid}: {err[a].mean():.2f}  " + "  ".join(f"{e:.2f}" for e in row))
    if args.decompose:
        decomposition(data, vectors["o3dreg"], chosen, vectors.get("nricp_amberg"))
        if args.inverse_consistent:
            print("(o3dreg mean, forward and backward)", end="")
            decomposition(data, vectors["o3dreg mean"], chosen)

    if args.skip_prediction:
        return 0
    if len(ids) < 4:
        # build_shape_model needs 2 shapes: the patients other than the template and the held-out.
        print(
            f"\nprediction skipped: its model is built of the patients other than the template "
            f"and the held-out one, 2 or more needed (4 patients); {len(ids)} serve"
        )
        return 0
    held_out = ordinal(len(ids) - 1)
    print(
        f"\nprediction: model of {len(ids) - 2} patients' semilandmark meshes, predict_landmarks "
        f"on the {held_out} ({len(chosen) * (len(ids) - 1)} predictions), mm"
        + (f"; the {held_out} without the top {args.cut:.0%} of its height" if args.cut > 0 else "")
    )
    print(
        f"{'model':<12}{'landmarks':<15}{'read on':<11}{'mean':>7}"
        + "".join(f"{lab:>8}" for lab in LABELS)
        + f"{'max':>7}{'system.':>9}{'random':>8}"
    )
    for scaling in (False, True):
        statuses = []
        rows: dict[tuple[str, str], list[np.ndarray]] = {}
        for tid in chosen:
            template = data[tid]["template"]
            attached = TemplateLandmarks.from_points(template, data[tid]["landmarks"])
            others = [p for p in ids if p != tid]
            for held in others:
                train = [p for p in others if p != held]
                model = build_shape_model(
                    [shapes[tid, p] for p in train], template[1], scaling=scaling
                )
                patient = without_top(data[held]["surface"], args.cut)
                pred = predict_landmarks(model, attached, patient)
                # onto='closest' from the same fit (predict_landmarks would fit the model again):
                # every vertex of the fitted instance moved to its closest patient point.
                _, _, on_patient = igl.point_mesh_squared_distance(
                    np.asarray(pred.fit.vertices, dtype=np.float64), *patient
                )
                statuses.append(pred.status)
                truth = data[held]["landmarks"]
                # The landmarks from the annotations of all the model's patients and the template.
                annotated = consensus_landmarks(data, tid, shapes, train)
                # Read on the instance registered onto the patient (predict_landmarks' default),
                # its vertices moved to their closest patient points (onto='closest') and the
                # instance itself (on_target=False): the same fit.
                readings = (
                    ("registered", pred.vertices),
                    ("closest", on_patient),
                    ("instance", pred.fit.vertices),
                )
                for where, mesh in readings:
                    for name, landmarks in (
                        ("template", attached),
                        ("snapped", attached.on_surface()),
                        (f"{len(ids) - 1} annotations", annotated),
                    ):
                        found = landmarks.positions(mesh) - truth
                        rows.setdefault((name, where), []).append(found)
        counts = ", ".join(f"{s} {statuses.count(s)}" for s in sorted(set(statuses)))
        print(f"{'similarity' if scaling else 'rigid'} predictions' verdicts: {counts}")
        for (name, where), found in rows.items():
            v = np.array(found).reshape(len(chosen), len(ids) - 1, len(LABELS), 3)
            e = np.linalg.norm(v, axis=-1)
            systematic, random = decompose(v)
            print(
                f"{'similarity' if scaling else 'rigid':<12}{name:<15}{where:<11}{e.mean():>7.2f}"
                + "".join(f"{x:>8.2f}" for x in e.mean(axis=(0, 1)))
                + f"{e.max():>7.2f}{systematic:>9.2f}{random:>8.2f}"
            )
    print(
        "model: rigid = build_shape_model(scaling=False) (size kept, the paper), similarity = "
        "scaling=True (size removed, fitted with a scale); landmarks: the template's annotations "
        "with their depth, the same snapped onto the surface, the mean of the template's and the "
        f"{len(ids) - 2} model patients' annotations (TemplateLandmarks.from_annotated_shapes); "
        "read on: the "
        "fitted instance registered onto the patient surface (predict_landmarks' default), its "
        "vertices moved to their closest patient points (onto='closest') or the instance itself "
        "(on_target=False)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
