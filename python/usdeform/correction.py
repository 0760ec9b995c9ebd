"""Correction: warp frames back to zero force (paper Section III-B).

Backward mapping: the zero-force pixel at ``(x, y)`` is read, bilinearly, from the deformed frame
at ``(x, y) + D(x, y, F)``, with ``D`` the regression's displacement at the frame's force and
stiffness profile. Sources outside the frame give ``fill`` and are marked invalid in the validity
mask: they hold no data, and compounding leaves them out.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, overload

import numpy as np

from . import _core
from ._arrays import frames_array
from .regression import DisplacementModel, VesselAnchoredModel
from .stiffness import StiffnessProfile, profiles_array
from .validation import correction_forces, threads_argument

__all__ = ["correct_frames"]

#: What the correction entry points accept as per-frame stiffness profiles.
Profiles = StiffnessProfile | Sequence[StiffnessProfile] | np.ndarray
#: What they accept as per-frame forces (N): one per frame, or one for all.
Forces = np.ndarray | Sequence[float] | float


@overload
def correct_frames(
    frames: np.ndarray,
    forces: Forces,
    profiles: Profiles,
    model: DisplacementModel | VesselAnchoredModel,
    *,
    fill: float = 0.0,
    threads: int | None = None,
    return_mask: Literal[False] = False,
    clamp_force: bool = False,
) -> np.ndarray: ...


@overload
def correct_frames(
    frames: np.ndarray,
    forces: Forces,
    profiles: Profiles,
    model: DisplacementModel | VesselAnchoredModel,
    *,
    fill: float = 0.0,
    threads: int | None = None,
    return_mask: Literal[True],
    clamp_force: bool = False,
) -> tuple[np.ndarray, np.ndarray]: ...


def correct_frames(
    frames: np.ndarray,
    forces: Forces,
    profiles: Profiles,
    model: DisplacementModel | VesselAnchoredModel,
    *,
    fill: float = 0.0,
    threads: int | None = None,
    return_mask: bool = False,
    clamp_force: bool = False,
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
        (:func:`usdeform.vessel_wall.correct_vessel_anchored`; ``threads`` does not apply).
    fill : float
        Value of pixels whose source lies outside the frame.
    threads : int, optional
        Worker threads (None: all cores; the result does not depend on it).
    return_mask : bool
        Also return the validity mask.
    clamp_force : bool
        Clamp forces outside the model's fitted range into it, with a
        :class:`~usdeform.validation.ForceClampWarning` (default: InputError naming the frame).

    Returns
    -------
    ndarray
        The corrected frames, same shape and dtype as ``frames``.
    ndarray of bool, only with ``return_mask``
        The validity mask, same shape: True where the pixel was sampled inside its frame, False
        where its source lies outside and it holds ``fill`` (no data: leave it out of compounding,
        see :meth:`usdeform.compounding.Compounder.add_frames`).

    Raises
    ------
    InputError
        For frames of another shape than the model's, for malformed forces or profiles, for forces
        outside the model's fitted range (see :func:`usdeform.validation.forces_in_range`) and for
        a model whose coefficients cannot come from a fit (:func:`usdeform.validation.check_model`).
    KeyboardInterrupt
        On Ctrl-C (checked every 64 frames).
    """
    if isinstance(model, VesselAnchoredModel):
        from .vessel_wall import correct_vessel_anchored  # vessel_wall imports the tracking stage

        threads_argument(threads)  # checked, though the vessel-anchored path does not use it

        corrected, valid, _ = correct_vessel_anchored(
            frames, forces, profiles, model, fill=fill, clamp_force=clamp_force
        )
        return (corrected, valid) if return_mask else corrected
    stack = frames_array(frames)
    n_frames = stack.shape[0]
    corrected, valid = _core.warp_frames(
        stack,
        correction_forces(forces, n_frames, model, clamp=clamp_force),
        profiles_array(profiles, n_frames),
        model.kernel,
        fill=float(fill),
        threads=threads_argument(threads),
        return_mask=True,
    )
    if np.ndim(frames) == 2:
        corrected, valid = corrected[0], valid[0]
    return (corrected, valid) if return_mask else corrected
