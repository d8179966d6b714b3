"""The keys runtime: every clip posed from its own keys, against the numpy reference; memory, validation, LOD."""

from pathlib import Path

import numpy as np
import pytest

from anim_core import runtime as R
from anim_core.math import quat as Q
from anim_core.methods.hybrid import SpringClip, SquadClip
from anim_core.runtime.crowd import CrowdBuffers


@pytest.fixture(scope="module")
def clips(built_clip_set):
    return built_clip_set()


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
    # 4 keys, 2 stored segments: 7 control points, 4 root segments, the partners and a 4x4 mirror map per joint
    walk = runtimes["walk-hybrid0"]
    assert walk.runtime_bytes == (7 * j * 4 * 4 + 3 * 8 + 5 * 8 + 4 * 4 * 3 * 4 + j * 4 + j * 4 * 4 * 4 + 3 * 4
                                  + 3 * 8)
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


# --- the conditions of issue 16, each from what it stores -------------------------------------------------------

CONDITIONS16 = Path(__file__).resolve().parents[1] / "server" / "clipset" / "conditions16.toml"
NEW_METHODS = ("hybrid_ik", "hybrid_c2", "reduced", "quantized")


@pytest.fixture(scope="module")
def clips16(built_clip_set):
    return [c for c in built_clip_set(CONDITIONS16) if c.method in NEW_METHODS]


@pytest.fixture(scope="module")
def runtimes16(clips16):
    return {c.id: R.runtime_for(c.clip) for c in clips16}


@pytest.mark.slow  # tens of seconds (the serial run's slowest; still run by `make test`)
def test_issue16_runtimes_match_their_clips(clips16, runtimes16, rng):
    """Each condition's kernel against its own ``sample``: float32 rounding for the keyframe-type clips and the C2
    spline (<= 0.002 degrees, 0.1 mm); foot locking within its base's fit error (FOOT_LOCK_TOLERANCE_DEG = 0.25
    degrees) and 5 mm, as the hybrids'."""
    assert len(clips16) == 4 * 10
    t = rng.uniform(-5.0, 15.0, 600)
    kinds = {"reduced": R.TableRuntime, "quantized": R.QuantizedRuntime, "hybrid_ik": R.FootLockRuntime}
    for c in clips16:
        rt = runtimes16[c.id]
        if c.method == "hybrid_c2":  # the crouch's hybrid_c2 is its spring hybrid 0
            assert isinstance(rt, R.SpringRuntime if c.animation == "crouch" else R.C2Runtime), c.id
        else:
            assert isinstance(rt, kinds[c.method]), c.id
        ref_rot, ref_pos = R.exact_global(c.clip, t)
        out = rt.pose(t)
        angle = np.degrees(Q.quat_angle(out.rotations.astype(np.float64), ref_rot)).max()
        distance = np.linalg.norm(out.positions - ref_pos, axis=-1).max()
        if c.method == "hybrid_ik":
            fit = rt.base.fit_error_deg if isinstance(rt.base, R.SplineRuntime) else 0.0  # spring: float32 only
            assert 0 <= rt.error_deg <= R.FOOT_LOCK_TOLERANCE_DEG
            assert angle <= min(R.FOOT_LOCK_TOLERANCE_DEG, 1.05 * fit + 2e-3), f"{c.id}: {angle:.4f} deg"
            assert distance <= 0.005, f"{c.id}: {distance * 1000:.3f} mm"
        else:
            assert angle <= 2e-3, f"{c.id}: {angle:.5f} deg"
            assert distance <= 1e-4, f"{c.id}: {distance * 1000:.3f} mm"
        parallel = rt.pose(t, parallel=True)
        assert np.array_equal(parallel.rotations, out.rotations) and np.array_equal(parallel.positions,
                                                                                    out.positions)


