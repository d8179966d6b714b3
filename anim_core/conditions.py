"""The registry of conditions: how each way of animating turns one animation's reference into the clip it plays.

A clip set is animations x conditions.  A *condition* (an entry ``[[conditions]]`` of the clip-set file) has an id,
a *method* and the method's parameters; a *method* is registered here once, by name, with

* a parameter model: a pydantic model, frozen, extra fields forbidden, strict types (``int`` stays ``int``,
  ``true`` is no number); validation errors name the field;
* a builder ``build(animation: Animation, params) -> AnimClip``;
* optionally ``stored_bytes(clip, params) -> int``, when the method stores its clip otherwise than as float32 keys
  (quaternion, root translation and time per key: the default of the ``bytes`` metric).

A builder gets one typed description of the animation (:class:`Animation`: its name and kind, the reference
keyframe clip on the frame grid, the base key times on that grid, the period, ``in_place``, the sample rate) and
returns a clip (:data:`AnimClip`); whoever uses a clip reads it through the clip types' own interface
(``duration``, ``mode``, ``sample``, ``key_times``, ``key_rotations``), never by guessing attributes.

Today's methods: ``keyframe`` (the reference: the dense keys themselves, no parameters) and ``hybrid`` (the
thesis method: 2 base keys plus ``increment`` extra keys per interval, mirroring, SQUAD or the spring; ``increment``
0..4).
``hybrid_ik``, ``hybrid_c2``, ``reduced`` and ``quantized`` (issue 16) are registered in
:mod:`anim_core.extra_conditions`.

Adding a method (worked example: hold every pose for ``hold`` frames, a "stepped" look)::

    from pydantic import Field

    from anim_core.clip import KeyframeClip
    from anim_core.conditions import Animation, Params, register

    class SteppedParams(Params):
        hold: int = Field(ge=1, le=8, description="frames each pose is held")

    @register("stepped", SteppedParams)
    def build_stepped(animation: Animation, params: SteppedParams) -> KeyframeClip:
        ref = animation.reference
        step = params.hold / animation.fps
        held = ref.sample((ref.times // step) * step)
        return KeyframeClip(ref.skeleton, ref.times, held.rotations, held.root_translation, ref.mode,
                            ref.in_place, ref.up_axis, ref.name)

and in the clip-set file::

    [[conditions]]
    id = "stepped2"
    method = "stepped"
    params = { hold = 2 }

A method is registered when the module defining it is imported.  The built-in ones are below; a method in a module
of its own is made known to every reader of clip-set files by adding that module's import at the end of this file
(under "methods defined in other modules").  Nothing else changes: the clip-set file, the manifests and the study
server take conditions by id, method and params.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Generic, Literal, TypeVar, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .clip import KeyframeClip
from .hybrid import AnimClip, SpringClip, SquadClip, build_crouch, build_gait, build_idle, build_other

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
    (:mod:`anim_core.keypick`), or given, the first at 0 and, ping-pong, the last at the end); ``period``: seconds
    of one gait cycle or ``other`` loop, or of the forward half of a ping-pong clip (``reference.duration`` in
    every case).
    """

    name: str
    kind: Kind
    reference: KeyframeClip
    key_times: tuple[float, ...]
    period: float
    in_place: bool
    fps: int


P = TypeVar("P", bound=Params)


@dataclass(frozen=True)
class Method(Generic[P]):
    """A registered method: its name, parameter model and builder."""

    name: str
    params: type[P]
    build: Callable[[Animation, P], AnimClip]
    stored_bytes: Callable[[Any, P], int] | None = None


_METHODS: dict[str, Method[Any]] = {}


def register(name: str, params: type[P], stored_bytes: Callable[[Any, P], int] | None = None
             ) -> Callable[[Callable[[Animation, P], AnimClip]], Callable[[Animation, P], AnimClip]]:
    """Decorator: register ``build`` as method ``name`` with parameter model ``params`` (names are unique), and
    ``stored_bytes(clip, params)`` if its clips are not stored as float32 keys."""
    if not (isinstance(params, type) and issubclass(params, Params)):
        raise TypeError(f"the parameters of method {name!r} must be a subclass of anim_core.conditions.Params")

    def decorator(build: Callable[[Animation, P], AnimClip]) -> Callable[[Animation, P], AnimClip]:
        if name in _METHODS:
            raise ValueError(f"method {name!r} is registered already")
        _METHODS[name] = Method(name, params, build, stored_bytes)
        return build

    return decorator


