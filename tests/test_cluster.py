"""Renders on Dask: a real ``dask scheduler`` and two ``dask worker`` processes on loopback, started here.

A small clip set (two animations, two conditions, 96x72) keeps it fast; every job is one animation's videos.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from server import cluster
from server.clipset.build import build_clip_set
from server.clipset.manifest import write_clip_set
from server.errors import MediaError
from server.media.build import render_media
from server.media.manifest import MANIFEST
from server.media.plan import read_clip_set
from server.media.scene import RenderSettings
from server.studies.service import clip_set_index, required_pairs
from server.studies.studyfile import thesis_study
from tests.server_fixtures import small_clip_config

TINY = RenderSettings(width=96, height=72, shadows=False)
SECRET = b"cluster test secret"
DASK = Path(sys.executable).with_name("dask")


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def clips_dir(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("clips")
    write_clip_set(build_clip_set(data, small_clip_config()), out)
    return out


@pytest.fixture(scope="module")
def pairs(clips_dir):
    design = thesis_study().design.model_copy(update={"animations": ["run", "idle"], "conditions": ["hybrid0"]})
    return required_pairs(design, clip_set_index(clips_dir))


@pytest.fixture(scope="module")
def local_render(data, clips_dir, pairs, tmp_path_factory):
    """The same videos rendered in this process, without Dask."""
    out = tmp_path_factory.mktemp("local")
    render_media(data, clips_dir, out, SECRET, TINY, pairs=pairs, workers=1)
    return out


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory):
    """``dask scheduler`` and two ``dask worker`` processes (no nanny: the worker is the process killed)."""
    logs = tmp_path_factory.mktemp("dask-logs")
    # The workers import this checkout's code (the one under test), not whatever the `dask` script finds first.
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    address = f"tcp://127.0.0.1:{_port()}"
    port = address.rsplit(":", 1)[1]
    procs = {"scheduler": subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", port,
                                            "--no-dashboard"], stdout=(logs / "scheduler.log").open("wb"),
                                           stderr=subprocess.STDOUT, env=env)}
    for name in ("w1", "w2"):
        procs[name] = subprocess.Popen([str(DASK), "worker", address, "--name", name, "--nthreads", "1",
                                        "--no-nanny", "--no-dashboard", "--death-timeout", "60"],
                                       stdout=(logs / f"{name}.log").open("wb"), stderr=subprocess.STDOUT, env=env)
    from distributed import Client

    client = None
    try:
        deadline = time.monotonic() + 60
        while client is None:
            try:
                client = Client(address, timeout=5, set_as_default=False)
            except OSError:
                if time.monotonic() > deadline:
                    pytest.fail(f"the scheduler did not start: {(logs / 'scheduler.log').read_text()[-2000:]}")
                time.sleep(0.5)
        client.wait_for_workers(2, timeout=60)
        yield address, client, procs
    finally:
        if client is not None:
            client.close()
        for proc in procs.values():
            proc.kill()
            proc.wait(10)


def _files(directory: Path) -> dict[str, bytes]:
    return {f.name: f.read_bytes() for f in sorted(directory.iterdir()) if f.suffix in (".mp4", ".jpg")}

def broken_clip_set(clips_dir: Path, out: Path) -> tuple[Path, Any]:
    """A copy of ``clips_dir`` in ``out`` whose first idle clip other than the keyframe one cannot be rendered (its
    rotations lack joints); returns the folder and that clip's manifest entry."""
    from server.media.plan import read_clip_set

    out.mkdir()
    for f in clips_dir.iterdir():
        (out / f.name).write_bytes(f.read_bytes())
    bad = next(c for c in read_clip_set(out) if c.animation == "idle" and c.condition != "keyframe")
    arrays = dict(np.load(bad.path))
    arrays["world_rotations"] = arrays["world_rotations"][:, :3]  # joints missing: the renderer cannot skin it
    with bad.path.open("wb") as f:
        np.savez(f, **arrays)
    return out, bad



