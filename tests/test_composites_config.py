"""Composite animations in clip-set files (issue 39): the bad input of the issue is a ConfigError naming the field,
and nothing is built; a good file reads into takes and composites, each condition applying where it says."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from anim_core.clips.build import ConfigError
from server.clipset.config import load_config

HEAD = """
fps = 30
[animations.walk]
kind = "gait"
source = "mocap/cmu/12_03_walk.bvh.gz"
frames = [1, 565]
[animations.idle]
kind = "idle"
source = "mocap/cmu/113_21_idle_30fps.bvh.gz"
frames = [0, 119]
[animations.travelling]
kind = "gait"
source = "mocap/cmu/09_11_run.bvh.gz"
frames = [1, 165]
in_place = false
"""
CONDITIONS = """
[[conditions]]
id = "keyframe"
method = "keyframe"
[[conditions]]
id = "crossfade250"
method = "crossfade"
params = { duration_ms = 250 }
"""


def _load(tmp_path: Path, composite: str, conditions: str = CONDITIONS):
    path = tmp_path / "set.toml"
    path.write_text(HEAD + composite + conditions, encoding="utf-8")
    return load_config(path)


def test_a_sequence_and_layers_read(tmp_path: Path) -> None:
    config = _load(tmp_path, """
[animations.idle_walk]
sequence = [{ animation = "idle", seconds = 2 }, { animation = "walk", seconds = 1.5 }]
[animations.walk_arms]
base = "walk"
layers = [{ animation = "idle", joints = "arms", mode = "additive", reference_pose = "rest" }]
""")
    assert set(config.animations) == {"walk", "idle", "travelling"}
    seq, lay = config.composites["idle_walk"], config.composites["walk_arms"]
    assert seq.form == "sequence" and seq.segments == (("idle", 2.0), ("walk", 1.5)) and seq.root_motion is None
    assert lay.form == "layered" and lay.base == "walk" and lay.layers[0].joints == "arms"
    by_id = {c.id: c for c in config.conditions}
    assert by_id["crossfade250"].applies("sequence") and not by_id["crossfade250"].applies("take")
    assert all(by_id["keyframe"].applies(f) for f in ("take", "sequence", "layered"))


@pytest.mark.parametrize(("composite", "field"), [
    ('sequence = [{ animation = "idle", seconds = 2 }, { animation = "jump", seconds = 2 }]', "sequence #2 animation"),
    ('sequence = [{ animation = "idle", seconds = -2 }, { animation = "walk", seconds = 2 }]', "sequence #1 seconds"),
    ('sequence = [{ animation = "idle", seconds = 0 }, { animation = "walk", seconds = 2 }]', "sequence #1 seconds"),
    ('sequence = [{ animation = "idle", seconds = 1e9 }, { animation = "walk", seconds = 2 }]', "sequence #1 seconds"),
    ('sequence = [{ animation = "idle", seconds = 2 }, { animation = "walk", seconds = 0.01 }]', "sequence #2 seconds"),
    ('sequence = [{ animation = "idle", seconds = "2" }, { animation = "walk", seconds = 2 }]', "sequence #1 seconds"),
    ('sequence = [{ animation = "idle", seconds = 2 }]', "sequence"),
    ('sequence = [{ animation = "walk", seconds = 2 }, { animation = "travelling", seconds = 2 }]', "root_motion"),
    ('root_motion = "fly"\nsequence = [{ animation = "walk", seconds = 2 }, { animation = "idle", seconds = 2 }]',
     "root_motion"),
    ('base = "walk"\nlayers = [{ animation = "idle", joints = "tail", mode = "override" }]', "layers #1 joints"),
    ('base = "walk"\nlayers = [{ animation = "idle", joints = "arms", mode = "blend" }]', "layers #1 mode"),
    ('base = "jump"\nlayers = [{ animation = "idle", joints = "arms", mode = "override" }]', "base animation"),
    ('base = "walk"\nlayers = [{ animation = "idle", joints = "arms", mode = "override", reference_pose = "rest" }]',
     "layers #1 reference_pose"),
])
def test_bad_composites_name_the_field(tmp_path: Path, composite: str, field: str) -> None:
    with pytest.raises(ConfigError, match=f"\\[animations.combo\\] {field}"):
        _load(tmp_path, f"[animations.combo]\n{composite}\n")


def test_crossfade_longer_than_the_shorter_segment(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=re.escape(
            "id = 'crossfade250' duration_ms: 250 ms is longer than the shortest segment of [animations.combo] "
            "(0.2 s)")):
        _load(tmp_path, '[animations.combo]\nsequence = [{ animation = "idle", seconds = 0.2 }, '
                        '{ animation = "walk", seconds = 2 }]\n')
    with pytest.raises(ConfigError, match="duration_ms"):
        _load(tmp_path, "", CONDITIONS.replace("duration_ms = 250", "duration_ms = -5"))
    with pytest.raises(ConfigError, match="duration_ms"):
        _load(tmp_path, "", CONDITIONS.replace("duration_ms = 250", "duration_ms = 100000"))


PARAMETRIC = CONDITIONS + """
[[conditions]]
id = "parametric50"
method = "parametric"
params = { weight = 0.5 }
"""


def test_a_blend_reads_and_parametric_applies_to_it_only(tmp_path: Path) -> None:
    config = _load(tmp_path, """
[animations.walk_run]
blend = ["walk", "run"]
[animations.run]
kind = "gait"
source = "mocap/cmu/09_11_run.bvh.gz"
frames = [1, 165]
""", PARAMETRIC)
    spec = config.composites["walk_run"]
    assert spec.form == "blend" and spec.blend == ("walk", "run") and spec.takes == ("walk", "run")
    by_id = {c.id: c for c in config.conditions}
    assert by_id["parametric50"].applies("blend")
    assert not any(by_id["parametric50"].applies(f) for f in ("take", "sequence", "layered"))
    assert by_id["keyframe"].applies("blend") and not by_id["crossfade250"].applies("blend")


@pytest.mark.parametrize(("composite", "field"), [
    ('blend = ["walk", "jump"]', "blend #2 animation"),
    ('blend = ["walk"]', "blend"),
    ('blend = ["walk", "travelling", "idle"]', "blend"),
    ('blend = "walk"', "blend"),
    ('blend = ["walk", "walk"]', "blend"),
    ('blend = ["walk", "idle"]', "blend"),  # the idle plays ping-pong: no cycle
    ('blend = ["walk", "travelling"]', "blend"),  # one in place, one travelling
    ('blend = ["walk", "travelling"]\nweight = 0.5', ": unknown field 'weight'"),  # the weight is the condition's
])
def test_bad_blends_name_the_field(tmp_path: Path, composite: str, field: str) -> None:
    with pytest.raises(ConfigError, match=f"\\[animations.combo\\]{'' if field[0] == ':' else ' '}{field}"):
        _load(tmp_path, f"[animations.combo]\n{composite}\n", PARAMETRIC)


@pytest.mark.parametrize("params", ["{ weight = 1.5 }", "{ weight = -0.1 }", "{ weight = true }", "{ }",
                                    '{ weight = 0.5, interp = "cubic" }'])
def test_bad_parametric_params_name_the_field(tmp_path: Path, params: str) -> None:
    field = "interp" if "interp" in params else "weight"
    with pytest.raises(ConfigError, match=f"id = 'parametric50': params of method 'parametric': {field}"):
        _load(tmp_path, "", PARAMETRIC.replace("{ weight = 0.5 }", params))
