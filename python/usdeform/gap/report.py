"""Write a diagnosis: DIR/diagnosis.json (the contract), DIR/report.html and its PNG figures beside it."""

from __future__ import annotations

import html
import io
import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from .._files import atomic_output
from .detectability import MAX_REPEATS, ProtocolAdvice
from .diagnosis import Diagnosis, _parameter_text
from .follow_up import FollowUpRecording, write_record_next
from .verdicts import CandidateResult

__all__ = ["write_report", "write_text"]


def write_text(path: str | Path, text: str) -> None:
    """Write a text file atomically (temp file, then rename)."""
    with atomic_output(Path(path)) as handle:
        handle.write(text.encode("utf-8"))


def _save_figure(figure, path: Path) -> None:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    plt.close(figure)
    with atomic_output(path) as handle:
        handle.write(buffer.getvalue())


def _force_figure(diagnosis: Diagnosis, path: Path) -> None:
    attribution = diagnosis.attribution
    assert attribution is not None  # write_report draws figures only for a diagnosis with its attribution
    observations = diagnosis.observations
    figure, axes = plt.subplots(1, len(observations), figsize=(6 * len(observations), 4), squeeze=False)
    best = diagnosis.effects[0].effect if diagnosis.effects else "best"
    for axis, observation, before, after in zip(
        axes[0], observations, attribution.predictions_before, attribution.predictions_after, strict=True
    ):
        axis.plot(observation.time_s, observation.force_n, "k.", markersize=3, label="recorded")
        axis.plot(observation.time_s, before.force_n, "C0-", label="ideal simulator")
        axis.plot(observation.time_s, after.force_n, "C3--", label=f"with {best}")
        axis.set_xlabel("time (s)")
        axis.set_ylabel("contact force (N)")
        axis.set_title(observation.name[-50:], fontsize=8)
        axis.legend(fontsize=8)
    _save_figure(figure, path)


def _residual_map_figure(diagnosis: Diagnosis, path: Path) -> None:
    """Mean axial displacement residual per depth x lateral bin at the highest force tercile, before / after."""
    measures = [m for m in diagnosis.measures if m.name == "displacement_axial_px"]
    if not measures:
        return
    recording = measures[0].recording
    chosen = [m for m in measures if m.recording == recording]
    top_force = max(m.force_range_n[1] for m in chosen if m.force_range_n)
    chosen = [m for m in chosen if m.force_range_n and m.force_range_n[1] == top_force]
    regions = list(dict.fromkeys(m.region for m in chosen))
    depths = list(dict.fromkeys(r.split(",")[0] for r in regions))
    laterals = list(dict.fromkeys(r.split(",")[1].strip() for r in regions))
    grids = np.full((2, len(depths), len(laterals)), np.nan)
    for m in chosen:
        row, col = depths.index(m.region.split(",")[0]), laterals.index(m.region.split(",")[1].strip())
        grids[0, row, col] = m.value / m.uncertainty
        grids[1, row, col] = (m.value_after if m.value_after is not None else np.nan) / m.uncertainty
    limit = max(3.0, float(np.nanmax(np.abs(grids))) if np.isfinite(grids).any() else 3.0)
    figure, axes = plt.subplots(1, 2, figsize=(9, 4))
    for axis, grid, title in zip(axes, grids, ("ideal simulator", "with the best candidate"), strict=True):
        image = axis.imshow(grid, cmap="RdBu_r", vmin=-limit, vmax=limit)
        axis.set_xticks(range(len(laterals)), laterals, fontsize=7, rotation=20)
        axis.set_yticks(range(len(depths)), depths, fontsize=7)
        axis.set_title(f"axial residual / uncertainty, {title}", fontsize=9)
    figure.colorbar(image, ax=axes, shrink=0.8)
    _save_figure(figure, path)


