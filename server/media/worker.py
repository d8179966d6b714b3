"""One render job (:class:`~server.media.plan.AnimationJob`) run where it is sent: in this process or on a Dask
worker (:func:`run_job`, :func:`render_task`); :mod:`server.media.build` sends them."""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import hashlib
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from anim_core.rig.gltf_character import MappedCharacter
from server.clipset.build import configured_character
from server.clipset.config import CharacterConfig
from server.clipset.manifest import ClipEntry
from server.errors import MediaError

from .plan import DIVIDER_PX, DIVIDER_RGB, AnimationJob, Output, rendered_frames

if TYPE_CHECKING:
    from anim_core.math.skinning import SkinnedMesh
    from anim_core.rig.character import Character

def init_worker() -> None:
    # llvmpipe reads this when the first context is made: one thread per worker process, two processes.
    os.environ["LP_NUM_THREADS"] = "1"


def _release_memory() -> None:
    """Hand freed heap back to the system between clips (encoders and frame buffers are large)."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


@functools.cache
def _character(data_dir: Path, config: CharacterConfig) -> Character:
    """The clip set's character, once per worker process, not per job."""
    made = configured_character(data_dir, config)
    return made.character if isinstance(made, MappedCharacter) else made


class RenderError(MediaError):
    """A render task failed; the message names the animation and the clip."""


class SchedulerLost(RenderError):
    """The Dask scheduler went away mid-job (nothing else failed): what was stored stays, the rest is missing."""


Arrays = dict[str, dict[str, NDArray[Any]]]


def job_arrays(job: AnimationJob) -> Arrays:
    """The arrays of the job's clips, by clip id (what a worker needs instead of the clip files)."""
    return {i: dict(np.load(c.path)) for i, c in job.clips.items()}


def job_character(job: AnimationJob) -> Character:
    return _character(job.data_dir, job.character)


@dataclass(frozen=True)
class RenderedFile:
    """A rendered file as a task returns it: its name in the media directory, its bytes and their sha256."""

    name: str
    data: bytes
    sha256: str


def render_task(job: AnimationJob, arrays: Arrays, character: Character) -> list[RenderedFile]:
    """A pure task: the job's videos and posters rendered from values (no file of the clip set or the data
    directory is read; a worker needs no shared filesystem), returned as bytes.  Renders are deterministic, so a
    task run again (its worker died) returns the same bytes."""
    import tempfile

    init_worker()
    with tempfile.TemporaryDirectory(prefix="animstudy-render-") as tmp:
        run_job(dataclasses.replace(job, out_dir=Path(tmp)), arrays, character)
        files = []
        for o in job.outputs:
            for name in (o.video, o.poster):
                data = (Path(tmp) / name).read_bytes()
                files.append(RenderedFile(name, data, hashlib.sha256(data).hexdigest()))
    return files


def _held_and_order(job: AnimationJob, pairs: list[Output]) -> tuple[set[str], list[str]]:
    """The clips whose frames are kept, and the order the clips are rendered in (the kept ones first).  Pairs
    need both sides at once: keep the frames of the clip shared by most pairs (the keyframe clip) and of the first
    side of any pair without it; everything else streams."""
    counts: dict[str, int] = {}
    for o in pairs:
        for i in set(o.clips):
            counts[i] = counts.get(i, 0) + 1
    anchor = max(counts, key=lambda i: counts[i]) if counts else None
    held = {o.clips[0] for o in pairs if anchor not in o.clips and o.clips[0] != o.clips[1]}
    if anchor is not None:
        held.add(anchor)
    needed = {i for o in job.outputs for i in o.clips}
    return held, sorted(needed, key=lambda i: (i not in held, i))


def _open_writers(job: AnimationJob, clip: ClipEntry, single: Output | None, ready: list[Output]) -> dict[str, Any]:
    """A video writer for the clip's own video (``single``) and for each pair of ``ready``, by output name."""
    from .video import VideoWriter

    s = job.settings
    writers = {}
    if single is not None:
        writers[single.name] = VideoWriter(job.out_dir / single.video, s.width, s.height, clip.fps)
    for o in ready:
        writers[o.name] = VideoWriter(job.out_dir / o.video, 2 * s.width + DIVIDER_PX, s.height, clip.fps)
    return writers


def clip_mesh(mesh: SkinnedMesh, clip: ClipEntry) -> SkinnedMesh:
    """The body as ``clip`` is skinned: with its render settings' ``skin_influences`` strongest weights per vertex
    (renormalised), or as bound."""
    from anim_core.bench.cost import skinned_mesh

    influences = clip.render.skin_influences if clip.render is not None else None
    return skinned_mesh(mesh, influences)


