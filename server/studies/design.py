"""A study's design and the trial order of one participant.

Modes (``Design.mode``):

- ``reference`` (the default, the thesis design): every condition against the reference condition, for every
  animation.
- ``all-pairs``: every pair of the conditions (the reference among them), for every animation.
- ``incomplete``: each participant sees ``pairs_per_session`` pairs per animation; consecutive participants take
  consecutive slices of one seeded cyclic order of the pairs, so every pair is shown equally often (±1) over
  participants (see ``server.studies.sessions``).
- ``constant-stimuli`` (issue 38): the reference against every level of one ``ladder`` (the design's
  ``conditions``: levels of the ladder listed, or the ladder's id alone for all of them), ``repeats`` times per
  side, as in ``reference`` mode.  The levels come from the clip set (its clips' ``ladder`` and ``level``),
  filled into ``levels`` when the study is created (:func:`server.studies.ladder.resolve`).
- ``staircase`` (issue 38): one QUEST+ staircase per animation over the ladder's levels, ``trials`` trials each,
  interleaved; the level of each trial is chosen on the server from the participant's own answers when the trial
  comes up (``server.participants.staircase``).  Catch trials of both ladder modes show the ladder's most
  detectable level (``detectable_at``) against the reference.
- ``adaptive``: each participant sees the N-1 pairs (N conditions) of a spanning tree chosen from the answers so
  far (ASAP-style batches; ``server.analysis.adaptive``): by default (``aim = "reference"``) the one expected to make
  the values against the reference most precise; with ``aim = "order"`` ASAP's own, the tree of the largest expected
  information gain about the whole scale.

Side balance is by construction in every mode: each comparison a participant sees is shown ``2 * repeats`` times,
``repeats`` times with its first condition (the "reference" of the comparison) on each side.

The order is constructed, never searched for without bound (:func:`arrange`): the session's items are shuffled
as they always were, up to a fixed number of times that depends only on the design's size (every shuffle without
a comparison twice in a row is accepted, exactly as before, so designs the old search could order keep their
orders, seeds included); if none of those shuffles is free of repeats, the last one is repaired by swaps, and a
design too tight for that is laid out by the classic interleaving construction.  No accepted design can fail and
the cost is bounded (see ``bench/design_orders.py``).
"""

from __future__ import annotations

import random
from collections import Counter
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
from itertools import combinations, pairwise
from typing import Annotated, Literal, Self, TypeVar

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, model_validator

from anim_core.methods.conditions import REFERENCE  # the reference condition's id is its method's name
from server.clipset.config import NAME_PATTERN

# Animation names and condition ids, as the clip set names them (a "-" never matches one of its clips).
Ident = Annotated[str, StringConstraints(pattern=NAME_PATTERN)]
# Shuffles tried before the order is repaired: about this many items shuffled in all, at least one shuffle.  The
# thesis design (16 items, 36 % of shuffles without a repeat) keeps the old search's order unless 32 shuffles in
# a row fail (probability 6e-7).
SHUFFLE_BUDGET = 512
# Longest session any design may have (the largest reference design, 16 x 16 comparisons x 2 sides x 5 repeats
# plus catch and practice trials, is 2577).
MAX_TRIALS = 2600
Mode = Literal["reference", "all-pairs", "incomplete", "adaptive", "constant-stimuli", "staircase"]
#: The threshold designs: their conditions are the levels of one ladder.
LADDER_MODES = ("constant-stimuli", "staircase")
Aim = Literal["reference", "order"]
# The thesis design, and the default of every design field.
THESIS_ANIMATIONS = ("walk", "run", "crouch", "idle")
THESIS_CONDITIONS = ("hybrid0", "hybrid1")


