"""A study's design and the trial order of one participant.

A design compares conditions (ids of the clip set, e.g. ``hybrid0``) with a reference condition (``keyframe``)
for each of its animations.  Side balance is by construction: every test comparison is shown ``2 * repeats``
times, ``repeats`` times with the reference on each side.  The order is a uniformly random permutation (seeded per
participant) among those with no comparison twice in a row, drawn by rejection: every valid order is equally
likely, so every comparison is equally likely at every position.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Annotated, Self

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, model_validator

from anim_core.methods.conditions import REFERENCE  # the reference condition's id is its method's name
from server.clipset.config import NAME_PATTERN

MAX_SHUFFLES = 10_000
# Animation names and condition ids, as the clip set names them (a "-" never matches one of its clips).
Ident = Annotated[str, StringConstraints(pattern=NAME_PATTERN)]
# The thesis design, and the default of every design field.
THESIS_ANIMATIONS = ("walk", "run", "crouch", "idle")
THESIS_CONDITIONS = ("hybrid0", "hybrid1")


class Design(BaseModel):
    """What a study shows: every condition against the reference, for every animation."""

    model_config = ConfigDict(extra="forbid")

    reference: Ident = Field(REFERENCE, description="the reference condition every other is compared with")
    conditions: list[Ident] = Field(default_factory=lambda: list(THESIS_CONDITIONS), min_length=1, max_length=16,
                                    description="the test conditions, each compared with the reference")
    animations: list[Ident] = Field(default_factory=lambda: list(THESIS_ANIMATIONS), min_length=1, max_length=16)
    repeats: int = Field(1, ge=1, le=5, description="showings of each comparison per side order")
    practice: Ident | None = Field(None, description="a condition shown once against the reference (first "
                                   "animation) as an unanalysed practice trial before the others")
    catch_trials: int = Field(0, ge=0, le=16, description="attention checks: one animation's reference clip on "
                              "both sides, one per animation in order")

    @model_validator(mode="after")
    def consistent(self) -> Self:
        for name in ("conditions", "animations"):
            values = getattr(self, name)
            repeated = sorted({v for v in values if values.count(v) > 1})
            if repeated:
                raise ValueError(f"{name} lists {', '.join(repeated)} more than once")
        if self.reference in self.conditions:
            raise ValueError(f"the reference {self.reference!r} cannot also be a compared condition")
        if self.catch_trials > len(self.animations):
            raise ValueError(f"catch_trials ({self.catch_trials}) cannot exceed the number of animations "
                             f"({len(self.animations)}): each uses a different animation")
        if self.practice == self.reference:
            raise ValueError("the practice condition must differ from the reference")
        tests = len(self.animations) * len(self.conditions)
        most = 2 * self.repeats  # showings of one test comparison; the others must separate them
        if most - 1 > tests * most + self.catch_trials - most:
            raise ValueError("this design cannot avoid showing a comparison twice in a row: add conditions, "
                             "animations or catch trials")
        return self

    def trials_total(self) -> int:
        return (len(self.animations) * len(self.conditions) * 2 * self.repeats + self.catch_trials
                + (1 if self.practice else 0))


@dataclass(frozen=True)
class PlannedTrial:
    comparison_id: int
    reference_side: str
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
    items = [PlannedTrial(c, side) for c in ids.test for side in ("right", "left") for _ in range(repeats)]
    # A catch trial shows one clip on both sides; the reference is said to be right, as it always was.
    items += [PlannedTrial(c, "right") for c in ids.catch]
    for _ in range(MAX_SHUFFLES):
        rng.shuffle(items)
        if all(a.comparison_id != b.comparison_id for a, b in pairwise(items)):
            break
    else:  # Design refuses designs that cannot avoid repeats; say so rather than loop forever
        raise ValueError("this design cannot avoid showing a comparison twice in a row")
    head = [PlannedTrial(ids.practice, rng.choice(("right", "left")), practice=True)] if ids.practice else []
    return head + items
