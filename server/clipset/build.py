"""Building a clip set from the data directory: the character (MakeHuman, or the clip-set file's glTF) and each
animation's motion file, verified (:mod:`server.assets`), turned into clips by anim_core
(:func:`anim_core.clipset.build_animation`); each clip's ``source`` records the character it was built for."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

from anim_core.bvh import BvhError
from anim_core.character import Character
from anim_core.clipset import AnimationConfig, BuiltClip, Source, build_animation, source_from_bvh
from server import assets
from server.assets import AssetError

from .config import CharacterConfig, ClipSetConfig, load_config


def character_files(data_dir: Path, config: CharacterConfig) -> dict[str, str]:
    """``{file name: sha256}`` of the files the character is made from (MakeHuman: verified content checksums)."""
    if config.gltf is None:
        return {name: assets.sha256_content(assets.verify(data_dir, name)) for name in assets.CHARACTER_FILES}
    names = {config.gltf: "glTF character"} | ({config.mapping: "joint mapping"} if config.mapping else {})
    return {name: assets.sha256(assets.user_file(data_dir, name, what)) for name, what in names.items()}


def load_character(data_dir: Path, config: CharacterConfig,
                   progress: Callable[[str], None] = lambda _msg: None) -> tuple[Character, dict[str, Any]]:
    """The clip set's character and its record for the clip manifest (``character`` there: which files, with
    their checksums, the clips were built for; :func:`record_config` reads it back)."""
    files = character_files(data_dir, config)
    if config.gltf is None:
        return assets.character(data_dir), {"files": files}
    mapped = assets.gltf_character(data_dir, config.gltf, config.mapping, config.units, config.up_axis)
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


def load_source(data_dir: Path, character: Character, config: AnimationConfig, relocate: tuple[str, ...]) -> Source:
    """One animation's motion file, read, retargeted and turned (errors name the file)."""
    bvh = assets.motion(data_dir, config.source)
    try:
        return source_from_bvh(bvh, character, config, relocate)
    except BvhError as exc:
        raise AssetError(f"corrupt motion file: {exc}") from None


def build_clip_set(data_dir: Path, config: ClipSetConfig | None = None,
                   progress: Callable[[str], None] = lambda _msg: None) -> list[BuiltClip]:
    """All clips of the set (animations x conditions), in manifest order: animation by animation, the reference
    first."""
    config = config or load_config()
    assets.check_data_dir(data_dir)
    progress("loading the character")
    character, record = load_character(data_dir, config.character, progress)
    clips: list[BuiltClip] = []
    for k, (name, cfg) in enumerate(config.animations.items(), 1):
        progress(f"[{k}/{len(config.animations)}] {name}: {cfg.source}")
        source = load_source(data_dir, character, cfg, config.relocate)
        clips.extend(build_animation(source, config.fps, config.conditions, progress))
    # Every clip records the character it was built for; the manifest keeps it once (``character``).
    return [dataclasses.replace(c, source={**c.source, "character": record}) for c in clips]
