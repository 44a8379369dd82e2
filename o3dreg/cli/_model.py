"""``o3dreg build-model`` and ``o3dreg model {info, modes, fit, explore}``: statistical shape models.

``build-model`` is a thin adapter over :func:`o3dreg.app.model_folder.build_model_folder`, which
documents the model folder's layout.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from collections.abc import Iterator
from typing import Any

import numpy as np

from .._validation import named_as
from ..app.explorer import write_model_explorer
from ..app.model_folder import (
    build_model_folder,
    check_inputs_outside,
    existing_model_files,
    patient_landmark_file,
)
from ..io import json_text
from ..io.landmark_files import LANDMARK_SUFFIXES, select_labels
from ..io.mesh import make_folder, read_triangle_mesh
from ..registration.options import ElasticLevel
from ..shape.landmark_transfer import (
    LANDMARK_REACH,
    PREDICTION_ONTO,
    OffTemplateError,
    landmark_errors,
    load_template_landmarks,
    predict_landmarks,
    read_landmarks,
    write_landmarks,
)
from ..shape.model import ShapeModel
from ..shape.statismo import read_statismo
from ._common import (
    add_jobs_option,
    add_json_option,
    add_labels_option,
    add_overwrite_option,
    all_or_nothing,
    check_input_files,
    check_outputs,
    emit,
    int_list,
    positive_int,
    process_pool,
    standard_deviations,
)
from ._registration_options import (
    add_registration_options,
    far_landmark_warnings,
    far_landmarks,
    read_quietly,
    settings_from_args,
)

logger = logging.getLogger("o3dreg")


BUILD_EPILOG = """The registration options are those of `o3dreg register` (one option set).

verdict: every patient's registration is judged 'ok', 'suspect' or 'failed' (as by o3dreg
register), then checked against the others: a patient whose mean distances or Procrustes
residual are outliers among the registered patients (robust z-score > 3.5 and more than twice
the median; five patients or more) becomes 'suspect'. Only 'ok' patients enter the model unless
--keep-flagged; the table lists every flagged patient with its reasons.

landmarks: with --landmarks TEMPLATE_FILE, patient PATH/NAME.EXT is started from the landmarks
in PATH/NAME.mrk.json, PATH/NAME.fcsv or PATH/NAME.csv (the first that exists; labels paired
with the template's: the same labels in every file, or those of --labels, which every file must
hold). A patient without a landmark file stops the command before any registration; landmarks
far from their own mesh (another patient's file, RAS against LPS) are named before it.

exit status: 0 every patient registered with verdict 'ok'; 1 a patient failed or was flagged
(the model is built from the others), or fewer than 2 'ok' patients; 2 bad input."""


FIT_EPILOG = """reading: the landmarks are read on the fitted instance brought onto the patient's
surface, by an elastic registration of the instance from where the fit left it (default,
--onto registration: the default levels from 8 cells on) or by moving each of its vertices to
its closest patient point (--onto closest).

verdict: the fit is judged 'ok', 'suspect' or 'failed' against the model's own
population: its distance to the patient against the model's leave-one-out residuals, the
Mahalanobis distance of its coefficients, the patient's size against the training shapes'
(models built without --scaling), and whether the patient's mirror image fits clearly better
(left and right swapped); with --onto registration, the registration's verdict as well (the
worse of the two is reported).

exit status: 0 verdict 'ok'; 1 'suspect' or 'failed' (outputs written, the reasons printed);
2 bad input.

