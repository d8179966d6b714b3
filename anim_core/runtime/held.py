"""The held-update path of the crowd runtime (method ``update_rate``, :class:`anim_core.methods.lod.HeldClip`):
each character's pose is evaluated at the clip's update rate and held in between.

A :class:`HeldCrowd` keeps, per character, the running time of the pose it shows.  Each frame it works out every
character's held time (the last update's frame on the clip's grid, numpy, ``O(N)``), poses only the characters
whose held time changed since the previous frame (into a scratch buffer, by the base clip's own runtime kernel)
and copies their poses into the crowd's buffers; every other character keeps its buffers as they were.  At a
display clock of 60 frames a second and an update rate of ``r``, about ``r / 60`` of the crowd is posed a frame.
The first frame poses everyone.  :class:`HeldRuntime` is what :func:`anim_core.runtime.runtime_for` returns for a
held clip: stateless, it poses every character at its held time (what the crowd shows, for accuracy checks), and
makes the stateful :class:`HeldCrowd` that skips the unchanged ones (what the benchmark and the clip costs time).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.skeleton import Skeleton
from ..methods.lod import HeldClip
from .crowd import CrowdBuffers
from .kinds import AnyRuntime


@dataclass(frozen=True, eq=False)
class HeldRuntime:
    """The runtime of a held clip: ``base``, the runtime of ``clip.base``, evaluated at held times."""

    clip: HeldClip
    base: AnyRuntime

    @property
    def skeleton(self) -> Skeleton:
        return self.base.skeleton

    @property
    def runtime_bytes(self) -> int:
        return self.base.runtime_bytes

    def pose(self, t: ArrayLike, out: CrowdBuffers | None = None, parallel: bool = False,
             active: NDArray[np.uint8] | None = None, first: int = 0, stride: int = 1) -> CrowdBuffers:
        """Every character (of ``first, first + stride, ...``) posed at its held time: the poses shown."""
        return self.base.pose(self.clip.held_time(t), out, parallel, active, first, stride)

    def crowd(self, n: int) -> HeldCrowd:
        """``n`` characters posed only when their held pose changes."""
        return HeldCrowd(self.clip, self.base, n)


@dataclass(eq=False)
class HeldCrowd:
    """``n`` characters playing ``clip`` through ``runtime`` (the runtime of ``clip.base``), each re-posed only
    when its held pose changes.  :attr:`out` holds the poses shown."""

    clip: HeldClip
    runtime: AnyRuntime
    n: int
    out: CrowdBuffers = field(init=False)
    posed: int = field(init=False, default=0)  # characters posed by the last call
    _scratch: CrowdBuffers = field(init=False, repr=False)
    _shown: NDArray[np.float64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        j = self.runtime.skeleton.n_joints
        self.out = CrowdBuffers.for_crowd(self.n, j)
        self._scratch = CrowdBuffers.for_crowd(self.n, j)
        self._shown = np.full(self.n, np.nan)

    def pose(self, t: ArrayLike, parallel: bool = False) -> CrowdBuffers:
        """The crowd's poses at running times ``t (N,)`` seconds: characters whose held time changed re-posed."""
        held = self.clip.held_time(t)
        changed = np.flatnonzero(held != self._shown)  # NaN (never posed) differs from everything
        m = int(changed.size)
        self.posed = m
        if m:
            part = CrowdBuffers(self._scratch.rotations[:m], self._scratch.positions[:m])
            self.runtime.pose(held[changed], part, parallel)
            self.out.rotations[changed] = part.rotations
            self.out.positions[changed] = part.positions
            self._shown[changed] = held[changed]
        return self.out
