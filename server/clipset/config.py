"""The clip-set file (TOML): animations x conditions.  Read and validated here only; errors name the file, the
entry and the field.  The format is documented in docs/motion/clip-sets.md."""

from __future__ import annotations

import dataclasses
import re
import tomllib
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any

from anim_core.clips.build import ConfigError
from anim_core.clips.entry import DEFAULT_MAX_KEYS, DEFAULT_TOLERANCE_MM, AnimationConfig
from anim_core.math.clip import PLAYBACK_MODES
from anim_core.methods.conditions import KINDS, REFERENCE, Condition, ConditionError, get_method
from anim_core.rig.rigmap import UNITS

DEFAULT_CONFIG = Path(__file__).with_name("thesis.toml")
#: The one rule for animation names and condition ids, wherever they are given (clip-set files, uploads, study
#: designs): a clip's id is ``<animation>-<condition>``, so neither holds a "-".
NAME_PATTERN = r"^[a-z0-9][a-z0-9_]{0,31}$"
NAME = re.compile(NAME_PATTERN)
#: A ladder has at least this many levels (fewer give no psychometric function).
MIN_LADDER_LEVELS = 3
#: The largest ``max_keys`` a clip-set entry may give: each key picked costs a pass of the hybrid over the take.
MAX_KEYS_LIMIT = 1000


@dataclass(frozen=True)
class CharacterConfig:
    """``[character]``'s choice of body: ``gltf`` None is the MakeHuman character of the data directory, else a
    skinned glTF file (path under the data directory or absolute) with an optional explicit joint ``mapping``
    file and ``units``/``up_axis`` overrides (docs/motion/your-own-motion.md, *A glTF character*)."""

    gltf: str | None = None
    mapping: str | None = None
    units: str | None = None
    up_axis: str | None = None


@dataclass(frozen=True)
class ClipSetConfig:
    fps: int
    relocate: tuple[str, ...]
    animations: dict[str, AnimationConfig]
    conditions: tuple[Condition, ...]
    character: CharacterConfig = CharacterConfig()
    #: composite animations (issue 39: sequences, layers), by name: server/clipset/composites.py
    composites: dict[str, Any] = dataclass_field(default_factory=dict)


def _frames(value: Any, where: str, count: int | None = None) -> tuple[int, ...]:
    if (not isinstance(value, list) or not all(isinstance(v, int) and v >= 0 for v in value)
            or (count is not None and len(value) != count) or list(value) != sorted(set(value))):
        n = f"{count} " if count else ""
        raise ConfigError(f"{where} must be a list of {n}increasing frame numbers, got {value!r}")
    return tuple(value)