@pytest.mark.slow  # tens of seconds (the serial run's slowest; still run by `make test`)
def test_a_worker_killed_mid_job_and_the_videos_are_byte_identical_to_a_local_render(
        data, clips_dir, pairs, local_render, dask_cluster, tmp_path):
    address, observer, procs = dask_cluster
    out = tmp_path / "media"
    errors: list[BaseException] = []

    def run() -> None:
        try:
            # One task per video: the framing and bounds each video task carries must give the bytes of a whole
            # animation's render (the test below with a restarted scheduler renders per animation).
            render_media(data, clips_dir, out, SECRET, TINY, pairs=pairs, scheduler=address, tasks="video")
        except BaseException as exc:  # handed to the test
            errors.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    # Kill -9 the second worker as soon as it is rendering a task.
    victim = next(w for w, info in observer.scheduler_info()["workers"].items() if info["name"] == "w2")
    deadline = time.monotonic() + 120
    while not observer.processing().get(victim):
        assert thread.is_alive() and time.monotonic() < deadline, "w2 never got a task"
        time.sleep(0.05)
    procs["w2"].kill()
    procs["w2"].wait(10)
    thread.join(300)
    assert not thread.is_alive() and errors == [], errors
    assert (out / MANIFEST).read_bytes() == (local_render / MANIFEST).read_bytes()
    mine, local = _files(out), _files(local_render)
    assert len(local) >= 2 * 2 * 3  # per animation at least 2 clip videos and a pair, each with a poster
    assert mine.keys() == local.keys()
    assert all(mine[name] == local[name] for name in local), "a video differs from the local render"


def test_an_unreachable_scheduler_is_named(data, clips_dir, pairs, tmp_path, monkeypatch):
    address = f"tcp://127.0.0.1:{_port()}"  # nothing listens there
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 1.0)  # Dask retries a refused connection until the timeout
    with pytest.raises(MediaError, match=f"cannot reach the Dask scheduler at {address}"):
        render_media(data, clips_dir, tmp_path / "media", SECRET, TINY, pairs=pairs, scheduler=address)


def test_workers_of_another_version_are_refused_naming_both(data, clips_dir, pairs, dask_cluster, tmp_path,
                                                          monkeypatch):
    address, _observer, _procs = dask_cluster
    monkeypatch.setattr(cluster, "PACKAGE_VERSION", "0.0.1-elsewhere")
    with pytest.raises(MediaError) as raised:
        render_media(data, clips_dir, tmp_path / "media", SECRET, TINY, pairs=pairs, scheduler=address)
    message = str(raised.value)
    assert "0.0.1-elsewhere" in message and f"animstudy {cluster.package_version()}" in message, message
    assert not (tmp_path / "media" / MANIFEST).exists()


def test_a_failing_clip_is_named_and_the_other_jobs_are_stored(data, clips_dir, pairs, local_render, dask_cluster,
                                                               tmp_path):
    address, _observer, _procs = dask_cluster
    broken, bad = broken_clip_set(clips_dir, tmp_path / "clips")
    out = tmp_path / "media"
    messages: list[str] = []
    with pytest.raises(MediaError, match=f"clip {bad.id}"):
        render_media(data, broken, out, SECRET, TINY, pairs=pairs, scheduler=address, progress=messages.append,
                     tasks="video")
    # Every video that does not show the broken clip was stored (one task per video: the same animation's too),
    # and is the local render's; the ones that show it are not.
    manifest = json.loads((local_render / MANIFEST).read_text())
    entries = [*({**e, "shows": [e["clip"]]} for e in manifest["clips"].values()),
               *({**e, "shows": [e["left"], e["right"]]} for e in manifest["pairs"])]
    fine = {e[k] for e in entries if bad.id not in e["shows"] for k in ("video", "poster")}
    broken_videos = {e["video"] for e in entries if bad.id in e["shows"]}
    stored, local = _files(out), _files(local_render)
    assert any(e["shows"][0].startswith("idle-") and bad.id not in e["shows"] for e in entries)
    assert fine == stored.keys(), "\n".join(messages)
    assert all(stored[n] == local[n] for n in fine)
    assert broken_videos and not broken_videos & stored.keys()


