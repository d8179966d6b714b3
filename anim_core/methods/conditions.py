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
``hybrid_ik``, ``hybrid_c2``, ``reduced`` and ``quantized`` (issue 16); ``update_rate``, ``bone_lod`` and
``skin_influences`` (issue 38, :mod:`anim_core.methods.lod`).  A method may name a ``graded`` parameter: the one a
ladder of levels (``[[ladders]]`` of a clip-set file) grades by default.  Every built-in builder and its parameter
model is in :mod:`anim_core.methods.builders`; they are registered at the end of this module, in one list.

Adding a method (worked example: hold every pose for ``hold`` frames, a "stepped" look)::

    from pydantic import Field

    from anim_core.math.clip import KeyframeClip
    from anim_core.methods.conditions import Animation, Params, register

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

A method is registered when :func:`register` is called for it.  The built-in ones are registered at the end of this
module (``BUILT_IN``); a new method is made known to every reader of clip-set files by adding its builder to
:mod:`anim_core.methods.builders` and its entry to ``BUILT_IN``.  Nothing else changes: the clip-set file, the
manifests and the study
server take conditions by id, method and params.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from pydantic import ValidationError

from . import builders as b
from . import composite_builders as cb
from .base import KINDS, REFERENCE, Animation, ConditionError, Kind, Params
from .hybrid import AnimClip

__all__ = [
    "KINDS",
    "REFERENCE",
    "AnimClip",
    "Animation",
    "Condition",
    "ConditionError",
    "Kind",
    "Method",
    "Params",
    "get_method",
    "methods",
    "register",
]

P = TypeVar("P", bound=Params)
#: What an animation of a clip set is: a source take, or a composite (issue 39) of takes in sequence or in layers.
ANIMATION_FORMS = ("take", "sequence", "layered", "blend")


@dataclass(frozen=True)
class Method(Generic[P]):
    """A registered method: its name, parameter model and builder."""

    name: str
    params: type[P]
    build: Callable[[Animation, P], AnimClip]
    stored_bytes: Callable[[Any, P], int] | None = None
    #: its gait clips' second half cycle mirrors the first (the fidelity gate checks the mirrored half)
    mirrors: bool = False
    #: the parameter a ladder of this method grades by default (``[[ladders]]``), or None: no default
    graded: str | None = None
    #: ``refuse(params, fps)``: why these parameters would make the reference itself at a clip rate of ``fps``
    #: keys per second (checked when a clip-set file is read), or None when they do not
    refuse: Callable[[Any, int], str | None] | None = None
    #: ``render(params)``: the per-clip render settings of a render-time condition (the clip is the reference's
    #: motion; the renderer skins it otherwise), or None: the clip's motion is the condition
    render: Callable[[Any], dict[str, Any]] | None = None
    #: the animations it builds clips of: ``"take"`` (a source take), ``"sequence"``, ``"layered"``, ``"blend"``
    #: (composites)
    applies_to: tuple[str, ...] = ("take",)


_METHODS: dict[str, Method[Any]] = {}


