"""Correction with a :class:`~usdeform.regression.VesselAnchoredModel`: its vessel part placed on each
frame's own lumen.

:func:`frame_vessel_anchor` finds a frame's zero-force lumen (in the frame corrected with the vessel
part on the lumen found, until the two agree); :func:`correct_vessel_anchored` corrects a sweep's
frames, each lumen searched where the previous frame's was. :func:`usdeform.correction.correct_frames`
calls it for a vessel-anchored model; the lumen search is :mod:`usdeform.vessel` (OpenCV), so this
module is loaded only when such a model corrects frames.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from . import _core
from ._arrays import frames_array
from .errors import InputError
from .regression import VesselAnchor, VesselAnchoredModel, correction_forces
from .stiffness import StiffnessProfile, profiles_array
from .vessel import Window, find_lumen, same_lumen, search_window, searchable_frame

__all__ = ["ANCHOR_MAX_ITERATIONS", "ANCHOR_TOLERANCE_PX", "correct_vessel_anchored", "frame_vessel_anchor"]

#: Largest change of the lumen's centre and radius, pixels, at which :func:`frame_vessel_anchor` stops.
ANCHOR_TOLERANCE_PX = 0.25
#: Most corrections :func:`frame_vessel_anchor` tries per frame.
ANCHOR_MAX_ITERATIONS = 8


def frame_vessel_anchor(
    frame: np.ndarray,
    force_n: float,
    profile: StiffnessProfile,
    model: VesselAnchoredModel,
    *,
    near: VesselAnchor | None = None,
    clamp_force: bool = False,
) -> VesselAnchor | None:
    """The zero-force lumen of one deformed frame: where the vessel part of ``model`` belongs.

    The lumen is found in the frame corrected by the image part alone (the dark region at or nearest
    to ``near``'s centre, else to the model's reference lumen), then again in the frame corrected with
    the vessel part on the lumen found, until centre and radius change by less than
    :data:`ANCHOR_TOLERANCE_PX` (at most :data:`ANCHOR_MAX_ITERATIONS` corrections). The corrected
    lumen then is the lumen the vessel part was placed on: a fixed point. It converges because the
    vessel part moves the lumen's edge by a fraction of its radius (its collapse), so each step
    shrinks the change by that fraction. A region that does not overlap ``near`` (when given) or the
    previous step's lumen is not taken for the lumen. Each search after the first, and the first when
    ``near`` is given, looks within :data:`~usdeform.vessel.SEARCH_WINDOW_RADII` radii of the lumen expected.

    Parameters
    ----------
    frame : ndarray
        (rows, cols) uint8 or non-negative float32 deformed frame of the model's frame shape.
    force_n : float
        Its force, N; in the model's fitted range unless ``clamp_force``.
    profile : StiffnessProfile
        Its stiffness profile.
    model : VesselAnchoredModel
        The model.
    near : VesselAnchor, optional
        Where the lumen is expected (in a sweep: the previous frame's); None: search from the model's
        reference lumen, without the overlap test.
    clamp_force : bool
        Clamp a force outside the fitted range into it, with a warning (default: InputError).

    Returns
    -------
    VesselAnchor or None
        The lumen at zero force, or None where no lumen is found in the frame.
    """
    shape = model.frame_shape
    image = searchable_frame(frame, shape, "frame")
    force = float(correction_forces(force_n, 1, model, clamp=clamp_force, name="force_n")[0])
    return _zero_force_lumen(image, force, profile, model, model.image_model.displacement(force, profile, shape), near)


def _zero_force_lumen(
    image: np.ndarray,
    force: float,
    profile: StiffnessProfile,
    model: VesselAnchoredModel,
    image_part: np.ndarray,
    near: VesselAnchor | None,
) -> VesselAnchor | None:
    """:func:`frame_vessel_anchor` on a checked frame and force, with the model's image part at that
    force, ``image_part`` (2, rows, cols), already evaluated (the correction warps with it too)."""
    shape = model.frame_shape

    def image_part_on(window: Window) -> np.ndarray:
        return image_part[:, window[0], window[1]]

    def placed_on(lumen: VesselAnchor) -> Callable[[Window], np.ndarray]:
        def field_on(window: Window) -> np.ndarray:
            return image_part_on(window) + model.vessel_displacement(force, profile, shape, lumen, window=window)

        return field_on

    if near is None:
        anchor = find_lumen(image, image_part_on, model.reference.centre_px)
    else:
        anchor = same_lumen(find_lumen(image, image_part_on, near.centre_px, search_window(near, shape)), near)
    for _ in range(ANCHOR_MAX_ITERATIONS):
        if anchor is None:
            return None
        found = find_lumen(image, placed_on(anchor), anchor.centre_px, search_window(anchor, shape))
        found = same_lumen(found, anchor)
        if found is None:
            return anchor
        change = max(*np.abs(np.subtract(found.centre_px, anchor.centre_px)), abs(found.radius_px - anchor.radius_px))
        anchor = found
        if change < ANCHOR_TOLERANCE_PX:
            break
    return anchor


def _anchors_argument(anchors: Sequence[VesselAnchor | None], n_frames: int) -> list[VesselAnchor | None]:
    """``anchors`` checked: one VesselAnchor or None per frame."""
    given = list(anchors)
    if len(given) != n_frames:
        raise InputError(f"anchors: expected one per frame ({n_frames}), got {len(given)}")
    for index, anchor in enumerate(given):
        if anchor is not None and not isinstance(anchor, VesselAnchor):
            raise InputError(f"anchors[{index}]: expected a VesselAnchor or None, got {type(anchor).__name__}")
    return given


def correct_vessel_anchored(
    frames: np.ndarray,
    forces: np.ndarray | Sequence[float] | float,
    profiles: StiffnessProfile | Sequence[StiffnessProfile] | np.ndarray,
    model: VesselAnchoredModel,
    *,
    fill: float = 0.0,
    clamp_force: bool = False,
    anchors: Sequence[VesselAnchor | None] | None = None,
) -> tuple[np.ndarray, np.ndarray, list[VesselAnchor | None]]:
    """Frames warped back to zero force with a vessel-anchored model, its vessel part on each frame's
    own lumen (:func:`frame_vessel_anchor`, searched where the previous frame's lumen was: the frames
    of a sweep follow the vessel). Where a frame's lumen is not found (a lumen pressed shut, or only
    a dark region that does not overlap the last lumen found), the vessel part stays where the last
    lumen was found, or on the model's reference lumen before any; the region the next lumen may lie
    in then grows by the last lumen's size per frame missed, so that a vessel that moved on while
    unseen is found again.

    Parameters
    ----------
    frames : ndarray
        ``(n_frames, rows, cols)`` or one ``(rows, cols)`` frame, uint8 or float32 (non-negative
        where the lumens are searched), of the model's frame shape.
    forces : float or array_like
        Each frame's force (N), or one for all; in the model's fitted range unless ``clamp_force``.
    profiles : StiffnessProfile, sequence of StiffnessProfile, or ndarray
        One profile for all frames, one per frame, or an ``(n_frames, 3)`` array of ``(c1, c2, c3)``.
    model : VesselAnchoredModel
        The fitted model.
    fill : float
        Value of pixels whose source lies outside the frame.
    clamp_force : bool
        Clamp forces outside the model's fitted range into it, with a warning (default: InputError).
    anchors : sequence of VesselAnchor or None, optional
        One per frame: the lumens to place the vessel part on instead of searching the frames (e.g.
        to warp masks or other images of the same frames as the frames were corrected; None
        entries as for a frame whose lumen is not found).

    Returns
    -------
    corrected : ndarray
        The corrected frames, same shape and dtype as ``frames``.
    valid : ndarray of bool
        True where a pixel's source lies inside its frame.
    anchors : list of VesselAnchor or None
        Each frame's zero-force lumen (None: not found there).
    """
    stack = frames_array(frames)
    n_frames, rows, cols = stack.shape
    if (rows, cols) != model.frame_shape:
        raise InputError(f"frames: {rows} x {cols} pixels, but the model was fitted on {model.frame_shape} frames")
    frame_forces = correction_forces(forces, n_frames, model, clamp=clamp_force)
    frame_profiles = profiles_array(profiles, n_frames)
    given = None if anchors is None else _anchors_argument(anchors, n_frames)
    corrected, valid = np.empty_like(stack), np.empty(stack.shape, dtype=bool)
    found: list[VesselAnchor | None] = []
    previous: VesselAnchor | None = None  # the last lumen found
    missed = 0  # frames since it was found
    for index, frame in enumerate(stack):
        profile = StiffnessProfile(*frame_profiles[index])
        force = float(frame_forces[index])
        image_part = model.image_model.displacement(force, profile, (rows, cols))
        if given is None:
            searchable_frame(frame, (rows, cols), f"frames[{index}]")
            # The lumen may have moved on while it was not seen: the region it is expected in grows by
            # its size with every frame since.
            near = None if previous is None else VesselAnchor(previous.centre_px, previous.radius_px * (1 + missed))
            anchor = _zero_force_lumen(frame, force, profile, model, image_part, near)
        else:
            anchor = given[index]
        found.append(anchor)
        previous, missed = (anchor, 0) if anchor is not None else (previous, missed + 1)
        field = image_part + model.vessel_displacement(force, profile, (rows, cols), previous or model.reference)
        warped, inside = _core.warp_by_field(frame[None], field[None], fill=float(fill))
        corrected[index], valid[index] = warped[0], inside[0]
    if np.ndim(frames) == 2:
        return corrected[0], valid[0], found
    return corrected, valid, found
