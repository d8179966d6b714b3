"""Pre-rendering of a clip set into blind videos: one per clip, and one side-by-side video per compared pair.

Every output's name is ``HMAC(secret, key)`` where ``key`` hashes everything that decides its pixels (clip content,
character, render settings, camera, layout); so names are opaque, stable across runs, and an output whose file
exists is up to date.  Only ``manifest.json`` (read by the server, never served) says what a name shows.
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import hashlib
import hmac
import json
import os
import re
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from anim_core.rig.gltf_character import MappedCharacter
from server.assets import AssetError
from server.clipset.build import configured_character, record_config
from server.clipset.config import CharacterConfig
from server.clipset.manifest import ClipEntry, ManifestError, read_clip_manifest
from server.errors import MediaError

from .manifest import RenderedClip, RenderedPair, RenderManifest, read_render_manifest, write_render_manifest
from .scene import Framing, RenderSettings, frame_motion

if TYPE_CHECKING:
    from anim_core.math.skinning import SkinnedMesh
    from anim_core.rig.character import Character

#: A video's or poster's file name.  Check names with ``MEDIA_NAME.fullmatch``, never ``match``: Python's ``$``
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
                                    n_frames=sum(_rendered_frames(self.clips[i]) for i in set(o.clips)))
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


def _rendered_frames(clip: ClipEntry) -> int:
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
            n_frames = sum(_rendered_frames(clips[i]) for i in {i for o in missing for i in o.clips})
            jobs.append(AnimationJob(animation, data_dir, group, missing, settings, framing, spacing,
                                     tuple(bounds.ravel().tolist()), out_dir, n_frames, body))
    return Plan(sorted(jobs, key=lambda j: -j.n_frames), clip_outputs, pair_outputs, clips)


# --- worker side -----------------------------------------------------------------------------------------------

def _init_worker() -> None:
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

    _init_worker()
    with tempfile.TemporaryDirectory(prefix="animstudy-render-") as tmp:
        run_job(dataclasses.replace(job, out_dir=Path(tmp)), arrays, character)
        files = []
        for o in job.outputs:
            for name in (o.video, o.poster):
                data = (Path(tmp) / name).read_bytes()
                files.append(RenderedFile(name, data, hashlib.sha256(data).hexdigest()))
    return files


def store_rendered(out_dir: Path, files: Sequence[RenderedFile]) -> None:
    """Write a task's files into ``out_dir`` (checked against their hashes; each appears whole or not at all)."""
    for f in files:
        if not MEDIA_NAME.fullmatch(f.name) or hashlib.sha256(f.data).hexdigest() != f.sha256:
            raise MediaError(f"a render task returned {f.name!r} damaged (name or sha256 does not match)")
        tmp = out_dir / f"{f.name}.{os.getpid()}.tmp"
        tmp.write_bytes(f.data)
        os.replace(tmp, out_dir / f.name)


def clip_mesh(mesh: SkinnedMesh, clip: ClipEntry) -> SkinnedMesh:
    """The body as ``clip`` is skinned: with its render settings' ``skin_influences`` strongest weights per vertex
    (renormalised), or as bound."""
    from anim_core.bench.cost import skinned_mesh

    influences = clip.render.skin_influences if clip.render is not None else None
    return skinned_mesh(mesh, influences)


