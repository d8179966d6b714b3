"""Shared fixtures: the real data directory and seeded random generators."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
pytest_plugins = ["tests.server_fixtures"]


def data_dir() -> Path:
    """``ANIMSTUDY_DATA_DIR`` or the sample data shipped in the repository (``data/``)."""
    path = Path(os.environ.get("ANIMSTUDY_DATA_DIR", REPO / "data"))
    if not (path / "mocap").is_dir():
        pytest.fail(f"motion-capture data not found in {path}: set ANIMSTUDY_DATA_DIR (see docs/reference/data.md)")
    return path


@pytest.fixture(scope="session")
def data() -> Path:
    return data_dir()


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
        admin = make_engine(url.render_as_string(hide_password=False)).execution_options(
            isolation_level="AUTOCOMMIT")
        with admin.connect() as conn:
            if not conn.scalar(text("SELECT 1 FROM pg_database WHERE datname = :n"), {"n": database}):
                conn.execute(text(f'CREATE DATABASE "{database}"'))
        admin.dispose()
        url = url.set(database=database)
    engine = make_engine(url.render_as_string(hide_password=False))
    with engine.begin() as conn:  # the test database belongs to the tests: start from nothing
        conn.execute(text("DROP SCHEMA public CASCADE"))
        conn.execute(text("CREATE SCHEMA public"))
    return engine


@pytest.fixture(scope="session", params=DATABASES)
def engine(request, tmp_path_factory):
    """A migrated database of each kind, shared by the tests (each test rolls back what it did)."""
    from server.db import migrate

    eng = _fresh_engine(request.param, tmp_path_factory)
    migrate(eng)
    yield eng
    eng.dispose()


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
