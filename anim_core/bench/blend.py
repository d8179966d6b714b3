"""The ``blend`` stage of the benchmark (issue 39): the run-time blending jobs (:mod:`anim_core.runtime.blending`)
timed beside keyframe playback, in the benchmark's units (median ms per frame for ``N`` characters, and
``ms_per_1000``: ms per 1,000 characters per frame) with the bytes each holds.

Per animation, with its keyframe clip A and the next animation's keyframe clip B (A again if there is one), cases
timed interleaved in the same rounds:

* ``playback``: keyframe playback, the fused table runtime (:class:`anim_core.runtime.TableRuntime`), what the
  ``pose`` stage times;
* ``playback_jobs``: the same as two jobs, sampling then local-to-model;
* ``crossfade``: sample A, sample B, blend (each character its own weight), local-to-model;
* ``crossfade_feet``: the crossfade with its feet held (:mod:`anim_core.methods.transition_feet`, what
  ``foot_lock`` stores in a built clip): the crossfade, then the two-bone IK job
  (:class:`anim_core.runtime.ik.TwoBoneIKJob`) on both legs of every character (the worst case: every character
  mid-transition with both feet down), each ankle's target its blended position plus a held offset of up to
  10 cm (drawn once per character and leg, added per frame in the timed step);
* ``additive``: sample A, an additive upper-body delta, local-to-model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ..clips.record import BuiltClip
from ..math.clip import KeyframeClip
from ..math.quat import quat_from_axis_angle
from ..math.skeleton import Skeleton
from ..methods.footlock import SOFT_REACH
from ..methods.ik import hinge_axis
from ..methods.transitions import CompositeError, joint_mask
from ..rig.character import LEGS
from ..runtime.blending import LocalPose, SamplingJob, additive, blend, local_to_model
from ..runtime.crowd import CrowdBuffers
from ..runtime.ik import TwoBoneIKJob
from ..runtime.offline import runtime_for

Step = Callable[[np.ndarray, int], Any]
CASES = ("playback", "playback_jobs", "crossfade", "crossfade_feet", "additive")


def _steps(a: KeyframeClip, b: KeyframeClip, n: int, seed: int) -> tuple[dict[str, Step], dict[str, int]]:
    sk = a.skeleton
    j = sk.n_joints
    job_a, job_b = SamplingJob.from_clip(a), SamplingJob.from_clip(b)
    table = runtime_for(a)  # a keyframe clip's: the table runtime, what the pose stage times
    buffers = CrowdBuffers.for_crowd(n, j)
    la, lb, lo = LocalPose.for_crowd(n, j), LocalPose.for_crowd(n, j), LocalPose.for_crowd(n, j)
    g_rot, g_pos = np.empty((n, j, 4), np.float32), np.empty((n, j, 3), np.float32)
    weights = np.random.default_rng(seed).uniform(0, 1, n).astype(np.float32)
    ones = np.ones(j, np.float32)
    try:
        upper = joint_mask(sk, "upper_body").astype(np.float32)
    except CompositeError:
        upper = ones
    delta = np.tile(quat_from_axis_angle([0.0, 0.0, 1.0], 0.2).astype(np.float32), (j, 1))

    def playback_jobs(t: np.ndarray, _f: int) -> None:
        local_to_model(sk, job_a.run(t, la), g_rot, g_pos)

    def crossfade(t: np.ndarray, _f: int) -> tuple[np.ndarray, np.ndarray]:
        local_to_model(sk, blend(job_a.run(t, la), job_b.run(t, lb), weights, ones, lo), g_rot, g_pos)
        return g_rot, g_pos

    def add(t: np.ndarray, _f: int) -> None:
        local_to_model(sk, additive(job_a.run(t, la), delta, upper, lo), g_rot, g_pos)

    ik = feet_job(a, b)
    ankles = ik.chains[:, 2].astype(np.intp)
    held = np.random.default_rng(seed + 1).uniform(-0.1, 0.1, (n, len(ankles), 3)).astype(np.float32)
    targets, both = np.empty_like(held), np.ones((n, len(ankles)), np.float32)

    def crossfade_feet(t: np.ndarray, f: int) -> tuple[np.ndarray, np.ndarray]:
        crossfade(t, f)
        np.take(g_pos, ankles, axis=1, out=targets)
        np.add(targets, held, out=targets)
        ik.run(g_rot, g_pos, targets, both)
        return g_rot, g_pos

    steps = {"playback": lambda t, _f: table.pose(t, buffers), "playback_jobs": playback_jobs,
             "crossfade": crossfade, "crossfade_feet": crossfade_feet, "additive": add}
    sizes = {"playback": table.runtime_bytes, "playback_jobs": job_a.runtime_bytes,
             "crossfade": job_a.runtime_bytes + job_b.runtime_bytes,
             "crossfade_feet": job_a.runtime_bytes + job_b.runtime_bytes + ik.runtime_bytes,
             "additive": job_a.runtime_bytes + int(delta.nbytes)}
    return steps, sizes


def feet_job(a: KeyframeClip, b: KeyframeClip) -> TwoBoneIKJob:
    """The IK job of the character's legs (:data:`anim_core.rig.character.LEGS`, as a built clip's ``foot_lock``
    finds them) as a built crossfade of ``a`` into ``b`` holds them: each knee's hinge from both takes' keys, the
    legs' soft reach (:data:`anim_core.methods.footlock.SOFT_REACH` of the shortest)."""
    sk: Skeleton = a.skeleton
    legs = [(int(s), int(m), int(e)) for s, m, e in (sk.indices(leg) for leg in LEGS)]
    rotations = np.concatenate([a.rotations, b.rotations])
    root = np.concatenate([a.root_translation, b.root_translation])
    hinges = []
    for chain in legs:
        try:
            hinges.append(hinge_axis(sk, rotations, root, chain))
        except ValueError:  # straight in every key: any axis across the leg costs the same
            hinges.append(np.array([1.0, 0.0, 0.0]))
    soft = SOFT_REACH * min(float(np.linalg.norm(sk.offsets[m]) + np.linalg.norm(sk.offsets[e])) for _, m, e in legs)
    return TwoBoneIKJob.for_legs(sk, legs, hinges, soft)


