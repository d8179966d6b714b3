"""Creating studies from study files over the rendered clip set, editing, opening and closing them, exporting
their votes."""

from __future__ import annotations

import csv
import io
import shutil
from collections.abc import Collection, Iterator, Mapping
from pathlib import Path
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session, aliased, object_session

from server.config import Settings
from server.db import utcnow
from server.errors import Conflict, NotFound, Unprocessable
from server.media.build import identical_clips, read_clip_set, rendered_pairs
from server.media.manifest import RenderManifest
from server.participants.models import ParticipantSession, SessionState, Trial, Vote
from server.researchers.models import Researcher
from server.stimuli import service as stimulus_sets

from .columns import EXPORT_COLUMNS, QUESTIONS_BEFORE
from .design import ComparisonIds, Design
from .models import Comparison, ComparisonKind, Stimulus, Study, StudyState
from .pilot import delete_pilot_sessions
from .scale import CHOICE_SCORES, MAX_SCORE, other_side
from .schemas import StudySummary
from .screening import ParticipantScreening, Screening, screen
from .studyfile import Recruitment, StudyFile, Texts

StimulusKey = tuple[str, str]  # (animation, condition)


def clip_set_index(clips_dir: Path) -> dict[StimulusKey, str]:
    """(animation, condition) -> clip id of the clip set in ``clips_dir`` (before its videos are rendered)."""
    return {(c.animation, c.condition): c.id for c in read_clip_set(clips_dir)}


def needed_stimuli(design: Design) -> list[tuple[ComparisonKind, StimulusKey, StimulusKey]]:
    """(kind, reference, test) of every comparison of the design, in the order they are created."""
    out = [(ComparisonKind.test, (a, first), (a, second))
           for a in design.animations for first, second in design.pairs()]
    out += [(ComparisonKind.catch, (a, design.reference), (a, design.reference))
            for a in design.animations[: design.catch_trials]]
    if design.practice:
        a = design.animations[0]
        out.append((ComparisonKind.practice, (a, design.reference), (a, design.practice)))
    return out


def check_known(design: Design, clips: Mapping[StimulusKey, str]) -> None:
    """422 naming the animations or conditions of ``design`` the clip set does not have."""
    animations = {a for a, _ in clips}
    unknown_animations = [a for a in design.animations if a not in animations]
    if unknown_animations:
        raise Unprocessable(f"design.animations: unknown animation(s) {', '.join(unknown_animations)} "
                            f"(the clip set has {', '.join(sorted(animations))})")
    conditions = [design.reference, *design.conditions, *([design.practice] if design.practice else [])]
    missing = sorted({f"{c} of {a}" for a in design.animations for c in conditions if (a, c) not in clips})
    if missing:
        known = sorted({c for _, c in clips})
        raise Unprocessable(f"design: unknown condition(s): {', '.join(missing)} (the clip set has "
                            f"{', '.join(known)})")


def required_pairs(design: Design, clips: Mapping[StimulusKey, str]) -> list[tuple[str, str]]:
    """(left clip, right clip) of every side-by-side video the design shows."""
    check_known(design, clips)
    pairs = []
    for _, ref, test in needed_stimuli(design):
        pairs += [(clips[ref], clips[test]), (clips[test], clips[ref])]
    return list(dict.fromkeys(pairs))


def identical_comparisons(design: Design, clips_dir: Path) -> list[tuple[str, str]]:
    """(test clip, reference clip) of every test comparison of ``design`` whose two clips have the same arrays:
    participants see one clip on both sides, as in a catch trial (e.g. a key reduction that kept every key)."""
    clips = read_clip_set(clips_dir)
    same, index = identical_clips(clips), {(c.animation, c.condition): c.id for c in clips}
    return [(index[test], index[ref]) for kind, ref, test in needed_stimuli(design)
            if kind == ComparisonKind.test and same[index[test]] == same[index[ref]]]


def _columns(definition: StudyFile) -> dict[str, Any]:
    texts = definition.texts.model_dump()
    return {"title": definition.title, "consent_version": texts.pop("consent_version"), "texts": texts,
            "scale": definition.scale.model_dump(), "questions": [q.model_dump() for q in definition.questions],
            "design": definition.design.model_dump(), "recruitment": definition.recruitment.model_dump(),
            "page": definition.page.model_dump(), "screening": definition.screening.model_dump()}


