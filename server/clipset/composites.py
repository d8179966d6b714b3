"""Composite animations of a clip-set file (issue 39): ``[animations.NAME]`` entries with ``sequence = [...]`` or
``base`` + ``layers``, read and validated here (errors name the file, the entry and the field; nothing is built
from a file with an error), and built from the takes they name (:func:`build_composites`).  The format is
documented in docs/motion/clip-sets.md, *Composite animations*.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from anim_core.clips.build import AnimationConfig, ConfigError
from anim_core.clips.composite import CompositeSpec, LayerSpec, build_composite
from anim_core.clips.record import BuiltClip
from anim_core.methods.conditions import Condition
from anim_core.methods.transitions import ENTRIES, JOINT_SETS

#: The longest segment of a sequence, seconds (a stimulus is seconds long; minutes are a mistake).
MAX_SEGMENT_S = 120.0
ROOT_MOTION = ("travel", "in_place")
LAYER_MODES = ("override", "additive")


def is_composite(entry: Any) -> bool:
    """Whether an ``[animations.NAME]`` table describes a composite (it has ``sequence``, ``base``, ``layers`` or
    ``blend``)."""
    return isinstance(entry, dict) and any(k in entry for k in ("sequence", "base", "layers", "blend"))


def _seconds(value: Any, where: str, fps: int) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{where} seconds: a number of seconds, got {value!r}")
    if not 0 < value <= MAX_SEGMENT_S:
        raise ConfigError(f"{where} seconds: 0 < seconds <= {MAX_SEGMENT_S:g}, got {value!r}")
    if abs(value * fps - round(value * fps)) > 1e-6:
        raise ConfigError(f"{where} seconds: a whole number of frames at {fps} fps, got {value!r}")
    return float(value)


def _take(name: Any, takes: Mapping[str, AnimationConfig], where: str) -> str:
    if not isinstance(name, str) or name not in takes:
        raise ConfigError(f"{where} animation: {name!r} is no take of this file (a composite names takes: "
                          f"{', '.join(takes) or 'none'})")
    return name


def _travels(cfg: AnimationConfig) -> bool:
    return cfg.playback == "loop" and not cfg.in_place


def _blend(name: str, entry: dict[str, Any], takes: Mapping[str, AnimationConfig], where: str) -> CompositeSpec:
    if unknown := sorted(set(entry) - {"blend"}):
        raise ConfigError(f"{where}: unknown field {unknown[0]!r} of a blend; allowed: blend")
    raw = entry["blend"]
    if not isinstance(raw, list) or len(raw) != 2:
        raise ConfigError(f"{where} blend: a list of 2 takes [\"A\", \"B\"] (a parametric condition mixes them), "
                          f"got {raw!r}")
    pair = tuple(_take(n, takes, f"{where} blend #{k}") for k, n in enumerate(raw, 1))
    if pair[0] == pair[1]:
        raise ConfigError(f"{where} blend: two different takes, got {pair[0]!r} twice")
    for n in pair:
        if takes[n].playback != "loop":
            raise ConfigError(f"{where} blend: both takes loop (their cycles are mapped onto one phase); {n!r} "
                              f"plays {takes[n].playback!r}")
    if takes[pair[0]].in_place != takes[pair[1]].in_place:
        raise ConfigError(f"{where} blend: the takes are played alike, both in place or both travelling; "
                          f"{pair[0]!r} in_place = {str(takes[pair[0]].in_place).lower()}, {pair[1]!r} "
                          f"in_place = {str(takes[pair[1]].in_place).lower()}")
    return CompositeSpec(name, "blend", blend=pair)


def parse_composite(name: str, entry: dict[str, Any], takes: Mapping[str, AnimationConfig], fps: int,
                    where: str) -> CompositeSpec:
    """One composite entry, validated against the file's takes."""
    if "blend" in entry:
        return _blend(name, entry, takes, where)
    if "sequence" in entry:
        if unknown := sorted(set(entry) - {"sequence", "root_motion", "entry"}):
            raise ConfigError(f"{where}: unknown field {unknown[0]!r} of a sequence; allowed: entry, root_motion, "
                              f"sequence")
        raw = entry["sequence"]
        if not isinstance(raw, list) or len(raw) < 2:
            raise ConfigError(f"{where} sequence: a list of at least 2 {{ animation = ..., seconds = ... }}")
        segments = []
        for k, seg in enumerate(raw, 1):
            here = f"{where} sequence #{k}"
            if not isinstance(seg, dict) or set(seg) != {"animation", "seconds"}:
                raise ConfigError(f"{here}: a table {{ animation = \"NAME\", seconds = S }}, got {seg!r}")
            segments.append((_take(seg["animation"], takes, here), _seconds(seg["seconds"], here, fps)))
        root_motion = entry.get("root_motion")
        if root_motion is not None and root_motion not in ROOT_MOTION:
            raise ConfigError(f"{where} root_motion: one of {', '.join(map(repr, ROOT_MOTION))}, got {root_motion!r}")
        if root_motion is None and len({_travels(takes[n]) for n, _ in segments}) > 1:
            raise ConfigError(f"{where} root_motion: the sequence mixes takes played in place with travelling ones; "
                              f"say root_motion = \"travel\" (each take with its travel) or \"in_place\"")
        enter = entry.get("entry", "matched")
        if enter not in ENTRIES:
            raise ConfigError(f"{where} entry: where each take after the first is entered, one of "
                              f"{', '.join(map(repr, ENTRIES))}, got {enter!r}")
        return CompositeSpec(name, "sequence", tuple(segments), root_motion, entry=enter)
    if unknown := sorted(set(entry) - {"base", "layers"}):
        raise ConfigError(f"{where}: unknown field {unknown[0]!r} of a layered animation; allowed: base, layers")
    base = _take(entry.get("base"), takes, f"{where} base")
    raw_layers = entry.get("layers")
    if not isinstance(raw_layers, list) or not raw_layers:
        raise ConfigError(f"{where} layers: a list of {{ animation, joints, mode }} tables")
    layers = []
    for k, layer in enumerate(raw_layers, 1):
        here = f"{where} layers #{k}"
        if not isinstance(layer, dict):
            raise ConfigError(f"{here}: a table {{ animation, joints, mode }}")
        if unknown := sorted(set(layer) - {"animation", "joints", "mode", "reference_pose"}):
            raise ConfigError(f"{here}: unknown field {unknown[0]!r}; allowed: animation, joints, mode, "
                              f"reference_pose")
        joints = layer.get("joints")
        if joints not in JOINT_SETS:
            raise ConfigError(f"{here} joints: unknown joint set {joints!r}; known: {', '.join(JOINT_SETS)}")
        mode = layer.get("mode")
        if mode not in LAYER_MODES:
            raise ConfigError(f"{here} mode: 'override' or 'additive', got {mode!r}")
        reference = layer.get("reference_pose", "first")
        if "reference_pose" in layer and mode != "additive":
            raise ConfigError(f"{here} reference_pose: only an additive layer has a reference pose")
        if reference not in ("first", "rest") and (isinstance(reference, bool) or not isinstance(reference, int)
                                                   or reference < 0):
            raise ConfigError(f"{here} reference_pose: 'first', 'rest' or a frame number, got {reference!r}")
        layers.append(LayerSpec(_take(layer.get("animation"), takes, here), joints, mode, reference))
    return CompositeSpec(name, "layered", (), None, base, tuple(layers))


