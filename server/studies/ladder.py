"""A threshold design's ladder levels, from the clip set (issue 38).

A clip-set ``[[ladders]]`` entry expands into one condition per level, and each carries its ``ladder`` and
``level``: the conditions of a :class:`~server.clipset.config.ClipSetConfig` and the entries of its clip manifest
(:class:`~server.clipset.manifest.ClipEntry`).  Those fields are the only source of a level; a condition's id is
never read for one.  When a study is created (and when its design changes) :func:`resolve` settles the design
against them: a ``conditions`` naming the ladder's id alone stands for all its levels, every condition (and the
practice condition) must be a level of the design's ladder by the clip set's fields, and the levels are stored
with the design (``Design.levels``), where the staircase, the exports and the results read them.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from pydantic import ValidationError

from server.errors import Unprocessable

from .design import LADDER_MODES, Design

#: condition id -> (ladder, level) as the clip set gives them ((None, None): a condition on no ladder)
LadderFields = Mapping[str, tuple[str | None, float | None]]


def ladder_fields(conditions: Iterable[Any]) -> dict[str, tuple[str | None, float | None]]:
    """condition id -> (ladder, level) of clip-set conditions (:class:`~anim_core.methods.conditions.Condition`,
    field ``id``) or clip-manifest entries (field ``condition``; one condition of several animations is one
    entry here)."""
    out: dict[str, tuple[str | None, float | None]] = {}
    for c in conditions:
        cid = getattr(c, "condition", None) or c.id
        level = getattr(c, "level", None)
        out.setdefault(cid, (getattr(c, "ladder", None), None if level is None else float(level)))
    return out


def _where(condition: str, fields: LadderFields) -> str:
    if condition not in fields:
        return f"{condition} (not in the clip set)"
    ladder, level = fields[condition]
    return f"{condition} (on no ladder)" if ladder is None else f"{condition} (level {level:g} of ladder {ladder!r})"


def resolve(design: Design, fields: LadderFields) -> Design:
    """``design`` settled against the clip set's ``fields`` (module docstring): for a threshold design, its
    ``conditions`` (the ladder's id expanded into every level, lowest first) and ``levels`` from the clip set;
    422 naming the field and the condition if one is no level of the design's ladder, if given ``levels``
    disagree with the clip set's, or if the expanded design breaks a design rule.  Other designs unchanged."""
    if design.mode not in LADDER_MODES or design.ladder is None:
        return design
    ladder = design.ladder
    on = {c: level for c, (name, level) in fields.items() if name == ladder and level is not None}
    if design.conditions == [ladder]:
        if not on:
            ladders = sorted({name for name, _ in fields.values() if name is not None})
            raise Unprocessable(f"design.conditions: {ladder!r} names ladder {ladder!r}, which the clip set does "
                                f"not have (its ladders: {', '.join(ladders) or 'none'})")
        conditions = sorted(on, key=lambda c: on[c])
    else:
        conditions = list(design.conditions)
    if outside := [c for c in conditions if c not in on]:
        raise Unprocessable(f"design.conditions: {', '.join(_where(c, fields) for c in outside)} not a level of "
                            f"ladder {ladder!r} by the clip set's manifest: a {design.mode} design runs over the "
                            f"levels of one ladder")
    if design.practice is not None and design.practice not in on:
        raise Unprocessable(f"design.practice: {_where(design.practice, fields)} is not a level of ladder "
                            f"{ladder!r} by the clip set's manifest")
    levels = {c: on[c] for c in conditions}
    if design.levels is not None:
        if wrong := [c for c in conditions if design.levels.get(c) != levels[c]]:
            shown = ", ".join(f"{c} is {design.levels.get(c)!r} in the design, {levels[c]:g} in the clip set"
                              for c in wrong)
            raise Unprocessable(f"design.levels: {shown}; drop levels (they are filled in from the clip set)")
    try:
        return Design.model_validate({**design.model_dump(), "conditions": conditions, "levels": levels})
    except ValidationError as exc:
        raise Unprocessable("design: " + "; ".join(e["msg"].removeprefix("Value error, ") for e in exc.errors())
                            ) from None
