"""The ``o3dreg`` command line: one sub-command per module in this package.

Exit codes: 0 success; 1 the job ran and wrote its outputs but its verdict is not 'ok'; 2 bad input or
a failure before any output was written; 130 interrupted (Ctrl-C), 143 terminated (SIGTERM).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import re
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NoReturn, TextIO

from .. import __version__, _startup
from . import _demo, _model, _reconstruct, _register, _view

# Each sub-command module defines ``add_parser(subparsers)`` which registers itself with a
# ``func(args) -> int`` default. New sub-commands are added to this tuple.
_COMMANDS = (_register, _reconstruct, _model, _demo, _view)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line: the command, the message and where the
    help is (argparse prints the whole usage block first).

    It records what is added to it through argparse's public calls: ``options``, every
    argument (in groups too), and ``subcommands``, the action of :meth:`add_subparsers` (whose
    parsers are of this class too), for the error messages that name a command's flags.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.options: list[argparse.Action] = []
        self.subcommands: Any = None
        super().__init__(*args, **kwargs)

    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action:
        action = super().add_argument(*args, **kwargs)
        self.options.append(action)
        return action

    def add_argument_group(self, *args: Any, **kwargs: Any) -> Any:
        return self._recorded(super().add_argument_group(*args, **kwargs))

    def add_mutually_exclusive_group(self, **kwargs: Any) -> Any:
        return self._recorded(super().add_mutually_exclusive_group(**kwargs))

    def add_subparsers(self, **kwargs: Any) -> Any:
        self.subcommands = super().add_subparsers(**kwargs)
        return self.subcommands

    def _recorded(self, group: Any) -> Any:
        """``group`` with its arguments, and those of the groups made in it, recorded here."""
        add_argument, add_group = group.add_argument, group.add_mutually_exclusive_group

        def recorded_argument(*args: Any, **kwargs: Any) -> argparse.Action:
            action = add_argument(*args, **kwargs)
            self.options.append(action)
            return action

        group.add_argument = recorded_argument
        group.add_mutually_exclusive_group = lambda **kw: self._recorded(add_group(**kw))
        return group

    def error(self, message: str) -> NoReturn:
        if "expected one argument" in message:
            # argparse takes a value starting with '-' (other than a number) for an option:
            # after '=' it is a value.
            message += " (a value starting with '-' goes after '=': --output=-name.ply)"
        self.exit(
            EXIT_BAD_INPUT,
            f"{self.prog}: error: {message} (see `{self.prog} --help`)\n",
        )


def build_parser() -> _Parser:
    parser = _Parser(
        prog="o3dreg",
        description="Elastic registration of surface meshes and statistical shape models.",
        epilog="exit status: 0 success; 1 the job ran and wrote its outputs but its verdict is "
        "not 'ok' (or some patients failed); 2 bad input, nothing written; 130 interrupted (SIGINT), 143 terminated (SIGTERM); "
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
        "o3dreg model modes model/ --modes 3 --sd -3 3 --overwrite  # redraws model/modes/",
        "o3dreg model fit model/ patient.ply --landmarks landmarks.mrk.json -o predicted.mrk.json",
    ],
    "o3dreg model info": ["o3dreg model info model/", "o3dreg model info model/ --json"],
    "o3dreg model modes": ["o3dreg model modes model/ --modes 3 --sd -3 3 -o modes/"],
}


def _walk(action: Any) -> list[_Parser]:
    """Every sub-command parser of a :meth:`_Parser.add_subparsers` action, nested ones too."""
    found = []
    for child in action.choices.values():
        found.append(child)
        if child.subcommands is not None:
            found.extend(_walk(child.subcommands))
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


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that every ``finally`` (temporary files) runs."""


def _on_sigterm(signum: int, frame: Any) -> None:
    raise Terminated


def _exit_with(status: int) -> Callable[[int, Any], None]:
    """A handler for a signal that arrives once the command is done (its files written or
    removed) and the process is ending: the documented exit ``status``, where the default
    action would end it by the signal."""

    def handler(signum: int, frame: Any) -> None:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(status)

    return handler


