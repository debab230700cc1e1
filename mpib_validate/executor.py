"""Where independent work items run: in this process, in local processes, or on Dask.

Every executor maps a top-level (picklable) function over items and returns the results
in item order, so what runs the work never changes the results. ``make_executor``:

- ``workers=0`` (default): in this process;
- ``workers=N``: N local processes (``concurrent.futures``);
- ``scheduler="tcp://host:8786"``: an existing Dask distributed cluster;
  ``scheduler="local"``: a Dask ``LocalCluster`` started here (``workers`` processes).

``map(fn, items, progress)`` calls ``progress(result)`` in this process as each item
finishes (in any order). Interrupting the map (Ctrl-C, or SIGTERM turned into
:class:`Terminated` by the command line) stops the local worker processes before it
returns: they ignore SIGINT themselves, so that only this process decides.
"""

from __future__ import annotations

import concurrent.futures as cf
import signal
from dataclasses import dataclass

#: Seconds to wait for a Dask scheduler to answer before giving up.
CONNECT_TIMEOUT_S = 5.0


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that it unwinds like Ctrl-C."""


class ExecutorError(ValueError):
    """An executor that cannot start (no Dask, an unreachable scheduler)."""


def raise_on_sigterm():
    """Make SIGTERM raise :class:`Terminated` in the main thread; returns the previous
    handler (for :func:`restore_sigterm`), or None where it cannot be set."""
    def handler(signum, frame):
        raise Terminated()

    try:
        return signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        return None


def restore_sigterm(previous) -> None:
    if previous is not None:
        try:
            signal.signal(signal.SIGTERM, previous)
        except ValueError:
            pass


def _ignore_sigint() -> None:
    """Worker initialiser: Ctrl-C reaches the whole process group; the parent handles
    it and stops the workers (no traceback from each of them)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@dataclass
class Executor:
    kind: str
    workers: int = 0
    scheduler: str | None = None

    def map(self, fn, items, progress=None):
        items = list(items)
        done = progress if progress is not None else (lambda result: None)
        if self.kind == "inprocess":
            out = []
            for x in items:
                out.append(fn(x))
                done(out[-1])
            return out
        if self.kind == "processes":
            return self._process_map(fn, items, done)
        return self._dask_map(fn, items, done)

    def _process_map(self, fn, items, done):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")  # no forked JIT/OpenMP state
        pool = cf.ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx,
                                      initializer=_ignore_sigint)
        try:
            futures = [pool.submit(fn, x) for x in items]
            for f in cf.as_completed(futures):
                done(f.result())
            results = [f.result() for f in futures]
        except BaseException:
            # stop the workers now: shutdown() alone would wait for their running items
            procs = list(getattr(pool, "_processes", {}).values())
            pool.shutdown(wait=False, cancel_futures=True)
            for p in procs:
                p.terminate()
            for p in procs:
                p.join(timeout=10)
            raise
        pool.shutdown(wait=True)
        return results

    def _dask_map(self, fn, items, done):
        try:
            from distributed import Client, LocalCluster, as_completed
        except ImportError:
            raise ExecutorError("the Dask executor needs dask[distributed] "
                                "(pip install 'mpib-validate[dask]')") from None

        def run(client):
            futures = client.map(fn, items, pure=False)
            for f in as_completed(futures):
                done(f.result())
            return client.gather(futures)

        if self.scheduler == "local":
            with LocalCluster(n_workers=max(self.workers, 1), threads_per_worker=1,
                              processes=True, dashboard_address=None) as cluster, \
                    Client(cluster) as client:
                return run(client)
        with self._connect() as client:
            return run(client)

    def _connect(self):
        try:
            from distributed import Client
        except ImportError:
            raise ExecutorError("the Dask executor needs dask[distributed] "
                                "(pip install 'mpib-validate[dask]')") from None
        try:
            return Client(self.scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as exc:
            raise ExecutorError(f"--scheduler '{self.scheduler}': cannot reach a Dask scheduler "
                                f"within {CONNECT_TIMEOUT_S:g} s ({type(exc).__name__}); start "
                                f"one with 'dask scheduler', or use --scheduler local") from None

    def check(self) -> None:
        """Raise :class:`ExecutorError` now if the executor cannot start (an unreachable
        scheduler), before any output is made."""
        if self.kind == "dask" and self.scheduler != "local":
            self._connect().close()


def make_executor(workers: int = 0, scheduler: str | None = None) -> Executor:
    if scheduler:
        return Executor("dask", workers, scheduler)
    if workers and workers > 0:
        return Executor("processes", workers)
    return Executor("inprocess")
