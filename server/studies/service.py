"""Creating studies from the rendered clip set, opening and closing them, exporting their votes."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload

from server.db import utcnow
from server.errors import Conflict, NotFound

from .design import ComparisonIds, Design
from .models import Comparison, ComparisonKind, Stimulus, Study, StudyState

DEFAULT_SLUG = "thesis"
DEFAULT_TITLE = "How good does this character animation look?"
CONSENT_VERSION = "2026-11-1"
DEFAULT_TEXTS = {
    "information": (
        "This study compares two ways of animating a human character. You will see two identical characters side "
        "by side and say which animation looks better. It takes about 10 minutes. We store your answers and the "
        "two demographic answers without your name or any other identifying information, and publish them "
        "anonymously for research. Taking part is voluntary: you can stop at any time without giving a reason, "
        "and withdraw to have your answers deleted."
    ),
    "consent": (
        "I have read the information above. I agree to take part and to my anonymous answers being stored and "
        "published for research."
    ),
    "instructions": (
        "Each trial shows two characters moving in sync. Watch them, then choose which animation looks better: "
        "significantly or slightly better on the left, equal, or slightly or significantly better on the right. "
        "Pay attention to how natural the motion looks, including the feet on the floor."
    ),
    "thanks": "Thank you for taking part!",
    "contact": "The researchers of this study (contact details are given by the person who invited you).",
}
CHOICE_SCORES = {"left_much": 2, "left_slightly": 1, "equal": 0, "right_slightly": -1, "right_much": -2}


def required_pairs(design: Design) -> list[tuple[str, str]]:
    """(left clip, right clip) of every side-by-side video the design shows."""
    pairs = []
    for animation in design.animations:
        keyframe = f"{animation}-keyframe"
        for increment in design.increments:
            hybrid = f"{animation}-hybrid{increment}"
            pairs += [(hybrid, keyframe), (keyframe, hybrid)]
    for animation in design.animations[: design.catch_trials]:
        pairs.append((f"{animation}-keyframe", f"{animation}-keyframe"))
    if design.practice:
        hybrid = f"{design.animations[0]}-hybrid{design.practice_increment}"
        keyframe = f"{design.animations[0]}-keyframe"
        pairs += [(hybrid, keyframe), (keyframe, hybrid)]
    return list(dict.fromkeys(pairs))


def create_study(session: Session, media: Mapping[str, Any], design: Design | None = None,
                 slug: str = DEFAULT_SLUG, title: str = DEFAULT_TITLE, texts: Mapping[str, str] | None = None,
                 completion_code: str | None = None, completion_url: str | None = None) -> Study:
    """A draft study over the videos of a render manifest (``server.media.build``), which must hold its pairs."""
    design = design or Design()
    if session.scalar(select(Study.id).where(Study.slug == slug)) is not None:
        raise Conflict(f"a study with slug {slug!r} exists already")
    if len(design.animations) * len(design.increments) == 1 and design.catch_trials == 0:
        raise Conflict("a design with a single comparison cannot avoid showing it twice in a row")
    pair_videos = {(p["left"], p["right"]): p["video"] for p in media["pairs"]}
    missing = [p for p in required_pairs(design) if p not in pair_videos]
    if missing:
        raise Conflict(f"the rendered videos lack the pairs {missing}; render them first")
    study = Study(slug=slug, title=title, texts={**DEFAULT_TEXTS, **(texts or {})}, consent_version=CONSENT_VERSION,
                  design=design.model_dump(), state=StudyState.draft, completion_code=completion_code,
                  completion_url=completion_url)
    stimuli: dict[str, Stimulus] = {}

    def stimulus(clip_id: str) -> Stimulus:
        if clip_id not in stimuli:
            entry = media["clips"][clip_id]
            animation, method = clip_id.rsplit("-", 1)
            increment = None if method == "keyframe" else int(method.removeprefix("hybrid"))
            stimuli[clip_id] = Stimulus(clip_id=clip_id, animation=animation,
                                        method="keyframe" if increment is None else "hybrid", increment=increment,
                                        video=entry["video"], poster=entry["poster"], frames=entry["frames"],
                                        fps=entry["fps"])
            study.stimuli.append(stimuli[clip_id])
        return stimuli[clip_id]

    def comparison(kind: ComparisonKind, animation: str, left: str, right: str, increment: int | None) -> None:
        study.comparisons.append(Comparison(
            kind=kind, animation=animation, increment=increment, keyframe=stimulus(left), hybrid=stimulus(right),
            video_hybrid_left=pair_videos[(right, left)], video_hybrid_right=pair_videos[(left, right)]))

    for animation in design.animations:
        for increment in design.increments:
            comparison(ComparisonKind.test, animation, f"{animation}-keyframe", f"{animation}-hybrid{increment}",
                       increment)
    for animation in design.animations[: design.catch_trials]:
        keyframe = f"{animation}-keyframe"
        comparison(ComparisonKind.catch, animation, keyframe, keyframe, None)
    if design.practice:
        animation = design.animations[0]
        comparison(ComparisonKind.practice, animation, f"{animation}-keyframe",
                   f"{animation}-hybrid{design.practice_increment}", design.practice_increment)
    session.add(study)
    session.commit()
    return study


def get_study(session: Session, slug: str) -> Study:
    study = session.scalar(select(Study).where(Study.slug == slug))
    if study is None:
        raise NotFound(f"no study {slug!r}")
    return study


def comparison_ids(study: Study) -> ComparisonIds:
    by_kind: dict[str, list[int]] = {k: [] for k in ComparisonKind}
    for c in study.comparisons:
        by_kind[c.kind].append(c.id)
    practice = by_kind[ComparisonKind.practice]
    return ComparisonIds(by_kind[ComparisonKind.test], by_kind[ComparisonKind.catch],
                         practice[0] if practice else None)


def trials_total(study: Study) -> int:
    design = Design.model_validate(study.design)
    ids = comparison_ids(study)
    return len(ids.test) * 2 * design.repeats + len(ids.catch) + (1 if ids.practice else 0)


def set_state(session: Session, study: Study, state: StudyState) -> Study:
    """Open or close a study (closing stops new sessions; running ones may finish)."""
    if state == StudyState.open:
        study.opened_at = study.opened_at or utcnow()
        study.closed_at = None
    elif state == StudyState.closed:
        study.closed_at = utcnow()
    study.state = state
    session.commit()
    return study


def score(choice: str, hybrid_side: str) -> int:
    """The answer from the hybrid's point of view: +2 hybrid much better ... -2 keyframe much better."""
    value = CHOICE_SCORES[choice]
    return value if hybrid_side == "left" else -value


