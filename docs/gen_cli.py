"""Write docs/cli.md from the command line's own ``--help`` texts.

Run after changing a sub-command: ``python docs/gen_cli.py``; ``tests/test_docs.py`` fails when the
page is out of date.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from o3dreg.cli import build_parser

HERE = Path(__file__).resolve().parent

INTRO = """# Command line

`o3dreg` is installed with the package. Every sub-command prints its own help with `--help`.

Global options come before the sub-command: `--version`, `-q/--quiet` (errors only),
`-v/--verbose` (progress logging; `-vv` for debug details). `build-model` and `demo` report
their progress on standard error: a bar on a terminal, elsewhere (a log file, a CI job) a line
per finished patient and per step.

Exit status:

| status | meaning |
|---|---|
| **0** | success |
| **1** | the job ran and wrote its outputs but its verdict is not `ok` (`register`, `model fit`: the reasons are printed; the exit status follows the verdict alone, and a registration level that stopped at `--max-iteration` is a note on the "stopping criteria" line), or a batch (`build-model`, `demo`) had failed or flagged patients (the model is built from the `ok` ones; the others are listed with their reasons on standard error) |
| **2** | bad input, or a failure before any output was written: one line on standard error, no traceback, no partial file (also a full disk, a read-only folder, out of memory) |
| **130** | interrupted (Ctrl-C, SIGINT): one line; finished files are kept, no partial file |
| **143** | terminated (SIGTERM): as for SIGINT |

Both hold from the moment o3dreg's package starts loading (its libraries take one to two seconds
before the command line is read) until the process ends. Only a signal within the Python
interpreter's own start, the first few tens of milliseconds, ends it by the signal.

Outputs: no existing file is replaced unless `--overwrite` is given; two outputs of one command
never share a path; an output never names one of the command's inputs (even with
`--overwrite`); every output's suffix, folder and write permission are checked before any work.
Files are written atomically (a hidden temporary file beside the output, flushed to disk and,
for meshes, read back before it is renamed), so an output name holds a complete file or nothing.
When one output of `register` fails (a full disk) or the command is interrupted while writing
them, the outputs it already wrote are removed and those it replaced with `--overwrite` are put
back: exit status 2 means no new file, and the earlier run's files stay as they were.
`build-model` refuses a folder that already holds a model unless `--overwrite` (finished
registrations are reused either way; a patient is registered again when the template, its file
or the options changed, and its record names where its file is now). The model's files are
written into a hidden folder and moved into place together once all are written, so a failed or
interrupted rebuild leaves the earlier model; `demo` likewise replaces an earlier demo's files
only when it has finished. Worker processes (`--jobs`) end with the command. Messages of the C++
libraries (Open3D, RPly) go to standard error, so `--json` output is always valid JSON. A
mistyped option or value is one line on standard error, with the command's `--help` to see.
Progress bars are drawn on a terminal only (`register`, `build-model`); in a log file,
`register -v` logs one line per level instead.

The Python API raises these types (the command line turns each into exit status 2): `TypeError`
for an argument of the wrong kind; `ValueError` for a wrong shape or value, and for a file whose
content is unusable (a truncated or corrupt `.npz`, NaN values in an archive, a volume header
with zero or NaN spacing); `OSError` for a missing, unreadable or truncated file and for an output
that cannot be written (exists without `overwrite`, folder missing or read-only, disk full);
`RuntimeError` for a missing optional dependency or a failed renderer; `MemoryError` only when
the machine runs out of memory. See [Robustness](robustness.md#data-safety) for the faults
tried.

Pictures and pages without a GPU: `o3dreg view MESH --screenshot PNG` draws with matplotlib by
default (a second or two, on any machine); `--backend open3d` uses Open3D's Filament renderer,
which on a machine without a GPU runs on software Vulkan and can hang, so it runs in a child
process stopped after `--time-limit` seconds. `o3dreg build-model` writes an interactive
`MODEL_DIR/explorer.html` (mode sliders, variance table, every patient's registration coloured
by distance with its verdict; one self-contained file that works offline), `o3dreg model
explore` rewrites it, and `o3dreg register ... --html PAGE.html` writes one registration's page;
see [the explorer](shape-model.md#explorer-in-the-browser).
"""


def _subparsers(parser) -> dict:
    """The sub-commands of an o3dreg parser (it records its ``add_subparsers`` action)."""
    return {} if parser.subcommands is None else dict(parser.subcommands.choices)


def render() -> str:
    os.environ["COLUMNS"] = "100"  # stable wrapping
    parser = build_parser()
    parts = [INTRO, "## o3dreg", "", "```text", parser.format_help().rstrip(), "```", ""]

    def walk(prefix: str, sub: argparse.ArgumentParser) -> None:
        parts.extend([f"## {prefix}", "", "```text", sub.format_help().rstrip(), "```", ""])
        for name, child in _subparsers(sub).items():
            walk(f"{prefix} {name}", child)

    for name, sub in _subparsers(parser).items():
        walk(f"o3dreg {name}", sub)
    return "\n".join(parts)


def main() -> None:
    (HERE / "cli.md").write_text(render(), encoding="utf-8")
    print(f"wrote {HERE / 'cli.md'}")


if __name__ == "__main__":
    main()