RESTARTED = """
import sys
from pathlib import Path
from server.media.build import render_media
from server.media.scene import RenderSettings
pairs = [tuple(p.split("|")) for p in sys.argv[4].split(",")]
render_media(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), {secret!r},
             RenderSettings(width={w}, height={h}, shadows=False), pairs=pairs, scheduler=sys.argv[5])
"""


def test_a_render_restarted_mid_job_renders_only_what_is_missing(data, clips_dir, pairs, local_render, dask_cluster,
                                                                 tmp_path):
    """The submitting process (the server, the command) is killed with -9 once the first job's files are stored;
    run again, it renders only the videos still missing, and they are the local render's."""
    address, _observer, _procs = dask_cluster
    out = tmp_path / "media"
    script = RESTARTED.format(secret=SECRET, w=TINY.width, h=TINY.height)
    first = subprocess.Popen([sys.executable, "-c", script, str(data), str(clips_dir), str(out),
                              ",".join(f"{a}|{b}" for a, b in pairs), address])
    deadline = time.monotonic() + 180
    while not (out.is_dir() and any(f.suffix == ".mp4" for f in out.iterdir())):
        assert first.poll() is None, "the render ended before it was killed"
        assert time.monotonic() < deadline, "no video was stored"
        time.sleep(0.05)
    first.kill()
    first.wait(10)
    assert not (out / MANIFEST).exists()  # it was killed mid-job
    # Up to date: a video with its poster (the kill may have come between a job's files).
    stored_before = {f.name for f in out.iterdir() if f.suffix == ".mp4" and f.with_suffix(".jpg").is_file()}
    total = sum(1 for n in _files(local_render) if n.endswith(".mp4"))
    assert 0 < len(stored_before) < total
    messages: list[str] = []
    render_media(data, clips_dir, out, SECRET, TINY, pairs=pairs, scheduler=address, progress=messages.append)
    missing = total - len(stored_before)
    assert f"{total} videos, {len(stored_before)} up to date, {missing} to render" in messages[0], messages
    assert f"rendered {missing} videos" in "\n".join(messages), messages
    assert _files(out) == _files(local_render)


def test_a_clip_set_builds_on_the_cluster_as_in_this_process(data, clips_dir, dask_cluster):
    """One task per animation on the real cluster (each reads no file: the motion comes read with the task);
    the clips are the ones built in this process (the clip set of the module), array for array."""
    address, _observer, _procs = dask_cluster
    messages: list[str] = []
    built = build_clip_set(data, small_clip_config(), progress=messages.append, scheduler=address)
    assert "building 2 animations on Dask" in messages, messages
    local = {c.id: c for c in read_clip_set(clips_dir)}
    assert [c.id for c in built] == list(local)
    for clip in built:
        with np.load(local[clip.id].path) as stored:
            arrays = clip.arrays()
            assert sorted(arrays) == sorted(stored.files)
            for name in stored.files:
                np.testing.assert_array_equal(arrays[name], stored[name], err_msg=f"{clip.id} {name}")


