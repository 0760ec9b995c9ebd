"""The compensation benchmark's scores: a case's cost and recovered shares, the summary per effect, the tables."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from ..compensation import MIN_AREA_COST_PCT, MIN_DICE_COST
from .cases import _SIGN, CONDITIONS, EFFECT_TYPES, MAX_WORSENING_DICE, METRICS, SHARE_THRESHOLDS

__all__ = ["COST_ESTIMATE_FACTOR", "case_scores", "estimated_cost", "json_text", "markdown_report", "summarise"]

#: The diagnosis's estimate of an effect's cost counts as right within this factor of the cost measured on the sweep.
COST_ESTIMATE_FACTOR = 1.5


def estimated_cost(estimate: list[dict[str, Any]]) -> dict[str, float | None]:
    """The diagnosis's own estimate of what its effect costs the correction (diagnosis.json's
    ``compensation.recordings``): the mean over its recordings of compensated minus uncompensated Dice, and of the
    uncompensated minus the compensated size of the area error (% points); None where no recording was scored."""
    keys = ("dice_uncompensated", "dice_compensated", "area_error_pct_uncompensated", "area_error_pct_compensated")
    scored = [row for row in estimate if all(isinstance(row.get(key), int | float) for key in keys)]
    if not scored:
        return dict.fromkeys(("dice", "area_error_pct"))
    return {
        "dice": float(np.mean([row["dice_compensated"] - row["dice_uncompensated"] for row in scored])),
        "area_error_pct": float(
            np.mean(
                [abs(row["area_error_pct_uncompensated"]) - abs(row["area_error_pct_compensated"]) for row in scored]
            )
        ),
    }


def _estimate_within(estimated: float | None, measured: float) -> bool | None:
    """Whether ``estimated`` is within :data:`COST_ESTIMATE_FACTOR` of ``measured`` (None: no estimate)."""
    if estimated is None or not math.isfinite(measured) or measured <= 0:
        return None
    return bool(measured / COST_ESTIMATE_FACTOR <= estimated <= measured * COST_ESTIMATE_FACTOR)


def case_scores(scores: dict[str, dict[str, Any]], estimate: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """A case's cost of the effect per metric (goodness(d) - goodness(a), module docstring), the shares the
    diagnosed (``recovered``), true (``recovered_true``) and forced diagnosed (``recovered_forced``) compensations
    recover (None where the metric costs nothing), whether it is costly, and whether the diagnosed compensation
    (``worse``) or the forced one (``worse_forced``) made Dice worse by more than :data:`MAX_WORSENING_DICE`.
    ``estimate``: the diagnosis's per-recording compensation scores; ``estimated_cost`` is what they say the effect
    costs (:func:`estimated_cost`) and ``estimate_within`` whether that is within :data:`COST_ESTIMATE_FACTOR` of the
    measured cost, per metric (None where the metric costs less than its threshold or there is no estimate)."""
    good = {c: {m: _SIGN[m] * scores[c][m] for m in METRICS} for c in CONDITIONS}
    cost = {m: good["d"][m] - good["a"][m] for m in METRICS}

    def share(condition: str) -> dict[str, float | None]:
        return {
            m: (good[condition][m] - good["a"][m]) / cost[m] if math.isfinite(cost[m]) and cost[m] != 0 else None
            for m in METRICS
        }

    estimated = estimated_cost(estimate or [])
    thresholds = {"dice": MIN_DICE_COST, "area_error_pct": MIN_AREA_COST_PCT}
    return {
        "cost": cost,
        "estimated_cost": estimated,
        "estimate_within": {
            m: _estimate_within(estimated[m], cost[m]) if cost[m] >= threshold else None
            for m, threshold in thresholds.items()
        },
        "recovered": share("b"),
        "recovered_true": share("c"),
        "recovered_forced": share("e"),
        "costly": bool(cost["dice"] >= MIN_DICE_COST or cost["area_error_pct"] >= MIN_AREA_COST_PCT),
        "worse": bool(scores["b"]["dice"] < scores["a"]["dice"] - MAX_WORSENING_DICE),
        "worse_forced": bool(scores["e"]["dice"] < scores["a"]["dice"] - MAX_WORSENING_DICE),
    }


def _median(values: list[float]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.median(finite)) if finite else None


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per effect type (and ``none``): cases, costly cases, the median cost per metric over all its cases, the
    median recovered shares (diagnosed and true) over the costly cases (module docstring), refusals and cases made
    worse; for null cases, how many came out unchanged bit for bit."""
    summary: dict[str, Any] = {"cases": len(rows), "effects": {}}
    for effect in (*EFFECT_TYPES, "none"):
        chosen = [row for row in rows if row["effect"] == effect]
        if not chosen:
            continue
        costly = [row for row in chosen if row["costly"]]
        entry: dict[str, Any] = {
            "cases": len(chosen),
            "costly": len(costly),
            "cost": {m: _median([row["cost"][m] for row in chosen]) for m in METRICS},
            "refused": sum(row["compensation"] == "refused" for row in chosen),
            "worse": sum(row["worse"] for row in chosen),
            "worse_forced": sum(row["worse_forced"] for row in chosen),
            "estimate_within": {
                m: [sum(row.get("estimate_within", {}).get(m) is v for row in chosen) for v in (True, False)]
                for m in ("dice", "area_error_pct")
            },
        }
        for key in ("recovered", "recovered_true", "recovered_forced"):
            entry[key] = {
                m: _median([row[key][m] for row in costly if row["cost"][m] >= SHARE_THRESHOLDS[m]]) for m in METRICS
            }
        if effect == "none":
            entry["unchanged"] = {c: sum(row.get("unchanged", {}).get(c, False) for row in chosen) for c in ("b", "c")}
        summary["effects"][effect] = entry
    return summary


