"""A condition's place on a ladder (issue 38): which graded family it belongs to and at which level.

The clip set's conditions carry ``ladder`` and ``level`` once the ladder declarations land (plan.md: a clip-set
``[[ladders]]`` expands into conditions ``<ladder><level>``, a non-integer level written with ``_`` for ``.``).
Until every clip set does, a condition named that way with the fields absent is read by its name here.

LEAD: this name adapter (:func:`from_name`) is the one place that reads a level from a condition id; remove it
(and let :func:`level_of` require the manifest's fields) when the clip-set ladders are merged.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from typing import Any

_LEVEL = r"(?P<level>[0-9]+(?:_[0-9]+)?)"


def from_name(condition: str, ladder: str) -> float | None:
    """The level of ``condition`` on ``ladder`` read from its id (``pps12`` -> 12, ``eps0_5`` -> 0.5), or None if
    the id is not ``<ladder><level>``.  LEAD: the adapter, see the module docstring."""
    match = re.fullmatch(re.escape(ladder) + _LEVEL, condition)
    if match is None:
        return None
    return float(match.group("level").replace("_", "."))


def level_of(condition: str, ladder: str, entry: Mapping[str, Any] | Any | None = None) -> float | None:
    """The level of ``condition`` on ``ladder``: the clip's own ``ladder``/``level`` fields when it has them
    (a manifest entry or its dict), else its name (:func:`from_name`); None if it is not on that ladder."""
    if entry is not None:
        fields = entry if isinstance(entry, Mapping) else vars(entry) if hasattr(entry, "__dict__") else {}
        if fields.get("ladder") is not None:
            return float(fields["level"]) if fields["ladder"] == ladder and fields.get("level") is not None else None
    return from_name(condition, ladder)


def off_ladder(conditions: Iterable[str], ladder: str) -> list[str]:
    """The conditions of ``conditions`` that are not levels of ``ladder`` (by name)."""
    return [c for c in conditions if from_name(c, ladder) is None]
