"""The keys runtime: every clip posed from its own keys, against the numpy reference; memory, validation, LOD."""

import numpy as np
import pytest

from anim_core import quat as Q
from anim_core import runtime as R
from anim_core.crowd import CrowdBuffers
from anim_core.hybrid import SpringClip, SquadClip
from server.clipset.build import build_clip_set


@pytest.fixture(scope="module")
def clips(data):
    return build_clip_set(data)


@pytest.fixture(scope="module")
def runtimes(clips):
    return {c.id: R.runtime_for(c.clip) for c in clips}


def test_keys_runtime_matches_the_reference_for_every_clip(clips, runtimes, rng):
    t = rng.uniform(-5.0, 15.0, 600)  # negative, several periods, both ping-pong directions
    assert len(clips) == 16
    for c in clips:
        rt = runtimes[c.id]
        ref_rot, ref_pos = R.exact_global(c.clip, t)
        out = rt.pose(t)
        angle = np.degrees(Q.quat_angle(out.rotations.astype(np.float64), ref_rot)).max()
        distance = np.linalg.norm(out.positions - ref_pos, axis=-1).max()
        if isinstance(c.clip, SquadClip):
            # The fitted curve: within the error measured at build time (on a 240 Hz grid; random times may land
            # a little past the grid's worst sample) and always within the stated tolerance.
            assert 0 < rt.fit_error_deg <= R.FIT_TOLERANCE_DEG
            assert angle <= min(R.FIT_TOLERANCE_DEG, 1.05 * rt.fit_error_deg + 1e-3), f"{c.id}: {angle:.4f} deg"
            assert distance <= 0.005, f"{c.id}: {distance * 1000:.2f} mm"
        else:  # dense keys with nlerp, or the spring's exact slerp: float32 rounding only
            assert angle <= 2e-3, f"{c.id}: {angle:.5f} degrees"
            assert distance <= 1e-4, f"{c.id}: {distance * 1000:.3f} mm"
        parallel = rt.pose(t, parallel=True)
        assert np.array_equal(parallel.rotations, out.rotations)
        assert np.array_equal(parallel.positions, out.positions)


