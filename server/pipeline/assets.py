"""The clip-set description of a study's uploaded assets, and merging their clips into the clip set: what the
build job of uploads (:func:`server.pipeline.jobs.build_job`) builds from."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from server.jobs.progress import BuildError
from server.uploads.models import StudyAsset


def current_clip_set(clips_dir: Path) -> Any:
    """The manifest of the clip set in ``clips_dir``, None if there is none; one that cannot be read stops the
    build (merging into it would drop the clips every other study shows)."""
    from server.clipset.manifest import MANIFEST, ManifestError, read_clip_manifest

    if not (clips_dir / MANIFEST).exists():
        return None
    try:
        return read_clip_manifest(clips_dir)
    except ManifestError as exc:
        raise BuildError(f"{exc}; the uploaded clips are added to it, so it must be readable first") from None


@dataclass(frozen=True)
class BaseClipSet:
    """What the assets' clips share with the clip set they join: ``fps``, ``[character]`` (``relocate`` and the
    body, a :class:`server.clipset.config.CharacterConfig`) and the ``conditions`` (id, method, params)."""

    fps: int
    relocate: tuple[str, ...]
    character: Any
    conditions: list[tuple[str, str, dict[str, Any]]]


def base_clip_set(data_dir: Path, clips_dir: Path) -> BaseClipSet:
    """The clip set in ``clips_dir`` (so the new animations have every condition the others have, on the same
    character, whose files must not have changed since), or the default clip-set file when there is none.  The
    manifest does not record ``relocate``: the default file's is used."""
    from server.clipset.build import record_config
    from server.clipset.config import load_config

    default = load_config()
    manifest = current_clip_set(clips_dir)
    if manifest is None:
        return BaseClipSet(default.fps, default.relocate, default.character,
                           [(c.id, c.method, c.params_dict()) for c in default.conditions])
    character, _ = record_config(data_dir, manifest.character.model_dump() if manifest.character else None)
    conditions = list({c.condition: (c.condition, c.method, c.params) for c in manifest.clips}.values())
    fps = manifest.clips[0].fps if manifest.clips else default.fps
    return BaseClipSet(fps, default.relocate, character, conditions)


def assets_config(assets: Sequence[StudyAsset], asset_file: Callable[[StudyAsset], Path],
                  base: BaseClipSet) -> Any:
    """The clip-set description (:class:`server.clipset.config.ClipSetConfig`) of ``assets``: each an animation
    with its kind, source file and frames, on the fps, character and conditions of ``base``; validated as a
    clip-set file is (ConfigError names the asset)."""
    from server.clipset.config import clip_set_config

    animations = {a.name: {"kind": a.kind, "source": str(asset_file(a)), "frames": [a.first_frame, a.last_frame],
                           **_playback(a), **_reading(a, asset_file(a))} for a in assets}
    conditions = [{"id": cid, "method": method, **({"params": params} if params else {})}
                  for cid, method, params in base.conditions]
    return clip_set_config(animations, conditions, base.fps, base.relocate, base.character, "the study's assets")


def _playback(asset: StudyAsset) -> dict[str, Any]:
    """Kind ``other``: the playback inspecting the file suggested (a take that travels loops: played ping-pong it
    would move backwards, and the build refuses that); the other kinds play as their kind does."""
    playback = ((asset.report or {}).get("suggested") or {}).get("playback")
    return {"playback": playback} if asset.kind == "other" and playback in ("loop", "pingpong") else {}


def _reading(asset: StudyAsset, path: Path) -> dict[str, Any]:
    """How the researcher said to read the asset's file (units, up axis, a joint mapping, build in spite of the
    fidelity gate), as clip-set animation fields; a mapping is written beside the file (the clip set names files)."""
    report = asset.report or {}
    options = report.get("options", {})
    fields: dict[str, Any] = {key: options[key] for key in ("units", "up_axis") if options.get(key)}
    if options.get("mapping"):
        mapping = path.with_name(f"{asset.name}.mapping.json")
        mapping.write_text(json.dumps(options["mapping"]), encoding="utf-8")
        fields["mapping"] = str(mapping)
    if report.get("accept_unfaithful"):
        fields["accept_unfaithful"] = True
    return fields


# --- merging into the clip set -----------------------------------------------------------------------------------

def check_names(clips_dir: Path, assets: Sequence[StudyAsset], asset_file: Callable[[StudyAsset], Path]) -> None:
    """An asset may not take the name of an animation of the clip set that comes from another file.  The clip set
    is the server's, one namespace for every researcher: the name may be another researcher's upload, so the
    message is the same whoever's it is and says nothing of it (not that it is an upload, nor whose, nor that it
    exists)."""
    manifest = current_clip_set(clips_dir)
    if manifest is None:
        return
    sources = {c.animation: str(c.source.get("file")) for c in manifest.clips}
    for a in assets:
        if a.name in sources and sources[a.name] != str(asset_file(a)):
            raise BuildError(f"asset {a.filename!r}: {a.name!r} cannot be the name of an uploaded animation on this "
                             "server; delete the asset and upload it again with another name (API: name=)")


def merge_clips(clips_dir: Path, built: list[Any]) -> Path:
    """:func:`server.clipset.manifest.merge_clip_set`, its errors as the job's (the clip set must be readable
    first: the uploaded clips are added to it)."""
    from server.clipset.manifest import ManifestError, merge_clip_set

    current_clip_set(clips_dir)  # an unreadable one stops the build, saying so
    try:
        return merge_clip_set(clips_dir, built)
    except ManifestError as exc:
        raise BuildError(str(exc)) from None
