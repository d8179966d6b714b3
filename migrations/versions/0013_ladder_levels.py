"""Threshold designs store their levels (issue 38).  A study of ``mode = "constant-stimuli"`` or ``"staircase"``
now keeps each condition's level in ``design.levels``, filled in from the clip set's ``ladder``/``level`` fields
when the study is created (``server.studies.ladder``); before, the levels were read from the condition ids
(``<ladder><level>``, ``_`` for a decimal point) wherever they were needed.  A threshold study stored before this
migration gets its levels here: from the server's clip manifest where it has the condition on the design's ladder,
else from the id exactly as the code before it read them (so its staircase, exports and results are what they
were).  A condition that is neither leaves the study without ``levels`` (it then refuses to run, saying so,
rather than guess).  Going back removes ``levels`` (the earlier code refused unknown design fields)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from alembic import context, op

revision = "0013"
down_revision = "0012"
branch_labels = None
depends_on = None

LADDER_MODES = ("constant-stimuli", "staircase")
STUDIES = sa.table("studies", sa.column("id", sa.Integer), sa.column("design", sa.JSON))


def _manifest_levels(clips_dir: Path | None) -> dict[tuple[str, str], float]:
    """(ladder, condition) -> level of the server's clip manifest (nothing if it has none or cannot be read)."""
    if clips_dir is None:
        return {}
    try:
        manifest = json.loads((Path(clips_dir) / "manifest.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    out = {}
    for clip in manifest.get("clips", []) if isinstance(manifest, dict) else []:
        if isinstance(clip, dict) and isinstance(clip.get("ladder"), str) and isinstance(clip.get("level"),
                                                                                          int | float):
            out[(clip["ladder"], str(clip.get("condition")))] = float(clip["level"])
    return out


def _from_name(condition: str, ladder: str) -> float | None:
    """The level the code before this migration read from a condition id (``pps12`` -> 12, ``eps0_5`` -> 0.5)."""
    match = re.fullmatch(re.escape(ladder) + r"(?P<level>[0-9]+(?:_[0-9]+)?)", condition)
    return None if match is None else float(match.group("level").replace("_", "."))


def _levels(design: dict[str, Any], known: dict[tuple[str, str], float]) -> dict[str, float] | None:
    ladder, conditions = design.get("ladder"), design.get("conditions")
    if not isinstance(ladder, str) or not isinstance(conditions, list):
        return None
    levels = {}
    for c in conditions:
        level = known.get((ladder, str(c)), _from_name(str(c), ladder))
        if level is None:
            return None
        levels[str(c)] = level
    return levels


def upgrade() -> None:
    known = _manifest_levels(context.config.attributes.get("clips_dir"))
    bind = op.get_bind()
    for sid, design in bind.execute(sa.select(STUDIES.c.id, STUDIES.c.design)).all():
        if not isinstance(design, dict) or design.get("mode") not in LADDER_MODES or design.get("levels"):
            continue
        levels = _levels(design, known)
        if levels is not None:
            bind.execute(STUDIES.update().where(STUDIES.c.id == sid).values(design={**design, "levels": levels}))


def downgrade() -> None:
    bind = op.get_bind()
    for sid, design in bind.execute(sa.select(STUDIES.c.id, STUDIES.c.design)).all():
        if isinstance(design, dict) and "levels" in design:
            bind.execute(STUDIES.update().where(STUDIES.c.id == sid).values(
                design={k: v for k, v in design.items() if k != "levels"}))