def write_report(diagnosis: Diagnosis, out: str | Path) -> Path:
    """Write DIR/diagnosis.json, DIR/record_next.json, DIR/report.html, DIR/force_curves.png and
    DIR/residual_map.png; returns DIR."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "diagnosis.json", json.dumps(diagnosis.to_json(), indent=1))
    write_record_next(out / "record_next.json", diagnosis.follow_up)
    if diagnosis.attribution is not None and diagnosis.observations:
        _force_figure(diagnosis, out / "force_curves.png")
        _residual_map_figure(diagnosis, out / "residual_map.png")
    rows = []
    for m in sorted(diagnosis.measures, key=lambda m: (not m.significant, -abs(m.value) / max(m.uncertainty, 1e-12))):
        force = f"{m.force_range_n[0]:.1f}-{m.force_range_n[1]:.1f}" if m.force_range_n else ""
        after = f"{m.value_after:.3g}" if m.value_after is not None and np.isfinite(m.value_after) else ""
        fitting = (
            f"{m.value_fitting_split:.3g} +/- {m.uncertainty_fitting_split:.2g}"
            if m.value_fitting_split is not None and np.isfinite(m.value_fitting_split)
            else ""
        )
        rows.append(
            f"<tr{' class=sig' if m.significant else ''}><td>{html.escape(m.name)}</td><td>{html.escape(m.region)}</td>"
            f"<td>{force}</td><td>{m.phase}</td><td>{m.value:.3g}</td><td>{m.uncertainty:.2g}</td><td>{after}</td>"
            f"<td>{fitting}</td><td>{'yes' if m.significant else ''}</td></tr>"
        )
    effects = "".join(
        f"<tr{' class=sig' if e.significant else ''}><td>{e.effect}</td><td>{html.escape(_parameter_text(e))}</td>"
        f"<td>{e.gap_before:.3g}</td><td>{e.gap_after:.3g}</td><td>{100 * e.shrink:.0f} %</td>"
        f"<td>{'yes' if e.significant else 'no'}</td><td>{_signature_text(e)}</td>"
        f"<td>{html.escape(', '.join(e.at_bound))}</td><td>{html.escape(_unidentified_text(e))}</td></tr>"
        for e in diagnosis.effects
    )
    calibration = _calibration_table(diagnosis.calibration)
    record_next = "".join(
        f"<tr><td>{a.effect}</td><td>{html.escape(a.reason)}</td>"
        f"<td>{_repeats(a)}</td>"
        f"<td>{html.escape(a.protocol)}</td></tr>"
        for a in diagnosis.record_next
    )
    record_next_section = (
        f"""<h2>What to record next</h2>
<p>Effects these recordings could not reveal at the top of their realistic range, or could not tell apart: how many
palpations like these would reveal each (the power check's expected z-scores grow as the square root of their
number), and the recording that shows its own signature.</p>
<table><tr><th>effect</th><th>why</th><th>palpations like these needed</th><th>protocol</th></tr>
{record_next}</table>"""
        if record_next
        else ""
    )
    page = f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>usdeform gap diagnosis</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}}td,th{{padding:2px 8px;font-size:13px}}
tr.sig{{background:#fde2e2}}table{{border-collapse:collapse}}tr:nth-child(even){{background:#f4f4f4}}</style></head><body>
<h1>Sim-to-real gap diagnosis: {diagnosis.verdict.replace("_", " ")}{_named(diagnosis.named)}</h1>
<p>{html.escape(diagnosis.summary)}</p>
{_compensation_paragraph(diagnosis)}
<p>Gap G (held out, mean squared z-score per measure group) of the ideal simulator: {diagnosis.gap_before:.3g};
measures are significant beyond |z| = {diagnosis.critical_z:.2f} (Bonferroni, 5 %).</p>
<h2>Figures</h2><img src="force_curves.png" alt="force curves"><br><img src="residual_map.png" alt="residual map">
<h2>Effects, best first (held out: each fitted on one half of the time blocks and measured on the other, both
ways, the two averaged)</h2>
<table><tr><th>effect</th><th>parameters +/- uncertainty</th><th>gap before</th><th>gap after</th>
<th>shrink</th><th>significant</th><th>shrink over its signature</th><th>fitted at the edge of the library</th>
<th>not identified (held neutral; would identify it)</th></tr>
{effects}</table>
<p>A parameter fitted at the edge of the library (within 2 % of the range the library models, or beyond it) is the
library's best, not the data's: the effect may be larger than modelled or the same physics in another form, and the
candidate is never counted as a clean explanation. An effect is significant only where the gap over the measures
its own physics shows in (its signature) drops significantly with it too; "absent" marks one whose signature did
not.</p>
{_checklist(diagnosis.follow_up)}
{record_next_section}
{_sections_table(diagnosis)}
{_sensor_table(diagnosis.sensor_calibration)}
{_reference_table(diagnosis.reference_targets)}
<h2>Calibration of the ideal simulator</h2>{calibration}
<h2>Measures (recorded minus simulated, held-out split), before and after the best candidate</h2>
<p>Significance takes both splits together (their z-scores combined), so a measure can be significant while its
held-out value alone is not; the fitting split (where the ideal simulator's force curve and correlation baseline
were fitted) is shown beside it.</p>
<table><tr><th>measure</th><th>region</th><th>force (N)</th><th>phase</th><th>value</th><th>uncertainty</th>
<th>after</th><th>fitting split</th><th>significant</th></tr>
{"".join(rows)}</table></body></html>
"""
    write_text(out / "report.html", page)
    return out


