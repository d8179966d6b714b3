"""One animation of a clip set as the builder takes it: its clip-set entry (:class:`AnimationConfig`), its mocap
on the character (:class:`Source`) and the error a bad entry raises (:class:`ConfigError`).  Made by
:func:`anim_core.clips.build.source_from_bvh`; the stages of :mod:`anim_core.clips.build` read it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from ..math.clip import KeyframeClip, PlaybackMode
from ..math.skeleton import Skeleton
from ..methods.conditions import Kind
from ..rig.character import FEET, RetargetedCharacter
from ..rig.rigmap import UNITS

Array = NDArray[np.float64]

METRES_PER_CMU_UNIT = UNITS["cmu"][0]  # CMU's BVH unit (1 / 0.45 inch)


class ConfigError(ValueError):
    """The clip set configuration is invalid; the message names the file and the entry."""


class KeyCapError(ConfigError):
    """Kind ``other``: ``max_keys`` keys do not reach ``tolerance_mm`` (a larger tolerance may)."""


DEFAULT_TOLERANCE_MM = 20.0  # kind "other": the hybrid through the picked keys stays this close to the reference
DEFAULT_MAX_KEYS = 64  # kind "other": key picking gives up beyond this many keys (clip-set field max_keys)


@dataclass(frozen=True)
class AnimationConfig:
    """One animation of a clip set: ``source`` names its motion file (BVH of any common rig, or glTF; for the
    manifest, the caller reads it), ``frames`` the source frames searched (kind ``other``: played), ``keys``/``cycle``
    source frames that override the automatic picks.

    How the caller reads the source: ``animation`` picks a glTF file's animation by name or index (default: the
    first); ``mapping`` names an explicit joint-mapping file, ``units`` (a key of :data:`anim_core.rig.rigmap.UNITS`)
    and ``up_axis`` (``"y"``/``"z"``) override the detection (:func:`anim_core.rig.normalize.normalize_bvh`).
    ``tolerance_mm`` (kind ``other``): the largest joint position error, mm, of the hybrid through the picked keys
    against the reference; ``max_keys`` (kind ``other``): the most keys the picking may take to reach it.
    ``accept_unfaithful``: build even if the fidelity gate (:mod:`anim_core.clips.fidelity`) fails; the clips are
    marked as such."""

    name: str
    kind: Kind
    source: str
    frames: tuple[int, int]
    playback: PlaybackMode
    in_place: bool
    keys: tuple[int, ...] | None = None
    cycle: tuple[int, int] | None = None
    tolerance_mm: float = DEFAULT_TOLERANCE_MM
    animation: str | int | None = None
    mapping: str | None = None
    units: str | None = None
    up_axis: Literal["y", "z"] | None = None
    accept_unfaithful: bool = False
    max_keys: int = DEFAULT_MAX_KEYS


@dataclass(frozen=True, eq=False)
class Source:
    """One animation's mocap on the character: a travelling clip at the file's frame rate, facing +Z."""

    config: AnimationConfig
    character: RetargetedCharacter
    clip: KeyframeClip  # times from 0 at config.frames[0]; mode "clamp" (it is only sampled inside)
    frame_time: float
    mocap: Skeleton  # the file's own (canonical) skeleton, on which the clip's rotations play unchanged
    metres_per_unit: float = METRES_PER_CMU_UNIT  # of the mocap skeleton
    #: ``(F, 31, 3)`` the canonical joints by the source file's own forward kinematics at config.frames (any units
    #: and orientation: the fidelity gate compares angles)
    own_positions: Array | None = field(default=None, repr=False)
    #: degrees of heading turn taken out of a turning take, first to last frame (:func:`straighten_heading`);
    #: None: the take was not straightened
    straightened_deg: float | None = None

    def time_of(self, frame: int) -> float:
        return (frame - self.config.frames[0]) * self.frame_time

    def positions(self, times: Array) -> Array:
        _, pos = self.character.skeleton.forward_kinematics(*self.clip.sample(times, method="slerp"))
        return pos

    def mocap_feet(self, times: Array) -> Array:
        """``(T, 2, 2, 3)`` ankle and toe positions in metres of the mocap on its own skeleton (not retargeted)."""
        rot, root = self.clip.sample(times, method="slerp")
        _, pos = self.mocap.forward_kinematics(rot, root / self.character.root_scale)
        return pos[:, np.array([self.mocap.indices(f) for f in FEET])] * self.metres_per_unit
