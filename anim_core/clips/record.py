"""The record of one built clip: what :mod:`anim_core.clips.build` makes, :mod:`anim_core.clips.measure` measures
and the server's manifest writes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..math.clip import PlaybackMode
from ..methods.conditions import AnimClip, Kind
from ..rig.character import RetargetedCharacter
from .fidelity import Fidelity

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class BuiltClip:
    """One clip of the set, sampled on its grid, with its metrics."""

    id: str
    animation: str
    kind: Kind
    condition: str
    method: str
    params: dict[str, Any]
    clip: AnimClip
    key_times: Array
    key_rotations: Array
    fps: int
    n_frames: int
    playback: PlaybackMode
    in_place: bool
    root_speed_mps: float
    source: dict[str, Any]
    character: RetargetedCharacter
    local_rotations: Array = field(repr=False)
    root_positions: Array = field(repr=False)
    world_rotations: Array = field(repr=False)
    world_positions: Array = field(repr=False)
    metrics: dict[str, float | None] = field(default_factory=dict)
    fidelity: Fidelity | None = None  # the fidelity gate's verdict (build_animation)
    #: ``(T,)`` metres the ground moves along -Z under a composite shown in place (issue 39), or None
    floor_travel: Array | None = field(default=None, repr=False)
    ladder: str | None = None  # the ladder ([[ladders]]) the condition is a level of, and its level
    level: float | int | None = None
    render: dict[str, Any] | None = None  # per-clip render settings of a render-time condition

    @property
    def times(self) -> Array:
        return np.arange(self.n_frames) / self.fps

    @property
    def duration_s(self) -> float:
        return self.n_frames / self.fps

    def arrays(self) -> dict[str, Array]:
        sk = self.character.skeleton
        return {
            "joint_names": np.array(sk.names), "parents": sk.parents, "offsets": sk.offsets,
            "bind_rotations": self.character.bind_rotations, "bind_positions": self.character.bind_positions,
            "times": self.times, "local_rotations": self.local_rotations, "root_positions": self.root_positions,
            "world_rotations": self.world_rotations, "world_positions": self.world_positions,
            "key_times": self.key_times, "key_rotations": self.key_rotations,
            **({} if self.floor_travel is None else {"floor_travel_m": self.floor_travel}),
        }
