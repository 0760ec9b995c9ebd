"""The command ``usdeform batch MANIFEST --out DIR [--scheduler ADDRESS] [--workers N]``.

Wired into the command line by ``add_batch_command(commands)``; the work is done by
:func:`usdeform.batch.run_batch`, this module only parses and prints.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..errors import UsdeformError
from ..options import NUMBERS

__all__ = ["add_batch_command"]


def _batch(args: argparse.Namespace) -> None:
    from tqdm import tqdm  # type: ignore[import-untyped,unused-ignore]

    from .._files import new_output_folders
    from .manifest import read_manifest
    from .runner import RESULTS_NAME, batch_client, dashboard_link, run_batch
    from .tasks import plan_tasks

    new_output_folders(args.out, "--out")  # before the cluster starts
    manifest = read_manifest(args.manifest)
    n_tasks = len(plan_tasks(manifest, args.out))
    try:
        client_context = batch_client(args.scheduler, n_workers=args.workers, kernel_threads=args.kernel_threads)
        with client_context as client:
            link = dashboard_link(client)
            workers = len(client.scheduler_info()["workers"])
            print(f"{len(manifest.subjects)} subjects, {n_tasks} tasks on {workers} workers", file=sys.stderr)
            if link is not None:
                print(f"dashboard: {link}", file=sys.stderr)
            with tqdm(total=n_tasks, unit="task", file=sys.stderr) as bar:

                def report(record: dict[str, Any]) -> None:
                    if record["status"] != "done":
                        bar.write(f"{record['id']}: {record['status']}: {record['error']}", file=sys.stderr)
                    bar.update(1)

                result = run_batch(manifest, args.out, client=client, retries=args.retries, on_record=report)
    except ImportError as error:
        raise UsdeformError(str(error)) from None
    counts = result.summary
    print(
        f"{counts['done']} done ({counts['reused']} reused from the last run), {counts['failed']} failed, "
        f"{counts['skipped']} skipped; wrote {result.results_path}"
    )
    if counts["failed"] or counts["skipped"]:
        raise UsdeformError(
            f"{counts['failed'] + counts['skipped']} of {n_tasks} tasks did not finish; "
            f"see {Path(args.out) / RESULTS_NAME}"
        )


def add_batch_command(commands: Any) -> None:
    """Add ``usdeform batch`` to the command line's subparsers ``commands``."""
    parser = commands.add_parser(
        "batch",
        help="fit, correct and reconstruct a cohort's recordings on a Dask cluster (pip install usdeform[cluster])",
        description="Run the subjects of a manifest (TOML or CSV, see the usdeform.batch documentation) on a local "
        "Dask cluster or an existing one; OUT/results.json records every task and lets a rerun skip finished work.",
    )
    parser.add_argument("manifest", type=Path, metavar="MANIFEST", help="batch manifest (.toml or .csv)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    parser.add_argument(
        "--scheduler", metavar="ADDRESS", help="address of a running Dask scheduler (default: start a local cluster)"
    )
    parser.add_argument(
        "--workers",
        type=NUMBERS["workers"].argument(),
        metavar="N",
        help="local cluster: worker processes (default: one per core)",
    )
    parser.add_argument(
        "--kernel-threads",
        type=NUMBERS["kernel_threads"].argument(),
        metavar="T",
        help="local cluster: threads of each worker's compiled kernels (default: cores / workers)",
    )
    parser.add_argument(
        "--retries",
        type=NUMBERS["retries"].argument(),
        default=2,
        metavar="R",
        help="retries of a task that fails unexpectedly (0 to 100, default 2)",
    )
    parser.set_defaults(run=_batch)
