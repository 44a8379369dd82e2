"""JSON text that every reader accepts: a measure that could not be taken (NaN, inf) is written
as ``null``, never as Python's ``NaN`` / ``Infinity``, which are not JSON (JavaScript's
``JSON.parse`` and most other parsers reject the whole document)."""

from __future__ import annotations

import json
import math
from typing import Any


def finite(data: Any) -> Any:
    """``data`` with every non-finite float (at any depth of dicts, lists, tuples) as ``None``."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {key: finite(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        return [finite(value) for value in data]
    return data


def dumps(data: Any, **options: Any) -> str:
    """:func:`json.dumps` of :func:`finite` ``(data)`` (refusing any NaN left: none can be)."""
    return json.dumps(finite(data), allow_nan=False, **options)