@pytest.mark.slow  # tens of seconds (the serial run's slowest; still run by `make test`)
def test_the_scheduler_restarted_mid_job_and_the_job_goes_on_with_what_is_missing(
        data, clips_dir, pairs, local_render, tmp_path, monkeypatch):
    """kill -9 the scheduler after the first video is stored; a new scheduler on the same address and a new
    worker come up (as SLURM or Kubernetes would bring them back): the same job finishes, each video is stored
    once, and every video is the local render's."""
    from server.media import build

    monkeypatch.setattr(cluster, "RECONNECT_PAUSE_S", 0.5)
    logs = tmp_path / "logs"
    logs.mkdir()
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    port = str(_port())
    address = f"tcp://127.0.0.1:{port}"
    procs: list[subprocess.Popen] = []

    def start(what: str, *args: str) -> subprocess.Popen:
        proc = subprocess.Popen([str(DASK), what, *args, "--no-dashboard"], env=env, stderr=subprocess.STDOUT,
                                stdout=(logs / f"{what}{len(procs)}.log").open("wb"))
        procs.append(proc)
        return proc

    def up() -> subprocess.Popen:
        scheduler = start("scheduler", "--host", "127.0.0.1", "--port", port)
        start("worker", address, "--nthreads", "1", "--no-nanny", "--death-timeout", "60")
        return scheduler

    out = tmp_path / "media"
    stored: list[str] = []
    real_store = build.store_rendered

    def store(directory, files):
        real_store(directory, files)
        stored.extend(f.name for f in files if f.name.endswith(".mp4"))

    monkeypatch.setattr(build, "store_rendered", store)
    errors: list[BaseException] = []
    messages: list[str] = []

    def run() -> None:
        try:
            render_media(data, clips_dir, out, SECRET, TINY, pairs=pairs, scheduler=address,
                         progress=messages.append)
        except BaseException as exc:  # handed to the test
            errors.append(exc)

    try:
        scheduler = up()
        time.sleep(2)  # the scheduler listens before the job tries to reach it
        thread = threading.Thread(target=run)
        thread.start()
        deadline = time.monotonic() + 180
        while not stored:
            assert thread.is_alive() and time.monotonic() < deadline, (errors, messages[-5:])
            time.sleep(0.05)
        scheduler.kill()
        scheduler.wait(10)
        before = len(stored)
        up()
        thread.join(300)
        assert not thread.is_alive() and errors == [], (errors, messages[-5:])
    finally:
        for proc in procs:
            proc.kill()
            proc.wait(10)
    assert any("waiting for the scheduler to come back" in m for m in messages), messages
    local = _files(local_render)
    videos = {name for name in local if name.endswith(".mp4")}
    assert sorted(stored) == sorted(set(stored)) and set(stored) == videos  # each stored once, none left out
    assert 0 < before < len(videos)
    mine = _files(out)
    assert mine.keys() == local.keys() and all(mine[n] == local[n] for n in local)



def test_the_local_cluster_opens_no_port_beyond_loopback():
    """dask/distributed#8136: ``dashboard_address=None`` still starts the scheduler's HTTP server, on port 8787 of
    every interface (a second cluster on the machine warned "Port 8787 is already in use").  The local cluster's
    scheduler listens on 127.0.0.1 only, on a free port, and two run side by side without a warning."""
    import warnings

    from server.cluster import dask_client

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "Port 8787 is already in use" is a UserWarning
        with dask_client(None, workers=1) as first, dask_client(None, workers=1) as second:
            for client in (first, second):
                scheduler = client.cluster.scheduler
                assert scheduler.http_server is not None
                hosts = {s.getsockname()[0] for s in scheduler.http_server._sockets.values()}
                assert hosts == {"127.0.0.1"}, hosts


def test_local_workers_start_with_the_render_code_imported_and_a_configured_method_is_kept():
    """Local workers are forked from a server that imported the render and build code once (a spawned worker
    imports it anew, ~2 s of a core each, per job); every cluster of this process forks from the same server.  A
    start method configured in Dask's own settings (other than its default) is used as it is."""
    import dask

    from server.cluster import dask_client

    parents = set()
    for _ in range(2):
        with dask_client(None, workers=2) as client:
            # eval of a string: a function of this module would make the worker import this module, and with it
            # the render code
            found = client.run(eval, "'server.media.worker' in __import__('sys').modules, __import__('os').getppid()")
        assert len(found) == 2 and all(loaded for loaded, _ in found.values()), found
        parents |= {parent for _, parent in found.values()}
    assert len(parents) == 1 and os.getpid() not in parents  # one fork server, not this process
    with dask.config.set({"distributed.worker.multiprocessing-method": "fork"}):
        cluster._fork_local_workers()  # set in Dask's configuration: left alone, not replaced
        assert dask.config.get("distributed.worker.multiprocessing-method") == "fork"
