"""Run-time cost of one clip, measured on the build machine for the clip manifest (issue 38): what a ladder's
levels save, beside what they look like.

* ``cost_ms_per_1000``: milliseconds a frame to pose 1,000 characters playing the clip (every joint sampled plus
  forward kinematics to model space, one thread), the median over :data:`FRAMES` frames of a clock advancing
  1/60 s a frame, each character at its own random phase: the ``keys`` variant of ``animstudy bench`` at 1,000
  characters (:mod:`anim_core.bench.suite`), in its units.  An ``update_rate`` clip is posed by the held-update
  path (:class:`anim_core.runtime.HeldCrowd`: a character is posed only when its held pose changes); a ``bone_lod``
  clip by its runtime with the held joints inactive.
* ``skin_ms_per_1000`` (render-time conditions, ``skin_influences``): milliseconds a frame of linear blend skinning
  (positions and normals) of the character's body, scaled to 1,000 characters from :data:`SKIN_CHARACTERS`
  characters over :data:`SKIN_FRAMES` frames (median).

Each measurement takes a few hundred milliseconds at most; they are timings on a shared machine, not exact
figures (the bench's interleaved rounds compare conditions more fairly).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..math.skinning import SkinnedMesh
from ..methods.lod import BoneLodClip, strongest_influences
from ..runtime import HeldRuntime, runtime_for
from ..runtime.crowd import CrowdBuffers
from .suite import FPS

CHARACTERS = 1000
FRAMES = 30
WARMUP = 3
SKIN_CHARACTERS = 2
SKIN_FRAMES = 9
SEED = 38


def _median_ms(step: Callable[[np.ndarray], Any], phases: np.ndarray, frames: int, warmup: int) -> float:
    times = []
    for frame in range(warmup + frames):
        t = phases + frame / FPS
        start = time.perf_counter()
        step(t)
        if frame >= warmup:
            times.append((time.perf_counter() - start) * 1000.0)
    return float(np.median(times))


def pose_step(clip: Any, n: int) -> Callable[[np.ndarray], Any]:
    """A function posing ``n`` characters playing ``clip`` at running times ``t (n,)``, as the crowd runtime
    does for its kind of clip (module docstring)."""
    runtime = runtime_for(clip)
    if isinstance(runtime, HeldRuntime):
        return runtime.crowd(n).pose
    buffers = CrowdBuffers.for_crowd(n, runtime.skeleton.n_joints)
    active = (~clip.frozen).astype(np.uint8) if isinstance(clip, BoneLodClip) else None
    return lambda t: runtime.pose(t, buffers, False, active)


def pose_cost_ms_per_1000(clip: Any, frames: int = FRAMES, seed: int = SEED) -> float:
    """``cost_ms_per_1000`` of ``clip`` (module docstring); per 1,000 characters, measured at 1,000."""
    phases = np.random.default_rng(seed).uniform(0.0, 2.0 * float(clip.duration), CHARACTERS)
    return _median_ms(pose_step(clip, CHARACTERS), phases, frames, WARMUP) * 1000.0 / CHARACTERS


def skinned_mesh(mesh: SkinnedMesh, influences: int | None) -> SkinnedMesh:
    """``mesh`` with only the ``influences`` strongest weights per vertex (None: as it is)."""
    if influences is None:
        return mesh
    joints, weights = strongest_influences(mesh.joints, mesh.weights, influences)
    return SkinnedMesh(mesh.vertices, mesh.normals, joints, weights, mesh.inverse_bind)


def skin_cost_ms_per_1000(clip: Any, mesh: SkinnedMesh, influences: int | None, frames: int = SKIN_FRAMES,
                          seed: int = SEED) -> float:
    """``skin_ms_per_1000``: linear blend skinning of ``mesh`` (cut to ``influences``) posed by ``clip``, per
    1,000 characters per frame (measured on :data:`SKIN_CHARACTERS`, scaled)."""
    skinned = skinned_mesh(mesh, influences)
    phases = np.random.default_rng(seed).uniform(0.0, 2.0 * float(clip.duration), SKIN_CHARACTERS)
    pose = pose_step(clip, SKIN_CHARACTERS)
    posed = {}

    def step(t: np.ndarray) -> Any:
        out = posed[float(t[0])]
        return skinned.skin(skinned.skinning_matrices(out.rotations, out.positions))

    for frame in range(WARMUP + frames):  # the poses first: only the skinning is timed
        t = phases + frame / FPS
        out = pose(t)
        posed[float(t[0])] = CrowdBuffers(out.rotations.copy(), out.positions.copy())
    return _median_ms(step, phases, frames, WARMUP) * 1000.0 / SKIN_CHARACTERS