class Design(BaseModel):
    """What a study shows: pairs of conditions (by ``mode``), for every animation."""

    model_config = ConfigDict(extra="forbid")

    mode: Mode = Field("reference", description="reference: every condition against the reference; all-pairs: "
                       "every pair of conditions; incomplete: pairs_per_session pairs per participant, every pair "
                       "equally often; adaptive: N-1 pairs per participant chosen from the answers so far")
    reference: Ident = Field(REFERENCE, description="the reference condition every other is compared with "
                             "(reference mode); the anchor (0) of the scale in every mode")
    conditions: list[Ident] = Field(default_factory=lambda: list(THESIS_CONDITIONS), min_length=1, max_length=16,
                                    description="the test conditions, each compared with the reference")
    animations: list[Ident] = Field(default_factory=lambda: list(THESIS_ANIMATIONS), min_length=1, max_length=16)
    repeats: int = Field(1, ge=1, le=5, description="showings of each comparison per side order")
    pairs_per_session: int | None = Field(None, ge=1, le=136, description="incomplete mode: the pairs of "
                                          "conditions each participant sees per animation (default: the number "
                                          "of conditions, the reference included, minus one)")
    aim: Aim | None = Field(None, description="adaptive mode: what the batches are chosen for; reference (the "
                            "default): each condition's value against the reference; order: the whole scale, by "
                            "ASAP's expected information gain (better for ranking the conditions among themselves)")
    practice: Ident | None = Field(None, description="a condition shown once against the reference (first "
                                   "animation) as an unanalysed practice trial before the others")
    catch_trials: int = Field(0, ge=0, le=16, description="attention checks: one animation's reference clip on "
                              "both sides, one per animation in order (ladder modes: the most detectable level "
                              "against the reference)")
    ladder: Ident | None = Field(None, description="constant-stimuli and staircase: the ladder (e.g. pps) whose "
                                 "levels the conditions are")
    trials: int | None = Field(None, ge=4, le=200, description="staircase: trials per staircase (one staircase "
                               "per animation)")
    detectable_at: Literal["low", "high"] = Field("low", description="ladder modes: the end of the ladder easiest "
                                                  "to tell from the reference (low for update rates and bits, "
                                                  "high for an error tolerance)")
    levels: dict[Ident, float] | None = Field(None, description="ladder modes: each condition's level, filled in "
                                              "from the clip set (its clips' ladder and level fields) when the "
                                              "study is created; a study file need not give it, and one that "
                                              "does has it checked against the clip set")

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
        if self.aim is not None and self.mode != "adaptive":
            raise ValueError("aim is for mode = \"adaptive\" only")
        self._check_ladder()
        if self.pairs_per_session is not None:
            if self.mode != "incomplete":
                raise ValueError("pairs_per_session is for mode = \"incomplete\" only")
            if self.pairs_per_session > len(self.pairs()):
                raise ValueError(f"pairs_per_session ({self.pairs_per_session}) exceeds the "
                                 f"{len(self.pairs())} pairs of {len(self.all_conditions())} conditions")
        if self.whole_ladder() and self.mode != "staircase":  # its size is known once the levels are filled in
            return self
        most = 2 * self.repeats  # showings of one comparison; the others must separate them
        if self.mode != "staircase" and most - 1 > self.session_items() - most:
            raise ValueError("this design cannot avoid showing a comparison twice in a row: add conditions, "
                             "animations or catch trials")
        if self.trials_total() > MAX_TRIALS:
            raise ValueError(f"this design has {self.trials_total()} trials per participant, more than "
                             f"{MAX_TRIALS}: use fewer conditions, animations or repeats, or mode = "
                             f"\"incomplete\" or \"adaptive\"")
        return self

    def _check_ladder(self) -> None:
        if self.mode not in LADDER_MODES:
            for name in ("ladder", "trials", "levels"):
                if getattr(self, name) is not None:
                    raise ValueError(f"{name} is for mode = \"constant-stimuli\" or \"staircase\" only")
            return
        if self.ladder is None:
            raise ValueError(f"ladder: mode = {self.mode!r} needs the ladder whose levels it shows (e.g. ladder = "
                             f"\"pps\")")
        if self.mode == "staircase" and self.trials is None:
            raise ValueError("trials: mode = \"staircase\" needs the trials per staircase (e.g. trials = 30)")
        if self.mode != "staircase" and self.trials is not None:
            raise ValueError("trials is for mode = \"staircase\" only")
        if "conditions" not in self.model_fields_set:
            raise ValueError(f"conditions: name the ladder ({self.ladder!r}) for all its levels, or list the "
                             f"levels the design shows")
        if self.ladder in self.conditions and len(self.conditions) > 1:
            raise ValueError(f"conditions: the ladder's id {self.ladder!r} stands for all its levels; give it "
                             f"alone, or list levels without it")
        if self.whole_ladder():
            if self.levels is not None:
                raise ValueError(f"levels: conditions = [{self.ladder!r}] takes every level from the clip set; "
                                 f"drop levels")
            return
        if len(self.conditions) < 3:
            raise ValueError(f"conditions: a {self.mode} design needs at least 3 levels of ladder "
                             f"{self.ladder!r}, got {len(self.conditions)}")
        if self.levels is not None and set(self.levels) != set(self.conditions):
            raise ValueError(f"levels: one level for each condition and for no other (conditions "
                             f"{', '.join(self.conditions)}; levels of {', '.join(self.levels)})")

    def whole_ladder(self) -> bool:
        """Ladder modes: ``conditions`` is the ladder's id alone, all its levels (expanded at creation)."""
        return self.mode in LADDER_MODES and self.ladder is not None and self.conditions == [self.ladder]

    def level_order(self) -> dict[str, float]:
        """Ladder modes: each condition's level (``levels``, from the clip set), ordered from the hardest to tell
        from the reference to the easiest.  ValueError for a design not yet settled against its clip set
        (:func:`server.studies.ladder.resolve`)."""
        if self.levels is None or self.whole_ladder():
            raise ValueError(f"design.levels: the levels of ladder {self.ladder!r} are not known yet; they are "
                             f"filled in from the clip set when the study is created")
        levels = self.levels
        return dict(sorted(levels.items(), key=lambda kv: kv[1], reverse=self.detectable_at == "low"))

    def easiest(self) -> str:
        """Ladder modes: the level easiest to tell from the reference (the catch trials')."""
        return list(self.level_order())[-1]

    def all_conditions(self) -> list[str]:
        """The reference first, then the other conditions."""
        return [self.reference, *self.conditions]

    def pairs(self) -> list[tuple[str, str]]:
        """(first, second) conditions of every comparison the design can show, per animation; the first is the
        comparison's "reference" (scores are from the second's point of view)."""
        if self.mode in ("reference", *LADDER_MODES):
            return [(self.reference, c) for c in self.conditions]
        return list(combinations(self.all_conditions(), 2))

    def pairs_per_animation(self) -> int:
        """The pairs one participant sees per animation."""
        if self.mode == "incomplete":
            return self.pairs_per_session or len(self.all_conditions()) - 1
        if self.mode == "adaptive":
            return len(self.all_conditions()) - 1  # a spanning tree of the conditions
        return len(self.pairs())

    def session_items(self) -> int:
        """Trials of one session apart from the practice trial."""
        if self.mode == "staircase":
            return len(self.animations) * (self.trials or 0) + self.catch_trials
        return len(self.animations) * self.pairs_per_animation() * 2 * self.repeats + self.catch_trials

    def trials_total(self) -> int:
        return self.session_items() + (1 if self.practice else 0)


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


