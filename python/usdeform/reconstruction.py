"""Reconstruction: recordings into volumes, with or without deformation correction.

The stages the command line chains, callable from Python: the PLUS clip rectangle, the output grid
(from a PLUS configuration or enclosing the frames), compounding a recording's tracked frames, the
per-frame stiffness profiles of a sweep from its sampled positions (probe surface positions, poses
interpolated in time where tracking dropped out), and correct-then-compound as one call.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .compounding import DEFAULT_MAX_BYTES, Compounder, grid_for_frames
from .correction import correct_frames
from .errors import InputError
from .io.plus_config import ReconstructionSettings
from .options import COMPOUNDINGS, INTERPOLATIONS, Compounding, Interpolation, checked_option
from .propagation import SampledProfiles
from .recording import Recording
from .regression import DisplacementModel
from .volume import Volume, VoxelGrid

__all__ = [
    "DEFAULT_SPACING_MM",
    "clip_frames",
    "compound_recording",
    "correct_and_compound",
    "correct_recording",
    "interpolate_in_time",
    "probe_surface_positions",
    "sweep_profiles",
]

#: Voxel size when neither the caller nor a PLUS configuration gives one, mm.
DEFAULT_SPACING_MM = 0.5


def clip_frames(
    frames: np.ndarray, image_to_world: np.ndarray, origin: tuple[int, int], size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """The PLUS clip rectangle of every frame, with the poses of the clipped images.

    Parameters
    ----------
    frames : ndarray
        ``(n, rows, cols)`` frames.
    image_to_world : ndarray
        ``(n, 4, 4)`` poses, mm.
    origin : tuple of int
        ``(col, row)`` of the first pixel kept.
    size : tuple of int
        ``(cols, rows)`` of the kept rectangle.

    Returns
    -------
    frames, image_to_world : ndarray
        The clipped frames and their poses (their pixel (0, 0) is the original pixel ``origin``).

    Examples
    --------
    >>> frames = np.zeros((1, 6, 8), np.uint8)
    >>> clipped, poses = clip_frames(frames, np.eye(4)[np.newaxis], origin=(3, 2), size=(4, 3))
    >>> clipped.shape, poses[0, :2, 3].tolist()
    ((1, 3, 4), [3.0, 2.0])
    """
    (col, row), (cols, rows) = origin, size
    if col < 0 or row < 0 or row + rows > frames.shape[1] or col + cols > frames.shape[2]:
        raise InputError(
            f"ClipRectangle: origin {origin} and size {size} (col, row) exceed the "
            f"{frames.shape[1]} x {frames.shape[2]} frames"
        )
    clipped_to_image = np.eye(4)
    clipped_to_image[:2, 3] = (col, row)
    return frames[:, row : row + rows, col : col + cols], image_to_world @ clipped_to_image


def probe_surface_positions(probe_to_base: np.ndarray) -> np.ndarray:
    """Probe positions in the base frame without their component along the probe axis, so that how
    deep the probe pressed does not count in the distances of the stiffness weights.

    Parameters
    ----------
    probe_to_base : ndarray
        ``(n, 4, 4)`` probe poses, mm.

    Returns
    -------
    ndarray
        ``(n, 3)`` positions, mm.
    """
    translation, axis = probe_to_base[:, :3, 3], probe_to_base[:, :3, 2]
    axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
    return translation - np.sum(translation * axis, axis=1, keepdims=True) * axis


def interpolate_in_time(times_s: np.ndarray, known_times_s: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` ``(k, d)`` known at ``known_times_s`` ``(k,)``, linearly interpolated at ``times_s``
    ``(n,)`` (held constant beyond the ends): ``(n, d)``.

    Examples
    --------
    >>> interpolate_in_time(np.array([0.0, 0.5, 2.0]), np.array([0.0, 1.0]), np.array([[0.0], [10.0]])).ravel().tolist()
    [0.0, 5.0, 10.0]
    """
    return np.stack([np.interp(times_s, known_times_s, column) for column in np.asarray(values).T], axis=1)


def _valid_frames(recording: Recording, name: str) -> np.ndarray:
    valid = np.flatnonzero(recording.pose_valid)
    if valid.size == 0:
        raise InputError(f"{name}: no frame has a valid probe pose")
    return valid


