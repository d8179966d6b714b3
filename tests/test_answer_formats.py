"""Answer formats (2AFC, same/different) and threshold designs (constant stimuli, QUEST+ staircases) of issue 38,
through the real session code and the API, over stand-in media of a `pps` ladder."""

from __future__ import annotations

import math
import random
import tempfile
import tomllib
from collections import Counter
from pathlib import Path

import pytest
from pydantic import ValidationError
from sqlalchemy import func, select

from server.errors import Unprocessable
from server.media.manifest import RenderedClip, RenderedPair, RenderManifest
from server.participants import service, staircase
from server.participants.models import ParticipantSession, Trial
from server.research.export import export_rows
from server.studies import scale
from server.studies.columns import EXPORT_COLUMNS
from server.studies.design import Design
from server.studies.ladder import ladder_fields, resolve
from server.studies.models import Study, StudyState
from server.studies.service import create_study, set_state
from server.studies.studyfile import StudyFile, StudyFileError, load_study_file, parse_study_text
from tests.server_fixtures import fake_name, study_file, vote, write_fake_media

REPO = Path(__file__).resolve().parents[1]
UPDATE_RATE = REPO / "studies" / "update-rate.toml"
LEVELS = (4, 6, 8, 12, 16, 24)
PPS = [f"pps{n}" for n in LEVELS]
LEVEL_OF = dict(zip(PPS, LEVELS, strict=True))  # the stand-in clip set's levels (its manifest says them)


def ladder_media(animations: tuple[str, ...] = ("walk", "run"), conditions: tuple[str, ...] = ("keyframe", *PPS)
                 ) -> RenderManifest:
    """A render manifest with opaque names for the reference and the pps levels of ``animations``."""
    clips = {}
    for a in animations:
        for c in conditions:
            cid = f"{a}-{c}"
            clips[cid] = RenderedClip(clip=cid, animation=a, condition=c, video=f"{fake_name(cid)}.mp4",
                                      poster=f"{fake_name(cid)}.jpg", frames=30, fps=30, width=160, height=120)
    pairs = [RenderedPair(left=x, right=y, video=f"{fake_name(f'{x}|{y}')}.mp4",
                          poster=f"{fake_name(f'{x}|{y}')}.jpg", frames=30, fps=30, width=324, height=120)
             for x, cx in clips.items() for y, cy in clips.items() if cx.animation == cy.animation]
    return RenderManifest(clips=clips, pairs=pairs)


def ladder_clip_manifest(folder: Path, animations: tuple[str, ...] = ("walk", "run"),
                         levels: dict[str, float] | None = None) -> Path:
    """A stand-in clip manifest (``manifest.json`` only, no arrays) of the reference and the pps levels of
    ``animations``, each level with its ``ladder`` and ``level`` fields (default :data:`LEVEL_OF`), as a built
    clip set's manifest has them; the clip ids are :func:`ladder_media`'s."""
    from server.clipset.manifest import ClipEntry, ClipManifest, write_json

    clips = []
    for a in animations:
        for c, level in [("keyframe", None), *(levels or LEVEL_OF).items()]:
            clips.append(ClipEntry(
                id=f"{a}-{c}", animation=a, kind="gait", condition=c, method="keyframe" if level is None
                else "update_rate", params={} if level is None else {"rate": level}, key_count=30, duration_s=1.0,
                fps=30, frames=30, playback="loop", in_place=True, root_speed_mps=1.0, metrics={}, source={},
                file=f"{a}-{c}.npz", ladder=None if level is None else "pps", level=level))
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "manifest.json", ClipManifest(clips=clips))
    return folder


def threshold_file(mode: str = "staircase", answer_format: str = "2afc", slug: str = "update-rate",
                   **design: object) -> StudyFile:
    fields = {"mode": mode, "ladder": "pps", "conditions": PPS, "animations": ["walk", "run"],
              **({"trials": 12} if mode == "staircase" else {}), "catch_trials": 1, **design}
    return study_file(Design.model_validate(fields), slug=slug, scale={"format": answer_format})


def make_threshold_study(db, file: StudyFile, media_dir: Path | None = None) -> Study:
    media = ladder_media()
    if media_dir is not None:
        write_fake_media(media_dir, media)
    with tempfile.TemporaryDirectory() as folder:  # read when the study is created (its levels, its set's metrics)
        clips_dir = ladder_clip_manifest(Path(folder))
        return set_state(db, create_study(db, media, file, media_dir=media_dir, clips_dir=clips_dir),
                         StudyState.open)