def register(name: str, params: type[P], stored_bytes: Callable[[Any, P], int] | None = None, mirrors: bool = False,
             graded: str | None = None, refuse: Callable[[P, int], str | None] | None = None,
             render: Callable[[P], dict[str, Any]] | None = None, applies_to: tuple[str, ...] = ("take",),
             ) -> Callable[[Callable[[Animation, P], AnimClip]], Callable[[Animation, P], AnimClip]]:
    """Decorator: register ``build`` as method ``name`` with parameter model ``params`` (names are unique),
    ``stored_bytes(clip, params)`` if its clips are not stored as float32 keys, ``mirrors`` if a gait's second
    half cycle is the mirror image of its first (the fidelity gate then checks the mirrored half), ``graded``:
    the numeric parameter a ladder (``[[ladders]]`` of a clip-set file) grades unless it names another,
    ``refuse(params, fps)``: a reason why parameters make the reference itself at ``fps`` keys per second (a ladder
    level doing so is refused when the file is read), ``render(params)``: per-clip render settings of a
    render-time condition; ``applies_to``: the animations it builds clips of (:data:`ANIMATION_FORMS`; a clip set
    builds only the pairs that apply)."""
    if not applies_to or any(a not in ANIMATION_FORMS for a in applies_to):
        raise ValueError(f"applies_to of method {name!r}: some of {ANIMATION_FORMS}, got {applies_to!r}")
    if not (isinstance(params, type) and issubclass(params, Params)):
        raise TypeError(f"the parameters of method {name!r} must be a subclass of anim_core.methods.conditions.Params")
    if graded is not None and graded not in params.model_fields:
        raise TypeError(f"method {name!r}: graded parameter {graded!r} is not a field of {params.__name__}")

    def decorator(build: Callable[[Animation, P], AnimClip]) -> Callable[[Animation, P], AnimClip]:
        if name in _METHODS:
            raise ValueError(f"method {name!r} is registered already")
        _METHODS[name] = Method(name, params, build, stored_bytes, mirrors, graded, refuse, render,
                                tuple(applies_to))
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
    its validated ``params``; a level of a ladder (``[[ladders]]``) also carries the ``ladder``'s id and its
    ``level`` (the graded parameter's value)."""

    id: str
    method: str
    params: Params
    ladder: str | None = None
    level: float | int | None = None

    @classmethod
    def parse(cls, id: str, method: str, params: Mapping[str, Any] | None = None, ladder: str | None = None,
              level: float | int | None = None) -> Condition:
        """Validate ``params`` with ``method``'s model; errors name the method and each failing field."""
        m = get_method(method)
        try:
            parsed = m.params.model_validate(dict(params or {}))
        except ValidationError as exc:
            raise ConditionError(f"params of method {method!r}: {_field_errors(exc)}") from None
        return cls(id, method, parsed, ladder, level)

    def render_settings(self) -> dict[str, Any] | None:
        """Per-clip render settings of a render-time condition (e.g. ``{"skin_influences": 2}``), else None."""
        render = get_method(self.method).render
        return None if render is None else render(self.params)

    def refused(self, fps: int) -> str | None:
        """Why this condition would make the reference itself at ``fps`` keys per second, if it would."""
        refuse = get_method(self.method).refuse
        return None if refuse is None else refuse(self.params, fps)

    @property
    def is_reference(self) -> bool:
        return self.method == REFERENCE

    def params_dict(self) -> dict[str, Any]:
        return self.params.model_dump()

    def applies(self, form: str) -> bool:
        """Whether the method builds clips of an animation of ``form`` (:data:`ANIMATION_FORMS`)."""
        return form in get_method(self.method).applies_to

    def build(self, animation: Animation) -> AnimClip:
        return get_method(self.method).build(animation, self.params)

    def stored_bytes(self, clip: AnimClip) -> int | None:
        """Bytes the method stores ``clip`` in, if it registered how; None: float32 keys."""
        count = get_method(self.method).stored_bytes
        return None if count is None else count(clip, self.params)


# --- the methods, registered in this one place ------------------------------------------------------------------

#: (name, parameter model, builder, stored bytes or None, mirrors a gait, graded parameter or None), in the order
#: :func:`methods` lists them; ``REFUSE`` and ``RENDER`` hold the ``refuse`` and ``render`` functions of those that
#: have one.
BUILT_IN: tuple[tuple[str, type[Params], Callable[[Animation, Any], AnimClip], Callable[[Any, Any], int] | None,
                      bool, str | None], ...] = (
    (REFERENCE, b.KeyframeParams, cb.build_reference, None, False, None),
    ("hybrid", b.HybridParams, b.build_hybrid, None, True, "increment"),
    ("hybrid_ik", b.HybridIkParams, b.build_hybrid_ik, b.hybrid_ik_bytes, True, "increment"),
    ("hybrid_c2", b.HybridC2Params, b.build_hybrid_c2, None, True, "increment"),
    ("reduced", b.ReducedParams, b.build_reduced, None, False, "epsilon_deg"),
    ("quantized", b.QuantizedParams, b.build_quantized, b.quantized_bytes, False, "bits"),
    ("update_rate", b.UpdateRateParams, b.build_update_rate, None, False, "rate"),
    ("bone_lod", b.BoneLodParams, b.build_bone_lod, b.bone_lod_bytes, False, "depth"),
    ("skin_influences", b.SkinInfluencesParams, b.build_skin_influences, None, False, "influences"),
)
REFUSE: dict[str, Callable[[Any, int], str | None]] = {"update_rate": b.update_rate_refused}
RENDER: dict[str, Callable[[Any], dict[str, Any]]] = {"skin_influences": b.skin_influences_render}
for _name, _params, _build, _stored, _mirrors, _graded in BUILT_IN:
    register(_name, _params, _stored, _mirrors, _graded, REFUSE.get(_name), RENDER.get(_name),
             applies_to=ANIMATION_FORMS if _name == REFERENCE else ("take",))(_build)
# The transitions of sequences (issue 39; the reference of a composite is its plain form: a sequence's cut, the
# layers as described): anim_core.methods.composite_builders.
for _name, _params, _build, _forms in cb.COMPOSITE_METHODS:
    register(_name, _params, applies_to=_forms)(_build)
