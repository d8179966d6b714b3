"""Composite animations given inline in a study file (issue 39): ``[clips.animations.<name>]`` holds takes and
composites as a clip-set file's ``[animations]`` does (one schema: server/clipset/composites.py), `study create`
builds and renders the composite's clips, and bad input names the inline field.  Expected values come from the
study text written here, never from the code under test."""

from __future__ import annotations

from pathlib import Path

import pytest

from anim_core.clips.build import ConfigError
from server import cli
from server.cli.study import _study_session
from server.clipset.config import inline_config
from server.config import Settings
from server.stimuli import service as stimulus_sets
from server.studies import service

FUTURE_WORK = Path(__file__).resolve().parents[1] / "studies" / "future-work.toml"
TAKES = {
    "idle": {"kind": "idle", "source": "mocap/cmu/113_21_idle_30fps.bvh.gz", "frames": [0, 119]},
    "walk": {"kind": "gait", "source": "mocap/cmu/12_03_walk.bvh.gz", "frames": [1, 565]},
}
CONDITIONS = [{"id": "keyframe", "method": "keyframe"},
              {"id": "crossfade250", "method": "crossfade", "params": {"duration_ms": 250}}]
INLINE = '''[clips.animations.idle]
kind = "idle"
source = "mocap/cmu/113_21_idle_30fps.bvh.gz"
frames = [0, 119]

[clips.animations.walk]
kind = "gait"
source = "mocap/cmu/12_03_walk.bvh.gz"
frames = [1, 565]

[clips.animations.idle_walk]
sequence = [{ animation = "idle", seconds = 1 }, { animation = "walk", seconds = 1 }]
root_motion = "in_place"

[[clips.conditions]]
id = "keyframe"
method = "keyframe"

[[clips.conditions]]
id = "crossfade250"
method = "crossfade"
params = { duration_ms = 250 }
'''


def study_text(slug: str, condition: str = "crossfade250") -> str:
    """future-work.toml showing the inline sequence idle_walk in ``condition``."""
    text = FUTURE_WORK.read_text().replace('slug = "future-work"', f'slug = "{slug}"')
    text = text.replace('animations = ["walk", "crouch"]', 'animations = ["idle_walk"]').replace(
        'conditions = ["hybrid0", "hybrid_ik0", "hybrid_c2_0"]', f'conditions = ["{condition}"]')
    return text.replace('[clips]\nset = "../server/clipset/conditions16.toml"\n', INLINE)


def test_inline_animations_hold_composites() -> None:
    config = inline_config({**TAKES, "idle_walk": {"sequence": [{"animation": "idle", "seconds": 1},
                                                                {"animation": "walk", "seconds": 1}],
                                                   "root_motion": "in_place"}}, CONDITIONS, "s.toml")
    assert set(config.animations) == {"idle", "walk"}
    assert config.composites["idle_walk"].segments == (("idle", 1.0), ("walk", 1.0))


@pytest.mark.parametrize(("animations", "message"), [
    ({**TAKES, "combo": {"sequence": [{"animation": "idle", "seconds": 1}, {"animation": "jump", "seconds": 1}]}},
     "s.toml [clips.animations.combo] sequence #2 animation: 'jump' is no take"),
    ({**TAKES, "combo": {"sequence": [{"animation": "idle", "seconds": 0.1}, {"animation": "walk", "seconds": 1}],
                         "root_motion": "in_place"}},
     "id = 'crossfade250' duration_ms: 250 ms is longer than the shortest segment of [animations.combo]"),
    ({**TAKES, "combo": {"blend": ["walk", "idle"]}}, "s.toml [clips.animations.combo] blend: both takes loop"),
    ({"combo": {"base": "walk", "layers": []}}, "s.toml [clips.animations.combo] base animation"),
])
def test_bad_inline_composites_name_the_field(animations: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", "\\[").replace("]", "\\]")):
        inline_config(animations, CONDITIONS, "s.toml")


@pytest.mark.slow  # about half a minute: the sequence's two 2 s clips built and rendered small
def test_study_create_builds_a_sequence_given_inline(tmp_path, monkeypatch, capsys, data):
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))
    monkeypatch.setenv("ANIMSTUDY_DATA_DIR", str(data))
    monkeypatch.setenv("ANIMSTUDY_SECRET_KEY", "inline-composite-secret-0123456789abcdef")
    monkeypatch.delenv("ANIMSTUDY_DATABASE_URL", raising=False)
    monkeypatch.delenv("DATABASE_URL", raising=False)
    study = tmp_path / "sequence.toml"
    study.write_text(study_text("sequence"))
    assert cli.main(["study", "validate", str(study)]) == 0
    assert cli.main(["study", "create", str(study), "--width", "64", "--height", "48", "--no-shadows"]) == 0
    out = capsys.readouterr().out
    assert "idle_walk: composite (sequence) of idle, walk" in out and "clips: 2 built into the clip set" in out
    with _study_session(Settings.from_env()) as db:
        content = stimulus_sets.content_of(service.get_study(db, "sequence").stimulus_set)
        assert {(c.animation, c.condition, c.method) for c in content.clips} == {
            ("idle_walk", "keyframe", "keyframe"), ("idle_walk", "crossfade250", "crossfade")}
        assert all("transition_foot_skate_ratio" in c.metrics for c in content.clips)
        assert stimulus_sets.missing(content, Settings.from_env().media_dir) == []
    # a condition that builds no clip of a sequence is refused, named
    wrong = tmp_path / "wrong.toml"
    wrong.write_text(study_text("wrong", "keyframe").replace('conditions = ["keyframe"]', 'conditions = ["hybrid0"]')
                     .replace('id = "crossfade250"\nmethod = "crossfade"\nparams = { duration_ms = 250 }',
                              'id = "hybrid0"\nmethod = "hybrid"\nparams = { increment = 0 }'))
    assert cli.main(["study", "create", str(wrong)]) == 2
    assert "design.conditions: hybrid0 build no clip of 'idle_walk' (a sequence)" in capsys.readouterr().err
