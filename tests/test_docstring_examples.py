"""The examples in the package's docstrings run and print what they say (doctest).

Every module with an example is collected here: an example no test runs can be false unnoticed
(``registration_rigid``'s box half-turned is one such example)."""

import doctest
import importlib
import pkgutil
from pathlib import Path

import pytest

import o3dreg


def modules_with_examples() -> list[str]:
    names = []
    for info in pkgutil.walk_packages(o3dreg.__path__, "o3dreg."):
        spec = importlib.util.find_spec(info.name)
        if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
            continue
        if ">>> " in Path(spec.origin).read_text(encoding="utf-8"):
            names.append(info.name)
    return names


MODULES = modules_with_examples()


def test_examples_are_found():
    assert "o3dreg.registration.rigid" in MODULES and "o3dreg.registration.elastic" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