EXPORT_COLUMNS = ("session_id", "trial_index", "practice", "catch", "animation", "increment", "hybrid_side",
                  "choice", "score", "rt_ms", "gamer", "tech_savvy", "answered_at", "consent_version",
                  "session_state", "prolific_pid", "prolific_study_id", "prolific_session_id")
# Export column <- key of the session's external ids (as the participant page passes them on from the URL).
EXTERNAL_ID_COLUMNS = {"prolific_pid": "PROLIFIC_PID", "prolific_study_id": "STUDY_ID",
                       "prolific_session_id": "SESSION_ID"}


def export_rows(session: Session, study: Study) -> Iterator[dict[str, Any]]:
    """One row per vote (withdrawn participants' votes no longer exist), in session and trial order."""
    from server.participants.models import ParticipantSession, Trial, Vote

    rows = session.execute(
        select(Vote, Trial, ParticipantSession, Comparison)
        .join(Trial, Vote.trial_id == Trial.id)
        .join(ParticipantSession, Trial.session_id == ParticipantSession.id)
        .join(Comparison, Trial.comparison_id == Comparison.id)
        .where(ParticipantSession.study_id == study.id)
        .order_by(ParticipantSession.created_at, ParticipantSession.id, Trial.index)
        .options(selectinload(Trial.comparison))
    )
    for vote, trial, ps, comp in rows:
        external = ps.external or {}
        yield {
            "session_id": ps.id, "trial_index": trial.index, "practice": trial.practice,
            "catch": comp.kind == ComparisonKind.catch, "animation": comp.animation, "increment": comp.increment,
            "hybrid_side": trial.hybrid_side, "choice": vote.choice, "score": vote.score, "rt_ms": vote.rt_ms,
            "gamer": ps.gamer, "tech_savvy": ps.tech_savvy, "answered_at": vote.answered_at.isoformat(),
            "consent_version": ps.consent_version, "session_state": ps.state,
            **{column: external.get(key) for column, key in EXTERNAL_ID_COLUMNS.items()},
        }
