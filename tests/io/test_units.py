"""Length units named by files, in millimetres."""

from __future__ import annotations

import pytest

from o3dreg.io.units import millimetres_per_unit


@pytest.mark.parametrize(
    ("name", "mm"),
    [("mm", 1.0), ("CM", 10.0), ('"m"', 1000.0), ("um", 1e-3), ("\u00b5m", 1e-3), ("metres", 1e3)],
)
def test_units_in_millimetres(name, mm):
    assert millimetres_per_unit(name) == mm


@pytest.mark.parametrize("name", ["inch", "", "???", None, 3])
def test_an_unknown_unit_is_none(name):
    assert millimetres_per_unit(name) is None
