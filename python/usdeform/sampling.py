"""Sampling positions: one robotic palpation turned into what the regression needs (paper Sec. III-A).

From a palpation recording (frames, force, probe displacement) this stage fits the position's
stiffness profile (:mod:`usdeform.stiffness`), tracks the pixel displacements from the lowest-force
frame (:mod:`usdeform.optical_flow`), adds the eq. 10 boundary rows, and packs the result as the
regression's :class:`~usdeform.regression.Observations`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from .errors import InputError
from .optical_flow import TrackedDisplacements, track_palpation
from .recording import Recording
from .regression import Observations
from .stiffness import StiffnessFit, fit_stiffness

__all__ = ["SampledPosition", "measure_palpation"]


@dataclass(frozen=True, eq=False)
class SampledPosition:
    """A palpated position: its stiffness fit, the optical-flow tracks (``tracked.kept_fraction``
    says how many survived to the highest force), the regression observations (tracks plus the eq. 10
    boundary rows) and the wall-clock seconds the measurement took."""

    stiffness: StiffnessFit
    tracked: TrackedDisplacements
    observations: Observations
    seconds: float


def measure_palpation(
    recording: Recording, flexible_layer_mm: float, boundary_points: int = 32, **tracking: Any
) -> SampledPosition:
    """Stiffness and pixel displacements of one palpation.

    Parameters
    ----------
    recording : Recording
        The palpation, with per-frame force and probe displacement.
    flexible_layer_mm : float
        Thickness L_T of the compressible tissue under the probe, mm (eq. 10).
    boundary_points : int
        Points of the eq. 10 boundary rows.
    **tracking
        Passed to :func:`usdeform.optical_flow.track_palpation`.

    Returns
    -------
    SampledPosition
        The stiffness fit, the tracks and the observations (which carry the frame shape).
    """
    if recording.force is None or recording.probe_displacement is None:
        raise InputError("recording: a palpation needs per-frame force and probe displacement")
    start = time.perf_counter()
    stiffness = fit_stiffness(recording.force, recording.probe_displacement)
    tracked = track_palpation(recording.frames, recording.force, **tracking)
    measured = tracked.with_boundary(recording.probe_displacement, flexible_layer_mm, boundary_points)
    observations = Observations(
        measured.points_px,
        measured.displacements_px,
        measured.valid,
        recording.force[measured.frame_indices],
        float(recording.force[measured.reference_index]),
        stiffness.profile,
        tracked.frame_shape,
    )
    return SampledPosition(stiffness, tracked, observations, time.perf_counter() - start)
