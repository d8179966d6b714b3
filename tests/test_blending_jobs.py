"""The run-time blending jobs (issue 39) against the numpy reference: float32 kernels within stated tolerances,
exact where a weight is 0 or 1, every bad buffer refused before a kernel runs.  Seeded."""

from __future__ import annotations

import numpy as np
import pytest

from anim_core.math import quat as Q
from anim_core.math.clip import KeyframeClip
from anim_core.runtime.blending import LocalPose, SamplingJob, additive, blend, local_to_model
from tests.synthetic import biped, random_rotations

N = 64
TOL = 2e-6  # float32 rounding of unit quaternions and metre-scale positions


def _poses(seed: int) -> tuple[LocalPose, LocalPose]:
    rng = np.random.default_rng(seed)
    j = biped().n_joints
    a = LocalPose(random_rotations(rng, (N, j)).astype(np.float32), rng.normal(size=(N, 3)).astype(np.float32))
    b = LocalPose(random_rotations(rng, (N, j)).astype(np.float32), rng.normal(size=(N, 3)).astype(np.float32))
    return a, b


def test_blend_against_nlerp() -> None:
    a, b = _poses(1)
    j = a.rotations.shape[1]
    w = np.random.default_rng(2).uniform(0, 1, N).astype(np.float32)
    w[:3] = [0, 1, 0.5]
    jw = np.ones(j, np.float32)
    jw[3:6] = 0  # the left leg keeps pose a
    out = blend(a, b, w, jw, LocalPose.for_crowd(N, j))
    a64, b64 = a.rotations.astype(np.float64), b.rotations.astype(np.float64)
    expected = Q.nlerp(a64, b64, (w[:, None] * jw[None]).astype(np.float64))
    assert np.abs(Q.align_hemisphere(out.rotations, expected) - expected).max() < TOL
    assert np.array_equal(out.rotations[0], a.rotations[0]) and np.array_equal(out.rotations[1][jw == 1],
                                                                                b.rotations[1][jw == 1])
    assert np.array_equal(out.rotations[:, 3:6], a.rotations[:, 3:6])
    assert np.allclose(out.root, a.root + (b.root - a.root) * w[:, None], atol=TOL)


def test_additive_against_reference() -> None:
    base, other = _poses(3)
    j = base.rotations.shape[1]
    jw = np.zeros(j, np.float32)
    jw[1:3] = [1.0, 0.5]
    delta = other.rotations[0]
    out = additive(base, delta, jw, LocalPose.for_crowd(N, j))
    d64 = Q.align_hemisphere(delta.astype(np.float64), Q.identity(()))  # any sign: nlerp from 1 takes it as given
    weighted = Q.nlerp(Q.identity((j,)), delta.astype(np.float64), jw.astype(np.float64), shortest=False)
    expected = Q.quat_mul(base.rotations.astype(np.float64), weighted)
    assert d64.shape == (j, 4)
    assert np.abs(out.rotations[:, 1:3] - expected[:, 1:3]).max() < TOL
    assert np.array_equal(out.rotations[:, jw == 0], base.rotations[:, jw == 0])
    zero = additive(base, np.tile(np.float32([1, 0, 0, 0]), (j, 1)), np.ones(j, np.float32),
                    LocalPose.for_crowd(N, j))
    assert np.array_equal(zero.rotations, base.rotations)


def test_sampling_and_local_to_model_match_the_clip() -> None:
    sk = biped()
    rng = np.random.default_rng(4)
    times = np.arange(31) / 30
    rot = Q.make_continuous(random_rotations(rng, (31, sk.n_joints)) * 0.1 + Q.identity((31, sk.n_joints)))
    rot = Q.quat_normalize(rot)
    root = np.stack([np.zeros(31), np.ones(31), times * 1.2], axis=-1)
    clip = KeyframeClip(sk, times, rot, root, "loop", False, 1, "x")
    t = rng.uniform(0, 3, N)
    local = SamplingJob.from_clip(clip).run(t, LocalPose.for_crowd(N, sk.n_joints))
    ref = clip.sample(t)
    assert np.abs(Q.align_hemisphere(local.rotations, ref.rotations) - ref.rotations).max() < TOL
    assert np.abs(local.root - ref.root_translation).max() < 1e-5
    g_rot, g_pos = np.empty((N, sk.n_joints, 4), np.float32), np.empty((N, sk.n_joints, 3), np.float32)
    local_to_model(sk, local, g_rot, g_pos)
    e_rot, e_pos = sk.forward_kinematics(ref.rotations, ref.root_translation)
    assert np.abs(Q.quat_angle(g_rot, e_rot)).max() < 1e-3  # radians, float32 along the chain
    assert np.abs(g_pos - e_pos).max() < 1e-5


def test_bad_buffers_are_refused() -> None:
    a, b = _poses(5)
    j = a.rotations.shape[1]
    out = LocalPose.for_crowd(N, j)
    with pytest.raises(ValueError, match="weights must be finite weights"):
        blend(a, b, np.full(N, 1.5, np.float32), np.ones(j, np.float32), out)
    with pytest.raises(ValueError, match="weights must have shape"):
        blend(a, b, np.ones(N - 1, np.float32), np.ones(j, np.float32), out)
    with pytest.raises(ValueError, match="pose b rotations must be a float32"):
        blend(a, LocalPose(b.rotations.astype(np.float64), b.root), np.ones(N, np.float32), np.ones(j, np.float32),
              out)
    frozen = LocalPose.for_crowd(N, j)
    frozen.rotations.flags.writeable = False
    with pytest.raises(ValueError, match="output rotations must be writeable"):
        blend(a, b, np.ones(N, np.float32), np.ones(j, np.float32), frozen)
    with pytest.raises(ValueError, match="delta must have shape"):
        additive(a, np.ones((j + 1, 4), np.float32), np.ones(j, np.float32), out)
    with pytest.raises(ValueError, match="joint weights must be finite"):
        additive(a, a.rotations[0], np.full(j, np.nan, np.float32), out)
