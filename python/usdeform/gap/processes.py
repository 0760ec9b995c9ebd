"""The diagnosis's worker processes: one pool for a whole diagnosis (the FEM library's solves of every recording,
then the attribution's fits), and the calls run in it with their results in submission order.

Each call is deterministic, so a diagnosis is the same whatever the number of processes; where the pool's
processes stop (a script without a ``__main__`` guard re-runs itself in each spawned worker), the calls left run
in this process.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from typing import Any

from ..validation import available_cores

__all__ = ["available_workers", "run_all", "worker_pool"]


def available_workers() -> int:
    """Processes for the diagnosis: the cores this process may run on, 1 in a daemonic process (a Dask or
    multiprocessing worker cannot start processes of its own)."""
    if multiprocessing.current_process().daemon:
        return 1
    return available_cores()


def _exit_with_parent(parent_pid: int) -> None:
    """Worker initializer: end this worker when the process that started it is gone (killed, say), rather than
    wait forever for work that will not come (a pool's orphaned workers otherwise never exit)."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


@contextmanager
def worker_pool(workers: int | None = None) -> Iterator[Executor | None]:
    """A pool of ``workers`` spawned processes (default :func:`available_workers`), None for one: every call then
    runs in this process. Spawned, not forked: a fork would inherit the Rust kernels' thread pool without its
    threads. Left by an exception (Ctrl-C, SIGTERM, a failed call), the queued calls are dropped rather than run
    to the end (minutes of FEM)."""
    workers = available_workers() if workers is None else workers
    if workers < 1:
        raise ValueError(f"workers: expected at least 1, got {workers}")
    if workers == 1:
        yield None
        return
    pool = ProcessPoolExecutor(
        workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_exit_with_parent,
        initargs=(os.getpid(),),
    )
    try:
        yield pool
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()


def run_all(
    pool: Executor | None, function: Callable[..., Any], arguments: Sequence[tuple], progress=None
) -> list[Any]:
    """``function(*args)`` for each of ``arguments``, in ``pool`` (None: in this process), in their order;
    ``progress``: an optional tqdm-like object whose ``update(1)`` is called after each. Calls the pool could not
    run (its processes stopped) run here, with a RuntimeWarning."""
    results: dict[int, Any] = {}
    if pool is not None and arguments:
        try:
            futures = [pool.submit(function, *args) for args in arguments]
            for index, future in enumerate(futures):
                results[index] = future.result()
                if progress is not None:
                    progress.update(1)
        except BrokenProcessPool:
            warnings.warn(
                "usdeform.gap: the diagnosis's worker processes stopped (a script that diagnoses needs its calls "
                "under `if __name__ == '__main__':`, as for any multiprocessing, or workers=1); running the rest "
                "in this process",
                RuntimeWarning,
                stacklevel=2,
            )
    for index, args in enumerate(arguments):
        if index not in results:
            results[index] = function(*args)
            if progress is not None:
                progress.update(1)
    return [results[index] for index in range(len(arguments))]
