"""What a render makes (:func:`plan`): every output's name is ``HMAC(secret, key)`` where ``key`` hashes everything
that decides its pixels (clip content, character, render settings, camera, layout); so names are opaque, stable
across runs, and an output whose file exists is up to date.  The jobs of the plan are run by
:mod:`server.media.worker`, dispatched by :mod:`server.media.build`."""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import json
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from server.assets import AssetError
from server.clipset.build import record_config
from server.clipset.config import CharacterConfig
from server.clipset.manifest import ClipEntry, ManifestError, read_clip_manifest
from server.errors import MediaError

from .manifest import read_render_manifest
from .scene import Framing, RenderSettings, frame_motion

if TYPE_CHECKING:
    pass

#: also matches before a trailing newline, and an import once wrote a file named ``<hex>.mp4\n``.
MEDIA_NAME = re.compile(r"^[0-9a-f]{24}\.(mp4|jpg)$")
DIVIDER_PX = 4
DIVIDER_RGB = (58, 60, 64)
BODY_PADDING_M = 0.12  # how far the skin reaches beyond the joints, for framing and shadow bounds


@dataclass(frozen=True)
class Output:
    """One video (and its poster): a single clip, or a side-by-side pair (left, right)."""

    name: str
    clips: tuple[str, ...]
    key: str

    @property
    def video(self) -> str:
        return f"{self.name}.mp4"

    @property
    def poster(self) -> str:
        return f"{self.name}.jpg"


@dataclass(frozen=True)
class AnimationJob:
    """Everything one worker needs to render the missing outputs of one animation."""

    animation: str
    data_dir: Path
    clips: dict[str, ClipEntry]
    outputs: list[Output]
    settings: RenderSettings
    framing: Framing
    grid_spacing_m: float
    # Shadow and culling bounds (min xyz, max xyz) of every clip of the animation: a task given some of its clips
    # renders the pixels a job given all of them does.
    bounds: tuple[float, ...]
    out_dir: Path
    n_frames: int = field(default=0)
    character: CharacterConfig = field(default=CharacterConfig())

    def video_tasks(self) -> list[AnimationJob]:
        """One job per output (a Dask task per video): its clips only, the animation's framing and bounds."""
        return [dataclasses.replace(self, clips={i: self.clips[i] for i in o.clips}, outputs=[o],
                                    n_frames=sum(rendered_frames(self.clips[i]) for i in set(o.clips)))
                for o in self.outputs]


def rendered_settings(media_dir: Path) -> RenderSettings:
    """The size and shadows the videos in ``media_dir`` were rendered at (``animstudy render --width --height
    --no-shadows``), so that what is added to them later (a study created over them, an upload's build) renders
    alike; the defaults if there are none."""
    default = RenderSettings()
    try:
        done = read_render_manifest(media_dir).settings
    except ManifestError:
        return default
    width, height, shadows = done.get("width"), done.get("height"), done.get("shadows")
    if not (isinstance(width, int) and isinstance(height, int) and isinstance(shadows, bool)):
        return default
    return RenderSettings(width=width, height=height, shadows=shadows)


def read_clip_set(clips_dir: Path, read_arrays: bool = True) -> list[ClipEntry]:
    """The clips listed in the clip manifest of ``clips_dir`` (:mod:`server.clipset.manifest`).  With
    ``read_arrays`` (to render them) every clip's file is read and hashed here, so that a missing or broken one is
    a MediaError before any work; without, only the manifest is read (to know what the clip set has)."""
    try:
        clips = read_clip_manifest(clips_dir).clips
        if read_arrays:
            for c in clips:
                c.digest  # noqa: B018 - computed (the file read) now
        return clips
    except ManifestError as exc:
        raise MediaError(str(exc)) from None
    except FileNotFoundError as exc:
        raise MediaError(f"no clip set at {clips_dir}: {exc.filename} is missing (run `animstudy clips build`)"
                         ) from None
    except (KeyError, ValueError, OSError) as exc:
        raise MediaError(f"the clip set in {clips_dir} is unreadable ({exc!r}); rebuild it") from None


def identical_clips(clips: Sequence[ClipEntry]) -> dict[str, str]:
    """Clip id -> the first clip of ``clips`` of the same animation with the same arrays (itself for the first),
    e.g. a key reduction that kept every key of its reference.  Only within an animation: a render job holds one
    animation's clips, so a clip of another animation (say an upload of the same motion under another name) is
    not there to render from (issue 36: ``KeyError: 'walk-hybrid2'``)."""
    first: dict[tuple[str, str], str] = {}
    return {c.id: first.setdefault((c.animation, c.digest), c.id) for c in clips}


def _name(secret: bytes, key: str) -> str:
    return hmac.new(secret, key.encode(), hashlib.sha256).hexdigest()[:24]