@contextlib.contextmanager
def _signals_and_streams(ending: bool = False) -> Iterator[None]:
    """SIGTERM handled like SIGINT; native (Open3D, RPly) output on fd 1 sent to stderr.

    Afterwards the previous SIGTERM handler is back, or where that was the default (the signal
    ends the process), one that ends it with status 143; with ``ending`` (the process ends
    with the command) SIGINT and SIGTERM both end it with 130 and 143 from then on.

    Python's ``sys.stdout`` keeps the real standard output, so ``--json`` stays valid JSON
    whatever the C++ libraries print. Nothing is redirected when ``sys.stdout`` is not fd 1
    (an embedding program, a test capturing output).
    """
    main_thread = threading.current_thread() is threading.main_thread()
    previous = None
    if main_thread:
        previous = _startup.hand_over(signal.signal(signal.SIGTERM, _on_sigterm))
    try:
        real = sys.stdout.fileno() == 1
    except (AttributeError, OSError, ValueError):
        real = False
    saved, python_stdout = -1, sys.stdout
    if real:
        sys.stdout.flush()
        saved = os.dup(1)
        os.dup2(2, 1)
        sys.stdout = open(  # closed in the finally below
            saved, "w", encoding=python_stdout.encoding, closefd=False, buffering=1
        )
    try:
        yield
    finally:
        if main_thread:
            if ending:
                signal.signal(signal.SIGINT, _exit_with(EXIT_INTERRUPTED))
            default = ending or previous in (signal.SIG_DFL, None)
            signal.signal(signal.SIGTERM, _exit_with(EXIT_TERMINATED) if default else previous)
        if real:
            try:
                sys.stdout.flush()
            except BrokenPipeError:
                pass
            sys.stdout.close()
            sys.stdout = python_stdout
            os.dup2(saved, 1)
            os.close(saved)


def _chosen(parser: _Parser, args: argparse.Namespace) -> list[_Parser]:
    """The parsers that read ``args``: ``parser``, its chosen sub-command's, and so on."""
    found: list[_Parser] = []
    current: _Parser | None = parser
    while current is not None:
        found.append(current)
        sub = current.subcommands
        current = None if sub is None else sub.choices.get(getattr(args, sub.dest, None) or "")
    return found


def _with_flags(message: str, parser: _Parser, args: argparse.Namespace) -> str:
    """``message`` with each API parameter it names (```step_size```) followed by the command's
    flag for it (``(--step-size)``): the errors come from the library, the user typed flags."""
    flags: dict[str, str] = {}
    for current in _chosen(parser, args):
        for action in current.options:
            if action.option_strings and action.dest != "help":
                flags.setdefault(action.dest, max(action.option_strings, key=len))
    for dest, flag in flags.items():
        message = message.replace(f"`{dest}`", f"`{dest}` ({flag})")
    for name, dest in API_NAMES.items():
        if dest in flags and f"`{name}`" in message and f"`{name}` (" not in message:
            message = message.replace(f"`{name}`", f"`{name}` ({flags[dest]})")
    return message


#: API parameters whose command-line option has another name (its argparse dest): an error of
#: the library that names them names the option too.
API_NAMES = {
    "number_of_vertices": "decimate",
    "min_vertices": "min_component_vertices",
    "box": "crop_box",
    "plane": "crop_plane",
    "resolution": "levels",
    "number_of_modes": "modes",
    "landmark_labels": "labels",
}


#: Exit status of each outcome (documented in docs/cli.md).
EXIT_OK, EXIT_INCOMPLETE, EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 130, 143