def definition(study: Study) -> StudyFile:
    """The study file a study was made from (with its edits)."""
    return StudyFile.model_validate({
        "slug": study.slug, "title": study.title, "texts": {**study.texts, "consent_version": study.consent_version},
        "scale": study.scale, "questions": study.questions, "design": study.design, "recruitment": study.recruitment,
        "page": study.page or {}, "screening": study.screening or {}})


def create_study(session: Session, media: RenderManifest, study_file: StudyFile,
                 owner: Researcher | None = None, media_dir: Path | None = None,
                 clips_dir: Path | None = None, animations: Collection[str] | None = None,
                 stimulus_set: stimulus_sets.SetContent | None = None) -> Study:
    """A draft study over the videos of a render manifest (``server.media.build``), which must hold its pairs;
    its stimulus set (:mod:`server.stimuli`) hashes the files in ``media_dir`` and takes the clips' metrics from
    the clip set in ``clips_dir`` (or is ``stimulus_set``, the set ``media`` was made from: an imported study's).
    ``animations``: the ones its owner may use (default: all; the others are unknown to them, see
    ``server.uploads.service.usable_animations``)."""
    study = new_draft(session, study_file, owner)
    _build_comparisons(session, study, media, study_file.design, media_dir, clips_dir, animations, stimulus_set)
    session.add(study)
    session.commit()
    return study


def new_draft(session: Session, study_file: StudyFile, owner: Researcher | None) -> Study:
    """The row of a new draft study, nothing shown yet (409 if the slug is taken); not added to the session."""
    if session.scalar(select(Study.id).where(Study.slug == study_file.slug)) is not None:
        raise Conflict(f"a study with slug {study_file.slug!r} exists already")
    return Study(slug=study_file.slug, state=StudyState.draft, owner_id=owner.id if owner else None,
                 **_columns(study_file))


def _build_comparisons(session: Session, study: Study, media: RenderManifest, design: Design,
                       media_dir: Path | None, clips_dir: Path | None,
                       animations: Collection[str] | None = None,
                       given: stimulus_sets.SetContent | None = None) -> None:
    """The study's stimuli, comparisons and stimulus set for ``design`` (replacing any it had), from the clips of
    ``animations`` (default: all)."""
    if study.opened_at is not None:  # its set is pinned
        raise Conflict(f"study {study.slug!r} has been open: what it shows is pinned")
    clips = {k: v for k, v in media.clip_index().items() if animations is None or k[0] in animations}
    pair_videos = media.pair_videos()
    needed = required_pairs(design, clips)
    missing = [p for p in needed if p not in pair_videos]
    if missing:
        raise Conflict(f"the rendered videos lack {len(missing)} of the pairs the design shows; "
                       "`animstudy study create` renders them")
    if study.comparisons or study.stimuli:
        study.comparisons.clear()
        study.stimuli.clear()
        if object_session(study) is not None:  # delete the old rows before the new ones meet the unique constraint
            session.flush()
    stimuli: dict[StimulusKey, Stimulus] = {}

    def stimulus(key: StimulusKey) -> Stimulus:
        if key not in stimuli:
            entry = media.clips[clips[key]]
            stimuli[key] = Stimulus(clip_id=clips[key], animation=key[0], condition=key[1], video=entry.video,
                                    poster=entry.poster, frames=entry.frames, fps=entry.fps)
            study.stimuli.append(stimuli[key])
        return stimuli[key]

    for kind, ref, test in needed_stimuli(design):
        r, t = clips[ref], clips[test]
        study.comparisons.append(Comparison(kind=kind, reference=stimulus(ref), test=stimulus(test),
                                            video_reference_left=pair_videos[(r, t)],
                                            video_reference_right=pair_videos[(t, r)]))
    content = given or stimulus_sets.make_content(media, [s.clip_id for s in study.stimuli], needed, media_dir,
                                                  clips_dir)
    study.stimulus_set = stimulus_sets.store(session, content)


