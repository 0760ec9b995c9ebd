"""Correction: warp frames back to zero force (paper Section III-B).

Backward mapping: the zero-force pixel at ``(x, y)`` is read, bilinearly, from the deformed frame
at ``(x, y) + D(x, y, F)``, with ``D`` the regression's displacement at the frame's force and
stiffness profile. Sources outside the frame give ``fill`` and are marked invalid in the validity
mask: they hold no data, and compounding leaves them out.

A :class:`~usdeform.regression.DisplacementModel` is warped by the compiled kernel; a
:class:`~usdeform.regression.VesselAnchoredModel` by
:func:`usdeform.correction._vessel.correct_vessel_anchored`, which places its vessel part on each
frame's own lumen. :func:`correct_frames` takes either.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import singledispatch
from typing import Literal, overload

import numpy as np

from .. import _core
from .._arrays import frames_array
from ..errors import InputError
from ..regression import (
    DeformationModel,
    DisplacementModel,
    LumenTrack,
    StiffnessProfile,
    VesselAnchoredModel,
    correction_forces,
    profiles_array,
)
from ..validation import threads_argument

__all__ = ["correct_frames", "correct_like"]

#: What the correction entry points accept as per-frame stiffness profiles.
Profiles = StiffnessProfile | Sequence[StiffnessProfile] | np.ndarray
#: What they accept as per-frame forces (N): one per frame, or one for all.
Forces = np.ndarray | Sequence[float] | float


@overload
def correct_frames(
    frames: np.ndarray,
    forces: Forces,
    profiles: Profiles,
    model: DeformationModel,
    *,
    fill: float = 0.0,
    threads: int | None = None,
    return_mask: Literal[False] = False,
    clamp_force: bool = False,
    lumen_track: LumenTrack | None = None,
) -> np.ndarray: ...


@overload
def correct_frames(
    frames: np.ndarray,
    forces: Forces,
    profiles: Profiles,
    model: DeformationModel,
    *,
    fill: float = 0.0,
    threads: int | None = None,
    return_mask: Literal[True],
    clamp_force: bool = False,
    lumen_track: LumenTrack | None = None,
) -> tuple[np.ndarray, np.ndarray]: ...


def correct_frames(
    frames: np.ndarray,
    forces: Forces,
    profiles: Profiles,
    model: DeformationModel,
    *,
    fill: float = 0.0,
    threads: int | None = None,
    return_mask: bool = False,
    clamp_force: bool = False,
    lumen_track: LumenTrack | None = None,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Frames warped back to zero force.

    Parameters
    ----------
    frames : ndarray
        ``(n_frames, rows, cols)`` or one ``(rows, cols)`` frame, uint8 or float32; ``(rows, cols)``
        must be the model's ``frame_shape``.
    forces : float or array_like
        Each frame's force (N), or one for all.
    profiles : StiffnessProfile, sequence of StiffnessProfile, or ndarray
        One profile for all frames, one per frame, or an ``(n_frames, 3)`` array of ``(c1, c2, c3)``.
    model : DisplacementModel or VesselAnchoredModel
        The fitted model; a vessel-anchored one is placed on each frame's own lumen
        (:func:`usdeform.correction._vessel.correct_vessel_anchored`; its lumens are searched frame
        after frame, ``threads`` serve its warp).
    fill : float
        Value of pixels whose source lies outside the frame.
    threads : int, optional
        Worker threads (None: all cores; the result does not depend on it).
    return_mask : bool
        Also return the validity mask.
    clamp_force : bool
        Clamp forces outside the model's fitted range into it, with a
        :class:`~usdeform.validation.ForceClampWarning` (default: InputError naming the frame).
    lumen_track : LumenTrack, optional
        With a vessel-anchored model: the lumen search of the sweep's earlier frames, to go on from
        and update (a sweep corrected in parts, e.g. live, finds the lumens it finds in one call);
        ignored by a model in image coordinates, which has no lumen to follow.

    Returns
    -------
    ndarray
        The corrected frames, same shape and dtype as ``frames``.
    ndarray of bool, only with ``return_mask``
        The validity mask, same shape: True where the pixel was sampled inside its frame, False
        where its source lies outside and it holds ``fill`` (no data: leave it out of compounding,
        see :meth:`usdeform.volume.Compounder.add_frames`).

    Raises
    ------
    InputError
        For frames of another shape than the model's, for malformed forces or profiles, for forces
        outside the model's fitted range (see :func:`usdeform.validation.forces_in_range`) and for
        a model whose coefficients cannot come from a fit (:func:`usdeform.regression.check_model`).
    KeyboardInterrupt
        On Ctrl-C (checked every 64 frames).
    """
    request = _Request(frames, forces, profiles, float(fill), threads, clamp_force, lumen_track)
    corrected, valid = _corrected(model, request)
    return (corrected, valid) if return_mask else corrected


