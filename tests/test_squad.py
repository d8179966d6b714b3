"""SQUAD: agreement with numpy-quaternion, interpolation of the keys, C1 continuity at the keys."""

import numpy as np
import pytest
import quaternion as npq

from anim_core.math import quat as Q


def random_walk_keys(rng, n_keys, n_tracks, step=0.9):
    """Sign-continuous random keys: each a random rotation of up to ``step`` rad from the previous one."""
    q = [Q.quat_normalize(rng.normal(size=(n_tracks, 4)))]
    for _ in range(n_keys - 1):
        axis = rng.normal(size=(n_tracks, 3))
        q.append(Q.quat_mul(q[-1], Q.quat_from_axis_angle(axis, rng.uniform(0.05, step, n_tracks))))
    return Q.make_continuous(np.array(q), axis=0)


def evaluate(q, a, b, times, t):
    """Evaluate precomputed SQUAD segments at times ``t``."""
    seg = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    h = (t - times[seg]) / (times[seg + 1] - times[seg])
    return Q.squad_eval(q[seg], q[seg + 1], a[seg], b[seg], h[:, None])


def angular_velocity(qa, qb, dt):
    """World angular velocity (rad/s) of the motion from ``qa`` to ``qb`` in ``dt`` seconds."""
    return 2.0 * Q.quat_log(Q.align_hemisphere(Q.quat_mul(qb, Q.quat_conj(qa)), Q.identity())) / dt


def velocity_jumps(q, a, b, times, interior_keys, delta=1e-6):
    """|omega after - omega before| at the given key times, shape (keys, tracks)."""
    tk = times[interior_keys]
    before = evaluate(q, a, b, times, tk - delta)
    at = evaluate(q, a, b, times, tk)
    after = evaluate(q, a, b, times, tk + delta)
    return np.linalg.norm(angular_velocity(at, after, delta) - angular_velocity(before, at, delta), axis=-1)


@pytest.mark.parametrize("uneven", [False, True])
def test_squad_equals_numpy_quaternion_open_ends(rng, uneven):
    keys = random_walk_keys(rng, 9, 12)
    times = np.cumsum(rng.uniform(0.2, 1.5, 9)) if uneven else np.arange(9.0)
    times -= times[0]
    t_out = np.sort(rng.uniform(times[0], times[-1], 400))
    ref = npq.as_float_array(npq.squad(npq.as_quat_array(keys), times, t_out))
    q, a, b = Q.squad_tangents(keys, times, ends="open")
    ours = evaluate(q, a, b, times, t_out)
    print(f"max |squad - quaternion.squad| = {np.abs(ours - ref).max():.1e} (uneven={uneven})")
    assert np.abs(ours - ref).max() < 1e-12


@pytest.mark.parametrize("ends", ["open", "cyclic", "reflect"])
def test_squad_passes_exactly_through_every_key(rng, ends):
    keys = random_walk_keys(rng, 6, 20)
    n_seg = 6 if ends == "cyclic" else 5
    times = np.concatenate([[0.0], np.cumsum(rng.uniform(0.3, 1.0, n_seg))])
    q, a, b = Q.squad_tangents(keys, times, ends=ends)
    at_keys = evaluate(q, a, b, times, times[:6])
    assert Q.quat_angle(at_keys, keys).max() < 1e-14
    if ends == "cyclic":  # the period end is key 0 again
        assert Q.quat_angle(evaluate(q, a, b, times, times[-1:]), keys[:1]).max() < 1e-14


@pytest.mark.parametrize("uneven", [False, True])
def test_squad_is_c1_at_keys_and_slerp_is_not(rng, uneven):
    keys = random_walk_keys(rng, 8, 30, step=0.6)
    times = np.concatenate([[0.0], np.cumsum(rng.uniform(0.25, 0.6, 8) if uneven else np.full(8, 0.4))])
    q, a, b = Q.squad_tangents(keys, times, ends="cyclic")
    interior = np.arange(1, 8)
    squad_jump = velocity_jumps(q, a, b, times, interior)
    # Slerp on the same keys = SQUAD with control points equal to the keys.
    slerp_jump = velocity_jumps(q, q[:-1], q[1:], times, interior)
    print(f"max angular-velocity jump at keys: squad {squad_jump.max():.2e} rad/s, "
          f"slerp {slerp_jump.max():.2f} rad/s (median {np.median(slerp_jump):.2f})")
    assert squad_jump.max() < 1e-3
    assert np.median(slerp_jump) > 0.1


def test_cyclic_squad_is_c1_across_the_wrap(rng):
    keys = random_walk_keys(rng, 4, 30, step=0.8)
    times = np.array([0.0, 0.3, 0.5, 0.8, 1.0])
    q, a, b = Q.squad_tangents(keys, times, ends="cyclic")
    delta = 1e-6
    end = evaluate(q, a, b, times, np.array([1.0 - delta, 1.0]))
    start = evaluate(q, a, b, times, np.array([0.0, delta]))
    jump = angular_velocity(start[0], start[1], delta) - angular_velocity(end[0], end[1], delta)
    assert np.linalg.norm(jump, axis=-1).max() < 1e-3


def test_reflect_ends_have_zero_velocity(rng):
    keys = random_walk_keys(rng, 3, 10)
    times = np.array([0.0, 0.7, 1.2])
    q, a, b = Q.squad_tangents(keys, times, ends="reflect")
    delta = 1e-6
    for t0, t1 in ((0.0, delta), (1.2 - delta, 1.2)):
        ends = evaluate(q, a, b, times, np.array([t0, t1]))
        # Velocity vanishes, so the displacement over delta is second order: << delta * typical speed (~1 rad/s).
        assert np.linalg.norm(angular_velocity(ends[0], ends[1], delta), axis=-1).max() < 1e-4


def test_squad_rejects_bad_input(rng):
    keys = random_walk_keys(rng, 3, 1)
    with pytest.raises(ValueError, match="at least 2 keys"):
        Q.squad_tangents(keys[:1])
    with pytest.raises(ValueError, match="strictly increasing"):
        Q.squad_tangents(keys, np.array([0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="4 key times"):
        Q.squad_tangents(keys, np.arange(3.0), ends="cyclic")
    with pytest.raises(ValueError, match="ends must be"):
        Q.squad_tangents(keys, ends="wrap")
