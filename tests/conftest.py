"""Shared fixtures: the real data directory and seeded random generators."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
pytest_plugins = ["tests.server_fixtures"]

# --- parallel runs (pytest-xdist, `make test`) -----------------------------------------------------------------
# Each xdist worker (PYTEST_XDIST_WORKER = gw0, gw1, ...) gets its own of everything a test may share:
# - its PostgreSQL test database: TEST_DATABASE_URL is pointed at ``<database>_<worker>`` (created at session start,
#   dropped at the end with every ``<database>_<worker>_*`` database that :func:`own_database` derived from it), so
#   the schema drops, migrations and commits of one worker never meet another's;
# - its var directory: ANIMSTUDY_VAR_DIR defaults to a directory of the worker's own (tests that need one set their
#   own anyway; this catches a command run without one, which would otherwise write ./var of the checkout);
# - its temporary directories (pytest's basetemp is per worker under xdist), hence its SQLite files, its Dask
#   scheduler's directory (LocalCluster and tests/test_cluster.py take free ports and temp dirs) and rendered media.
# Ports are always taken free from the kernel (port 0), so they need nothing.  Numba's on-disk cache
# (anim_core/**/__pycache__) stays shared: numba writes it atomically (a temp file renamed), and a per-worker cache
# would only compile every kernel twice.  Tests that cannot share the machine (PostgreSQL stopped for everyone) are
# marked ``serial`` and run by `make test` in a step of their own after the parallel one.
WORKER = os.environ.get("PYTEST_XDIST_WORKER")


def _worker_database_url(url: str, worker: str) -> str:
    from sqlalchemy import make_url

    base = make_url(url)
    return base.set(database=f"{base.database}_{worker}").render_as_string(hide_password=False)


if WORKER and os.environ.get("TEST_DATABASE_URL"):  # before any test module reads it (tests/test_faults.py does)
    os.environ.setdefault("TEST_BASE_DATABASE_URL", os.environ["TEST_DATABASE_URL"])
    os.environ["TEST_DATABASE_URL"] = _worker_database_url(os.environ["TEST_BASE_DATABASE_URL"], WORKER)


@contextmanager
def _admin_connection():
    """An AUTOCOMMIT connection to the PostgreSQL server's maintenance database (to create and drop databases: the
    workers' and the tests' own), closed with its engine."""
    from sqlalchemy import make_url

    from server.config import normalize_database_url
    from server.db import make_engine

    base = os.environ.get("TEST_BASE_DATABASE_URL") or os.environ["TEST_DATABASE_URL"]
    url = make_url(normalize_database_url(base)).set(database="postgres")
    admin = make_engine(url.render_as_string(hide_password=False)).execution_options(isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as conn:
            yield conn
    finally:
        admin.dispose()


def _worker_databases(conn, name: str) -> list[str]:
    from sqlalchemy import text

    pattern = name.replace("\\", "\\\\").replace("_", "\\_").replace("%", "\\%") + "\\_%"
    return list(conn.scalars(text("SELECT datname FROM pg_database WHERE datname = :n OR datname LIKE :p"),
                             {"n": name, "p": pattern}))


def pytest_sessionstart(session):
    if WORKER and "ANIMSTUDY_VAR_DIR" not in os.environ:
        os.environ["ANIMSTUDY_VAR_DIR"] = tempfile.mkdtemp(prefix=f"animstudy-var-{WORKER}-")
        session.config.add_cleanup(lambda: shutil.rmtree(os.environ.pop("ANIMSTUDY_VAR_DIR"), ignore_errors=True))
    if not (WORKER and os.environ.get("TEST_BASE_DATABASE_URL")):
        return
    from sqlalchemy import make_url, text

    name = make_url(os.environ["TEST_DATABASE_URL"]).database
    with _admin_connection() as conn:
        for stale in _worker_databases(conn, name):  # left by an interrupted run
            conn.execute(text(f'DROP DATABASE IF EXISTS "{stale}" WITH (FORCE)'))
        conn.execute(text(f'CREATE DATABASE "{name}"'))


def pytest_sessionfinish(session, exitstatus):
    if not (WORKER and os.environ.get("TEST_BASE_DATABASE_URL")):
        return
    from sqlalchemy import make_url, text

    name = make_url(os.environ["TEST_DATABASE_URL"]).database
    with _admin_connection() as conn:
        for database in _worker_databases(conn, name):
            conn.execute(text(f'DROP DATABASE IF EXISTS "{database}" WITH (FORCE)'))


def pytest_collection_modifyitems(session, config, items):
    """Whole files, those with the most tests marked ``slow`` first, then those with the most tests (the order
    within a file kept): `make test` hands files to its workers in this order (``--no-loadscope-reorder``), so the
    long files start first and the run ends on short ones, with both workers busy to the end."""
    files: dict[Path, list] = {}
    for item in items:
        files.setdefault(item.path, []).append(item)

    def weight(path: Path) -> tuple[int, int]:
        return -sum(1 for item in files[path] if item.get_closest_marker("slow")), -len(files[path])

    items[:] = [item for path in sorted(files, key=weight) for item in files[path]]
    # `make test` runs the tests marked serial from the files that say "mark.serial" only (a shorter collection):
    # a serial test marked some other way would be run by neither step.
    hidden = sorted({str(path.name) for path, found in files.items()
                     if any(item.get_closest_marker("serial") for item in found)
                     and "mark.serial" not in path.read_text(encoding="utf-8")})
    if hidden:
        raise pytest.UsageError(f"tests marked serial in {', '.join(hidden)}, whose text does not say mark.serial: "
                                "write @pytest.mark.serial (or pytestmark = pytest.mark.serial) there")


def data_dir() -> Path:
    """``ANIMSTUDY_DATA_DIR`` or the sample data shipped in the repository (``data/``)."""
    path = Path(os.environ.get("ANIMSTUDY_DATA_DIR", REPO / "data"))
    if not (path / "mocap").is_dir():
        pytest.fail(f"motion-capture data not found in {path}: set ANIMSTUDY_DATA_DIR (see docs/reference/data.md)")
    return path


@pytest.fixture(scope="session")
def data() -> Path:
    return data_dir()


@pytest.fixture(scope="session", autouse=True)
def cheap_password_hashes():
    """Researcher passwords hashed at argon2's cheapest parameters in the test process: each account and login
    of a test otherwise costs ~0.1-0.15 s of both cores (64 MiB, 4 lanes), over 100 s a suite.  Same code path,
    the parameters are stored in each hash; tests/test_security.py checks the production ones in a process of its
    own, and subprocess servers keep them."""
    from argon2 import PasswordHasher, profiles

    from server.researchers import service

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(service, "_hasher", PasswordHasher.from_parameters(profiles.CHEAPEST))
        yield


@pytest.fixture
def production_password_hashes(monkeypatch):
    """The production argon2 parameters back, for a test whose race needs the check to take its real time.  With
    the login route changed to count failures after the check instead of before (the race the throttle closes),
    tests/test_hostile_round3.py's two concurrency tests failed in 8 of 12 runs with the cheapest hash and in 10 of
    12 with this one (2026-12-05, both databases, three rounds each)."""
    from argon2 import PasswordHasher

    from server.researchers import service

    monkeypatch.setattr(service, "_hasher", PasswordHasher.from_parameters(service.PASSWORD_PROFILE))


@pytest.fixture(scope="session")
def bvh_paths(data: Path) -> list[Path]:
    paths = sorted(data.glob("mocap/**/*.bvh*"))
    assert paths, f"no BVH files under {data / 'mocap'}"
    return paths


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20170601)


# --- databases -------------------------------------------------------------------------------------------------
# Every database test runs on SQLite and, when TEST_DATABASE_URL is set (CI sets it), on PostgreSQL too.

DATABASES = ["sqlite"] + (["postgresql"] if os.environ.get("TEST_DATABASE_URL") else [])


def own_database(url, database: str) -> str:
    """The name of the extra PostgreSQL database ``database`` for the test database of ``url``: named after it
    (``test`` + ``test_animstudy_live`` -> ``test_animstudy_live``, ``test_b`` -> ``test_b_animstudy_live``), so
    that two runs against two test databases on one server never share one."""
    return f"{url.database}_{database.removeprefix('test_')}"


def _fresh_engine(kind: str, tmp_path_factory: pytest.TempPathFactory, database: str | None = None):
    """An empty database: a new SQLite file, or the PostgreSQL test database (or ``database`` on the same
    server, created if needed; see :func:`own_database`) with its schema dropped."""
    from sqlalchemy import make_url, text

    from server.config import normalize_database_url
    from server.db import make_engine

    if kind == "sqlite":
        return make_engine(f"sqlite:///{tmp_path_factory.mktemp('db') / 'test.db'}")
    url = make_url(normalize_database_url(os.environ["TEST_DATABASE_URL"]))
    if database:
        database = own_database(url, database)
        with _admin_connection() as conn:
            if not conn.scalar(text("SELECT 1 FROM pg_database WHERE datname = :n"), {"n": database}):
                conn.execute(text(f'CREATE DATABASE "{database}"'))
        url = url.set(database=database)
    engine = make_engine(url.render_as_string(hide_password=False))
    with engine.begin() as conn:  # the test database belongs to the tests: start from nothing
        conn.execute(text("DROP SCHEMA public CASCADE"))
        conn.execute(text("CREATE SCHEMA public"))
    return engine


@pytest.fixture(scope="session")
def migrated_copy(tmp_path_factory):
    """``make(kind, database)``: a new database at the head revision, as ``migrate`` leaves an empty one, for a
    fixture that needs one per test: a copy of one the worker migrated once (SQLite: the file; PostgreSQL:
    ``CREATE DATABASE ... TEMPLATE``, ``database`` named as in :func:`_fresh_engine`).  A migration of an empty
    database takes 0.3-1 s."""
    from sqlalchemy import make_url, text

    from server.config import normalize_database_url
    from server.db import make_engine, migrate

    templates: dict[str, str] = {}

    def make(kind: str, database: str):
        if kind not in templates:
            template = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_template")
            migrate(template)
            templates[kind] = template.url.database
            template.dispose()  # no connection may stay open to a PostgreSQL template; SQLite folds in its WAL
        if kind == "sqlite":
            path = tmp_path_factory.mktemp("db") / "test.db"
            shutil.copyfile(templates[kind], path)
            return make_engine(f"sqlite:///{path}")
        url = make_url(normalize_database_url(os.environ["TEST_DATABASE_URL"]))
        name = own_database(url, database)
        with _admin_connection() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
            conn.execute(text(f'CREATE DATABASE "{name}" TEMPLATE "{templates[kind]}"'))
        return make_engine(url.set(database=name).render_as_string(hide_password=False))

    return make


@pytest.fixture(scope="session")
def _shared_engines(tmp_path_factory):
    """``get(kind)``: the run's one migrated database of that kind, made at its first use and kept to the end.

    Not the parametrized ``engine`` itself: pytest keeps one instance of a parametrized session fixture at a time,
    and with the tests in file order (:func:`pytest_collection_modifyitems`) the kinds alternate file by file, so
    each switch dropped and migrated a database anew (about 60 migrations in a run of three workers, 22 s sampled)."""
    from server.db import migrate

    made: dict = {}

    def get(kind: str):
        if kind not in made:
            made[kind] = _fresh_engine(kind, tmp_path_factory)
            migrate(made[kind])
        return made[kind]

    yield get
    for eng in made.values():
        eng.dispose()


@pytest.fixture(scope="session", params=DATABASES)
def engine(request, _shared_engines):
    """A migrated database of each kind, shared by the tests (each test rolls back what it did)."""
    return _shared_engines(request.param)


@pytest.fixture
def db(engine):
    """A session whose work is rolled back after the test (commits become savepoints)."""
    from sqlalchemy.orm import Session

    connection = engine.connect()
    transaction = connection.begin()
    session = Session(bind=connection, join_transaction_mode="create_savepoint", expire_on_commit=False)
    yield session
    session.close()
    transaction.rollback()
    connection.close()


@pytest.fixture(scope="session")
def character(data: Path):
    """The MakeHuman character of the data directory (a module may define its own ``character``)."""
    from server.assets import character as load_character

    return load_character(data)


@pytest.fixture(scope="session")
def cmu_walk(data: Path):
    """Two seconds of the CMU walk 02_01 after its T-pose frame (two steps): the motion the wild-rig tests re-express
    on other rigs."""
    import dataclasses

    from anim_core.io.bvh import read_bvh

    bvh = read_bvh(data / "mocap" / "cmu" / "02_01_walk.bvh.gz")
    return dataclasses.replace(bvh, motion=bvh.motion[1:241])


CONDITIONS16 = REPO / "server" / "clipset" / "conditions16.toml"


def once_per_run(directory: Path, name: str, make: Callable[[Path], None]) -> Path:
    """``directory / name``, made by ``make(path)`` by the first test of the run to ask: under a file lock, so a
    second worker waits instead of making it too, and into a temporary name renamed when complete, so an
    interrupted ``make`` leaves nothing that looks done.  Callers copy or read it, never change it."""
    import fcntl

    path = directory / name
    with open(directory / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not path.exists():
            partial = directory / f"{name}.partial"
            if partial.is_dir():
                shutil.rmtree(partial)
            else:
                partial.unlink(missing_ok=True)
            make(partial)
            partial.replace(path)
    return path


@pytest.fixture(scope="session")
def run_directory(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where a run keeps what it builds once for all its tests (:func:`once_per_run`): `make test` names one
    directory for both of its steps (``ANIMSTUDY_TEST_RUN_DIR``, removed at the end), so the serial step reuses the
    parallel step's work; otherwise the temporary directory the run's workers share."""
    if os.environ.get("ANIMSTUDY_TEST_RUN_DIR"):
        return Path(os.environ["ANIMSTUDY_TEST_RUN_DIR"])
    return tmp_path_factory.getbasetemp().parent if WORKER else tmp_path_factory.getbasetemp()


