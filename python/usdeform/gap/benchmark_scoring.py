"""Scoring of the gap benchmark (:mod:`usdeform.gap.benchmark`): each case's verdict against what was hidden
(:func:`score_case`), the summary over cases with the confusion matrix, and its markdown table."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

__all__ = [
    "ATTRIBUTING",
    "BenchmarkCase",
    "CaseKind",
    "confusion",
    "fitted_magnitude",
    "markdown_summary",
    "score_case",
    "summarise",
]

CaseKind = Literal["single", "null", "pair", "out_of_library"]


@dataclass
class BenchmarkCase:
    """One generated case: what was hidden (never shown to the diagnosis) and where its file is."""

    index: int
    kind: CaseKind
    hidden: list[str]
    parameters: dict[str, dict[str, float]]
    magnitudes: dict[str, float]
    path: Path
    generation_s: float
    duration_s: float


def fitted_magnitude(effect: str, parameters: dict[str, float], duration_s: float) -> float:
    """The diagnosis's fitted parameters reduced to the scalar magnitude of ``draw_effect``."""
    if effect in ("image_latency", "force_latency"):
        return abs(parameters["delay_s"])
    if effect == "force_sensor_error":
        times = np.linspace(0, duration_s, 200)
        return float(np.sqrt(np.mean((parameters["offset_n"] + parameters["drift_n_per_s"] * times) ** 2)))
    if effect == "viscoelasticity":
        return parameters["g"]
    if effect == "sound_speed_mismatch":
        return abs(parameters["error_m_s"])
    if effect == "probe_tilt":
        return abs(parameters["tilt_deg"])
    if effect == "out_of_plane_motion":
        return parameters["shift_mm_per_mm"]
    if effect == "layered_tissue":
        return parameters["thickness_mm"]
    if effect == "lumen_pressure":
        return parameters["pressure_kpa"]
    if effect == "sliding_contact":
        return parameters["slip_fraction"]
    return float("nan")


ATTRIBUTING = ("explained", "explained_in_part", "ambiguous")  # verdicts that name an effect as the cause


def _named(diagnosis_json: dict) -> list[str]:
    """The effects the verdict names (rows of diagnoses written before ``named`` existed: the top when explained)."""
    if "named" in diagnosis_json:
        return list(diagnosis_json["named"])
    effects = diagnosis_json["effects"]
    return [effects[0]["effect"]] if effects and diagnosis_json["verdict"] == "explained" else []


def score_case(case: BenchmarkCase, diagnosis_json: dict, duration_s: float) -> dict[str, object]:
    """Per-case outcome: verdict, the effects it names, top candidate, identification, magnitude error, shrink,
    and (single effects) whether the diagnosis flagged the hidden effect as one the recording could not reveal.

    Identified: a verdict that attributes (:data:`ATTRIBUTING`) naming the hidden effect (an ambiguous verdict
    names two, and counts when one of them is the hidden effect); a fit at the edge of the library attributes
    nothing, so on an out-of-library case it counts as flagged, like "unexplained"."""
    effects = diagnosis_json["effects"]
    top = effects[0]["effect"] if effects else None
    verdict = diagnosis_json["verdict"]
    named = _named(diagnosis_json)
    attributes = verdict in ATTRIBUTING
    row: dict[str, object] = {
        "case": case.index,
        "kind": case.kind,
        "hidden": "+".join(case.hidden),
        "hidden_parameters": case.parameters,
        "verdict": verdict,
        "named": named,
        "top": top,
        "top_shrink": effects[0]["shrink"] if effects else None,
        "generation_s": case.generation_s,
    }
    if case.kind == "single":
        truth = case.hidden[0]
        row["identified"] = attributes and truth in named
        entry = next((e for e in effects if e["effect"] == truth), None)
        magnitude = case.magnitudes[truth]
        if entry is not None and np.isfinite(magnitude):
            fitted = fitted_magnitude(truth, entry["parameters"], duration_s)
            row["fitted_magnitude"] = fitted
            row["true_magnitude"] = magnitude
            row["magnitude_error"] = abs(fitted - magnitude) / abs(magnitude)
        row["shrink_of_true"] = entry["shrink"] if entry is not None else None
        row["flagged_undetectable"] = truth in diagnosis_json.get("undetectable", [])  # absent when diagnosis failed
    elif case.kind == "pair":
        sets = [set(name.split("+")) for name in named]
        row["identified"] = attributes and set(case.hidden) in sets
        row["one_identified"] = attributes and any(chosen & set(case.hidden) for chosen in sets)
    elif case.kind == "null":
        row["false_attribution"] = attributes
    else:
        row["flagged_unexplained"] = verdict in ("unexplained", "at_edge_of_library")
    return row