def show_design(session: Session, study: Study, media: RenderManifest, media_dir: Path | None,
                clips_dir: Path | None) -> Study:
    """A draft's comparisons and stimulus set for its own design over ``media`` (a study created through the API
    with inline ``[clips]``, once its build job has rendered them)."""
    if study.state != StudyState.draft:
        raise Conflict(f"study {study.slug!r} is {study.state}, no longer a draft")
    _build_comparisons(session, study, media, Design.model_validate(study.design), media_dir, clips_dir)
    session.commit()
    return study


def get_study(session: Session, slug: str) -> Study:
    study = session.scalar(select(Study).where(Study.slug == slug))
    if study is None:
        raise NotFound(f"no study {slug!r}")
    return study


def can_manage(researcher: Researcher, study: Study) -> bool:
    return researcher.is_admin or study.owner_id == researcher.id


def managed_study(session: Session, slug: str, researcher: Researcher) -> Study:
    """The study ``slug`` if ``researcher`` owns it or is an admin; another researcher's study answers as an
    unknown one (404, the same message), so slugs cannot be probed."""
    study = session.scalar(select(Study).where(Study.slug == slug))
    if study is None or not can_manage(researcher, study):
        raise NotFound(f"no study {slug!r}")
    return study


def public_study(session: Session, slug: str) -> Study:
    """The study ``slug`` as participants may see it: a draft (its texts not yet final nor public) answers as an
    unknown study (404)."""
    study = session.scalar(select(Study).where(Study.slug == slug))
    if study is None or study.state == StudyState.draft:
        raise NotFound(f"no study {slug!r}")
    return study


def visible_studies(session: Session, researcher: Researcher) -> list[Study]:
    query = select(Study).order_by(Study.id)
    if not researcher.is_admin:
        query = query.where(Study.owner_id == researcher.id)
    return list(session.scalars(query))


def default_study(session: Session) -> Study | None:
    """The open study created first (``animstudy serve`` creates the thesis study first)."""
    return session.scalar(select(Study).where(Study.state == StudyState.open).order_by(Study.id).limit(1))


def update_study(session: Session, study: Study, changes: Mapping[str, Any],
                 media: RenderManifest | None = None, media_dir: Path | None = None,
                 clips_dir: Path | None = None, animations: Collection[str] | None = None) -> Study:
    """Apply a partial study file (sections are merged into the current ones): ``screening`` at any time (it
    changes the analysis, not what participants see); ``title``, ``texts``, ``scale``,
    ``questions`` and ``recruitment`` until the study first opens; ``design`` only while it is a draft that never
    opened (its comparisons are rebuilt over ``media``, the render manifest).  Otherwise 409: participants saw it
    as it is.  An invalid result raises pydantic's ValidationError (the API answers 422)."""
    if study.opened_at is not None and set(changes) - {"screening"}:
        raise Conflict(f"study {study.slug!r} has been open: participants saw it as it is; create a new study "
                       "(only [screening], which participants never see, can still change)")
    if "slug" in changes and changes["slug"] != study.slug:
        raise Conflict("a study's slug cannot change")
    if changes.get("clips") is not None:
        raise Unprocessable("clips: a study's clip set is chosen when it is created (`animstudy study create`)")
    current = definition(study).model_dump()
    for key, value in changes.items():
        merge = isinstance(current.get(key), dict) and isinstance(value, dict)
        current[key] = {**current[key], **value} if merge else value
    updated = StudyFile.model_validate(current)
    if updated.design != Design.model_validate(study.design):  # designs stored before a field existed compare equal
        if study.state != StudyState.draft or media is None:
            raise Conflict("the design can change only while the study is a draft")
        delete_pilot_sessions(session, study, commit=False)  # their trials show the old comparisons
        _build_comparisons(session, study, media, updated.design, media_dir, clips_dir, animations)
    for key, value in _columns(updated).items():
        setattr(study, key, value)
    session.commit()
    return study


def delete_study(session: Session, study: Study, settings: Settings) -> None:
    """A draft that never opened, with its uploaded files (their rows go with the study)."""
    if study.state != StudyState.draft or study.opened_at is not None:
        raise Conflict(f"study {study.slug!r} is {study.state}; only a draft that never opened can be deleted")
    study_id = study.id
    delete_pilot_sessions(session, study, commit=False)  # a draft's only sessions; their trials hold comparisons
    session.delete(study)
    session.commit()
    shutil.rmtree(settings.study_assets_dir(study_id), ignore_errors=True)