def _number(value: float | None, digits: int = 3) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _within(counts: list[int]) -> str:
    """``k of n``: the cases whose estimate is within the factor, of those with an estimate and a cost."""
    return "-" if not sum(counts) else f"{counts[0]} of {sum(counts)}"


def _share(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.0f} %"


def markdown_report(summary: dict[str, Any], rows: list[dict[str, Any]], command: str, seconds: float) -> str:
    """``benchmark.md``: the table per effect type, the null check and the table per case."""
    lines = [
        "# Compensation benchmark",
        "",
        f"`{command}`: {summary['cases']} cases in {seconds / 60:.1f} min.",
        "",
        "Cost: the effect's median cost (no effect minus effect) in Dice, area error (% points) and centre-line "
        "depth error (mm), over all cases. Recovered: median share ((b) - (a)) / ((d) - (a)) over the cases where "
        f"the effect costs >= {MIN_DICE_COST} Dice or {MIN_AREA_COST_PCT:g} % area (and that metric's own threshold), "
        "with the diagnosis's fitted effect (b), with the true parameters (c) and with the diagnosis's fitted effect "
        "forced whatever its verdict (e).",
        "",
        f"Estimate within {COST_ESTIMATE_FACTOR:g}x: of the cases whose effect costs at least the threshold in Dice "
        "(area), how many the diagnosis's own estimate of that cost (its compensation entry) puts within a factor "
        f"{COST_ESTIMATE_FACTOR:g} of the cost measured on the sweep.",
        "",
        "| effect | cases | costly | cost Dice | cost area % | cost depth mm | recovered Dice / area / depth (b) "
        f"| with true parameters (c) | forced (e) | refused | worse by > {MAX_WORSENING_DICE} Dice (b / e) "
        f"| estimate within {COST_ESTIMATE_FACTOR:g}x, Dice / area |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for effect, entry in summary["effects"].items():
        cost = entry["cost"]
        shares = [
            " / ".join(_share(entry[key][m]) for m in METRICS)
            for key in ("recovered", "recovered_true", "recovered_forced")
        ]
        lines.append(
            f"| {effect} | {entry['cases']} | {entry['costly']} | {_number(cost['dice'])} | "
            f"{_number(cost['area_error_pct'], 1)} | {_number(cost['depth_error_mm'], 2)} | {shares[0]} | "
            f"{shares[1]} | {shares[2]} | {entry['refused']} | {entry['worse']} / {entry['worse_forced']} | "
            f"{_within(entry['estimate_within']['dice'])} / {_within(entry['estimate_within']['area_error_pct'])} |"
        )
    null = summary["effects"].get("none")
    if null:
        lines += [
            "",
            f"Null cases unchanged bit for bit when compensated: {null['unchanged']['b']} of {null['cases']} with the "
            f"diagnosis (a refused compensation counts as unchanged), {null['unchanged']['c']} of {null['cases']} "
            "with the (empty) true compensation.",
        ]
    added = [row["follow_up"] for row in rows if row.get("follow_up")]
    if added:
        recordings = [float(item["recordings"]) for item in added]
        recording_seconds = [float(item["seconds"]) for item in added]
        lines += [
            "",
            f"Follow-up (round 1): {len(added)} of {len(rows)} cases; recordings added median "
            f"{np.median(recordings):.3g}, max {max(recordings):.3g}; seconds of recording median "
            f"{np.median(recording_seconds):.3g}, max {max(recording_seconds):.3g}. "
            "A verdict 'A -> B' is round 0's, then round 1's.",
        ]
    lines += [
        "",
        "## Cases",
        "",
        "Dice, area error % and depth error mm under (a) effect / (b) diagnosed / (c) true / (d) no effect / "
        "(e) diagnosed, forced.",
        "",
        "| case | effect | parameters | verdict | compensation | Dice | area % | depth mm | s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        parameters = ", ".join(f"{k} {v:.3g}" for k, v in row["parameters"].items()) or "-"
        values = {
            m: " / ".join(_number(row["scores"][c][m], 3 if m == "dice" else 2) for c in CONDITIONS) for m in METRICS
        }
        errors = [f"{c}: {row['scores'][c]['error']}" for c in CONDITIONS if row["scores"][c].get("error")]
        compensation = row["compensation"] + (f" ({', '.join(row['named'])})" if row["named"] else "")
        lines.append(
            f"| {row['case']} | {row['effect']} | {parameters} | {_verdicts(row)} | {compensation} | "
            f"{values['dice']} | {values['area_error_pct']} | {values['depth_error_mm']} | {row['total_s']:.0f} |"
            + ("" if not errors else " " + "; ".join(errors))
        )
    return "\n".join(lines) + "\n"


def json_text(value: Any, indent: int | None = None) -> str:
    """Strict JSON: NumPy scalars as numbers, NaN (a metric of a refused fit) as null."""

    def plain(item: Any) -> Any:
        if isinstance(item, dict):
            return {key: plain(entry) for key, entry in item.items()}
        if isinstance(item, list | tuple):
            return [plain(entry) for entry in item]
        if isinstance(item, np.integer | np.floating):
            item = item.item()
        return None if isinstance(item, float) and not math.isfinite(item) else item

    return json.dumps(plain(value), indent=indent, allow_nan=False)


def _verdicts(row: dict[str, Any]) -> str:
    """The case's verdict, preceded by round 0's where a follow-up round changed it."""
    first = row.get("verdict_round0", row["verdict"])
    return row["verdict"] if first == row["verdict"] else f"{first} -> {row['verdict']}"
