"""A sequence's takes share one heading (issue 39, root motion kept consistent across a transition): every take is
turned to face +Z when it is read (a gait along its travel, anything else the way its hips face on average:
``anim_core.clips.build.source_from_bvh``), so takes recorded facing different ways switch without the character
turning on the spot.  Checked here on the CMU idle and walk with their files turned 90 and -60 degrees about the
vertical; the heading is computed in the test from the hips (tests/test_turning_takes.py's ``heading``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from anim_core.io.bvh import format_bvh, read_bvh
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from tests.test_turning_takes import _turned, heading

CONFIG = """
fps = 30

[character]
relocate = ["LHipJoint", "RHipJoint"]

[animations.walk]
kind = "gait"
source = "{walk}"
frames = [1, 565]
playback = "loop"
in_place = true

[animations.idle]
kind = "idle"
source = "{idle}"
frames = [0, 119]
playback = "pingpong"
in_place = false

[animations.idle_walk]
root_motion = "travel"
sequence = [{{ animation = "idle", seconds = 2 }}, {{ animation = "walk", seconds = 2 }}]

[[conditions]]
id = "keyframe"
method = "keyframe"

[[conditions]]
id = "crossfade250"
method = "crossfade"
params = {{ duration_ms = 250, curve = "smoothstep" }}
"""
TAKES = {"walk": ("mocap/cmu/12_03_walk.bvh.gz", -60.0), "idle": ("mocap/cmu/113_21_idle_30fps.bvh.gz", 90.0)}


def _build(data: Path, root: Path, turn: bool) -> dict:
    """The clip set over a data directory of links to ``data`` plus the two takes, turned or as they are."""
    own = root / ("turned" if turn else "plain")
    own.mkdir()
    for item in data.iterdir():
        (own / item.name).symlink_to(item)
    names = {}
    for name, (source, degrees) in TAKES.items():
        bvh = read_bvh(data / source)
        rot, pos = bvh.pose_arrays()
        if turn:
            rot, pos = _turned(rot, pos, np.full(len(rot), np.radians(degrees)))
        names[name] = f"{name}.bvh"
        (own / names[name]).write_text(format_bvh(bvh.with_poses(rot, pos)))
    path = root / f"{own.name}.toml"
    path.write_text(CONFIG.format(**names), encoding="utf-8")
    return {c.id: c for c in build_clip_set(own, load_config(path))}


@pytest.fixture(scope="module")
def built(data: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict]:
    root = tmp_path_factory.mktemp("heading")
    return _build(data, root, False), _build(data, root, True)


def _unwrap_deg(a: np.ndarray) -> np.ndarray:
    return np.degrees(np.unwrap(a))


@pytest.mark.parametrize("condition", ["keyframe", "crossfade250"])
def test_takes_filed_facing_other_ways_switch_without_turning(built: tuple[dict, dict], condition: str) -> None:
    plain, turned = built
    c = turned[f"idle_walk-{condition}"]
    sk = c.character.skeleton
    yaw = _unwrap_deg(heading(c.world_positions, sk))
    # The same sequence as from the files as recorded (rotation about the vertical changes nothing; seen: equal).
    same = _unwrap_deg(heading(plain[f"idle_walk-{condition}"].world_positions, sk))
    assert np.abs(yaw - same).max() < 1e-6, np.abs(yaw - same).max()
    # Both takes face +Z: the mean heading of each segment within 10 degrees of 0 (seen: -2.3 and -1.8; the walk's
    # hips sway about 17 degrees within a stride).  At a switch the hips turn by no more than a cut's pose jump
    # (seen: 2.2 and 3.0 degrees; the files were turned by 90 and -60), a crossfade's by no more than the takes'
    # own largest step from frame to frame (seen: 0.05 and 0.25 against the walk's 1.19).
    for segment in (slice(0, 60), slice(60, 120)):
        assert abs(yaw[segment].mean()) < 10.0, (segment, yaw[segment].mean())
    steps = np.abs(np.diff(np.append(yaw, yaw[0])))
    own = max(np.abs(np.diff(_unwrap_deg(heading(turned[f"{t}-keyframe"].world_positions, sk)))).max()
              for t in TAKES)
    for f in (0, 60):  # the switch into frame f: from frame f - 1
        assert steps[f - 1] <= (5.0 if condition == "keyframe" else own), (f, steps[f - 1], own)
