"""A study's design and the trial order of one participant.

Side balance is by construction: every test comparison is shown ``2 * repeats`` times, ``repeats`` times with the
hybrid on each side.  The order is a uniformly random permutation (seeded per participant) among those with no
comparison twice in a row, drawn by rejection: every valid order is equally likely, so every comparison is equally
likely at every position.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from itertools import pairwise

from pydantic import BaseModel, Field

MAX_SHUFFLES = 10_000


class Design(BaseModel):
    """What a study shows.  The thesis default: increments 0 and 1 against keyframe, each once per side."""

    animations: list[str] = Field(default_factory=lambda: ["walk", "run", "crouch", "idle"], min_length=1)
    increments: list[int] = Field(default_factory=lambda: [0, 1], min_length=1)
    repeats: int = Field(default=1, ge=1, le=5)
    practice: bool = False
    practice_increment: int = 2  # the practice trial: keyframe against this increment of the first animation
    catch_trials: int = Field(default=0, ge=0, le=8)  # each shows one animation's keyframe clip on both sides


@dataclass(frozen=True)
class PlannedTrial:
    comparison_id: int
    hybrid_side: str
    practice: bool = False


@dataclass(frozen=True)
class ComparisonIds:
    """The comparison ids a session draws from (test, catch and practice comparisons of the study)."""

    test: list[int]
    catch: list[int] = field(default_factory=list)
    practice: int | None = None


def trial_order(ids: ComparisonIds, repeats: int, seed: int) -> list[PlannedTrial]:
    """The trials of one session: the practice trial first, then tests and catch trials, shuffled."""
    rng = random.Random(seed)
    items = [PlannedTrial(c, side) for c in ids.test for side in ("left", "right") for _ in range(repeats)]
    items += [PlannedTrial(c, "left") for c in ids.catch]
    for _ in range(MAX_SHUFFLES):
        rng.shuffle(items)
        if all(a.comparison_id != b.comparison_id for a, b in pairwise(items)):
            break
    else:  # only a design with one comparison repeated cannot avoid repeats; say so rather than loop forever
        raise ValueError("this design cannot avoid showing a comparison twice in a row")
    head = [PlannedTrial(ids.practice, rng.choice(("left", "right")), practice=True)] if ids.practice else []
    return head + items