def _key(scene: dict[str, Any], layout: str, clips: Sequence[ClipEntry]) -> str:
    text = json.dumps({"scene": scene, "layout": layout, "clips": [c.digest for c in clips]}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def grid_spacing(clip: ClipEntry, settings: RenderSettings) -> float:
    """Grid spacing that a looping in-place walk scrolls by a whole number of cells per cycle (a seamless loop)."""
    if not clip.in_place or clip.root_speed_mps <= 0:
        return settings.grid_spacing_m
    stride = clip.root_speed_mps * clip.frames / clip.fps
    return stride / max(1, round(stride / settings.grid_spacing_m))


def _bounds(positions: NDArray[Any]) -> NDArray[np.float64]:
    """Shadow and culling bounds of joint positions: their box, widened by 0.3 m for the skin."""
    everything = positions.reshape(-1, 3)
    return np.array([everything.min(axis=0) - 0.3, everything.max(axis=0) + 0.3])


def rendered_frames(clip: ClipEntry) -> int:
    """Frames actually rendered: the backward half of a ping-pong period repeats the forward half."""
    return clip.frames // 2 + 1 if clip.playback == "pingpong" else clip.frames


@dataclass
class Plan:
    jobs: list[AnimationJob]
    clip_outputs: dict[str, Output]
    pair_outputs: dict[tuple[str, str], Output]
    clips: dict[str, ClipEntry]

    @property
    def outputs(self) -> list[Output]:
        return [*self.clip_outputs.values(), *self.pair_outputs.values()]


def plan(data_dir: Path, clips_dir: Path, out_dir: Path, settings: RenderSettings, secret: bytes,
         pairs: Sequence[tuple[str, str]] = (), animations: Sequence[str] | None = None,
         every_clip: bool = True) -> Plan:
    """Work out every output's name and which ones are missing, grouped into one job per animation: a video of
    every pair in ``pairs`` (left clip, right clip; the studies decide which pairs they show) and of every clip of
    the clip set (``every_clip=False``: of the clips those pairs show; participants only ever see pairs, so the
    commands render no video of a clip no pair shows, and keep it where it exists and is up to date).

    Clips of one animation with identical arrays (e.g. a key reduction that kept every key) share their outputs:
    a video is planned, named and rendered once, from the first such clip of the animation.

    ``animations`` limits the plan to those animations' clips and pairs (default: all).
    """
    every = read_clip_set(clips_dir)
    clips = {c.id: c for c in every if animations is None or c.animation in animations}
    animation_of = {c.id: c.animation for c in every}
    pairs = [pair for pair in pairs if animations is None or animation_of.get(pair[0]) in animations]
    for left, right in pairs:
        if left not in clips or right not in clips:
            raise MediaError(f"pair ({left}, {right}) names a clip that is not in the clip set")
        if clips[left].animation != clips[right].animation or clips[left].frames != clips[right].frames:
            raise MediaError(f"pair ({left}, {right}) joins clips of different animations or lengths")
    try:
        record = read_clip_manifest(clips_dir).character
        body, files = record_config(data_dir, None if record is None else record.model_dump())
    except AssetError as exc:
        raise MediaError(str(exc)) from None
    # MakeHuman keeps its old key (its files' checksums), so its videos stay valid.
    character: Any = list(files.values()) if body.gltf is None else {**asdict(body), "files": files}
    canonical = identical_clips(list(clips.values()))
    paired = {i for pair in pairs for i in pair}

    def exists(o: Output) -> bool:
        return (out_dir / o.video).is_file() and (out_dir / o.poster).is_file()

    jobs, clip_outputs, pair_outputs = [], {}, {}
    for animation in dict.fromkeys(c.animation for c in clips.values()):
        # The camera frames every clip of the animation, asked for or not, so that names do not depend on the
        # request.
        group = {i: c for i, c in clips.items() if c.animation == animation}
        positions = np.concatenate([np.load(c.path)["world_positions"] for c in group.values()])
        framing = frame_motion(positions, settings, padding=BODY_PADDING_M)
        bounds = _bounds(positions)
        spacing = grid_spacing(next(iter(group.values())), settings)
        scene = {"settings": settings.as_dict(), "character": character, "framing": asdict(framing),
                 "grid_spacing_m": spacing, "divider": [DIVIDER_PX, *DIVIDER_RGB]}
        outputs = []
        for c in group.values():
            key = _key(scene, "clip", [c])
            output = Output(_name(secret, key), (canonical[c.id],), key)
            if every_clip or c.id in paired:
                outputs.append(output)
            elif not exists(output):
                continue
            clip_outputs[c.id] = output
        for left, right in pairs:
            if clips[left].animation == animation:
                key = _key(scene, "pair", [clips[left], clips[right]])
                pair_outputs[(left, right)] = Output(_name(secret, key), (canonical[left], canonical[right]), key)
                outputs.append(pair_outputs[(left, right)])
        distinct = {o.name: o for o in outputs}.values()
        missing = [o for o in distinct if not exists(o)]
        if missing:
            n_frames = sum(rendered_frames(clips[i]) for i in {i for o in missing for i in o.clips})
            jobs.append(AnimationJob(animation, data_dir, group, missing, settings, framing, spacing,
                                     tuple(bounds.ravel().tolist()), out_dir, n_frames, body))
    return Plan(sorted(jobs, key=lambda j: -j.n_frames), clip_outputs, pair_outputs, clips)


# --- worker side -----------------------------------------------------------------------------------------------
