"""Helpers shared by the sub-commands: argument types, output checks, tables and progress."""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from ..io.mesh import atomic_write_text


def _number_list(text: str, convert: type, kind: str, minimum: float) -> list:
    try:
        values = [convert(v) for v in text.split(",") if v.strip()]
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
    return atomic_write_text(
        path, json.dumps(data, indent=2) + "\n", overwrite=overwrite, name="report"
    )


def emit(text: str, args: argparse.Namespace) -> None:
    """Human output on stdout unless ``--quiet`` or ``--json``."""
    if not getattr(args, "quiet", False) and not getattr(args, "json", False):
        print(text)


def emit_json(data: Any) -> None:
    json.dump(data, sys.stdout, indent=2)
    sys.stdout.write("\n")
