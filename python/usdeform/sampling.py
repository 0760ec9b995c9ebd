"""Sampling positions: one robotic palpation turned into what the regression needs (paper Sec. III-A).

From a palpation recording (frames, force, probe displacement) this stage fits the position's
stiffness profile (:mod:`usdeform.stiffness`), tracks the pixel displacements from the lowest-force
frame (:mod:`usdeform.optical_flow`), adds the eq. 10 boundary rows, and packs the result as the
regression's :class:`~usdeform.regression.Observations`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import FitError, InputError
from .optical_flow import TrackedDisplacements, track_palpation
from .propagation import SampledProfiles
from .recording import Recording
from .regression import Observations
from .stiffness import StiffnessFit, fit_stiffness

__all__ = ["SampledPosition", "measure_palpation", "measure_positions"]


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


def measure_positions(
    recordings: Sequence[Recording], flexible_layer_mm: float, *, names: Sequence[str] | None = None
) -> tuple[list[SampledPosition], SampledProfiles]:
    """Measure several palpations (one per sampling position) and place them along the sweep.

    Parameters
    ----------
    recordings : sequence of Recording
        Palpations with frames of one size, valid probe poses, ContactForce and ProbeDisplacement.
    flexible_layer_mm : float
        Thickness of the flexible layer, mm (paper eq. 10).
    names : sequence of str, optional
        One name per recording (e.g. its file), used in error messages.

    Returns
    -------
    measured : list of SampledPosition
        Each palpation's stiffness, tracks and regression observations.
    sampled : SampledProfiles
        Each position (the mean probe-surface position of its valid poses, base frame, mm) and its
        stiffness profile: what :func:`usdeform.reconstruction.correct_recording` interpolates.
    """
    from .reconstruction import probe_surface_positions  # reconstruction imports the correction kernels

    names = [f"palpation {index}" for index in range(len(recordings))] if names is None else list(names)
    if len(names) != len(recordings) or not recordings:
        raise InputError(f"recordings: expected one or more palpations, one name each, got {len(recordings)}")
    shapes = {recording.shape for recording in recordings}
    if len(shapes) > 1:
        raise InputError(f"palpations: frames must have one size, got {sorted(shapes)} (rows, cols)")
    positions, measured = [], []
    for name, recording in zip(names, recordings, strict=True):
        if not recording.pose_valid.any():
            raise InputError(f"{name}: no frame has a valid probe pose")
        positions.append(probe_surface_positions(recording.probe_to_base[recording.pose_valid]).mean(axis=0))
        try:
            measured.append(measure_palpation(recording, flexible_layer_mm))
        except (InputError, FitError) as error:
            raise type(error)(f"{name}: {error}") from None
    return measured, SampledProfiles(np.array(positions), tuple(m.stiffness.profile for m in measured))
