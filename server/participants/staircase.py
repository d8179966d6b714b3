"""Staircase sessions (``[design] mode = "staircase"``, issue 38): one QUEST+ staircase per animation over the
levels of the design's ladder, interleaved, with a fixed trial budget.

A session's trials are all stored when it starts (so ``trials_total`` and the order of animations, sides, catch
and practice trials are fixed by the seed), each staircase trial first showing the level QUEST+ chooses with no
answers.  When a trial is answered, the next trial's level is chosen from this participant's own answers to that
animation's earlier trials (:func:`advance`) and stored as the trial's comparison; the page learns it only with
that trial (no preload of an undecided trial: ``router.trial_read``).  The choice is a pure function of the
design and the answers (QUEST+ with the minimum-entropy rule is deterministic), so :func:`replay` recomputes every
level from the vote log.

The psychometric model (:mod:`server.analysis.quest`: QUEST+'s cumulative normal): intensity is the level on a
log scale (linear if a level is not positive), signed so that it grows towards the ladder's easily detected end;
the probability of telling the test from the reference has the guess rate of the format as its floor (0.5 for
2AFC; a grid of false-alarm rates for same/different) and a small lapse rate.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, aliased

from server.analysis import quest
from server.studies.design import ComparisonIds, Design, PlannedTrial, arrange
from server.studies.models import Comparison, ComparisonKind, Stimulus
from server.studies.scale import detected

from .models import ParticipantSession, Trial, Vote

FALSE_ALARMS = (0.0, 0.1, 0.2)  # same/different: "different" said of identical clips


def intensities(design: Design) -> dict[str, float]:
    """Each level's intensity for QUEST+ (growing with detectability), hardest level first."""
    levels = design.level_order()
    logged = all(v > 0 for v in levels.values())
    sign = -1.0 if design.detectable_at == "low" else 1.0
    return {c: sign * (math.log10(v) if logged else v) for c, v in levels.items()}


@lru_cache(maxsize=64)
def _model(xs: tuple[float, ...], answer_format: str) -> tuple[quest.Grid, np.ndarray]:
    """The QUEST+ grid over the intensities ``xs`` and its P(detected) per intensity and parameter (read-only)."""
    grid = quest.Grid(xs, (0.5,) if answer_format == "2afc" else FALSE_ALARMS)
    detection = grid.detection()
    detection.flags.writeable = False
    return grid, detection


def _posterior(design: Design, answer_format: str, history: Iterable[tuple[str, bool]]
               ) -> tuple[list[str], quest.Grid, np.ndarray, np.ndarray]:
    """The levels (condition ids, in intensity order), the grid, P(detected) and the posterior after ``history``:
    (condition shown, detected) of one animation's staircase trials so far, in order.  The whole history is
    replayed each time (microseconds a trial)."""
    levels = intensities(design)
    conditions = list(levels)
    index = {c: i for i, c in enumerate(conditions)}
    grid, detection = _model(tuple(levels.values()), answer_format)
    return conditions, grid, detection, quest.posterior(detection, [(index[c], bool(d)) for c, d in history])


def next_condition(design: Design, answer_format: str, history: Iterable[tuple[str, bool]]) -> str:
    """The level (condition id) QUEST+ chooses after ``history`` (as :func:`_posterior`)."""
    conditions, _, detection, post = _posterior(design, answer_format, history)
    return conditions[quest.next_index(detection, post)]


@dataclass(frozen=True)
class StaircaseSlot(PlannedTrial):
    animation: str = ""


