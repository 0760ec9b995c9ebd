"""``usdeform compensation-benchmark``: the run over cases and its command line."""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from .._files import new_output_folders
from ..errors import InputError
from ..gap.benchmark import MAX_CASES, finished_rows
from ..gap.diagnosis import check_seed
from ..gap.report import write_text
from ..options import NUMBERS, Number
from .cases import _ROUND, EFFECT_TYPES, SETTING_RANGES, BenchmarkSettings, _draw_case, run_case
from .scoring import _number, _share, case_scores, json_text, markdown_report, summarise

__all__ = ["add_compensation_benchmark_command", "run_compensation_benchmark"]


def run_compensation_benchmark(
    n_cases: int,
    seed: int,
    out: str | Path,
    *,
    settings: BenchmarkSettings = BenchmarkSettings(),  # noqa: B008 (frozen)
    effects: Sequence[str | None] = _ROUND,
    progress: bool = True,
    command: str = "",
    resume: bool = False,
) -> dict[str, Any]:
    """Run ``n_cases`` cases (module docstring) and write ``out/cases.jsonl`` (a line per finished case),
    ``out/benchmark.json`` and ``out/benchmark.md``, each case's ``diagnosis.json`` in ``out/case_NNN``.
    Returns the summary (:func:`summarise`). Case ``i`` withholds ``effects[i % len(effects)]`` (an ID of
    :data:`EFFECT_TYPES` or None; default: each in turn, then none) and depends on ``seed``, ``i`` and that alone.

    ``resume``: keep the cases ``out/cases.jsonl`` already holds (same seed and settings) and run only the others;
    a case depends on ``seed`` and its index alone, so the scores are those of an uninterrupted run.

    Raises InputError before any work for a ``n_cases`` below 1, a negative seed, bad settings, an ``out`` that
    is an existing file, a ``cases.jsonl`` there that already holds cases (without ``resume``) or holds cases of
    another seed or settings (with it). Call it under ``if __name__ == "__main__":`` in scripts: the diagnosis
    starts processes."""

    if isinstance(n_cases, bool) or not isinstance(n_cases, int | np.integer) or not 1 <= n_cases <= MAX_CASES:
        raise InputError(f"--cases: expected an integer from 1 to {MAX_CASES}, got {n_cases!r}")
    seed = check_seed(seed, "--seed")
    settings.check()
    unknown = [effect for effect in effects if effect is not None and effect not in EFFECT_TYPES]
    if not effects or unknown:
        raise InputError(f"effects: expected IDs of {', '.join(EFFECT_TYPES)} or None, got {list(effects)!r}")
    out = Path(out)
    created = new_output_folders(out, "--out")
    log = out / "cases.jsonl"
    if not resume and log.exists() and log.read_text().strip():
        raise InputError(f"--out: {log} already holds cases; pass --resume to continue, or choose another folder")
    recorded = _run_settings(settings)
    finished = [row for row in finished_rows(log, seed) if row["case"] < n_cases] if resume else []
    for row in finished:
        if row.get("settings") != recorded:
            raise InputError(
                f"--out: {log}: case {row['case']} was run with the settings {row.get('settings')}, not {recorded}; "
                "resume with those or choose another folder"
            )
    log_is_new = not log.exists()
    out.mkdir(parents=True, exist_ok=True)
    log.write_text("".join(json_text(row) + "\n" for row in finished))
    command = command or f"run_compensation_benchmark({n_cases}, {seed}, {str(out)!r})"
    start = time.perf_counter()
    generation, diagnosis = np.random.SeedSequence(seed).spawn(2)
    rngs = [np.random.default_rng(s) for s in generation.spawn(int(n_cases))]
    diagnosis_seeds = [int(s.generate_state(1)[0]) for s in diagnosis.spawn(int(n_cases))]
    rows: list[dict[str, Any]] = list(finished)
    pending = sorted(set(range(int(n_cases))) - {row["case"] for row in finished})
    unfinished: Path | None = None  # the folder of the case under way, when this run made it
    try:
        for index in tqdm(
            pending, desc="compensation benchmark", disable=not progress, total=int(n_cases), initial=len(rows)
        ):
            case = _draw_case(index, effects[index % len(effects)], rngs[index], diagnosis_seeds[index], settings)
            case_folder = out / f"case_{index:03d}"
            unfinished = None if case_folder.exists() else case_folder
            row = run_case(case, settings, case_folder)
            row.update(**case_scores(row["scores"], row.get("estimate")), seed=seed, settings=recorded)
            rows.append(row)
            with log.open("a") as handle:
                handle.write(json_text(row) + "\n")
    except BaseException:  # errors, Ctrl-C, SIGTERM: the finished cases stay; before the first, what the run made goes
        if unfinished is not None:
            shutil.rmtree(unfinished, ignore_errors=True)
        if not rows and created:
            shutil.rmtree(created[-1], ignore_errors=True)
        elif not rows and log_is_new:
            log.unlink(missing_ok=True)
        raise
    rows.sort(key=lambda row: row["case"])
    summary = summarise(rows)
    seconds = time.perf_counter() - start
    document = {"command": command, "seconds": seconds, "settings": dataclasses.asdict(settings), "summary": summary}
    write_text(out / "benchmark.json", json_text({**document, "cases": rows}, indent=1))
    write_text(out / "benchmark.md", markdown_report(summary, rows, command, seconds))
    return summary