@dataclass(frozen=True)
class _Request:
    """What the frames are corrected with: their forces and profiles, and the options (as
    :func:`correct_frames` takes them)."""

    frames: np.ndarray
    forces: Forces
    profiles: Profiles
    fill: float = 0.0
    threads: object = None
    clamp_force: bool = False
    lumen_track: LumenTrack | None = None


@singledispatch
def _corrected(model: object, request: _Request) -> tuple[np.ndarray, np.ndarray]:
    """:func:`correct_frames` for each type of model: the corrected frames and their validity mask."""
    raise InputError(f"model: expected a DisplacementModel or VesselAnchoredModel, got {type(model).__name__}")


@_corrected.register
def _(model: DisplacementModel, request: _Request) -> tuple[np.ndarray, np.ndarray]:
    stack = frames_array(request.frames)
    n_frames = stack.shape[0]
    corrected, valid = _core.warp_frames(
        stack,
        correction_forces(request.forces, n_frames, model, clamp=request.clamp_force),
        profiles_array(request.profiles, n_frames),
        model.kernel,
        fill=request.fill,
        threads=threads_argument(request.threads),
        return_mask=True,
    )
    if np.ndim(request.frames) == 2:
        corrected, valid = corrected[0], valid[0]
    return corrected, valid


@_corrected.register
def _(model: VesselAnchoredModel, request: _Request) -> tuple[np.ndarray, np.ndarray]:
    from ._vessel import correct_vessel_anchored  # loads OpenCV (metrics)

    corrected, valid, _ = correct_vessel_anchored(
        request.frames,
        request.forces,
        request.profiles,
        model,
        fill=request.fill,
        clamp_force=request.clamp_force,
        threads=threads_argument(request.threads),
        track=request.lumen_track,
    )
    return corrected, valid


def correct_like(
    images: np.ndarray, frames: np.ndarray, forces: Forces, profiles: Profiles, model: DeformationModel
) -> np.ndarray:
    """``images`` (one per frame of ``frames``, e.g. masks of the frames' lumens) warped as
    :func:`correct_frames` corrects ``frames``: a vessel-anchored model is placed on the lumens it
    finds in ``frames``, a model in image coordinates warps ``images`` as it would ``frames``.

    Parameters
    ----------
    images : ndarray
        ``(n_frames, rows, cols)``, uint8 or float32.
    frames : ndarray
        The deformed frames, same shape.
    forces, profiles, model
        As for :func:`correct_frames`.

    Returns
    -------
    ndarray
        The warped images, same shape and dtype as ``images``.
    """
    return _corrected_like(model, images, _Request(frames, forces, profiles))


@singledispatch
def _corrected_like(model: object, images: np.ndarray, request: _Request) -> np.ndarray:
    """:func:`correct_like` for each type of model."""
    raise InputError(f"model: expected a DisplacementModel or VesselAnchoredModel, got {type(model).__name__}")


@_corrected_like.register
def _(model: DisplacementModel, images: np.ndarray, request: _Request) -> np.ndarray:
    return correct_frames(images, request.forces, request.profiles, model)


@_corrected_like.register
def _(model: VesselAnchoredModel, images: np.ndarray, request: _Request) -> np.ndarray:
    from ._vessel import checked_sweep, correct_vessel_anchored, further_lumens, sweep_lumens

    stack, forces, profiles = checked_sweep(request.frames, request.forces, request.profiles, model, False)
    anchors = sweep_lumens(stack, forces, profiles, model)
    others = further_lumens(stack, forces, profiles, model, anchors) if model.other_vessels else None
    return correct_vessel_anchored(images, forces, profiles, model, anchors=anchors, other_anchors=others)[0]