def _frames(job: AnimationJob, clip: ClipEntry, a: dict[str, NDArray[Any]], renderer: Any,
            mesh: SkinnedMesh) -> Iterator[tuple[int, Any, NDArray[np.uint8] | None]]:
    """(frame, YUV planes, RGB or None) of ``clip`` in playback order.  The second half of a ping-pong period is
    the first half backwards (frame f shows the pose of frame T - f), so only the first half is rendered."""
    from .video import yuv420

    n = rendered_frames(clip)
    shift = (np.arange(n) / clip.fps * clip.root_speed_mps) % job.grid_spacing_m
    if "floor_travel_m" in a:  # a travelling composite shown in place (issue 39): the ground moves instead
        shift = a["floor_travel_m"][:n] % job.grid_spacing_m
    rendered = []
    for f, rgb in enumerate(renderer.render(a["world_rotations"][:n], a["world_positions"][:n], shift,
                                            clip_mesh(mesh, clip))):
        planes = yuv420(rgb)
        rendered.append(planes)
        yield f, planes, rgb
    for f in range(n, clip.frames):
        yield f, rendered[clip.frames - f], None


def run_job(job: AnimationJob, arrays: Arrays | None = None, character: Character | None = None,
            stored: Callable[[str], None] = lambda _name: None) -> list[tuple[str, float]]:
    """Render the job's outputs into ``job.out_dir``; returns (output name, seconds) per finished video.
    ``arrays`` and ``character``: given as values (default: read from the clip files and the data directory);
    ``stored`` is called with each video's name once it is in place."""
    from anim_core.rig.character import bind_mesh

    from .renderer import ClipRenderer
    from .video import Planes, hstack_planes, write_poster, yuv420

    started = time.perf_counter()
    arrays = arrays if arrays is not None else job_arrays(job)
    first = next(iter(arrays.values()))
    character = character if character is not None else job_character(job)
    mesh = bind_mesh(character, [str(n) for n in first["joint_names"]], first["bind_rotations"],
                     first["bind_positions"])
    renderer = ClipRenderer(mesh, character.faces, job.framing, job.settings, np.reshape(job.bounds, (2, 3)),
                            job.grid_spacing_m)
    s = job.settings
    pairs = [o for o in job.outputs if len(o.clips) == 2]
    held, order = _held_and_order(job, pairs)
    # Frames are kept and tiled as the encoder's YUV 4:2:0 planes: half the memory, and one conversion per frame.
    divider = yuv420(np.broadcast_to(np.array(DIVIDER_RGB, np.uint8), (s.height, DIVIDER_PX, 3)))

    kept: dict[str, list[Planes]] = {}
    first_rgb: dict[str, NDArray[np.uint8]] = {}  # for the posters of pairs
    done: list[tuple[str, float]] = []
    # A render that fails must not leave its GL context behind: the next task in this worker process would find
    # no valid context.
    try:
        for k, clip_id in enumerate(order, 1):
            clip = job.clips[clip_id]
            print(f"  {job.animation}: rendering clip {k}/{len(order)} ({clip.frames} frames)", flush=True)
            single = next((o for o in job.outputs if o.clips == (clip_id,)), None)
            # Pairs that can be written while this clip renders: the other side is held, or it is this clip.
            ready = [o for o in pairs if clip_id in o.clips and all(i == clip_id or i in kept for i in o.clips)]
            writers = _open_writers(job, clip, single, ready)
            frames: list[Planes] = []
            t0 = time.perf_counter()
            try:
                for f, planes, rgb in _frames(job, clip, arrays[clip.id], renderer, mesh):
                    if f == 0:
                        first_rgb[clip_id] = rgb
                    if single is not None:
                        writers[single.name].write(planes)
                        if f == 0:
                            write_poster(job.out_dir / single.poster, rgb)
                    for o in ready:
                        left = planes if o.clips[0] == clip_id else kept[o.clips[0]][f]
                        right = planes if o.clips[1] == clip_id else kept[o.clips[1]][f]
                        writers[o.name].write(hstack_planes(left, divider, right))
                        if f == 0:
                            bar = np.broadcast_to(np.array(DIVIDER_RGB, np.uint8), (s.height, DIVIDER_PX, 3))
                            poster = np.concatenate([first_rgb[o.clips[0]], bar, first_rgb[o.clips[1]]], axis=1)
                            write_poster(job.out_dir / o.poster, poster)
                    if clip_id in held:
                        frames.append(planes)
            except BaseException as exc:
                for w in writers.values():
                    w.abort()
                if isinstance(exc, Exception) and not isinstance(exc, RenderError):
                    raise RenderError(f"rendering clip {clip_id} ({job.animation}) failed: "
                                      f"{type(exc).__name__}: {exc}") from exc
                raise
            for w in writers.values():
                w.close()
            done += [(name, time.perf_counter() - t0) for name in writers]
            for name in writers:
                stored(name)
            if clip_id in held:
                kept[clip_id] = frames
            _release_memory()
    finally:
        renderer.close()
    print(f"  {job.animation}: {len(done)} videos in {time.perf_counter() - started:.1f} s", flush=True)
    return done


# --- main side -------------------------------------------------------------------------------------------------
