"""Building a clip set from the data directory: the character (MakeHuman, or the clip-set file's glTF) and each
animation's motion file, verified (:mod:`server.assets`), brought onto the canonical skeleton
(:func:`anim_core.clips.sources.read_motions`: any common rig, BVH or glTF) and turned into clips by anim_core
(:func:`anim_core.clips.build.build_animation`); each clip's ``source`` records the character it was built for."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from anim_core.bench.cost import with_run_time_costs
from anim_core.clips.build import build_animation, source_from_bvh
from anim_core.clips.entry import AnimationConfig, Source
from anim_core.clips.record import BuiltClip
from anim_core.clips.sources import read_motions
from anim_core.methods.conditions import Condition
from anim_core.rig.character import Character
from anim_core.rig.gltf_character import MappedCharacter
from anim_core.rig.normalize import Normalized
from anim_core.rig.rigmap import read_mapping_file
from server import assets
from server.assets import AssetError

from .config import CharacterConfig, ClipSetConfig, load_config


def character_files(data_dir: Path, config: CharacterConfig) -> dict[str, str]:
    """``{file name: sha256}`` of the files the character is made from (MakeHuman: verified content checksums)."""
    if config.gltf is None:
        return {name: assets.sha256_content(assets.verify(data_dir, name)) for name in assets.CHARACTER_FILES}
    names = {config.gltf: "glTF character"} | ({config.mapping: "joint mapping"} if config.mapping else {})
    return {name: assets.sha256(assets.user_file(data_dir, name, what)) for name, what in names.items()}


def configured_character(data_dir: Path, config: CharacterConfig) -> Character | MappedCharacter:
    """The character a ``[character]`` section names: the MakeHuman one of the data directory (``gltf`` None), or
    the glTF file mapped onto the canonical skeleton; every error names the file."""
    if config.gltf is None:
        return assets.character(data_dir)
    return assets.gltf_character(data_dir, config.gltf, config.mapping, config.units, config.up_axis)


def load_character(data_dir: Path, config: CharacterConfig,
                   progress: Callable[[str], None] = lambda _msg: None) -> tuple[Character, dict[str, Any]]:
    """The clip set's character and its record for the clip manifest (``character`` there: which files, with
    their checksums, the clips were built for; :func:`record_config` reads it back)."""
    files = character_files(data_dir, config)
    mapped = configured_character(data_dir, config)
    if not isinstance(mapped, MappedCharacter):
        return mapped, {"files": files}
    folded = sorted(set(mapped.folded.values()))
    progress(f"character {config.gltf}: {mapped.mapping.convention} names, {mapped.units}, {mapped.up_axis} up; "
             f"{len(mapped.mapping.unmapped)} joints unmapped" + (f", their weights folded into {', '.join(folded)}"
                                                                 if folded else ""))
    return mapped.character, {**dataclasses.asdict(config), "files": files}


def record_config(data_dir: Path, record: dict[str, Any] | None) -> tuple[CharacterConfig, dict[str, str]]:
    """The character configuration of a clip manifest's ``character`` record (None: the MakeHuman character,
    as in manifests from before it was recorded) and its files' checksums, checked against the recorded ones (a
    file changed since the clips were built is an error saying to rebuild them)."""
    if record is None:
        return CharacterConfig(), character_files(data_dir, CharacterConfig())
    config = CharacterConfig(**{k: v for k, v in record.items() if k != "files"})
    current = character_files(data_dir, config)
    changed = [name for name, digest in record["files"].items() if current.get(name) != digest]
    if changed:
        raise AssetError(f"the character file {changed[0]} changed since the clip set was built; rebuild it "
                         f"(`animstudy clips build`)")
    return config, current


def _pick(motions: list[tuple[str, Normalized]], config: AnimationConfig, where: str) -> Normalized:
    """The glTF animation ``config.animation`` names (by name or index; default: the first)."""
    wanted = config.animation
    names = [name for name, _ in motions]
    if wanted is None:
        return motions[0][1]
    if isinstance(wanted, int):
        if wanted >= len(motions):
            raise AssetError(f"{where} animation: index {wanted}, but {config.source} holds {len(motions)} "
                             f"animation(s): {', '.join(repr(n) for n in names)}")
        return motions[wanted][1]
    if wanted not in names:
        raise AssetError(f"{where} animation: {config.source} holds no animation {wanted!r}; it holds "
                         f"{', '.join(repr(n) for n in names)}")
    return motions[names.index(wanted)][1]


def load_source(data_dir: Path, character: Character, config: AnimationConfig, relocate: tuple[str, ...]) -> Source:
    """One animation's motion file (under the data directory, or an absolute path), read, mapped onto the
    canonical skeleton with the entry's ``mapping``/``units``/``up_axis``, retargeted and turned (errors name the
    entry, the field and the file)."""
    return _retargeted(read_source(data_dir, config), character, config, relocate)


def read_source(data_dir: Path, config: AnimationConfig) -> Normalized:
    """The file part of :func:`load_source`: the motion file read and mapped onto the canonical skeleton."""
    where = f"[animations.{config.name}]"
    path = assets.verify(data_dir, config.source)
    try:
        explicit = (read_mapping_file(assets.user_file(data_dir, config.mapping, f"{where} mapping"))
                    if config.mapping else None)
    except AssetError:
        raise
    except ValueError as exc:  # RigMapError names the mapping file
        raise AssetError(f"{where} mapping: {exc}") from None
    try:
        normalized = _pick(read_motions(path, explicit, config.units, config.up_axis), config, where)
    except AssetError:
        raise
    except (ValueError, OSError) as exc:  # BvhError (with its line), GltfError and RigMapError name the file
        raise AssetError(f"{where} source: {exc}") from None
    return normalized


def _retargeted(normalized: Normalized, character: Character, config: AnimationConfig,
                relocate: tuple[str, ...]) -> Source:
    return source_from_bvh(normalized.bvh, character, config, relocate, normalized.metres_per_unit,
                           normalized.source_positions)


def animation_clips(data_dir: Path, character: Character, config: AnimationConfig, fps: int,
                    conditions: Sequence[Condition], relocate: tuple[str, ...],
                    progress: Callable[[str], None] = lambda _msg: None) -> list[BuiltClip]:
    """The clips of one animation (its motion file read by :func:`load_source`), one per condition, the reference
    first (:func:`anim_core.clips.build.build_animation`).  Raises :class:`AssetError` (file) or
    :class:`~anim_core.clips.build.ConfigError` (entry, field or condition); nothing is written."""
    return built_clips(load_source(data_dir, character, config, relocate), fps, conditions, progress)


def built_clips(source: Source, fps: int, conditions: Sequence[Condition],
                progress: Callable[[str], None] = lambda _msg: None) -> list[BuiltClip]:
    """One animation's clips (:func:`anim_core.clips.build.build_animation`) with their measured run-time costs
    when the clip set has ladders (:func:`anim_core.bench.cost.with_run_time_costs`; measured here, above
    ``anim_core.clips``, which the bench imports)."""
    return with_run_time_costs(build_animation(source, fps, conditions, progress), source.character.mesh)


class AnimationError(ValueError):
    """Building one animation's clips failed; the message starts with its name, ``cause`` is the error (an
    AssetError or ConfigError naming the file or the field)."""

    def __init__(self, animation: str, cause: Exception) -> None:
        super().__init__(f"{animation!r}: {cause}")
        self.animation = animation
        self.cause = cause


def clips_task(normalized: Normalized, character: Character, config: AnimationConfig, fps: int,
               conditions: Sequence[Condition], relocate: tuple[str, ...]) -> list[BuiltClip]:
    """A pure task: one animation's clips from its motion as read (a worker reads no file)."""
    return built_clips(_retargeted(normalized, character, config, relocate), fps, conditions)


