"""Options several commands share are defined once (cli/_common.py): the same flag, action and
help everywhere."""

import argparse

from o3dreg.cli import build_parser


def parsers(parser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from parsers(sub)


def test_a_shared_option_reads_the_same_in_every_command():
    found = {}
    for parser in parsers(build_parser()):
        for action in parser._actions:
            for flag in ("--json", "--jobs"):
                if flag in action.option_strings:
                    found.setdefault(flag, set()).add((action.help, action.default))
            if "--overwrite" in action.option_strings:
                assert action.help.startswith("replace "), (parser.prog, action.help)
    assert {flag: len(kinds) for flag, kinds in found.items()} == {"--json": 1, "--jobs": 1}
