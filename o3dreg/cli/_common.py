"""Helpers shared by the sub-commands: argument types, output checks, tables and progress."""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import contextlib
import math
import multiprocessing
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any

from ..io import json_text
from ..io.mesh import HOST, atomic_write_text


def _number_list(text: str, convert: type, kind: str, minimum: float) -> list:
    text = text.strip()
    items = text.split(",")
    if any(not v.strip() for v in items):
        # "2,,4" or "2,4,": a value left out is a typo, not a shorter list.
        raise argparse.ArgumentTypeError(
            f"expected comma-separated {kind} with no empty item, got {text!r}"
        )
    try:
        values = [convert(v) for v in items]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated {kind}, got {text!r}") from None
    if not values or min(values) < minimum:
        bound = "positive integers" if convert is int else "non-negative numbers"
        raise argparse.ArgumentTypeError(f"expected {bound}, got {text!r}")
    return values


def int_list(text: str) -> list[int]:
    """``"2,4,8"`` -> ``[2, 4, 8]`` (positive integers), for argparse ``type=``."""
    return _number_list(text, int, "integers", 1)


def float_list(text: str) -> list[float]:
    """``"0.1,1"`` -> ``[0.1, 1.0]`` (non-negative numbers), for argparse ``type=``."""
    return _number_list(text, float, "numbers", 0.0)


def label_list(text: str) -> list[str]:
    """``"chin,mand_r"`` -> ``["chin", "mand_r"]`` (landmark labels, spaces around them
    dropped), for argparse ``type=``."""
    items = [v.strip() for v in text.split(",")]
    if not all(items):
        raise argparse.ArgumentTypeError(
            f"expected comma-separated landmark labels with no empty item, got {text!r}"
        )
    return items


def add_labels_option(parser: argparse.ArgumentParser, files: str) -> None:
    """``--labels``: the landmarks of ``files`` to use, by label."""
    parser.add_argument(
        "--labels",
        type=label_list,
        metavar="LABEL,...",
        help=f"use only these landmarks of {files} (comma-separated labels, e.g. "
        "chin,mand_r,mand_l; default all): leave out landmarks of anatomy the meshes do not show",
    )


def finite_float(text: str) -> float:
    """A finite number, for argparse ``type=`` (``nan`` and ``inf`` are refused)."""
    text = text.strip()
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1, for argparse ``type=``."""
    text = text.strip()
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return value


# -- the options several commands share: one definition each ------------------------------------
def add_json_option(parser: argparse.ArgumentParser) -> None:
    """``--json``: the command's result as JSON on standard output."""
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


def add_jobs_option(parser: argparse.ArgumentParser) -> None:
    """``--jobs``: registrations run side by side, one process each."""
    parser.add_argument(
        "--jobs", type=positive_int, default=1, help="parallel registrations (processes)"
    )


def add_overwrite_option(parser: argparse.ArgumentParser, what: str) -> None:
    """``--overwrite``: replace ``what`` (the files the command writes) instead of refusing."""
    parser.add_argument("--overwrite", action="store_true", help=f"replace {what}")


def standard_deviations(text: str) -> float:
    """A multiple of a mode's standard deviation, at most 100 either way, for ``type=``
    (``1e308`` wrote meshes of inf coordinates)."""
    value = finite_float(text)
    if abs(value) > 100.0:
        raise argparse.ArgumentTypeError(f"expected a number in [-100, 100], got {text!r}")
    return value


def check_outputs(
    outputs: dict[str, str | None],
    overwrite: bool,
    *,
    inputs: dict[str, str | None] | None = None,
    suffixes: dict[str, Sequence[str]] | None = None,
) -> None:
    """The one rule for a command's output files, applied before any work.

    ``outputs`` and ``inputs`` map an option name (``"--output"``) to a path (``None``: not
    given). Raises ``ValueError`` when an output has another suffix than ``suffixes[option]``
    allows, when two outputs share a path or when an output is one of the inputs (even with
    ``overwrite``); ``OSError`` when an output's folder is missing or not writable, when an
    output is a folder, or when it exists and ``overwrite`` is false.
    """
    given = {option: path for option, path in outputs.items() if path is not None}
    for option, path in given.items():
        allowed = (suffixes or {}).get(option)
        if allowed and not path.lower().endswith(tuple(allowed)):
            expected = allowed[0] if len(allowed) == 1 else f"one of {', '.join(allowed)}"
            raise ValueError(f"{option} must end with {expected}, got {path!r}")
        folder = os.path.dirname(os.path.abspath(path))
        # Asked of the path as given too: the system resolves "x/../out.ply" through x.
        if not os.path.isdir(folder) or not os.path.isdir(os.path.dirname(path) or "."):
            raise OSError(f"{option}: folder {os.path.dirname(path) or folder!r} does not exist")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise OSError(f"{option}: cannot write {path!r}: folder {folder!r} is not writable")
        if os.path.isdir(path):
            raise OSError(f"{option}: {path!r} is a folder")
        if os.path.exists(path) and not overwrite:
            raise OSError(f"{option}: {path!r} exists; pass --overwrite to replace it")
    seen: dict[str, str] = {}
    for option, path in given.items():
        key = os.path.realpath(path)
        if key in seen:
            raise ValueError(f"{seen[key]} and {option} name the same file {path!r}")
        seen[key] = option
    for option, source in (inputs or {}).items():
        if source is None:
            continue
        key = os.path.realpath(source)
        if key in seen:
            raise ValueError(
                f"{seen[key]} {source!r} is the input {option}; an output never replaces an input"
            )