def _checklist(recordings: list[FollowUpRecording]) -> str:
    """The follow-up protocol of record_next.json as a checklist ("" when nothing more is needed)."""
    if not recordings:
        return ""
    items = "".join(
        f"<li>&#9744; <b>{html.escape(r.name)}</b> ({r.kind}): {_what_to_record(r)}. Reveals "
        f"{html.escape(', '.join(r.reveals))}. {html.escape(r.reason)}</li>"
        for r in recordings
    )
    return f"""<h2>Record next (record_next.json)</h2>
<p>Record each as one PLUS sequence file named as listed, then run <code>usdeform diagnose NEW_FILES --follow-up
THIS_FOLDER --out NEW_FOLDER</code>: the second diagnosis decides on all the recordings.</p><ul>{items}</ul>"""


def _what_to_record(r: FollowUpRecording) -> str:
    """One follow-up recording's parameters in words."""
    if r.known_weight_n is not None:
        return f"the probe off the tissue, loaded by a known {r.known_weight_n:g} N"
    depth = (
        ""
        if r.kind != "reference_target"
        else (
            ", over the phantom's base or the table"
            if r.reference_depth_mm is None
            else f", over a reflector {r.reference_depth_mm:g} mm deep"
        )
    )
    if depth:
        depth += " (its depth in mm as the header key ReferenceTargetDepth, or diagnose --reference-depth-mm)"
    return (
        f"at {r.position_mm:g} mm, up to {r.max_force_n:g} N at {r.ramp_speed_mm_s:g} mm/s"
        + (f", hold {r.hold_s:g} s" if r.hold_s else "")
        + (f", tilted {r.tilt_deg:g} degrees" if r.tilt_deg else "")
        + depth
    )


def _compensation_paragraph(diagnosis: Diagnosis) -> str:
    """The line saying what the named effect costs the correction and what compensation gives back ("" without)."""
    line = diagnosis.compensation.get("summary")
    return f"<p><b>{html.escape(str(line))}</b></p>" if line else ""


def _repeats(advice: ProtocolAdvice) -> str:
    """How many palpations like these would reveal the effect ("" for an ambiguity, which repeats do not lift)."""
    if advice.reason != "undetectable":
        return ""
    return str(advice.repeats) if advice.repeats is not None else f"more than {MAX_REPEATS}"


def _named(named: list[str]) -> str:
    """`` (A)`` or `` (A or B)``: the effects the verdict names, for the page's title."""
    return f" ({html.escape(' or '.join(named))})" if named else ""


