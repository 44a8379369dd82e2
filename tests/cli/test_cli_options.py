"""Options several commands share are defined once (cli/_common.py): the same flag, action and
help everywhere."""

import re

from o3dreg.cli import build_parser


def parsers(parser):
    yield parser
    if parser.subcommands is not None:
        for sub in parser.subcommands.choices.values():
            yield from parsers(sub)


def test_every_parser_records_each_option_its_usage_shows():
    # The errors that name a command's flags read the options the parser recorded: every option
    # of the usage line (groups and mutually exclusive groups included) must be among them, and
    # nothing else.
    for parser in parsers(build_parser()):
        usage = parser.format_usage()
        shown = set(re.findall(r"(?<![\w-])(--?[a-zA-Z][\w-]*)", usage))
        recorded = [action.option_strings for action in parser.options if action.option_strings]
        assert shown <= {flag for flags in recorded for flag in flags}, parser.prog
        assert all(shown & set(flags) for flags in recorded), parser.prog
        assert len(recorded) >= 3, parser.prog  # -h, -q, -v at least


def test_a_shared_option_reads_the_same_in_every_command():
    found = {}
    for parser in parsers(build_parser()):
        for action in parser.options:
            for flag in ("--json", "--jobs"):
                if flag in action.option_strings:
                    found.setdefault(flag, set()).add((action.help, action.default))
            if "--overwrite" in action.option_strings:
                assert action.help.startswith("replace "), (parser.prog, action.help)
    assert {flag: len(kinds) for flag, kinds in found.items()} == {"--json": 1, "--jobs": 1}