def console() -> NoReturn:
    """The ``o3dreg`` command (and ``python -m o3dreg``): :func:`main` on ``sys.argv``, then the
    process ends with its status. A SIGINT or SIGTERM that arrives once the command is done,
    while the interpreter shuts down, ends it with the documented 130 or 143 rather than by the
    signal. The process ends right after the command, without the interpreter's shutdown: that
    first gives the signals their default actions back, then frees the libraries' objects for
    tens of milliseconds, during which a signal would end it by the signal. Every file of the
    command is closed by then; the logs and standard streams are flushed here."""
    # A stream closed by the caller (`>&-`) is None in Python: print() would write the other
    # stream's lines there (errors on stdout) and flushing it would raise.
    if sys.stdout is None:
        sys.stdout = open(os.devnull, "w")  # lives as long as the process
    if sys.stderr is None:
        sys.stderr = open(os.devnull, "w")
    try:
        status = main(ending=True)
    except SystemExit as done:  # argparse's --help, --version and usage errors
        if isinstance(done.code, str):
            print(done.code, file=sys.stderr)
        status = done.code if isinstance(done.code, int) else int(done.code is not None)
    try:
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed or broken pipe: nothing more to say
        pass
    os._exit(status)


def _warning_to_log(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: TextIO | None = None,
    line: str | None = None,
) -> None:
    """``warnings.showwarning`` of the command line: the message as an ``o3dreg`` log line (no
    source line, which would read as a traceback)."""
    logging.getLogger("o3dreg").warning("%s", message)


_NUMBER = r"(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
# A negative number, or a comma list starting with one, as the options take them: -1e9, -1,0,0.
_NEGATIVE_NUMBERS = re.compile(rf"-{_NUMBER}(?:,-?{_NUMBER})*")
# What argparse itself reads as a value: left as typed.
_PLAIN_NEGATIVE = re.compile(r"-\d+|-\d*\.\d+")


def _numbers_as_values(argv: Sequence[str]) -> list[str]:
    """``argv`` with each negative number (list) marked as a value: argparse reads a token
    starting with '-' as an option unless it is a plain negative number such as -3, so
    ``--up -1,0,0`` or ``--threshold -1e9`` would be refused. A leading space makes it a value
    (no option of ours starts with '-' and a digit; the converters strip it). Plain negative
    numbers and the tokens after ``--`` are left as they are."""
    out = list(argv)
    for k, token in enumerate(out):
        if token == "--":
            break
        if _NEGATIVE_NUMBERS.fullmatch(token) and not _PLAIN_NEGATIVE.fullmatch(token):
            out[k] = " " + token
    return out


def main(argv: Sequence[str] | None = None, *, ending: bool = False) -> int:
    """Run one command line (``argv``; default ``sys.argv[1:]``) and return its exit status
    (``ending``: the process ends with it, see :func:`console`)."""
    parser = build_parser()
    args, unknown = parser.parse_known_args(
        _numbers_as_values(sys.argv[1:] if argv is None else argv)
    )
    if unknown:  # named by the sub-command that was given them, with its --help
        _chosen(parser, args)[-1].error(f"unrecognized arguments: {' '.join(unknown)}")
    if args.quiet and args.verbose:  # one before the command, one after it: argparse lets both
        parser.error("-q/--quiet and -v/--verbose ask for opposite things: give one")
    level = (
        logging.ERROR
        if args.quiet
        else {0: logging.WARNING, 1: logging.INFO}.get(args.verbose, logging.DEBUG)
    )
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT
    command = _chosen(parser, args)[-1].prog  # "o3dreg model fit", as the user typed it
    try:
        with _signals_and_streams(ending), warnings.catch_warnings():
            # The library's warnings are log lines here: one line each, hidden by --quiet.
            warnings.showwarning = _warning_to_log
            return int(args.func(args))
    except BrokenPipeError:  # e.g. piped into `head`: not an error of ours
        sys.stderr.close()
        return EXIT_OK
    except (TypeError, ValueError, OSError, RuntimeError) as exc:
        # The documented exception types of the API: bad input, unreadable or unwritable files.
        print(f"{command}: error: {_with_flags(str(exc), parser, args)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except MemoryError:
        hint = "; e.g. fewer or coarser --levels" if hasattr(args, "levels") else ""
        print(
            f"{command}: error: out of memory (an input or an option asks for more than this "
            f"machine has{hint})",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    except Terminated:
        print(f"{command}: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print(f"{command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    console()