def _run_settings(settings: BenchmarkSettings) -> dict[str, Any]:
    """The settings a case's scores depend on, as its row records them (the number of workers is left out: the
    diagnosis is the same for any)."""
    return json.loads(json_text({k: v for k, v in dataclasses.asdict(settings).items() if k != "workers"}))


def _run(args: argparse.Namespace) -> None:
    settings = BenchmarkSettings(
        args.frame_size,
        args.palpation_frames,
        args.sweep_frames,
        workers=args.workers,
        follow_up=not args.no_follow_up,
    )
    summary = run_compensation_benchmark(
        args.cases, args.seed, args.out, settings=settings, command=args.command_line, resume=args.resume
    )
    for effect, entry in summary["effects"].items():
        share = entry["recovered"]["dice"]
        print(
            f"{effect}: {entry['cases']} cases, {entry['costly']} costly; cost {_number(entry['cost']['dice'])} Dice; "
            f"recovered {_share(share)} of the Dice"
        )
    print(f"wrote {Path(args.out) / 'benchmark.md'}, benchmark.json and cases.jsonl")


#: The argparse types of the integer options, with the ranges run_compensation_benchmark checks.
_SETTINGS = {
    name: Number(name, low, high, integer=True).argument()
    for name, low, high in (("cases", 1, MAX_CASES), *SETTING_RANGES)
}


def add_compensation_benchmark_command(commands: argparse._SubParsersAction) -> None:
    """``usdeform compensation-benchmark --cases N --seed S --out DIR``."""
    parser = commands.add_parser(
        "compensation-benchmark",
        help="measure what a recording effect costs the corrected volume and what --compensate gives back",
        description="Simulate palpations and a sweep with a withheld recording effect (image latency, force-sensor "
        "error, viscoelasticity, sound speed; every fifth case none), diagnose the palpations blind, and score the "
        "corrected sweep against the zero-force truth with the effect, compensated by the diagnosis, compensated "
        "with the true parameters and without the effect.",
    )
    parser.add_argument("--cases", type=_SETTINGS["cases"], default=5, help="number of cases (default 5)")
    parser.add_argument(
        "--seed",
        type=NUMBERS["diagnosis_seed"].argument(),
        default=0,
        help="seed of the cases and the diagnoses (default 0)",
    )
    parser.add_argument("--out", type=Path, required=True, help="output folder (benchmark.md, benchmark.json, ...)")
    parser.add_argument(
        "--frame-size", type=_SETTINGS["frame_size"], default=128, metavar="PX", help="frame rows and columns (128)"
    )
    parser.add_argument(
        "--palpation-frames",
        type=_SETTINGS["palpation_frames"],
        default=60,
        metavar="N",
        help="frames per palpation (60)",
    )
    parser.add_argument(
        "--sweep-frames", type=_SETTINGS["sweep_frames"], default=40, metavar="N", help="frames of the sweep (40)"
    )
    parser.add_argument(
        "--workers", type=_SETTINGS["workers"], default=1, help="processes of each diagnosis (default 1)"
    )
    parser.add_argument(
        "--no-follow-up", action="store_true", help="compensate from the first diagnosis, without its record_next.json"
    )
    parser.add_argument(
        "--resume", action="store_true", help="keep the cases DIR/cases.jsonl holds (same --seed) and run the others"
    )
    parser.set_defaults(run=_run)