def check_input_files(name: str, paths: Sequence[str]) -> None:
    """Before any work: each of ``paths`` (the argument ``name``) is a file. ``OSError`` naming
    those missing (a typo: said at once, not as a failed patient after the others' work), or a
    folder."""
    missing = [p for p in paths if not os.path.isfile(p) and not os.path.isdir(p)]
    if missing:
        files = "no such file" if len(missing) == 1 else "no such files"
        raise OSError(f"`{name}`: {files} {', '.join(map(repr, missing))}")
    for path in paths:
        if os.path.isdir(path):
            raise OSError(f"`{name}`: {path!r} is a folder, not a file")


def write_json(path: str, data: Any, *, overwrite: bool, name: str) -> str:
    """``data`` as a JSON file (atomically); errors name the option ``name`` that gave ``path``."""
    return atomic_write_text(
        path, json_text.dumps(data, indent=2) + "\n", overwrite=overwrite, name=name
    )


def emit(text: str, args: argparse.Namespace) -> None:
    """Human output on stdout unless ``--quiet`` or ``--json``."""
    if not getattr(args, "quiet", False) and not getattr(args, "json", False):
        print(text)


def emit_json(data: Any) -> None:
    sys.stdout.write(json_text.dumps(data, indent=2))
    sys.stdout.write("\n")


#: How often a worker checks that the process that started it is still there (seconds).
PARENT_CHECK_SECONDS = 0.5


def _die_with_parent() -> None:  # pragma: no cover - runs in the worker processes
    """Worker initializer: the worker ends when its parent dies, even by SIGKILL (its parent
    process then changes: it is checked every :data:`PARENT_CHECK_SECONDS` on a thread)."""
    # A forked worker inherits the CLI's SIGTERM handler, which raises an exception that the
    # pool would catch and return: the worker must simply end.
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="o3dreg-parent-check", daemon=True).start()


@contextlib.contextmanager
def process_pool(jobs: int) -> Iterator[cf.ProcessPoolExecutor | None]:
    """A pool of ``jobs`` worker processes (None for one job) that never outlives the command.

    Workers end when the parent dies; on an exception (Ctrl-C, SIGTERM) pending work is
    cancelled and the running workers are terminated instead of waited for.
    """
    if jobs <= 1:
        yield None
        return
    # The pool's workers are the child processes started after it (it has no public handle).
    before = set(multiprocessing.active_children())
    pool = cf.ProcessPoolExecutor(jobs, initializer=_die_with_parent)
    try:
        yield pool
    except BaseException:
        # shutdown(wait=True) would wait for every running registration: end them now.
        workers = [p for p in multiprocessing.active_children() if p not in before]
        pool.shutdown(wait=False, cancel_futures=True)
        for worker in workers:
            worker.terminate()
        for worker in workers:
            worker.join(timeout=10)
        raise
    else:
        pool.shutdown()


@contextlib.contextmanager
def all_or_nothing(paths: Sequence[str | None]) -> Iterator[None]:
    """On an exception, remove the ``paths`` the block created and put back those it replaced.

    One command's outputs are then all written or none is (exit status 2 means nothing written),
    and a failed or interrupted ``--overwrite`` run leaves the earlier outputs as they were: each
    existing output is kept under a hidden name (a hard link: no copy) until the block ends.
    """
    chosen = [os.fspath(p) for p in paths if p is not None]
    new = [p for p in chosen if not os.path.lexists(p)]
    kept: dict[str, str] = {}
    try:
        for path in chosen:
            if path not in new and os.path.isfile(path) and path not in kept:
                kept[path] = _keep(path)
        yield
    except BaseException:
        for path in new:
            with contextlib.suppress(OSError):
                os.unlink(path)
        for path, backup in kept.items():
            with contextlib.suppress(OSError):
                os.replace(backup, path)
        raise
    finally:
        for backup in kept.values():
            with contextlib.suppress(OSError):
                os.unlink(backup)


def _keep(path: str) -> str:
    """A hidden hard link (a copy where links are refused) to ``path``, named as the atomic
    writer's temporary files, which a later write removes if this process is killed."""
    folder, name = os.path.split(os.path.abspath(path))
    base, suffix = os.path.splitext(name)
    backup = os.path.join(folder, f".{base}.{HOST}-{os.getpid()}.kept.part{suffix}")
    with contextlib.suppress(FileNotFoundError):
        os.unlink(backup)
    try:
        os.link(path, backup)
    except OSError:
        shutil.copy2(path, backup)
    return backup