landmarks: every landmark of --landmarks must lie on the template (a .h5 model: its mean
shape), within 5% of its size; --labels chooses those to predict from a file that also holds
others (a Slicer file with landmarks of the skull beside a mandible's), and --truth then needs
only those.

examples:
  o3dreg model fit model/ patient.ply --landmarks landmarks.mrk.json
  o3dreg model fit model/ patient.ply --landmarks lm.fcsv --labels chin,mand_r,mand_l
  o3dreg model fit model.h5 patient.ply --landmarks lm.csv --truth truth.csv --json"""


def add_parser(subparsers: Any) -> None:
    build = subparsers.add_parser(
        "build-model",
        help="register a template onto many patients and build a shape model",
        description="Batch elastic registration of TEMPLATE onto every TARGET (resumable), "
        "generalised Procrustes alignment, PCA; writes the model folder.",
        epilog=BUILD_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    build.add_argument(
        "template", metavar="TEMPLATE", help="template mesh (moves; ~1k-4k vertices)"
    )
    build.add_argument("targets", metavar="TARGET", nargs="+", help="patient meshes")
    build.add_argument("-o", "--output", required=True, help="model folder (created)")
    add_jobs_option(build)
    build.add_argument("--scheduler", help="Dask scheduler ADDRESS (tcp://host:8786) to run on")
    build.add_argument("--force", action="store_true", help="register finished patients again")
    add_registration_options(build)
    build.add_argument(
        "--landmarks",
        metavar="TEMPLATE_FILE",
        help="start each registration from landmarks: TEMPLATE_FILE on the template, and per "
        "patient PATIENT.mrk.json, PATIENT.fcsv or PATIENT.csv beside PATIENT's mesh (same stem)",
    )
    add_labels_option(build, "TEMPLATE_FILE and the patients' files")
    build.add_argument(
        "--keep-flagged",
        action="store_true",
        help="also put patients whose verdict is 'suspect' or 'failed' in the model",
    )
    build.add_argument(
        "--scaling", action="store_true", help="similarity Procrustes (size removed)"
    )
    build.add_argument(
        "--slide",
        action="store_true",
        help="slide the semilandmarks along the patient surfaces before the PCA (least bending "
        "energy from the mean; it moves them away from the registration's correspondences: "
        "see docs/shape-model.md)",
    )
    add_overwrite_option(
        build, "a folder that already holds a model (finished registrations are reused)"
    )
    add_json_option(build)
    build.set_defaults(func=run_build)

    model = subparsers.add_parser("model", help="inspect and use a shape model")
    sub = model.add_subparsers(dest="model_command", metavar="ACTION")
    info = sub.add_parser("info", help="variance table (Table 4)")
    info.add_argument(
        "model_dir",
        metavar="MODEL",
        help="model folder (o3dreg build-model) or statismo / scalismo .h5 file",
    )
    add_json_option(info)
    info.set_defaults(func=run_info)
    modes = sub.add_parser("modes", help="write mean and mode meshes (Figure 6)")
    modes.add_argument(
        "model_dir",
        metavar="MODEL",
        help="model folder (o3dreg build-model) or statismo / scalismo .h5 file",
    )
    modes.add_argument(
        "--modes", type=positive_int, default=None, help="number of modes (default 2, or fewer)"
    )
    modes.add_argument(
        "--sd",
        type=standard_deviations,
        nargs="+",
        default=[-3.0, 3.0],
        help="multiples of the standard deviation",
    )
    modes.add_argument(
        "-o", "--output", help="folder (default MODEL/modes; MODEL_modes beside a .h5 file)"
    )
    add_overwrite_option(modes, "existing mesh files")
    add_json_option(modes)
    modes.set_defaults(func=run_modes)
    fit = sub.add_parser(
        "fit",
        help="fit the model to a patient and predict landmarks",
        description="Fit the model's pose and shape to PATIENT and predict the landmarks placed "
        "on the model's template.",
        epilog=FIT_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    fit.add_argument(
        "model_dir",
        metavar="MODEL",
        help="model folder (o3dreg build-model) or statismo / scalismo .h5 file",
    )
    fit.add_argument("patient", metavar="PATIENT", help="patient mesh")
    fit.add_argument(
        "--landmarks",
        required=True,
        help="landmarks on the model's template (a model folder) or on its mean shape, in the "
        "model's frame (a .h5 file) (.mrk.json, .fcsv, .csv, .pp; LPS)",
    )
    add_labels_option(fit, "--landmarks")
    fit.add_argument("--truth", help="true landmarks on the patient, to report errors")
    fit.add_argument(
        "-o", "--output", help="write predicted landmarks (.mrk.json, .fcsv, .csv, .pp; LPS)"
    )
    add_overwrite_option(fit, "an existing --output")
    fit.add_argument("--modes", type=positive_int, default=None, help="modes used (default all)")
    fit.add_argument("--regularization", type=float, default=None, help="noise variance (mm^2)")
    fit.add_argument(
        "--onto",
        choices=PREDICTION_ONTO,
        default="registration",
        help="how the fitted instance is brought onto the patient surface (default registration)",
    )
    fit.add_argument(
        "--registration-levels",
        type=int_list,
        default=None,
        help="cells per axis of each level of that registration, coarse to fine (--onto "
        "registration; default the default levels from 8 cells on; levels given here weigh "
        "the barycentre term fully, as register's --levels)",
    )
    add_json_option(fit)
    fit.set_defaults(func=run_fit)
    _add_explore(sub)
    model.set_defaults(func=lambda args: (model.print_help(), 2)[1])


@contextlib.contextmanager
def _executor(args: argparse.Namespace) -> Iterator[Any]:
    """The executor of the registrations: a Dask client's, a process pool, or None (serial)."""
    if args.scheduler:
        try:
            from distributed import Client  # optional (the dask extra), seconds to import
        except ImportError as exc:
            raise RuntimeError("--scheduler needs Dask: pip install 'o3dreg[dask]'") from exc
        try:
            client = Client(args.scheduler, timeout="10s")
        except OSError as exc:  # TimeoutError included
            raise OSError(f"--scheduler: cannot reach {args.scheduler!r}: {exc}") from exc
        try:
            yield client.get_executor()
        finally:
            client.close()
        return
    with process_pool(args.jobs or 1) as pool:
        yield pool


def run_build(args: argparse.Namespace) -> int:
    _check_model_folder(args.output, args.overwrite)
    # model.py writes OUT/template.ply: a template file there would be replaced by its copy.
    check_inputs_outside(args.output, [args.template], "TEMPLATE")
    if args.labels and not args.landmarks:
        raise ValueError("--labels chooses landmarks of --landmarks: give --landmarks")
    template = read_triangle_mesh(args.template, name="TEMPLATE")
    if not args.scheduler:  # a Dask cluster's workers read the files: they may be theirs only
        check_input_files("TARGET", args.targets)
    if args.landmarks:
        with named_as("--landmarks"):
            _warn_far_template_landmarks(args.landmarks, template, args.labels)
        if not args.scheduler:
            _warn_far_patient_landmarks(args.targets, args.labels)
    # The library names the patient files `targets` and the landmark files `landmarks`,
    # `source` (the template's) and `target` (a patient's): the user typed TARGET and --landmarks.
    with (
        _executor(args) as executor,
        named_as("TEMPLATE", "template"),
        named_as("TARGET", "targets"),
        named_as("--landmarks", "landmarks"),
        named_as("--landmarks", "source"),
        named_as("TARGET landmarks", "target"),
    ):
        folder = build_model_folder(
            template,
            args.targets,
            args.output,
            executor=executor,
            force=args.force,
            overwrite=args.overwrite,
            progress=not (args.json or args.quiet),
            settings=settings_from_args(args, template),
            landmarks=args.landmarks,
            landmark_labels=args.labels,
            keep_flagged=args.keep_flagged,
            scaling=args.scaling,
            slide=args.slide,
            target_name="TARGET",
        )
    batch, model = folder.batch, folder.model
    emit(batch.table(), args)
    if model is None:
        message = (
            f"only {len(batch.accepted)} patient(s) registered with verdict 'ok'; a model needs "
            "at least 2 (--keep-flagged also uses flagged ones)"
        )
        if args.json:
            # What was done, for a script that reads the JSON: the patients and no model.
            print(
                json_text.dumps(
                    {
                        "model_dir": args.output,
                        "model": None,
                        "message": message,
                        "patients": batch.as_dicts(),
                        "registered": [r.name for r in batch.registered],
                        "failed": [r.name for r in batch.failed],
                    },
                    indent=2,
                )
            )
        print(f"o3dreg build-model: {message}", file=sys.stderr)
        return 1
    if args.json:
        print(json_text.dumps(folder.report, indent=2))
    else:
        emit(str(model), args)
        emit(model.variance_table(), args)
        for curve in folder.curves[1:]:
            emit(curve.table(), args)
    code = 0
    if batch.failed:
        print(
            f"o3dreg build-model: {len(batch.failed)} patient(s) failed: "
            f"{', '.join(r.name for r in batch.failed)}; the model was built without them",
            file=sys.stderr,
        )
        code = 1
    if batch.flagged:
        kept = (
            "kept in the model (--keep-flagged)"
            if args.keep_flagged
            else ("left out of the model (--keep-flagged keeps them)")
        )
        print(
            f"o3dreg build-model: {len(batch.flagged)} patient(s) flagged, {kept}: "
            + "; ".join(f"{r.name} ({r.verdict}: {'; '.join(r.warnings)})" for r in batch.flagged),
            file=sys.stderr,
        )
        code = 1
    return code


def _warn_far_template_landmarks(path: str, template: Any, labels: list[str] | None) -> None:
    """Name the landmarks of ``path`` (those of ``labels``) off the template's surface, as
    ``o3dreg register --landmarks`` does: they steer every patient's start all the same."""
    landmarks = read_landmarks(path)
    used = [landmarks[0][k] for k in select_labels(landmarks[0], labels, repr(path))]
    far = far_landmarks(landmarks, template, used)
    for line in far_landmark_warnings([("template", *far)], used):
        logger.warning("build-model: %s", line)


def _warn_far_patient_landmarks(targets: list[str], labels: list[str] | None) -> None:
    """Name each patient whose landmarks (those of ``labels``) lie off its own surface: its
    start is placed by them, so the registration begins wrong (a landmark file of another
    patient, or in other coordinates, RAS against the mesh's LPS). Files the build will refuse
    are left to it, which names them."""
    for target in targets:
        try:
            landmarks = read_quietly(patient_landmark_file(target))
            used = [landmarks[0][k] for k in select_labels(landmarks[0], labels, "")]
            far, limit = far_landmarks(landmarks, read_triangle_mesh(target), used)
        except (OSError, ValueError):
            continue
        if far:
            share = (
                f"all {len(used)}" if len(far) == len(used) else f"{len(far)} of its {len(used)}"
            )
            logger.warning(
                "build-model: TARGET %r: %s landmarks lie far from its surface (more than "
                "%.3g, %.0f%% of its size): %s; they place its start all the same: check that its "
                "landmark file is its own and in the mesh's coordinates",
                target,
                share,
                limit,
                100 * LANDMARK_REACH,
                ", ".join(f"{label} ({d:.3g})" for label, d in far.items()),
            )


def _check_model_folder(output: str, overwrite: bool) -> None:
    """Before any work: the folder can be created or written, and holds no model (or overwrite)."""
    if os.path.exists(output) and not os.path.isdir(output):
        raise OSError(f"--output: {output!r} exists and is not a folder")
    folder = output if os.path.isdir(output) else os.path.dirname(os.path.abspath(output))
    if not os.path.isdir(folder):
        raise OSError(f"--output: folder {folder!r} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OSError(f"--output: folder {folder!r} is not writable")
    present = existing_model_files(output) if os.path.isdir(output) else []
    if present and not overwrite:
        raise OSError(
            f"--output: {output!r} already holds a model ({', '.join(present)}); pass "
            "--overwrite to rebuild it "
            "(finished registrations are reused) or choose another folder"
        )


#: Suffixes of a statismo / scalismo model file, accepted wherever a model folder is.
STATISMO_SUFFIXES = (".h5", ".hdf5")


def _is_statismo(model: str) -> bool:
    return model.lower().endswith(STATISMO_SUFFIXES) and not os.path.isdir(model)


def _load(model_dir: str) -> Any:
    """The model of a model folder (``MODEL/model.npz``) or of a statismo ``.h5`` file."""
    if _is_statismo(model_dir):
        with named_as("MODEL"):
            return read_statismo(model_dir)
    if os.path.isfile(model_dir):
        raise ValueError(
            f"MODEL must be a model folder (o3dreg build-model) or a statismo .h5 file, "
            f"got the file {model_dir!r}"
        )
    path = os.path.join(model_dir, "model.npz")
    if not os.path.isfile(path):
        raise OSError(f"MODEL: no model.npz in {model_dir!r} (run o3dreg build-model)")
    with named_as("MODEL/model.npz"):
        return ShapeModel.load(path)


def _beside(model_dir: str, name: str) -> str:
    """``MODEL/name`` for a model folder, ``STEM_name`` beside a statismo file."""
    if _is_statismo(model_dir):
        return f"{os.path.splitext(model_dir)[0]}_{name}"
    return os.path.join(model_dir, name)


def run_info(args: argparse.Namespace) -> int:
    model = _load(args.model_dir)
    if args.json:
        print(
            json_text.dumps(
                {
                    "points": model.number_of_points,
                    "triangles": int(model.faces.shape[0]),
                    "shapes": list(model.names),
                    "scaling": model.scaling,
                    "total_variance": model.total_variance,
                    "variances": model.variance_records(),
                },
                indent=2,
            )
        )
    else:
        emit(f"{model}\n{model.variance_table()}", args)
    return 0


def run_modes(args: argparse.Namespace) -> int:
    model = _load(args.model_dir)
    folder = args.output or _beside(args.model_dir, "modes")
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise OSError(f"--output: {folder!r} exists and is not a folder")
    if args.modes is None:
        count = min(2, model.number_of_modes)
    elif args.modes > model.number_of_modes:
        raise ValueError(
            f"--modes must be at most {model.number_of_modes} (the model's modes), got {args.modes}"
        )
    else:
        count = args.modes
    sds = list(dict.fromkeys(args.sd))  # --sd 1 1 writes one file
    names = ["mean.ply"] + [f"mode{m + 1}_{c:+g}sd.ply" for m in range(count) for c in sds]
    if os.path.isdir(folder):
        # Named as the user gave the folder: --output, or the default beside the model.
        where = "--output" if args.output else f"{folder} (the default folder)"
        check_outputs(
            {f"{where} {name}": os.path.join(folder, name) for name in names}, args.overwrite
        )
    # How the messages name the folder: the option, also when its default is written.
    given = "--output" if args.output else "--output (its default)"
    make_folder(folder, given)
    # All the meshes or none (a full disk left mean.ply behind an exit status 2).
    with (
        all_or_nothing([os.path.join(folder, name) for name in names]),
        named_as(given),
        named_as(given, "folder"),
    ):
        written = model.write_meshes(
            folder, modes=range(count), standard_deviations=sds, overwrite=args.overwrite
        )
    if args.json:
        print(json_text.dumps({"written": written}, indent=2))
    else:
        emit("\n".join(written), args)
    return 0


def run_fit(args: argparse.Namespace) -> int:
    check_outputs(
        {"--output": args.output},
        args.overwrite,
        inputs={"--landmarks": args.landmarks, "--truth": args.truth, "PATIENT": args.patient},
        suffixes={"--output": LANDMARK_SUFFIXES},
    )
    if args.registration_levels is not None and args.onto != "registration":
        raise ValueError(
            f"--registration-levels sets the registration of --onto registration, "
            f"got --onto {args.onto}"
        )
    model = _load(args.model_dir)
    if _is_statismo(args.model_dir):
        # A statismo file's reference mesh is its mean: the landmarks are placed on it.
        template = model.mesh()
    else:
        template_path = os.path.join(args.model_dir, "template.ply")
        template = read_triangle_mesh(template_path, name="MODEL/template.ply")
        model.check_template(template, "MODEL/template.ply")
    try:
        with named_as("--landmarks"):
            landmarks = load_template_landmarks(args.landmarks, template, labels=args.labels)
    except OffTemplateError as exc:
        far = ", ".join(f"{label} ({d:.3g})" for label, d in zip(exc.far, exc.distances))
        where = "template" if not _is_statismo(args.model_dir) else "model's mean shape"
        message = (
            f"--landmarks {args.landmarks!r}: landmarks off the {where} (farther than "
            f"{exc.max_distance:.3g} from its surface, {LANDMARK_REACH:.0%} of its size): {far}"
        )
        if exc.near:
            raise ValueError(
                f"{message}; choose the landmarks on it with --labels {','.join(exc.near)}"
            ) from None
        if not _is_statismo(args.model_dir):
            raise ValueError(f"{message}; are they placed on this template?") from None
        centre = np.asarray(template.vertices).mean(axis=0)
        raise ValueError(
            f"{message}; a .h5 model holds no template: its landmarks go on its mean shape, in "
            f"the model's frame (centred at {np.round(centre, 3).tolist()}): place them on "
            "`o3dreg model modes` mean.ply, or use the model folder, whose template.ply is in "
            "the patients' frame"
        ) from None
    patient = read_triangle_mesh(args.patient, name="PATIENT")
    truth_file = None
    if args.truth:  # read before the fit: a bad file costs no work
        truth_file = read_landmarks(args.truth, name="--truth")
        repeated = sorted({lab for lab in truth_file[0] if truth_file[0].count(lab) > 1})
        if repeated:
            raise ValueError(f"--truth repeats landmark labels {repeated}")
        missing = [lab for lab in landmarks.labels if lab not in truth_file[0]]
        if missing:
            raise ValueError(f"--truth lacks landmarks {missing}")
    prediction = predict_landmarks(
        model,
        landmarks,
        patient,
        onto=args.onto,
        number_of_modes=args.modes,
        regularization=args.regularization,
        registration_options=None
        if args.registration_levels is None
        else {"levels": [ElasticLevel(r) for r in args.registration_levels]},
    )
    errors = None
    if truth_file is not None:
        labels, truth = truth_file
        index = {label: k for k, label in enumerate(labels)}
        truth_pts = truth[[index[lab] for lab in prediction.labels]]
        errors = landmark_errors(prediction.positions, truth_pts)
    if args.output:
        with named_as("--output"):
            write_landmarks(
                args.output, prediction.labels, prediction.positions, overwrite=args.overwrite
            )
    fit = prediction.fit
    if args.json:
        out: dict[str, Any] = {
            "landmarks": prediction.as_dict(),
            "fit": {
                "coefficients": fit.coefficients.tolist(),
                "transformation": fit.transformation.tolist(),
                "mean_distance": fit.mean_distance,
                "iterations": fit.iterations,
                "success": fit.success,
                "message": fit.message,
                "status": fit.status,
                "warnings": list(fit.warnings),
                "mahalanobis_distance": fit.mahalanobis_distance,
            },
            "onto": args.onto,
            "registration": None,
            "status": prediction.status,
            "warnings": list(prediction.warnings),
        }
        registration = prediction.registration
        if registration is not None:
            d = registration.distances
            out["registration"] = {
                "status": registration.status,
                "warnings": list(registration.warnings),
                "source_to_target_mean": d.source_to_target_mean,
                "target_to_source_mean": d.target_to_source_mean,
                "seconds": sum(level.seconds for level in registration.levels),
                "levels": [level.resolution for level in registration.levels],
            }
        if errors is not None:
            out["errors"] = dict(zip(prediction.labels, errors.tolist()))
            out["mean_error"] = float(errors.mean())
        print(json_text.dumps(out, indent=2))
    else:
        lines = [str(fit)]
        if prediction.registration is not None:
            lines.append(f"registered onto the patient: {prediction.registration.distances}")
        lines.append(
            f"{'landmark':<16}{'x':>10}{'y':>10}{'z':>10}"
            + (f"{'error':>10}" if errors is not None else "")
        )
        for k, (label, p) in enumerate(zip(prediction.labels, prediction.positions)):
            err = f"{errors[k]:>10.3g}" if errors is not None else ""
            lines.append(f"{label:<16}{p[0]:>10.2f}{p[1]:>10.2f}{p[2]:>10.2f}{err}")
        if errors is not None:
            lines.append(f"mean error {errors.mean():.3g} mm")
        status, warnings = prediction.status, prediction.warnings
        lines.append(f"verdict: {status}" + ("" if warnings else " (nothing looked wrong)"))
        lines += [f"  - {w}" for w in warnings]
        emit("\n".join(lines), args)
    if prediction.status != "ok" and (args.quiet or args.json):
        print(
            f"o3dreg model fit: verdict {prediction.status}: " + "; ".join(prediction.warnings),
            file=sys.stderr,
        )
    # The exit status follows the verdict of the fit and of the registration onto the patient
    # (a fit that did not converge is 'suspect').
    return 0 if prediction.status == "ok" else 1


def _vector3(text: str) -> list[float]:
    text = text.strip()
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z, got {text!r}")
    return values


def _add_explore(sub: Any) -> None:
    explore = sub.add_parser(
        "explore",
        help="write the interactive explorer page (modes, variances, patients)",
        description="Write a self-contained HTML page (works offline): the mean shape with a "
        "slider per mode (+-3 SD), the variance table, and each patient's registered template "
        "coloured by its distance to the patient, with its verdict.",
    )
    explore.add_argument(
        "model_dir",
        metavar="MODEL",
        help="model folder (o3dreg build-model) or statismo / scalismo .h5 file",
    )
    explore.add_argument(
        "-o",
        "--output",
        help="page to write (default MODEL/explorer.html; MODEL_explorer.html beside a .h5 file)",
    )
    explore.add_argument(
        "--up",
        type=_vector3,
        default=[0.0, 0.0, 1.0],
        metavar="X,Y,Z",
        help="world direction shown upwards at first (default 0,0,1)",
    )
    add_overwrite_option(explore, "an existing page")
    explore.set_defaults(func=run_explore)


def run_explore(args: argparse.Namespace) -> int:
    model = _load(args.model_dir)
    output = args.output or _beside(args.model_dir, "explorer.html")
    if args.output is not None:
        # A page: never one of the model's own files (an HTML page written over model.npz
        # destroyed the model).
        check_outputs({"--output": args.output}, args.overwrite, suffixes={"--output": (".html",)})
    folder = "" if _is_statismo(args.model_dir) else os.path.join(args.model_dir, "registrations")
    with named_as("--output" if args.output else "--output (its default)"):
        written = write_model_explorer(
            output,
            model,
            registrations=folder if folder and os.path.isdir(folder) else None,
            up=args.up,
            # A model folder's own page is rewritten; a page beside a statismo file may be anyone's.
            overwrite=args.overwrite or (args.output is None and not _is_statismo(args.model_dir)),
        )
    emit(str(written), args)
    return 0
