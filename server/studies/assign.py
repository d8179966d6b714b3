"""Which comparisons a new session shows, by the study's design mode (``design.Design.mode``).

``reference`` and ``all-pairs``: every test comparison of the study.  ``incomplete``: a slice of
``pairs_per_session`` pairs per animation from a fixed cyclic order of the pairs, the slice moving on by that many
with every session, so over sessions every pair is shown equally often (±1).  ``adaptive``: per animation, the
N-1 pairs :func:`server.studies.adaptive.next_batch` picks from the votes answered before the session started
(the vote log) and the session's seed.  Catch and practice comparisons are the same in every mode.

The choices are pure functions of what is stored (the session's seed, its position among the study's sessions,
the votes and when they were answered), so :func:`session_batches` recomputes every adaptive round afterwards.
"""

from __future__ import annotations

import random
from collections import defaultdict
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import func, select
from sqlalchemy.orm import Session, aliased

from server.participants.models import ParticipantSession, Trial, Vote

from .adaptive import Batch, next_batch, posterior
from .design import ComparisonIds, Design
from .models import Comparison, ComparisonKind, Stimulus, Study
from .ranking import GradedComparison

PairKey = tuple[str, str, str]  # (animation, first condition, second condition)


def pair_comparisons(study: Study) -> dict[PairKey, int]:
    """(animation, first condition, second condition) -> comparison id of every test comparison of ``study``."""
    return {(c.reference.animation, c.reference.condition, c.test.condition): c.id for c in study.comparisons
            if c.kind == ComparisonKind.test}


def _other_ids(study: Study) -> tuple[list[int], int | None]:
    catch = [c.id for c in study.comparisons if c.kind == ComparisonKind.catch]
    practice = [c.id for c in study.comparisons if c.kind == ComparisonKind.practice]
    return catch, practice[0] if practice else None


def incomplete_pairs(design: Design, slug: str, position: int) -> list[PairKey]:
    """The pairs of the ``position``-th session (0-based) of an incomplete design: per animation a slice of
    ``pairs_per_animation()`` pairs of a cyclic order of all pairs (seeded by the study's slug and the animation,
    so animations do not share one pattern)."""
    pairs, k = design.pairs(), design.pairs_per_animation()
    out = []
    for animation in design.animations:
        order = list(pairs)
        random.Random(f"{slug}/{animation}").shuffle(order)
        out += [(animation, *order[(position * k + j) % len(order)]) for j in range(k)]
    return out


def study_votes(session: Session, study: Study, before: datetime | None = None
                ) -> dict[str, list[GradedComparison]]:
    """The test votes of ``study`` per animation (practice excluded), optionally only those answered before
    ``before``."""
    reference, test = aliased(Stimulus), aliased(Stimulus)
    query = (select(Trial.session_id, reference.animation, reference.condition, test.condition, Vote.score)
             .join(Trial, Vote.trial_id == Trial.id).join(Comparison, Trial.comparison_id == Comparison.id)
             .join(reference, Comparison.reference_id == reference.id).join(test, Comparison.test_id == test.id)
             .where(Comparison.study_id == study.id, Comparison.kind == ComparisonKind.test,
                    Trial.practice.is_(False)).order_by(Vote.id))
    if before is not None:
        query = query.where(Vote.answered_at < before)
    out: dict[str, list[GradedComparison]] = defaultdict(list)
    for sid, animation, ref, tst, score in session.execute(query):
        out[animation].append(GradedComparison(sid, ref, tst, score))
    return out


def adaptive_batches(design: Design, votes: dict[str, list[GradedComparison]], seed: int) -> dict[str, Batch]:
    """Per animation, the batch of pairs (indices into ``design.all_conditions()``) for a session with ``seed``."""
    conditions = design.all_conditions()
    return {a: next_batch(posterior(votes.get(a, []), conditions), seed + i, 2 * design.repeats)
            for i, a in enumerate(design.animations)}


def session_comparisons(session: Session, study: Study, seed: int, started_at: datetime) -> ComparisonIds:
    """The comparisons a new session of ``study`` (to be stored with ``seed`` and ``created_at = started_at``)
    draws its trials from."""
    design = Design.model_validate(study.design)
    catch, practice = _other_ids(study)
    ids = pair_comparisons(study)
    if design.mode == "incomplete":
        position = session.scalar(select(func.count()).select_from(ParticipantSession).where(
            ParticipantSession.study_id == study.id)) or 0
        chosen = [ids[p] for p in incomplete_pairs(design, study.slug, position)]
    elif design.mode == "adaptive":
        conditions = design.all_conditions()
        batches = adaptive_batches(design, study_votes(session, study, before=started_at), seed)
        chosen = [ids[(a, conditions[i], conditions[j])] for a, b in batches.items() for i, j in b.pairs]
    else:
        chosen = list(ids.values())
    return ComparisonIds(sorted(chosen), catch, practice)


@dataclass(frozen=True)
class Round:
    """One adaptive session as it was chosen: when, the votes it saw, the information its pairs promised."""

    session_id: str
    started_at: datetime
    votes_before: int
    information: dict[str, float]  # per animation, nats (sum over the batch's pairs)
    pairs: dict[str, list[tuple[str, str]]]


def session_batches(session: Session, study: Study) -> list[Round]:
    """Every session of an adaptive study, in order, with the batch recomputed from the vote log and its seed
    (withdrawn sessions' votes are gone, so rounds after a withdrawal may differ from what was shown)."""
    design = Design.model_validate(study.design)
    conditions = design.all_conditions()
    rounds = []
    for ps in session.scalars(select(ParticipantSession).where(ParticipantSession.study_id == study.id)
                              .order_by(ParticipantSession.created_at, ParticipantSession.id)):
        votes = study_votes(session, study, before=ps.created_at)
        batches = adaptive_batches(design, votes, ps.seed)
        rounds.append(Round(ps.id, ps.created_at, sum(len(v) for v in votes.values()),
                            {a: b.information for a, b in batches.items()},
                            {a: [(conditions[i], conditions[j]) for i, j in b.pairs] for a, b in batches.items()}))
    return rounds