def compound_recording(
    recording: Recording,
    *,
    settings: ReconstructionSettings | None = None,
    spacing_mm: float | None = None,
    interpolation: Interpolation | None = None,
    compounding: Compounding | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
    name: str = "recording",
) -> tuple[Volume, int]:
    """Compound a recording's tracked frames into a volume, as PLUS's volume reconstructor does.

    Parameters
    ----------
    recording : Recording
        Frames and poses; frames without a valid pose are left out.
    settings : ReconstructionSettings, optional
        A PLUS configuration's settings: clip rectangle, grid, and the defaults of the options below.
    spacing_mm : float, optional
        Voxel size, mm; given, the grid encloses the frames even when ``settings`` has an extent.
        Default: the configuration's, else :data:`DEFAULT_SPACING_MM`.
    interpolation : {"nearest", "linear"}, optional
        Default: the configuration's, else nearest.
    compounding : {"mean", "max", "latest"}, optional
        Default: the configuration's, else mean.
    max_bytes : int
        Memory limit of the volume.
    name : str
        What to call the recording in errors (e.g. its file).

    Returns
    -------
    volume : Volume
        The image and its coverage weight.
    n_frames : int
        How many frames were compounded.
    """
    valid = _valid_frames(recording, name)
    frames, image_to_base = recording.frames[valid], recording.image_to_base[valid]
    if settings is not None and settings.clip_rectangle_origin is not None and settings.clip_rectangle_size:
        frames, image_to_base = clip_frames(
            frames, image_to_base, settings.clip_rectangle_origin, settings.clip_rectangle_size
        )
    grid: VoxelGrid
    if settings is not None and settings.output_extent is not None and spacing_mm is None:
        grid = settings.voxel_grid()
    else:
        spacing = spacing_mm or (settings.output_spacing_mm if settings is not None else DEFAULT_SPACING_MM)
        grid = grid_for_frames(image_to_base, (frames.shape[1], frames.shape[2]), spacing)
    interpolation = interpolation or checked_option(
        "interpolation", settings.interpolation if settings is not None else "nearest", INTERPOLATIONS
    )
    compounding = compounding or checked_option(
        "compounding", settings.compounding if settings is not None else "mean", COMPOUNDINGS
    )
    compounder = Compounder(grid, interpolation, compounding, max_bytes=max_bytes)
    compounder.add_frames(frames, image_to_base)
    return compounder.volume(), len(valid)


def sweep_profiles(recording: Recording, sampled: SampledProfiles, *, name: str = "sweep") -> np.ndarray:
    """Each frame's stiffness profile from the sampled positions (paper eqs. 13-14).

    The probe's surface position (:func:`probe_surface_positions`) of each frame is weighted against
    the sampled positions; frames without a valid pose take the position interpolated in time.

    Parameters
    ----------
    recording : Recording
        The sweep.
    sampled : SampledProfiles
        Palpated positions in the base frame, ``(n, 3)`` mm, and their profiles.
    name : str
        What to call the recording in errors.

    Returns
    -------
    ndarray
        ``(n_frames, 3)`` of ``(c1, c2, c3)``.
    """
    if sampled.positions_mm.shape[1:] != (3,):
        raise InputError(
            "sampled_positions: correcting a sweep needs the palpations' 3-D positions in the base frame, "
            "as 'usdeform fit' records them"
        )
    valid = _valid_frames(recording, name)
    surface = probe_surface_positions(recording.probe_to_base[valid])
    positions = interpolate_in_time(recording.timestamps, recording.timestamps[valid], surface)
    return sampled.along(positions)


def correct_recording(
    recording: Recording, model: DisplacementModel, sampled: SampledProfiles, *, name: str = "sweep"
) -> Recording:
    """The recording with every frame warped back to zero force.

    Parameters
    ----------
    recording : Recording
        The sweep, with each frame's force; its frames must have the model's ``frame_shape``.
    model : DisplacementModel
        The fitted model.
    sampled : SampledProfiles
        Where the stiffness was palpated (see :func:`sweep_profiles`).
    name : str
        What to call the recording in errors.

    Returns
    -------
    Recording
        The same recording with corrected frames.
    """
    if recording.force is None:
        raise InputError(f"{name}: correction needs each frame's ContactForce")
    if tuple(recording.shape) != model.frame_shape:
        rows, cols = recording.shape
        raise InputError(
            f"{name}: frames of {rows} x {cols} pixels, but the model was fitted on "
            f"{model.kernel.frame_shape[0]} x {model.kernel.frame_shape[1]} frames"
        )
    profiles = sweep_profiles(recording, sampled, name=name)
    corrected = correct_frames(recording.frames, recording.force, profiles, model)
    return dataclasses.replace(recording, frames=corrected)


def correct_and_compound(
    recording: Recording,
    model: DisplacementModel,
    sampled: SampledProfiles,
    *,
    spacing_mm: float = DEFAULT_SPACING_MM,
    interpolation: Interpolation = "nearest",
    compounding: Compounding = "mean",
    max_bytes: int = DEFAULT_MAX_BYTES,
    name: str = "sweep",
) -> Volume:
    """Correct a sweep's tracked frames to zero force and compound them, fused (the corrected frames
    are never all held in memory); the volume equals compounding :func:`correct_recording`'s frames.

    Parameters
    ----------
    recording, model, sampled, name
        As for :func:`correct_recording`.
    spacing_mm : float
        Voxel size, mm; the grid encloses the frames.
    interpolation, compounding, max_bytes
        As for :class:`~usdeform.compounding.Compounder`.

    Returns
    -------
    Volume
    """
    if recording.force is None:
        raise InputError(f"{name}: correction needs each frame's ContactForce")
    profiles = sweep_profiles(recording, sampled, name=name)
    valid = _valid_frames(recording, name)
    image_to_base = recording.image_to_base[valid]
    grid = grid_for_frames(image_to_base, recording.shape, spacing_mm)
    compounder = Compounder(grid, interpolation, compounding, max_bytes=max_bytes)
    compounder.add_corrected_frames(
        recording.frames[valid], image_to_base, recording.force[valid], profiles[valid], model
    )
    return compounder.volume()
