"""Numbers in the plain sentences of warnings."""

from __future__ import annotations

#: A factor beyond this is "over" it: an exact fit's distance (to rounding, ~1e-15 of the size)
#: makes any ratio to it meaningless digits.
LARGEST_FACTOR = 1000.0


def ratio_text(larger: float, smaller: float) -> str:
    """``larger / smaller`` to two significant digits below 10, to the unit from there to
    :data:`LARGEST_FACTOR`, ``'over 1000'`` beyond (a ``smaller`` of 0 included)."""
    if smaller <= 0 or larger >= LARGEST_FACTOR * smaller:
        return f"over {LARGEST_FACTOR:.0f}"
    ratio = larger / smaller
    return f"{ratio:.2g}" if ratio < 10 else f"{ratio:.0f}"
