"""Load, crash and outage test of the participant API (loopback only, bounded in count and time).

``animstudy loadtest`` starts the server (uvicorn, several workers) on a fresh database, lets N simulated
participants run the whole API concurrently (consent, demographics, every vote), optionally kills the server
with SIGKILL or stops PostgreSQL in the middle, and at the end checks the database: every vote the server
acknowledged is stored exactly once, and nothing else is stored.  Clients behave like the participant page:
they retry with backoff on connection errors and 5xx, re-send a vote with the same idempotency key until it
is acknowledged, and follow the server's state after a 409.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import make_url, select, text

from .config import REPO_ROOT, normalize_database_url
from .db import make_engine, migrate, session_factory
from .media.manifest import RenderedClip, RenderedPair, RenderManifest
from .participants.models import Trial, Vote
from .studies.design import Design
from .studies.models import StudyState
from .studies.scale import CHOICES
from .studies.service import create_study, required_pairs, set_state
from .studies.studyfile import thesis_study

DEFAULT_PG = "postgresql://postgres@127.0.0.1:5432/animstudy_load"


def synthetic_media(design: Design) -> RenderManifest:
    """A render manifest with opaque names, for studies whose videos nobody watches (API load tests)."""
    clips, pairs = {}, []
    keys = {(a, c): f"{a}-{c}" for a in design.animations
            for c in (design.reference, *design.conditions, *([design.practice] if design.practice else []))}
    for i, ((animation, condition), clip) in enumerate(sorted(keys.items())):
        clips[clip] = RenderedClip(clip=clip, animation=animation, condition=condition, video=f"{i:024x}.mp4",
                                   poster=f"{i:024x}.jpg", frames=40, fps=30, width=640, height=480)
    for k, (left, right) in enumerate(required_pairs(design, keys)):
        pairs.append(RenderedPair(left=left, right=right, video=f"{k + 1000:024x}.mp4",
                                  poster=f"{k + 1000:024x}.jpg", frames=40, fps=30, width=1284, height=480))
    return RenderManifest(clips=clips, pairs=pairs)


def prepare_database(kind: str, workdir: Path, pg_url: str = DEFAULT_PG) -> str:
    """A migrated, empty database with the default study open; returns its URL."""
    if kind == "sqlite":
        url = f"sqlite:///{workdir / 'load.db'}"
    else:
        target = make_url(normalize_database_url(pg_url))
        admin = make_engine(target.set(database="postgres").render_as_string(hide_password=False))
        with admin.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
            if not conn.scalar(text("SELECT 1 FROM pg_database WHERE datname = :n"), {"n": target.database}):
                conn.execute(text(f'CREATE DATABASE "{target.database}"'))
        admin.dispose()
        url = target.render_as_string(hide_password=False)
        engine = make_engine(url)
        with engine.begin() as conn:
            conn.execute(text("DROP SCHEMA public CASCADE"))
            conn.execute(text("CREATE SCHEMA public"))
        engine.dispose()
    engine = make_engine(url)
    migrate(engine)
    with session_factory(engine)() as db:
        study_file = thesis_study()
        set_state(db, create_study(db, synthetic_media(study_file.design), study_file), StudyState.open)
    engine.dispose()
    return url


@dataclass
class Server:
    """uvicorn in its own process group (so SIGKILL takes the workers too)."""

    database_url: str
    workdir: Path
    workers: int
    port: int = 0
    process: subprocess.Popen | None = None

    def start(self) -> None:
        if not self.port:
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                self.port = s.getsockname()[1]
        env = {**os.environ, "DATABASE_URL": self.database_url, "ANIMSTUDY_VAR_DIR": str(self.workdir / "var"),
               "ANIMSTUDY_SECRET_KEY": "load-test-secret-key-0123456789abcdef",
               # every simulated participant comes from 127.0.0.1: no limit on new sessions per address
               "ANIMSTUDY_SESSIONS_PER_MINUTE": "0"}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "server.app:app_from_env", "--factory", "--host", "127.0.0.1",
             "--port", str(self.port), "--workers", str(self.workers), "--log-level", "warning",
             "--no-access-log"], cwd=REPO_ROOT, env=env, start_new_session=True)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(f"{self.base}/healthz", timeout=1) as r:
                    if r.status == 200:
                        return
            except (urllib.error.URLError, OSError):
                time.sleep(0.1)
        raise RuntimeError("the server did not start within 30 s")

    @property
    def base(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def kill(self) -> None:
        if self.process is not None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()
            self.process = None

    def stop(self) -> None:
        if self.process is not None:
            os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.kill()
            self.process = None


@dataclass
class Stats:
    latencies: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    statuses: Counter = field(default_factory=Counter)
    acknowledged: dict[int, tuple[str, str]] = field(default_factory=dict)  # trial id -> (session, choice)
    retries: int = 0
    connection_errors: int = 0
    sessions: list[str] = field(default_factory=list)
    first_vote: float | None = None
    last_vote: float | None = None


@dataclass
class Answer:
    status: int
    headers: dict[str, str]
    body: bytes

    def json(self) -> Any:
        return json.loads(self.body)


class Client:
    """One keep-alive HTTP/1.1 connection, as a browser tab holds one.  Deliberately minimal (fixed-length bodies
    only, which is all this API sends): a general-purpose client costs a few milliseconds of CPU per request,
    and the load generator shares the machine with the server it measures."""

    def __init__(self, host: str, port: int, timeout: float = 10.0) -> None:
        self.host, self.port, self.timeout = host, port, timeout
        self._streams: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None

    async def request(self, method: str, path: str, token: str | None = None, body: Any = None) -> Answer:
        try:
            return await asyncio.wait_for(self._exchange(method, path, token, body), self.timeout)
        except BaseException:
            self.close()  # a half-read answer would poison the next one
            raise

    async def _exchange(self, method: str, path: str, token: str | None, body: Any) -> Answer:
        if self._streams is None:
            self._streams = await asyncio.open_connection(self.host, self.port)
        reader, writer = self._streams
        payload = b"" if body is None else json.dumps(body).encode()
        head = [f"{method} {path} HTTP/1.1", f"Host: {self.host}:{self.port}", f"Content-Length: {len(payload)}"]
        if body is not None:
            head.append("Content-Type: application/json")
        if token:
            head.append(f"Authorization: Bearer {token}")
        writer.write(("\r\n".join(head) + "\r\n\r\n").encode() + payload)
        lines = (await reader.readuntil(b"\r\n\r\n")).decode("latin-1").split("\r\n")
        status = int(lines[0].split(" ", 2)[1])
        headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:] if line)}
        if "content-length" not in headers and status not in (204, 304):
            raise ConnectionError(f"answer without Content-Length ({status})")
        data = await reader.readexactly(int(headers.get("content-length", 0)))
        if headers.get("connection", "").lower() == "close":
            self.close()
        return Answer(status, headers, data)

    def close(self) -> None:
        if self._streams is not None:
            self._streams[1].close()
            self._streams = None


async def _call(client: Client, stats: Stats, name: str, method: str, path: str, deadline: float,
                token: str | None = None, body: Any = None) -> Answer:
    """One logical request, retried with backoff on connection errors and 5xx until an answer below 500."""
    delay = 0.05
    while True:
        start = time.perf_counter()
        try:
            r: Answer | None = await client.request(method, path, token, body)
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError, ValueError):
            stats.connection_errors += 1
            r = None
        else:
            stats.latencies[name].append((time.perf_counter() - start) * 1000)
            stats.statuses[f"{name} {r.status}"] += 1
            if r.status < 500:
                return r
        if time.monotonic() > deadline:
            raise TimeoutError(f"{name}: no answer before the time limit")
        stats.retries += 1
        retry_after = float(r.headers.get("retry-after", 0)) if r is not None else 0.0
        await asyncio.sleep(max(delay, min(retry_after, 2.0)) * (0.5 + random.random()))
        delay = min(delay * 2, 1.0)


async def participant(client: Client, stats: Stats, rng: random.Random, deadline: float, pause_ms: float) -> None:
    r = await _call(client, stats, "create", "POST", "/api/v1/studies/thesis/sessions", deadline,
                    body={"consent": True, "external": {"PROLIFIC_PID": f"load-{rng.random():.12f}"}})
    if r.status != 201:
        raise RuntimeError(f"could not start a session: {r.status} {r.body!r}")
    sid, token = r.json()["session_id"], r.json()["token"]
    stats.sessions.append(sid)
    await _call(client, stats, "demographics", "PUT", f"/api/v1/sessions/{sid}/demographics", deadline,
                token=token, body={"gamer": rng.choice(["yes", "no"]), "tech_savvy": "dont_know"})
    upcoming: dict[str, Any] | None = None  # like the page: the vote's answer names the next trial
    while True:
        if upcoming is None:
            r = await _call(client, stats, "next", "GET", f"/api/v1/sessions/{sid}/next", deadline, token=token)
            if r.status == 204:
                return
            upcoming = r.json()
        trial = upcoming["trial_id"]
        if pause_ms:
            await asyncio.sleep(rng.uniform(0.5, 1.5) * pause_ms / 1000)
        body = {"choice": rng.choice(CHOICES), "rt_ms": rng.randint(800, 9000),
                "idempotency_key": f"{sid}-{trial}-{rng.random():.9f}"}
        r = await _call(client, stats, "vote", "POST", f"/api/v1/sessions/{sid}/trials/{trial}/vote", deadline,
                        token=token, body=body)
        if r.status in (200, 201):
            stats.acknowledged[trial] = (sid, body["choice"])
            now = time.monotonic()
            stats.first_vote = stats.first_vote or now
            stats.last_vote = now
            upcoming = r.json()["next"]
            if upcoming is None:
                return
        elif r.status == 409:  # the server moved on already; ask it where to
            upcoming = None
        else:
            raise RuntimeError(f"vote refused: {r.status} {r.body!r}")


async def _run_clients(port: int, n: int, concurrency: int, seed: int, deadline: float, pause_ms: float,
                       stats: Stats, ramp_s: float = 0.0) -> None:
    rng = random.Random(seed)
    gate = asyncio.Semaphore(concurrency)

    async def one(i: int) -> None:
        await asyncio.sleep(ramp_s * i / n)  # arrivals spread over the ramp (0: everybody at once)
        async with gate:
            client = Client("127.0.0.1", port)
            try:
                await participant(client, stats, random.Random(rng.random() + i), deadline, pause_ms)
            finally:
                client.close()

    await asyncio.gather(*(one(i) for i in range(n)))


def check_database(database_url: str, stats: Stats) -> dict[str, int]:
    """Every acknowledged vote stored once with its choice; no vote stored that was never acknowledged."""
    engine = make_engine(database_url)
    with session_factory(engine)() as db:
        # keyed by the trial's id in the API (its public id), as the acknowledgements are
        stored = {public: (v.session_id, v.choice) for v, public in db.execute(
            select(Vote, Trial.public_id).join(Trial, Trial.id == Vote.trial_id)
            .where(Vote.session_id.in_(stats.sessions)))}
        total = db.scalar(text("SELECT count(*) FROM votes"))
        per_trial = db.execute(text("SELECT trial_id, count(*) FROM votes GROUP BY trial_id HAVING count(*) > 1"))
        duplicated = len(per_trial.all())
    engine.dispose()
    lost = sum(1 for trial, ack in stats.acknowledged.items() if stored.get(trial) != ack)
    unacknowledged = sum(1 for trial in stored if trial not in stats.acknowledged)
    return {"acknowledged": len(stats.acknowledged), "stored": int(total), "lost": lost, "duplicated": duplicated,
            "stored_without_acknowledgement": unacknowledged}


def _pg_cluster(action: str) -> None:
    version = sorted(os.listdir("/etc/postgresql"))[-1]
    subprocess.run(["pg_ctlcluster", "--skip-systemctl-redirect", version, "main", action], check=True,
                   capture_output=True)


def run(database: str = "sqlite", participants: int = 200, workers: int = 2, concurrency: int = 100,
        seed: int = 1, time_limit: float = 300.0, pause_ms: float = 0.0, ramp_s: float = 0.0,
        crash_at: float | None = None,
        outage_at: float | None = None, outage_s: float = 5.0, pg_url: str = DEFAULT_PG,
        progress: Any = print) -> dict[str, Any]:
    """The whole scenario; returns the report (see :func:`format_report`)."""
    if outage_at is not None and database != "postgresql":
        raise ValueError("a database outage is a PostgreSQL scenario")
    with tempfile.TemporaryDirectory(prefix="animstudy-load-") as tmp:
        workdir = Path(tmp)
        url = prepare_database(database, workdir, pg_url)
        server = Server(url, workdir, workers)
        server.start()
        progress(f"{participants} participants against {server.base} ({database}, {workers} workers)")
        stats = Stats()
        expected_votes = participants * 16
        deadline = time.monotonic() + time_limit
        events: list[str] = []

        async def faults() -> None:
            for at, kind in ((crash_at, "crash"), (outage_at, "outage")):
                if at is None:
                    continue
                while len(stats.acknowledged) < at * expected_votes and time.monotonic() < deadline:
                    await asyncio.sleep(0.02)
                if kind == "crash":
                    server.kill()
                    events.append(f"SIGKILL after {len(stats.acknowledged)} votes")
                    await asyncio.sleep(1.0)
                    await asyncio.to_thread(server.start)
                    events.append("server restarted")
                else:
                    await asyncio.to_thread(_pg_cluster, "stop")
                    events.append(f"PostgreSQL stopped after {len(stats.acknowledged)} votes")
                    await asyncio.sleep(outage_s)
                    await asyncio.to_thread(_pg_cluster, "start")
                    events.append(f"PostgreSQL started again after {outage_s:.0f} s")

        async def main() -> None:
            await asyncio.gather(_run_clients(server.port, participants, concurrency, seed, deadline, pause_ms,
                                              stats, ramp_s), faults())

        started = time.monotonic()
        try:
            asyncio.run(main())
        finally:
            server.stop()
        elapsed = time.monotonic() - started
        check = check_database(url, stats)
    voting = (stats.last_vote - stats.first_vote) if stats.first_vote and stats.last_vote else elapsed
    return {
        "database": database, "participants": participants, "workers": workers, "concurrency": concurrency,
        "pause_ms": pause_ms, "ramp_s": ramp_s,
        "seconds": elapsed, "votes_per_s": check["acknowledged"] / max(voting, 1e-9),
        "latency_ms": {name: {"p50": float(np.percentile(v, 50)), "p95": float(np.percentile(v, 95)),
                              "p99": float(np.percentile(v, 99)), "n": len(v)}
                       for name, v in sorted(stats.latencies.items())},
        "statuses": dict(sorted(stats.statuses.items())), "retries": stats.retries,
        "connection_errors": stats.connection_errors, "events": events, "check": check,
    }


def format_report(report: dict[str, Any]) -> str:
    lines = [f"{report['participants']} participants, {report['database']}, {report['workers']} workers, "
             f"{report['concurrency']} at a time, think time {report['pause_ms']:.0f} ms, "
             f"arrivals over {report['ramp_s']:.0f} s: {report['seconds']:.1f} s, "
             f"{report['votes_per_s']:.0f} votes/s"]
    for name, q in report["latency_ms"].items():
        lines.append(f"  {name:13} p50 {q['p50']:7.1f} ms  p95 {q['p95']:7.1f} ms  p99 {q['p99']:7.1f} ms  "
                     f"({q['n']} answers)")
    lines.append("  statuses: " + ", ".join(f"{k}: {v}" for k, v in report["statuses"].items()))
    lines.append(f"  retries {report['retries']}, connection errors {report['connection_errors']}")
    for event in report["events"]:
        lines.append(f"  event: {event}")
    c = report["check"]
    lines.append(f"  check: {c['acknowledged']} acknowledged, {c['stored']} stored, {c['lost']} lost, "
                 f"{c['duplicated']} duplicated, {c['stored_without_acknowledgement']} stored without acknowledgement")
    return "\n".join(lines)


def main(a: argparse.Namespace) -> int:
    """``animstudy loadtest`` with its parsed options (``server.cli.loadtest_parser``)."""
    report = run(a.database, a.participants, a.workers, a.concurrency, time_limit=a.time_limit,
                 pause_ms=a.pause_ms, ramp_s=a.ramp_s, crash_at=a.crash_at, outage_at=a.outage_at, outage_s=a.outage_s,
                 pg_url=a.pg_url or DEFAULT_PG)
    print(format_report(report))
    if a.json:
        a.json.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    ok = report["check"]["lost"] == 0 and report["check"]["duplicated"] == 0 and \
        report["check"]["stored_without_acknowledgement"] == 0
    return 0 if ok else 1