T = TypeVar("T")


def arrange(items: list[T], rng: random.Random, key: Callable[[T], Hashable]) -> list[T]:
    """``items`` in a random order with no two neighbours of equal ``key``, shuffled in place and returned.

    Up to ``SHUFFLE_BUDGET // len(items)`` shuffles are tried and the first without a repeat is kept (the old
    rejection sampler, so its orders are unchanged wherever it succeeded within that budget); otherwise the last
    shuffle is repaired (:func:`_repair`), or, for a multiset too tight for repairs, interleaved
    (:func:`_interleave`).  Raises ``ValueError`` only if no such order exists (a key on more than half the items,
    rounded up)."""
    counts = Counter(key(x) for x in items)
    if counts and max(counts.values()) > (len(items) + 1) // 2:
        raise ValueError("this design cannot avoid showing a comparison twice in a row")
    for _ in range(max(1, SHUFFLE_BUDGET // max(len(items), 1))):
        rng.shuffle(items)
        if all(key(a) != key(b) for a, b in pairwise(items)):
            return items
    if not _repair(items, rng, key):
        items[:] = _interleave(items, rng, key, counts)
    return items


def _repair(items: list[T], rng: random.Random, key: Callable[[T], Hashable]) -> bool:
    """Remove repeats by swaps, left to right: a swap is made only if it creates no new repeat, so the items left
    of the position stay free of repeats.  False if some repeat found no partner (then ``items`` is a
    permutation of the input still)."""
    n = len(items)
    keys = [key(x) for x in items]

    def fits(k: Hashable, at: int) -> bool:
        return (at == 0 or keys[at - 1] != k) and (at == n - 1 or keys[at + 1] != k)

    for i in range(1, n):
        if keys[i] != keys[i - 1]:
            continue
        start = rng.randrange(n)
        for step in range(n):
            j = (start + step) % n
            if abs(j - i) <= 1 or keys[j] == keys[i]:
                continue
            if fits(keys[j], i) and fits(keys[i], j):
                items[i], items[j] = items[j], items[i]
                keys[i], keys[j] = keys[j], keys[i]
                break
        else:
            return False
    return True


def _interleave(items: Sequence[T], rng: random.Random, key: Callable[[T], Hashable],
                counts: Counter) -> list[T]:
    """The classic construction: groups by decreasing size (ties in random order) fill the even positions, then
    the odd ones; no neighbours share a key whenever no key is on more than half the items (rounded up)."""
    groups: dict[Hashable, list[T]] = {}
    for x in items:
        groups.setdefault(key(x), []).append(x)
    order = sorted(groups, key=lambda k: (-counts[k], rng.random()))
    flat = [x for k in order for x in groups[k]]
    out: list[T] = [flat[0]] * len(flat)
    positions = [*range(0, len(flat), 2), *range(1, len(flat), 2)]
    for p, x in zip(positions, flat, strict=True):
        out[p] = x
    return out


def session_items(ids: ComparisonIds, repeats: int) -> list[PlannedTrial]:
    """The trials of a session before ordering: every test comparison ``repeats`` times per side, the catch
    trials (a catch trial shows one clip on both sides; the reference is said to be right, as it always was)."""
    items = [PlannedTrial(c, side) for c in ids.test for side in ("right", "left") for _ in range(repeats)]
    return items + [PlannedTrial(c, "right") for c in ids.catch]


def trial_order(ids: ComparisonIds, repeats: int, seed: int) -> list[PlannedTrial]:
    """The trials of one session: the practice trial first, then tests and catch trials in an order with no
    comparison twice in a row (:func:`arrange`)."""
    rng = random.Random(seed)
    items = arrange(session_items(ids, repeats), rng, key=lambda t: t.comparison_id)
    head = [PlannedTrial(ids.practice, rng.choice(("right", "left")), practice=True)] if ids.practice else []
    return head + items
