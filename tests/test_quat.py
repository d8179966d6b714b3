"""Quaternion math: properties with seeded random inputs and stated tolerances.

References are independent implementations: scipy's ``Rotation`` (scalar-last, converted here) and
``numpy-quaternion``.
"""

import numpy as np
import pytest
import quaternion as npq
from scipy.spatial.transform import Rotation

from anim_core.math import quat as Q

ORDERS = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX", "xyz", "xzy", "yxz", "yzx", "zxy", "zyx"]


def random_quats(rng, n):
    return Q.quat_normalize(rng.normal(size=(n, 4)))


def to_scipy(q):
    return Rotation.from_quat(q[..., [1, 2, 3, 0]])


def test_product_and_rotation_match_matrices(rng):
    a, b = random_quats(rng, 200), random_quats(rng, 200)
    v = rng.normal(size=(200, 3))
    ma, mb = Q.matrix_from_quat(a), Q.matrix_from_quat(b)
    np.testing.assert_allclose(Q.matrix_from_quat(Q.quat_mul(a, b)), ma @ mb, atol=1e-14)
    np.testing.assert_allclose(Q.rotate(a, v), np.einsum("nij,nj->ni", ma, v), atol=1e-14)
    np.testing.assert_allclose(ma, to_scipy(a).as_matrix(), atol=1e-14)


def test_inverse_and_conjugate(rng):
    q = rng.normal(size=(100, 4))  # not unit: quat_inv must still invert
    np.testing.assert_allclose(Q.quat_mul(q, Q.quat_inv(q)), Q.identity((100,)), atol=1e-14)
    u = Q.quat_normalize(q)
    np.testing.assert_allclose(Q.quat_mul(Q.quat_conj(u), u), Q.identity((100,)), atol=1e-14)


def test_normalize_rejects_zero():
    with pytest.raises(ValueError, match="zero quaternion"):
        Q.quat_normalize(np.zeros(4))


def test_matrix_round_trip_including_half_turns(rng):
    q = random_quats(rng, 500)
    # 180-degree rotations: w = 0, the case where the naive trace formula divides by zero.
    half_turns = np.concatenate([np.zeros((50, 1)), Q.quat_normalize(rng.normal(size=(50, 3)))], axis=1)
    q = np.concatenate([q, half_turns, Q.identity((1,))])
    back = Q.quat_from_matrix(Q.matrix_from_quat(q))
    assert Q.quat_angle(back, q).max() < 1e-7  # angle from atan2: ~sqrt(eps) at worst for w = 0 exactly
    np.testing.assert_allclose(Q.matrix_from_quat(back), Q.matrix_from_quat(q), atol=1e-14)


def test_log_exp_inverse_and_small_angles(rng):
    q = random_quats(rng, 500)
    np.testing.assert_allclose(Q.quat_exp(Q.quat_log(q)), q, atol=1e-14)
    ref = npq.as_float_array(np.log(npq.as_quat_array(q)))
    np.testing.assert_allclose(Q.quat_log(q), ref[:, 1:], atol=1e-14)
    tiny = np.array([[0.0, 0.0, 0.0], [1e-300, 0, 0], [1e-12, -2e-12, 3e-12]])
    e = Q.quat_exp(tiny)
    assert np.all(np.isfinite(e))
    np.testing.assert_allclose(Q.quat_log(e), tiny, rtol=1e-12, atol=0)
    np.testing.assert_allclose(Q.quat_log(Q.identity()), np.zeros(3))


def test_slerp_matches_numpy_quaternion_and_extrapolates(rng):
    a, b = random_quats(rng, 300), random_quats(rng, 300)
    b = Q.align_hemisphere(b, a)
    t = rng.uniform(-1.0, 2.0, size=300)
    ref = npq.as_float_array(np.array([
        npq.slerp_evaluate(x, y, s) for x, y, s in zip(npq.as_quat_array(a), npq.as_quat_array(b), t, strict=True)
    ]))
    np.testing.assert_allclose(Q.slerp_unclamped(a, b, t), ref, atol=1e-13)
    # Clamped slerp holds the ends; unclamped continues along the same great circle at constant speed.
    np.testing.assert_allclose(Q.slerp(a, b, t), Q.slerp_unclamped(a, b, np.clip(t, 0, 1)), atol=1e-15)
    full = Q.quat_angle(a, b)
    travelled = np.abs(t) * full  # < 2 pi here; quat_angle reports the angle folded into [0, pi]
    expected = np.where(travelled > np.pi, 2 * np.pi - travelled, travelled)
    np.testing.assert_allclose(Q.quat_angle(Q.slerp_unclamped(a, b, t), a), expected, atol=1e-7)


