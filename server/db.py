"""Database engine, sessions and migrations (SQLAlchemy 2, Alembic)."""

from __future__ import annotations

import fcntl
import os
import sqlite3
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from alembic import command
from alembic.config import Config
from sqlalchemy import Connection, DateTime, Dialect, Engine, MetaData, create_engine, event
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker
from sqlalchemy.types import TypeDecorator

from .config import REPO_ROOT

MIGRATIONS_DIR = REPO_ROOT / "migrations"
SQLITE_BEGIN = "sqlite_begin"  # execution option: "DEFERRED" for read-only transactions on SQLite
SQLITE_TIMEOUT_S = 30.0  # how long a writer waits for its turn before the request answers 503

# Named constraints, so migrations can refer to them on every database (SQLite batch mode needs names).
NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC datetimes on every database (SQLite would return them naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is not None and value.tzinfo is None:
            raise ValueError("naive datetimes are not stored; use server.db.utcnow()")
        return None if value is None else value.astimezone(UTC)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=UTC)
        return value


class WriterQueue:
    """The writers of one SQLite file, one at a time across threads and processes.

    SQLite admits one writer; the others retry in its busy handler, which sleeps 1, 2, 5, 10 ... 100 ms between
    tries.  Under load that gave votes seconds of latency while the file was free most of the time.  Here a
    writer waits on a thread lock (woken at once when it is released) and then, across worker processes, for an
    advisory file lock (``flock``, tried every 0.2 to 2 ms by the one waiting thread of each process; the kernel
    drops it when a process dies, even by SIGKILL), then begins.
    """

    def __init__(self, path: Path, timeout_s: float) -> None:
        self.path = path
        self.timeout_s = timeout_s
        self._threads = threading.Lock()
        self._fd: int | None = None
        self._pid: int | None = None
        self._owner: int | None = None  # the thread in its turn

    def enter(self) -> None:
        if self._owner == threading.get_ident():
            # Another transaction of this thread (an event loop serving two requests) holds the turn: waiting
            # would wait for ourselves.  Refuse at once (the request answers 503 and is retried).
            raise sqlite3.OperationalError("database is locked")
        if not self._threads.acquire(timeout=self.timeout_s):
            raise sqlite3.OperationalError("database is locked")
        self._owner = threading.get_ident()
        try:
            if self._pid != os.getpid():  # a forked child must not share the parent's lock
                self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
                self._pid = os.getpid()
            deadline = time.monotonic() + self.timeout_s
            pause = 0.0002
            while True:
                try:
                    fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    return
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        raise sqlite3.OperationalError("database is locked") from None
                    time.sleep(pause)  # one thread per process waits here; the other process commits in ~1 ms
                    pause = min(pause * 2, 0.002)
        except BaseException:
            self._owner = None
            self._threads.release()
            raise

    def leave(self) -> None:
        fcntl.flock(self._fd, fcntl.LOCK_UN)  # type: ignore[arg-type]
        self._owner = None
        self._threads.release()


class _QueuedConnection(sqlite3.Connection):
    """A pysqlite connection that leaves its :class:`WriterQueue` when its transaction ends, however it ends."""

    writers: WriterQueue | None = None
    writing = False

    def enter_writers(self) -> None:
        if self.writers is not None and not self.writing:
            self.writers.enter()
            self.writing = True

    def leave_writers(self) -> None:
        if self.writing:
            self.writing = False
            self.writers.leave()  # type: ignore[union-attr]

    def commit(self) -> None:
        try:
            super().commit()
        finally:
            self.leave_writers()

    def rollback(self) -> None:
        try:
            super().rollback()
        finally:
            self.leave_writers()

    def close(self) -> None:
        try:
            super().close()
        finally:
            self.leave_writers()


