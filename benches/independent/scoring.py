"""Scoring of the diagnosis's verdicts on the independent generator's cases (diagnosis.json's ``verdict`` and
``named``) and the benchmark summary (benchmark.md)."""

from __future__ import annotations

from collections import Counter

import numpy as np

from .cases import LIBRARY_KINDS

ATTRIBUTING = ("explained", "explained_in_part", "ambiguous")
"""Verdicts that name an effect as the cause (diagnosis.json's ``named`` lists them, two when ambiguous);
``at_edge_of_library``, ``unexplained`` and ``no_significant_gap`` name none."""

CORRECT: dict[str, frozenset[str]] = {
    "image_latency": frozenset({"image_latency"}),
    "force_sensor_error": frozenset({"force_sensor_error"}),
    "viscoelasticity": frozenset({"viscoelasticity"}),
    "force_latency": frozenset({"force_latency"}),
    "force_sensor_lag": frozenset({"force_latency"}),
    "pose_latency": frozenset({"image_latency", "force_latency"}),
    "force_sensor_drift": frozenset({"force_sensor_error"}),
    "surface_inclination": frozenset({"probe_tilt"}),
    "probe_tilt": frozenset({"probe_tilt"}),
    "out_of_plane_drift": frozenset({"out_of_plane_motion"}),
    "sound_speed_mismatch": frozenset({"sound_speed_mismatch"}),
    "soft_layer": frozenset({"layered_tissue"}),
    "frictionless_contact": frozenset({"sliding_contact"}),
    "lumen_pressure": frozenset({"lumen_pressure"}),
    "image_clock_drift": frozenset({"image_latency"}),
}
"""Library effect IDs whose naming is correct for each in-library kind (equivalences in benches/gap_independent.py);
for nulls and out-of-library kinds every naming is a false attribution."""
assert set(CORRECT) == set(LIBRARY_KINDS)


def _parts(name: object) -> list[str]:
    """The effects of a named entry: one, or the two of a pair ``a+b``."""
    return str(name).split("+")


def score(kind: str, result: dict) -> dict[str, object]:
    """Verdict, named effects, top candidate; ``correct``: an attributing verdict names an entry all of whose effects
    count for the kind (one of an ambiguous verdict's two will do); ``in_pair``: a correct effect is part of a named
    entry; ``false_attribution``: a null or out-of-library case with an attributing verdict."""
    effects = result.get("effects", [])
    top = effects[0] if effects else None
    correct = CORRECT.get(kind, frozenset())
    named = list(result.get("named", []))
    attributing = result["verdict"] in ATTRIBUTING
    return {
        "verdict": result["verdict"],
        "named": named,
        "top": top["effect"] if top else None,
        "top_shrink": top["shrink"] if top else None,
        "top_parameters": top["parameters"] if top else None,
        "correct": bool(correct) and attributing and any(set(_parts(n)) <= correct for n in named),
        "in_pair": bool(correct) and attributing and any(set(_parts(n)) & correct for n in named),
        "false_attribution": not correct and attributing,
        "correct_entries": {e["effect"]: e["parameters"] for e in effects if e["effect"] in correct},
        "significant_measures": [
            {k: m.get(k) for k in ("name", "region", "phase", "value", "uncertainty")}
            for m in result.get("measures", [])
            if m.get("significant")
        ],
        "calibration": result.get("calibration"),
    }


def fmt(value: object, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}={fmt(v)}" for k, v in value.items() if k != "g_prony_equivalent")
    return str(value)


def _rate(flags: list[bool]) -> str:
    return f"{sum(flags)}/{len(flags)}" + (f" ({100 * sum(flags) / len(flags):.0f} %)" if flags else "")


def _named_text(row: dict) -> str:
    return ", ".join(row["named"]) if row["verdict"] in ATTRIBUTING and row["named"] else "(none)"