def run_job(job: AnimationJob, arrays: Arrays | None = None, character: Character | None = None,
            stored: Callable[[str], None] = lambda _name: None) -> list[tuple[str, float]]:
    """Render the job's outputs into ``job.out_dir``; returns (output name, seconds) per finished video.
    ``arrays`` and ``character``: given as values (default: read from the clip files and the data directory);
    ``stored`` is called with each video's name once it is in place."""
    from anim_core.rig.character import bind_mesh

    from .renderer import ClipRenderer
    from .video import Planes, VideoWriter, hstack_planes, write_poster, yuv420

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
    # Pairs need both sides at once: keep the frames of the clip shared by most pairs (the keyframe clip) and of
    # the first side of any pair without it; everything else streams.
    counts: dict[str, int] = {}
    for o in pairs:
        for i in set(o.clips):
            counts[i] = counts.get(i, 0) + 1
    anchor = max(counts, key=lambda i: counts[i]) if counts else None
    held = {anchor} | {o.clips[0] for o in pairs if anchor not in o.clips and o.clips[0] != o.clips[1]}
    held.discard(None)
    needed = {i for o in job.outputs for i in o.clips}
    order = sorted(needed, key=lambda i: (i not in held, i))
    first_rgb: dict[str, NDArray[np.uint8]] = {}  # posters of pairs are RGB
    # Frames are kept and tiled as the encoder's YUV 4:2:0 planes: half the memory, and one conversion per frame.
    divider = yuv420(np.broadcast_to(np.array(DIVIDER_RGB, np.uint8), (s.height, DIVIDER_PX, 3)))

    def frames_of(clip: ClipEntry) -> Iterator[tuple[int, Planes, NDArray[np.uint8] | None]]:
        """(frame, planes, RGB or None) in playback order.  The second half of a ping-pong period is the first
        half backwards (frame f shows the pose of frame T - f), so only the first half is rendered."""
        a = arrays[clip.id]
        n = _rendered_frames(clip)
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
            writers = {}
            if single is not None:
                writers[single.name] = VideoWriter(job.out_dir / single.video, s.width, s.height, clip.fps)
            for o in ready:
                writers[o.name] = VideoWriter(job.out_dir / o.video, 2 * s.width + DIVIDER_PX, s.height, clip.fps)
            frames: list[Planes] = []
            t0 = time.perf_counter()
            try:
                for f, planes, rgb in frames_of(clip):
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

class PeakMemory:
    """Samples the resident memory of this process and all its descendants (Linux ``/proc``) in a thread."""

    def __init__(self, interval: float = 0.1) -> None:
        self.peak_bytes = 0
        self._interval = interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def _tree_rss() -> int:
        parents: dict[int, int] = {}
        rss: dict[int, int] = {}
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()
            except OSError:  # the process ended while we looked
                continue
            pid = int(stat.parent.name)
            parents[pid] = int(fields[1])
            rss[pid] = int(fields[21]) * os.sysconf("SC_PAGE_SIZE")
        tree, frontier = {os.getpid()}, [os.getpid()]
        while frontier:
            parent = frontier.pop()
            children = [pid for pid, pp in parents.items() if pp == parent and pid not in tree]
            tree.update(children)
            frontier += children
        return sum(rss.get(pid, 0) for pid in tree)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak_bytes = max(self.peak_bytes, self._tree_rss())
            self._stop.wait(self._interval)

    def __enter__(self) -> PeakMemory:
        if Path("/proc/self/stat").exists():
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()


#: How a render is cut into Dask tasks: ``animation`` (one per animation: each clip rendered once, every video of
#: the animation made from those frames), ``video`` (one per video: a clip rendered once per video that shows it,
#: the reference once per pair, about three times the frames of a study of one reference and two conditions) or
#: ``auto`` (whichever is expected to finish first on the cluster's workers).
TaskSize = Literal["auto", "animation", "video"]


def render_tasks(p: Plan, workers: int, size: TaskSize = "auto") -> list[AnimationJob]:
    """The Dask tasks of a plan.  ``auto`` compares the two cuts by their expected span on ``workers`` workers
    (the larger of the frames per worker and the longest task): per video wins only when there are many more
    workers than animations, so the extra frames are rendered by workers that would otherwise wait."""
    whole = list(p.jobs)
    if size == "animation":
        return whole
    split = [t for j in p.jobs for t in j.video_tasks()]
    if size == "video":
        return split

    def span(tasks: list[AnimationJob]) -> float:
        return max(sum(t.n_frames for t in tasks) / max(1, workers), max((t.n_frames for t in tasks), default=0))

    return split if span(split) < span(whole) else whole