def test_slerp_takes_the_short_way_for_antipodal_inputs(rng):
    a = random_quats(rng, 100)
    b = Q.quat_mul(a, Q.quat_from_axis_angle(rng.normal(size=(100, 3)), 0.3))
    mid_short = Q.slerp(a, -b, 0.5)  # -b is the same rotation as b
    np.testing.assert_allclose(Q.quat_angle(mid_short, a), 0.15, atol=1e-12)
    mid_nlerp = Q.nlerp(a, -b, 0.5)
    assert Q.quat_angle(mid_nlerp, a).max() < 0.16
    with pytest.raises(ValueError, match="antipodal"):
        Q.slerp_unclamped(a[:1], -a[:1], 0.5, shortest=False)


def test_slerp_small_angles_are_exact_to_rounding(rng):
    a = random_quats(rng, 50)
    for angle in (1e-15, 1e-9, 1e-6):
        b = Q.quat_mul(a, Q.quat_from_axis_angle([1.0, 2.0, 3.0], angle))
        for t in (0.25, -1.0, 3.0):
            mid = Q.slerp_unclamped(a, b, t)
            np.testing.assert_allclose(np.linalg.norm(mid, axis=-1), 1.0, atol=1e-15)
            expected = Q.quat_mul(a, Q.quat_from_axis_angle([1.0, 2.0, 3.0], t * angle))
            np.testing.assert_allclose(mid, expected, atol=1e-15)


@pytest.mark.parametrize("order", ORDERS)
def test_euler_round_trip_and_scipy_agreement(rng, order):
    angles = rng.uniform(-np.pi, np.pi, size=(400, 3))
    angles[:, 1] = rng.uniform(-np.pi / 2, np.pi / 2, size=400)
    q = Q.quat_from_euler(angles, order)
    np.testing.assert_allclose(Q.matrix_from_quat(q), Rotation.from_euler(order, angles).as_matrix(), atol=1e-14)
    back = Q.euler_from_quat(q, order)
    np.testing.assert_allclose(back, angles, atol=1e-12)
    np.testing.assert_allclose(back, to_scipy(q).as_euler(order), atol=1e-12)


@pytest.mark.parametrize("order", ORDERS)
def test_euler_gimbal_lock_reproduces_the_rotation(rng, order):
    angles = rng.uniform(-np.pi, np.pi, size=(100, 3))
    angles[:, 1] = np.where(rng.random(100) < 0.5, np.pi / 2, -np.pi / 2)
    q = Q.quat_from_euler(angles, order)
    back = Q.euler_from_quat(q, order)
    assert Q.quat_angle(Q.quat_from_euler(back, order), q).max() < 1e-12
    np.testing.assert_allclose(back[:, 2], 0.0, atol=1e-12)


def test_bad_euler_order_is_a_clear_error():
    with pytest.raises(ValueError, match="permutation of 'XYZ'"):
        Q.quat_from_euler(np.zeros(3), "XYX")
    with pytest.raises(ValueError, match="permutation of 'XYZ'"):
        Q.euler_from_quat(Q.identity(), "Xyz")


def test_make_continuous_and_canonicalize(rng):
    q = random_quats(rng, 50)
    # A smooth path with random sign flips: make_continuous must undo exactly the flips.
    path = Q.quat_mul(q[:1], Q.quat_from_axis_angle([0.0, 1.0, 0.0], np.linspace(0, 6, 50)))
    flips = np.where(rng.random(50) < 0.5, -1.0, 1.0)[:, None]
    fixed = Q.make_continuous(path * flips, axis=0)
    np.testing.assert_allclose(fixed * np.sign(fixed[0, 0] * path[0, 0]), path, atol=1e-15)
    assert np.all(np.sum(fixed[1:] * fixed[:-1], axis=-1) > 0)
    c = Q.canonicalize(-np.abs(q))
    assert np.all(c[:, 0] >= 0)
    np.testing.assert_allclose(Q.quat_angle(c, -np.abs(q)), 0.0, atol=1e-12)
