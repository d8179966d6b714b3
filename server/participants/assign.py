"""Which comparisons a new session shows (:mod:`server.studies.assign` chooses the pairs by the design's mode,
:func:`server.analysis.adaptive.adaptive_batches` an adaptive design's).

The choices are pure functions of what is stored (the session's seed, its position among the study's sessions,
the votes the results count and when they were answered).  :func:`session_batches` shows every adaptive round
afterwards with the pairs its session was given (its stored trials) and the information they promised given the
votes before it.
"""

from __future__ import annotations

import threading
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np
from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session, aliased

from server.analysis.adaptive import adaptive_batches, counts_posterior, information_gain, vote_counts
from server.analysis.ranking import GradedComparison
from server.analysis.statistics import counted
from server.studies.assign import incomplete_pairs, pair_comparisons
from server.studies.design import ComparisonIds, Design
from server.studies.models import Comparison, ComparisonKind, Stimulus, Study
from server.studies.service import comparison_ids

from .models import ParticipantSession, SessionState, Trial, Vote

_REFERENCE, _TEST = aliased(Stimulus), aliased(Stimulus)  # a comparison's two stimuli


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


@dataclass
class _Finished:
    """The export rows of a study's finished sessions, which no longer change, and its comparisons' playback."""

    rows: dict[str, list[dict[str, Any]]] = field(default_factory=dict)  # session id -> its rows
    playback: dict[tuple[str, str, str], float] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)


# At most this many newly finished sessions are read by name; more (a new server process's first read) are read
# with all the others, as a statement has room for only so many parameters.
NAMED_SESSIONS = 500
# (study id, slug, creation time) -> its finished sessions' rows, for the last few studies: not the id alone, which
# SQLite can give a new study after a deletion
_FINISHED: dict[tuple[int, str, datetime], _Finished] = {}


def screened_out(session: Session, study: Study) -> frozenset[str]:
    """The sessions of ``study`` its screening rules leave out of the results (pilot sessions not screened with
    them, as in the results): the results' own screening (:func:`server.participants.rows.screen_rows`) of the
    finished sessions.

    The rules look only at finished sessions (``screening.screen``), whose votes no longer change (a withdrawal
    deletes them and the session is no longer finished), so their export rows are remembered and only the
    sessions finished since are read; the rows kept are those of the sessions the database says are finished, so
    the answer is the same on every server instance sharing it.  Screening itself runs each time: the panel rules
    compare every finished participant with all the others."""
    # Imported here: the rows read the votes through participants.service, which assigns a new session's
    # comparisons through this module.
    from .rows import screen_rows, vote_rows

    finished = set(session.scalars(select(ParticipantSession.id).where(
        ParticipantSession.study_id == study.id, ParticipantSession.state == SessionState.completed,
        ParticipantSession.pilot.is_(False))).all())
    key = (study.id, study.slug, study.created_at)
    if key not in _FINISHED and len(_FINISHED) >= 8:
        _FINISHED.pop(next(iter(_FINISHED)))
    cache = _FINISHED.setdefault(key, _Finished())
    with cache.lock:
        for gone in set(cache.rows) - finished:  # withdrawn
            del cache.rows[gone]
        new = finished - set(cache.rows)
        if new:
            rows, playback = vote_rows(session, study, sessions=new if len(new) <= NAMED_SESSIONS else None)
            cache.rows.update({sid: [] for sid in new})
            for row in rows:  # a session withdrawn since the first read has no rows left
                if row["session_id"] in new and row["session_state"] == SessionState.completed:
                    cache.rows[row["session_id"]].append(row)
            cache.playback.update(playback)
        rows = [row for kept in cache.rows.values() for row in kept]
        playback = dict(cache.playback)
    records = screen_rows(study, rows, playback)
    return frozenset(sid for sid, record in records.items() if record.screened_out)


@dataclass(frozen=True)
class CountedVote:
    animation: str
    vote: GradedComparison
    answered_at: datetime