def blend_stage(clips: Sequence[BuiltClip], characters: Sequence[int], frames: int, warmup: int,
                rng: np.random.Generator, timer: Callable[..., dict[int, list[float]]]
                ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Result rows (stage ``blend``, variant ``keys``, one thread) and memory rows of every case per animation and
    crowd size; ``timer(cases, phases, frames, warmup)`` is the benchmark's interleaved timer."""
    from .suite import Case

    keyframes = [c for c in clips if c.method == "keyframe" and isinstance(c.clip, KeyframeClip)]
    results: list[dict[str, Any]] = []
    memory: list[dict[str, Any]] = []
    for k, c in enumerate(keyframes):
        other = keyframes[(k + 1) % len(keyframes)]
        b = other.clip if other.clip.skeleton is c.clip.skeleton else c.clip
        for n in characters:
            steps, sizes = _steps(c.clip, b, n, int(rng.integers(1 << 31)))
            phases = rng.uniform(0.0, 2 * c.clip.duration, n)
            cases = [Case(c.animation, name, name, None, "keys", steps[name]) for name in CASES]
            timed = timer(cases, phases, frames, warmup)
            for i, case in enumerate(cases):
                ms = np.asarray(timed[i])
                median = float(np.median(ms))
                results.append({"animation": c.animation, "condition": case.condition, "method": case.method,
                                "increment": None, "variant": "keys", "stage": "blend", "characters": n,
                                "threads": 1, "median_ms": median, "p95_ms": float(np.percentile(ms, 95)),
                                "fps": 1000.0 / median, "frames": len(ms), "ms_per_1000": median / n * 1000.0,
                                "runtime_bytes": sizes[case.method]})
        memory += [{"clip": f"{c.animation}-{name}", "animation": c.animation, "method": name,
                    "runtime_bytes": sizes[name]} for name in CASES]
    return results, memory


def format_blend(results: Sequence[dict[str, Any]]) -> str:
    """The blend stage's rows as a table: ms per 1,000 characters per frame and runtime bytes per case."""
    rows = [r for r in results if r["stage"] == "blend"]
    if not rows:
        return ""
    lines = ["\nblend stage: ms per 1,000 characters per frame (median), runtime bytes; one thread"]
    for animation in dict.fromkeys(r["animation"] for r in rows):
        for n in sorted({r["characters"] for r in rows if r["animation"] == animation}):
            cells = [f"{r['method']} {r['ms_per_1000']:.3g} ms ({r['runtime_bytes']} B)" for r in rows
                     if r["animation"] == animation and r["characters"] == n]
            lines.append(f"{animation} x{n}: " + ", ".join(cells))
    return "\n".join(lines) + "\n"
