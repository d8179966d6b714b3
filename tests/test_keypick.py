"""Generic key picking (kind "other") on real CMU motion."""

import numpy as np
import pytest

from anim_core.io.bvh import clip_from_bvh, read_bvh
from anim_core.methods.hybrid import build_idle
from anim_core.methods.keypick import pick_keys

CMU_M = 0.0254 / 0.45


@pytest.fixture(scope="module")
def crouch(data):
    return clip_from_bvh(read_bvh(data / "mocap" / "cmu" / "115_06_crouch_first164.bvh.gz"), 1)


def error_mm(source, times):
    """Independent of pick_keys: sample the hybrid through ``times`` and compare joint positions to the source."""
    clip = build_idle(source, list(times))
    pose = clip.sample(source.times - times[0])
    a = source.skeleton.forward_kinematics(source.rotations, source.root_translation)[1]
    b = source.skeleton.forward_kinematics(pose.rotations, pose.root_translation)[1]
    return np.linalg.norm(a - b, axis=-1).max() * CMU_M * 1000


def test_fewer_keys_for_a_looser_tolerance_each_within_it(crouch):
    picked = {tol: pick_keys(crouch, tol, CMU_M) for tol in (0.05, 0.02, 0.01)}
    counts = [len(p.frames) for p in picked.values()]
    print({tol: (len(p.frames), round(p.error * 1000, 1)) for tol, p in picked.items()})
    assert counts == sorted(counts) and counts[0] < counts[-1]
    for tol, p in picked.items():
        assert p.frames[0] == 0 and p.frames[-1] == len(crouch.times) - 1
        assert error_mm(crouch, p.times) <= tol * 1000 + 1e-9
        assert len(p.frames) < len(crouch.times) / 5
    # The two end keys alone are not enough for this motion: the picking had to add keys.
    assert error_mm(crouch, (crouch.times[0], crouch.times[-1])) > 50


def test_unreachable_tolerance_is_a_clear_error(crouch):
    with pytest.raises(ValueError, match=r"3 keys reproduce the motion within [\d.]+ mm only, not 0.1 mm"):
        pick_keys(crouch, 0.0001, CMU_M, max_keys=3)
    with pytest.raises(ValueError, match="tolerance must be positive"):
        pick_keys(crouch, 0.0)
