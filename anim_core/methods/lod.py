"""Level-of-detail conditions from the seed articles (issue 38): cheaper ways to pose a character, each graded.

* :class:`HeldClip` (method ``update_rate``): the reference's pose re-evaluated ``rate`` times a second and held in
  between, on the reference's own time grid: the update times are ``k / rate`` seconds of running time, each
  moved to the first frame of the grid at or after it, and every frame shows the reference's key of the last
  update frame.  At 30 frames a second a rate of 6 holds every pose 5 frames; a rate of 4 holds them 7 or 8 frames
  in turn (7.5 on average).  A loop restarts its updates at its seam (its last hold may be shorter); a ping-pong
  clip holds on its running time, forward and back.  Its runtime (:class:`anim_core.runtime.HeldCrowd`) poses a
  character only in the frames where its held time changes.
* :func:`frozen_joints` (method ``bone_lod``): the joints of a named set (``fingers``, ``toes``, ``neck``) or those
  deeper in the hierarchy than ``depth`` (the root is depth 0) held at their bind pose; every other joint's keys
  are the reference's, bit for bit.  Its runtime is the table runtime with those joints inactive (they hold the
  clip's first key, which is their bind pose).
* :func:`strongest_influences` (method ``skin_influences``): a render-time condition.  The clip is the reference's
  motion; the renderer skins it with only the ``influences`` (1 to 4) strongest skin weights of each vertex,
  renormalised to sum to 1 (the blending formula of the seed articles for 1 to 4 weights).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.clip import KeyframeClip, Pose
from ..math.quat import quat_conj, quat_mul
from ..math.skeleton import Skeleton

Array = NDArray[np.float64]
#: Named joint sets of ``bone_lod``: a joint belongs to a set when its name contains one of the patterns.
JOINT_SETS: dict[str, tuple[str, ...]] = {
    "fingers": ("Finger", "Index", "Thumb"),
    "toes": ("Toe",),
    "neck": ("Neck",),
}
JointSet = Literal["fingers", "toes", "neck"]
_EPS = 1e-6  # frames: running times within this of a frame count as on it


def held_frames(frames: NDArray[np.int64], rate: float, fps: int) -> NDArray[np.int64]:
    """The frame of the last update at or before each running frame: updates at ``k / rate`` seconds, each on the
    first grid frame at or after it (``ceil(k * fps / rate)``)."""
    k = np.floor(frames * (rate / fps) + 1e-9)
    return np.ceil(k * (fps / rate) - 1e-9).astype(np.int64)


@dataclass(frozen=True, eq=False)
class HeldClip:
    """The keyframe clip ``base`` (the reference, keys on a grid of ``fps`` a second) updated ``rate`` times a second
    and held in between (module docstring).  It reads like any clip: :attr:`duration`, :attr:`mode`,
    :meth:`sample`, :attr:`key_times` (the update frames of one period, the keys it stores) and
    :attr:`key_rotations`."""

    base: KeyframeClip
    rate: float
    fps: int
    #: ``(P,)`` for each running frame of one period, the base key it shows
    shown: NDArray[np.int64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not 0 < self.rate < self.fps:
            raise ValueError(f"an update rate is below the clip's own rate of {self.fps} keys per second, got "
                             f"{self.rate}")
        n = self.base.n_keys - 1
        period = n if self.base.mode == "loop" else 2 * n
        held = held_frames(np.arange(period), self.rate, self.fps)
        shown = held if self.base.mode == "loop" else np.where(held <= n, held, 2 * n - held)
        object.__setattr__(self, "shown", shown)

    @property
    def skeleton(self) -> Skeleton:
        return self.base.skeleton

    @property
    def duration(self) -> float:
        return self.base.duration

    @property
    def mode(self) -> str:
        return self.base.mode

    @property
    def in_place(self) -> bool:
        return self.base.in_place

    @property
    def up_axis(self) -> int:
        return self.base.up_axis

    @property
    def name(self) -> str:
        return self.base.name

    @property
    def velocity(self) -> Array:
        return self.base.velocity

    @property
    def key_times(self) -> Array:
        return self.base.times[np.unique(self.shown)]

    @property
    def key_rotations(self) -> Array:
        return self.base.rotations[np.unique(self.shown)]

    def held(self, t: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """For running times ``t`` (s): the base key shown and the number of whole periods played before."""
        t = np.asarray(t, dtype=np.float64)
        period = self.shown.size
        frame = np.floor(t * self.fps + _EPS).astype(np.int64)
        return self.shown[frame % period], frame // period

    def held_time(self, t: ArrayLike) -> Array:
        """The running time (s) of the pose shown at running times ``t``: the last update's frame."""
        t = np.asarray(t, dtype=np.float64)
        period = self.shown.size
        frame = np.floor(t * self.fps + _EPS).astype(np.int64)
        held = held_frames(frame % period, self.rate, self.fps)
        return (frame // period * period + held) / self.fps

    def sample(self, t: ArrayLike, method: str = "nlerp") -> Pose:
        """The pose shown at running times ``t``: the base's key of the last update, exactly (no interpolation)."""
        key, cycles = self.held(t)
        base = self.base
        rot = base.rotations[key]
        root = base.root_translation[key]
        if base.in_place:
            root = root - base.velocity * base.times[key][..., None]
        elif base.mode == "loop":
            root = root + base.velocity * (cycles * base.duration)[..., None]
        return Pose(rot, root)


def joint_depths(skeleton: Skeleton) -> NDArray[np.int64]:
    """``(J,)`` each joint's depth in the hierarchy: the root 0, its children 1, ... (parents come first)."""
    depth = np.zeros(skeleton.n_joints, np.int64)
    for j, p in enumerate(skeleton.parents):  # once per skeleton, at build time: not a hot path
        depth[j] = 0 if p < 0 else depth[p] + 1
    return depth


def frozen_joints(skeleton: Skeleton, joints: str | None, depth: int | None) -> NDArray[np.bool_]:
    """``(J,)`` the joints ``bone_lod`` holds: those of the named set ``joints`` (:data:`JOINT_SETS`), or those
    deeper than ``depth``.  A set the skeleton has no joint of, or a depth below which it has none, is a
    ValueError naming it."""
    if joints is not None:
        patterns = JOINT_SETS[joints]
        mask = np.array([any(p in name for p in patterns) for name in skeleton.names], bool)
        if not mask.any():
            raise ValueError(f"bone_lod joints = {joints!r}: the character has no joint of that set (no joint name "
                             f"contains {' or '.join(repr(p) for p in patterns)})")
        return mask
    assert depth is not None
    depths = joint_depths(skeleton)
    mask = depths > depth
    if not mask.any():
        raise ValueError(f"bone_lod depth = {depth}: the character has no joint deeper than {depth} (its deepest is "
                         f"{int(depths.max())}), so the clip would be the reference")
    return mask


@dataclass(frozen=True, eq=False)
class BoneLodClip(KeyframeClip):
    """A keyframe clip some of whose joints (``frozen`` ``(J,)``) hold one pose throughout (:func:`bone_lod`)."""

    frozen: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool), repr=False)