def observer(threshold: float, rng: random.Random, answer_format: str = "2afc", lapse: float = 0.02):
    """A planted observer: tells a level from the reference with a probability falling from 1 (far below
    ``threshold`` poses per second) to the guess rate (far above), 75 % correct in 2AFC at the threshold."""
    def answer(trial: Trial) -> str:
        c = trial.comparison
        if c.reference_id == c.test_id:
            p_detect = 0.0
        else:
            level = LEVEL_OF[c.test.condition]
            p_detect = 1 / (1 + math.exp(4 * (math.log(level) - math.log(threshold)) / 0.5))
        p_detect = lapse / 2 + (1 - lapse) * p_detect
        if answer_format == "2afc":
            p_right = 0.5 + 0.5 * p_detect
            side = trial.reference_side if rng.random() < p_right else scale.other_side(trial.reference_side)
            return side
        return "different" if rng.random() < p_detect else "same"
    return answer


def run_session(db, study: Study, answer) -> ParticipantSession:
    ps = service.start_session(db, study, None).session
    service.set_answers(db, ps, {"gamer": "no", "tech_savvy": "yes"})
    for index in range(ps.trials_total):
        trial = db.scalar(select(Trial).where(Trial.session_id == ps.id, Trial.index == index))
        service.cast_vote(db, ps, trial, answer(trial), 900, f"k{ps.id}{index}", {})
    return ps


# --- the formats -------------------------------------------------------------------------------------------------


def test_every_format_has_its_ids_once_and_defaults():
    assert scale.FORMAT_CHOICES["rating5"] == scale.CHOICES
    assert set(scale.ALL_CHOICES) == {*scale.CHOICES, "left", "right", "same", "different"}
    two = StudyFile.model_validate({**study_file().model_dump(), "scale": {"format": "2afc"}})
    assert two.scale.labels == ["The left one", "The right one"] and two.scale.question == "Which one is the original?"
    assert two.scale.choices() == ["left", "right"]
    assert StudyFile.model_validate(study_file().model_dump()).scale.format == "rating5"  # the default
    # scores and correctness, from the test's point of view
    assert scale.format_score("2afc", "left", "left") == -1 and scale.format_score("2afc", "right", "left") == 1
    assert scale.correct("2afc", "left", "left", same_clip=False) is True
    assert scale.correct("2afc", "right", "left", same_clip=False) is False
    assert scale.correct("2afc", "right", "left", same_clip=True) is None
    assert scale.correct("same_different", "same", "left", same_clip=True) is True
    assert scale.correct("same_different", "same", "left", same_clip=False) is False
    assert scale.correct("rating5", "equal", "left", same_clip=False) is None


@pytest.mark.parametrize(("text", "field"), [
    ('[scale]\nformat = "2afc"\nlabels = ["a", "b", "c"]', "labels"),
    ('[scale]\nformat = "same_different"\nlabels = ["only one"]', "labels"),
    ('[scale]\nformat = "3afc"', "scale.format"),
    ('[design]\nmode = "staircase"\nladder = "pps"\nconditions = ["pps4", "pps8", "pps16"]\ntrials = 20',
     "scale.format"),  # a rating scale cannot run a staircase
    ('[scale]\nformat = "2afc"\n[design]\nmode = "staircase"\nladder = "pps"\nconditions = ["pps", "pps4"]\n'
     'trials = 20', "conditions: the ladder's id 'pps' stands for all its levels"),
    ('[scale]\nformat = "2afc"\n[design]\nmode = "staircase"\nladder = "pps"\nconditions = ["pps4", "pps8", '
     '"pps16"]\ntrials = 20\nlevels = { pps4 = 4, pps8 = 8 }', "levels: one level for each condition"),
    ('[design]\nmode = "reference"\nconditions = ["hybrid0"]\nlevels = { hybrid0 = 1 }', "levels is for mode"),
    ('[scale]\nformat = "2afc"\n[design]\nmode = "staircase"\nladder = "pps"\nconditions = ["pps4", "pps8"]\n'
     'trials = 20', "at least 3 levels"),
    ('[scale]\nformat = "2afc"\n[design]\nmode = "staircase"\nladder = "pps"\nconditions = ["pps4", "pps8", '
     '"pps16"]', "trials"),
    ('[scale]\nformat = "2afc"\n[design]\nmode = "constant-stimuli"\nconditions = ["pps4", "pps8", "pps16"]',
     "ladder"),
    ('[scale]\nformat = "2afc"\n[design]\nmode = "staircase"\nladder = "pps"\ntrials = 20', "conditions"),
    ('[design]\nmode = "reference"\nconditions = ["hybrid0"]\nladder = "pps"', "ladder"),
])
def test_bad_formats_and_threshold_designs_name_the_field(text, field):
    base = UPDATE_RATE.read_text(encoding="utf-8").split("[scale]")[0]
    with pytest.raises(StudyFileError) as info:
        parse_study_text(base + text)
    assert any(field in e for e in info.value.errors), info.value.errors


