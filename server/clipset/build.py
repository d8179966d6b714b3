"""Building a clip set from the data directory: the character and each animation's motion file, verified
(:mod:`server.assets`), turned into clips by anim_core (:func:`anim_core.clipset.build_animation`)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from anim_core.bvh import BvhError
from anim_core.character import Character
from anim_core.clipset import AnimationConfig, BuiltClip, Source, build_animation, source_from_bvh
from server import assets
from server.assets import AssetError

from .config import ClipSetConfig, load_config


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
    character = assets.character(data_dir)
    clips: list[BuiltClip] = []
    for k, (name, cfg) in enumerate(config.animations.items(), 1):
        progress(f"[{k}/{len(config.animations)}] {name}: {cfg.source}")
        source = load_source(data_dir, character, cfg, config.relocate)
        clips.extend(build_animation(source, config.fps, config.conditions, progress))
    return clips