@pytest.fixture(scope="session")
def built_clip_set(data: Path, run_directory: Path):
    """``build(config=None)``: a copy of ``build_clip_set(data, load_config(config))`` (``config`` a clip-set
    file of the repository: the default set, or :data:`CONDITIONS16`), built once per run and shared.

    The first worker to ask builds it (:func:`once_per_run`) and pickles it into the run's directory; every call
    unpickles a copy of its own, so a test that changes its clips changes no other test's.  Keyed by the data
    directory and the file's bytes; a run never changes either."""
    import hashlib
    import pickle

    def build(config: Path | None = None) -> list:
        from server.clipset.build import build_clip_set
        from server.clipset.config import load_config

        text = config.read_bytes() if config is not None else b"<the default clip set>"
        key = hashlib.sha256(str(data).encode() + b"\0" + text).hexdigest()[:16]

        def make(path: Path) -> None:
            clips = build_clip_set(data, load_config(config) if config is not None else None)
            path.write_bytes(pickle.dumps(clips, protocol=pickle.HIGHEST_PROTOCOL))

        return pickle.loads(once_per_run(run_directory, f"clip-set-{key}.pickle", make).read_bytes())

    return build


# The browser tests' Chromium, in one place: Debian's (never a downloaded browser), headless, no network chatter of
# its own so a test's requests are the page's only.
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