def run_on_dask(p: Plan, out_dir: Path, scheduler: str | None, workers: int,
                progress: Callable[[str], None], stored: Callable[[str], None] = lambda _name: None,
                size: TaskSize = "auto") -> list[list[tuple[str, float]]]:
    """The plan's :func:`render_tasks` (``size``) on the cluster (see :mod:`server.cluster`), the character sent
    once per job; each task's videos are stored as it finishes, so a render interrupted later renders only what is
    still missing.  A failed task fails the render naming its clip, after the others have finished and been
    stored."""
    from concurrent.futures import CancelledError

    from distributed import as_completed as dask_completed

    from server.cluster import dask_client, share

    videos = sum(len(j.outputs) for j in p.jobs)
    with dask_client(scheduler, min(workers, videos)) as client, client.as_current():
        tasks = render_tasks(p, len(client.scheduler_info()["workers"]) or workers, size)
        # Longest first, so that the last task to start is a short one.
        tasks.sort(key=lambda t: -t.n_frames)
        shared = {c: share(client, job_character(j), "character") for c, j in {j.character: j for j in p.jobs}.items()}
        futures = {client.submit(render_task, t, job_arrays(t), shared[t.character], pure=False,
                                 key=f"render-{t.animation}-{t.outputs[0].name[:8]}-{uuid.uuid4().hex[:8]}"): t
                   for t in tasks}
        results, failures, lost = [], [], 0
        for future in dask_completed(futures):
            task = futures[future]
            try:
                files = future.result()
            except CancelledError:  # the scheduler went away: every task still to finish is cancelled
                lost += 1
                continue
            except Exception as exc:  # the task's own error, or its workers kept dying
                failures.append(str(exc) if isinstance(exc, MediaError) else
                                f"rendering {task.animation} ({', '.join(task.outputs[0].clips)}) failed: "
                                f"{type(exc).__name__}: {exc}")
                progress(f"  {task.animation}: FAILED ({failures[-1]})")
                continue
            store_rendered(out_dir, files)
            for o in task.outputs:
                stored(o.name)
            results.append([(f.name, 0.0) for f in files if f.name.endswith(".mp4")])
            progress(f"  {task.animation}: {len(task.outputs)} video(s) stored ({len(results)}/{len(tasks)} tasks)")
    if lost:
        failures.insert(0, f"lost the Dask scheduler {scheduler or '(local cluster)'} mid-job: {lost} of "
                           f"{len(tasks)} videos not rendered, {len(results)} stored; run it again once the "
                           "scheduler is back, and it renders only the missing ones")
        if len(failures) == 1:
            raise SchedulerLost(failures[0])
    if failures:
        raise RenderError("; ".join(failures))
    return results


def _run_until_done(p: Plan, replan: Callable[[], Plan], out_dir: Path, scheduler: str | None, workers: int,
                    progress: Callable[[str], None], stored: Callable[[str], None], size: TaskSize
                    ) -> list[list[tuple[str, float]]]:
    """:func:`run_on_dask`; when the configured scheduler is lost mid-job (restarted, or its machine rebooted), the
    job waits for it (and for a worker) and goes on with what is still missing, for up to
    :data:`server.cluster.RECONNECT_S`; nothing stored is rendered again.  A scheduler unreachable at the start is
    an error at once, as is any other failure."""
    from server import cluster

    results: list[list[tuple[str, float]]] = []
    since: float | None = None
    while True:
        try:
            results += run_on_dask(p, out_dir, scheduler, workers, progress, stored, size)
            return results
        except (SchedulerLost, cluster.ClusterError) as exc:
            if not scheduler or (since is None and not isinstance(exc, SchedulerLost)):
                raise
            since = since if since is not None else time.monotonic()
            if time.monotonic() - since > cluster.RECONNECT_S:
                raise MediaError(f"{exc} (waited {cluster.RECONNECT_S:.0f} s for the scheduler to come back)"
                                 ) from None
            progress(f"  {exc}; waiting for the scheduler to come back")
            time.sleep(cluster.RECONNECT_PAUSE_S)
            p = replan()


