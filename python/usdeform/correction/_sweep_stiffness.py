"""Each frame of a sweep's stiffness profile: interpolated from the palpated positions (paper eqs. 12-14), or
rescaled to the frame's own ContactForce and ProbeDisplacement."""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np

from .._arrays import interpolate_in_time
from ..errors import InputError
from ..options import StiffnessSource, checked_option
from ..recording import Recording
from ..regression import StiffnessProfile
from ._propagation import SampledProfiles, probe_surface_positions

__all__ = [
    "STIFFNESS_SOURCE_CHOICES",
    "STIFFNESS_SOURCE_FIELD",
    "StiffnessSourceChoice",
    "stiffness_source_for",
    "sweep_profiles",
]

#: What a caller may ask for as a sweep's stiffness source: one of the sources
#: (:data:`~usdeform.options.StiffnessSource`), or ``"auto"``, which picks one per recording
#: (:func:`stiffness_source_for`).
StiffnessSourceChoice = Literal["auto", "interpolated", "sweep"]


STIFFNESS_SOURCE_CHOICES: tuple[StiffnessSourceChoice, ...] = get_args(StiffnessSourceChoice)


#: Header field of a corrected recording (its ``metadata``, written to the sequence file) naming the
#: stiffness source its correction used.
STIFFNESS_SOURCE_FIELD = "StiffnessSource"


def stiffness_source_for(recording: Recording, stiffness_source: StiffnessSourceChoice = "auto") -> StiffnessSource:
    """The stiffness source a sweep is corrected with: ``stiffness_source`` itself, or for ``"auto"``
    ``"sweep"`` where every frame records a finite ContactForce and ProbeDisplacement, else
    ``"interpolated"``.

    On an independent 3D sweep (161 frames at 15 N, stiffness varying by 20-35 % along the path) the
    sweep's own force and displacement gave a mean Dice of 0.992 (worst frame 0.987) against 0.970
    (0.893) interpolated.

    Examples
    --------
    >>> import dataclasses
    >>> frames = np.zeros((2, 4, 4), np.uint8)
    >>> poses = np.tile(np.eye(4), (2, 1, 1))
    >>> sweep = Recording(frames, np.arange(2.0), poses, np.ones(2, bool), np.eye(4), force=np.ones(2))
    >>> stiffness_source_for(sweep), stiffness_source_for(dataclasses.replace(sweep, probe_displacement=np.ones(2)))
    ('interpolated', 'sweep')
    """
    choice = checked_option("stiffness_source", stiffness_source, STIFFNESS_SOURCE_CHOICES)
    if choice != "auto":
        return choice
    recorded = (recording.force, recording.probe_displacement)
    return "sweep" if all(v is not None and np.all(np.isfinite(v)) for v in recorded) else "interpolated"


def sweep_profiles(
    recording: Recording,
    sampled: SampledProfiles,
    *,
    stiffness_source: StiffnessSourceChoice = "auto",
    name: str = "sweep",
) -> np.ndarray:
    """Each frame's stiffness profile.

    ``"interpolated"`` (paper eqs. 13-14): the probe's surface position
    (:func:`~usdeform.correction.probe_surface_positions`) of each frame is weighted against the sampled
    positions; frames without a valid pose take the
    position interpolated in time. ``"sweep"``: that profile scaled (all three coefficients) so that
    it reaches the frame's recorded ContactForce at its recorded ProbeDisplacement, the stiffness the
    sweep itself measured (lambda at a known force); frames whose force, displacement or interpolated
    force there is not positive keep the interpolated profile. The recorded lambda must count from the
    unloaded surface, as the palpations' does. ``"auto"``: ``"sweep"`` where every frame records both,
    else ``"interpolated"`` (:func:`stiffness_source_for`).

    Parameters
    ----------
    recording : Recording
        The sweep.
    sampled : SampledProfiles
        Palpated positions in the base frame, ``(n, 3)`` mm, and their profiles.
    stiffness_source : {"auto", "interpolated", "sweep"}
        Where the stiffness comes from.
    name : str
        What to call the recording in errors.

    Returns
    -------
    ndarray
        ``(n_frames, 3)`` of ``(c1, c2, c3)``.
    """
    source = stiffness_source_for(recording, stiffness_source)
    if sampled.positions_mm.shape[1:] != (3,):
        raise InputError(
            "sampled_positions: correcting a sweep needs the palpations' 3-D positions in the base frame, "
            "as 'usdeform fit' records them"
        )
    valid = recording.posed_indices(name)
    surface = probe_surface_positions(recording.probe_to_base[valid])
    positions = interpolate_in_time(recording.timestamps, recording.timestamps[valid], surface)
    profiles = sampled.along(positions)
    if source == "interpolated":
        return profiles
    if recording.force is None or recording.probe_displacement is None:
        raise InputError(f"{name}: stiffness_source='sweep' needs each frame's ContactForce and ProbeDisplacement")
    lambdas, forces = recording.probe_displacement, recording.force
    interpolated_force = np.array(
        [StiffnessProfile(*profile).force_at(lam) for profile, lam in zip(profiles, lambdas, strict=True)]
    )
    measurable = (lambdas > 0) & (forces > 0) & (interpolated_force > 0)
    scale = np.where(measurable, forces / np.where(measurable, interpolated_force, 1.0), 1.0)
    return profiles * scale[:, np.newaxis]
