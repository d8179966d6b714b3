"""Blending at run time, ozz-animation style: one job per stage, each validating its buffers before its numba
kernel touches them.

* :class:`SamplingJob`: a keyframe table's local pose (rotations ``(N, J, 4)``, root ``(N, 3)``) of ``N``
  characters at their own times (ozz's SamplingJob): nlerp between the two keys around each time.
* :class:`BlendingJob`: two local poses mixed per character by a weight ``(N,)`` and per joint by a weight
  ``(J,)`` (a joint set: 1 inside, 0 outside), nlerp per joint, the root linearly (ozz's BlendingJob with two
  layers).  Weight 0 writes the first pose and 1 the second, exactly.
* :class:`AdditiveJob`: ``base * nlerp(1, delta, w_j)`` per joint (ozz's additive layer), ``delta (J, 4)`` one
  delta pose for the crowd or ``(N, J, 4)`` one per character; a joint of weight 0 is the base's, exactly.
* :class:`LocalToModelJob`: local pose to model space (forward kinematics, ozz's LocalToModelJob).

Conventions as :mod:`anim_core.runtime.kinds`: float32 poses, float64 times, quaternions (w, x, y, z).  The
sequence a crossfading character runs per frame is sample A, sample B, blend, local-to-model; its cost is measured
by ``animstudy bench --stages blend`` beside keyframe playback (sample, local-to-model) in the same units.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.clip import PLAYBACK_MODES, KeyframeClip
from ..math.skeleton import Skeleton
from .crowd import keyframe_root, numba, uniform
from .kinds import skeleton_arrays

F32 = NDArray[np.float32]
Array = NDArray[np.float64]

if numba is not None:
    from .kernels import local_to_model as _local_to_model_kernel

    # Every kernel here uses only what this file defines: numba's on-disk cache of a kernel is refreshed when its
    # own file changes, not when a function it inlines from another file does (the FK kernel is kernels.py's).
    _njit = numba.njit(cache=True, fastmath=False)

    @_njit
    def _sample_kernel(keys, roots, velocity, params, times, out_rot, out_root):
        dt, duration, mode = params[0], params[1], int(params[2])
        n_keys = keys.shape[0]
        for c in range(times.shape[0]):
            t = times[c]
            cycles = 0.0
            if mode == 0:
                cycles = np.floor(t / duration)
                ct = min(max(t - cycles * duration, 0.0), duration)
            elif mode == 1:
                ct = t % (2.0 * duration)
                if ct > duration:
                    ct = 2.0 * duration - ct
            else:
                ct = min(max(t, 0.0), duration)
            f = ct / dt
            i = min(max(int(np.floor(f)), 0), n_keys - 2)
            a = np.float32(f - i)
            b = np.float32(1.0) - a
            travel = ct + cycles * duration
            for k in range(3):
                out_root[c, k] = b * roots[i, k] + a * roots[i + 1, k] + velocity[k] * travel
            for j in range(keys.shape[1]):
                w = b * keys[i, j, 0] + a * keys[i + 1, j, 0]
                x = b * keys[i, j, 1] + a * keys[i + 1, j, 1]
                y = b * keys[i, j, 2] + a * keys[i + 1, j, 2]
                z = b * keys[i, j, 3] + a * keys[i + 1, j, 3]
                inv = np.float32(1.0) / np.sqrt(w * w + x * x + y * y + z * z)
                out_rot[c, j, 0], out_rot[c, j, 1], out_rot[c, j, 2], out_rot[c, j, 3] = (
                    w * inv, x * inv, y * inv, z * inv)

    @_njit
    def _blend_kernel(a_rot, a_root, b_rot, b_root, weights, joint_weights, out_rot, out_root):
        for c in range(a_rot.shape[0]):
            wc = weights[c]
            for k in range(3):
                out_root[c, k] = a_root[c, k] + (b_root[c, k] - a_root[c, k]) * wc
            for j in range(a_rot.shape[1]):
                w = wc * joint_weights[j]
                if w <= np.float32(0.0):
                    for k in range(4):
                        out_rot[c, j, k] = a_rot[c, j, k]
                elif w >= np.float32(1.0):
                    for k in range(4):
                        out_rot[c, j, k] = b_rot[c, j, k]
                else:
                    dot = (a_rot[c, j, 0] * b_rot[c, j, 0] + a_rot[c, j, 1] * b_rot[c, j, 1]
                           + a_rot[c, j, 2] * b_rot[c, j, 2] + a_rot[c, j, 3] * b_rot[c, j, 3])
                    s = np.float32(1.0) if dot >= 0 else np.float32(-1.0)  # the short way
                    q0 = a_rot[c, j, 0] + (s * b_rot[c, j, 0] - a_rot[c, j, 0]) * w
                    q1 = a_rot[c, j, 1] + (s * b_rot[c, j, 1] - a_rot[c, j, 1]) * w
                    q2 = a_rot[c, j, 2] + (s * b_rot[c, j, 2] - a_rot[c, j, 2]) * w
                    q3 = a_rot[c, j, 3] + (s * b_rot[c, j, 3] - a_rot[c, j, 3]) * w
                    inv = np.float32(1.0) / np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
                    out_rot[c, j, 0], out_rot[c, j, 1], out_rot[c, j, 2], out_rot[c, j, 3] = (
                        q0 * inv, q1 * inv, q2 * inv, q3 * inv)

    @_njit
    def _additive_kernel(base, delta, joint_weights, out_rot):
        per_character = delta.shape[0] > 1
        for c in range(base.shape[0]):
            for j in range(base.shape[1]):
                wj = joint_weights[j]
                bw, bx, by, bz = base[c, j, 0], base[c, j, 1], base[c, j, 2], base[c, j, 3]
                if wj <= np.float32(0.0):
                    out_rot[c, j, 0], out_rot[c, j, 1], out_rot[c, j, 2], out_rot[c, j, 3] = bw, bx, by, bz
                    continue
                d = delta[c if per_character else 0, j]
                # delta^w as nlerp from the identity (ozz's additive weighting)
                dw = np.float32(1.0) + (d[0] - np.float32(1.0)) * wj
                dx, dy, dz = d[1] * wj, d[2] * wj, d[3] * wj
                inv = np.float32(1.0) / np.sqrt(dw * dw + dx * dx + dy * dy + dz * dz)
                dw, dx, dy, dz = dw * inv, dx * inv, dy * inv, dz * inv
                out_rot[c, j, 0] = bw * dw - bx * dx - by * dy - bz * dz
                out_rot[c, j, 1] = bw * dx + bx * dw + by * dz - bz * dy
                out_rot[c, j, 2] = bw * dy - bx * dz + by * dw + bz * dx
                out_rot[c, j, 3] = bw * dz + bx * dy - by * dx + bz * dw

def need_numba() -> None:
    if numba is None:  # pragma: no cover - numba is a dependency
        raise RuntimeError("the blending jobs need numba")


def buffer(name: str, buf: Any, shape: tuple[int, ...]) -> F32:
    """``buf`` if it is a C-contiguous float32 array of ``shape``; ValueError naming the buffer otherwise."""
    if not isinstance(buf, np.ndarray) or buf.dtype != np.float32:
        raise ValueError(f"{name} must be a float32 array, got {getattr(buf, 'dtype', type(buf))}")
    if buf.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {buf.shape}")
    if not buf.flags.c_contiguous:
        raise ValueError(f"{name} must be C-contiguous")
    return buf


def output(name: str, buf: Any, shape: tuple[int, ...]) -> F32:
    out = buffer(name, buf, shape)
    if not out.flags.writeable:
        raise ValueError(f"{name} must be writeable")
    return out


def weights_buffer(name: str, w: Any, shape: tuple[int, ...]) -> F32:
    w = buffer(name, w, shape)
    if not np.all(np.isfinite(w)) or np.any(w < 0) or np.any(w > 1):
        raise ValueError(f"{name} must be finite weights in [0, 1]")
    return w


@dataclass
class LocalPose:
    """Local rotations ``(N, J, 4)`` and root translation ``(N, 3)`` float32 of ``N`` characters."""

    rotations: F32
    root: F32

    @classmethod
    def for_crowd(cls, n: int, joints: int) -> LocalPose:
        return cls(np.empty((n, joints, 4), np.float32), np.empty((n, 3), np.float32))


@dataclass(frozen=True, eq=False)
class SamplingJob:
    """A keyframe clip's uniform keys (float32, sign-continuous), its root without travel and the travel per
    second, and ``params`` = (dt, duration, playback mode index)."""

    skeleton: Skeleton
    keys: F32
    roots: F32
    velocity: F32
    params: Array

    @classmethod
    def from_clip(cls, clip: KeyframeClip) -> SamplingJob:
        if not uniform(clip.times):
            raise ValueError("the sampling job needs keys on a uniform grid")
        root, velocity = keyframe_root(clip)
        return cls(clip.skeleton, np.ascontiguousarray(clip.rotations, np.float32),
                   np.ascontiguousarray(root, np.float32), np.asarray(velocity, np.float32),
                   np.array([clip.times[1] - clip.times[0], clip.duration, PLAYBACK_MODES.index(clip.mode)]))

    @property
    def runtime_bytes(self) -> int:
        return int(self.keys.nbytes + self.roots.nbytes + self.velocity.nbytes + self.params.nbytes)

    def run(self, t: ArrayLike, out: LocalPose) -> LocalPose:
        need_numba()
        times = np.ascontiguousarray(t, np.float64)
        if times.ndim != 1 or not np.all(np.isfinite(times)):
            raise ValueError("times must be a 1-D array of finite seconds, one per character")
        n, j = times.shape[0], self.skeleton.n_joints
        _sample_kernel(self.keys, self.roots, self.velocity, self.params, times,
                       output("output rotations", out.rotations, (n, j, 4)), output("output root", out.root, (n, 3)))
        return out


def blend(a: LocalPose, b: LocalPose, weights: ArrayLike, joint_weights: ArrayLike, out: LocalPose) -> LocalPose:
    """The blending job: ``out = nlerp(a, b, weights[c] * joint_weights[j])`` per character and joint (root: lerp by
    ``weights[c]``).  Every buffer is validated first."""
    need_numba()
    n, j = a.rotations.shape[:2] if isinstance(a.rotations, np.ndarray) and a.rotations.ndim == 3 else (-1, -1)
    if n < 0:
        raise ValueError("pose a rotations must be an (N, J, 4) array")
    _blend_kernel(buffer("pose a rotations", a.rotations, (n, j, 4)), buffer("pose a root", a.root, (n, 3)),
                  buffer("pose b rotations", b.rotations, (n, j, 4)), buffer("pose b root", b.root, (n, 3)),
                  weights_buffer("weights", weights, (n,)), weights_buffer("joint weights", joint_weights, (j,)),
                  output("output rotations", out.rotations, (n, j, 4)), output("output root", out.root, (n, 3)))
    return out


def additive(base: LocalPose, delta: ArrayLike, joint_weights: ArrayLike, out: LocalPose) -> LocalPose:
    """The additive job: ``out = base * nlerp(1, delta, joint_weights[j])``; ``delta (J, 4)`` or ``(N, J, 4)``;
    the root is the base's."""
    need_numba()
    if not isinstance(base.rotations, np.ndarray) or base.rotations.ndim != 3:
        raise ValueError("base rotations must be an (N, J, 4) array")
    n, j = base.rotations.shape[:2]
    d = np.asarray(delta)
    d = buffer("delta", d[None] if d.ndim == 2 else d, (1, j, 4) if d.ndim == 2 else (n, j, 4))
    buffer("base root", base.root, (n, 3))
    _additive_kernel(buffer("base rotations", base.rotations, (n, j, 4)), d,
                     weights_buffer("joint weights", joint_weights, (j,)),
                     output("output rotations", out.rotations, (n, j, 4)))
    out_root = output("output root", out.root, (n, 3))
    if out_root is not base.root:
        out_root[:] = base.root
    return out


def local_to_model(skeleton: Skeleton, pose: LocalPose, out_rotations: F32, out_positions: F32) -> None:
    """The local-to-model job: model-space rotations ``(N, J, 4)`` and positions ``(N, J, 3)``."""
    need_numba()
    j = skeleton.n_joints
    if not isinstance(pose.rotations, np.ndarray) or pose.rotations.ndim != 3:
        raise ValueError("local rotations must be an (N, J, 4) array")
    n = pose.rotations.shape[0]
    _local_to_model_kernel(buffer("local rotations", pose.rotations, (n, j, 4)), buffer("root", pose.root, (n, 3)),
                           *skeleton_arrays(skeleton),
                           output("output rotations", out_rotations, (n, j, 4)),
                           output("output positions", out_positions, (n, j, 3)))
