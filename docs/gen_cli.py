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
`-v/--verbose` (progress logging; `-vv` for debug details).

Exit status: **0** success; **1** the job ran and wrote its outputs but did not converge (or a
batch had failed patients); **2** bad input or a failure before any output was written (one line
on standard error, no partial files); **130** interrupted.

Outputs are never overwritten unless `--overwrite` is given, and are written atomically.
"""


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


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
