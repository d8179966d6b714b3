"""Creating studies from study files over the rendered clip set, editing, opening and closing them: the study
definition, which knows nothing of its participants (:mod:`server.participants` builds on it)."""

from __future__ import annotations

import shutil
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session, aliased, object_session

from server.clipset.manifest import MANIFEST
from server.config import Settings
from server.db import utcnow
from server.errors import Conflict, NotFound, Unprocessable
from server.media.build import rendered_pairs
from server.media.manifest import RenderManifest
from server.media.plan import identical_clips, read_clip_set
from server.researchers.models import Researcher
from server.stimuli import service as stimulus_sets

from . import ladder
from .columns import EXPORT_COLUMNS, QUESTIONS_BEFORE
from .design import LADDER_MODES, ComparisonIds, Design
from .models import Comparison, ComparisonKind, Stimulus, Study, StudyState
from .screening import Screening
from .studyfile import Recruitment, StudyFile, Texts

StimulusKey = tuple[str, str]  # (animation, condition)


def clip_set_index(clips_dir: Path) -> dict[StimulusKey, str]:
    """(animation, condition) -> clip id of the clip set in ``clips_dir`` (before its videos are rendered)."""
    return {(c.animation, c.condition): c.id for c in read_clip_set(clips_dir, read_arrays=False)}