def comparison_ids(study: Study) -> ComparisonIds:
    by_kind: dict[str, list[int]] = {k: [] for k in ComparisonKind}
    for c in study.comparisons:
        by_kind[c.kind].append(c.id)
    practice = by_kind[ComparisonKind.practice]
    return ComparisonIds(by_kind[ComparisonKind.test], by_kind[ComparisonKind.catch],
                         practice[0] if practice else None)


def trials_total(study: Study) -> int:
    return Design.model_validate(study.design).trials_total()


def open_study(session: Session, study: Study, media_dir: Path) -> Study:
    """Open ``study`` for participants once every file of its stimulus set is in ``media_dir`` with the bytes
    the set records (409 naming what is missing otherwise); from then on the set is pinned."""
    if study.stimulus_set is None:
        raise Conflict(f"study {study.slug!r} has no stimulus set; create it again with `animstudy study create`")
    lacking = stimulus_sets.missing(stimulus_sets.content_of(study.stimulus_set), media_dir)
    if lacking:
        shown = "; ".join(lacking[:10]) + (f"; and {len(lacking) - 10} more" if len(lacking) > 10 else "")
        raise Conflict(f"study {study.slug!r} cannot open: its stimulus set is incomplete ({shown}); "
                       "`animstudy study create` renders what is missing")
    return set_state(session, study, StudyState.open)


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


def recruitment(study: Study) -> Recruitment:
    # Stored: a template saved before the rules of studyfile.template_problem reads, and gives no URL.
    return Recruitment.model_validate(study.recruitment, context={"stored": True})


def texts(study: Study) -> Texts:
    return Texts.model_validate({**study.texts, "consent_version": study.consent_version})


def failed_catch_trials(session: Session, study: Study, session_id: str | None = None) -> dict[str, int]:
    """Failed catch trials per participant session of ``study`` (or of the one session ``session_id``): a
    'significantly better' answer when both sides show the same clip.  Sessions without a failure are absent."""
    query = (select(Trial.session_id, func.count(Vote.id)).join(Vote, Vote.trial_id == Trial.id)
             .join(Comparison, Trial.comparison_id == Comparison.id)
             .where(Comparison.study_id == study.id, Comparison.kind == ComparisonKind.catch,
                    func.abs(Vote.score) == MAX_SCORE).group_by(Trial.session_id))
    if session_id is not None:
        query = query.where(Trial.session_id == session_id)
    return {sid: n for sid, n in session.execute(query).all()}


def session_outcome(study: Study, state: str, failed_catch: int) -> str | None:
    """What a finished session's participant is told (and which completion code or link they get):
    ``completed``, or ``screened_out`` when the study screens by catch trials (``[screening] rules``) and more
    were failed than it allows; None for a session that has not finished.  The other rules are applied to the
    results and exports only: most compare a participant with the panel, which grows after they leave."""
    if state != SessionState.completed:
        return None
    if "catch" not in screening_rules(study).rules:
        return "completed"
    return "screened_out" if failed_catch > recruitment(study).catch_failures_allowed else "completed"


def export_columns(study: Study) -> list[str]:
    """The fixed columns, with one per question of the study (its id) before ``answered_at`` and one per accepted
    URL parameter (its name, e.g. ``PROLIFIC_PID``) at the end."""
    base = list(EXPORT_COLUMNS)
    at = base.index(QUESTIONS_BEFORE)
    return base[:at] + [q["id"] for q in study.questions] + base[at:] + list(study.recruitment["parameters"])


# A text cell beginning with one of these is a formula (or becomes one) in Excel, LibreOffice and Google Sheets:
# leading spaces and line breaks are skipped by some of them, and the full-width forms (U+FF1D ＝ and its
# neighbours) are read as the ASCII ones by others.
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r", "\n", " ", "\uff1d", "\uff0b", "\uff0d", "\uff20")


def csv_cell(value: object) -> object:
    """A value as a CSV cell: booleans ``true``/``false``, None empty, and text that a spreadsheet would evaluate
    (participant-supplied ids could be ``=HYPERLINK(...)``) prefixed with ``'``, which spreadsheets show as text.
    Numbers stay numbers: a score of -2 is not text."""
    if isinstance(value, bool):
        return str(value).lower()
    if value is None:
        return ""
    if isinstance(value, str) and value.startswith(FORMULA_STARTS):
        return "'" + value
    return value


