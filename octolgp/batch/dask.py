"""Where batch work runs: a ``dask.distributed`` client for a scheduler argument.

A scheduler decides where the work runs, never what is computed: every batch
method that accepts one gives the same map in-process and on a cluster.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

from octolgp.errors import OctolgpError


@contextlib.contextmanager
def dask_client(scheduler: Any, workers: int | None) -> Iterator[Any]:
    """A ``distributed.Client`` for ``scheduler``; an embedded cluster is closed after.

    Parameters
    ----------
    scheduler : "local", str or distributed.Client
        ``"local"``: an embedded ``LocalCluster`` of ``workers`` single-threaded
        processes; an address such as ``"tcp://host:8786"``: that cluster; a
        ``Client``: used as is (not closed).
    workers : int, optional
        Processes of the embedded cluster (default: one per core).

    Raises
    ------
    OctolgpError
        If dask.distributed is missing, the argument is bad or the cluster cannot
        be reached.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise OctolgpError(
            "scheduler: dask.distributed is not installed (pip install 'octolgp[dask]')"
        ) from None
    if isinstance(scheduler, Client):
        yield scheduler
        return
    if not isinstance(scheduler, str) or not scheduler:
        raise OctolgpError(
            f"scheduler must be 'local', a scheduler address or a Client, got {scheduler!r}"
        )
    if scheduler == "local":
        if workers is not None and workers < 1:
            raise OctolgpError(f"workers must be >= 1, got {workers}")
        with (
            LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
            ) as cluster,
            Client(cluster) as client,
        ):
            yield client
        return
    try:
        client = Client(scheduler, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise OctolgpError(f"scheduler {scheduler!r}: cannot connect: {exc}") from None
    with client:
        yield client