def test_issue16_runtimes_hold_what_the_clips_store(clips16, runtimes16):
    j = 31
    by_id = {c.id: c for c in clips16}
    for cid, rt in runtimes16.items():
        held = [v for v in vars(rt).values() if isinstance(v, np.ndarray)]
        if isinstance(rt, R.FootLockRuntime):
            held += [v for v in vars(rt.base).values() if isinstance(v, np.ndarray)]
        assert rt.runtime_bytes == sum(a.nbytes for a in held), cid
        assert {id(a) for a in held} == {id(a) for a in rt.arrays().values()}, cid
        assert all(not a.flags.writeable for a in held), cid
    # reduced: its own uneven key times, searched per character; bytes by the layout (float32 keys and root,
    # float64 times, 3 + 3 scalars)
    walk5 = by_id["walk-reduced5"].clip
    rt = runtimes16["walk-reduced5"]
    k = walk5.n_keys
    assert np.array_equal(rt.key_times, walk5.times) and np.ptp(np.diff(walk5.times)) > 0 and rt.params[0] == 0
    assert rt.runtime_bytes == k * j * 4 * 4 + k * 3 * 4 + 3 * 4 + 3 * 8 + k * 8
    # quantized: the integers (uint8 at 8 bits, uint16 at 12) and per-track low and step, no float keys
    for cid, dtype, size in (("walk-quantized8", np.uint8, 1), ("walk-quantized12", np.uint16, 2)):
        clip, rt = by_id[cid].clip, runtimes16[cid]
        assert rt.codes.dtype == dtype and np.array_equal(rt.codes, clip.tracks.codes)
        assert not any(a.dtype.kind == "f" and a.shape == clip.rotations.shape for a in rt.arrays().values())
        k = clip.n_keys
        assert rt.key_times.size == 0 and rt.params[0] > 0  # on the grid
        assert rt.runtime_bytes == k * j * 4 * size + 2 * j * 4 * 4 + k * 3 * 4 + 3 * 4 + 3 * 8
    reduced_quantized = runtimes16["walk-quantized12_reduced2"]
    assert reduced_quantized.key_times.size == by_id["walk-quantized12_reduced2"].clip.n_keys
    # hybrid_c2: the control points and their steps (4 floats each), the knots and the SQUAD root
    c2 = runtimes16["walk-hybrid_c2_0"]
    n = by_id["walk-hybrid_c2_0"].clip.spline.control.shape[0]
    assert c2.control.shape == c2.steps.shape == (n, j, 4) and c2.knots.shape == (n + 7,)
    # hybrid_ik: its hybrid's runtime plus legs, hinges, joint lists and the tracks at every frame
    ik_clip, ik = by_id["walk-hybrid_ik0"].clip, runtimes16["walk-hybrid_ik0"]
    assert isinstance(ik.base, R.SplineRuntime) and ik.base.runtime_bytes == R.runtime_for(ik_clip.base).runtime_bytes
    assert ik.track_values.shape == ik.track_slopes.shape == (ik_clip.weights.shape[0] + 1, 2, 4)
    assert np.allclose(ik.track_values[:-1, :, :3], ik_clip.targets, atol=1e-6)
    assert np.allclose(ik.track_values[:-1, :, 3], ik_clip.weights, atol=1e-6)
    assert ik.chains.tolist() == [list(leg) for leg in ik_clip.legs]
    names = ik_clip.skeleton.names
    assert [[names[x] for x in row if x >= 0] for row in ik.below] == [
        ["LeftLeg", "LeftFoot", "LeftToeBase"], ["RightLeg", "RightFoot", "RightToeBase"]]
    assert ik.turns[:, :3].tolist() == [[1, 2, 2], [1, 2, 2]]
    assert ik.runtime_bytes == ik.base.runtime_bytes + sum(a.nbytes for a in (
        ik.chains, ik.hinges, ik.below, ik.turns, ik.track_values, ik.track_slopes, ik.ik_params))


def test_issue16_kernels_refuse_bad_inputs(runtimes16):
    for cid in ("walk-reduced5", "walk-quantized8", "walk-hybrid_c2_0", "walk-hybrid_ik0", "crouch-hybrid_ik0"):
        rt = runtimes16[cid]
        j = rt.skeleton.n_joints
        for kwargs, message in ((dict(t=np.array([0.0, np.inf])), "finite"),
                                (dict(out=CrowdBuffers.for_crowd(3, j)), r"shape \(2, 31, 4\)"),
                                (dict(active=np.ones(j + 1, np.uint8)), "active"), (dict(stride=-1), "stride")):
            args = {"t": np.array([0.0, 0.5]), **kwargs}
            with pytest.raises(ValueError, match=message):
                rt.pose(args.pop("t"), **args)


def test_a_foot_lock_or_c2_kernel_off_its_clip_is_refused(clips16):
    ik = next(c.clip for c in clips16 if c.id == "walk-hybrid_ik0")
    with pytest.raises(ValueError, match="foot-lock kernel"):
        R.foot_lock_runtime(ik, tolerance_deg=1e-9)
    c2 = next(c.clip for c in clips16 if c.id == "walk-hybrid_c2_0")
    with pytest.raises(ValueError, match="C2 kernel"):
        R.c2_runtime(c2, tolerance_deg=1e-9)


@pytest.mark.parametrize("threads", [2, 3, 8])
def test_threads_pose_exactly_the_characters_of_first_and_stride(runtimes16, rng, monkeypatch, threads):
    """``parallel=True`` with any thread count, crowd size, ``first`` and ``stride`` (update-rate LOD): the same
    bytes as one thread for the characters ``first, first + stride, ...``, and every other character's buffers
    untouched (seeded: 40 draws per thread count over the four issue-16 kinds)."""
    from anim_core.runtime import kinds

    monkeypatch.setattr(kinds, "pose_threads", lambda: threads)
    chosen = [rt for cid, rt in sorted(runtimes16.items()) if cid.startswith("walk-")]
    for _ in range(40):
        rt = chosen[rng.integers(len(chosen))]
        n, stride = int(rng.integers(1, 40)), int(rng.integers(1, 5))
        first = int(rng.integers(stride))
        t = rng.uniform(-2.0, 8.0, n)
        joints = rt.skeleton.parents.shape[0]
        serial = CrowdBuffers(np.full((n, joints, 4), 7.0, np.float32), np.full((n, joints, 3), 7.0, np.float32))
        split = CrowdBuffers(np.full((n, joints, 4), 7.0, np.float32), np.full((n, joints, 3), 7.0, np.float32))
        rt.pose(t, serial, first=first, stride=stride)
        rt.pose(t, split, parallel=True, first=first, stride=stride)
        assert np.array_equal(split.rotations, serial.rotations) and np.array_equal(split.positions, serial.positions)
        posed = np.zeros(n, bool)
        posed[first::stride] = True
        assert (split.rotations[~posed] == 7.0).all() and (split.positions[~posed] == 7.0).all()
        assert (split.rotations[posed] != 7.0).all()