def export_csv(session: Session, study: Study, include_pilot: bool = False) -> str:
    """The export as CSV (cells as :func:`csv_cell` writes them)."""
    buffer = io.StringIO()
    # RFC 4180 line ends: with "\n" alone the csv module would not quote a value holding a bare "\r", and every
    # reader would split the row there.
    writer = csv.DictWriter(buffer, fieldnames=export_columns(study), lineterminator="\r\n")
    writer.writeheader()
    for row in export_rows(session, study, include_pilot):
        writer.writerow({k: csv_cell(v) for k, v in row.items()})
    return buffer.getvalue()


def export_document(session: Session, study: Study, include_pilot: bool = False) -> dict[str, Any]:
    """The export as one JSON document: the study, the columns, the rows."""
    return {"study": {"slug": study.slug, "title": study.title, "state": study.state, "design": study.design,
                      "consent_version": study.consent_version, "questions": study.questions},
            "columns": export_columns(study), "votes": list(export_rows(session, study, include_pilot))}


def pairs_in_use(session: Session) -> list[tuple[str, str]]:
    """(left clip, right clip) of every pair video some study shows (rendering must keep them)."""
    reference, test = aliased(Stimulus), aliased(Stimulus)
    rows = session.execute(select(reference.clip_id, test.clip_id)
                           .join(Comparison, Comparison.reference_id == reference.id)
                           .join(test, Comparison.test_id == test.id)).all()
    return list(dict.fromkeys(p for r, t in rows for p in ((r, t), (t, r))))


def pairs_to_render(session: Session, design: Design, clips_dir: Path, media_dir: Path) -> list[tuple[str, str]]:
    """The pair videos to have when ``design`` is added: the pairs every study in the database shows, the ones
    rendered before (e.g. by `animstudy render --study` of a study not created yet) as far as the clip set still
    has their clips — adding a study removes nothing — and the pairs ``design`` needs."""
    index = clip_set_index(clips_dir)
    clip_ids = set(index.values())
    before = [p for p in rendered_pairs(media_dir) if set(p) <= clip_ids]
    return list(dict.fromkeys([*pairs_in_use(session), *before, *required_pairs(design, index)]))


def screening_rules(study: Study) -> Screening:
    """The study's ``[screening]`` (NULL before migration 0009: the catch-trial rule alone)."""
    return Screening.model_validate(study.screening or {})


