"""Throughput of ``usdeform batch`` on a local Dask cluster: sweeps per minute for 1 and 2 workers (or
``--workers``), against running the same tasks one after another in this process.

The cohort: ``--subjects`` subjects, each fitting two simulated palpations and correcting and
compounding ``--sweeps-per-subject`` simulated sweeps (copies of two simulated sweeps, so the work
per sweep is the same everywhere). Every run writes to a fresh folder (nothing is reused); the best of
``--repeats`` runs is reported (the first pays for first-use costs). Cluster start-up is timed
apart; the workers import the package before the clock starts.

    python benches/bench_batch.py [--subjects 6] [--sweeps-per-subject 2] [--frames 100] [--size 128]
"""

from __future__ import annotations

import argparse
import importlib
import multiprocessing
import os
import shutil
import tempfile
import time
from pathlib import Path

from usdeform.batch import batch_client, plan_tasks, read_manifest, run_batch, run_task
from usdeform.io import write_sequence
from usdeform.sim import coarse_phantom, simulate_palpation, simulate_sweep


def _recordings(folder: Path, frames: int, size: int) -> None:
    """Two palpations and two sweeps of the coarse test phantom (the one the tests use)."""
    phantom = coarse_phantom()
    for name, s_mm, seed in (("palpation-15.mha", 15.0, 11), ("palpation-45.mha", 45.0, 12)):
        palpation, _ = simulate_palpation(phantom, s_mm, 8.0, n_frames=8, seed=seed, rows=size, cols=size)
        write_sequence(folder / name, palpation)
    for name, start_mm, seed in (("sweep-a.mha", 10.0, 3), ("sweep-b.mha", 20.0, 4)):
        sweep, _ = simulate_sweep(phantom, start_mm, 30.0, 8.0, n_frames=frames, seed=seed, rows=size, cols=size)
        write_sequence(folder / name, sweep)


def _manifest(folder: Path, subjects: int, sweeps_per_subject: int) -> Path:
    lines = ["[options]", "flexible_layer_mm = 60.0", ""]
    for subject in range(subjects):
        sweeps = []
        for index in range(sweeps_per_subject):
            path = folder / f"s{subject}-sweep{index}.mha"
            shutil.copy(folder / ("sweep-a.mha" if index % 2 == 0 else "sweep-b.mha"), path)
            sweeps.append(f'"{path}"')
        palpations = f'"{folder / "palpation-15.mha"}", "{folder / "palpation-45.mha"}"'
        lines += [
            "[[subjects]]",
            f'id = "s{subject}"',
            f"palpations = [{palpations}]",
            f"sweeps = [{', '.join(sweeps)}]",
        ]
    path = folder / "cohort.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def _spin(iterations: int) -> int:
    total = 0
    for value in range(iterations):
        total += value % 7
    return total


def _seconds_to_spin(processes: int, iterations: int) -> float:
    workers = [multiprocessing.Process(target=_spin, args=(iterations,)) for _ in range(processes)]
    start = time.perf_counter()
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    return time.perf_counter() - start


def _two_process_speedup(iterations: int = 10_000_000) -> float:
    """How much more pure-Python work two processes do than one in the same time, right now: 2.0 on
    two idle cores, less when other programs load them (the ceiling of any 2-worker speed-up). On a
    shared Linux machine the scheduler's autogroups give each login session a share of the cores,
    whatever its number of processes, so this may be near 1.0 while others are busy."""
    return 2 * _seconds_to_spin(1, iterations) / _seconds_to_spin(2, iterations)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subjects", type=int, default=6)
    parser.add_argument("--sweeps-per-subject", type=int, default=2)
    parser.add_argument("--frames", type=int, default=100, help="frames per sweep")
    parser.add_argument("--size", type=int, default=128, help="frame rows = columns, pixels")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=2, help="runs per configuration; the best is reported")
    args = parser.parse_args()

    ceiling = [_two_process_speedup()]
    with tempfile.TemporaryDirectory(prefix="usdeform-bench-batch-") as scratch:
        folder = Path(scratch)
        start = time.perf_counter()
        _recordings(folder, args.frames, args.size)
        manifest = read_manifest(_manifest(folder, args.subjects, args.sweeps_per_subject))
        n_sweeps = args.subjects * args.sweeps_per_subject
        print(
            f"cohort: {args.subjects} subjects x (1 fit of 2 palpations + {args.sweeps_per_subject} sweeps of "
            f"{args.frames} frames {args.size}x{args.size}) = {n_sweeps} sweeps; cores: {os.cpu_count()}; "
            f"recordings simulated in {time.perf_counter() - start:.1f} s"
        )

        in_process, in_process_busy = [], []
        for repeat in range(args.repeats):
            start = time.perf_counter()
            records: dict[str, dict] = {}
            for task in plan_tasks(manifest, folder / f"in-process-{repeat}"):  # plan order: a fit before its sweeps
                records[task.id] = run_task(task, needed=records.get(task.depends_on or ""))
                assert records[task.id]["status"] == "done", records[task.id]
            in_process.append(time.perf_counter() - start)
            in_process_busy.append(sum(record["seconds"] for record in records.values()))
        rows: list[tuple[str, str, list[float], list[float], float | None]] = [
            ("one process, no Dask", "all", in_process, in_process_busy, None)
        ]

        for n_workers in args.workers:
            start = time.perf_counter()
            with batch_client(n_workers=n_workers, dashboard_address=":0") as client:
                client.run(importlib.import_module, "usdeform.batch.stages")
                kernel_threads = client.run(lambda: os.environ.get("RAYON_NUM_THREADS"))
                start_seconds = time.perf_counter() - start
                times, busy = [], []
                for repeat in range(args.repeats):
                    start = time.perf_counter()
                    result = run_batch(manifest, folder / f"dask-{n_workers}-{repeat}", client=client)
                    times.append(time.perf_counter() - start)
                    busy.append(sum(record["seconds"] for record in result.records))
                    assert result.summary["done"] == len(result.records), result.summary
            threads = ",".join(sorted(set(kernel_threads.values())))
            rows.append((f"Dask, {n_workers} worker(s) x 1 thread", threads, times, busy, start_seconds))

    ceiling.append(_two_process_speedup())
    print(
        "\nmachine: two processes did {:.2f}x / {:.2f}x the work of one (before / after the runs; 2.00 on two idle "
        "cores: the ceiling of the 2-worker speed-up)".format(*ceiling)
    )
    baseline = min(rows[0][2])
    print(
        f"best of {args.repeats} runs (all runs, s, in brackets); sweeps/min counts the fits' time too; "
        "in tasks: the tasks' own seconds summed over all workers, in the best run"
    )
    print(
        "| run | kernel threads per worker | seconds | sweeps/min | vs one process | in tasks, s | cluster start, s |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, threads, times, busy, startup in rows:
        best = min(times)
        all_runs = ", ".join(f"{seconds:.1f}" for seconds in times)
        start_text = "-" if startup is None else f"{startup:.1f}"
        print(
            f"| {name} | {threads} | {best:.1f} ({all_runs}) | {60 * n_sweeps / best:.1f} | "
            f"{best / baseline:.2f}x | {busy[times.index(best)]:.1f} | {start_text} |"
        )


if __name__ == "__main__":
    main()
