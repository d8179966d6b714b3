"""Helpers for API tests: an app on the rolled-back test session, a study over fake media, a researcher."""

from __future__ import annotations

import dataclasses
import hashlib
import random
import socket
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from server.app import create_app
from server.clipset.config import ClipSetConfig, load_config
from server.config import Settings
from server.deps import get_session
from server.media.manifest import RenderedClip, RenderedPair, RenderManifest
from server.participants import service as participant_service
from server.researchers.service import create_researcher
from server.studies.design import Design
from server.studies.models import Study, StudyState
from server.studies.service import create_study, set_state
from server.studies.studyfile import StudyFile, thesis_study

ANIMATIONS = ("walk", "run", "crouch", "idle")
CONDITIONS = ("keyframe", "hybrid0", "hybrid1", "hybrid2")
RESEARCHER = ("lead@example.org", "correct horse battery")


@contextmanager
def seeded_sessions(rng: random.Random, given: Sequence[int] = ()) -> Iterator[None]:
    """New participant sessions' seeds (``secrets.randbits`` in the participants' service: a session's trial order,
    sides and adaptive pairs) from ``rng``, after the ``given`` ones in order: a simulated study's votes, and what
    they add up to, are the same every run."""
    pending = list(given)

    def randbits(bits: int) -> int:
        return pending.pop(0) if pending else rng.getrandbits(bits)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(participant_service.secrets, "randbits", randbits)
        yield


def small_clip_config() -> ClipSetConfig:
    """The built-in clip set cut to two animations (run, idle) and two conditions: quick to build and render."""
    config = load_config()
    return dataclasses.replace(config, animations={k: config.animations[k] for k in ("run", "idle")},
                               conditions=config.conditions[:2])


def fake_name(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def fake_media(design: Design | None = None) -> RenderManifest:
    """A render manifest with opaque names for every clip and every pair a design can need."""
    clips = {}
    for a in ANIMATIONS:
        for m in CONDITIONS:
            cid = f"{a}-{m}"
            clips[cid] = RenderedClip(clip=cid, animation=a, condition=m, video=f"{fake_name(cid)}.mp4",
                                      poster=f"{fake_name(cid)}.jpg", frames=40, fps=30, width=640, height=480)
    pairs = []
    for left, lc in clips.items():
        for right, rc in clips.items():
            if lc.animation == rc.animation:
                name = fake_name(f"{left}|{right}")
                pairs.append(RenderedPair(left=left, right=right, video=f"{name}.mp4", poster=f"{name}.jpg",
                                          frames=40, fps=30, width=1284, height=480))
    return RenderManifest(clips=clips, pairs=pairs)


def write_fake_media(media_dir: Path, media: RenderManifest | None = None) -> RenderManifest:
    """Write ``media`` (default :func:`fake_media`) as the render manifest of ``media_dir`` with a small stand-in
    file for each of its videos and posters (bytes: the name), so that stimulus sets over it are complete."""
    media = media or fake_media()
    media_dir.mkdir(parents=True, exist_ok=True)
    for v in [*media.clips.values(), *media.pairs]:
        for name in (v.video, v.poster):
            (media_dir / name).write_bytes(f"stand-in for {name}\n".encode())
    (media_dir / "manifest.json").write_text(media.model_dump_json())
    return media


def study_file(design: Design | None = None, slug: str = "thesis", **sections: object) -> StudyFile:
    """studies/thesis.toml with another design, slug or sections (given as dicts or models)."""
    base = thesis_study().model_dump()
    base.update(slug=slug, **{k: v.model_dump() if hasattr(v, "model_dump") else v for k, v in sections.items()})
    if design is not None:
        base["design"] = design.model_dump()
    return StudyFile.model_validate(base)


def make_study(db: Session, design: Design | None = None, slug: str = "thesis", state: StudyState = StudyState.open,
               owner: object = None, media_dir: Path | None = None, clips_dir: Path | None = None,
               **sections: object) -> Study:
    """A study over :func:`fake_media` (its stimulus set hashes the stand-in files of ``media_dir`` and takes the
    clips' metrics from the clip set in ``clips_dir``, if given)."""
    study = create_study(db, fake_media(design), study_file(design, slug, **sections), owner=owner,  # type: ignore[arg-type]
                         media_dir=media_dir, clips_dir=clips_dir)
    return set_state(db, study, state)


def make_client(db: Session, engine: object, tmp_path: Path) -> Iterator[TestClient]:
    settings = Settings(var_dir=tmp_path / "var", secret_key="test-secret-0123456789abcdef0123456789")
    app = create_app(settings, engine, run_migrations=False)
    app.dependency_overrides[get_session] = lambda: db
    with TestClient(app) as client:
        yield client


@pytest.fixture
def client(db, engine, tmp_path):
    yield from make_client(db, engine, tmp_path)


@pytest.fixture
def study(db, tmp_path):
    """The thesis study, open, over stand-in files in the media directory of :func:`client`'s settings."""
    media_dir = tmp_path / "var" / "media"
    write_fake_media(media_dir)
    return make_study(db, media_dir=media_dir)


@pytest.fixture
def researcher_headers(db, client):
    create_researcher(db, *RESEARCHER, admin=True)
    r = client.post("/api/v1/auth/token", data={"username": RESEARCHER[0], "password": RESEARCHER[1]})
    assert r.status_code == 200, r.text
    return {"Authorization": f"Bearer {r.json()['access_token']}"}


def start(client: TestClient, slug: str = "thesis", **external: str) -> tuple[str, dict]:
    r = client.post(f"/api/v1/studies/{slug}/sessions", json={"consent": True, "external": external or None})
    assert r.status_code == 201, r.text
    body = r.json()
    return body["session_id"], {"Authorization": f"Bearer {body['token']}"}


def vote(client: TestClient, sid: str, headers: dict, trial_id: int, choice: str = "equal", key: str | None = None,
         rt_ms: int = 1500, **extra: object):
    body = {"choice": choice, "rt_ms": rt_ms, "idempotency_key": key or f"k{trial_id}", **extra}
    return client.post(f"/api/v1/sessions/{sid}/trials/{trial_id}/vote", json=body, headers=headers)


def answer_all(client: TestClient, sid: str, headers: dict, choice: str = "equal") -> list[dict]:
    trials = []
    while (r := client.get(f"/api/v1/sessions/{sid}/next", headers=headers)).status_code == 200:
        trials.append(r.json())
        assert vote(client, sid, headers, r.json()["trial_id"], choice).status_code == 201
    assert r.status_code == 204
    return trials


@contextmanager
def live_server(app: FastAPI) -> Iterator[str]:
    """Serve ``app`` on a free loopback port in a thread; yields the base URL."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.02)
    assert server.started, "server did not start"
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=10)