def test_a_mirrored_gait_stores_half_its_segments(clips, runtimes):
    gaits = [c for c in clips if c.method == "hybrid" and c.animation in ("walk", "run")]
    assert len(gaits) == 6
    for c in gaits:
        rt = runtimes[c.id]
        k = c.clip.n_keys
        assert rt.controls.shape[0] == 3 * (k // 2) + 1 and rt.seg_times.size == k // 2 + 1
        assert rt.mirror_src.shape == (c.clip.skeleton.n_joints,)
        assert rt.params[2] == pytest.approx(c.clip.duration / 2)
    idle = runtimes["idle-hybrid2"]
    assert idle.mirror_src.size == 0 and idle.controls.shape[0] == 3 * (5 - 1) + 1  # ping-pong: every segment


def test_runtime_bytes_are_the_arrays_the_runtime_holds(clips, runtimes):
    for c in clips:
        rt = runtimes[c.id]
        held = [v for v in vars(rt).values() if isinstance(v, np.ndarray)]
        assert rt.runtime_bytes == sum(a.nbytes for a in held)
        assert {id(a) for a in held} == {id(a) for a in rt.arrays().values()}  # exactly what the kernel gets
        assert all(not a.flags.writeable for a in held)
    # The same figures from the layouts the docstrings state (J = 31 joints).
    j = 31
    crouch = runtimes["crouch-hybrid0"]  # 2 keys: keys, 1 segment of angles and 1/sin, root keys, params
    assert crouch.runtime_bytes == 2 * j * 4 * 4 + 2 * j * 4 + 2 * 3 * 4 + 2 * 8 + 6 * 8
    walk = runtimes["walk-hybrid0"]  # 4 keys, 2 stored segments: 7 control points, 4 root segments
    assert walk.runtime_bytes == (7 * j * 4 * 4 + 3 * 8 + 5 * 8 + 4 * 4 * 3 * 4 + j * 4 + 4 * 4 + 3 * 4 + 3 * 8)
    keyframe = runtimes["walk-keyframe"]
    n = clips[0].clip.n_keys
    assert keyframe.runtime_bytes == n * j * 4 * 4 + n * 3 * 4 + 3 * 4 + 3 * 8


def test_the_kernel_refuses_bad_inputs(runtimes):
    rt = runtimes["walk-hybrid0"]
    j = rt.skeleton.n_joints
    t = np.linspace(0.0, 1.0, 5)
    cases = [
        (dict(t=np.zeros((5, 2))), "1-D"),
        (dict(t=np.array(["a", "b"])), "real numbers"),
        (dict(t=np.array([0.0, np.nan])), "finite"),
        (dict(out=CrowdBuffers.for_crowd(4, j)), r"shape \(5, 31, 4\)"),
        (dict(out=CrowdBuffers(np.zeros((5, j, 4)), np.zeros((5, j, 3), np.float32))), "float32"),
        (dict(out=CrowdBuffers(np.zeros((5, j, 4), np.float32), np.zeros((5, j, 6), np.float32)[..., ::2])),
         "C-contiguous"),
        (dict(active=np.ones(j - 1, np.uint8)), "active"),
        (dict(active=np.ones(j, np.float64)), "active"),
        (dict(stride=0), "stride"),
        (dict(first=2, stride=2), "first"),
    ]
    for kwargs, message in cases:
        args = {"t": t, **kwargs}
        with pytest.raises(ValueError, match=message):
            rt.pose(args.pop("t"), **args)


def test_update_rate_lod_poses_only_its_share_of_characters(runtimes, rng):
    rt = runtimes["run-hybrid1"]
    t = rng.uniform(0.0, 3.0, 11)
    out = CrowdBuffers.for_crowd(11, rt.skeleton.n_joints)
    out.rotations[:] = np.nan
    rt.pose(t, out, first=1, stride=3)
    posed = np.zeros(11, bool)
    posed[1::3] = True
    assert not np.isnan(out.rotations[posed]).any() and np.isnan(out.rotations[~posed]).all()
    assert np.array_equal(out.rotations[posed], rt.pose(t).rotations[posed])


def test_lod_error_is_zero_at_lod_0_and_grows(clips, runtimes):
    for c in clips:
        rt = runtimes[c.id]
        t = R.sample_times(c.clip, 240.0)
        full = rt.pose(t).rotations
        assert np.array_equal(R.lod_pose(rt, t, bone_lod=0), full)
        assert np.array_equal(R.lod_pose(rt, t, update_every=1), full)
        bone = [R.angle_error_deg(R.lod_pose(rt, t, bone_lod=level), full) for level in (1, 2)]
        # Level 2 holds a superset of level 1's joints still: the mean error grows, the worst never shrinks.
        assert 0 < bone[0][1] < bone[1][1] and 0 < bone[0][0] <= bone[1][0] + 1e-9, (c.id, bone)
        rate = [R.angle_error_deg(R.lod_pose(rt, t, update_every=k), full) for k in (2, 4)]
        assert 0 < rate[0][0] < rate[1][0] and 0 < rate[0][1] < rate[1][1], (c.id, rate)
    names = clips[0].clip.skeleton.names
    held = [n for n, on in zip(names, R.bone_lod_mask(clips[0].clip.skeleton, 1), strict=True) if not on]
    assert held == ["LeftToeBase", "RightToeBase", "LeftFingerBase", "LeftHandIndex1", "LThumb", "RightFingerBase",
                    "RightHandIndex1", "RThumb"]
    with pytest.raises(ValueError, match="bone LOD level"):
        R.bone_lod_mask(clips[0].clip.skeleton, 3)


def test_crouch_path_parameter_is_the_clips(clips, rng):
    crouch = next(c.clip for c in clips if isinstance(c.clip, SpringClip))
    params = R.crouch_params(crouch)
    for ct in rng.uniform(0.0, crouch.duration, 50):
        assert R.crouch_path_parameter(ct, params) == pytest.approx(crouch.path_parameter(ct), abs=1e-12)
    free = SpringClip(crouch.skeleton, crouch.key_params, crouch.key_rotations, crouch.key_root, crouch.duration,
                      land_on_last_key=False)
    t = rng.uniform(-3.0, 6.0, 200)
    got = R.runtime_for(free).pose(t).rotations.astype(np.float64)
    assert np.degrees(Q.quat_angle(got, R.exact_global(free, t)[0])).max() < 2e-3


def test_a_fit_outside_the_tolerance_is_refused(clips):
    run0 = next(c.clip for c in clips if c.id == "run-hybrid0")
    with pytest.raises(ValueError, match="from exact SQUAD"):
        R.spline_runtime(run0, tolerance_deg=0.01)