def test_the_update_rate_study_file():
    from server.clipset.config import load_config

    study = load_study_file(UPDATE_RATE)
    assert study.scale.format == "2afc" and study.design.mode == "staircase" and study.design.ladder == "pps"
    assert study.design.trials_total() == 2 * 30 + 2
    with pytest.raises(ValueError, match="not known yet"):  # the levels are the clip set's
        study.design.level_order()
    clip_set = load_config(REPO / "server" / "clipset" / "update-rate.toml")
    design = resolve(study.design, ladder_fields(clip_set.conditions))
    assert list(design.level_order()) == PPS[::-1] and design.easiest() == "pps4"
    assert design.levels == LEVEL_OF
    assert tomllib.loads(UPDATE_RATE.read_text(encoding="utf-8"))["design"]["animations"] == ["walk", "run"]


def test_levels_come_from_the_clip_sets_ladder_fields_never_from_names(tmp_path):
    """The design's levels are the manifest's ``ladder``/``level`` fields: a condition named like a level is
    read at the level its clip says; one on another ladder (or on none) is refused naming the field and the
    condition; the ladder's id stands for all its levels; given levels must agree."""
    from server.media.plan import read_clip_set

    odd = {"pps4": 4, "pps6": 6, "pps12": 11.5, "fast": 30}  # pps12's clip says 11.5; "fast" is named otherwise
    fields = ladder_fields(read_clip_set(ladder_clip_manifest(tmp_path / "clips", levels=odd), read_arrays=False))
    assert fields["pps12"] == ("pps", 11.5) and fields["keyframe"] == (None, None)
    base = {"mode": "constant-stimuli", "ladder": "pps", "animations": ["walk"]}
    design = resolve(Design(**base, conditions=["pps4", "pps12", "fast"]), fields)
    assert design.levels == {"pps4": 4, "pps12": 11.5, "fast": 30}
    assert list(design.level_order()) == ["fast", "pps12", "pps4"] and design.easiest() == "pps4"
    whole = resolve(Design(**base, conditions=["pps"]), fields)
    assert whole.conditions == ["pps4", "pps6", "pps12", "fast"] and whole.trials_total() == 4 * 2 + 0
    refused = [
        (["pps4", "pps6", "keyframe2"], {}, "design.conditions: keyframe2 (not in the clip set) not a level of "
                                            "ladder 'pps'"),
        (["eps"], {"ladder": "eps"}, "design.conditions: 'eps' names ladder 'eps', which the clip set does not "
                                     "have (its ladders: pps)"),
        (["pps4", "pps6", "pps12"], {"practice": "hybrid1"}, "design.practice: hybrid1 (not in the clip set) is not "
                                                              "a level of ladder 'pps'"),
        (["pps4", "pps6", "keyframe"], {"reference": "hybrid0"}, "design.conditions: keyframe (on no ladder) not a "
                                                                  "level of ladder 'pps'"),
        (["pps4", "pps6", "pps12"], {"levels": {"pps4": 4, "pps6": 6, "pps12": 12}},
         "design.levels: pps12 is 12.0 in the design, 11.5 in the clip set"),
    ]
    for conditions, changes, message in refused:
        with pytest.raises(Unprocessable) as info:
            resolve(Design(**{**base, "conditions": conditions, **changes}), fields)
        assert message in info.value.detail, info.value.detail
    built = ladder_clip_manifest(tmp_path / "fewer", levels={"pps4": 4, "pps8": 8})
    other = ladder_fields(read_clip_set(built, read_arrays=False))
    with pytest.raises(Unprocessable, match=r"pps16 \(not in the clip set\)"):
        resolve(Design(**base, conditions=["pps4", "pps8", "pps16"]), other)


