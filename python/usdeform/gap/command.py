"""Command-line commands ``usdeform diagnose`` and ``usdeform gap-benchmark`` (wired into cli.py by the coordinator)."""

from __future__ import annotations

import argparse

__all__ = ["add_diagnose_command", "add_gap_benchmark_command"]


def _diagnose(args: argparse.Namespace) -> None:
    from .._files import check_output_folder
    from .diagnosis import check_seed, diagnose
    from .report import write_report

    check_seed(args.seed, "--seed")
    check_output_folder(args.out, "--out")
    diagnosis = diagnose(args.recordings, config=args.config, seed=args.seed)
    out = write_report(diagnosis, args.out)
    print(f"{diagnosis.verdict}: {diagnosis.summary}")
    if diagnosis.compensation.get("summary"):
        print(diagnosis.compensation["summary"])
    print(f"wrote {out / 'diagnosis.json'} and {out / 'report.html'}")


def _gap_benchmark(args: argparse.Namespace) -> None:
    from .benchmark import run_benchmark

    summary = run_benchmark(args.cases, args.seed, args.out, command=args.command_line, resume=args.resume)
    top1 = summary["top1_identification"][0]  # type: ignore[index]
    print(f"{summary['cases']} cases; top-1 identification {top1}; see {args.out}/benchmark.md")


def add_diagnose_command(commands) -> None:
    """``usdeform diagnose RECORDING... --out DIR``: sim-to-real gap diagnosis of palpation recordings."""
    parser = commands.add_parser(
        "diagnose", help="diagnose the sim-to-real gap of PLUS palpation recordings (diagnosis.json, report.html)"
    )
    parser.add_argument("recordings", nargs="+", help="PLUS sequence files (.mha / .seq.nrrd) of palpations")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument(
        "--config", help="PLUS XML configuration with the Image -> Probe calibration, for files that do not carry it"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the bootstrap (default 0)")
    parser.set_defaults(run=_diagnose)


def add_gap_benchmark_command(commands) -> None:
    """``usdeform gap-benchmark --cases N --seed S --out DIR``: the withheld-effect benchmark."""
    parser = commands.add_parser("gap-benchmark", help="benchmark the gap diagnosis on cases with a withheld effect")
    parser.add_argument("--cases", type=int, default=45, help="number of cases (default 45)")
    parser.add_argument("--seed", type=int, default=0, help="seed of generation and diagnosis (independent streams)")
    parser.add_argument("--out", required=True, help="output directory (benchmark.md, benchmark.json, cases.jsonl)")
    parser.add_argument(
        "--resume", action="store_true", help="keep the cases DIR/cases.jsonl holds (same --seed) and run the others"
    )
    parser.set_defaults(run=_gap_benchmark)
