"""Sweeps as a robot makes them: the nuisances of a real robotic sweep, each alone and all together.

On the stiff phantom (palpated at ``n_palpations`` positions along the path, ideal palpations), one
force-controlled sweep per scenario, corrected with the package's defaults (``usdeform fit`` /
``correct``: the recommended method, stiffness source ``auto``) and with the paper's method
(``fit --method paper``), measured against the simulator's zero-force truth on every frame and on
the compounded volume (:func:`~usdeform.experiments.paper_3d.measures.measure_variants`). The
nuisances (:data:`NUISANCE_NAMES`; sizes in :class:`RobotSweepConfig`):

- ``force``: the controller holds the target only within about +/-1.2 N (slow oscillation and ripple,
  :class:`~usdeform.sim.ForceController`);
- ``delay``: the frames show the tissue 100 ms before their stamp (force and pose stamped on time);
- ``jitter``: out-of-plane jitter of the probe against the tissue, 0.3 mm rms per frame (unrecorded);
- ``path``: the probe rotates about its elevation axis by up to 15 degrees along the path and curves
  5 mm sideways relative to the vessel (the vessel moves in the image; the recorded path stays straight);
- ``vessel``: the vessel deepens by 5 mm and its radius shrinks by 30 % along the path;
- ``stiffness``: stiffness +/-30 % along the path and +/-30 % across the probe face.

The sweeps, force controller and sensor effects apply to the sweep only; the tissue (vessel,
stiffness) to palpations and sweep alike.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..._files import atomic_output
from ...correction import correct_recording
from ...errors import InputError
from ...fitting import FittedPalpations, MethodName, fit_palpations
from ...sim import (
    Effects,
    ForceController,
    ImageLatency,
    OutOfPlaneMotion,
    Phantom,
    SweepPath,
    simulate_palpation,
    simulate_sweep,
    stiff_phantom,
)
from .measures import measure_variants

__all__ = ["NUISANCE_NAMES", "ROBOT_QUICK", "RobotSweepConfig", "nuisance_scenarios", "run_robot_sweeps"]

#: The nuisances, each switchable on its own.
NUISANCE_NAMES = ("force", "delay", "jitter", "path", "vessel", "stiffness")

#: The compared corrections: label and ``usdeform fit --method``.
METHODS: dict[str, MethodName] = {"defaults": "recommended", "paper": "paper"}

#: The issue's targets on every sweep (defaults): mean Dice, worst-frame Dice, |area error| (%),
#: |centre-line depth error| (mm), |vessel volume error| (%).
TARGETS = {"mean_dice": 0.98, "worst_dice": 0.95, "area_pct": 2.0, "depth_mm": 0.2, "volume_pct": 3.0}


@dataclass(frozen=True)
class RobotSweepConfig:
    """The sweeps and the size of each nuisance.

    Path of ``length_mm`` along the stiff phantom (cut to that length), ``n_palpations`` palpations to
    ``palpation_force_n`` (N) of ``palpation_frames`` frames, sweeps at ``force_n`` (N) with frames
    ``frame_spacing_mm`` apart, every ``frame_step``-th frame of the 50 fps stream (1 mm, 6: 8.3 mm/s),
    volumes of ``voxel_mm`` voxels; ``mesh_size_mm`` overrides the preset's mesh. The defaults are sized
    for a table of eight sweeps in well under an hour on two shared cores (0.3 mm pixels, a 3 mm mesh).
    Nuisances: force oscillation amplitude and ripple rms (N), image delay (s), out-of-plane jitter
    (mm rms), probe tilt at mid-path (degrees) and sideways curve of the path (mm), vessel deepening
    (mm) and relative radius change over the path, stiffness variation along the path and across
    the probe face (fractions).
    """

    rows: int = 128
    cols: int = 128
    palpation_frames: int = 24
    n_palpations: int = 3
    palpation_force_n: float = 20.0
    force_n: float = 15.0
    length_mm: float = 40.0
    frame_spacing_mm: float = 1.0
    frame_step: int = 6
    voxel_mm: float = 0.5
    seed: int = 0
    mesh_size_mm: float | None = 3.0
    force_oscillation_n: float = 0.8
    force_ripple_n: float = 0.25
    image_delay_s: float = 0.1
    jitter_mm: float = 0.3
    max_tilt_deg: float = 15.0
    path_curve_mm: float = 5.0
    vessel_deepening_mm: float = 5.0
    vessel_radius_change: float = -0.3
    stiffness_along_path: float = 0.3
    stiffness_across: float = 0.3


#: A small configuration for smoke tests: small frames, a coarse mesh, a short path.
ROBOT_QUICK = RobotSweepConfig(rows=96, cols=96, palpation_frames=20, n_palpations=2, length_mm=12.0, mesh_size_mm=4.0)


@dataclass(frozen=True)
class _Scenario:
    """One sweep: its label, the phantom and what the robot adds."""

    label: str
    phantom: Phantom
    effects: Effects
    controller: ForceController
    path: SweepPath


def _phantom(names: frozenset[str], config: RobotSweepConfig) -> Phantom:
    """The stiff phantom as long as the path (its vessel and stiffness changes span the path, see
    :class:`~usdeform.sim.Phantom`) with the tissue nuisances of ``names``."""
    phantom = dataclasses.replace(stiff_phantom(), length_mm=config.length_mm)
    geometry: dict[str, Any] = {}
    if "vessel" in names:
        geometry["vessel_shift_depth_mm"] = config.vessel_deepening_mm
        geometry["vessel_radius_change_mm"] = config.vessel_radius_change * phantom.base_section.vessel_radius_mm
    if "path" in names:  # the probe curving sideways by +c moves the vessel by -c relative to it
        geometry["vessel_shift_x_mm"] = phantom.vessel_shift_x_mm - config.path_curve_mm
    if geometry:  # knots 5 mm apart: <= 1 mm of vessel motion between them, as the presets' (Phantom: < 0.2 mm)
        knots = int(np.ceil(config.length_mm / 5.0)) + 1
        phantom = dataclasses.replace(phantom, geometry_knots=max(knots, phantom.geometry_knots), **geometry)
    if "stiffness" in names:
        phantom = dataclasses.replace(phantom, stiffness_amplitude=config.stiffness_along_path)
        phantom = phantom.with_section_changes(lateral_stiffness_gradient=config.stiffness_across)
    if config.mesh_size_mm is not None:
        phantom = phantom.with_section_changes(mesh_size_mm=config.mesh_size_mm)
    return phantom


def _scenario(label: str, names: frozenset[str], config: RobotSweepConfig) -> _Scenario:
    unknown = names - set(NUISANCE_NAMES)
    if unknown:
        raise InputError(
            f"nuisance: unknown {', '.join(sorted(unknown))}; expected {', '.join(NUISANCE_NAMES)}, all or table"
        )
    effects = Effects(
        latency=ImageLatency(config.image_delay_s if "delay" in names else 0.0),
        out_of_plane=OutOfPlaneMotion(jitter_mm=config.jitter_mm if "jitter" in names else 0.0),
    )
    controller = (
        ForceController(oscillation_n=config.force_oscillation_n, tracking_ripple_n=config.force_ripple_n)
        if "force" in names
        else ForceController()
    )
    path = SweepPath(config.max_tilt_deg if "path" in names else 0.0)
    return _Scenario(label, _phantom(names, config), effects, controller, path)


def nuisance_scenarios(choices: Iterable[str], config: RobotSweepConfig) -> list[_Scenario]:
    """The sweeps ``--nuisance`` asks for: names of :data:`NUISANCE_NAMES` together in one sweep,
    ``all`` (every nuisance together) or ``table`` (no nuisance, all together, each alone)."""
    chosen = list(dict.fromkeys(choices))
    if "table" in chosen:
        if len(chosen) > 1:
            raise InputError("nuisance: table runs every sweep; give it alone")
        labels = {"none": frozenset[str](), "all": frozenset(NUISANCE_NAMES)}  # first: a cut-off run has them
        labels |= {name: frozenset({name}) for name in NUISANCE_NAMES}
        return [_scenario(label, names, config) for label, names in labels.items()]
    if "all" in chosen:
        if len(chosen) > 1:
            raise InputError("nuisance: all is every nuisance together; give it alone")
        return [_scenario("all", frozenset(NUISANCE_NAMES), config)]
    return [_scenario(" + ".join(chosen), frozenset(chosen), config)]


def _fit(phantom: Phantom, config: RobotSweepConfig) -> dict[str, FittedPalpations]:
    """Palpate ``phantom`` along the path (ideal palpations) and fit each of :data:`METHODS`."""
    positions = np.linspace(0.0, config.length_mm, config.n_palpations)
    palpations = [
        simulate_palpation(
            phantom,
            float(position),
            config.palpation_force_n,
            n_frames=config.palpation_frames,
            seed=config.seed + number,
            rows=config.rows,
            cols=config.cols,
        )[0]
        for number, position in enumerate(positions)
    ]
    depth = phantom.base_section.depth_mm
    return {label: fit_palpations(palpations, depth, method=method) for label, method in METHODS.items()}


def _summary(frames: dict[str, list[float]], volume: dict[str, float]) -> dict[str, float]:
    """The table's numbers of one variant: mean and worst-frame Dice, mean area error (% of the
    zero-force area), largest centroid distance (mm), volume error (%), centre-line depth error mean
    and largest (mm)."""
    area = np.asarray(frames["area_mm2"], dtype=float)
    truth_area = area - np.asarray(frames["area_diff_mm2"], dtype=float)
    dice = np.asarray(frames["dice"], dtype=float)
    return {
        "mean_dice": float(dice.mean()),
        "worst_dice": float(dice.min()),
        "area_pct": float(100.0 * np.nanmean((area - truth_area) / truth_area)),
        "centroid_max_mm": float(np.nanmax(frames["centroid_mm"])),
        "volume_pct": volume["volume_error_pct"],
        "depth_mm": volume["depth_error_mean_mm"],
        "depth_max_mm": volume["depth_error_max_mm"],
    }


def _misses(row: dict[str, float]) -> list[str]:
    """The targets of :data:`TARGETS` that ``row`` misses."""
    misses = [name for name in ("mean_dice", "worst_dice") if not row[name] >= TARGETS[name]]
    return misses + [name for name in ("area_pct", "depth_mm", "volume_pct") if not abs(row[name]) <= TARGETS[name]]


def _run(scenario: _Scenario, fits: dict[str, FittedPalpations], config: RobotSweepConfig) -> dict[str, object]:
    """Simulate, correct and measure one sweep; its per-variant summary and sweep ranges."""
    n_frames = round(config.length_mm / config.frame_spacing_mm) + 1
    recording, truth = simulate_sweep(
        scenario.phantom,
        0.0,
        config.length_mm,
        config.force_n,
        n_frames=n_frames,
        seed=config.seed + 100,
        effects=scenario.effects,
        rows=config.rows,
        cols=config.cols,
        controller=scenario.controller,
        frame_step=config.frame_step,
        path=scenario.path,
    )
    assert recording.force is not None
    corrected = {label: correct_recording(recording, f.fit.fitted, f.sampled) for label, f in fits.items()}
    frames, volumes, _ = measure_variants(recording, truth, corrected, np.arange(n_frames), config.voxel_mm)
    summary = {name: _summary(frames[name], volumes[name]) for name in frames}
    return {
        "sweep": scenario.label,
        "force_range_n": [float(recording.force.min()), float(recording.force.max())],
        "tilt_range_deg": [float(truth.probe_tilt_deg.min()), float(truth.probe_tilt_deg.max())],
        "truth_volume_mm3": volumes["truth"]["volume_mm3"],
        "variants": summary,
        "misses": {name: _misses(row) for name, row in summary.items() if name != "deformed"},
    }


def run_robot_sweeps(
    output_dir: str | Path, choices: Iterable[str], config: RobotSweepConfig | None = None
) -> list[dict[str, object]]:
    """Run the sweeps of ``choices`` (see :func:`nuisance_scenarios`; ``config`` None: the defaults);
    write ``robot_sweeps.md`` and ``robot_sweeps.json`` to ``output_dir`` after each sweep; return the rows."""
    config = RobotSweepConfig() if config is None else config
    scenarios = nuisance_scenarios(choices, config)
    output = Path(output_dir)
    output.mkdir(parents=True, exist_ok=True)
    fitted: dict[Phantom, dict[str, FittedPalpations]] = {}
    rows: list[dict[str, object]] = []
    with tqdm(total=len(scenarios), desc="robot sweeps", unit="sweep") as progress:
        for scenario in scenarios:
            progress.set_postfix_str(scenario.label)
            if scenario.phantom not in fitted:
                fitted[scenario.phantom] = _fit(scenario.phantom, config)
            rows.append(_run(scenario, fitted[scenario.phantom], config))
            _write(rows, config, output)  # a cut-off run keeps what it measured
            progress.update()
    return rows


def _write(rows: list[dict[str, object]], config: RobotSweepConfig, output: Path) -> None:
    lines = [
        "# Sweeps as a robot makes them",
        "",
        f"Stiff phantom cut to the path ({config.length_mm:g} mm), "
        f"{config.n_palpations} ideal palpations to {config.palpation_force_n:g} N, sweeps at {config.force_n:g} N "
        f"with frames {config.frame_spacing_mm:g} mm apart ({config.frame_step} frame(s) of 50 fps per frame), "
        f"{config.rows} x {config.cols} pixels, voxels {config.voxel_mm:g} mm; every frame measured. "
        "`defaults`: `usdeform fit` / `correct` defaults; `paper`: `fit --method paper`. "
        "Targets (defaults): mean Dice >= 0.98, worst >= 0.95, |area| <= 2 %, |centre-line depth| <= 0.2 mm, "
        "|volume| <= 3 %.",
        "",
        "| sweep | variant | mean Dice | worst Dice | area error | max centroid | volume error | "
        "centre-line depth mean / max | missed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        variants: dict[str, dict[str, float]] = row["variants"]  # type: ignore[assignment]
        misses: dict[str, list[str]] = row["misses"]  # type: ignore[assignment]
        for name, v in variants.items():
            lines.append(
                f"| {row['sweep']} | {name} | {v['mean_dice']:.3f} | {v['worst_dice']:.3f} | {v['area_pct']:+.1f} % | "
                f"{v['centroid_max_mm']:.2f} mm | {v['volume_pct']:+.1f} % | "
                f"{v['depth_mm']:+.2f} / {v['depth_max_mm']:.2f} mm | {', '.join(misses.get(name, [])) or '-'} |"
            )
    lines += [
        "",
        "| sweep | force range (N) | probe tilt range (degrees) | truth lumen volume (mm^3) |",
        "|---|---|---|---|",
    ]
    for row in rows:
        force, tilt = row["force_range_n"], row["tilt_range_deg"]
        lines.append(
            f"| {row['sweep']} | {force[0]:.2f}-{force[1]:.2f} | {tilt[0]:.1f}-{tilt[1]:.1f} | "  # type: ignore[index]
            f"{row['truth_volume_mm3']:.0f} |"
        )
    with atomic_output(output / "robot_sweeps.md") as handle:
        handle.write(("\n".join(lines) + "\n").encode())
    payload = {"config": asdict(config), "targets": TARGETS, "sweeps": rows}
    with atomic_output(output / "robot_sweeps.json") as handle:
        handle.write(json.dumps(payload, indent=1, default=float).encode())