def confusion(rows: list[dict]) -> list[dict[str, object]]:
    """The confusion matrix: cases counted by hidden effect ("none" for nulls) x effects named (" or " between the
    two of an ambiguous verdict, "-" for none) x verdict, sorted by hidden effect then count."""
    counts: dict[tuple[str, str, str], int] = {}
    for row in rows:
        named = " or ".join(row.get("named") or []) or "-"
        key = (str(row["hidden"] or "none"), named, str(row["verdict"]))
        counts[key] = counts.get(key, 0) + 1
    return [
        {"hidden": hidden, "named": named, "verdict": verdict, "cases": count}
        for (hidden, named, verdict), count in sorted(counts.items(), key=lambda item: (item[0][0], -item[1]))
    ]


def summarise(rows: list[dict]) -> dict[str, object]:
    """Benchmark table values from the per-case rows."""

    def rate(values):
        values = [bool(v) for v in values]
        return (float(np.mean(values)) if values else None, len(values))

    singles = [r for r in rows if r["kind"] == "single"]
    errors = [r["magnitude_error"] for r in singles if "magnitude_error" in r]
    shrinks = [r["top_shrink"] for r in rows if r["kind"] in ("single", "pair") and r["top_shrink"] is not None]
    per_effect = {}
    for effect in sorted({r["hidden"] for r in singles}):
        chosen = [r for r in singles if r["hidden"] == effect]
        per_effect[effect] = {
            "identified": rate(r["identified"] for r in chosen)[0],
            "cases": len(chosen),
            "median_magnitude_error": float(np.median([r["magnitude_error"] for r in chosen if "magnitude_error" in r]))
            if any("magnitude_error" in r for r in chosen)
            else None,
            "tops": [f"{r['top']} ({r['verdict']})" for r in chosen],  # top is None when the diagnosis failed
        }
    times = [r["total_s"] for r in rows]
    diagnosis_times = [r["diagnosis_s"] for r in rows]
    return {
        "cases": len(rows),
        "top1_identification": rate(r["identified"] for r in singles),
        # misses apart: a hidden effect that leaves no gap a palpation shows, or a gap blamed on the wrong effect
        "single_no_significant_gap": rate(r["verdict"] == "no_significant_gap" for r in singles),
        "top1_where_gap_seen": rate(r["identified"] for r in singles if r["verdict"] != "no_significant_gap"),
        # the diagnosis's own power check: the hidden effect could not show in that recording at any realistic size
        "single_flagged_undetectable": rate(r["flagged_undetectable"] for r in singles),
        "top1_where_detectable": rate(r["identified"] for r in singles if not r["flagged_undetectable"]),
        # the hidden effect named, but fitted at an edge of the library: no clean explanation, not counted above
        "single_named_at_edge": rate(
            r["verdict"] == "at_edge_of_library" and r["hidden"] in r.get("named", []) for r in singles
        ),
        "pair_identification": rate(r["identified"] for r in rows if r["kind"] == "pair"),
        "pair_one_identified": rate(r["one_identified"] for r in rows if r["kind"] == "pair"),
        "median_magnitude_error": float(np.median(errors)) if errors else None,
        "median_heldout_shrink": float(np.median(shrinks)) if shrinks else None,
        "null_false_attribution": rate(r["false_attribution"] for r in rows if r["kind"] == "null"),
        "null_no_significant_gap": rate(r["verdict"] == "no_significant_gap" for r in rows if r["kind"] == "null"),
        "ool_flagged_unexplained": rate(r["flagged_unexplained"] for r in rows if r["kind"] == "out_of_library"),
        "median_case_s": float(np.median(times)) if times else None,
        "max_case_s": float(np.max(times)) if times else None,
        "median_diagnosis_s": float(np.median(diagnosis_times)) if diagnosis_times else None,
        "per_effect": per_effect,
        "confusion": confusion(rows),
    }