# Module scope, not session: while a sync Playwright is open its event loop counts as running in this thread
# (playwright/_impl/_greenlets.py sets it after every call), so asyncio.run() in a later non-browser test of the
# worker would fail.
@pytest.fixture(scope="module")
def playwright():
    from playwright.sync_api import sync_playwright  # only the browser tests need it

    with sync_playwright() as p:
        yield p


# A participant answers after watching a stimulus loop once, counted on the media clock (static/participant.js,
# measure): at FAST_PLAYBACK times the speed a test's participant waits a fraction of each loop's real time, the
# gate unchanged.  Tests that measure playback itself (hitches, stalls) are marked ``real_speed``.
FAST_PLAYBACK = 8
_FAST_PLAYBACK_JS = f"document.addEventListener('play', e => {{ e.target.playbackRate = {FAST_PLAYBACK}; }}, true);"


class FastPlaybackBrowser:
    """The shared Chromium whose new contexts and pages play every video at :data:`FAST_PLAYBACK` times its speed;
    everything else is the browser's own (``real`` is the browser itself)."""

    def __init__(self, real) -> None:
        self.real = real

    def new_context(self, **options):
        context = self.real.new_context(**options)
        context.add_init_script(_FAST_PLAYBACK_JS)
        return context

    def new_page(self, **options):
        return self.new_context(**options).new_page()

    def __getattr__(self, name: str):
        return getattr(self.real, name)


@pytest.fixture(scope="module")
def browser(playwright):
    # One launch per file (a launch costs one to three seconds), a fresh context per test; tests never close it
    # (:func:`own_contexts` closes what they opened).
    b = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
    yield FastPlaybackBrowser(b)
    b.close()


@contextmanager
def own_contexts(browser):
    """Close, on leaving, every browser context opened inside (``browser.new_page`` opens one too): a test's pages,
    cookies and storage are its own, as with a browser of its own, on the shared :func:`browser`."""
    before = set(browser.contexts)
    try:
        yield browser
    finally:
        for context in browser.contexts:
            if context not in before:
                context.close()


@pytest.fixture
def page(browser, request):
    """A 1280x720 page in a context of its own, its videos at :data:`FAST_PLAYBACK` times their speed unless the
    test is marked ``real_speed``; a JavaScript error on it fails the test."""
    real = request.node.get_closest_marker("real_speed") is not None
    context = (browser.real if real else browser).new_context(viewport={"width": 1280, "height": 720})
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    yield pg
    context.close()
    assert not errors, errors