def summary_markdown(rows: list[dict], command: str) -> str:
    """Rates, per-kind table, confusion matrix and per-case tables."""
    library = [r for r in rows if r["kind"] in CORRECT]
    negatives = [r for r in rows if r["kind"] not in CORRECT]
    seconds = [r["generation_s"] + r["diagnosis_s"] for r in rows]
    lines = [
        "# Gap diagnosis on the independent generator",
        "",
        f"Command: `{command}`",
        "",
        f"Attributing verdicts: {', '.join(ATTRIBUTING)}; the named effects are diagnosis.json's `named`.",
        "",
        "| rate | value |",
        "|---|---|",
        f"| top-1 over in-library cases (a correct effect named; one of an ambiguous pair will do) | "
        f"{_rate([bool(r['correct']) for r in library])} |",
        f"| ... a correct effect part of a named pair | {_rate([bool(r['in_pair']) for r in library])} |",
        f"| ... in-library cases attributed to a wrong effect only | "
        f"{_rate([r['verdict'] in ATTRIBUTING and not r['in_pair'] for r in library])} |",
        f"| false attribution over nulls and out-of-library cases | "
        f"{_rate([bool(r['false_attribution']) for r in negatives])} |",
        f"| ... nulls | {_rate([bool(r['false_attribution']) for r in negatives if r['kind'] == 'null'])} |",
        f"| ... out-of-library | {_rate([bool(r['false_attribution']) for r in negatives if r['kind'] != 'null'])} |",
        f"| diagnosis errors (all kinds) | {_rate([r['verdict'].startswith('error') for r in rows])} |",
    ]
    if seconds:
        lines.append(
            f"| time per case, median / max (s) | {np.median(seconds):.0f} / {np.max(seconds):.0f} "
            f"(diagnosis median {np.median([r['diagnosis_s'] for r in rows]):.0f}) |"
        )
    lines += ["", "| hidden kind | counts as correct | cases | correct | in a pair | false attribution | verdicts |"]
    lines.append("|---|---|---|---|---|---|---|")
    for kind in sorted({r["kind"] for r in rows}):
        chosen = [r for r in rows if r["kind"] == kind]
        verdicts = Counter(r["verdict"] for r in chosen)
        target = ", ".join(sorted(CORRECT.get(kind, ()))) or "(nothing)"
        lines.append(
            f"| {kind} | {target} | {len(chosen)} | "
            + (
                f"{_rate([bool(r['correct']) for r in chosen])} | {_rate([bool(r['in_pair']) for r in chosen])} | - |"
                if kind in CORRECT
                else f"- | - | {_rate([bool(r['false_attribution']) for r in chosen])} |"
            )
            + f" {', '.join(f'{v} {n}' for v, n in sorted(verdicts.items()))} |"
        )
    cells = Counter((r["kind"], r["verdict"], _named_text(r)) for r in rows)
    lines += ["", "Confusion matrix (hidden kind x verdict x named effects):", ""]
    lines += ["| hidden kind | verdict | named | cases |", "|---|---|---|---|"]
    lines += [f"| {k} | {v} | {n} | {c} |" for (k, v, n), c in sorted(cells.items())]
    lines += [
        "",
        "| case | kind | hidden parameters | verdict | named | top effect | top shrink | correct | gen s | diag s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        mark = row["correct"] if row["kind"] in CORRECT else ("false" if row["false_attribution"] else "ok")
        lines.append(
            f"| {row['case']} | {row['kind']} | {fmt(row['hidden_parameters']) or '-'} | {row['verdict']} | "
            f"{_named_text(row)} | {row['top']} | {fmt(row['top_shrink'], 2)} | {mark} | "
            f"{row['generation_s']:.0f} | {row['diagnosis_s']:.0f} |"
        )
    lines += [
        "",
        "Calibration against the generator's truth (the diagnosis's library is a Yeoh section with a fixed"
        " base; its modulus absorbs the force scale, so only the ratios across cases compare):",
        "",
        "| case | modulus kPa true / fitted | depth mm true / fitted | probe face mm true / fitted | vessel depth mm "
        "true / fitted | vessel radius mm true / fitted | peak lambda mm | significant measures |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        phantom = row["phantom"]
        fitted = (row.get("calibration") or [{}])[0]
        lines.append(
            f"| {row['case']} | {phantom['shear_modulus_kpa']:.1f} / {fmt(fitted.get('shear_modulus_kpa'))} | "
            f"{phantom['depth_mm']:.1f} / {fmt(fitted.get('section_depth_mm'))} | "
            f"{phantom['probe_width_mm']:.1f} / {fmt(fitted.get('section_probe_width_mm'))} | "
            f"{phantom['vessel_depth_mm']:.1f} / {fmt(fitted.get('vessel_depth_mm'))} | "
            f"{phantom['vessel_radius_mm']:.1f} / {fmt(fitted.get('vessel_radius_mm'))} | "
            f"{row['peak_lambda_mm']:.1f} | {len(row['significant_measures'])} |"
        )
    return "\n".join(lines) + "\n"
