"""``animstudy serve`` and ``animstudy researcher create``: the server and its accounts."""

from __future__ import annotations

import argparse
import getpass
import secrets
import sys

import uvicorn
from sqlalchemy import select

from anim_core.clips.build import ConfigError
from server.assets import AssetError
from server.config import Settings
from server.db import make_engine, migrate, session_factory
from server.errors import MediaError, ServiceError
from server.jobs.control import resume_lost_jobs
from server.jobs.models import BuildState
from server.pipeline.jobs import prepare_default
from server.researchers.models import Researcher
from server.researchers.service import create_researcher

from .common import fail


def ensure_researcher(settings: Settings, session_factory: object) -> None:
    """The first researcher account: from ANIMSTUDY_ADMIN_EMAIL/PASSWORD, or made up and printed once."""



    with session_factory() as session:  # type: ignore[operator]
        if session.scalar(select(Researcher.id).limit(1)) is not None:
            return
        email = settings.admin_email or "admin@localhost"
        password = settings.admin_password or secrets.token_urlsafe(12)
        create_researcher(session, email, password, admin=True)  # manages every study, the default one too
        shown = password if not settings.admin_password else "(from ANIMSTUDY_ADMIN_PASSWORD)"
        print(f"researcher account created (admin): e-mail {email}, password {shown}", flush=True)


def serve(settings: Settings, host: str, port: int, workers: int) -> int:
    """Migrate, prepare the default study if there is none, and serve."""


    engine = make_engine(settings.sqlalchemy_url)
    try:
        migrate(engine, media_dir=settings.media_dir, clips_dir=settings.clips_dir)
        factory = session_factory(engine)
        # The default study is a job like any other, so a server stopped while rendering it goes on where it was.
        job = prepare_default(settings, factory)
        if job is not None and job.state != BuildState.done:
            return fail(f"{job.error} (job {job.id})")
        ensure_researcher(settings, factory)
        with factory() as session:  # jobs whose process ended mid-job (this server's, a command's) go on
            for job in resume_lost_jobs(session, settings, engine):
                print(f"resumed {job.kind} job {job.id} (pid {job.pid}): it renders what is still missing",
                      flush=True)
    except (AssetError, ConfigError, MediaError, ServiceError) as exc:
        return fail(str(exc))
    finally:
        engine.dispose()
    print(f"serving on http://{host}:{port} (database {engine.url.render_as_string(hide_password=True)})",
          flush=True)
    # The app reads X-Forwarded-For itself, from ANIMSTUDY_TRUSTED_PROXIES only (server.deps.client_address);
    # uvicorn would otherwise trust it from 127.0.0.1 by default.
    uvicorn.run("server.app:app_from_env", factory=True, host=host, port=port, workers=workers,
                log_level="info", proxy_headers=False)
    return 0


def read_password(given: str | None, from_stdin: bool) -> str | None:
    """The new account's password: ``--password`` (with a warning: every user of the machine sees a command's
    arguments), the first line of standard input (``--password-stdin``), or typed twice at a prompt that does not
    echo it (a terminal only).  None if there is none."""

    if given is not None:
        print("warning: --password shows the password to every user of this machine (process list, shell "
              "history); use the prompt or --password-stdin", file=sys.stderr)
        return given
    if from_stdin:
        line = sys.stdin.readline().rstrip("\r\n")
        return line or None
    if not sys.stdin.isatty():
        return None
    first = getpass.getpass("password: ")
    if first != getpass.getpass("password again: "):
        print("the two passwords differ", file=sys.stderr)
        return None
    return first or None


def researcher_create(settings: Settings, email: str, password: str, admin: bool = False) -> int:

    engine = make_engine(settings.sqlalchemy_url)
    migrate(engine, media_dir=settings.media_dir, clips_dir=settings.clips_dir)
    try:
        with session_factory(engine)() as session:
            researcher = create_researcher(session, email, password, admin=admin)
    except ServiceError as exc:
        return fail(exc.detail)
    print(f"researcher {researcher.email} created{' (admin: sees and manages every study)' if admin else ''}")
    return 0


def run(settings: Settings, args: argparse.Namespace) -> int:
    """``animstudy serve`` and ``animstudy researcher create``."""
    if args.command == "serve":
        return serve(settings, args.host, args.port, max(1, args.workers))
    password = read_password(args.password, args.password_stdin)
    if password is None:
        return fail("no password: give it at the prompt, or on standard input with --password-stdin")
    return researcher_create(settings, args.email, password, args.admin)