def markdown_summary(summary: dict[str, object], command: str) -> str:
    def fmt(value):
        if isinstance(value, tuple):
            return "n/a" if value[0] is None else f"{100 * value[0]:.0f} % (of {value[1]})"
        return "n/a" if value is None else f"{value:.3g}"

    lines = [
        "# Gap benchmark",
        "",
        f"Command: `{command}`",
        "",
        "| measure | value | target |",
        "|---|---|---|",
        f"| cases | {summary['cases']} | >= 40 |",
        f"| top-1 identification (single effects) | {fmt(summary['top1_identification'])} | >= 90 % |",
        f"| single effects called no_significant_gap | {fmt(summary['single_no_significant_gap'])} | |",
        f"| top-1 where a gap was seen (single effects) | {fmt(summary['top1_where_gap_seen'])} | |",
        f"| single effects the diagnosis flagged undetectable in their recording | "
        f"{fmt(summary['single_flagged_undetectable'])} | |",
        f"| top-1 where the hidden effect was not flagged undetectable | {fmt(summary['top1_where_detectable'])} | |",
        f"| single effects named but fitted at the edge of the library (not counted as identified) | "
        f"{fmt(summary['single_named_at_edge'])} | |",
        f"| pairs identified exactly / one of two | {fmt(summary['pair_identification'])} / "
        f"{fmt(summary['pair_one_identified'])} | |",
        f"| median fitted-magnitude error | {fmt(summary['median_magnitude_error'])} | <= 0.25 |",
        f"| median held-out gap shrink | {fmt(summary['median_heldout_shrink'])} | >= 0.70 |",
        f"| false attribution on nulls | {fmt(summary['null_false_attribution'])} | <= 10 % |",
        f"| nulls called no_significant_gap | {fmt(summary['null_no_significant_gap'])} | |",
        f"| out-of-library flagged unexplained | {fmt(summary['ool_flagged_unexplained'])} | >= 80 % |",
        f"| time per case, median / max (s) | {fmt(summary['median_case_s'])} / {fmt(summary['max_case_s'])} "
        "| <= 180 |",
        f"| diagnosis time per case, median (s) | {fmt(summary['median_diagnosis_s'])} | |",
        "",
        "| hidden effect | cases | identified | median magnitude error | top candidates (verdict) |",
        "|---|---|---|---|---|",
    ]
    per_effect: dict[str, dict] = summary["per_effect"]  # type: ignore[assignment]
    for effect, values in per_effect.items():
        lines.append(
            f"| {effect} | {values['cases']} | {fmt(values['identified'])} | {fmt(values['median_magnitude_error'])} | "
            f"{', '.join(values['tops'])} |"
        )
    lines += [
        "",
        "Confusion matrix (identified: a verdict that attributes, explained, explained_in_part or ambiguous, naming "
        "the hidden effect; ambiguous names two):",
        "",
        "| hidden effect | named | verdict | cases |",
        "|---|---|---|---|",
    ]
    confusion_rows: list[dict] = summary["confusion"]  # type: ignore[assignment]
    lines += [f"| {r['hidden']} | {r['named']} | {r['verdict']} | {r['cases']} |" for r in confusion_rows]
    return "\n".join(lines) + "\n"
