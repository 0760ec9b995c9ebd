"""The paper's 3D experiments (Section IV-B, Figs. 9 and 10) on the simulated phantoms.

For each phantom the pipeline is run as on a real system: palpations at ``n_palpations`` positions
equally spaced along the path (the ends included) give the stiffness profiles and the regression's
observations (:func:`usdeform.fitting.measure_positions`); force-controlled sweeps along the path
at each force are corrected with every model (:func:`usdeform.correction.correct_recording`,
stiffness interpolated between the palpations or taken from the sweep's own force and probe
displacement) and compounded. The ground truth is the simulator's zero-force frames compounded at
the zero-force probe poses (the probe touching the unloaded surface, from the simulator's own
geometry, not from the package's).

Measured:

- per frame, on ``random_frames`` frames drawn per sweep: the vessel segmented
  (:func:`usdeform.metrics.segment_vessel`) in the deformed and the corrected frame against the one
  in the zero-force frame: centroid distance (mm), area difference (mm^2), Dice (paper Fig. 10);
- per volume: the lumen segmented slice by slice across the sweep (:func:`segment_volume_lumen`)
  against the truth lumen (the simulator's zero-force lumen masks compounded): lumen volume (mm^3),
  centre-line depth error (mm, :func:`centre_line_depth_mm`), 3-D Dice, and the lumen's extent in the
  coronal view at the true centre-line depth relative to the truth's (Fig. 9);
- per sweep frame: how far the interpolated stiffness misses the recorded displacement at the
  recorded force (the error the ``"sweep"`` stiffness source removes);
- why a corrected lumen is too small or large, by region (:func:`wall_errors_mm`): the model's
  displacement against the simulator's true field just outside the lumen's top, bottom, left and
  right walls, and in the tissue away from the vessel.

Sweeps as a robot makes them (force ripple, image delay, out-of-plane jitter, a curved and tilted path,
a changing vessel, laterally varying stiffness), each alone and all together:
:mod:`~usdeform.experiments.paper_3d.robot_sweeps` (``usdeform experiment paper-3d --nuisance NAME``).

Volumes use the simulator's layout: the sweep runs along the base y axis and the probe axis along
base -z, so a volume slice at fixed y is an axial view and one at fixed z a coronal view.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from .config import NUISANCES, QUICK, Paper3dConfig, SweepCase
from .measures import centre_line_depth_mm, compound_filled, lumen_from_masks, segment_volume_lumen, wall_errors_mm
from .robot_sweeps import NUISANCE_NAMES, ROBOT_QUICK, RobotSweepConfig, run_robot_sweeps
from .running import run_paper_3d

__all__ = [
    "NUISANCES",
    "NUISANCE_NAMES",
    "QUICK",
    "ROBOT_QUICK",
    "Paper3dConfig",
    "RobotSweepConfig",
    "SweepCase",
    "centre_line_depth_mm",
    "compound_filled",
    "lumen_from_masks",
    "run_command",
    "run_paper_3d",
    "run_robot_sweeps",
    "segment_volume_lumen",
    "wall_errors_mm",
]


def run_command(output_dir: Path, *, quick: bool, nuisances: Sequence[str] | None) -> str:
    """``usdeform experiment paper-3d``: the paper's sweeps, or with ``nuisances`` (``--nuisance``,
    see :func:`~usdeform.experiments.paper_3d.robot_sweeps.nuisance_scenarios`) the robot's; ``quick``
    runs the small configurations. Returns the name of the results file written."""
    if nuisances is None:
        run_paper_3d(output_dir, QUICK if quick else Paper3dConfig())
        return "results.md"
    run_robot_sweeps(output_dir, nuisances, ROBOT_QUICK if quick else RobotSweepConfig())
    return "robot_sweeps.md"