def plan(design: Design, ids: ComparisonIds, comparisons: dict[tuple[str, str], int], answer_format: str,
         seed: int) -> list[PlannedTrial]:
    """The trials of a new staircase session: per animation ``trials`` slots (sides balanced: half each, the odd
    one drawn), each at the level QUEST+ chooses first, and the catch trials, in a seeded order with no
    animation's staircase twice in a row where the design allows it; the practice trial first."""
    rng = random.Random(seed)
    first = next_condition(design, answer_format, [])
    trials = design.trials or 0
    items: list[PlannedTrial] = []
    for animation in design.animations:
        sides = ["left", "right"] * (trials // 2) + ([rng.choice(("left", "right"))] if trials % 2 else [])
        rng.shuffle(sides)
        items += [StaircaseSlot(comparisons[(animation, first)], side, animation=animation) for side in sides]
    items += [PlannedTrial(c, "right") for c in ids.catch]  # a catch trial's sides are drawn below
    try:
        arrange(items, rng, key=lambda t: t.animation if isinstance(t, StaircaseSlot) else t.comparison_id)
    except ValueError:  # one animation: its staircase cannot be interleaved with another
        rng.shuffle(items)
    items = [t if isinstance(t, StaircaseSlot) else PlannedTrial(t.comparison_id, rng.choice(("left", "right")))
             for t in items]
    head = [PlannedTrial(ids.practice, rng.choice(("right", "left")), practice=True)] if ids.practice else []
    return head + items


_REF, _TEST = aliased(Stimulus), aliased(Stimulus)


def _history(session: Session, ps: ParticipantSession, animation: str, answer_format: str
             ) -> list[tuple[str, bool]]:
    """(condition, detected) of the session's answered staircase trials of ``animation``, in trial order."""
    rows = session.execute(
        select(_TEST.condition, Vote.choice, Trial.reference_side).select_from(Vote)
        .join(Trial, Vote.trial_id == Trial.id).join(Comparison, Trial.comparison_id == Comparison.id)
        .join(_REF, Comparison.reference_id == _REF.id).join(_TEST, Comparison.test_id == _TEST.id)
        .where(Vote.session_id == ps.id, Comparison.kind == ComparisonKind.test, Trial.practice.is_(False),
               _REF.animation == animation).order_by(Trial.index))
    return [(condition, detected(answer_format, choice, side)) for condition, choice, side in rows]


def advance(session: Session, ps: ParticipantSession, answered: Trial) -> None:
    """After ``answered`` got its vote (in the same transaction): choose and store the level of the session's
    next trial if it is a staircase trial.  Nothing for other designs, the last trial, practice and catch
    trials."""
    design = Design.model_validate(ps.study.design)
    if design.mode != "staircase":
        return
    nxt = session.scalar(select(Trial).where(Trial.session_id == ps.id, Trial.index == answered.index + 1))
    if nxt is None or nxt.practice or nxt.comparison.kind != ComparisonKind.test:
        return
    animation = nxt.comparison.reference.animation
    answer_format = (ps.study.scale or {}).get("format", "2afc")
    condition = next_condition(design, answer_format, _history(session, ps, animation, answer_format))
    chosen = session.scalar(
        select(Comparison).join(_REF, Comparison.reference_id == _REF.id).join(_TEST, Comparison.test_id == _TEST.id)
        .where(Comparison.study_id == ps.study_id, Comparison.kind == ComparisonKind.test,
               _REF.animation == animation, _TEST.condition == condition))
    if chosen is not None and chosen.id != nxt.comparison_id:
        nxt.comparison = chosen
        session.flush()


def undecided(ps: ParticipantSession, trial: Trial) -> bool:
    """Whether ``trial`` is a staircase trial whose level is chosen only once the trial before it is answered
    (the page must not be told it early, e.g. by a preload)."""
    return (ps.study.design.get("mode") == "staircase" and not trial.practice
            and trial.comparison.kind == ComparisonKind.test)


def replay(design: Design, answer_format: str,
           trials: Sequence[tuple[str | None, str, str | None, str]]) -> list[str | None]:
    """The level each staircase trial of a session must show, recomputed from its answers alone: ``trials`` is
    the session in order as (animation of a staircase trial or None, condition shown, choice or None,
    reference side).  What :func:`advance` stored, if the server did its job."""
    history: dict[str, list[tuple[str, bool]]] = {}
    out: list[str | None] = []
    for animation, shown, choice, side in trials:
        if animation is None:
            out.append(None)
            continue
        out.append(next_condition(design, answer_format, history.get(animation, [])))
        if choice is not None:
            history.setdefault(animation, []).append((shown, detected(answer_format, choice, side)))
    return out


def estimate(design: Design, answer_format: str, history: Iterable[tuple[str, bool]]) -> dict[str, float]:
    """The posterior mean of the staircase's parameters after ``history``, the threshold (``mean``) and spread
    (``sd``) also as a ladder level (``threshold_level``: the level at the midpoint between guess rate and 1)."""
    _, grid, _, post = _posterior(design, answer_format, history)
    params = grid.mean(post)
    logged = all(v > 0 for v in design.level_order().values())
    x = params["mean"] * (-1.0 if design.detectable_at == "low" else 1.0)
    params["threshold_level"] = 10**x if logged else x
    return params


def simulate(design: Design, answer_format: str, detect: Callable[[float], float], rng: random.Random
             ) -> list[tuple[str, bool]]:
    """One simulated staircase of ``design.trials`` trials: a planted observer who detects a level with
    probability ``detect(level)`` (a 2AFC guess adds half the rest); (condition, detected) per trial."""
    levels = design.level_order()
    history: list[tuple[str, bool]] = []
    for _ in range(design.trials or 0):
        condition = next_condition(design, answer_format, history)
        p = detect(levels[condition])
        if answer_format == "2afc":
            p += (1 - p) / 2
        history.append((condition, rng.random() < p))
    return history