def screened_rows(session: Session, study: Study, include_pilot: bool = False
                  ) -> tuple[list[dict[str, Any]], dict[str, ParticipantScreening]]:
    """The export rows (see :func:`export_rows`) and every completed participant's screening record, by the
    study's ``[screening]`` rules (``screening.screen``).  Pilot sessions only with ``include_pilot``."""
    reference, test = aliased(Stimulus), aliased(Stimulus)
    questions = [q["id"] for q in study.questions]
    parameters = list(study.recruitment["parameters"])
    query = (
        select(Vote, Trial, ParticipantSession, Comparison.kind, reference.animation, reference.condition,
               test.condition, reference.clip_id, test.clip_id, reference.video, test.video,
               Comparison.video_reference_left, Comparison.video_reference_right, reference.frames,
               reference.fps, test.frames, test.fps)
        .join(Trial, Vote.trial_id == Trial.id)
        .join(ParticipantSession, Trial.session_id == ParticipantSession.id)
        .join(Comparison, Trial.comparison_id == Comparison.id)
        .join(reference, Comparison.reference_id == reference.id)
        .join(test, Comparison.test_id == test.id)
        .where(ParticipantSession.study_id == study.id)
        .order_by(ParticipantSession.created_at, ParticipantSession.id, Trial.index)
    )
    if not include_pilot:
        query = query.where(ParticipantSession.pilot.is_(False))
    pinned = study.stimulus_set
    content = stimulus_sets.content_of(pinned) if pinned is not None else None
    hashes = content.hashes() if content is not None else {}
    # clips built in spite of the fidelity gate (accept_unfaithful) mark every vote on them
    unfaithful = {c.id for c in content.clips if c.metrics.get("unfaithful")} if content is not None else set()
    mode = study.design.get("mode", "reference")  # designs stored before issue 27 have no mode
    rows: list[dict[str, Any]] = []
    playback: dict[tuple[str, str, str], float] = {}
    for (vote, trial, ps, kind, animation, ref_condition, test_condition, ref_clip, test_clip, ref_video, test_video,
         pair_ref_left, pair_ref_right, ref_frames, ref_fps, test_frames, test_fps) in session.execute(query):
        # one playback of the pair video: until the longer of its two clips has ended
        playback[(animation, ref_condition, test_condition)] = 1000 * max(ref_frames / ref_fps,
                                                                          test_frames / test_fps)
        left, right = (ref_video, test_video) if trial.reference_side == "left" else (test_video, ref_video)
        left_condition, right_condition = ((ref_condition, test_condition) if trial.reference_side == "left"
                                           else (test_condition, ref_condition))
        pair = pair_ref_left if trial.reference_side == "left" else pair_ref_right
        answers, external, device = ps.answers or {}, ps.external or {}, ps.device or {}
        rows.append({
            "session_id": ps.id, "trial_index": trial.index, "practice": trial.practice,
            "catch": kind == ComparisonKind.catch, "animation": animation, "reference_condition": ref_condition,
            "test_condition": test_condition, "reference_side": trial.reference_side,
            "test_side": other_side(trial.reference_side), "choice": vote.choice, "score": vote.score,
            "rt_ms": vote.rt_ms, **{q: answers.get(q) for q in questions},
            "answered_at": vote.answered_at.isoformat(), "consent_version": ps.consent_version,
            "session_state": ps.state, "outcome": None,
            "viewport_width": device.get("viewport_width"),
            "viewport_height": device.get("viewport_height"), "device_pixel_ratio": device.get("device_pixel_ratio"),
            "video_scale": device.get("scale"), "video_scaled": device.get("scaled"),
            "unfaithful": ref_clip in unfaithful or test_clip in unfaithful,
            "left_video": hashes.get(left), "right_video": hashes.get(right), "pair_video": hashes.get(pair),
            "stimulus_set": pinned.digest if pinned is not None else None,
            "design_mode": mode, "left_condition": left_condition,
            "right_condition": right_condition,
            "screened_by": None, "pilot": ps.pilot,
            **{p: external.get(p) for p in parameters},
        })
    records = screen(rows, screening_rules(study), recruitment(study).catch_failures_allowed, playback)
    for row in rows:
        record = records.get(row["session_id"])
        if record is not None:  # a completed session
            row["outcome"] = "screened_out" if record.screened_out else "completed"
            row["screened_by"] = ";".join(record.flagged_by) or None
    return rows, records


def export_rows(session: Session, study: Study, include_pilot: bool = False) -> Iterator[dict[str, Any]]:
    """One row per vote (withdrawn participants' votes no longer exist), in session and trial order; ``outcome``
    and ``screened_by`` by the study's screening rules; pilot sessions only with ``include_pilot``."""
    yield from screened_rows(session, study, include_pilot)[0]


def _analysed_test_rows(session: Session, study: Study, include_pilot: bool) -> list[dict[str, Any]]:
    """Test trials of the participants who finished and were not screened out (the subject model's input)."""
    rows, _ = screened_rows(session, study, include_pilot)
    return [r for r in rows if not r["practice"] and not r["catch"] and r["outcome"] == "completed"]


def export_sureal(session: Session, study: Study, include_pilot: bool = False) -> dict[str, Any]:
    """The analysed test votes as a ``sureal`` dataset (its JSON form: ``sureal --dataset FILE.json``, or
    ``sureal.tools.misc.import_json_file``): a comparison (animation, reference, test condition) is a distorted
    video, its animation the content, each participant's side-swapped showings the repetitions of their score;
    scores -2..+2 from the test condition's point of view."""
    rows = _analysed_test_rows(session, study, include_pilot)
    comparisons = sorted({(r["animation"], r["reference_condition"], r["test_condition"]) for r in rows})
    animations = sorted({a for a, _, _ in comparisons})
    scores: dict[tuple[str, str, str], dict[str, list[int]]] = {c: {} for c in comparisons}
    for r in rows:
        key = (r["animation"], r["reference_condition"], r["test_condition"])
        scores[key].setdefault(r["session_id"], []).append(r["score"])
    return {
        "dataset_name": study.slug,
        "ref_videos": [{"content_id": i, "content_name": a, "path": a} for i, a in enumerate(animations)],
        "dis_videos": [{"asset_id": i, "content_id": animations.index(a), "path": f"{a}/{test}-vs-{ref}",
                        "animation": a, "reference_condition": ref, "test_condition": test,
                        "os": scores[(a, ref, test)]}
                       for i, (a, ref, test) in enumerate(comparisons)],
    }


