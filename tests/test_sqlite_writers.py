"""SQLite writers wait their turn in server.db.WriterQueue: across engines (as across worker processes), released
however a transaction ends, bounded in time, and freed by the kernel when the holder is killed."""

import multiprocessing
import os
import signal
import threading
import time

import pytest
from sqlalchemy import text
from sqlalchemy.exc import OperationalError

from server.db import make_engine

ROWS = text("SELECT count(*) FROM t")


@pytest.fixture
def url(tmp_path):
    url = f"sqlite:///{tmp_path / 'w.db'}"
    engine = make_engine(url)
    with engine.begin() as conn:
        conn.execute(text("CREATE TABLE t (x INTEGER)"))
    engine.dispose()
    return url


def write_in_thread(engine, done: threading.Event, errors: list) -> threading.Thread:
    def run():
        try:
            with engine.begin() as conn:
                conn.execute(text("INSERT INTO t VALUES (2)"))
        except Exception as e:  # handed to the test
            errors.append(e)
        done.set()

    thread = threading.Thread(target=run)
    thread.start()
    return thread


@pytest.mark.parametrize("ending", ["commit", "rollback", "close"])
def test_a_second_writer_waits_until_the_first_transaction_ends(url, ending):
    first, second = make_engine(url), make_engine(url)  # two engines: two queues, like two worker processes
    conn = first.connect()
    tx = conn.begin()
    conn.execute(text("INSERT INTO t VALUES (1)"))
    done, errors = threading.Event(), []
    thread = write_in_thread(second, done, errors)
    assert not done.wait(0.5), "the second writer did not wait"
    if ending == "commit":
        tx.commit()
    elif ending == "rollback":
        tx.rollback()
    conn.close()  # "close" ends the transaction by returning the connection to the pool
    assert done.wait(5), "the second writer was not let in"
    thread.join()
    assert errors == []
    with second.connect() as c:
        assert c.scalar(ROWS) == (2 if ending == "commit" else 1)
    first.dispose()
    second.dispose()


def test_a_writer_gives_up_after_the_timeout(url):
    first, second = make_engine(url), make_engine(url, sqlite_timeout_s=0.3)
    with first.begin() as conn:
        conn.execute(text("INSERT INTO t VALUES (1)"))
        started = time.monotonic()
        with pytest.raises(OperationalError, match="database is locked"), second.begin() as other:
            other.execute(text("INSERT INTO t VALUES (2)"))
        assert 0.25 < time.monotonic() - started < 5
    # and the queue is usable again afterwards
    with second.begin() as other:
        other.execute(text("INSERT INTO t VALUES (3)"))
    with second.connect() as c:
        assert c.scalar(ROWS) == 2
    first.dispose()
    second.dispose()


def _hold_the_write_lock(url: str, ready) -> None:
    engine = make_engine(url)
    conn = engine.connect()
    conn.begin()
    conn.execute(text("INSERT INTO t VALUES (1)"))
    ready.set()
    time.sleep(60)


def test_a_killed_writer_does_not_block_the_others(url):
    ctx = multiprocessing.get_context("spawn")
    ready = ctx.Event()
    holder = ctx.Process(target=_hold_the_write_lock, args=(url, ready))
    holder.start()
    try:
        assert ready.wait(30)
        engine = make_engine(url)
        done, errors = threading.Event(), []
        thread = write_in_thread(engine, done, errors)
        assert not done.wait(0.5), "the writer did not wait for the other process"
        os.kill(holder.pid, signal.SIGKILL)
        assert done.wait(10), "the lock of the killed process was not released"
        thread.join()
        assert errors == []
        with engine.connect() as c:
            assert c.scalar(ROWS) == 1  # the killed transaction's row is gone, ours is stored
        engine.dispose()
    finally:
        holder.kill()
        holder.join()


def test_a_second_transaction_of_the_same_thread_is_refused_at_once(url):
    """An event loop serving two requests is one thread: if the first still held its turn, waiting for it would
    wait for ourselves until the timeout."""
    engine = make_engine(url)
    with engine.connect() as first:
        first.begin()
        first.execute(text("INSERT INTO t VALUES (1)"))
        started = time.monotonic()
        with pytest.raises(OperationalError, match="database is locked"), engine.begin() as second:
            second.execute(text("INSERT INTO t VALUES (2)"))
        assert time.monotonic() - started < 1
        first.commit()
    with engine.connect() as c:
        assert c.scalar(ROWS) == 1
    engine.dispose()
