"""Foot contacts: when a foot is down, when it skates, and its contact phases as frame intervals.

Conventions: positions in metres, ``up_axis`` (default 1, Y) is vertical and the other two axes are the ground
plane; frames are sampled at ``fps`` frames per second along axis 0.  A *foot* is tracked by ``K`` joints (e.g.
ankle and toe), a batch of ``F`` feet by arrays ``(T, F, K, 3)``.  Skeleton-agnostic: callers pick the joints.

The measure (issue 14, after Guided Motion Diffusion's skating ratio, refined for a rolling foot):

* the *standing height* of each foot joint is its :data:`STANDING_PERCENTILE` th percentile height over the clip
  (no character model needed, so mocap on its own skeleton and the character are measured alike);
* a foot is *down* in a frame when every one of its joints is within :data:`CONTACT_CLEARANCE_M` of its standing
  height (a foot swinging just above the floor has its heel or toe up);
* a foot that is down *skates* when even its slowest joint moves faster than :data:`SKATE_SPEED_MPS` horizontally
  (a foot rolling over its heel or toe keeps that point still; a sliding foot moves everywhere).

Sequences with ``periodic=True`` hold one period without a repeated end frame (frame ``T`` is frame ``0``), and
velocities and contact intervals wrap around.  ``ground_velocity (3,)`` m/s is added to every joint's velocity,
for clips played in place, so speeds are against the ground.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

CONTACT_CLEARANCE_M = 0.05
SKATE_SPEED_MPS = 0.5
STANDING_PERCENTILE = 5.0


def _feet(feet: ArrayLike) -> Array:
    p = np.asarray(feet, dtype=np.float64)
    if p.ndim != 4 or p.shape[-1] != 3 or p.shape[0] < 2:
        raise ValueError(f"expected foot positions of shape (T >= 2, F, K, 3), got {p.shape}")
    return p


def standing_heights(feet: ArrayLike, up_axis: int = 1, percentile: float = STANDING_PERCENTILE) -> Array:
    """``(F, K)`` height of each foot joint when standing: its ``percentile`` th percentile over the frames."""
    return np.percentile(_feet(feet)[..., up_axis], percentile, axis=0)


def foot_down(feet: ArrayLike, up_axis: int = 1, clearance: float = CONTACT_CLEARANCE_M,
              standing: ArrayLike | None = None) -> NDArray[np.bool_]:
    """``(T, F)``: every joint of the foot within ``clearance`` m of its standing height ``(F, K)`` (default:
    :func:`standing_heights` of these frames)."""
    p = _feet(feet)
    h = standing_heights(p, up_axis) if standing is None else np.asarray(standing, dtype=np.float64)
    if h.shape != p.shape[1:3]:
        raise ValueError(f"expected standing heights of shape {p.shape[1:3]}, got {h.shape}")
    return np.all(p[..., up_axis] - h < clearance, axis=2)


def foot_speed(feet: ArrayLike, fps: float, up_axis: int = 1, periodic: bool = False,
               ground_velocity: ArrayLike | None = None) -> Array:
    """``(T, F)`` horizontal speed in m/s of each foot's slowest joint (central differences; one-sided at the ends
    of a non-periodic sequence)."""
    p = _feet(feet)
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if periodic:
        vel = (np.roll(p, -1, axis=0) - np.roll(p, 1, axis=0)) * (0.5 * fps)
    else:
        vel = np.gradient(p, 1.0 / fps, axis=0, edge_order=1)
    if ground_velocity is not None:
        vel = vel + np.asarray(ground_velocity, dtype=np.float64)
    vel[..., up_axis] = 0.0
    return np.linalg.norm(vel, axis=-1).min(axis=2)


def foot_skating(feet: ArrayLike, fps: float, up_axis: int = 1, periodic: bool = False,
                 ground_velocity: ArrayLike | None = None, clearance: float = CONTACT_CLEARANCE_M,
                 speed: float = SKATE_SPEED_MPS, standing: ArrayLike | None = None) -> NDArray[np.bool_]:
    """``(T, F)``: the foot is down (:func:`foot_down`; ``standing``: its standing heights ``(F, K)``, default
    those of these frames) and its slowest joint moves faster than ``speed`` m/s."""
    down = foot_down(feet, up_axis, clearance, standing)
    return down & (foot_speed(feet, fps, up_axis, periodic, ground_velocity) > speed)


def foot_skate_ratio(feet: ArrayLike, fps: float, up_axis: int = 1, periodic: bool = False,
                     ground_velocity: ArrayLike | None = None, standing: ArrayLike | None = None) -> float:
    """Share of frames (0..1) in which at least one foot skates (:func:`foot_skating`)."""
    return float(np.mean(np.any(foot_skating(feet, fps, up_axis, periodic, ground_velocity,
                                             standing=standing), axis=1)))


def contact_intervals(down: ArrayLike, periodic: bool = False) -> NDArray[np.intp]:
    """Runs of ``True`` in ``down (T,)`` as ``(N, 2)`` ``[start, stop)`` frame intervals, in order of start.

    With ``periodic=True`` a run that wraps from the last frame to the first is one interval whose ``stop``
    exceeds ``T`` (frames ``start..T-1`` then ``0..stop-T-1``); a foot down in every frame gives ``[[0, T]]``.
    """
    d = np.asarray(down, dtype=bool)
    if d.ndim != 1:
        raise ValueError(f"expected a contact sequence of shape (T,), got {d.shape}")
    n = d.size
    edges = np.diff(np.concatenate([[0], d.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    runs = np.stack([starts, stops], axis=1).astype(np.intp)
    if periodic and len(runs) > 1 and runs[0, 0] == 0 and runs[-1, 1] == n:
        runs = np.vstack([runs[1:-1], [[runs[-1, 0], n + runs[0, 1]]]])
        runs = runs[np.argsort(runs[:, 0], kind="stable")]
    return runs


def interval_mask(intervals: ArrayLike, n_frames: int) -> NDArray[np.bool_]:
    """``(T,)`` mask of the frames covered by ``[start, stop)`` intervals (stops beyond ``T`` wrap around)."""
    mask = np.zeros(n_frames, dtype=bool)
    for start, stop in np.asarray(intervals, dtype=np.intp).reshape(-1, 2):  # one per contact phase
        mask[np.arange(start, stop) % n_frames] = True
    return mask
