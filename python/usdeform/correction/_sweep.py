"""A sweep corrected to zero force: each frame warped back with its stiffness profile and placed where it belongs.

Geometry of corrected frames: a corrected frame is an image of the tissue at zero force, whose top
row touches the unloaded surface. It therefore belongs at the probe pose moved back, against the probe
axis (the probe frame's +z points into the tissue), by the frame's probe displacement lambda
(:func:`zero_force_probe_to_base`); left at the pressed-in pose it would sit lambda too deep.

Pixels without data: the warp samples some pixels of a corrected frame from outside the frame (its
edges); they hold 0, not tissue. :func:`correct_recording` returns their mask as the recording's
``pixel_valid``, and compounding leaves them out of the image and the coverage, as the fused
:func:`correct_and_compound` does. A corrected sequence written to a file keeps the mask in a companion
file (:func:`usdeform.io.pixel_valid_path`).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence

import numpy as np

from ..errors import InputError
from ..options import Compounding, Interpolation
from ..recording import Recording
from ..regression import DeformationModel, LumenTrack, StiffnessProfile, VesselAnchor, VesselAnchoredModel
from ..validation import forces_in_range
from ..volume import (
    DEFAULT_MAX_BYTES,
    DEFAULT_SPACING_MM,
    Compounder,
    HoleFillingElement,
    Volume,
    VoxelType,
    finish_volume,
    grid_for_frames,
)
from ._coverage import LumenCoverageWarning, uncovered_lumens
from ._frames import correct_frames
from ._propagation import SampledProfiles
from ._sweep_stiffness import STIFFNESS_SOURCE_FIELD, StiffnessSourceChoice, stiffness_source_for, sweep_profiles

__all__ = ["correct_and_compound", "correct_recording", "frame_probe_displacements", "zero_force_probe_to_base"]


def zero_force_probe_to_base(probe_to_base: np.ndarray, probe_displacement_mm: np.ndarray) -> np.ndarray:
    """Probe poses moved back against the probe axis by each frame's probe displacement: where the
    probe face touched the unloaded surface, the pose of a frame corrected to zero force.

    Parameters
    ----------
    probe_to_base : ndarray
        ``(n, 4, 4)`` pressed-in probe poses, mm; the probe frame's +z points into the tissue.
    probe_displacement_mm : ndarray
        ``(n,)`` probe displacement lambda along the probe axis, mm (positive pressed in).

    Returns
    -------
    ndarray
        ``(n, 4, 4)`` poses, ``probe_to_base @ translation(0, 0, -lambda)``.

    Examples
    --------
    >>> zero_force_probe_to_base(np.eye(4)[np.newaxis], np.array([3.0]))[0, :3, 3].tolist()
    [0.0, 0.0, -3.0]
    """
    poses = np.asarray(probe_to_base, dtype=np.float64)
    lambdas = np.asarray(probe_displacement_mm, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or lambdas.shape != poses.shape[:1]:
        raise InputError(
            f"probe_to_base, probe_displacement_mm: expected (n, 4, 4) poses and (n,) displacements, "
            f"got shapes {poses.shape} and {lambdas.shape}"
        )
    pulled_back = np.tile(np.eye(4), (len(poses), 1, 1))
    pulled_back[:, 2, 3] = -lambdas
    return poses @ pulled_back


def frame_probe_displacements(recording: Recording, profiles: np.ndarray, *, name: str = "sweep") -> np.ndarray:
    """Each frame's probe displacement lambda (mm): the recorded ProbeDisplacement, or, where the
    recording has none, the lambda at which the frame's stiffness profile reaches its ContactForce.

    Parameters
    ----------
    recording : Recording
        The sweep, with each frame's force.
    profiles : ndarray
        ``(n_frames, 3)`` stiffness profiles ``(c1, c2, c3)`` (see :func:`sweep_profiles`).
    name : str
        What to call the recording in errors.

    Returns
    -------
    ndarray
        ``(n_frames,)`` lambda, mm.
    """
    if recording.probe_displacement is not None:
        return np.asarray(recording.probe_displacement, dtype=np.float64)
    if recording.force is None:
        raise InputError(f"{name}: placing corrected frames needs each frame's ProbeDisplacement or ContactForce")
    lambdas = np.array(
        [StiffnessProfile(*profile).lambda_at(force) for profile, force in zip(profiles, recording.force, strict=True)]
    )
    unreached = np.flatnonzero(~np.isfinite(lambdas))
    if unreached.size:
        frame = int(unreached[0])
        raise InputError(
            f"{name}: frame {frame} has no ProbeDisplacement and its stiffness profile never reaches its "
            f"ContactForce {recording.force[frame]:.3g} N"
        )
    return lambdas


def _with_forces_in_range(recording: Recording, model: DeformationModel, clamp_force: bool, name: str) -> Recording:
    """``recording`` with its ContactForce checked against the model's fitted range, clamped where
    ``clamp_force`` allows it (:func:`~usdeform.validation.forces_in_range`); InputError without a force."""
    if recording.force is None:
        raise InputError(f"{name}: correction needs each frame's ContactForce")
    force = forces_in_range(
        recording.force, model.normalization.force_scale, clamp=clamp_force, name=f"{name}: ContactForce"
    )
    return recording if force is recording.force else dataclasses.replace(recording, force=force)


def correct_recording(
    recording: Recording,
    model: DeformationModel,
    sampled: SampledProfiles,
    *,
    stiffness_source: StiffnessSourceChoice = "auto",
    clamp_force: bool = False,
    name: str = "sweep",
    lumen_track: LumenTrack | None = None,
) -> Recording:
    """The recording with every frame warped back to zero force and placed where it belongs.

    Each corrected frame images the tissue at zero force, so its probe pose is moved back against
    the probe axis by the frame's probe displacement (:func:`zero_force_probe_to_base`; lambda from
    :func:`frame_probe_displacements`), and its ContactForce and ProbeDisplacement become 0: the
    corrected recording describes an unloaded probe on the unloaded surface (correcting it again
    changes nothing).

    Parameters
    ----------
    recording : Recording
        The sweep, with each frame's force; its frames must have the model's ``frame_shape``.
    model : DisplacementModel or VesselAnchoredModel
        The fitted model (a vessel-anchored one is placed on each frame's own lumen, see
        :func:`~usdeform.correction.correct_frames`).
    sampled : SampledProfiles
        Where the stiffness was palpated (see :func:`sweep_profiles`). Where it records the palpations'
        lumens and the model is vessel-anchored, a :class:`LumenCoverageWarning` names the frames whose
        lumens lie beyond them (:func:`uncovered_lumens`; not for a part of a sweep, ``lumen_track``).
    stiffness_source : {"auto", "interpolated", "sweep"}
        Each frame's stiffness from the sampled positions or from its own force and displacement
        (see :func:`sweep_profiles`); ``"auto"``: from its own where every frame records both
        (:func:`stiffness_source_for`).
    clamp_force : bool
        Clamp forces outside the model's fitted range into it, with a warning, instead of refusing
        them (:func:`~usdeform.validation.forces_in_range`).
    name : str
        What to call the recording in errors.
    lumen_track : LumenTrack, optional
        A vessel-anchored model's lumen search of the sweep's earlier frames, to go on from and update
        (see :func:`~usdeform.correction.correct_frames`): the recording is the next part of a sweep.

    Returns
    -------
    Recording
        Corrected frames at the zero-force poses, with zero force and displacement; its
        ``pixel_valid`` is False where a pixel's source lies outside its frame (it holds 0, not data),
        and compounding leaves such pixels out. Its ``metadata[STIFFNESS_SOURCE_FIELD]`` names the
        stiffness source used.
    """
    if tuple(recording.shape) != model.frame_shape:
        rows, cols = recording.shape
        fitted_rows, fitted_cols = model.frame_shape or (0, 0)  # always set on a model
        raise InputError(
            f"{name}: frames of {rows} x {cols} pixels, but the model was fitted on "
            f"{fitted_rows} x {fitted_cols} frames"
        )
    recording = _with_forces_in_range(recording, model, clamp_force, name)
    assert recording.force is not None  # checked by _with_forces_in_range
    source = stiffness_source_for(recording, stiffness_source)
    profiles = sweep_profiles(recording, sampled, stiffness_source=source, name=name)
    lambdas = frame_probe_displacements(recording, profiles, name=name)
    corrected, pixel_valid = correct_frames(
        recording.frames, recording.force, profiles, model, return_mask=True, lumen_track=lumen_track
    )
    if isinstance(model, VesselAnchoredModel) and sampled.lumens is not None and lumen_track is None:
        _warn_uncovered(recording, profiles, model, sampled.lumens)
    return dataclasses.replace(
        recording,
        frames=corrected,
        pixel_valid=pixel_valid,
        probe_to_base=zero_force_probe_to_base(recording.probe_to_base, lambdas),
        force=np.zeros(len(recording)),
        probe_displacement=np.zeros(len(recording)),
        metadata={**recording.metadata, STIFFNESS_SOURCE_FIELD: source},
    )


def _warn_uncovered(
    recording: Recording,
    profiles: np.ndarray,
    model: VesselAnchoredModel,
    palpated: Sequence[Sequence[VesselAnchor | None]],
) -> None:
    """Warn (:class:`LumenCoverageWarning`) for each vessel whose zero-force lumens leave the palpated
    depths or radii in some frames (:func:`uncovered_lumens`); the lumens are searched again."""
    from ..metrics import pixel_size_mm
    from ._vessel import further_lumens, sweep_lumens

    assert recording.force is not None  # checked by correct_recording
    found = [sweep_lumens(recording.frames, recording.force, profiles, model)]
    if model.other_vessels:
        found += further_lumens(recording.frames, recording.force, profiles, model, found[0])
    for uncovered in uncovered_lumens(found, palpated, pixel_size_mm(recording.image_to_probe)):
        warnings.warn(uncovered.message(), LumenCoverageWarning, stacklevel=3)


def correct_and_compound(
    recording: Recording,
    model: DeformationModel,
    sampled: SampledProfiles,
    *,
    stiffness_source: StiffnessSourceChoice = "auto",
    clamp_force: bool = False,
    spacing_mm: float = DEFAULT_SPACING_MM,
    interpolation: Interpolation = "nearest",
    compounding: Compounding = "mean",
    hole_filling: Sequence[HoleFillingElement] = (),
    voxel_type: VoxelType = "float32",
    max_bytes: int = DEFAULT_MAX_BYTES,
    name: str = "sweep",
) -> Volume:
    """Correct a sweep's tracked frames to zero force and compound them at their zero-force poses,
    fused for a model in image coordinates (the corrected frames are never all held in memory; a
    vessel-anchored model's are, as in :func:`correct_recording`); the volume equals compounding
    :func:`correct_recording`'s recording (pixels sampled from outside their frame left out).

    Parameters
    ----------
    recording, model, sampled, stiffness_source, clamp_force, name
        As for :func:`correct_recording` (:func:`stiffness_source_for` tells which source ``"auto"`` uses).
    spacing_mm : float
        Voxel size, mm; the grid encloses the frames at their zero-force poses.
    interpolation, compounding
        As for :class:`~usdeform.volume.Compounder`.
    hole_filling, voxel_type, max_bytes
        As for :func:`finish_volume` (default: no hole filling).

    Returns
    -------
    Volume
    """
    recording = _with_forces_in_range(recording, model, clamp_force, name)
    assert recording.force is not None  # checked by _with_forces_in_range
    profiles = sweep_profiles(recording, sampled, stiffness_source=stiffness_source, name=name)
    lambdas = frame_probe_displacements(recording, profiles, name=name)
    valid = recording.posed_indices(name)
    image_to_base = zero_force_probe_to_base(recording.probe_to_base[valid], lambdas[valid]) @ recording.image_to_probe
    grid = grid_for_frames(image_to_base, recording.shape, spacing_mm)
    compounder = Compounder(grid, interpolation, compounding, max_bytes=max_bytes)
    if model.anchor == "vessel":
        # Every frame corrected as correct_recording does (each lumen is searched where the previous
        # frame's was, frames without a pose included), then the posed ones inserted.
        corrected, pixel_valid = correct_frames(recording.frames, recording.force, profiles, model, return_mask=True)
        compounder.add_frames(corrected[valid], image_to_base, valid=pixel_valid[valid])
    else:
        compounder.add_corrected_frames(
            recording.frames[valid], image_to_base, recording.force[valid], profiles[valid], model.image_model
        )
    return finish_volume(compounder.volume(), hole_filling=hole_filling, voxel_type=voxel_type, max_bytes=max_bytes)