PWCMP_COLUMNS = ("observer", "session", "scene", "cond1", "cond2", "selection")


def export_pwcmp_csv(session: Session, study: Study, include_pilot: bool = False) -> str:
    """The analysed test votes as pairwise comparisons in pwcmp's table (observer, session, scene, cond1, cond2,
    selection): cond1 the condition shown left, cond2 the one shown right, selection 1 or 2 for the side the
    participant preferred (slightly or much); "equal" answers are left out, as pwcmp models a forced choice.
    Works for any design: it reads each trial's two conditions."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\r\n")
    writer.writerow(PWCMP_COLUMNS)
    for r in _analysed_test_rows(session, study, include_pilot):
        left, right = ((r["reference_condition"], r["test_condition"]) if r["reference_side"] == "left"
                       else (r["test_condition"], r["reference_condition"]))
        raw = CHOICE_SCORES[r["choice"]]
        if raw:
            writer.writerow([csv_cell(v) for v in (r["session_id"], 1, r["animation"], left, right,
                                                   1 if raw > 0 else 2)])
    return buffer.getvalue()


def participant_counts(session: Session, study: Study, include_pilot: bool = False,
                       records: Mapping[str, ParticipantScreening] | None = None) -> dict[str, int]:
    """``started``: every session created (withdrawn included); ``completed``: finished and not withdrawn;
    ``screened_out``: of those, the ones whose votes are not analysed (by the study's screening rules; ``records``
    if the caller has them); ``pilot``: the researcher's preview sessions, which count in the others only with
    ``include_pilot``."""
    query = select(ParticipantSession.state, ParticipantSession.pilot, func.count()).where(
        ParticipantSession.study_id == study.id).group_by(ParticipantSession.state, ParticipantSession.pilot)
    by_state: dict[str, int] = {}
    pilot = 0
    for state, is_pilot, n in session.execute(query).all():
        pilot += n if is_pilot else 0
        if include_pilot or not is_pilot:
            by_state[state] = by_state.get(state, 0) + n
    if records is None:
        rules = screening_rules(study).rules
        if rules == ["catch"]:  # the cheap count, without reading every vote
            failed = failed_catch_trials(session, study)
            query = select(ParticipantSession.id).where(
                ParticipantSession.study_id == study.id, ParticipantSession.state == SessionState.completed,
                ParticipantSession.id.in_(failed))
            if not include_pilot:
                query = query.where(ParticipantSession.pilot.is_(False))
            completed = session.scalars(query) if failed else []
            screened = sum(session_outcome(study, SessionState.completed, failed[sid]) == "screened_out"
                           for sid in completed)
        else:
            records = screened_rows(session, study, include_pilot)[1]
    if records is not None:
        screened = sum(r.screened_out for r in records.values())
    return {"started": sum(by_state.values()), "completed": by_state.get(SessionState.completed, 0),
            "screened_out": screened, "withdrawn": by_state.get(SessionState.withdrawn, 0),
            "active": by_state.get(SessionState.active, 0), "pilot": pilot}


def study_summary(session: Session, study: Study) -> StudySummary:
    """The study as its list and the command line show it: state, owner, participant and vote counts, what may
    still be edited."""
    counts = participant_counts(session, study)
    votes = session.scalar(select(func.count(Vote.id)).join(ParticipantSession).where(
        ParticipantSession.study_id == study.id, ParticipantSession.pilot.is_(False))) or 0
    never_opened = study.opened_at is None
    return StudySummary(slug=study.slug, title=study.title, state=study.state,
                        owner=study.owner.email if study.owner else None, started=counts["started"],
                        completed=counts["completed"], votes=votes, trials_total=trials_total(study),
                        participant_url=f"/s/{study.slug}",
                        editable={"texts": never_opened, "recruitment": never_opened,
                                  "design": never_opened and study.state == StudyState.draft})