def _animation(name: str, entry: Any, where: str) -> AnimationConfig:
    if not NAME.fullmatch(name):
        raise ConfigError(f"{where}: an animation name is 1..32 lower-case letters, digits or '_' (no '-')")
    if not isinstance(entry, dict):
        raise ConfigError(f"{where} must be a table")
    known = {"kind", "source", "frames", "playback", "in_place", "keys", "cycle", "tolerance_mm", "animation",
             "mapping", "units", "up_axis", "accept_unfaithful", "max_keys"}
    if unknown := sorted(set(entry) - known):
        raise ConfigError(f"{where}: unknown field {unknown[0]!r}; allowed: {', '.join(sorted(known))}")
    kind = entry.get("kind")
    if kind not in KINDS:
        raise ConfigError(f"{where}: kind must be {', '.join(repr(k) for k in KINDS)}, got {kind!r}")
    source = entry.get("source")
    if not isinstance(source, str) or not source.strip():
        raise ConfigError(f"{where}: source must name a motion file (.bvh, .bvh.gz, .glb or .gltf) under the data "
                          f"directory or by an absolute path")
    gltf = source.lower().endswith((".glb", ".gltf"))
    if not gltf and not source.lower().endswith((".bvh", ".bvh.gz")):
        raise ConfigError(f"{where} source: {source!r} is not a motion file; expected .bvh, .bvh.gz, .glb or .gltf")
    playback = entry.get("playback", "loop" if kind == "gait" else "pingpong")
    if playback not in PLAYBACK_MODES[:2]:
        raise ConfigError(f"{where}: playback must be 'loop' or 'pingpong', got {playback!r}")
    if kind != "other" and (kind == "gait") != (playback == "loop"):
        raise ConfigError(f"{where}: a {kind} plays {'loop' if kind == 'gait' else 'pingpong'} in the hybrid "
                          f"method, so its keyframe clip must too (kind 'other' plays either)")
    in_place = entry.get("in_place", kind == "gait")
    if not isinstance(in_place, bool):
        raise ConfigError(f"{where}: in_place must be true or false")
    if kind == "other" and in_place and playback != "loop":
        raise ConfigError(f"{where}: in_place takes out the travel of a loop; a ping-pong clip plays its keys "
                          f"where they are (set playback = 'loop' or drop in_place)")
    frames = _frames(entry.get("frames"), f"{where} frames", 2)
    keys = entry.get("keys")
    cycle = entry.get("cycle")
    if cycle is not None and kind != "gait":
        raise ConfigError(f"{where}: only a gait has a cycle")
    if keys is not None:
        keys = _frames(keys, f"{where} keys", None if kind == "other" else 2)
        if kind == "other":
            _other_keys(keys, frames, playback, where)
    tolerance = entry.get("tolerance_mm", DEFAULT_TOLERANCE_MM)
    if "tolerance_mm" in entry and kind != "other":
        raise ConfigError(f"{where}: only an animation of kind 'other' has tolerance_mm (its keys are picked "
                          f"within it)")
    if isinstance(tolerance, bool) or not isinstance(tolerance, int | float) or not 0 < tolerance <= 1000:
        raise ConfigError(f"{where} tolerance_mm: a distance in millimetres (0 < tolerance_mm <= 1000), got "
                          f"{tolerance!r}")
    max_keys = entry.get("max_keys", DEFAULT_MAX_KEYS)
    if "max_keys" in entry and kind != "other":
        raise ConfigError(f"{where}: only an animation of kind 'other' has max_keys (its keys are picked)")
    if isinstance(max_keys, bool) or not isinstance(max_keys, int) or not 2 <= max_keys <= MAX_KEYS_LIMIT:
        raise ConfigError(f"{where} max_keys: the most keys the picking may take, a whole number 2..{MAX_KEYS_LIMIT}, "
                          f"got {max_keys!r}")
    animation = entry.get("animation")
    if animation is not None:
        if not gltf:
            raise ConfigError(f"{where} animation: only a glTF source (.glb, .gltf) holds several animations")
        named = isinstance(animation, str) and animation != ""
        if isinstance(animation, bool) or not (named or (isinstance(animation, int) and animation >= 0)):
            raise ConfigError(f"{where} animation: the name of one of the file's animations or its index (0 = the "
                              f"first), got {animation!r}")
    mapping = entry.get("mapping")
    if mapping is not None and (not isinstance(mapping, str) or not mapping.lower().endswith((".toml", ".json"))):
        raise ConfigError(f"{where} mapping: a .toml or .json mapping file (character joint = file joint) under "
                          f"the data directory or by an absolute path, got {mapping!r}")
    units = entry.get("units")
    if units is not None and units not in UNITS:
        raise ConfigError(f"{where} units: one of {', '.join(repr(u) for u in UNITS)}, got {units!r}")
    up_axis = entry.get("up_axis")
    if up_axis is not None and up_axis not in ("y", "z"):
        raise ConfigError(f"{where} up_axis: 'y' or 'z', got {up_axis!r}")
    accept_unfaithful = entry.get("accept_unfaithful", False)
    if not isinstance(accept_unfaithful, bool):
        raise ConfigError(f"{where} accept_unfaithful: true (build even if the fidelity gate fails; the clips are "
                          f"marked unfaithful) or false, got {accept_unfaithful!r}")
    return AnimationConfig(
        name, kind, source, frames, playback, in_place, keys,  # type: ignore[arg-type]
        None if cycle is None else _frames(cycle, f"{where} cycle", 2),  # type: ignore[arg-type]
        float(tolerance), animation, mapping, units, up_axis, accept_unfaithful, max_keys)


