"""Command-line commands ``usdeform diagnose`` and ``usdeform gap-benchmark`` (wired into cli.py by the coordinator)."""

from __future__ import annotations

import argparse

from ..options import NUMBERS, Number

__all__ = ["add_diagnose_command", "add_gap_benchmark_command"]


def _diagnose(args: argparse.Namespace) -> None:
    from .._files import check_output_folder
    from .diagnosis import check_seed, diagnose
    from .report import write_report

    check_seed(args.seed, "--seed")
    check_output_folder(args.out, "--out")
    recordings = list(args.recordings)
    if args.follow_up is not None:
        from .follow_up import first_recordings

        recordings = [*first_recordings(args.follow_up), *recordings]
    diagnosis = diagnose(recordings, config=args.config, seed=args.seed, reference_depth_mm=args.reference_depth_mm)
    out = write_report(diagnosis, args.out)
    print(f"{diagnosis.verdict}: {diagnosis.summary}")
    if diagnosis.compensation.get("summary"):
        print(diagnosis.compensation["summary"])
    asked = f"; record next: {len(diagnosis.follow_up)} recordings" if diagnosis.follow_up else ""
    print(f"wrote {out / 'diagnosis.json'}, {out / 'record_next.json'} and {out / 'report.html'}{asked}")


def _gap_benchmark(args: argparse.Namespace) -> None:
    from .benchmark import run_benchmark

    summary = run_benchmark(
        args.cases,
        args.seed,
        args.out,
        command=args.command_line,
        resume=args.resume,
        follow_up_round=not args.no_follow_up,
    )
    top1 = summary["top1_identification"][0]  # type: ignore[index]
    loop = summary.get("loop")
    after = f", {loop['top1'][1][0]} after the follow-up" if isinstance(loop, dict) else ""
    print(f"{summary['cases']} cases; top-1 identification {top1}{after}; see {args.out}/benchmark.md")


def add_diagnose_command(commands) -> None:
    """``usdeform diagnose RECORDING... --out DIR``: sim-to-real gap diagnosis of palpation recordings."""
    parser = commands.add_parser(
        "diagnose", help="diagnose the sim-to-real gap of PLUS palpation recordings (diagnosis.json, report.html)"
    )
    parser.add_argument("recordings", nargs="+", help="PLUS sequence files (.mha / .seq.nrrd) of palpations")
    parser.add_argument(
        "--out", "--output", dest="out", required=True, help="output directory (diagnosis.json, record_next.json)"
    )
    parser.add_argument(
        "--follow-up",
        metavar="DIR",
        help="a first diagnosis's folder: its recordings (DIR/diagnosis.json) are diagnosed with those given",
    )
    parser.add_argument(
        "--config", help="PLUS XML configuration with the Image -> Probe calibration, for files that do not carry it"
    )
    parser.add_argument(
        "--seed", type=NUMBERS["diagnosis_seed"].argument(), default=0, help="seed of the bootstrap (default 0)"
    )
    parser.add_argument(
        "--reference-depth-mm",
        metavar="MM",
        type=Number("reference_depth_mm", 1.0, 300.0).argument(),
        help="depth (mm below the unloaded surface) of a reflector fixed in the world under every palpation; a "
        "recording's ReferenceTargetDepth header key gives it for that recording",
    )
    parser.set_defaults(run=_diagnose)


def add_gap_benchmark_command(commands) -> None:
    """``usdeform gap-benchmark --cases N --seed S --out DIR``: the withheld-effect benchmark."""
    parser = commands.add_parser("gap-benchmark", help="benchmark the gap diagnosis on cases with a withheld effect")
    from .benchmark import MAX_CASES

    cases = Number("cases", 1, MAX_CASES, integer=True).argument()
    parser.add_argument("--cases", type=cases, default=45, help=f"number of cases (default 45, at most {MAX_CASES})")
    parser.add_argument(
        "--seed",
        type=NUMBERS["diagnosis_seed"].argument(),
        default=0,
        help="seed of generation and diagnosis (independent streams)",
    )
    parser.add_argument("--out", required=True, help="output directory (benchmark.md, benchmark.json, cases.jsonl)")
    parser.add_argument(
        "--resume", action="store_true", help="keep the cases DIR/cases.jsonl holds (same --seed) and run the others"
    )
    parser.add_argument(
        "--no-follow-up",
        action="store_true",
        help="score the first diagnosis only, without recording what its record_next.json asks for",
    )
    parser.set_defaults(run=_gap_benchmark)
