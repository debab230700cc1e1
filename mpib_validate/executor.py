"""Where independent work items run: in this process, in local processes, or on Dask.

Every executor maps a top-level (picklable) function over items and returns the results
in item order, so what runs the work never changes the results. ``make_executor``:

- ``workers=0`` (default): in this process;
- ``workers=N``: N local processes (``concurrent.futures``);
- ``scheduler="tcp://host:8786"``: an existing Dask distributed cluster;
  ``scheduler="local"``: a Dask ``LocalCluster`` started here (``workers`` processes).
"""

from __future__ import annotations

import concurrent.futures as cf
from dataclasses import dataclass


@dataclass
class Executor:
    kind: str
    workers: int = 0
    scheduler: str | None = None

    def map(self, fn, items):
        items = list(items)
        if self.kind == "inprocess":
            return [fn(x) for x in items]
        if self.kind == "processes":
            import multiprocessing as mp

            ctx = mp.get_context("spawn")  # no forked JIT/OpenMP state
            with cf.ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx) as pool:
                return list(pool.map(fn, items))
        return self._dask_map(fn, items)

    def _dask_map(self, fn, items):
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise ValueError("the Dask executor needs dask[distributed] "
                             "(pip install 'mpib-validate[dask]')") from None
        if self.scheduler == "local":
            with LocalCluster(n_workers=max(self.workers, 1), threads_per_worker=1,
                              processes=True, dashboard_address=None) as cluster, \
                    Client(cluster) as client:
                return client.gather(client.map(fn, items, pure=False))
        with Client(self.scheduler) as client:
            return client.gather(client.map(fn, items, pure=False))


def make_executor(workers: int = 0, scheduler: str | None = None) -> Executor:
    if scheduler:
        return Executor("dask", workers, scheduler)
    if workers and workers > 0:
        return Executor("processes", workers)
    return Executor("inprocess")
