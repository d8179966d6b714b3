"""Ladders given inline in a study file (``[[clips.ladders]]``, issue 38): read by the clip-set file's own ladder
code (one condition per level, with its ladder and level), refused with the same errors naming the table, the
ladder, the field and the level; through the API a 422 with nothing created."""

from __future__ import annotations

from pathlib import Path

import pytest

from anim_core.clips.build import ConfigError
from server.clipset.config import inline_config
from server.studies.studyfile import StudyFileError, parse_study_text

UPDATE_RATE = Path(__file__).resolve().parents[1] / "studies" / "update-rate.toml"
INLINE = '''
[clips]
conditions = [{ id = "keyframe", method = "keyframe" }]

[[clips.ladders]]
id = "pps"
method = "update_rate"
levels = LEVELS
'''


def study_text(levels: str = "[4, 6, 8, 12, 16, 24]", slug: str = "inline-ladder") -> str:
    text = UPDATE_RATE.read_text().replace('slug = "update-rate"', f'slug = "{slug}"')
    return text + INLINE.replace("LEVELS", levels)


def test_a_study_file_gives_a_ladder_inline():
    study = parse_study_text(study_text(), "inline.toml")
    assert study.clips is not None and study.clips.ladders is not None
    config = inline_config(study.clips.animations, study.clips.conditions, "inline.toml", study.clips.ladders)
    got = [(c.id, c.method, c.ladder, c.level, c.params_dict()) for c in config.conditions]
    assert got == [("keyframe", "keyframe", None, None, {})] + [
        (f"pps{r}", "update_rate", "pps", r, {"rate": r}) for r in (4, 6, 8, 12, 16, 24)]
    # without inline conditions the ladder is added to the default file's
    default = inline_config(None, None, "x", study.clips.ladders)
    assert [c.id for c in default.conditions][-6:] == ["pps4", "pps6", "pps8", "pps12", "pps16", "pps24"]
    assert "keyframe" in [c.id for c in default.conditions]


@pytest.mark.parametrize("levels, message", [
    ("[4, 8]", r"\[\[clips.ladders\]\] id = 'pps' levels: a list of at least 3 levels, got \[4, 8\]"),
    ("[4, 12, 8]", r"\[\[clips.ladders\]\] id = 'pps' levels: level 8 is out of order"),
    ("[4, 8, 8, 12]", r"\[\[clips.ladders\]\] id = 'pps' levels: level 8 is repeated"),
    # a level making the same clip as the reference: an update rate at the clips' own rate
    ("[12, 24, 30]", r"\[\[clips.ladders\]\] id = 'pps' level 30: rate 30 poses/s is at or above the clips' own "
                     r"rate of 30 keys/s"),
])
def test_bad_inline_ladders_are_refused_as_in_a_clip_set_file(levels, message):
    study = parse_study_text(study_text(levels), "inline.toml")
    assert study.clips is not None
    with pytest.raises(ConfigError, match=message):
        inline_config(study.clips.animations, study.clips.conditions, "inline.toml", study.clips.ladders)


def test_inline_ladders_and_a_clip_set_file_are_not_both_given():
    text = study_text().replace("[clips]\n", '[clips]\nset = "../server/clipset/update-rate.toml"\n')
    with pytest.raises(StudyFileError, match=r"either set .* or conditions/ladders/animations inline"):
        parse_study_text(text, "x.toml")


@pytest.mark.parametrize("levels, message", [
    ("[4, 8]", "[[clips.ladders]] id = 'pps' levels: a list of at least 3 levels"),
    ("[4, 12, 8]", "[[clips.ladders]] id = 'pps' levels: level 8 is out of order"),
    ("[4, 8, 8, 12]", "[[clips.ladders]] id = 'pps' levels: level 8 is repeated"),
    ("[12, 24, 30]", "[[clips.ladders]] id = 'pps' level 30: rate 30 poses/s is at or above"),
])
def test_the_api_refuses_a_bad_inline_ladder_and_creates_nothing(client, researcher_headers, levels, message):
    for path, body in (("/api/v1/studies/file", {"content": study_text(levels).encode()}),
                       ("/api/v1/studies", {"json": parse_study_text(study_text(levels)).model_dump(mode="json")})):
        r = client.post(path, headers=researcher_headers, **body)
        assert r.status_code == 422, r.text
        assert message in r.json()["detail"], r.text
    assert client.get("/api/v1/studies", headers=researcher_headers).json() == []