def counted_votes(session: Session, study: Study) -> list[CountedVote]:
    """The votes of ``study`` that its results count (``statistics.counted``: test votes of participants not
    screened out; no pilot sessions), in the order they were answered: what the adaptive design plans on."""
    excluded = screened_out(session, study)
    query = (select(Trial.session_id, Trial.practice, Comparison.kind, Vote.answered_at, Vote.score,
                    _REFERENCE.animation, _REFERENCE.condition, _TEST.condition)
             .select_from(Vote).join(Trial, Vote.trial_id == Trial.id)
             .join(ParticipantSession, Trial.session_id == ParticipantSession.id)
             .join(Comparison, Trial.comparison_id == Comparison.id)
             .join(_REFERENCE, Comparison.reference_id == _REFERENCE.id).join(_TEST, Comparison.test_id == _TEST.id)
             .where(Comparison.study_id == study.id, ParticipantSession.pilot.is_(False))
             .order_by(Vote.answered_at, Vote.id))
    verdicts: dict[tuple[bool, str, bool], bool] = {}  # counted() of each kind of vote: a few, not one per vote
    out = []
    for sid, practice, kind, answered_at, score, animation, ref, tst in session.execute(query):
        key = (practice, kind, sid in excluded)
        if key not in verdicts:
            verdicts[key] = counted({"practice": practice, "catch": kind == ComparisonKind.catch,
                                     "outcome": "screened_out" if key[2] else None})
        if verdicts[key]:
            out.append(CountedVote(animation, GradedComparison(sid, ref, tst, score), answered_at))
    return out


def study_votes(session: Session, study: Study, before: datetime | None = None
                ) -> dict[str, list[GradedComparison]]:
    """The counted votes (:func:`counted_votes`) of ``study`` per animation, optionally only those answered
    before ``before``."""
    out: dict[str, list[GradedComparison]] = defaultdict(list)
    for v in counted_votes(session, study):
        if before is None or v.answered_at < before:
            out[v.animation].append(v.vote)
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
    participant withdraws) and their expected information gain given the votes counted now that were answered
    before it started (a withdrawal deletes votes and a participant screened out later no longer counts, so a
    round can show other information than it promised then).

    One pass: the sessions in the order they started, each round's vote counts those of the round before plus the
    votes answered in between, and the posterior a pure function of the counts (``adaptive.counts_posterior``,
    remembered), so a request refits only the rounds whose votes changed since the last one."""
    design = Design.model_validate(study.design)
    conditions = design.all_conditions()
    index = {c: i for i, c in enumerate(conditions)}
    given: dict[str, dict[str, set[tuple[str, str]]]] = defaultdict(lambda: defaultdict(set))
    for sid, animation, ref, tst in session.execute(_test_trials(study)):
        given[sid][animation].add(tuple(sorted((ref, tst), key=index.__getitem__)))
    votes = counted_votes(session, study)
    counts = {a: np.zeros((len(conditions), len(conditions), 5), dtype=np.int64) for a in design.animations}
    seen = 0
    rounds = []
    for ps in session.scalars(select(ParticipantSession).where(ParticipantSession.study_id == study.id)
                              .order_by(ParticipantSession.created_at, ParticipantSession.id)):
        while seen < len(votes) and votes[seen].answered_at < ps.created_at:
            v = votes[seen]
            if v.animation in counts:
                counts[v.animation] += vote_counts([v.vote], conditions)
            seen += 1
        pairs = {a: sorted(given[ps.id][a], key=lambda p: (index[p[0]], index[p[1]])) for a in design.animations}
        information = {}
        for a, shown in pairs.items():
            post = counts_posterior(counts[a], tuple(conditions))
            information[a] = float(sum(information_gain(post, index[x], index[y]) for x, y in shown))
        rounds.append(Round(ps.id, ps.created_at, seen, information, pairs))
    return rounds
