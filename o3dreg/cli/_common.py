"""Helpers shared by the sub-commands: argument types, output checks, tables and progress."""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from ..meshio import atomic_write


def int_list(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def float_list(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected non-negative numbers, got {text!r}")
    return values


def check_outputs(paths: dict[str, str | None], overwrite: bool) -> None:
    """Refuse before any work if an output exists (unless ``overwrite``) or its folder is missing."""
    for option, path in paths.items():
        if path is None:
            continue
        folder = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(folder):
            raise OSError(f"{option}: folder {folder!r} does not exist")
        if os.path.exists(path) and not overwrite:
            raise OSError(f"{option}: {path!r} exists; pass --overwrite to replace it")


def write_json(path: str, data: Any, *, overwrite: bool) -> str:
    def writer(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=2, sort_keys=False)
            fh.write("\n")

    return atomic_write(path, writer, overwrite=overwrite, name="report")


def emit(text: str, args: argparse.Namespace) -> None:
    """Human output on stdout unless ``--quiet`` or ``--json``."""
    if not getattr(args, "quiet", False) and not getattr(args, "json", False):
        print(text)


def emit_json(data: Any) -> None:
    json.dump(data, sys.stdout, indent=2)
    sys.stdout.write("\n")
