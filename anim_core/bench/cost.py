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

The clips (or skins) of one animation are timed interleaved, frame by frame, as the bench times its cases.

Each measurement takes a few hundred milliseconds at most; they are timings on a shared machine, not exact
figures (the bench's interleaved rounds compare conditions more fairly).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ..clips.build import skin_level
from ..clips.record import BuiltClip
from ..math.skinning import SkinnedMesh
from ..methods.base import REFERENCE
from ..methods.lod import strongest_influences
from ..runtime import HeldRuntime, animated_joints, runtime_for
from ..runtime.crowd import CrowdBuffers
from .suite import FPS, interleaved_ms

CHARACTERS = 1000
FRAMES = 60
WARMUP = 10
SKIN_CHARACTERS = 2
SKIN_FRAMES = 9
SEED = 38


def _medians_ms(steps: Sequence[Callable[[np.ndarray], Any]], phases: np.ndarray, frames: int, warmup: int
                ) -> list[float]:
    """The median milliseconds of each step, timed interleaved in a new (seeded) order every frame
    (:func:`anim_core.bench.suite.interleaved_ms`)."""
    timed = interleaved_ms([lambda t, _f, step=step: step(t) for step in steps], phases, frames, warmup, SEED)
    return [float(np.median(ms)) for ms in timed]


def pose_step(clip: Any, n: int) -> Callable[[np.ndarray], Any]:
    """A function posing ``n`` characters playing ``clip`` at running times ``t (n,)``, as the crowd runtime
    does for its kind of clip (module docstring)."""
    runtime = runtime_for(clip)
    if isinstance(runtime, HeldRuntime):
        return runtime.crowd(n).pose
    buffers = CrowdBuffers.for_crowd(n, runtime.skeleton.n_joints)
    active = animated_joints(clip)  # a bone-LOD clip's frozen joints copied from their bind-pose key, not sampled
    return lambda t: runtime.pose(t, buffers, False, active)


def pose_costs_ms_per_1000(clips: Sequence[Any], frames: int = FRAMES, seed: int = SEED) -> list[float]:
    """``cost_ms_per_1000`` of each clip (module docstring), the clips of one animation timed interleaved; per
    1,000 characters, measured at 1,000."""
    duration = max(float(c.duration) for c in clips)
    phases = np.random.default_rng(seed).uniform(0.0, 2.0 * duration, CHARACTERS)
    steps = [pose_step(c, CHARACTERS) for c in clips]
    return [ms * 1000.0 / CHARACTERS for ms in _medians_ms(steps, phases, frames, WARMUP)]


def skinned_mesh(mesh: SkinnedMesh, influences: int | None) -> SkinnedMesh:
    """``mesh`` with only the ``influences`` strongest weights per vertex (None: as it is)."""
    if influences is None:
        return mesh
    joints, weights = strongest_influences(mesh.joints, mesh.weights, influences)
    return SkinnedMesh(mesh.vertices, mesh.normals, joints, weights, mesh.inverse_bind)


def skin_costs_ms_per_1000(clip: Any, mesh: SkinnedMesh, influences: Sequence[int | None],
                           frames: int = SKIN_FRAMES, seed: int = SEED) -> list[float]:
    """``skin_ms_per_1000`` for each entry of ``influences`` (None: the full skin): linear blend skinning of
    ``mesh``, cut to that many influences, posed by ``clip`` (the poses computed first, only the skinning timed),
    the skins timed interleaved; per 1,000 characters per frame, measured on :data:`SKIN_CHARACTERS`."""
    skins = [skinned_mesh(mesh, k) for k in influences]
    phases = np.random.default_rng(seed).uniform(0.0, 2.0 * float(clip.duration), SKIN_CHARACTERS)
    pose = pose_step(clip, SKIN_CHARACTERS)
    posed: dict[float, CrowdBuffers] = {}
    for frame in range(WARMUP + frames):
        t = phases + frame / FPS
        out = pose(t)
        posed[float(t[0])] = CrowdBuffers(out.rotations.copy(), out.positions.copy())

    def skinning(skin: SkinnedMesh) -> Callable[[np.ndarray], Any]:
        def step(t: np.ndarray) -> Any:
            out = posed[float(t[0])]
            return skin.skin(skin.skinning_matrices(out.rotations, out.positions))
        return step

    medians = _medians_ms([skinning(s) for s in skins], phases, frames, WARMUP)
    return [ms * 1000.0 / SKIN_CHARACTERS for ms in medians]


def run_time_costs(clips: Sequence[BuiltClip], mesh: SkinnedMesh) -> list[dict[str, float]]:
    """Each clip's measured run-time cost (this module's): ``cost_ms_per_1000``, and for the
    reference and each render-time condition ``skin_ms_per_1000`` and ``skin_weights`` (the non-zero skin weights
    of the body it is skinned with: what an engine's per-vertex loop blends); one animation's clips timed
    interleaved."""
    out = [{"cost_ms_per_1000": round(ms, 4)} for ms in pose_costs_ms_per_1000([c.clip for c in clips])]
    skinned = [k for k, c in enumerate(clips) if c.render is not None or c.method == REFERENCE]
    levels = [skin_level(clips[k], mesh.weights) for k in skinned]
    for k, level, ms in zip(skinned, levels, skin_costs_ms_per_1000(clips[0].clip, mesh, levels), strict=True):
        out[k]["skin_ms_per_1000"] = round(ms, 2)
        weights = mesh.weights if level is None else strongest_influences(mesh.joints, mesh.weights, level)[1]
        out[k]["skin_weights"] = int(np.count_nonzero(weights))  # weights blended per character and frame
    return out


def with_run_time_costs(clips: list[BuiltClip], mesh: SkinnedMesh) -> list[BuiltClip]:
    """One animation's built clips (:func:`anim_core.clips.build.build_animation`), each with its measured
    :func:`run_time_costs` in its metrics when any of them is a ladder's level (then every clip of the animation:
    the levels compare with all of them)."""
    if any(c.ladder is not None for c in clips):
        for c, cost in zip(clips, run_time_costs(clips, mesh), strict=True):
            c.metrics.update(cost)
    return clips
