"""One rule for animation names and condition ids (issue 23): clip-set files, uploads and study designs agree."""

from pathlib import Path

import pytest
from pydantic import TypeAdapter, ValidationError

from server.clipset.config import ConfigError, load_config
from server.errors import Unprocessable
from server.studies.design import Design, Ident
from server.studies.studyfile import load_study_file
from server.uploads.service import animation_name

ROOT = Path(__file__).resolve().parents[1]
GOOD = ("walk", "walk_2", "0run", "a" * 32)
BAD = ("walk-2", "Walk", "_walk", "a" * 33, "wälk", "walk 2")


def _clip_set_file(tmp_path: Path, animation: str, condition: str = "keyframe") -> Path:
    path = tmp_path / "set.toml"
    path.write_text(f'fps = 30\n\n[animations.{animation}]\nbvh = "mocap/cmu/12_03_walk.bvh.gz"\nkind = "gait"\n'
                    f'frames = [1, 40]\nkeys = [1, 20]\n\n[[conditions]]\nid = "{condition}"\nmethod = "keyframe"\n',
                    encoding="utf-8")
    return path


def _design(conditions: str = "hybrid0", animations: str = "walk") -> Design:
    """A valid design but for the one name given (two of each, so no comparison need repeat)."""
    return Design(conditions=[conditions, "other"], animations=[animations, "another"])


@pytest.mark.parametrize("name", BAD)
def test_every_reader_refuses_the_same_bad_names(name, tmp_path):
    for field in ("conditions", "animations"):
        with pytest.raises(ValidationError) as exc:
            _design(**{field: name})
        assert [e["type"] for e in exc.value.errors()] == ["string_pattern_mismatch"]
    with pytest.raises(Unprocessable):
        animation_name("motion.bvh", name)
    with pytest.raises(ConfigError):
        load_config(_clip_set_file(tmp_path, f'"{name}"'))
    with pytest.raises(ConfigError):
        load_config(_clip_set_file(tmp_path, "walk", name))


@pytest.mark.parametrize("name", GOOD)
def test_every_reader_accepts_the_same_good_names(name):
    assert _design(conditions=name, animations=name).conditions == [name, "other"]
    assert animation_name("motion.bvh", name) == name


def test_every_shipped_clip_set_and_study_name_is_valid():
    names = set()
    for toml in sorted((ROOT / "server" / "clipset").glob("*.toml")):
        config = load_config(toml)
        names |= set(config.animations) | {c.id for c in config.conditions}
    for toml in sorted((ROOT / "studies").glob("*.toml")):
        design = load_study_file(toml).design
        names |= {design.reference, *design.conditions, *design.animations}
    assert names, "no names found"
    for name in sorted(names):
        TypeAdapter(Ident).validate_python(name)  # a design's names: raises if the rule refused one
