"""Sampling positions: one robotic palpation turned into what the regression needs (paper Sec. III-A).

From a palpation recording (frames, force, probe displacement) this stage fits the position's
stiffness profile (:mod:`usdeform.fitting`), tracks the pixel displacements from the lowest-force
frame (:mod:`usdeform.optical_flow`), adds the eq. 10 boundary rows, measures where the vessel
wall moved (:mod:`usdeform.fitting`), and packs the results as the regression's
:class:`~usdeform.regression.Observations`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..correction import SampledProfiles, probe_surface_positions, searched_lumen
from ..errors import FitError, InputError
from ..metrics import lumen_seeds, segment_vessel
from ..optical_flow import TrackedDisplacements, TrackingSettings, track_palpation
from ..options import WALL_MODES, WallMode, checked_option
from ..recording import Recording
from ..regression import Observations, VesselAnchor
from ..validation import available_cores, threads_argument
from ._stiffness import StiffnessFit, fit_stiffness
from ._vessel_wall import track_vessel_wall

__all__ = ["SampledPosition", "measure_palpation", "measure_positions", "measure_wall"]


@dataclass(frozen=True, eq=False)
class SampledPosition:
    """A palpated position: its stiffness fit, the optical-flow tracks (``tracked.kept_fraction``
    says how many survived to the highest force), the regression observations (tracks plus the eq. 10
    boundary rows), the wall-clock seconds the measurement took, and the vessel wall's observations
    (None where not measured; ``wall_note`` then says why), and those of each further vessel's wall
    (``other_walls``: a vein beside the artery, left to right)."""

    stiffness: StiffnessFit
    tracked: TrackedDisplacements
    observations: Observations
    seconds: float
    wall: Observations | None = None
    wall_note: str = ""
    other_walls: tuple[Observations, ...] = ()


def _observations(
    measured: TrackedDisplacements, stiffness: StiffnessFit, force: np.ndarray, vessel: VesselAnchor | None
) -> Observations:
    """Tracked displacements as regression observations (forces of their frames, the stiffness
    profile, the reference frame's lumen)."""
    return Observations(
        measured.points_px,
        measured.displacements_px,
        measured.valid,
        force[measured.frame_indices],
        float(force[measured.reference_index]),
        stiffness.profile,
        measured.frame_shape,
        vessel,
    )


def measure_palpation(
    recording: Recording,
    flexible_layer_mm: float,
    boundary_points: int = 32,
    *,
    wall: WallMode = "auto",
    wall_seed_px: Sequence[float] | None = None,
    tracking: TrackingSettings = TrackingSettings(),
) -> SampledPosition:
    """Stiffness, pixel displacements and vessel-wall displacements of one palpation.

    Parameters
    ----------
    recording : Recording
        The palpation, with per-frame force and probe displacement.
    flexible_layer_mm : float
        Thickness L_T of the compressible tissue under the probe, mm (eq. 10).
    boundary_points : int
        Points of the eq. 10 boundary rows.
    wall : {"auto", "require", "off"}
        Measure the vessel wall (:func:`usdeform.fitting.track_vessel_wall`) where the
        lowest-force frame shows a lumen, always, or never.
    wall_seed_px : sequence of float, optional
        (x, y) of the lumen in the lowest-force frame, pixels; None: the largest dark region.
    tracking : TrackingSettings
        The tracker's settings (:func:`usdeform.optical_flow.track_palpation`).

    Returns
    -------
    SampledPosition
        The stiffness fit, the tracks and the observations (which carry the frame shape).
    """
    if recording.force is None or recording.probe_displacement is None:
        raise InputError("recording: a palpation needs per-frame force and probe displacement")
    checked_option("wall", wall, WALL_MODES)
    start = time.perf_counter()
    stiffness = fit_stiffness(recording.force, recording.probe_displacement)
    tracked = track_palpation(recording.frames, recording.force, tracking)
    measured = tracked.with_boundary(recording.probe_displacement, flexible_layer_mm, boundary_points)
    # Every lumen of the lowest-force frame (the largest first), unless one is named: each wall measured.
    seeds: list[Sequence[float] | None] = [wall_seed_px]
    if wall_seed_px is None and wall != "off":
        seeds = _open_lumens(recording.frames[tracked.reference_index]) or [None]
    walls = [measure_wall(recording, tracked, stiffness, wall=wall, seed_px=seed) for seed in seeds]
    wall_observations, note = walls[0]
    others = [found for found, _ in walls[1:] if found is not None]
    if wall_observations is None and others:  # the largest lumen's wall failed: the next one leads
        wall_observations, others = others[0], others[1:]
    lumens = [found.vessel for found in [wall_observations, *others] if found is not None and found.vessel is not None]
    if len(walls) > 1:
        note += f"; {len(others)} further vessel{'s' if len(others) != 1 else ''}"
    observations = _observations(measured, stiffness, recording.force, lumens[0] if lumens else None)

    def with_lumens(found: Observations) -> Observations:
        return dataclasses.replace(found, vessel=lumens[0], other_vessels=tuple(lumens[1:]))

    if lumens:
        observations = with_lumens(observations)
        wall_observations = None if wall_observations is None else with_lumens(wall_observations)
    return SampledPosition(
        stiffness,
        tracked,
        observations,
        time.perf_counter() - start,
        wall_observations,
        note,
        tuple(with_lumens(found) for found in others),
    )


#: Longest axis of an open lumen over its shortest, at the palpation's lowest force: a dark region more
#: elongated than this (a hypoechoic layer such as subcutaneous fat, a shadow's band) is not a vessel.
MAX_LUMEN_ELONGATION = 4.0


def _open_lumens(frame: np.ndarray) -> list[Sequence[float] | None]:
    """The (x, y) seeds of :func:`usdeform.metrics.lumen_seeds` whose dark region is shaped like an open
    lumen (its fitted ellipse at most :data:`MAX_LUMEN_ELONGATION` times longer than wide)."""
    kept: list[Sequence[float] | None] = []
    for seed in lumen_seeds(frame):
        try:
            axes = segment_vessel(frame, seed).ellipse_axes_px
        except InputError:
            continue
        if max(axes) <= MAX_LUMEN_ELONGATION * max(min(axes), 1e-9):
            kept.append(seed)
    return kept


def measure_wall(
    recording: Recording,
    tracked: TrackedDisplacements,
    stiffness: StiffnessFit,
    *,
    wall: WallMode = "auto",
    seed_px: Sequence[float] | None = None,
) -> tuple[Observations | None, str]:
    """The vessel wall's displacements in one palpation as regression observations.

    Parameters
    ----------
    recording : Recording
        The palpation (frames and per-frame force).
    tracked : TrackedDisplacements
        Its tissue tracks (:func:`usdeform.optical_flow.track_palpation`).
    stiffness : StiffnessFit
        Its stiffness fit.
    wall : {"auto", "require", "off"}
        Measure where the lowest-force frame shows a lumen, always, or never.
    seed_px : sequence of float, optional
        (x, y) of the lumen in the lowest-force frame, pixels; None: the largest dark region.

    Returns
    -------
    tuple
        The observations (None where not measured; their ``vessel`` is the lowest-force frame's
        lumen) and a note saying how many wall points were measured or why none were.
    """
    checked_option("wall", wall, WALL_MODES)
    if wall == "off" or recording.force is None:
        return None, "not measured (wall='off')" if wall == "off" else "not measured: the recording has no force"
    try:
        wall_tracks = track_vessel_wall(recording.frames, recording.force, tracked=tracked, seed_px=seed_px)
    except InputError as error:
        if wall == "require":
            raise
        return None, f"not measured: {error}"
    note = f"{len(wall_tracks.points_px)} wall points, {wall_tracks.valid.mean():.0%} of them measured"
    # The lumen the wall was measured on (segmented as track_vessel_wall did), measured as the correction's
    # lumen search measures a sweep frame's: where a vessel-anchored model's window sits in this palpation.
    reference_frame = recording.frames[wall_tracks.reference_index]
    lumen = searched_lumen(reference_frame, VesselAnchor.of_mask(segment_vessel(reference_frame, seed_px).mask))
    return _observations(wall_tracks, stiffness, recording.force, lumen), note


def measure_positions(
    recordings: Sequence[Recording],
    flexible_layer_mm: float,
    *,
    names: Sequence[str] | None = None,
    wall: WallMode = "auto",
    threads: int | None = None,
) -> tuple[list[SampledPosition], SampledProfiles]:
    """Measure several palpations (one per sampling position) and place them along the sweep.

    The palpations are measured in ``threads`` threads at once (the tracker's compiled kernels and
    OpenCV release the GIL); each is measured alone, so the result is the same for any ``threads``.

    Parameters
    ----------
    recordings : sequence of Recording
        Palpations with frames of one size, valid probe poses, ContactForce and ProbeDisplacement.
    flexible_layer_mm : float
        Thickness of the flexible layer, mm (paper eq. 10).
    names : sequence of str, optional
        One name per recording (e.g. its file), used in error messages.
    wall : {"auto", "require", "off"}
        Whether each palpation's vessel wall is measured (see :func:`measure_palpation`).
    threads : int, optional
        Palpations measured at once (None: one per core, at most one per palpation).

    Returns
    -------
    measured : list of SampledPosition
        Each palpation's stiffness, tracks and regression observations.
    sampled : SampledProfiles
        Each position (the mean probe-surface position of its valid poses, base frame, mm), its
        stiffness profile (what :func:`usdeform.correction.correct_recording` interpolates) and its
        lumens at contact.
    """
    names = [f"palpation {index}" for index in range(len(recordings))] if names is None else list(names)
    if len(names) != len(recordings) or not recordings:
        raise InputError(f"recordings: expected one or more palpations, one name each, got {len(recordings)}")
    shapes = {recording.shape for recording in recordings}
    if len(shapes) > 1:
        raise InputError(f"palpations: frames must have one size, got {sorted(shapes)} (rows, cols)")
    workers = threads_argument(threads) or available_cores()
    for name, recording in zip(names, recordings, strict=True):
        if not recording.pose_valid.any():
            raise InputError(f"{name}: no frame has a valid probe pose")
    positions = [probe_surface_positions(r.probe_to_base[r.pose_valid]).mean(axis=0) for r in recordings]
    measured = []
    with ThreadPoolExecutor(min(workers, len(recordings))) as pool:
        runs = [pool.submit(measure_palpation, recording, flexible_layer_mm, wall=wall) for recording in recordings]
        try:
            for name, run in zip(names, runs, strict=True):
                try:
                    measured.append(run.result())
                except (InputError, FitError) as error:
                    raise type(error)(f"{name}: {error}") from None
        finally:  # the first failure in order is raised; palpations not started are not measured
            for run in runs:
                run.cancel()
    lumens = tuple((m.observations.vessel, *m.observations.other_vessels) for m in measured)
    return measured, SampledProfiles(np.array(positions), tuple(m.stiffness.profile for m in measured), lumens)
