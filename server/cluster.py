"""Where renders run: Dask distributed (docs/cluster.md).

Without ``ANIMSTUDY_DASK_SCHEDULER`` a job starts an in-process ``LocalCluster`` (worker processes on this machine,
one thread each: OSMesa renders on one core per process; TLS with temporary credentials, so no other user of the
machine can reach it) and closes it when done, so every command works with nothing to start.  With
``ANIMSTUDY_DASK_SCHEDULER=tcp://host:8786`` (or ``tls://``, with Dask's TLS settings: docs/cluster.md) the job is
submitted to that cluster; its workers need the same animstudy version installed (checked: a worker with another
version is refused) but no shared filesystem: tasks get their inputs as values and return the encoded bytes.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING

from server.errors import MediaError

if TYPE_CHECKING:
    from distributed import Client, Future

CONNECT_TIMEOUT_S = 10.0
WORKERS_TIMEOUT_S = 60.0
CLOSE_TIMEOUT_S = 30.0
# How long a job whose scheduler went away mid-job waits for it to come back (restarted by hand, by SLURM or by
# Kubernetes, with workers) before it fails; and the pause between two tries to reach it.
RECONNECT_S = 600.0
RECONNECT_PAUSE_S = 5.0
log = logging.getLogger(__name__)  # how long a job waits for a cluster without workers to get one


class ClusterError(MediaError):
    """The Dask cluster cannot run the job (unreachable, no workers, other versions); the message says which.
    A :class:`~server.errors.MediaError`: every command that renders reports it as one."""


def package_version() -> str:
    """The installed animstudy version (what a worker must have too)."""
    try:
        return version("animstudy")
    except PackageNotFoundError:
        return "unknown"


# The submitting side's version, read once (a test may stand in another one here; workers report their own).
PACKAGE_VERSION = package_version()


def machine_workers() -> int:
    """Worker processes for the local cluster: one per core this process may use (the runtime's count)."""
    from anim_core.runtime import pose_threads

    return pose_threads()


def check_versions(client: Client, address: str) -> None:
    """Refuse a cluster whose workers run another animstudy version (naming both), or that has no worker."""
    try:
        client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
    except TimeoutError:
        raise ClusterError(f"the Dask scheduler at {address} has no workers (waited {WORKERS_TIMEOUT_S:.0f} s); "
                           "start some with `dask worker " + address + "`") from None
    reported = client.run(package_version)
    other = {worker: v for worker, v in reported.items() if v != PACKAGE_VERSION}
    if other:
        listed = ", ".join(f"{worker} has animstudy {v}" for worker, v in sorted(other.items()))
        raise ClusterError(f"Dask workers with another animstudy version than this side's {PACKAGE_VERSION}: "
                           f"{listed}; install the same version on every worker")


def _value(value: object) -> object:
    return value


def share(client: Client, value: object, name: str) -> Future:
    """``value`` (the character) on the cluster once, for every task of a job to take as an argument: as a task
    of its own rather than scattered data, since a scattered value lost with its worker cannot be recovered and a
    task's result is computed again."""
    return client.submit(_value, value, pure=False, key=f"{name}-{uuid.uuid4().hex[:8]}")


# What a local worker runs (renders, clip builds), imported once by the fork server, not by every worker.
FORKSERVER_PRELOAD = ("distributed", "server.media.worker", "server.clipset.build")


def _fork_local_workers() -> None:
    """Local workers forked from one server process per process that starts clusters, instead of spawned: a
    spawned worker starts a new interpreter and imports Dask, numpy, pyrender and the render code (~2 s of a core
    each, two workers a job); a forked one starts in milliseconds with all of it imported, and every later local
    cluster of this process (a server's jobs, a test run) forks from the same server.  Dask's own setting is kept
    when it names another method than its default, ``spawn``."""
    import multiprocessing

    import dask
    from distributed.utils import get_mp_context

    key = "distributed.worker.multiprocessing-method"
    if dask.config.get(key) != "spawn" or "forkserver" not in multiprocessing.get_all_start_methods():
        return
    # For the process, not for one cluster: a nanny restarts a killed worker later, by the method set then.
    dask.config.set({key: "forkserver"})
    # distributed sets its own preload list on its first call (once); ours replaces it before the server starts.
    get_mp_context().set_forkserver_preload(list(FORKSERVER_PRELOAD))


@contextmanager
def dask_client(scheduler: str | None, workers: int | None = None) -> Iterator[Client]:
    """A client of the cluster at ``scheduler``, or of a local cluster of ``workers`` processes (default: one per
    core) closed on exit.  :class:`ClusterError` names the address when the scheduler cannot be reached."""
    from distributed import Client, LocalCluster
    from distributed.security import Security

    if scheduler:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            raise ClusterError(f"cannot reach the Dask scheduler at {scheduler} ({exc}); is it running, and is "
                               "ANIMSTUDY_DASK_SCHEDULER right?") from None
        try:
            check_versions(client, scheduler)
            yield client
        finally:
            client.close()
        return
    # TLS with a certificate made for this cluster alone (held in memory, handed to the worker processes through
    # their pipes): its ports on 127.0.0.1 are open to every user of the machine, and a Dask scheduler runs any
    # code it is sent.  Without the certificate nobody connects (docs/cluster.md).
    security = Security.temporary()
    _fork_local_workers()
    # Only critical worker logs: a task's failure ("Compute Failed", logged at ERROR with its traceback) reaches the
    # caller as the task's own exception, which every command reports as one line (issue 37).
    # The scheduler's HTTP server (health and metrics routes) starts even with dashboard_address=None, on port 8787
    # of every interface (dask/distributed#8136): a second cluster warned "Port 8787 is already in use".  A free
    # port on loopback instead; no dashboard is served (bokeh is not installed).
    cluster = LocalCluster(n_workers=workers or machine_workers(), threads_per_worker=1, processes=True,
                           dashboard_address="127.0.0.1:0", silence_logs=logging.CRITICAL, security=security,
                           protocol="tls://")
    client = Client(cluster, security=security, set_as_default=False)
    try:
        yield client
    finally:
        # The job's files are stored by now: workers slow to stop (a loaded machine) must not fail it.
        for part in (client, cluster):
            try:
                part.close(timeout=CLOSE_TIMEOUT_S)
            except Exception as exc:  # logged, never raised over the job's own outcome
                log.warning("closing the local Dask cluster: %s: %s", type(exc).__name__, exc)
