"""Feet held through a blended transition (anim_core/methods/transition_feet.py), on hand-made contact tracks:
which frames are held, and how a hold's offsets start and end.  The whole lock on the sample takes is tested in
test_composite_clips.py."""

from __future__ import annotations

import numpy as np
import pytest

from anim_core.methods.transition_feet import eased_offsets, held_phases


def _track(n: int, *runs: tuple[int, int]) -> np.ndarray:
    out = np.zeros(n, bool)
    for a, b in runs:
        out[np.arange(a, b) % n] = True
    return out


def test_held_phases_from_the_switch_on_and_one_frame_after() -> None:
    n = 20
    down = np.stack([_track(n, (2, 6), (10, 15)), _track(n, (17, 23))], axis=1)  # foot 1 runs across the seam
    held = held_phases(down, [(12, 14), (0, 2)])
    # foot 0: the phase 10..14 meets the window at 12: held from 12 to its end and one frame after (15); 2..5 no
    assert np.flatnonzero(held[:, 0]).tolist() == [12, 13, 14, 15]
    # foot 1: the phase 17..22 (mod 20) meets the window at the seam: held from frame 0 on, 17..19 as they are
    assert np.flatnonzero(held[:, 1]).tolist() == [0, 1, 2, 3]


def test_a_phase_away_from_every_window_is_not_held() -> None:
    down = _track(30, (3, 8))[:, None]
    assert not held_phases(down, [(10, 18)]).any()


def test_a_hold_from_a_switch_starts_where_the_foot_is_and_eases_out() -> None:
    n, release = 30, 5
    held = _track(n, (10, 15))[:, None]
    steps = _track(n, (10, 15), (25, 28))[:, None]
    given = np.zeros((n, 1, 3))
    given[10:15, 0, 0] = [0.1, 0.12, 0.15, 0.2, 0.2]
    off = eased_offsets(given, held, steps, [10], release)
    assert np.array_equal(off[:10], np.zeros((10, 1, 3)))  # before the switch: as animated
    np.testing.assert_allclose(off[10:15, 0, 0], [0.0, 0.02, 0.05, 0.1, 0.1], atol=1e-15)
    x = np.arange(1, 6) / 6
    np.testing.assert_allclose(off[15:20, 0, 0], 0.1 * (1 - (3 * x**2 - 2 * x**3)), atol=1e-15)
    assert np.array_equal(off[20:], np.zeros((10, 1, 3)))  # released before the next step


def test_a_landing_after_the_switch_eases_in_from_the_switch() -> None:
    n = 30
    held = _track(n, (13, 17))[:, None]
    steps = _track(n, (0, 6), (13, 17))[:, None]
    given = np.zeros((n, 1, 3))
    given[13:17, 0, 2] = [0.3, 0.1, 0.0, 0.0]  # resting (offset 0) from its slowest frame, 15
    off = eased_offsets(given, held, steps, [10], 8)
    np.testing.assert_allclose(off[13:17, 0, 2], [0.3, 0.1, 0.0, 0.0])  # kept as given
    x = np.array([1, 2, 3]) / 4  # frames 10, 11, 12: the swing since the switch, no further back
    np.testing.assert_allclose(off[10:13, 0, 2], 0.3 * (3 * x**2 - 2 * x**3), atol=1e-15)
    assert np.array_equal(off[:10], np.zeros((10, 1, 3)))
    assert np.array_equal(off[17:], np.zeros((13, 1, 3)))  # its last offset is 0: nothing to release


@pytest.mark.parametrize("release", [1, 3])
def test_the_release_is_at_most_release_frames(release: int) -> None:
    n = 40
    held = _track(n, (5, 9))[:, None]
    given = np.zeros((n, 1, 3))
    given[5:9, 0, 1] = [0.0, 0.0, 0.1, 0.2]
    off = eased_offsets(given, held, held, [5], release)
    assert np.flatnonzero(off[:, 0, 1]).tolist() == [7, 8, *range(9, 9 + release)]