def make_engine(url: str, sqlite_timeout_s: float = SQLITE_TIMEOUT_S) -> Engine:
    """An engine for ``url``; SQLite gets foreign keys, WAL, queued writers and a timeout (several uvicorn workers
    share the file)."""
    if url.startswith("sqlite"):
        path = url.split("///", 1)[-1]
        writers = None
        if path and path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            writers = WriterQueue(Path(f"{path}.writers"), sqlite_timeout_s)
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": sqlite_timeout_s,
                                                  "factory": _QueuedConnection})

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection: _QueuedConnection, _record: object) -> None:
            # pysqlite's own transaction handling breaks SAVEPOINT; let SQLAlchemy emit BEGIN itself.
            dbapi_connection.isolation_level = None
            dbapi_connection.writers = writers
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute("PRAGMA journal_mode=WAL")
            # In WAL mode NORMAL still survives a crash of the process (kill -9); it skips the fsync per commit.
            cursor.execute("PRAGMA synchronous=NORMAL")
            cursor.close()

        @event.listens_for(engine, "begin")
        def _sqlite_begin(connection: Connection) -> None:
            # IMMEDIATE: take the write lock up front.  A deferred transaction that reads and then writes fails
            # at once ("database is locked") when another writer got in between; this one waits its turn, in
            # the WriterQueue.  Read-only work (GET requests) asks for DEFERRED and, with WAL, runs beside the
            # writers.
            mode = connection.get_execution_options().get(SQLITE_BEGIN, "IMMEDIATE")
            dbapi_connection = connection.connection.dbapi_connection
            if mode == "IMMEDIATE":
                try:
                    dbapi_connection.enter_writers()  # type: ignore[union-attr]
                except sqlite3.OperationalError as e:  # as SQLAlchemy reports SQLite's own "database is locked"
                    raise OperationalError(f"BEGIN {mode}", None, e) from e
            try:
                connection.exec_driver_sql(f"BEGIN {mode}")
            except BaseException:
                dbapi_connection.leave_writers()  # type: ignore[union-attr]
                raise

        return engine
    # No pre-ping: it is a round trip on every request.  A connection that died with the server fails its first
    # statement instead; SQLAlchemy then drops the whole pool, the request answers 503 and the client retries.
    # The participant endpoints wait for the database on the event loop: never for long.
    return create_engine(url, connect_args={"connect_timeout": 5})


def read_only(engine: Engine) -> Engine:
    """The engine for requests that only read: on SQLite a deferred transaction (runs beside the writers, WAL),
    on PostgreSQL autocommit (no BEGIN and ROLLBACK round trips around the one or two SELECTs of a request)."""
    if engine.dialect.name == "sqlite":
        return engine.execution_options(**{SQLITE_BEGIN: "DEFERRED"})
    return engine.execution_options(isolation_level="AUTOCOMMIT")


def session_factory(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(bind=engine, expire_on_commit=False)


def alembic_config(url: str | None = None) -> Config:
    cfg = Config(str(MIGRATIONS_DIR / "alembic.ini"))
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    if url:
        cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return cfg


def _alembic(engine: Engine, run: Callable[[Config], None], **attributes: object) -> None:
    """Run an Alembic command on one connection in one transaction.

    On SQLite foreign keys are off meanwhile (as SQLite's own procedure for schema changes says): batch mode
    recreates a table to change it, and dropping the old copy with foreign keys on would cascade-delete the
    rows that refer to it (dropping ``trials`` would delete every vote).  The keys are checked before the commit.
    """
    with engine.connect() as connection:
        sqlite_db = engine.dialect.name == "sqlite"
        if sqlite_db:  # outside any transaction, or SQLite ignores it
            connection.connection.dbapi_connection.execute("PRAGMA foreign_keys=OFF")  # type: ignore[union-attr]
        try:
            with connection.begin():
                cfg = alembic_config()
                cfg.attributes["connection"] = connection
                cfg.attributes.update(attributes)
                run(cfg)
                if sqlite_db:
                    broken = connection.exec_driver_sql("PRAGMA foreign_key_check").all()
                    if broken:
                        raise RuntimeError(f"the migration left rows without their parents: {broken[:5]}")
        finally:
            if sqlite_db:
                connection.connection.dbapi_connection.execute("PRAGMA foreign_keys=ON")  # type: ignore[union-attr]


def migrate(engine: Engine, revision: str = "head", media_dir: Path | None = None,
            clips_dir: Path | None = None) -> None:
    """Upgrade the database to ``revision`` (run at start-up).  ``media_dir`` and ``clips_dir`` (the settings')
    let migration 0007 record the files existing studies show (see its docstring)."""
    _alembic(engine, lambda cfg: command.upgrade(cfg, revision), media_dir=media_dir, clips_dir=clips_dir)


def downgrade(engine: Engine, revision: str = "base") -> None:
    _alembic(engine, lambda cfg: command.downgrade(cfg, revision))
