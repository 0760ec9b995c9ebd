"""Correction: frames and sweeps warped back to zero force (paper Section III-B, eqs. 12-14).

Two ways in: :func:`correct_frames` warps frames, given each frame's force and stiffness profile;
:func:`correct_recording` corrects a sweep (a :class:`~usdeform.recording.Recording`) with the stiffness
propagated from the palpated positions, and places each frame at its zero-force pose. A vessel-anchored
model's vessel part is placed on each frame's own lumen (the lumen search below).

Behind the door: :mod:`._frames` (the warp), :mod:`._vessel` (the lumen search and the vessel-anchored
warp), :mod:`._propagation` (stiffness between palpated positions), :mod:`._coverage` (a sweep's lumens against
the palpated ones), :mod:`._sweep_stiffness` (each
sweep frame's stiffness profile) and :mod:`._sweep` (a sweep corrected and placed).
"""

from __future__ import annotations

from ._coverage import (
    DEPTH_MARGIN_RADII,
    RADIUS_MARGIN_FRACTION,
    LumenCoverageWarning,
    UncoveredLumens,
    uncovered_lumens,
)
from ._frames import Forces, Profiles, correct_frames
from ._propagation import (
    SampledProfiles,
    interpolate_profile,
    inverse_distance_weights,
    probe_surface_positions,
    profiles_along_sweep,
)
from ._sweep import correct_recording, frame_probe_displacements, zero_force_probe_to_base
from ._sweep_stiffness import (
    STIFFNESS_SOURCE_CHOICES,
    STIFFNESS_SOURCE_FIELD,
    StiffnessSourceChoice,
    stiffness_source_for,
    sweep_profiles,
)
from ._vessel import (
    ANCHOR_MAX_ITERATIONS,
    ANCHOR_TOLERANCE_PX,
    SEARCH_WINDOW_RADII,
    checked_sweep,
    frame_vessel_anchor,
    further_lumens,
    lumen_search,
    searchable_frames,
    searched_lumen,
    sweep_lumens,
    vessel_placements,
)

__all__ = [
    "ANCHOR_MAX_ITERATIONS",
    "ANCHOR_TOLERANCE_PX",
    "DEPTH_MARGIN_RADII",
    "RADIUS_MARGIN_FRACTION",
    "SEARCH_WINDOW_RADII",
    "STIFFNESS_SOURCE_CHOICES",
    "STIFFNESS_SOURCE_FIELD",
    "Forces",
    "LumenCoverageWarning",
    "Profiles",
    "SampledProfiles",
    "StiffnessSourceChoice",
    "UncoveredLumens",
    "checked_sweep",
    "correct_frames",
    "correct_recording",
    "frame_probe_displacements",
    "frame_vessel_anchor",
    "further_lumens",
    "interpolate_profile",
    "inverse_distance_weights",
    "lumen_search",
    "probe_surface_positions",
    "profiles_along_sweep",
    "searchable_frames",
    "searched_lumen",
    "stiffness_source_for",
    "sweep_lumens",
    "sweep_profiles",
    "uncovered_lumens",
    "vessel_placements",
    "zero_force_probe_to_base",
]
