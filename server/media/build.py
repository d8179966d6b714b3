"""Pre-rendering of a clip set into blind videos: one per clip, and one side-by-side video per compared pair.

Every output's name is ``HMAC(secret, key)`` where ``key`` hashes everything that decides its pixels (clip content,
character, render settings, camera, layout); so names are opaque, stable across runs, and an output whose file
exists is up to date.  Only ``manifest.json`` (read by the server, never served) says what a name shows.
"""

from __future__ import annotations

import hashlib
import os
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

from server.clipset.manifest import ManifestError
from server.errors import MediaError

from .manifest import RenderedClip, RenderedPair, RenderManifest, read_render_manifest, write_render_manifest
from .plan import DIVIDER_PX, MEDIA_NAME, AnimationJob, Output, Plan, plan
from .scene import RenderSettings
from .worker import (
    RenderedFile,
    RenderError,
    SchedulerLost,
    init_worker,
    job_arrays,
    job_character,
    render_task,
    run_job,
)


def store_rendered(out_dir: Path, files: Sequence[RenderedFile]) -> None:
    """Write a task's files into ``out_dir`` (checked against their hashes; each appears whole or not at all)."""
    for f in files:
        if not MEDIA_NAME.fullmatch(f.name) or hashlib.sha256(f.data).hexdigest() != f.sha256:
            raise MediaError(f"a render task returned {f.name!r} damaged (name or sha256 does not match)")
        tmp = out_dir / f"{f.name}.{os.getpid()}.tmp"
        tmp.write_bytes(f.data)
        os.replace(tmp, out_dir / f.name)


class PeakMemory:
    """Samples the resident memory of this process and all its descendants (Linux ``/proc``) in a thread.

    Every ``interval`` seconds it reads the members' ``statm``; which processes are members (a read of every
    process's ``stat``: 15-20 ms per sample on a machine running a few hundred processes, a fifth of a core beside
    the render when done every sample) is looked up every ``rescan`` seconds."""

    def __init__(self, interval: float = 0.1, rescan: float = 1.0) -> None:
        self.peak_bytes = 0
        self._interval = interval
        self._rescan = rescan
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def _tree() -> set[int]:
        parents: dict[int, int] = {}
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                parents[int(stat.parent.name)] = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):  # the process ended while we looked
                continue
        tree, frontier = {os.getpid()}, [os.getpid()]
        while frontier:
            parent = frontier.pop()
            children = [pid for pid, pp in parents.items() if pp == parent and pid not in tree]
            tree.update(children)
            frontier += children
        return tree

    @staticmethod
    def _rss(pids: set[int]) -> int:
        pages = 0
        for pid in pids:
            try:
                pages += int(Path(f"/proc/{pid}/statm").read_text().split()[1])
            except (OSError, IndexError, ValueError):
                continue
        return pages * os.sysconf("SC_PAGE_SIZE")

    def _run(self) -> None:
        tree: set[int] = set()
        scanned = -float("inf")
        while not self._stop.is_set():
            if time.monotonic() - scanned >= self._rescan:
                tree, scanned = self._tree(), time.monotonic()
            self.peak_bytes = max(self.peak_bytes, self._rss(tree))
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
                init_worker()
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
