"""The ``o3dreg`` command line: one sub-command per module in this package.

Exit codes: 0 success; 1 the job ran and wrote its outputs but did not converge; 2 bad input or
a failure before any output was written; 130 interrupted.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from .. import __version__
from . import _demo, _model, _reconstruct, _register, _view

# Each sub-command module defines ``add_parser(subparsers)`` which registers itself with a
# ``func(args) -> int`` default. New sub-commands are added to this tuple.
_COMMANDS = (_register, _reconstruct, _model, _demo, _view)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="o3dreg",
        description="Elastic registration of surface meshes and statistical shape models.",
        epilog="exit status: 0 success; 1 the job ran and wrote its outputs but did not converge "
        "(or some patients failed); 2 bad input, nothing written; 130 interrupted. "
        "`o3dreg COMMAND --help` shows each command's options and examples.",
    )
    parser.add_argument("--version", action="version", version=f"o3dreg {__version__}")
    _add_verbosity(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in _COMMANDS:
        module.add_parser(sub)
    for child in _walk(sub):
        _add_verbosity(child, default=argparse.SUPPRESS)
        if child.epilog is None and child.prog in _EXAMPLES:
            child.epilog = "examples:\n" + "\n".join(f"  {line}" for line in _EXAMPLES[child.prog])
            child.formatter_class = argparse.RawDescriptionHelpFormatter
    return parser


# Examples for the sub-commands whose modules do not write their own epilog.
_EXAMPLES = {
    "o3dreg reconstruct": [
        "o3dreg reconstruct scan/ -o bone.ply --threshold 400 --largest 1 --smooth 10",
        "o3dreg reconstruct mask.nrrd -o mandible.ply --threshold 0.5 --largest 1 --smooth 20",
        "o3dreg reconstruct scan.nii.gz -o template.ply --threshold 400 --largest 1 --decimate 2500",
    ],
    "o3dreg build-model": [
        "o3dreg build-model template.ply bones/*.ply -o model/ --jobs 2",
        "o3dreg build-model template.ply bones/*.ply -o model/ --scheduler tcp://scheduler:8786",
    ],
    "o3dreg model": [
        "o3dreg model info model/",
        "o3dreg model modes model/ --modes 3 --sd -3 3",
        "o3dreg model fit model/ patient.ply --landmarks landmarks.mrk.json -o predicted.mrk.json",
    ],
    "o3dreg model info": ["o3dreg model info model/", "o3dreg model info model/ --json"],
    "o3dreg model modes": ["o3dreg model modes model/ --modes 3 --sd -3 3 -o modes/"],
    "o3dreg model fit": [
        "o3dreg model fit model/ patient.ply --landmarks landmarks.mrk.json",
        "o3dreg model fit model/ patient.ply --landmarks lm.csv --truth truth.csv --json",
    ],
}


def _walk(action: argparse._SubParsersAction) -> list[argparse.ArgumentParser]:
    """Every sub-command parser, nested ones included."""
    found = []
    for child in action.choices.values():
        found.append(child)
        for a in child._actions:
            if isinstance(a, argparse._SubParsersAction):
                found.extend(_walk(a))
    return found


def _add_verbosity(parser: argparse.ArgumentParser, default=None) -> None:
    """``-q`` / ``-v``, accepted before or after the sub-command."""
    group = parser.add_mutually_exclusive_group()
    kw = {} if default is None else {"default": default}
    group.add_argument("-q", "--quiet", action="store_true", help="print only errors", **kw)
    group.add_argument(
        "-v",
        "--verbose",
        action="count",
        help="log progress (-vv: debug details)",
        **({"default": 0} if default is None else kw),
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = (
        logging.ERROR
        if args.quiet
        else {0: logging.WARNING, 1: logging.INFO}.get(args.verbose, logging.DEBUG)
    )
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args))
    except (TypeError, ValueError, OSError, RuntimeError) as exc:
        print(f"o3dreg {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. piped into `head`: not an error of ours
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print(f"o3dreg {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