# --- the API -----------------------------------------------------------------------------------------------------


def test_the_page_gets_the_format_ids_and_a_vote_outside_them_is_refused(db, client, tmp_path):
    make_threshold_study(db, threshold_file(), tmp_path / "var" / "media")
    public = client.get("/api/v1/studies/update-rate").json()
    assert public["scale"]["format"] == "2afc" and public["scale"]["choices"] == ["left", "right"]
    assert public["trials_total"] == 2 * 12 + 1
    r = client.post("/api/v1/studies/update-rate/sessions", json={"consent": True})
    sid, headers = r.json()["session_id"], {"Authorization": f"Bearer {r.json()['token']}"}
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
    for bad in ("left_much", "same", "sideways"):
        r = vote(client, sid, headers, trial["trial_id"], bad)
        assert r.status_code == 422 and "choice" in r.text, r.text
    assert db.scalar(select(func.count()).select_from(service.Vote).where(service.Vote.session_id == sid)) == 0
    assert vote(client, sid, headers, trial["trial_id"], "left").status_code == 201
    # the thesis study (five-point) keeps its ids, and refuses the new ones
    thesis = client.get("/api/v1/studies/update-rate").json()["scale"]
    assert "choices" in thesis


def test_a_rating_study_refuses_2afc_answers(db, client, study):
    public = client.get("/api/v1/studies/thesis").json()["scale"]
    assert public["format"] == "rating5" and public["choices"] == list(scale.CHOICES)
    r = client.post("/api/v1/studies/thesis/sessions", json={"consent": True})
    sid, headers = r.json()["session_id"], {"Authorization": f"Bearer {r.json()['token']}"}
    trial = client.get(f"/api/v1/sessions/{sid}/next", headers=headers).json()
    assert vote(client, sid, headers, trial["trial_id"], "left").status_code == 422


def test_a_threshold_study_with_a_rating_scale_creates_nothing(db, client, researcher_headers):
    body = threshold_file().model_dump()
    body["scale"] = {"format": "rating5"}
    r = client.post("/api/v1/studies", json=body, headers=researcher_headers)
    assert r.status_code == 422 and "scale.format" in r.text, r.text
    assert db.scalar(select(func.count()).select_from(Study)) == 0


def test_a_staircase_never_tells_the_page_an_undecided_level(db, client, tmp_path):
    make_threshold_study(db, threshold_file(), tmp_path / "var" / "media")
    r = client.post("/api/v1/studies/update-rate/sessions", json={"consent": True})
    sid, headers = r.json()["session_id"], {"Authorization": f"Bearer {r.json()['token']}"}
    ps = db.get(ParticipantSession, sid)
    shown = []
    r = client.get(f"/api/v1/sessions/{sid}/next", headers=headers)
    while r.status_code == 200:
        trial = r.json()
        following = db.scalar(select(Trial).where(Trial.session_id == sid, Trial.index == trial["index"] + 1))
        if following is not None and staircase.undecided(ps, following):
            assert trial["preload_url"] is None
        shown.append(trial["video_url"])
        r = vote(client, sid, headers, trial["trial_id"], "left" if trial["index"] % 3 else "right")
        assert r.status_code == 201, r.text
        r = client.get(f"/api/v1/sessions/{sid}/next", headers=headers)
    assert r.status_code == 204 and len(shown) == 2 * 12 + 1


def _replayed(db, ps: ParticipantSession, design: Design) -> tuple[list[str | None], list[str | None]]:
    """(stored, replayed) level of every trial of a finished session (None: not a staircase trial)."""
    trials = sorted(ps.trials, key=lambda t: t.index)
    rows = []
    for t in trials:
        votes = db.scalar(select(service.Vote).where(service.Vote.trial_id == t.id))
        animation = t.comparison.reference.animation if staircase.undecided(ps, t) else None
        rows.append((animation, t.comparison.test.condition, votes.choice if votes else None, t.reference_side))
    stored = [row[1] if row[0] is not None else None for row in rows]
    return stored, staircase.replay(design, "2afc", rows)


