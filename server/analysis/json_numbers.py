"""Numbers as JSON can carry them: the analysis marks "not defined" with NaN (numpy's way), the results API and
the exports with ``null`` (JSON has no NaN).  One rule for every module that hands analysis numbers out."""

from __future__ import annotations

import math
from typing import Any


def finite_or_none(value: float | None) -> float | None:
    """``value`` as a Python float, or None when it is None, NaN or infinite."""
    return None if value is None or not math.isfinite(value) else float(value)


def json_safe(value: Any) -> Any:
    """``value`` with every float made :func:`finite_or_none`, through dicts, lists and tuples (tuples become
    lists); other values unchanged."""
    if isinstance(value, float):
        return finite_or_none(value)
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value