def needed_stimuli(design: Design) -> list[tuple[ComparisonKind, StimulusKey, StimulusKey]]:
    """(kind, reference, test) of every comparison of the design, in the order they are created."""
    out = [(ComparisonKind.test, (a, first), (a, second))
           for a in design.animations for first, second in design.pairs()]
    caught = design.easiest() if design.mode in LADDER_MODES else design.reference  # ladders: the easiest level
    out += [(ComparisonKind.catch, (a, design.reference), (a, caught))
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
    design = _build_comparisons(session, study, media, study_file.design, media_dir, clips_dir, animations,
                                stimulus_set)
    study.design = design.model_dump()
    session.add(study)
    session.commit()
    return study


def new_draft(session: Session, study_file: StudyFile, owner: Researcher | None) -> Study:
    """The row of a new draft study, nothing shown yet (409 if the slug is taken); not added to the session."""
    if session.scalar(select(Study.id).where(Study.slug == study_file.slug)) is not None:
        raise Conflict(f"a study with slug {study_file.slug!r} exists already")
    return Study(slug=study_file.slug, state=StudyState.draft, owner_id=owner.id if owner else None,
                 **_columns(study_file))


def settled(design: Design, clips_dir: Path | None) -> Design:
    """``design`` settled against the clip manifest in ``clips_dir`` (:func:`server.studies.ladder.resolve`: a
    threshold design's levels from its clips' ``ladder``/``level`` fields, 422 if they disagree).  Without a clip
    manifest only a design whose levels are given already (an imported study's) is accepted."""
    if design.mode not in LADDER_MODES:
        return design
    if clips_dir is not None and (Path(clips_dir) / MANIFEST).is_file():
        return ladder.resolve(design, ladder.ladder_fields(read_clip_set(clips_dir, read_arrays=False)))
    if design.levels is None or design.whole_ladder():
        raise Unprocessable(f"design: the levels of ladder {design.ladder!r} come from the clip set's manifest "
                            f"(its clips' ladder and level), and there is none to read them from: build the clip "
                            f"set first (`animstudy clips build --config FILE`) or name its file in [clips] set")
    return design


def _build_comparisons(session: Session, study: Study, media: RenderManifest, design: Design,
                       media_dir: Path | None, clips_dir: Path | None,
                       animations: Collection[str] | None = None,
                       given: stimulus_sets.SetContent | None = None) -> Design:
    """The study's stimuli, comparisons and stimulus set for ``design`` (replacing any it had), from the clips of
    ``animations`` (default: all); returns the design :func:`settled` against the clip set, to be stored."""
    if study.opened_at is not None:  # its set is pinned
        raise Conflict(f"study {study.slug!r} has been open: what it shows is pinned")
    design = settled(design, clips_dir)
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
    return design


def show_design(session: Session, study: Study, media: RenderManifest, media_dir: Path | None,
                clips_dir: Path | None) -> Study:
    """A draft's comparisons and stimulus set for its own design over ``media`` (a study created through the API
    with inline ``[clips]``, once its build job has rendered them)."""
    if study.state != StudyState.draft:
        raise Conflict(f"study {study.slug!r} is {study.state}, no longer a draft")
    design = _build_comparisons(session, study, media, Design.model_validate(study.design), media_dir, clips_dir)
    study.design = design.model_dump()
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


def revision(study: Study, changes: Mapping[str, Any], media: RenderManifest | None = None) -> StudyFile:
    """The study file that a partial study file makes of the study's (sections are merged into the current ones):
    ``screening`` at any time (it changes the analysis, not what participants see); ``title``, ``texts``,
    ``scale``, ``questions`` and ``recruitment`` until the study first opens; ``design`` only while it is a draft
    that never opened and ``media``, the render manifest, is given.  Otherwise 409: participants saw it as it is.
    An invalid result raises pydantic's ValidationError (the API answers 422).  Nothing is stored."""
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
    if isinstance(changes.get("design"), dict) and "levels" not in changes["design"]:
        current["design"]["levels"] = None  # filled in again from the clip set when the design is rebuilt
    updated = StudyFile.model_validate(current)
    if redesigns(study, updated) and (study.state != StudyState.draft or media is None):
        raise Conflict("the design can change only while the study is a draft")
    return updated


def redesigns(study: Study, updated: StudyFile) -> bool:
    """Whether ``updated`` changes the study's design, so that its comparisons are built anew."""
    # designs stored before a field existed compare equal; levels are the clip set's, filled in by a rebuild
    return (updated.design.model_copy(update={"levels": None})
            != Design.model_validate(study.design).model_copy(update={"levels": None}))


def revise_study(session: Session, study: Study, updated: StudyFile, media: RenderManifest | None = None,
                 media_dir: Path | None = None, clips_dir: Path | None = None,
                 animations: Collection[str] | None = None) -> Study:
    """Store ``updated`` (a :func:`revision` of the study), rebuilding the comparisons over ``media`` when the design
    changed.  What showed the old comparisons goes first: :func:`server.participants.service.update_study`."""
    if redesigns(study, updated):
        assert media is not None  # revision refuses a redesign without it
        design = _build_comparisons(session, study, media, updated.design, media_dir, clips_dir, animations)
        updated = updated.model_copy(update={"design": design})
    else:  # the same design: its levels as they were settled
        stored = Design.model_validate(study.design)
        updated = updated.model_copy(update={"design": updated.design.model_copy(update={"levels": stored.levels})})
    for key, value in _columns(updated).items():
        setattr(study, key, value)
    session.commit()
    return study


def check_deletable(study: Study) -> None:
    """409 unless ``study`` is a draft that never opened: only those can be deleted."""
    if study.state != StudyState.draft or study.opened_at is not None:
        raise Conflict(f"study {study.slug!r} is {study.state}; only a draft that never opened can be deleted")


def remove_study(session: Session, study: Study, settings: Settings) -> None:
    """A draft that never opened, with its uploaded files (their rows go with the study).  Its pilot sessions go
    first: :func:`server.participants.service.delete_study`."""
    check_deletable(study)
    study_id = study.id
    session.delete(study)
    session.commit()
    shutil.rmtree(settings.study_assets_dir(study_id), ignore_errors=True)


def comparison_ids(study: Study) -> ComparisonIds:
    """The ids of the study's test, catch and practice comparisons, in their order."""
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


def export_columns(study: Study) -> list[str]:
    """The fixed columns, with one per question of the study (its id) before ``answered_at`` and one per accepted
    URL parameter (its name, e.g. ``PROLIFIC_PID``) at the end."""
    base = list(EXPORT_COLUMNS)
    at = base.index(QUESTIONS_BEFORE)
    return base[:at] + [q["id"] for q in study.questions] + base[at:] + list(study.recruitment["parameters"])


def pairs_in_use(session: Session, clip_ids: Collection[str]) -> list[tuple[str, str]]:
    """(left clip, right clip) of every pair video some study shows (rendering must keep them), as far as both
    clips are among ``clip_ids`` (the clip set being rendered).  Studies over other clip sets (a study file's
    ``[clips]``, another researcher's inline clips) show clips this one does not have: asking for those made
    every other build and render fail, naming the other study's animation (issue 36)."""
    reference, test = aliased(Stimulus), aliased(Stimulus)
    rows = session.execute(select(reference.clip_id, test.clip_id)
                           .join(Comparison, Comparison.reference_id == reference.id)
                           .join(test, Comparison.test_id == test.id)).all()
    return list(dict.fromkeys(p for r, t in rows if r in clip_ids and t in clip_ids for p in ((r, t), (t, r))))


def pairs_to_render(session: Session, design: Design, clips_dir: Path, media_dir: Path) -> list[tuple[str, str]]:
    """The pair videos to have when ``design`` is added: the pairs every study in the database shows, the ones
    rendered before (e.g. by `animstudy render --study` of a study not created yet) as far as the clip set still
    has their clips — adding a study removes nothing — and the pairs ``design`` needs."""
    index = clip_set_index(clips_dir)
    clip_ids = set(index.values())
    before = [p for p in rendered_pairs(media_dir) if set(p) <= clip_ids]
    return list(dict.fromkeys([*pairs_in_use(session, clip_ids), *before, *required_pairs(design, index)]))


def screening_rules(study: Study) -> Screening:
    """The study's ``[screening]`` (NULL before migration 0009: the catch-trial rule alone)."""
    return Screening.model_validate(study.screening or {})


