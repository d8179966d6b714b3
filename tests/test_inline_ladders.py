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