def _other_keys(keys: tuple[int, ...], frames: tuple[int, ...], playback: str, where: str) -> None:
    """Given keys of an ``other`` animation span its frames: the first at the first frame, and the last at the last
    frame (ping-pong) or before it (a loop's last frame is its first again)."""
    first, last = frames
    if len(keys) < 2:
        raise ConfigError(f"{where} keys: at least 2 keys, got {list(keys)}")
    if keys[0] != first:
        raise ConfigError(f"{where} keys: the first key is the first frame ({first}), got {keys[0]}")
    if playback == "pingpong" and keys[-1] != last:
        raise ConfigError(f"{where} keys: a ping-pong clip turns at its last key, the last frame ({last}); got "
                          f"{keys[-1]}")
    if playback == "loop" and keys[-1] >= last:
        raise ConfigError(f"{where} keys: a loop's last frame ({last}) is its first again, so every key is before "
                          f"it; got {keys[-1]}")


def _character(raw: Any, path: Path) -> tuple[tuple[str, ...], CharacterConfig]:
    where = f"{path} [character]"
    if not isinstance(raw, dict):
        raise ConfigError(f"{where} must be a table")
    known = {"relocate", "gltf", "mapping", "units", "up_axis"}
    if unknown := sorted(set(raw) - known):
        raise ConfigError(f"{where}: unknown field {unknown[0]!r}; allowed: {', '.join(sorted(known))}")
    relocate = raw.get("relocate", [])
    if not isinstance(relocate, list) or not all(isinstance(r, str) for r in relocate):
        raise ConfigError(f"{where}: relocate must be a list of joint names")
    for field in ("gltf", "mapping"):
        value = raw.get(field)
        if value is not None and (not isinstance(value, str) or not value.strip()):
            raise ConfigError(f"{where}: {field} must be a file path (under the data directory or absolute)")
    gltf = raw.get("gltf")
    if gltf is not None and not gltf.lower().endswith((".glb", ".gltf")):
        raise ConfigError(f"{where}: gltf must name a .glb or .gltf file, got {gltf!r}")
    units, up_axis = raw.get("units"), raw.get("up_axis")
    if units is not None and units not in UNITS:
        raise ConfigError(f"{where}: units must be one of {', '.join(UNITS)}, got {units!r}")
    if up_axis is not None and up_axis not in ("y", "z"):
        raise ConfigError(f"{where}: up_axis must be 'y' or 'z', got {up_axis!r}")
    if gltf is None and any(raw.get(f) is not None for f in ("mapping", "units", "up_axis")):
        raise ConfigError(f"{where}: mapping, units and up_axis describe a glTF character; give gltf too")
    return tuple(relocate), CharacterConfig(gltf, raw.get("mapping"), units, up_axis)


def _conditions(raw: Any, path: Path) -> tuple[Condition, ...]:
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{path}: [[conditions]] must list the conditions (at least the reference, method "
                          f"{REFERENCE!r})")
    out: list[Condition] = []
    for k, entry in enumerate(raw, 1):
        where = f"{path} [[conditions]] #{k}"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where} must be a table")
        if unknown := sorted(set(entry) - {"id", "method", "params"}):
            raise ConfigError(f"{where}: unknown field {unknown[0]!r}; allowed: id, method, params")
        cid = entry.get("id")
        if not isinstance(cid, str) or not NAME.fullmatch(cid):
            raise ConfigError(f"{where}: id must be 1..32 lower-case letters, digits or '_' (no '-'), got {cid!r}")
        where = f"{path} [[conditions]] id = {cid!r}"
        if any(c.id == cid for c in out):
            raise ConfigError(f"{where}: duplicate id (condition ids are unique)")
        method = entry.get("method")
        if not isinstance(method, str):
            raise ConfigError(f"{where}: method must be a string naming a registered method")
        params = entry.get("params", {})
        if not isinstance(params, dict):
            raise ConfigError(f"{where}: params must be a table, e.g. params = {{ increment = 0 }}")
        try:
            out.append(Condition.parse(cid, method, params))
        except ConditionError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    references = [c.id for c in out if c.is_reference]
    if len(references) != 1:
        raise ConfigError(f"{path}: [[conditions]] must hold exactly one condition with method {REFERENCE!r} "
                          f"(the reference the others are compared with), got {references or 'none'}")
    return tuple(out)


