"""Which comparisons a new session shows (:mod:`server.studies.assign` chooses the pairs by the design's mode).

The choices are pure functions of what is stored (the session's seed, its position among the study's sessions,
the votes and when they were answered).  :func:`session_batches` shows every adaptive round afterwards with the
pairs its session was given (its stored trials) and the information they promised given the votes before it.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session, aliased

from server.studies.adaptive import information_gain, posterior
from server.studies.assign import adaptive_batches, incomplete_pairs, pair_comparisons
from server.studies.design import ComparisonIds, Design
from server.studies.models import Comparison, ComparisonKind, Stimulus, Study
from server.studies.ranking import GradedComparison
from server.studies.service import comparison_ids

from .models import ParticipantSession, Trial, Vote


def sessions_started(session: Session, study: Study) -> int:
    """How many sessions of ``study`` were ever created (withdrawn ones included: their rows stay)."""
    return session.scalar(select(func.count()).select_from(ParticipantSession).where(
        ParticipantSession.study_id == study.id)) or 0


def _test_trials(study: Study, *columns: Any) -> Select:
    """(session id, animation, first condition, second condition, *columns) of every test trial of ``study``
    (practice and catch trials excluded)."""
    reference, test = aliased(Stimulus), aliased(Stimulus)
    return (select(Trial.session_id, reference.animation, reference.condition, test.condition, *columns)
            .select_from(Trial).join(Comparison, Trial.comparison_id == Comparison.id)
            .join(reference, Comparison.reference_id == reference.id).join(test, Comparison.test_id == test.id)
            .where(Comparison.study_id == study.id, Comparison.kind == ComparisonKind.test,
                   Trial.practice.is_(False)))


def study_votes(session: Session, study: Study, before: datetime | None = None
                ) -> dict[str, list[GradedComparison]]:
    """The test votes of ``study`` per animation (practice excluded), optionally only those answered before
    ``before``."""
    query = _test_trials(study, Vote.score).join(Vote, Vote.trial_id == Trial.id).order_by(Vote.id)
    if before is not None:
        query = query.where(Vote.answered_at < before)
    out: dict[str, list[GradedComparison]] = defaultdict(list)
    for sid, animation, ref, tst, score in session.execute(query):
        out[animation].append(GradedComparison(sid, ref, tst, score))
    return out


def session_comparisons(session: Session, study: Study, seed: int, started_at: datetime) -> ComparisonIds:
    """The comparisons a new session of ``study`` (to be stored with ``seed`` and ``created_at = started_at``)
    draws its trials from."""
    design = Design.model_validate(study.design)
    every = comparison_ids(study)  # catch and practice comparisons are the same in every mode
    ids = pair_comparisons(study)
    if design.mode == "incomplete":
        position = sessions_started(session, study)
        chosen = [ids[p] for p in incomplete_pairs(design, study.slug, position)]
    elif design.mode == "adaptive":
        conditions = design.all_conditions()
        batches = adaptive_batches(design, study_votes(session, study, before=started_at), seed)
        chosen = [ids[(a, conditions[i], conditions[j])] for a, b in batches.items() for i, j in b.pairs]
    else:
        chosen = list(ids.values())
    return ComparisonIds(sorted(chosen), every.catch, every.practice)


@dataclass(frozen=True)
class Round:
    """One adaptive session as it was chosen: when, the votes it saw, the information its pairs promised."""

    session_id: str
    started_at: datetime
    votes_before: int
    information: dict[str, float]  # per animation, nats (sum over the batch's pairs)
    pairs: dict[str, list[tuple[str, str]]]


def session_batches(session: Session, study: Study) -> list[Round]:
    """Every session of an adaptive study, in order: the pairs it was given (from its trials, which stay when a
    participant withdraws) and their expected information gain given the votes stored before it started (a
    withdrawal deletes votes, so a round after one can show less information than it promised then)."""
    design = Design.model_validate(study.design)
    conditions = design.all_conditions()
    index = {c: i for i, c in enumerate(conditions)}
    given: dict[str, dict[str, set[tuple[str, str]]]] = defaultdict(lambda: defaultdict(set))
    for sid, animation, ref, tst in session.execute(_test_trials(study)):
        given[sid][animation].add(tuple(sorted((ref, tst), key=index.__getitem__)))
    rounds = []
    for ps in session.scalars(select(ParticipantSession).where(ParticipantSession.study_id == study.id)
                              .order_by(ParticipantSession.created_at, ParticipantSession.id)):
        votes = study_votes(session, study, before=ps.created_at)
        pairs = {a: sorted(given[ps.id][a], key=lambda p: (index[p[0]], index[p[1]])) for a in design.animations}
        information = {}
        for a, shown in pairs.items():
            post = posterior(votes.get(a, []), conditions)
            information[a] = float(sum(information_gain(post, index[x], index[y]) for x, y in shown))
        rounds.append(Round(ps.id, ps.created_at, sum(len(v) for v in votes.values()), information, pairs))
    return rounds
