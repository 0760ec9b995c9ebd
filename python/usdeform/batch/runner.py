"""Run a manifest's tasks on a Dask cluster and keep the results manifest up to date.

:func:`batch_client` starts a local cluster (or connects to a running scheduler);
:func:`submit_batch` puts a manifest's tasks on it and returns their futures; :func:`run_batch`
does both, waits, and writes ``OUT/results.json`` atomically each time tasks finish (at most once a
second, and at the end), so an interrupted batch leaves a valid results manifest and a rerun reuses
the work that is done.

Each task carries only paths and options: the worker reads the recordings itself, so every worker
must see the input paths and the output folder (one machine, or a shared file system).
"""

from __future__ import annotations

import contextlib
import datetime
import importlib.util
import json
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .._files import atomic_output
from ..errors import FileFormatError
from ..validation import available_cores
from .manifest import Manifest
from .tasks import TaskSpec, one_line, plan_tasks, run_task, task_record

if TYPE_CHECKING:
    from distributed import Client, Future

__all__ = ["RESULTS_NAME", "BatchResult", "batch_client", "dashboard_link", "read_results", "run_batch", "submit_batch"]

RESULTS_NAME = "results.json"
RESULTS_FORMAT = "usdeform-batch-results"
RESULTS_VERSION = 1
STATUSES = ("done", "failed", "skipped", "pending")


def _distributed() -> Any:
    """The ``distributed`` module, or an ImportError saying how to install it."""
    try:
        import distributed
    except ImportError as error:
        raise ImportError(
            f"usdeform batch runs on Dask, which is not installed ({error}): pip install 'usdeform[cluster]'"
        ) from None
    return distributed