def build_each(data_dir: Path, character: Character, wanted: Sequence[tuple[AnimationConfig, Sequence[Condition]]],
               fps: int, relocate: tuple[str, ...], progress: Callable[[str], None] = lambda _msg: None,
               each: Callable[[int, str], None] = lambda _k, _name: None, scheduler: str | None = None,
               workers: int = 1) -> list[BuiltClip]:
    """The clips of each animation of ``wanted`` (in its conditions), in order: the motion files read here, the
    clips built by one Dask task per animation (:mod:`server.cluster`: the cluster at ``scheduler``, else a local
    one of ``workers`` processes; in this process when ``workers`` is 1), the character sent once.
    :class:`AnimationError` names the first animation (in order) that failed."""
    sources = []
    for k, (cfg, conditions) in enumerate(wanted):
        each(k, cfg.name)
        try:
            sources.append((cfg, conditions, read_source(data_dir, cfg)))
        except ValueError as exc:
            raise AnimationError(cfg.name, exc) from None
    if not scheduler and (workers <= 1 or len(sources) <= 1):
        built = []
        for cfg, conditions, normalized in sources:
            try:
                built += built_clips(_retargeted(normalized, character, cfg, relocate), fps, conditions, progress)
            except ValueError as exc:
                raise AnimationError(cfg.name, exc) from None
        return built
    from server.cluster import dask_client, share

    with dask_client(scheduler, min(workers, len(sources))) as client:
        shared = share(client, character, "character")
        futures = [client.submit(clips_task, normalized, shared, cfg, fps, tuple(conditions), relocate,
                                 pure=False) for cfg, conditions, normalized in sources]
        progress(f"building {len(futures)} animations on Dask")
        built = []
        for (cfg, _conditions, _normalized), future in zip(sources, futures, strict=True):
            try:
                built += future.result()
            except ValueError as exc:  # the task's own error (ConfigError, ...), raised again here
                raise AnimationError(cfg.name, exc) from None
            progress(f"{cfg.name}: clips built")
    return built


def build_clip_set(data_dir: Path, config: ClipSetConfig | None = None,
                   progress: Callable[[str], None] = lambda _msg: None, scheduler: str | None = None,
                   workers: int = 1) -> list[BuiltClip]:
    """All clips of the set (animations x conditions), in manifest order: animation by animation, the reference
    first; on Dask as :func:`build_each` says (default: in this process)."""
    config = config or load_config()
    assets.check_data_dir(data_dir)
    progress("loading the character")
    character, record = load_character(data_dir, config.character, progress)
    try:
        takes = [c for c in config.conditions if c.applies("take")]
        clips = build_each(data_dir, character, [(cfg, takes) for cfg in config.animations.values()],
                           config.fps, config.relocate, progress, lambda k, name: progress(
                               f"[{k + 1}/{len(config.animations)}] {name}: {config.animations[name].source}"),
                           scheduler, workers)
    except AnimationError as exc:  # as it was raised: its message names the entry
        raise exc.cause from None
    if config.composites:  # issue 39: sequences and layers of the takes
        from .composites import build_composites

        clips += build_composites(data_dir, character, config.composites, config.animations, config.fps,
                                  config.conditions, config.relocate, progress)
    # Every clip records the character it was built for; the manifest keeps it once (``character``).
    return [dataclasses.replace(c, source={**c.source, "character": record}) for c in clips]