def level_id(ladder: str, level: float | int) -> str:
    """A ladder level's condition id: the ladder's id and the level, "_" for a decimal point (``eps0_5``)."""
    text = str(level) if isinstance(level, int) else f"{level:g}" if "e" not in f"{level:g}" else repr(level)
    return f"{ladder}{text.replace('.', '_').replace('-', 'm').replace('+', '')}"


def _ladders(raw: Any, path: Path, fps: int, explicit: tuple[Condition, ...], table: str = "[[ladders]]"
             ) -> tuple[Condition, ...]:
    """The conditions of the ``[[ladders]]`` entries (``table``: how the file names them, ``[[clips.ladders]]``
    in a study file), one per level, each carrying its ladder's id and level; every error names the ladder, the
    field and the level, and nothing is built."""
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise ConfigError(f"{path}: {table} must be a list of tables (id, method, levels, param?, params?)")
    out: list[Condition] = []
    taken = {c.id: "[[conditions]]" for c in explicit}
    for k, entry in enumerate(raw, 1):
        where = f"{path} {table} #{k}"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where} must be a table")
        if unknown := sorted(set(entry) - {"id", "method", "levels", "param", "params"}):
            raise ConfigError(f"{where}: unknown field {unknown[0]!r}; allowed: id, method, levels, param, params")
        lid = entry.get("id")
        if not isinstance(lid, str) or not NAME.fullmatch(lid):
            raise ConfigError(f"{where} id: 1..32 lower-case letters, digits or '_' (no '-'), got {lid!r}")
        where = f"{path} {table} id = {lid!r}"
        method = entry.get("method")
        if not isinstance(method, str):
            raise ConfigError(f"{where} method: a string naming a registered method")
        try:
            m = get_method(method)
        except ConditionError as exc:
            raise ConfigError(f"{where} method: {exc}") from None
        if method == REFERENCE:
            raise ConfigError(f"{where} method: {REFERENCE!r} is the reference, it has no levels")
        param = entry.get("param", m.graded)
        if param is None:
            raise ConfigError(f"{where} param: method {method!r} grades no parameter by default; name one")
        if not isinstance(param, str) or param not in m.params.model_fields:
            raise ConfigError(f"{where} param: method {method!r} has no parameter {param!r}; it has "
                              f"{', '.join(m.params.model_fields) or 'none'}")
        params = entry.get("params", {})
        if not isinstance(params, dict):
            raise ConfigError(f"{where} params: a table of the method's other parameters, e.g. params = "
                              f"{{ blend_frames = 3 }}")
        if param in params:
            raise ConfigError(f"{where} params: {param!r} is the graded parameter; its values are the levels")
        levels = entry.get("levels")
        if not isinstance(levels, list) or len(levels) < MIN_LADDER_LEVELS:
            raise ConfigError(f"{where} levels: a list of at least {MIN_LADDER_LEVELS} levels, got {levels!r}")
        for i, level in enumerate(levels):
            if isinstance(level, bool) or not isinstance(level, int | float):
                raise ConfigError(f"{where} levels: level {level!r} is not a number")
            if i and level <= levels[i - 1]:
                what = "repeated" if level == levels[i - 1] else "out of order"
                raise ConfigError(f"{where} levels: level {level!r} is {what}; levels increase strictly, got "
                                  f"{levels}")
        for level in levels:
            cid = level_id(lid, level)
            if not NAME.fullmatch(cid):
                raise ConfigError(f"{where} levels: level {level!r} makes the condition id {cid!r}, not 1..32 "
                                  f"lower-case letters, digits or '_'; shorten the ladder's id")
            if cid in taken:
                raise ConfigError(f"{where} levels: level {level!r} makes the condition id {cid!r}, which "
                                  f"{taken[cid]} has already")
            try:
                condition = Condition.parse(cid, method, {**params, param: level}, lid, level)
            except ConditionError as exc:
                raise ConfigError(f"{where} level {level!r}: {exc}") from None
            if (reason := condition.refused(fps)) is not None:
                raise ConfigError(f"{where} level {level!r}: {reason}; drop the level")
            taken[cid] = f"{table} id = {lid!r}"
            out.append(condition)
    return tuple(out)