def test_staircase_levels_follow_the_answers_and_replay_from_the_vote_log(db):
    study = make_threshold_study(db, threshold_file(trials=20))
    design = Design.model_validate(study.design)
    rng = random.Random(38)
    keen = run_session(db, study, observer(20, rng))  # tells even 16 poses per second from the original
    blind = run_session(db, study, lambda t: scale.other_side(t.reference_side))  # always wrong: sees nothing
    for ps in (keen, blind):
        stored, replayed = _replayed(db, ps, design)
        assert stored == replayed
        assert sum(s is not None for s in stored) == 2 * 20
        sides = Counter((t.comparison.reference.animation, t.reference_side) for t in ps.trials
                        if staircase.undecided(ps, t))
        assert set(sides.values()) == {10}  # balanced sides per staircase
    level = {c: v for c, v in design.level_order().items()}

    def last_levels(ps):
        return [level[t.comparison.test.condition] for t in sorted(ps.trials, key=lambda t: t.index)
                if staircase.undecided(ps, t)][-10:]
    # the keen observer is taken up the ladder (harder levels), the blind one down to the easiest
    assert sum(last_levels(keen)) / 10 > 12 and sum(last_levels(blind)) / 10 < 6
    # a catch trial (the easiest level) answered wrongly screens the blind participant out
    assert service.outcome(db, blind) == "screened_out" and service.outcome(db, keen) == "completed"


def test_staircase_export_has_format_ladder_level_and_correct(db):
    study = make_threshold_study(db, threshold_file(trials=8))
    ps = run_session(db, study, lambda t: t.reference_side)  # always the original: always correct
    rows = [r for r in export_rows(db, study) if r["session_id"] == ps.id]
    assert {"answer_format", "ladder", "level", "correct"} <= set(EXPORT_COLUMNS)
    assert len(rows) == 2 * 8 + 1 and all(set(r) >= {"answer_format", "ladder", "level", "correct"} for r in rows)
    assert {r["answer_format"] for r in rows} == {"2afc"} and {r["ladder"] for r in rows} == {"pps"}
    assert all(r["correct"] is True and r["level"] == LEVEL_OF[r["test_condition"]] for r in rows)
    assert all(r["score"] == -1 for r in rows)  # the reference's side: -1 from the test's point of view
    catch = [r for r in rows if r["catch"]]
    assert len(catch) == 1 and catch[0]["test_condition"] == "pps4"


def test_constant_stimuli_shows_every_level_on_both_sides(db):
    study = make_threshold_study(db, threshold_file("constant-stimuli", "same_different", repeats=2,
                                                    slug="constant"))
    ps = run_session(db, study, observer(10, random.Random(1), "same_different"))
    shown = Counter((t.comparison.reference.animation, t.comparison.test.condition, t.reference_side)
                    for t in ps.trials if t.comparison.kind == "test")
    catch = [t for t in ps.trials if t.comparison.kind == "catch"]
    assert len(catch) == 1 and catch[0].comparison.test.condition == "pps4"  # the easiest level
    assert shown == Counter({(a, c, s): 2 for a in ("walk", "run") for c in PPS for s in ("left", "right")})
    assert ps.trials_total == 2 * 6 * 2 * 2 + 1
    rows = list(export_rows(db, study))
    assert {r["answer_format"] for r in rows} == {"same_different"}
    assert all(r["correct"] == (r["choice"] == "different") for r in rows)


def test_the_data_dictionary_names_the_new_columns(client):
    text = client.get("/api/v1/data-dictionary").text
    for column in ("answer_format", "ladder", "level", "correct", "`same`, `different`"):
        assert column in text


def test_design_validation_of_threshold_modes():
    with pytest.raises(ValidationError, match="stands for all its levels"):
        Design(mode="constant-stimuli", ladder="pps", conditions=["pps4", "pps", "pps8"])
    with pytest.raises(ValidationError, match="drop levels"):
        Design(mode="constant-stimuli", ladder="pps", conditions=["pps"], levels={"pps4": 4})
    d = Design(mode="staircase", ladder="eps", conditions=["eps0_5", "eps2", "eps1"], trials=10,
               detectable_at="high", animations=["walk"], levels={"eps0_5": 0.5, "eps2": 2, "eps1": 1})
    assert list(d.level_order()) == ["eps0_5", "eps1", "eps2"] and d.easiest() == "eps2"
    assert d.trials_total() == 10 and d.pairs() == [("keyframe", c) for c in d.conditions]