def check_transitions(composites: Mapping[str, CompositeSpec], conditions: Sequence[Condition], path: Path) -> None:
    """Every transition fits: a condition's ``duration_ms`` is at most the shortest segment of every sequence."""
    for spec in composites.values():
        if spec.form != "sequence":
            continue
        shortest = min(s for _, s in spec.segments)
        for c in conditions:
            ms = getattr(c.params, "duration_ms", None)
            if c.applies("sequence") and ms is not None and ms / 1000.0 > shortest:
                raise ConfigError(f"{path} [[conditions]] id = {c.id!r} duration_ms: {ms} ms is longer than the "
                                  f"shortest segment of [animations.{spec.name}] ({shortest:g} s)")


def split_composites(table: dict[str, Any], fps: int, path: Path | str,
                     parse_take: Callable[[str, Any, str], AnimationConfig], prefix: str = "animations"
                     ) -> tuple[dict[str, AnimationConfig], dict[str, CompositeSpec]]:
    """The ``[animations]`` table as takes (parsed by ``parse_take``) and composites (validated against them);
    errors name ``path`` and ``[PREFIX.NAME]`` (a study file's inline tables: ``prefix = "clips.animations"``)."""
    takes = {name: parse_take(name, entry, f"{path} [{prefix}.{name}]") for name, entry in table.items()
             if not is_composite(entry)}
    composites = {}
    for name, entry in table.items():
        if is_composite(entry):
            where = f"{path} [{prefix}.{name}]"
            parse_take_name_only(name, where)
            composites[name] = parse_composite(name, entry, takes, fps, where)
    return takes, composites


def parse_take_name_only(name: str, where: str) -> None:
    from .config import NAME

    if not NAME.fullmatch(name):
        raise ConfigError(f"{where}: an animation name is 1..32 lower-case letters, digits or '_' (no '-')")


def build_composites(data_dir: Path, character: Any, composites: Mapping[str, CompositeSpec],
                     takes: Mapping[str, AnimationConfig], fps: int, conditions: Sequence[Condition],
                     relocate: tuple[str, ...], progress: Callable[[str], None] = lambda _msg: None
                     ) -> list[BuiltClip]:
    """The clips of every composite (its takes' motion files read again, in this process)."""
    from .build import load_source

    out: list[BuiltClip] = []
    for spec in composites.values():
        progress(f"{spec.name}: composite ({spec.form}) of {', '.join(spec.takes)}")
        sources = {n: load_source(data_dir, character, takes[n], relocate) for n in spec.takes}
        out += build_composite(spec, sources, fps, conditions, progress)
    return out