@pytest.mark.slow  # about half a minute: builds 4 clips and renders their small videos
def test_study_create_builds_a_ladder_given_inline(tmp_path, monkeypatch, capsys, data):
    """`animstudy study create` of a staircase study whose ladder is given inline and named by its id in the
    design: the levels are built from [[clips.ladders]], rendered, and the study stores them with their values
    from the built manifest."""
    from server import cli
    from server.cli.study import _study_session
    from server.config import Settings
    from server.stimuli import service as stimulus_sets
    from server.studies import service

    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    monkeypatch.setenv("ANIMSTUDY_DATA_DIR", str(data))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "inline-ladder-secret-0123456789abcdef01")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    text = study_text("[4, 8, 12]").replace('animations = ["walk", "run"]', 'animations = ["walk"]').replace(
        "trials = 30 ", "trials = 6 ").replace("catch_trials = 2", "catch_trials = 1")
    study = tmp_path / "inline-ladder.toml"
    study.write_text(text)
    assert cli.main(["study", "validate", str(study)]) == 0
    assert cli.main(["study", "create", str(study), "--width", "96", "--height", "72", "--no-shadows"]) == 0
    out = capsys.readouterr().out
    assert "[1/1] walk: building 4 clips" in out, out
    with _study_session(Settings.from_env()) as db:
        created = service.get_study(db, "inline-ladder")
        content = stimulus_sets.content_of(created.stimulus_set)
        design = created.design
    assert design["conditions"] == ["pps4", "pps8", "pps12"]
    assert design["levels"] == {"pps4": 4, "pps8": 8, "pps12": 12}
    assert {(c.condition, c.method) for c in content.clips} == {
        ("keyframe", "keyframe"), ("pps4", "update_rate"), ("pps8", "update_rate"), ("pps12", "update_rate")}


def test_study_create_refuses_an_inline_level_that_builds_the_same_clip_as_another(tmp_path, monkeypatch, capsys,
                                                                                   data):
    """A bone-LOD depth holding exactly the joints another inline condition holds (depth 7: the fingers) is found
    when the clips the design shows are built: `study create` fails naming the ladder and the level, and no study
    is created."""
    from server import cli
    from server.cli.study import _study_session
    from server.config import Settings
    from server.studies.models import Study

    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    monkeypatch.setenv("ANIMSTUDY_DATA_DIR", str(data))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "inline-ladder-secret-0123456789abcdef01")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    head, design = study_text().split("[design]")
    text = head.split("[scale]")[0] + '''
[design]
conditions = ["fingers", "depth5", "depth6", "depth7"]
animations = ["walk"]
''' + "[recruitment]" + design.split("[recruitment]")[1]
    text = text.replace(INLINE.replace("LEVELS", "[4, 6, 8, 12, 16, 24]"), '''
[clips]
conditions = [{ id = "keyframe", method = "keyframe" },
              { id = "fingers", method = "bone_lod", params = { joints = "fingers" } }]

[[clips.ladders]]
id = "depth"
method = "bone_lod"
levels = [5, 6, 7]
''')
    study = tmp_path / "same.toml"
    study.write_text(text)
    assert cli.main(["study", "create", str(study), "--width", "96", "--height", "72", "--no-shadows"]) == 2
    err = capsys.readouterr().err
    assert ("[[ladders]] id = 'depth' level 7 (bone_lod): on animation 'walk' it makes the same clip as condition "
            "'fingers'") in err, err
    with _study_session(Settings.from_env()) as db:
        assert db.query(Study).count() == 0