def _calibration_table(calibration: list[dict[str, object]]) -> str:
    """The calibrated quantities (names carry their units) a row each, a column per recording."""
    names = list(dict.fromkeys(key for row in calibration for key in row if key != "recording"))
    head = "".join(f"<th>{html.escape(Path(str(row.get('recording', ''))).name)}</th>" for row in calibration)
    body = "".join(
        f"<tr><td>{html.escape(name)}</td>"
        + "".join(f"<td>{_cell(row.get(name, ''))}</td>" for row in calibration)
        + "</tr>"
        for name in names
    )
    return f"<table><tr><th>quantity</th>{head}</tr>{body}</table>"


def _cell(value: object) -> str:
    if value is None:  # e.g. the vessel's geometry where no lumen was seen
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    return html.escape(str(value))


def _signature_text(effect: CandidateResult) -> str:
    """Each member's held-out shrink over its own signature groups, those without a significant drop marked."""
    return "; ".join(
        f"{name}: {100 * shrink:.0f} %" + (" (absent)" if name in effect.signature_absent else "")
        for name, shrink in effect.signature_shrink.items()
    )


def _unidentified_text(effect: CandidateResult) -> str:
    """``name: kind`` of each parameter held at its neutral value, with the recording that would identify it."""
    return ", ".join(f"{name}: a {kind} recording" for name, kind in effect.unidentified.items())


def _sections_table(diagnosis: Diagnosis) -> str:
    """The library sections left out (and the effect taken out with each) or solved another way ("" when none)."""
    rows = [
        f"<tr><td>{html.escape(s['recording'])}</td><td>{html.escape(s['section'])}</td><td>left out</td>"
        f"<td>{html.escape(s['effect'] or 'none')}</td><td>{html.escape(s['error'])}</td></tr>"
        for s in diagnosis.unsolved_sections
    ] + [
        f"<tr><td>{html.escape(s['recording'])}</td><td>{html.escape(s['section'])}</td><td>solved</td><td></td>"
        f"<td>{html.escape(s['how'])}</td></tr>"
        for s in diagnosis.resolved_sections
    ]
    if not rows:
        return ""
    return f"""<h2>Library sections solved another way or left out</h2>
<table><tr><th>recording</th><th>section</th><th>outcome</th><th>effect not fitted</th><th>how, or why</th></tr>
{"".join(rows)}</table>"""


def _reference_table(targets: list[dict[str, Any]]) -> str:
    """The speed of sound each reflector fixed in the world shows, or why it was not found ("" when none was asked)."""
    rows = [
        f"<tr><td>{html.escape(Path(t['recording']).name)}</td><td>"
        + (
            f"{t['sound_speed_m_s']:.0f} +/- {t['sound_speed_uncertainty_m_s']:.0f} m/s</td>"
            f"<td>{t['reflector_depth_mm']:.1f} mm</td></tr>"
            if t["found"]
            else f"not found</td><td>{html.escape(t['note'])}</td></tr>"
        )
        for t in targets
    ]
    if not rows:
        return ""
    return f"""<h2>Reflectors fixed in the world</h2>
<table><tr><th>recording</th><th>speed of sound</th><th>depth as displayed, or why not found</th></tr>
{"".join(rows)}</table>"""


def _sensor_table(calibrations: list[dict[str, object]]) -> str:
    """The force sensor fitted on each known-weight recording ("" when none was given)."""
    if not calibrations:
        return ""
    rows = "".join(
        f"<tr><td>{html.escape(str(c['recording']))}</td><td>{_cell(c['gain_error'])} +/- "
        f"{_cell(c['gain_error_uncertainty'])}</td><td>{_cell(c['offset_n'])} +/- {_cell(c['offset_uncertainty_n'])}"
        f"</td><td>{_cell(c['drift_n_per_s'])} +/- {_cell(c['drift_uncertainty_n_per_s'])}</td></tr>"
        for c in calibrations
    )
    return f"""<h2>Force sensor on a known weight</h2>
<p>Reading = (1 + gain error) x load + offset + drift x time, fitted on each known-weight recording. These are
reported beside the verdict; the force-sensor candidate is still fitted on the palpations.</p>
<table><tr><th>recording</th><th>gain error</th><th>offset (N)</th><th>drift (N/s; empty: not identified)</th></tr>
{rows}</table>"""
