"""From a clip-set description to a study's stimuli, in one way: build → size → pairs → render → pin.  Every entry
point goes through :func:`make_stimuli` (``animstudy study create``, ``render`` and the default study of ``serve``
in :mod:`server.pipeline.commands`; the build of uploads and of an API study's inline ``[clips]`` in
:mod:`server.pipeline.jobs`), so the way from a study's settings to its videos crosses to Dask once
(:func:`server.media.build.render_media`).

- **build** (:func:`build`): the clips a design needs that the clip set lacks, from a typed
  :class:`~server.clipset.config.ClipSetConfig`; the character is loaded and verified once per build; the clips
  are merged into the clip set (files under temporary names, the manifest replaced last).
- **pairs** (:func:`pairs`): the side-by-side videos the design shows (and the ones rendered before, so the
  render manifest keeps listing them).
- **render** (:func:`render`): the missing videos, into the one media directory shared by every clip set (names
  are hashes of what decides the pixels, so clip sets never collide), the render manifest into the clip set's
  own folder.
- **pin**: :func:`server.studies.service.create_study` makes the study's stimulus set from the render manifest
  and :func:`server.studies.service.open_study` pins it.

A study file without ``[clips]`` uses the server's clip set (``<var>/clips``, its render manifest in
``<var>/media``); one with ``[clips] set = "file.toml"`` gets the clip set of that file, kept in
``<var>/clipsets/<key>/`` (``key``: a hash of the file's path and content, so an edited file is another clip set);
one with inline ``[clips]`` conditions, ladders and/or animations gets the default clip-set file with those replaced
(``key``: a hash of the study's owner, the tables and the default file: one researcher's inline clips are never
another's).  A build or render of one clip set asks only for the pairs of studies whose clips it has
(:func:`server.studies.service.pairs_in_use`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy.orm import Session

from anim_core.clips.record import BuiltClip
from anim_core.methods.conditions import REFERENCE, Condition
from server.clipset.config import DEFAULT_CONFIG, ClipSetConfig, inline_config, load_config
from server.clipset.manifest import MANIFEST, ManifestError, merge_clip_set, read_clip_manifest
from server.config import Settings
from server.errors import Unprocessable
from server.media.build import rendered_pairs
from server.media.manifest import RenderManifest, read_render_manifest
from server.media.plan import rendered_settings
from server.media.scene import RenderSettings
from server.studies.design import Design
from server.studies.studyfile import Clips, StudyFile

Progress = Callable[[str], None]
CLIPSETS = "clipsets"


@dataclass(frozen=True)
class Place:
    """Where one clip set lives: its clips and the folder of its render manifest (the videos are in the media
    directory)."""

    clips_dir: Path
    render_dir: Path
    config: ClipSetConfig | None = None  # None: the server's clip set (built from the default file if missing)
    media_dir: Path | None = None  # where the videos go; None: the server's media directory
    #: The pairs its render manifest lists already are kept (adding a study removes nothing); False for a
    #: command's own output folder (``animstudy render --out``), whose manifest lists what was asked for.
    keep_rendered: bool = True

    def videos(self, settings: Settings) -> Path:
        return self.media_dir or settings.media_dir


def server_place(settings: Settings) -> Place:
    return Place(settings.clips_dir, settings.media_dir)


def file_place(settings: Settings, config_path: Path) -> Place:
    """The place of the clip set of ``config_path`` (read and validated here; ConfigError names the file)."""
    path = Path(config_path).resolve()
    config = load_config(path)
    key = hashlib.sha256(str(path).encode() + b"\0" + path.read_bytes()).hexdigest()[:16]
    base = settings.var / CLIPSETS / key
    return Place(base / "clips", base / "render", config)


def inline_place(settings: Settings, clips: Clips, where: str, owner_id: int | None = None) -> Place:
    """The place of a clip set given inline (``[clips]`` conditions and/or animations over the default file),
    one per owner: a researcher's inline clips are built, rendered and listed apart from every other
    researcher's, whatever they are named (``owner_id`` None: a study without owner, made on the server's
    command line)."""
    config = inline_config(clips.animations, clips.conditions, where, clips.ladders)
    given = {"animations": clips.animations, "conditions": clips.conditions}
    if clips.ladders is not None:  # only then: the key of inline clips without ladders is as it was
        given["ladders"] = clips.ladders
    tables = json.dumps(given, sort_keys=True)
    owner = b"" if owner_id is None else f"owner {owner_id}\0".encode()
    key = hashlib.sha256(b"inline\0" + owner + tables.encode() + b"\0" + DEFAULT_CONFIG.read_bytes()
                         ).hexdigest()[:16]
    base = settings.var / CLIPSETS / key
    return Place(base / "clips", base / "render", config)


def study_place(settings: Settings, study_file: StudyFile, study_path: Path | None,
                owner_id: int | None = None) -> Place:
    """The clip set ``study_file`` uses: its ``[clips] set`` (relative to ``study_path``'s folder), its inline
    ``[clips]`` (``owner_id``'s: :func:`inline_place`), or the server's."""
    clips = study_file.clips
    if clips is None:
        return server_place(settings)
    if clips.set is None:
        return inline_place(settings, clips, str(study_path or "the study file"), owner_id)
    base = Path(study_path).parent if study_path is not None else Path.cwd()
    return file_place(settings, base / clips.set)


def needed_conditions(design: Design) -> list[str]:
    return list(dict.fromkeys([design.reference, *design.conditions, *([design.practice] if design.practice
                                                                        else [])]))


def settled(place: Place, design: Design, where: str = "") -> Design:
    """``design`` settled against the clip set of ``place`` (:func:`server.studies.ladder.resolve`): a threshold
    design's levels (and a ladder named for all its levels) from a described clip set's conditions, or from the
    manifest of the server's; 422 (naming ``where``, if any) when they disagree."""
    from server.studies import ladder
    from server.studies.service import settled as settled_by_manifest

    try:
        if place.config is not None:
            return ladder.resolve(design, ladder.ladder_fields(place.config.conditions))
        return settled_by_manifest(design, place.clips_dir)
    except Unprocessable as exc:
        raise Unprocessable(f"{where}: {exc.detail}" if where else exc.detail) from None


def build_animations(data_dir: Path, config: ClipSetConfig, wanted: dict[str, tuple[Condition, ...]],
                     progress: Progress = lambda _m: None,
                     each: Callable[[int, str], None] = lambda _k, _name: None, scheduler: str | None = None,
                     workers: int = 1) -> list[BuiltClip]:
    """The clips of each animation of ``wanted`` in its conditions (the reference among them), on the character
    of ``config``, loaded and verified once; one Dask task per animation
    (:func:`server.clipset.build.build_each`; default: in this process).  AssetError/ConfigError of the character
    as they are; of an animation as :class:`AnimationError`.  Nothing is written."""
    from server.clipset.build import build_each, load_character

    progress("loading the character")
    character, record = load_character(data_dir, config.character, progress)
    built = build_each(data_dir, character, [(config.animations[name], c) for name, c in wanted.items()],
                       config.fps, config.relocate, progress, each, scheduler, workers)
    # Every clip records the character it was built for; the manifest keeps it once.
    return [dataclasses.replace(c, source={**c.source, "character": record}) for c in built]


def build_composite_animations(data_dir: Path, config: ClipSetConfig, wanted: dict[str, tuple[Condition, ...]],
                               progress: Progress = lambda _m: None) -> list[BuiltClip]:
    """The clips of each composite of ``wanted`` (sequences, layers, blends of ``config``'s takes) in its conditions
    that apply to it (the reference among them), in this process (:func:`server.clipset.composites.build_composites`).
    Nothing is written."""
    if not wanted:
        return []
    from server.clipset.build import load_character
    from server.clipset.composites import build_composites

    character, record = load_character(data_dir, config.character, progress)
    built = []
    for name, conditions in wanted.items():
        built += build_composites(data_dir, character, {name: config.composites[name]}, config.animations,
                                  config.fps, conditions, config.relocate, progress)
    return [dataclasses.replace(c, source={**c.source, "character": record}) for c in built]


def check_design(config: ClipSetConfig, design: Design) -> list[str]:
    """The conditions ``design`` needs (:func:`needed_conditions`), or 422 naming what ``config`` does not have."""
    conditions = needed_conditions(design)
    by_id = {c.id: c for c in config.conditions}
    if unknown := [c for c in conditions if c not in by_id]:
        raise Unprocessable(f"design: condition(s) {', '.join(unknown)} are not in the study's clip set (it has "
                            f"{', '.join(by_id)})")
    names = [*config.animations, *config.composites]
    if unknown := [a for a in design.animations if a not in names]:
        raise Unprocessable(f"design.animations: {', '.join(unknown)} are not in the study's clip set (it has "
                            f"{', '.join(names)})")
    for name in design.animations:  # a take has no crossfade clip, a sequence no hybrid one
        form = config.composites[name].form if name in config.composites else "take"
        if wrong := [c for c in conditions if not by_id[c].applies(form)]:
            raise Unprocessable(f"design.conditions: {', '.join(wrong)} build no clip of {name!r} (a {form}); its "
                                f"clip set builds {', '.join(c.id for c in config.conditions if c.applies(form))}")
    return conditions


def build(data_dir: Path, config: ClipSetConfig, clips_dir: Path, design: Design,
          progress: Progress = lambda _m: None, scheduler: str | None = None, workers: int = 1) -> int:
    """Build the clips of ``design`` that the clip set in ``clips_dir`` lacks, from ``config``; returns how many
    clips were built.  An animation is built with every condition it already had plus the ones needed (the
    reference first: the others are made from it).  422 naming what ``config`` does not have."""
    conditions = check_design(config, design)
    try:
        current = read_clip_manifest(clips_dir).clips if (clips_dir / MANIFEST).is_file() else []
    except ManifestError:
        current = []  # unreadable: built again from scratch
    have: dict[str, set[str]] = {}
    for c in current:
        have.setdefault(c.animation, set()).add(c.condition)
    todo = [a for a in design.animations if not set(conditions) <= have.get(a, set())]
    if not todo:
        progress(f"clips: all {len(design.animations) * len(conditions)} the design needs are built")
        return 0
    wanted = {}
    for name in todo:
        keep = have.get(name, set()) | set(conditions)
        wanted[name] = tuple(c for c in config.conditions if c.id in keep or c.method == REFERENCE)
    takes = {name: c for name, c in wanted.items() if name in config.animations}
    built = build_animations(data_dir, config, takes, progress, lambda k, name: progress(
        f"[{k + 1}/{len(todo)}] {name}: building {len(wanted[name])} clips"), scheduler, workers) if takes else []
    built += build_composite_animations(data_dir, config, {name: c for name, c in wanted.items()
                                                           if name in config.composites}, progress)
    try:
        merge_clip_set(clips_dir, built)
    except ManifestError as exc:
        raise Unprocessable(str(exc)) from None
    progress(f"clips: {len(built)} built into the clip set")
    return len(built)


def pairs(session: Session, place: Place, design: Design, media_dir: Path) -> list[tuple[str, str]]:
    """The pair videos to have: the design's, and the ones this clip set's render manifest has already (so that
    adding a study removes nothing from it); for the server's clip set every study's too."""
    return study_pairs(session, place, {"": design}, media_dir)


def study_pairs(session: Session, place: Place, designs: Mapping[str, Design],
                media_dir: Path) -> list[tuple[str, str]]:
    """:func:`pairs` of several designs (``where`` -> design: a 422 of a design names its ``where``, if any)."""
    from server.studies.service import clip_set_index, pairs_in_use, pairs_to_render, required_pairs

    index = clip_set_index(place.clips_dir)
    needed = []
    for where, design in designs.items():
        try:
            if place.config is None and place.keep_rendered:
                needed += pairs_to_render(session, design, place.clips_dir, media_dir)
            else:
                needed += required_pairs(design, index)
        except Unprocessable as exc:
            raise Unprocessable(f"{where}: {exc.detail}" if where else exc.detail) from None
    ids = set(index.values())
    if place.config is None and not place.keep_rendered:  # every study's pairs too, for new studies made over it
        return list(dict.fromkeys([*needed, *pairs_in_use(session, ids)]))
    if place.config is None:
        return list(dict.fromkeys(needed))
    before = [p for p in rendered_pairs(place.render_dir) if set(p) <= ids]
    return list(dict.fromkeys([*before, *needed]))


def render(settings: Settings, place: Place, wanted: list[tuple[str, str]], render_settings: RenderSettings,
           progress: Progress = lambda _m: None, workers: int = 2, every_clip: bool = False,
           videos_done: Callable[[int, int], None] = lambda _d, _t: None) -> RenderManifest:
    """Render what is missing of ``wanted`` and the clips they show (``every_clip``: every clip) into the media
    directory; returns the render manifest of ``place``.  ``videos_done``: as for
    :func:`server.media.build.render_media`."""
    from server.media.build import render_media

    render_media(settings.data, place.clips_dir, place.videos(settings), settings.secret, render_settings,
                 pairs=wanted, workers=workers, every_clip=every_clip, progress=progress,
                 manifest_dir=place.render_dir, scheduler=settings.dask_scheduler, videos_done=videos_done)
    return read_render_manifest(place.render_dir)


def build_missing(settings: Settings, place: Place, designs: Mapping[str, Design],
                  progress: Progress = lambda _m: None, workers: int = 1) -> int:
    """Build what the clip set of ``place`` lacks: the server's whole (from the default clip-set file) when it has
    no manifest; for a described clip set the clips ``designs`` need (:func:`build`).  Returns how many clips
    were built."""
    from server.clipset.build import build_clip_set
    from server.clipset.manifest import write_clip_set

    if place.config is None:
        if (place.clips_dir / MANIFEST).is_file():
            return 0
        progress(f"building the server's clip set in {place.clips_dir}")
        clips = build_clip_set(settings.data, progress=progress, scheduler=settings.dask_scheduler, workers=workers)
        write_clip_set(clips, place.clips_dir)
        return len(clips)
    return sum(build(settings.data, place.config, place.clips_dir, design, progress, settings.dask_scheduler,
                     workers) for design in designs.values())


def make_stimuli(settings: Settings, session: Session, place: Place, designs: Mapping[str, Design],
                 size: RenderSettings | None = None, progress: Progress = lambda _m: None, workers: int = 2,
                 every_clip: bool = False, videos_done: Callable[[int, int], None] = lambda _d, _t: None,
                 built: Callable[[int], None] = lambda _n: None) -> RenderManifest:
    """The one way from a clip set to the videos of ``designs`` (``where`` -> design, :func:`study_pairs`):
    build what is missing (:func:`build_missing`; ``built(n)`` after), pick the video size (``size``, else the
    size and shadows of the videos there already, so that a study's videos look alike), compute the pairs
    (:func:`study_pairs`) and render what is missing (:func:`render`); returns the render manifest of ``place``
    to pin a study over (:func:`server.studies.service.create_study`, ``show_design``, ``update_study``)."""
    if place.config is None:  # the server's clip set: built whole first, its manifest then says the levels
        built(build_missing(settings, place, designs, progress, workers))
    designs = {where: settled(place, design, where) for where, design in designs.items()}
    if place.config is not None:
        built(build_missing(settings, place, designs, progress, workers))
    before = place.render_dir if (place.render_dir / MANIFEST).is_file() else place.videos(settings)
    chosen = size or rendered_settings(before)
    wanted = study_pairs(session, place, designs, place.videos(settings))
    session.commit()  # no transaction held while rendering: a job's progress is written meanwhile (SQLite locks)
    return render(settings, place, wanted, chosen, progress, workers, every_clip, videos_done)


def prepare(settings: Settings, session: Session, study_file: StudyFile, study_path: Path | None = None,
            render_settings: RenderSettings | None = None, progress: Progress = lambda _m: None,
            workers: int = 2, videos_done: Callable[[int, int], None] = lambda _d, _t: None,
            owner_id: int | None = None) -> tuple[RenderManifest, Place]:
    """Build and render what ``study_file`` needs that is missing (:func:`make_stimuli`); returns the render
    manifest to create it over and the place of its clip set (pass ``place.clips_dir`` to ``create_study``);
    ``owner_id``: the study's owner (whose inline ``[clips]`` they are)."""
    place = study_place(settings, study_file, study_path, owner_id)
    if place.config is not None:
        what = study_file.clips.set if study_file.clips and study_file.clips.set else "given in the study file"
        progress(f"clip set {what} -> {place.clips_dir}")
    media = make_stimuli(settings, session, place, {"": study_file.design}, render_settings, progress, workers,
                         videos_done=videos_done)
    return media, place


def clip_set_dirs(settings: Settings) -> list[Path]:
    """Every clip set's folder: the server's and each one a study file named (``gc`` collects what their
    manifests do not name)."""
    return [settings.clips_dir, *sorted(p / "clips" for p in (settings.var / CLIPSETS).glob("*") if p.is_dir())]


def render_manifest_dirs(settings: Settings) -> list[Path]:
    """Every render manifest's folder: the media directory and each clip set's (``gc`` keeps what they list)."""
    return [settings.media_dir, *sorted(p / "render" for p in (settings.var / CLIPSETS).glob("*") if p.is_dir())]