def methods() -> tuple[str, ...]:
    """Names of the registered methods, in registration order."""
    return tuple(_METHODS)


def get_method(name: str) -> Method[Any]:
    try:
        return _METHODS[name]
    except KeyError:
        raise ConditionError(f"unknown method {name!r}; registered: {', '.join(_METHODS)}") from None


def _field_errors(exc: ValidationError) -> str:
    return "; ".join(f"{'.'.join(str(p) for p in e['loc']) or '(params)'}: {e['msg']}" for e in exc.errors())


@dataclass(frozen=True)
class Condition:
    """One condition of a clip set: ``id`` (unique in the set; a clip's id is ``<animation>-<id>``), ``method`` and
    its validated ``params``."""

    id: str
    method: str
    params: Params

    @classmethod
    def parse(cls, id: str, method: str, params: Mapping[str, Any] | None = None) -> Condition:
        """Validate ``params`` with ``method``'s model; errors name the method and each failing field."""
        m = get_method(method)
        try:
            parsed = m.params.model_validate(dict(params or {}))
        except ValidationError as exc:
            raise ConditionError(f"params of method {method!r}: {_field_errors(exc)}") from None
        return cls(id, method, parsed)

    @property
    def is_reference(self) -> bool:
        return self.method == REFERENCE

    def params_dict(self) -> dict[str, Any]:
        return self.params.model_dump()

    def build(self, animation: Animation) -> AnimClip:
        return get_method(self.method).build(animation, self.params)

    def stored_bytes(self, clip: AnimClip) -> int | None:
        """Bytes the method stores ``clip`` in, if it registered how; None: float32 keys."""
        count = get_method(self.method).stored_bytes
        return None if count is None else count(clip, self.params)


# --- the built-in methods ---------------------------------------------------------------------------------------

class KeyframeParams(Params):
    """The reference has no parameters."""


class HybridParams(Params):
    increment: int = Field(ge=0, le=4, description="extra keys per interval between the base keys (thesis: 0..2)")


@register(REFERENCE, KeyframeParams)
def build_keyframe(animation: Animation, params: KeyframeParams) -> KeyframeClip:
    """The reference itself: the dense keys on the grid."""
    return animation.reference


@register("hybrid", HybridParams)
def build_hybrid(animation: Animation, params: HybridParams) -> SquadClip | SpringClip:
    """The thesis's hybrid: a gait mirrors half a cycle of keys onto the other half (SQUAD), a crouch follows its
    keys with the spring, an idle sways on SQUAD between its two extremes, any other motion goes through its picked
    keys on SQUAD, loop or ping-pong as its reference plays (:mod:`anim_core.hybrid`)."""
    ref, keys = animation.reference, list(animation.key_times)
    if animation.kind == "gait":
        # build_gait measures the travel from its source, so it gets the reference travelling.
        travelling = KeyframeClip(ref.skeleton, ref.times, ref.rotations, ref.root_translation, ref.mode,
                                  False, ref.up_axis, ref.name)
        return build_gait(travelling, keys, animation.period, increment=params.increment, in_place=animation.in_place,
                          name=animation.name)
    if animation.kind == "crouch":
        return build_crouch(ref, keys, increment=params.increment, duration=animation.period, time_scale=None,
                            name=animation.name)
    if animation.kind == "idle":
        return build_idle(ref, keys, increment=params.increment, name=animation.name)
    return build_other(ref, keys, increment=params.increment, in_place=animation.in_place, name=animation.name)


# --- methods defined in other modules (imported last: they import ``register`` from here) -----------------------

from . import extra_conditions  # noqa: E402, F401  (hybrid_ik, hybrid_c2, reduced, quantized: issue 16)