def bone_lod(reference: KeyframeClip, frozen: NDArray[np.bool_], bind_rotations: Array | None) -> BoneLodClip:
    """``reference`` with the ``frozen`` joints' local rotations set, at every key, to their bind pose (local
    rotations from the global ``bind_rotations (J, 4)``; None: the skeleton's rest, identity); the other joints'
    keys are the reference's own arrays."""
    sk = reference.skeleton
    if bind_rotations is None:
        local = np.zeros((sk.n_joints, 4))
        local[:, 0] = 1.0
    else:
        g = np.asarray(bind_rotations, np.float64)
        parents = np.asarray(sk.parents)
        parent_g = np.where((parents >= 0)[:, None], g[np.maximum(parents, 0)], np.array([1.0, 0.0, 0.0, 0.0]))
        local = quat_mul(quat_conj(parent_g), g)
    rot = np.array(reference.rotations)
    rot[:, frozen] = local[frozen]
    return BoneLodClip(sk, reference.times, rot, reference.root_translation, reference.mode, reference.in_place,
                       reference.up_axis, reference.name, frozen=np.asarray(frozen, bool))


def strongest_influences(joints: NDArray[np.intp], weights: Array, k: int) -> tuple[NDArray[np.intp], Array]:
    """Skin influences ``joints``/``weights (V, K)`` cut to the ``k`` strongest per vertex (ties: the earlier
    slot), renormalised to sum to 1; a vertex with at most ``k`` non-zero weights keeps its row unchanged (bit for
    bit).  Returns ``(V, k)`` arrays."""
    weights = np.asarray(weights, np.float64)
    joints = np.asarray(joints)
    if not 1 <= k <= weights.shape[1]:
        raise ValueError(f"influences must be 1..{weights.shape[1]}, got {k}")
    order = np.argsort(-weights, axis=1, kind="stable")[:, :k]
    kept_w = np.take_along_axis(weights, order, axis=1)
    kept_j = np.take_along_axis(joints, order, axis=1)
    dropped = np.count_nonzero(weights, axis=1) > k
    total = kept_w.sum(axis=1, keepdims=True)
    kept_w = np.where(dropped[:, None], kept_w / np.where(total > 0, total, 1.0), kept_w)
    return kept_j, kept_w


def max_influences(weights: Array) -> int:
    """The most non-zero weights any vertex has."""
    return int(np.count_nonzero(np.asarray(weights), axis=1).max())
