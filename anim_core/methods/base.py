"""What a method's builder receives and is validated by: the animation kinds, the reference method's name, the
base of every parameter model and the typed description of one animation (:class:`Animation`).

The registry of methods is :mod:`anim_core.methods.conditions`; the built-in builders are in
:mod:`anim_core.methods.builders`.  Both build on this module, which imports neither.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict

from ..math.clip import KeyframeClip

Kind = Literal["gait", "crouch", "idle", "other"]
KINDS: tuple[Kind, ...] = get_args(Kind)
REFERENCE = "keyframe"  # the method every other condition is compared with


class ConditionError(ValueError):
    """A condition names an unknown method or has invalid parameters; the message names the entry and field."""


class Params(BaseModel):
    """Base of every method's parameter model: frozen, no extra fields, strict types."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True)


@dataclass(frozen=True, eq=False)
class Animation:
    """One animation as a builder receives it.

    ``reference``: the keyframe clip on the frame grid (``fps`` keys per second; mode ``"loop"`` for a gait, its last
    key repeating the first, ``"pingpong"`` otherwise), already planted and placed as the reference plays;
    ``key_times``: the base keys' times (s) on that grid (gait: left foot forward, left foot passing; crouch:
    standing, deepest; idle: the two extremes of the sway; other: the keys picked within the animation's tolerance
    (:mod:`anim_core.methods.keypick`), or given, the first at 0 and, ping-pong, the last at the end); ``period``:
    seconds
    of one gait cycle or ``other`` loop, or of the forward half of a ping-pong clip (``reference.duration`` in
    every case).  ``bind_rotations``: ``(J, 4)`` global rotations that put the reference's skeleton in the
    character's bind pose (left/right symmetric), about which a gait is mirrored
    (:class:`anim_core.rig.mirror.Mirror`); None: the skeleton's rest pose, which must then be symmetric.
    """

    name: str
    kind: Kind
    reference: KeyframeClip
    key_times: tuple[float, ...]
    period: float
    in_place: bool
    fps: int
    bind_rotations: NDArray[np.float64] | None = field(default=None, repr=False)