@pytest.mark.parametrize("answer_format", ["2afc", "same_different"])
def test_results_and_exports_of_a_threshold_study_answer(db, client, researcher_headers, tmp_path, answer_format):
    """The researcher's endpoints never fail on a threshold study's votes (no 5xx), whatever they make of them."""
    study = make_threshold_study(db, threshold_file(answer_format=answer_format, trials=8), tmp_path / "var" / "media")
    study.owner_id = None
    db.commit()
    for threshold in (6, 12, 20):
        run_session(db, study, observer(threshold, random.Random(threshold), answer_format))
    for path in ("results", "export.csv", "export.json", "export.sureal.json", "export.pwcmp.csv", "definition"):
        r = client.get(f"/api/v1/studies/update-rate/{path}", headers=researcher_headers)
        assert r.status_code == 200, (path, r.status_code, r.text[:300])
    thresholds = client.get("/api/v1/studies/update-rate/results", headers=researcher_headers).json()["thresholds"]
    assert thresholds["ladder"] == "pps"
    assert thresholds["animations"] if answer_format == "2afc" else thresholds["note"]
    header = client.get("/api/v1/studies/update-rate/export.csv", headers=researcher_headers).text.splitlines()[0]
    assert header.split(",")[-7:-3] == ["answer_format", "ladder", "level", "correct"]