@contextlib.contextmanager
def batch_client(
    scheduler: str | None = None,
    *,
    n_workers: int | None = None,
    threads_per_worker: int = 1,
    kernel_threads: int | None = None,
    dashboard_address: str = ":8787",
) -> Iterator[Client]:
    """A Dask client: connected to ``scheduler`` (an address such as ``tcp://host:8786``), or to a new
    local cluster of worker processes that is closed on exit.

    The local cluster has ``n_workers`` processes (default: one per core) of ``threads_per_worker``
    task threads each (default 1: the compiled kernels run their own threads), and each worker's
    kernels use ``kernel_threads`` threads (``RAYON_NUM_THREADS``; default: cores / workers, at least
    1), so that workers do not oversubscribe the cores. The scheduler serves its HTTP endpoints (and the
    dashboard, with bokeh installed) at ``dashboard_address`` (":0": any free port). For a cluster
    started by hand the same holds: ``RAYON_NUM_THREADS=T dask worker ADDRESS --nthreads 1``.
    """
    distributed = _distributed()
    import dask

    if scheduler is not None:
        with distributed.Client(scheduler) as client:
            yield client
        return
    cores = available_cores()
    n_workers = n_workers or cores
    kernel_threads = kernel_threads or max(1, cores // n_workers)
    # Dask sets MALLOC_TRIM_THRESHOLD_ in new workers to hand freed memory back to the system sooner;
    # that also turns off glibc's adaptive mmap threshold, so every large frame array is mapped anew
    # and page-faulted: a 256 x 256, 200-frame sweep took 15-20 % longer. Tasks are short and keep
    # nothing, so the workers keep glibc's default.
    with (
        dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}),
        distributed.LocalCluster(
            n_workers=n_workers,
            threads_per_worker=threads_per_worker,
            processes=True,
            dashboard_address=dashboard_address,
            env={"RAYON_NUM_THREADS": str(kernel_threads)},
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        yield client


def _has_bokeh() -> bool:
    return importlib.util.find_spec("bokeh") is not None


def dashboard_link(client: Client) -> str | None:
    """The address of the cluster's Dask dashboard, or None when it has none (no HTTP server, or
    bokeh, which draws it, is not installed where the scheduler runs)."""
    if "dashboard" not in client.scheduler_info().get("services", {}) or not client.run_on_scheduler(_has_bokeh):
        return None
    return str(client.dashboard_link)


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def read_results(path: Path) -> dict[str, dict[str, Any]]:
    """The task records of a results manifest by task id ({} if the file does not exist)."""
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise FileFormatError(f"{path}: not a results manifest ({error}); delete it to run everything again") from None
    if not isinstance(document, dict) or document.get("format") != RESULTS_FORMAT:
        raise FileFormatError(f"{path}: format: expected {RESULTS_FORMAT!r}; delete it to run everything again")
    tasks = document.get("tasks")
    if not isinstance(tasks, list) or not all(isinstance(item, dict) and "id" in item for item in tasks):
        raise FileFormatError(f"{path}: tasks: expected a list of task records")
    return {item["id"]: item for item in tasks}


class _ResultsFile:
    """The results manifest of one run: every task's latest record, written atomically."""

    def __init__(
        self,
        path: Path,
        manifest: Manifest,
        tasks: list[TaskSpec],
        previous: Mapping[str, dict[str, Any]],
        min_interval_s: float = 1.0,
    ):
        self.path, self.manifest, self.min_interval_s = path, manifest, min_interval_s
        # Until a task reports, its previous record stands, so that an interrupted rerun loses nothing.
        self.records: dict[str, dict[str, Any]] = {
            task.id: previous.get(task.id)
            or {"id": task.id, "kind": task.kind, "subject": task.subject, "status": "pending"}
            for task in tasks
        }
        self.written_at = 0.0

    def update(self, record: dict[str, Any]) -> None:
        self.records[record["id"]] = record
        if time.monotonic() - self.written_at >= self.min_interval_s:
            self.write()

    def summary(self) -> dict[str, int]:
        counts = {status: 0 for status in STATUSES}
        for record in self.records.values():
            counts[record["status"]] = counts.get(record["status"], 0) + 1
        counts["reused"] = sum(bool(record.get("reused")) for record in self.records.values())
        return counts

    def write(self) -> None:
        document = {
            "format": RESULTS_FORMAT,
            "version": RESULTS_VERSION,
            "manifest": str(self.manifest.path) if self.manifest.path else None,
            "out": str(self.path.parent),
            "updated": _now(),
            "summary": self.summary(),
            "tasks": list(self.records.values()),
        }
        with atomic_output(self.path) as handle:
            handle.write((json.dumps(document, indent=1) + "\n").encode("utf-8"))
        self.written_at = time.monotonic()


def submit_batch(
    client: Client,
    manifest: Manifest,
    out_dir: str | Path,
    *,
    previous: Mapping[str, dict[str, Any]] | None = None,
    retries: int = 2,
) -> dict[str, Future]:
    """Submit the tasks of ``manifest`` (outputs under ``out_dir``) to ``client``'s cluster.

    Returns a future per task id whose result is the task's record (see :mod:`usdeform.batch.tasks`);
    ``previous``: the records of an earlier run by task id, whose finished work is reused. A task that
    raises an unexpected error is retried ``retries`` times; a task whose worker dies is rescheduled
    by the scheduler (up to its ``distributed.scheduler.allowed-failures``).
    """
    previous = previous or {}
    token = uuid.uuid4().hex[:12]
    futures: dict[str, Future] = {}
    for task in plan_tasks(manifest, out_dir):
        needed = futures[task.depends_on] if task.depends_on else None
        futures[task.id] = client.submit(
            run_task,
            task,
            previous.get(task.id),
            needed,
            key=f"usdeform-{task.kind}-{token}-{task.id}",
            retries=retries,
            pure=False,
        )
    return futures


def _erred_record(task: TaskSpec, futures: Mapping[str, Future]) -> dict[str, Any]:
    """The record of a task whose future ended without a record (it raised after its retries, its
    workers died, or the task it needed did)."""
    needed = futures.get(task.depends_on) if task.depends_on else None
    if needed is not None and needed.status == "error":
        reason = f"{task.depends_on} failed: {one_line(needed.exception())}"
        return task_record(task, "skipped", reason, time.time(), None, worker=None)
    future = futures[task.id]
    error = one_line(future.exception()) if future.status == "error" else f"future {future.status}"
    return task_record(task, "failed", error, time.time(), None, worker=None)


@dataclass(frozen=True)
class BatchResult:
    """The records of a finished batch in plan order, the results manifest's path and the counts
    per status (plus ``reused``)."""

    records: tuple[dict[str, Any], ...]
    results_path: Path
    summary: dict[str, int]


def run_batch(
    manifest: Manifest,
    out_dir: str | Path,
    *,
    client: Client | None = None,
    scheduler: str | None = None,
    n_workers: int | None = None,
    retries: int = 2,
    on_record: Callable[[dict[str, Any]], None] | None = None,
) -> BatchResult:
    """Run ``manifest`` with outputs under ``out_dir`` and return the records.

    ``client``: an existing Dask client; otherwise one from :func:`batch_client` (``scheduler``,
    ``n_workers``, the dashboard on any free port). ``on_record`` is called with each task's record
    as it finishes. ``OUT/results.json`` is written as tasks finish; the previous one, if any, says
    what to reuse.
    """
    distributed = _distributed()
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    tasks = plan_tasks(manifest, out)
    previous = read_results(out / RESULTS_NAME)
    results = _ResultsFile(out / RESULTS_NAME, manifest, tasks, previous)
    results.write()
    with contextlib.ExitStack() as stack:
        if client is None:
            client = stack.enter_context(batch_client(scheduler, n_workers=n_workers, dashboard_address=":0"))
        futures = submit_batch(client, manifest, out, previous=previous, retries=retries)
        task_of = {futures[task.id].key: task for task in tasks}
        try:
            for future in distributed.as_completed(futures.values()):
                task = task_of[future.key]
                record = future.result() if future.status == "finished" else _erred_record(task, futures)
                results.update(record)
                if on_record is not None:
                    on_record(record)
        finally:
            results.write()
    return BatchResult(tuple(results.records.values()), results.path, results.summary())
