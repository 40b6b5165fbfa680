"""Where the tiles run: Dask's local schedulers, a plain loop, a LocalCluster or a running cluster by address."""

from __future__ import annotations

import contextlib
import re

from ..core.errors import LabkitError
from ..core.progress import progress_steps

__all__ = ["SCHEDULERS", "check_scheduler"]

SCHEDULERS = ("threads", "processes", "sync", "serial", "cluster")
_ADDRESS = re.compile(r"^(tcp|tls|ucx)://(\[[0-9a-fA-F:]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")


def check_scheduler(scheduler: str) -> str:
    """A scheduler name of :data:`SCHEDULERS` or a Dask scheduler address ``tcp://HOST:PORT``; else LabkitError.

    Examples
    --------
    >>> from labkit.tiles import check_scheduler
    >>> check_scheduler("threads"), check_scheduler(" tcp://10.0.0.5:8786 ")
    ('threads', 'tcp://10.0.0.5:8786')
    """
    if isinstance(scheduler, str):
        text = scheduler.strip()
        if text in SCHEDULERS:
            return text
        m = _ADDRESS.match(text)
        if m and 0 < int(m.group(3)) < 65536:
            return text
    raise LabkitError(f"scheduler must be one of {', '.join(SCHEDULERS)} or a Dask scheduler address "
                      f"like tcp://HOST:PORT, got {scheduler!r}")


def _is_address(scheduler) -> bool:
    return isinstance(scheduler, str) and "://" in scheduler


@contextlib.contextmanager
def _dask_client(client, scheduler: str):
    """The distributed Client to run on (given, started for a LocalCluster, or connected by address), or None."""
    if client is not None or not (scheduler == "cluster" or _is_address(scheduler)):
        yield client
        return
    try:
        import distributed
    except ImportError:
        raise LabkitError(f"scheduler={scheduler!r} needs dask.distributed (pip install distributed); "
                          "use scheduler='threads'") from None
    if scheduler == "cluster":
        with distributed.LocalCluster(threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
                distributed.Client(cluster) as cl:
            yield cl
        return
    try:
        cl = distributed.Client(scheduler, timeout="10s")
    except OSError as exc:
        raise LabkitError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
    with cl:
        yield cl


def _run_jobs(run, jobs, client, scheduler, progress) -> list:
    """Results of ``run(*job)`` in the order of ``jobs``; progress counts finished tiles."""

    with progress_steps(progress, len(jobs), "tiles", "tiles") as step:
        if not jobs:
            return []
        if client is None and scheduler == "serial":
            out = []
            for job in jobs:
                out.append(run(*job))
                step(1)
            return out
        import dask

        tasks = [dask.delayed(run, pure=True)(*j, dask_key_name=f"tile-{j[0].row}-{j[0].col}") for j in jobs]
        if client is not None:
            from distributed import as_completed

            futures = client.compute(tasks)
            for _ in as_completed(futures):
                step(1)
            return client.gather(futures)
        from dask.callbacks import Callback

        def posttask(key, result, dsk, state, worker_id):
            name = key[0] if isinstance(key, tuple) else key
            if isinstance(name, str) and name.startswith("tile-"):
                step(1)

        with Callback(posttask=posttask):
            return list(dask.compute(*tasks, scheduler=scheduler))