def clip_set_config(animations: dict[str, dict[str, Any]], conditions: list[dict[str, Any]], fps: int,
                    relocate: tuple[str, ...], character: CharacterConfig, where: str) -> ClipSetConfig:
    """A clip-set description from its tables (``[animations.<name>]`` and ``[[conditions]]`` as dicts),
    validated as a clip-set file's are (errors name ``where``): for code that describes a clip set itself, like
    the build job of uploads, without writing a file to parse it again."""
    if not animations:
        raise ConfigError(f"{where}: no animation to build")
    return ClipSetConfig(fps, tuple(relocate), {name: _animation(name, entry, f"{where} [animations.{name}]")
                                                for name, entry in animations.items()},
                         _conditions(conditions, Path(where)), character)


def inline_config(animations: dict[str, dict[str, Any]] | None, conditions: list[dict[str, Any]] | None,
                  where: str, ladders: list[dict[str, Any]] | None = None) -> ClipSetConfig:
    """The default clip-set file with its animations and/or conditions replaced by inline tables (a study file's
    ``[clips]``), validated as a clip-set file's are: the animations are takes and composites (sequences, layers,
    blends: :mod:`server.clipset.composites`), and the conditions of inline ``ladders`` (``[[clips.ladders]]``)
    are added to the listed ones (the same checks, the same errors)."""
    from .composites import check_transitions, split_composites

    default = load_config()
    takes, composites = default.animations, default.composites
    if animations is not None:  # takes and composites, as a clip-set file's [animations]
        takes, composites = split_composites(animations, default.fps, where, _animation, "clips.animations")
        if not takes:
            raise ConfigError(f"{where} [clips.animations.<name>]: at least one take (composites name takes)")
    listed = default.conditions if conditions is None else _conditions(conditions, Path(where))
    chosen = listed + _ladders(ladders, Path(where), default.fps, listed, "[[clips.ladders]]")
    check_transitions(composites, chosen, Path(where))
    return dataclasses.replace(default, animations=takes, conditions=chosen, composites=composites)


def load_config(path: Path = DEFAULT_CONFIG) -> ClipSetConfig:
    """Read and validate a clip-set file."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"clip set file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read clip set file {path}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    except RecursionError:  # tomllib recurses per level of [ or {
        raise ConfigError(f"{path}: not a clip set file: its arrays or tables are nested too deeply") from None
    if unknown := sorted(set(raw) - {"fps", "character", "animations", "conditions", "ladders"}):
        hint = " (conditions are listed as [[conditions]] now)" if "increments" in unknown else ""
        raise ConfigError(f"{path}: unknown field {unknown[0]!r}{hint}; allowed: fps, character, animations, "
                          f"conditions, ladders")
    fps = raw.get("fps", 30)
    if not isinstance(fps, int) or isinstance(fps, bool) or not 1 <= fps <= 240:
        raise ConfigError(f"{path}: fps must be a whole number of frames per second (1..240), got {fps!r}")
    relocate, character = _character(raw.get("character", {}), path)
    table = raw.get("animations")
    if not isinstance(table, dict) or not table:
        raise ConfigError(f"{path}: [animations.<name>] must describe at least one animation")
    from .composites import check_transitions, split_composites

    animations, composites = split_composites(table, fps, path, _animation)
    if not animations:
        raise ConfigError(f"{path}: [animations.<name>] must describe at least one take (composites name takes)")
    conditions = _conditions(raw.get("conditions"), path)
    conditions += _ladders(raw.get("ladders"), path, fps, conditions)
    check_transitions(composites, conditions, path)
    return ClipSetConfig(fps, relocate, animations, conditions, character, composites)