def test_planted_observers_staircases_find_their_threshold():
    """QUEST+ over the update-rate ladder (40 trials) against planted observers of thresholds 7 and 14 poses per
    second (detection 50 % there): the posterior threshold lands near the planted one, and the two apart."""
    design = Design(mode="staircase", ladder="pps", conditions=PPS, trials=40, animations=["walk"], levels=LEVEL_OF)
    found = {}
    for planted in (7.0, 14.0):
        def detect(level: float, planted: float = planted) -> float:
            return 0.01 + 0.98 / (1 + (level / planted) ** 6)
        estimates = [staircase.estimate(design, "2afc", staircase.simulate(design, "2afc", detect,
                                                                           random.Random(seed)))["threshold_level"]
                     for seed in range(8)]
        found[planted] = sorted(estimates)[len(estimates) // 2]
        near = sum(planted / 1.5 <= e <= planted * 1.5 for e in estimates)
        assert near >= 7, (planted, estimates)
    assert found[7.0] < found[14.0]


def _rows(animation: str, level: int, trials: int, correct: int) -> list[dict]:
    return [{"practice": False, "catch": False, "outcome": "completed", "animation": animation,
             "test_condition": f"pps{level}", "level": level, "correct": k < correct} for k in range(trials)]


def test_threshold_results_name_the_cheapest_level_nobody_tells_from_the_reference():
    """Levels 4-8 always told apart, 12-24 at chance over 200 answers each (upper bounds near 57 %), the cost
    rising with the level: the cheapest indistinguishable level is pps12, every level is on the Pareto set but
    the dominated ones, and practice, catch and screened-out answers are left out."""
    from server.research.thresholds import threshold_results

    rows = [r for level in (4, 6, 8) for r in _rows("walk", level, 60, 60)]
    rows += [r for level in (12, 16, 24) for r in _rows("walk", level, 200, 100)]
    rows += [{**r, "catch": True} for r in _rows("walk", 12, 50, 0)]
    rows += [{**r, "outcome": "screened_out"} for r in _rows("walk", 16, 50, 0)]
    clips = [{"animation": "walk", "condition": f"pps{n}", "metrics": {"cost_ms_per_1000": n / 10}} for n in LEVELS]
    design = {"mode": "constant-stimuli", "ladder": "pps"}
    out = threshold_results(design, "2afc", rows, clips)
    (walk,) = out["animations"]
    assert walk["cheapest_indistinguishable"]["condition"] == "pps12"
    by = {p["condition"]: p for p in walk["points"]}
    assert by["pps12"]["detection"]["trials"] == 200 and by["pps16"]["detection"]["trials"] == 200
    assert by["pps4"]["detection"]["p"] == 1.0 and not by["pps4"]["indistinguishable"]
    assert [p["condition"] for p in walk["points"] if p["indistinguishable"]] == ["pps12", "pps16", "pps24"]
    assert [p["condition"] for p in walk["points"] if p["pareto"]] == ["pps4", "pps12"]
    assert walk["fit"] is not None and out["svg"].startswith("<svg")
    assert threshold_results({"mode": "reference"}, "rating5", rows, clips) is None
    assert threshold_results(design, "same_different", rows, clips)["note"].startswith("thresholds are fitted")


def test_a_study_is_created_over_its_clip_sets_levels_and_refused_when_they_disagree(db, tmp_path):
    """``conditions = ["pps"]`` is every level of the clip set's ladder; the study stores the levels its clips
    carry (pps12 at 11.5 here, whatever its name says) and exports them; a design whose conditions are not levels
    of its ladder by the manifest is refused naming the condition, and nothing is created."""
    import json

    media = ladder_media()
    clips = ladder_clip_manifest(tmp_path / "clips", levels={**LEVEL_OF, "pps12": 11.5})
    study = create_study(db, media, threshold_file("constant-stimuli", conditions=["pps"], slug="whole"),
                         clips_dir=clips)
    design = Design.model_validate(study.design)
    assert design.conditions == PPS and design.levels == {**LEVEL_OF, "pps12": 11.5}
    assert {c.test.condition for c in study.comparisons if c.kind == "test"} == set(PPS)
    set_state(db, study, StudyState.open)
    run_session(db, study, lambda t: t.reference_side)
    assert {r["level"] for r in export_rows(db, study) if r["test_condition"] == "pps12"} == {11.5}

    wrong = ladder_clip_manifest(tmp_path / "wrong")
    manifest = json.loads((wrong / "manifest.json").read_text())
    for c in manifest["clips"]:
        if c["condition"] == "pps8":
            c["ladder"] = "eps"
    (wrong / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(Unprocessable, match=r"design.conditions: pps8 \(level 8 of ladder 'eps'\) not a level of "
                                             r"ladder 'pps' by the clip set's manifest"):
        create_study(db, media, threshold_file("constant-stimuli", slug="refused"), clips_dir=wrong)
    db.rollback()
    assert db.scalar(select(Study.id).where(Study.slug == "refused")) is None


def test_a_drafts_changed_design_is_settled_again_against_its_clip_set(db, client, researcher_headers, tmp_path):
    """Through the API: a draft created with ``conditions = ["pps"]`` over the server's clip set stores every
    level with the manifest's values; a new design is settled again (its levels from the manifest, a condition the
    clip set lacks refused naming it), and a change elsewhere keeps the levels."""
    var = tmp_path / "var"
    write_fake_media(var / "media", ladder_media())
    ladder_clip_manifest(var / "clips", levels={**LEVEL_OF, "pps12": 11.5})
    body = threshold_file("constant-stimuli", conditions=["pps"], slug="draft").model_dump(mode="json")
    r = client.post("/api/v1/studies", json=body, headers=researcher_headers)
    assert r.status_code == 201, r.text

    def design() -> dict:
        return client.get("/api/v1/studies/draft/definition", headers=researcher_headers).json()["design"]

    assert design()["conditions"] == PPS and design()["levels"] == {**LEVEL_OF, "pps12": 11.5}
    r = client.patch("/api/v1/studies/draft", json={"design": {"conditions": ["pps4", "pps8", "pps12"]}},
                     headers=researcher_headers)
    assert r.status_code == 200, r.text
    assert design()["levels"] == {"pps4": 4, "pps8": 8, "pps12": 11.5}
    r = client.patch("/api/v1/studies/draft", json={"title": "Renamed", "design": {"repeats": 1}},
                     headers=researcher_headers)
    assert r.status_code == 200, r.text
    assert design()["levels"] == {"pps4": 4, "pps8": 8, "pps12": 11.5}
    r = client.patch("/api/v1/studies/draft", json={"design": {"conditions": ["pps4", "pps8", "pps10"]}},
                     headers=researcher_headers)
    assert r.status_code == 422 and "pps10 (not in the clip set) not a level of ladder 'pps'" in r.text, r.text
    assert design()["conditions"] == ["pps4", "pps8", "pps12"]
