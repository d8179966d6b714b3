"""Cheaper storage of a keyframe clip: key reduction (the ``reduced`` condition) and quantized rotations
(``quantized``).  Offline builders; the results play back as ordinary :class:`~anim_core.math.clip.KeyframeClip` s.

Conventions as in :mod:`anim_core.math.clip`: local rotations ``(K, J, 4)`` scalar first ``(w, x, y, z)``, root
translation ``(K, 3)`` in metres, times in seconds, angles in degrees where the name says ``_deg``.

**Key reduction** (:func:`reduce_keys`) keeps the first and last key and, greedily from the start, makes each
segment as long as it can: from the last kept key ``i`` it tries ``j = i + 2, i + 3, ...`` and keeps the last ``j``
for which every original key between ``i`` and ``j``, played back from the kept keys (nlerp between the two
neighbouring kept keys, exactly as :meth:`KeyframeClip.sample` does), has every joint's *global* (model-space)
rotation within ``tolerance_deg`` of the original and the root within ``root_tolerance_m``.  So the error at the
original key times is at most the tolerance by construction.  Greedy is not optimal in general (a dynamic
programme over all segments would find the fewest keys at ``O(K^2)`` checks), but the first segment that fails
ends the search, so it costs ``O(K L)`` poses for segments of ``L`` keys.

**Quantization** (:func:`quantize_rotations`, per-track range quantization as in ACL's range reduction): each
component of each joint's (sign-continuous) quaternion track is stored as an unsigned ``bits``-bit integer over the
track's own ``[min, max]``; playback dequantizes and normalizes.  The error of one local rotation is bounded (the
tests hold every clip to this bound): each component is off by at most half a step ``(max - min) / (2^bits - 1) /
2``, so the 4-D error ``e`` is at most half the norm of the four steps, the normalized quaternion is at most
``asin(e)`` away on the unit sphere and the rotation at most ``2 asin(e)``.  A global rotation is off by at most the
sum of the bounds of the joint and its ancestors (the angle of a product is at most the sum of the angles).  The
clip keeps its tracks (:class:`QuantizedClip`), so the crowd runtime can hold the integers rather than the float
keys.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..math.clip import KeyframeClip
from ..math.quat import make_continuous, quat_angle
from ..math.skeleton import Skeleton

Array = NDArray[np.float64]

FLOAT_BYTES = 4  # stored values are float32 unless quantized


def _global_rotations(skeleton: Skeleton, rotations: Array, root: Array) -> Array:
    return skeleton.forward_kinematics(rotations, root)[0]


def reduce_keys(clip: KeyframeClip, tolerance_deg: float, root_tolerance_m: float = 0.01) -> KeyframeClip:
    """The fewest keys the greedy search finds (see the module docstring) such that ``clip`` played from them
    stays within ``tolerance_deg`` (every joint's global rotation) and ``root_tolerance_m`` (root position) of
    ``clip`` at each of its key times.  Same playback mode, in-place flag and name."""
    if not tolerance_deg > 0 or not root_tolerance_m > 0:
        raise ValueError(f"tolerances must be positive, got {tolerance_deg} deg and {root_tolerance_m} m")
    sk, times, rot, root = clip.skeleton, clip.times, clip.rotations, clip.root_translation
    original = _global_rotations(sk, rot, root)
    tol = np.radians(tolerance_deg)
    n = clip.n_keys

    def fits(i: int, j: int) -> bool:
        inner = np.arange(i + 1, j)
        probe = KeyframeClip(sk, times[[i, j]], rot[[i, j]], root[[i, j]], "clamp")
        pose = probe.sample(times[inner] - times[i])
        ok_rot = quat_angle(_global_rotations(sk, pose.rotations, pose.root_translation), original[inner]) <= tol
        ok_root = np.linalg.norm(pose.root_translation - root[inner], axis=-1) <= root_tolerance_m
        return bool(ok_rot.all() and ok_root.all())

    kept = [0]
    while kept[-1] < n - 1:
        i = kept[-1]
        j = i + 1
        while j + 1 < n and fits(i, j + 1):  # one candidate segment per round
            j += 1
        kept.append(j)
    k = np.array(kept)
    return KeyframeClip(sk, times[k], rot[k], root[k], clip.mode, clip.in_place, clip.up_axis, clip.name)


@dataclass(frozen=True)
class QuantizedTracks:
    """Rotations ``(K, J, 4)`` stored as ``codes`` (unsigned ints of ``bits`` bits) over per-track ``low`` and
    ``step`` ``(J, 4)``; :meth:`dequantize` gives unit quaternions."""

    codes: NDArray[np.uint32]
    low: Array
    step: Array
    bits: int

    def dequantize(self) -> Array:
        q = self.low + self.codes.astype(np.float64) * self.step
        return q / np.linalg.norm(q, axis=-1, keepdims=True)

    def stored_bytes(self) -> int:
        """Bytes of the packed codes plus ``low`` and ``step`` as float32."""
        return int(np.ceil(self.codes.size * self.bits / 8)) + 2 * self.low.size * FLOAT_BYTES


def quantize_rotations(rotations: Array, bits: int) -> QuantizedTracks:
    """Per-track range quantization of ``rotations (K, J, 4)`` at ``bits`` (2..31) bits per component."""
    if not isinstance(bits, int) or not 2 <= bits <= 31:
        raise ValueError(f"bits must be an integer from 2 to 31, got {bits!r}")
    q = make_continuous(np.asarray(rotations, dtype=np.float64), axis=0)
    low, high = q.min(axis=0), q.max(axis=0)
    levels = 2**bits - 1
    step = (high - low) / levels
    safe = np.where(step > 0, step, 1.0)
    codes = np.clip(np.rint((q - low) / safe), 0, levels).astype(np.uint32)
    return QuantizedTracks(codes, low, step, bits)


@dataclass(frozen=True, eq=False)
class QuantizedClip(KeyframeClip):
    """A keyframe clip whose rotations are its ``tracks`` dequantized (what :meth:`sample` plays); the tracks are
    kept so that a runtime can hold the integers and dequantize them itself (:mod:`anim_core.runtime`)."""

    tracks: QuantizedTracks = field(kw_only=True)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.tracks.codes.shape != self.rotations.shape:
            raise ValueError(f"quantized tracks {self.tracks.codes.shape} do not match the rotations "
                             f"{self.rotations.shape}")


def quantized_clip(clip: KeyframeClip, bits: int) -> tuple[QuantizedClip, QuantizedTracks]:
    """``clip`` with its rotations quantized at ``bits`` bits per component and dequantized (what playback sees),
    and the stored tracks."""
    tracks = quantize_rotations(clip.rotations, bits)
    out = QuantizedClip(clip.skeleton, clip.times, tracks.dequantize(), clip.root_translation, clip.mode,
                        clip.in_place, clip.up_axis, clip.name, tracks=tracks)
    return out, tracks


def keyframe_bytes(n_keys: int, n_joints: int, bits: int | None = None) -> int:
    """Stored bytes of a keyframe clip of ``n_keys`` keys: rotations as float32 (or ``bits``-bit codes plus per-track
    range), root translation and key time as float32."""
    if bits is None:
        rot = n_keys * n_joints * 4 * FLOAT_BYTES
    else:
        rot = int(np.ceil(n_keys * n_joints * 4 * bits / 8)) + 2 * n_joints * 4 * FLOAT_BYTES
    return int(rot + n_keys * (3 + 1) * FLOAT_BYTES)
