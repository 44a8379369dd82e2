"""Length units that files name (NRRD ``space units``, Slicer's ``coordinateUnits``) in mm."""

from __future__ import annotations

__all__ = ["UNIT_NAMES", "millimetres_per_unit"]

#: Millimetres per unit, by the names and UCUM codes files use (case-insensitive).
UNIT_NAMES = {
    "mm": 1.0, "millimeter": 1.0, "millimeters": 1.0, "millimetre": 1.0, "millimetres": 1.0,
    "cm": 10.0, "centimeter": 10.0, "centimeters": 10.0, "centimetre": 10.0, "centimetres": 10.0,
    "m": 1000.0, "meter": 1000.0, "meters": 1000.0, "metre": 1000.0, "metres": 1000.0,
    "um": 1e-3, "\u00b5m": 1e-3, "micron": 1e-3, "microns": 1e-3, "micrometer": 1e-3,
    "micrometers": 1e-3, "micrometre": 1e-3, "micrometres": 1e-3,
}  # fmt: skip


def millimetres_per_unit(name: object) -> float | None:
    """Millimetres per ``name`` (``'cm'`` -> 10), ``None`` for a unit not in :data:`UNIT_NAMES`."""
    if not isinstance(name, str):
        return None
    return UNIT_NAMES.get(name.strip().strip('"').lower())
