"""The follow-up round of the gap benchmark: what round 0's record_next.json asks for, recorded on the simulator
with the case's phantom, position, hidden effects, scanner and force loop (:class:`~usdeform.gap.benchmark.CaseSetup`),
and the verdict on all of a case's recordings (round 1, at most one follow-up round), scored as round 0 is.

Round 1 of a case whose round 0 asks for nothing is round 0. Scores per round: top-1 identification of the single
effects, false attributions (a verdict that attributes, :data:`~usdeform.gap.benchmark_scoring.ATTRIBUTING`, on a
null or out-of-library case, or naming only effects that were not hidden), recordings, palpations and seconds of
recording added per case (median, max), and round 1's confusion matrix.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..io import write_sequence
from .benchmark_scoring import ATTRIBUTING, BenchmarkCase, confusion, score_case
from .follow_up import PALPATION_KINDS, FollowUpRecording, write_record_next
from .follow_up_sim import FollowUpSettings, simulate_follow_up

__all__ = ["false_attribution", "loop_markdown", "loop_summary", "record_case_follow_up", "round_one_row"]


def record_case_follow_up(
    entries: Sequence[FollowUpRecording], setup: Any, directory: Path, seed: int
) -> tuple[list[Path], dict[str, Any]]:
    """Record ``entries`` for a case (``setup``: its :class:`~usdeform.gap.benchmark.CaseSetup`) into
    ``directory``; returns the files and what was added (recordings, palpations, seconds, kinds not recorded)."""
    settings = FollowUpSettings(
        frames_per_s=setup.frames_per_s,
        settings=setup.settings,
        acoustics=setup.acoustics,
        controller=setup.controller,
        seed=seed,
    )
    directory.mkdir(parents=True, exist_ok=True)
    write_record_next(directory / "record_next.json", entries)
    paths, seconds, palpations, missing = [], 0.0, 0, []
    for item in simulate_follow_up(entries, setup.phantom, setup.effects, settings):
        if item.recording is None:
            missing.append(item.entry.kind)
            continue
        path = directory / f"{item.entry.name}.seq.nrrd"
        write_sequence(path, setup.apply(item.recording), frame_series=item.frame_series)
        paths.append(path)
        seconds += item.duration_s
        palpations += item.entry.kind in PALPATION_KINDS
    added = {
        "asked": [entry.kind for entry in entries],
        "recordings": len(paths),
        "palpations": palpations,
        "seconds": seconds,
        "not_recorded": missing,
    }
    return paths, added


def round_one_row(case: BenchmarkCase, result: dict, duration_s: float) -> dict[str, Any]:
    """The scores of round 1 (the fields :func:`score_case` gives that differ between rounds)."""
    row = score_case(case, result, duration_s)
    keys = ("verdict", "named", "top", "top_shrink", "identified", "flagged_undetectable", "false_attribution")
    return {key: row[key] for key in (*keys, "flagged_unexplained", "magnitude_error") if key in row}


def false_attribution(row: dict) -> bool | None:
    """Whether a verdict attributes the gap wrongly: on a null or out-of-library case at all, on a single effect
    naming only effects that were not hidden (None for pairs)."""
    if row["kind"] == "pair":
        return None
    if row["verdict"] not in ATTRIBUTING:
        return False
    if row["kind"] in ("null", "out_of_library"):
        return True
    hidden = set(str(row["hidden"]).split("+"))
    return not any(hidden & set(name.split("+")) for name in row.get("named", []))


def _rate(values: list[bool]) -> tuple[float | None, int]:
    return (float(np.mean(values)) if values else None, len(values))


def _spread(values: list[float]) -> tuple[float | None, float | None]:
    return (float(np.median(values)), float(np.max(values))) if values else (None, None)


def loop_summary(rows: list[dict]) -> dict[str, Any]:
    """Both rounds' top-1 and false attributions, the follow-up's cost per case, round 1's confusion matrix."""
    rounds = [rows, [{**row, **row.get("round1", {})} for row in rows]]
    singles = [[row for row in chosen if row["kind"] == "single"] for chosen in rounds]
    added = [row.get("follow_up", {}) for row in rows]
    not_recorded: dict[str, int] = {}
    for item in added:
        for kind in item.get("not_recorded", []):
            not_recorded[kind] = not_recorded.get(kind, 0) + 1
    flags = [[false_attribution(row) for row in chosen] for chosen in rounds]
    return {
        "top1": [_rate([bool(row.get("identified")) for row in chosen]) for chosen in singles],
        "false_attribution": [_rate([flag for flag in chosen if flag is not None]) for chosen in flags],
        "cases_followed_up": sum(bool(item.get("asked")) for item in added),
        "recordings_added": _spread([float(item.get("recordings", 0)) for item in added]),
        "palpations_added": _spread([float(item.get("palpations", 0)) for item in added]),
        "seconds_added": _spread([float(item.get("seconds", 0.0)) for item in added]),
        "not_recorded": not_recorded,
        "round1_s": _spread([float(row.get("round1_s", 0.0)) for row in rows]),
        "confusion_round1": confusion(rounds[1]),
    }


def loop_markdown(loop: dict[str, Any]) -> str:
    """The loop's table and round 1's confusion matrix, in markdown."""

    def rate(value: tuple[float | None, int]) -> str:
        return "n/a" if value[0] is None else f"{100 * value[0]:.0f} % (of {value[1]})"

    def spread(value: tuple[float | None, float | None]) -> str:
        return "n/a" if value[0] is None else f"{value[0]:.3g} / {value[1]:.3g}"

    missing = ", ".join(f"{kind} x{count}" for kind, count in loop["not_recorded"].items()) or "none"
    lines = [
        "",
        "## The follow-up loop (round 0: the first recording; round 1: plus what its record_next.json asked for)",
        "",
        "| measure | round 0 | round 1 |",
        "|---|---|---|",
        f"| top-1 identification (single effects) | {rate(loop['top1'][0])} | {rate(loop['top1'][1])} |",
        f"| false attribution (nulls, out of library, wrong single) | {rate(loop['false_attribution'][0])} | "
        f"{rate(loop['false_attribution'][1])} |",
        "",
        "| follow-up per case | median / max |",
        "|---|---|",
        f"| cases followed up | {loop['cases_followed_up']} |",
        f"| recordings added | {spread(loop['recordings_added'])} |",
        f"| palpations added | {spread(loop['palpations_added'])} |",
        f"| seconds of recording added | {spread(loop['seconds_added'])} |",
        f"| round-1 time (recording and diagnosis), s | {spread(loop['round1_s'])} |",
        f"| asked for but not recorded (the simulator cannot) | {missing} |",
        "",
        "Confusion matrix after round 1:",
        "",
        "| hidden effect | named | verdict | cases |",
        "|---|---|---|---|",
    ]
    lines += [f"| {r['hidden']} | {r['named']} | {r['verdict']} | {r['cases']} |" for r in loop["confusion_round1"]]
    return "\n".join(lines) + "\n"


def write_round(directory: Path, name: str, result: dict) -> None:
    """A round's diagnosis.json of a case."""
    from .report import write_text

    write_text(directory / name, json.dumps(result, indent=1))