def render_media(data_dir: Path, clips_dir: Path, out_dir: Path, secret: bytes,
                 settings: RenderSettings | None = None, pairs: Sequence[tuple[str, str]] = (),
                 workers: int = 2, animations: Sequence[str] | None = None, every_clip: bool = True,
                 progress: Callable[[str], None] = lambda _m: None, manifest_dir: Path | None = None,
                 scheduler: str | None = None, videos_done: Callable[[int, int], None] = lambda _d, _t: None,
                 tasks: TaskSize = "auto") -> Path:
    """Render what is missing of :func:`plan` and write the manifest; returns the manifest path.  Nothing
    rendered before is deleted or replaced (``animstudy gc`` collects what no study uses).  The manifest goes
    into ``manifest_dir`` (default ``out_dir``): the videos of several clip sets share one media directory.

    ``scheduler`` (``ANIMSTUDY_DASK_SCHEDULER``): the jobs run on that Dask cluster; otherwise on a local Dask
    cluster of ``workers`` processes, or in this process when ``workers`` is 1.  ``videos_done(done, total)`` is
    called before the first video and after each one is stored (``total``: the videos missing; a job's progress).
    ``tasks``: how the render is cut into Dask tasks (:data:`TaskSize`).
    """
    settings = settings or RenderSettings()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    p = plan(data_dir, clips_dir, out_dir, settings, secret, pairs, animations, every_clip)
    todo = sum(len(j.outputs) for j in p.jobs)
    videos = len({o.name for o in p.outputs})  # clips with identical arrays share theirs
    where = f"Dask scheduler {scheduler}" if scheduler else f"{min(workers, max(1, todo))} workers"
    progress(f"{videos} videos, {videos - todo} up to date, {todo} to render "
             f"({sum(j.n_frames for j in p.jobs)} frames, {where})")
    finished: list[str] = []

    def stored(name: str) -> None:
        finished.append(name)
        videos_done(len(finished), todo)

    videos_done(0, todo)
    if p.jobs:
        with PeakMemory() as memory:
            if workers <= 1 and not scheduler:
                _init_worker()
                results = [run_job(j, stored=stored) for j in p.jobs]
            else:
                results = _run_until_done(p, lambda: plan(data_dir, clips_dir, out_dir, settings, secret, pairs,
                                                          animations, every_clip),
                                          out_dir, scheduler, workers, progress, stored, tasks)
        progress(f"rendered {sum(len(r) for r in results)} videos in {time.perf_counter() - started:.1f} s, "
                 f"peak memory {memory.peak_bytes / 2**20:.0f} MiB (all processes)")
    manifest_dir = Path(manifest_dir or out_dir)
    manifest_dir.mkdir(parents=True, exist_ok=True)
    path = write_render_manifest(manifest_dir, _manifest(p, settings))
    # Videos not in this manifest stay: a study's pinned stimulus set may show them (server.stimuli); `animstudy
    # gc` removes the ones nothing uses.  Only leftovers of a killed render go.
    keep = {o.video for o in p.outputs} | {o.poster for o in p.outputs}
    leftovers = [f for f in out_dir.iterdir() if f.name.endswith(".tmp")]
    for f in leftovers:
        f.unlink(missing_ok=True)
    from .video import FILE_TIME

    for name in keep:  # files from before FILE_TIME existed, or touched since, get it too
        if (out_dir / name).is_file():
            os.utime(out_dir / name, (FILE_TIME, FILE_TIME))
    progress(f"done in {time.perf_counter() - started:.1f} s -> {path}")
    return path


def rendered_pairs(out_dir: Path) -> list[tuple[str, str]]:
    """(left, right) of every pair video in ``out_dir`` (none without a readable manifest)."""
    try:
        return [(p.left, p.right) for p in read_render_manifest(out_dir).pairs]
    except ManifestError:
        return []


def _manifest(p: Plan, settings: RenderSettings) -> RenderManifest:
    def video(o: Output, width: int) -> dict[str, Any]:
        c = p.clips[o.clips[0]]
        return {"video": o.video, "poster": o.poster, "frames": c.frames, "fps": c.fps, "width": width,
                "height": settings.height}

    pair_width = 2 * settings.width + DIVIDER_PX
    return RenderManifest(
        settings=settings.as_dict(),
        clips={i: RenderedClip(clip=i, animation=p.clips[i].animation, condition=p.clips[i].condition,
                               **video(o, settings.width)) for i, o in p.clip_outputs.items()},
        pairs=[RenderedPair(left=left, right=right, **video(o, pair_width))
               for (left, right), o in p.pair_outputs.items()],
    )
