"""Sweeps shaped like clinical scans (``usdeform experiment clinical-3d``).

An artery and a vein side by side (the vein's lumen ten times softer), skin and fat over muscle and a rigid
bone below, forces from 3 to 15 N, a probe that follows a convex surface, and vessels that deepen from 12 to
28 mm and widen along the sweep. Each phantom is palpated at three positions and fitted with the
recommended method; each sweep is corrected as ``usdeform correct`` corrects it and measured per vessel
against the lumen segmented in the simulator's zero-force frame
(:func:`~usdeform.experiments.clinical_3d.running.measure_sweep`).
"""

from __future__ import annotations

from pathlib import Path

from .running import TARGETS, VesselResult, measure_sweep, missed_targets, run_clinical_3d, write_results
from .scenarios import QUICK, Clinical3dConfig, Scenario, default_scenarios

__all__ = [
    "QUICK",
    "TARGETS",
    "Clinical3dConfig",
    "Scenario",
    "VesselResult",
    "default_scenarios",
    "measure_sweep",
    "missed_targets",
    "run_clinical_3d",
    "run_command",
    "write_results",
]


def run_command(output_dir: Path, *, quick: bool) -> str:
    """``usdeform experiment clinical-3d``: every scenario (``quick``: two, on small frames). Returns the name
    of the results file written."""
    run_clinical_3d(output_dir, QUICK if quick else Clinical3dConfig())
    return "clinical_3d.md"
