"""Correction with a :class:`~usdeform.regression.VesselAnchoredModel`: its vessel part placed on each
frame's own lumen.

:func:`frame_vessel_anchor` finds a frame's zero-force lumen (in the frame corrected with the vessel
part on the lumen found, until the two agree); :func:`sweep_lumens` finds a sweep's, each searched
where the previous frame's was (both compiled, ``usdeform._core.sweep_lumens``; the twin is
:func:`usdeform.reference.sweep_lumens`), and :func:`vessel_placements` says where each frame's
vessel part goes; :func:`correct_vessel_anchored` corrects the frames with them in one compiled call
(the model's field, the vessel part on each lumen and the warp, fused; threads over rows).
:func:`usdeform.correction.correct_frames` and
:meth:`usdeform.volume.Compounder.add_corrected_frames` call these for a vessel-anchored model.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .. import _core
from .._arrays import frames_array
from ..errors import InputError
from ..metrics import MIN_AREA_PX, MIN_CONTRAST, SMOOTHING_SIGMA_PX, THRESHOLD_FRACTION, segment_vessel
from ..regression import (
    LumenTrack,
    StiffnessProfile,
    VesselAnchor,
    VesselAnchoredModel,
    correction_forces,
    profiles_array,
)
from ..validation import threads_argument
from ._folds import vessel_part_scales

__all__ = [
    "ANCHOR_MAX_ITERATIONS",
    "ANCHOR_TOLERANCE_PX",
    "SEARCH_WINDOW_RADII",
    "checked_sweep",
    "correct_vessel_anchored",
    "distinct_lumens",
    "frame_vessel_anchor",
    "further_lumens",
    "lumen_search",
    "searchable_frames",
    "searched_lumen",
    "sweep_lumens",
    "track_state",
    "update_track",
    "vessel_placements",
]

#: Largest change of the lumen's centre and radius, pixels, at which :func:`frame_vessel_anchor` stops.
ANCHOR_TOLERANCE_PX = 0.25
#: Most corrections :func:`frame_vessel_anchor` tries per frame.
ANCHOR_MAX_ITERATIONS = 8
#: Half-width, in the expected lumen's radii, of the square a lumen is searched in when it is expected
#: somewhere (the previous frame's lumen, the previous correction's): the segmentation and its warp then
#: cover a part of the frame; a lumen reaching the square's edge, or none in it, is searched again in the
#: whole frame.
SEARCH_WINDOW_RADII = 2.5


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
    ``near`` is given, looks within :data:`SEARCH_WINDOW_RADII` radii of the lumen expected, and in
    the whole frame where that square holds none of it or only a part.

    A search warps its window back with the model's field (bilinear, the frame's edge replicated) and
    segments the dark region as :func:`usdeform.metrics.segment_vessel` does with its default
    settings; the lumen is the region's centroid and equivalent radius.

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
    image = searchable_frames(frame, model.frame_shape, "frame")
    force = correction_forces(force_n, 1, model, clamp=clamp_force, name="force_n")
    return _search(image[np.newaxis], force, profiles_array(profile, 1), model, LumenTrack(last_found=near))[0]


def sweep_lumens(
    frames: np.ndarray,
    forces: np.ndarray,
    profiles: np.ndarray,
    model: VesselAnchoredModel,
    track: LumenTrack | None = None,
) -> list[VesselAnchor | None]:
    """Each frame's zero-force lumen (:func:`frame_vessel_anchor`), searched where the previous
    frame's lumen was (the frames of a sweep follow the vessel); None where none is found. After
    frames without a lumen, the region the next lumen may lie in grows by the last lumen's size per
    frame missed, so that a vessel that moved on while unseen is found again. With ``track``, the
    search goes on from where an earlier part of the same sweep left it, and ``track`` is updated:
    a sweep searched in parts finds the lumens it finds in one call. Compiled, frame after frame.

    Parameters
    ----------
    frames : ndarray
        ``(n_frames, rows, cols)`` uint8 or non-negative float32, of the model's frame shape.
    forces : ndarray
        ``(n_frames,)`` checked forces, N (see :func:`usdeform.regression.correction_forces`).
    profiles : ndarray
        ``(n_frames, 3)`` stiffness profiles ``(c1, c2, c3)``.
    model : VesselAnchoredModel
        The model.
    track : LumenTrack, optional
        Where the search of the sweep's earlier frames stands (None: these are its first frames).

    Returns
    -------
    list of VesselAnchor or None
    """
    return _search(searchable_frames(frames, model.frame_shape, "frames"), forces, profiles, model, track)


def _search(
    stack: np.ndarray, forces: np.ndarray, profiles: np.ndarray, model: VesselAnchoredModel, track: LumenTrack | None
) -> list[VesselAnchor | None]:
    """:func:`sweep_lumens` on checked frames (n_frames, rows, cols)."""
    state = track if track is not None else LumenTrack()
    last, missed = track_state(state)
    found, last, missed = _core.sweep_lumens(
        stack,
        np.ascontiguousarray(forces, dtype=np.float64),
        np.ascontiguousarray(profiles, dtype=np.float64),
        model.image_model.kernel,
        model.vessel_kernel,
        lumen_search(model),
        last_found=last,
        frames_missed=missed,
    )
    update_track(state, last, missed)
    return [None if lumen is None else VesselAnchor(lumen[:2], lumen[2]) for lumen in found]


def track_state(track: LumenTrack) -> tuple[tuple[float, float, float] | None, int]:
    """``track`` as the compiled search takes it: ``(last_found, frames_missed)``, the lumen as
    ``(x, y, radius)``, pixels."""
    last = track.last_found
    return (None if last is None else (*last.centre_px, last.radius_px)), track.frames_missed


def update_track(track: LumenTrack, last_found: tuple[float, float, float] | None, frames_missed: int) -> None:
    """Sets ``track`` to where a compiled search stands after its last frame (as it returns it)."""
    track.last_found = None if last_found is None else VesselAnchor(last_found[:2], last_found[2])
    track.frames_missed = frames_missed


def lumen_search(model: VesselAnchoredModel) -> _core.LumenSearch:
    """The compiled search's settings (:data:`SEARCH_WINDOW_RADII`, :data:`ANCHOR_TOLERANCE_PX`,
    :data:`ANCHOR_MAX_ITERATIONS`, :func:`usdeform.metrics.segment_vessel`'s defaults) with the
    model's reference lumen."""
    return _core.LumenSearch(
        (*model.reference.centre_px, model.reference.radius_px),
        window_radii=SEARCH_WINDOW_RADII,
        tolerance_px=ANCHOR_TOLERANCE_PX,
        max_iterations=ANCHOR_MAX_ITERATIONS,
        smoothing_sigma_px=SMOOTHING_SIGMA_PX,
        threshold_fraction=THRESHOLD_FRACTION,
        min_contrast=MIN_CONTRAST,
        min_area_px=MIN_AREA_PX,
    )


def searched_lumen(frame: np.ndarray, lumen: VesselAnchor) -> VesselAnchor:
    """``lumen``, found in the whole of an unwarped ``frame`` (rows, cols), measured again as the lumen
    search measures a frame's lumen: segmented within :data:`SEARCH_WINDOW_RADII` radii of it, the window
    then centred on the lumen found there (at most :data:`ANCHOR_MAX_ITERATIONS` times, until it moves by
    less than :data:`ANCHOR_TOLERANCE_PX`); ``lumen`` itself where the window holds none of it or only a part.

    The segmentation's levels are the window's own, so its lumen differs from the whole frame's (a bright
    wall raises the window's tissue level: the lumen comes out larger). A vessel part is scaled by the
    ratio of a sweep frame's searched radius to its palpations' one: both must be measured alike."""
    rows, cols = np.shape(frame)
    found = lumen
    for _ in range(ANCHOR_MAX_ITERATIONS):
        half = SEARCH_WINDOW_RADII * found.radius_px
        (x, y), previous = found.centre_px, found
        top, left = max(int(np.floor(y - half)), 0), max(int(np.floor(x - half)), 0)
        bottom, right = min(int(np.ceil(y + half)) + 1, rows), min(int(np.ceil(x + half)) + 1, cols)
        try:
            mask = segment_vessel(frame[top:bottom, left:right], (x - left, y - top)).mask
        except InputError:
            return lumen
        if (top > 0 and mask[0].any()) or (bottom < rows and mask[-1].any()):
            return lumen
        if (left > 0 and mask[:, 0].any()) or (right < cols and mask[:, -1].any()):
            return lumen
        window = VesselAnchor.of_mask(mask)
        found = VesselAnchor((window.centre_px[0] + left, window.centre_px[1] + top), window.radius_px)
        moved = np.hypot(*np.subtract(found.centre_px, previous.centre_px))
        if max(moved, abs(found.radius_px - previous.radius_px)) < ANCHOR_TOLERANCE_PX:
            break
    return found


def searchable_frames(frames: np.ndarray, shape: tuple[int, int], name: str) -> np.ndarray:
    """``frames`` checked as deformed B-mode frames of ``shape``, uint8 or finite non-negative float32:
    a stack (n_frames, rows, cols) for ``name`` "frames" (a bad frame named by its index), else one frame."""
    array = np.asarray(frames)
    stack = array if name == "frames" else array[np.newaxis]
    if stack.dtype not in (np.uint8, np.float32) or stack.ndim != 3 or stack.shape[1:] != shape:
        what = "(n_frames, {}, {}) frames" if name == "frames" else "{} x {} frame"
        raise InputError(
            f"{name}: expected a {what.format(*shape)} of uint8 or float32, got {array.dtype} {array.shape}"
        )
    if stack.dtype == np.float32:
        bad = ~(np.isfinite(stack) & (stack >= 0)).reshape(len(stack), -1).all(axis=1)
        if bad.any():
            where = f"{name}[{int(np.argmax(bad))}]" if name == "frames" else name
            raise InputError(f"{where}: B-mode intensities must be finite and non-negative")
    return np.ascontiguousarray(array)


def vessel_placements(
    anchors: Sequence[VesselAnchor | None], model: VesselAnchoredModel, last_found: VesselAnchor | None = None
) -> np.ndarray:
    """Where each frame's vessel part goes, ``(n_frames, 3)`` of ``(x, y, radius)``, pixels: its lumen,
    or where a frame's lumen was not found, the last lumen found before it (``last_found``, from the
    sweep's earlier frames, before any here; the model's reference lumen before any at all)."""
    placed = np.empty((len(anchors), 3))
    last = last_found or model.reference
    for index, anchor in enumerate(anchors):
        last = anchor or last
        placed[index] = (*last.centre_px, last.radius_px)
    return placed


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
    threads: int | None = None,
    track: LumenTrack | None = None,
    other_anchors: Sequence[Sequence[VesselAnchor | None]] | None = None,
) -> tuple[np.ndarray, np.ndarray, list[VesselAnchor | None]]:
    """Frames warped back to zero force with a vessel-anchored model, its vessel part on each frame's
    own lumen (:func:`sweep_lumens`). Where a frame's lumen is not found (a lumen pressed shut, or
    only a dark region that does not overlap the last lumen found), the vessel part stays where the
    last lumen was found, or on the model's reference lumen before any (:func:`vessel_placements`).
    A model with further vessels (``other_vessels``: a vein beside the artery) places each one's part
    on that vessel's own lumen in the same way (:func:`further_lumens`); the model's field, the sum of
    its parts, is then computed a block of frames at a time and the frames warped by it.

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
    threads : int, optional
        Worker threads of the warp (None: all cores; the result does not depend on it). The lumen
        search runs frame after frame.
    track : LumenTrack, optional
        The lumen search of the sweep's earlier frames, to go on from and update (see
        :func:`sweep_lumens`; not with ``anchors``; the further vessels' searches start afresh).
    other_anchors : sequence of sequences of VesselAnchor or None, optional
        With ``anchors``: each further vessel's lumens, one sequence per vessel and one entry per frame
        (:func:`further_lumens`); None: searched in the frames.

    Returns
    -------
    corrected : ndarray
        The corrected frames, same shape and dtype as ``frames``.
    valid : ndarray of bool
        True where a pixel's source lies inside its frame.
    anchors : list of VesselAnchor or None
        Each frame's zero-force lumen (None: not found there).
    """
    stack, frame_forces, frame_profiles = checked_sweep(frames, forces, profiles, model, clamp_force)
    n_frames = len(stack)
    if track is not None and anchors is not None:
        raise InputError("track: the lumens are given (anchors), there is no search to go on with")
    last_found = None if track is None else track.last_found
    found = (
        sweep_lumens(stack, frame_forces, frame_profiles, model, track=track)
        if anchors is None
        else _anchors_argument(anchors, n_frames)
    )
    placements = [vessel_placements(found, model, last_found)]
    if model.other_vessels:
        if other_anchors is None:
            other_anchors = further_lumens(stack, frame_forces, frame_profiles, model, found)
        if len(other_anchors) != len(model.other_vessels):
            raise InputError(f"other_anchors: expected one sequence per further vessel ({len(model.other_vessels)})")
        placements += [
            vessel_placements(_anchors_argument(lumens, n_frames), part)
            for lumens, part in zip(other_anchors, model.vessel_models[1:], strict=True)
        ]
    scales = vessel_part_scales(frame_forces, frame_profiles, model, placements)
    if model.other_vessels or (scales < 1.0).any():
        corrected, valid = _warp_vessels(stack, frame_forces, frame_profiles, model, placements, scales, fill, threads)
    else:
        corrected, valid = _core.warp_frames(
            stack,
            frame_forces,
            frame_profiles,
            model.image_model.kernel,
            fill=float(fill),
            threads=threads_argument(threads),
            return_mask=True,
            vessel=model.vessel_kernel,
            anchors=placements[0],
        )
    if np.ndim(frames) == 2:
        return corrected[0], valid[0], found
    return corrected, valid, found


def further_lumens(
    frames: np.ndarray,
    forces: np.ndarray,
    profiles: np.ndarray,
    model: VesselAnchoredModel,
    main: Sequence[VesselAnchor | None] | None = None,
) -> list[list[VesselAnchor | None]]:
    """Each further vessel's zero-force lumens in a sweep's checked frames, one list per vessel of
    ``model.other_vessels`` (one entry per frame, None where not found): each searched as
    :func:`sweep_lumens` searches the main one, with the image part and that vessel's own part.

    A lumen is one vessel's: where a further vessel's search ends on the lumen of the main vessel
    (``main``, each frame's lumen as :func:`sweep_lumens` finds it; None: searched here) or of a further
    vessel before it, that frame counts as not found for it (:func:`distinct_lumens`). A branch palpated
    where it leaves the artery is then not placed on the artery where the sweep shows no branch."""
    stack = searchable_frames(frames, model.frame_shape, "frames")
    if main is None:
        main = sweep_lumens(stack, forces, profiles, model)
    found = [list(main), *(sweep_lumens(stack, forces, profiles, part) for part in model.vessel_models[1:])]
    return distinct_lumens(found)[1:]


def distinct_lumens(found: Sequence[Sequence[VesselAnchor | None]]) -> list[list[VesselAnchor | None]]:
    """``found`` (per vessel, each frame's lumen or None) with each lumen that coincides with an earlier
    vessel's lumen of the same frame set to None; two lumens coincide where the centre of one lies within
    the other (their centres closer than the larger radius).

    Examples
    --------
    >>> artery, beside = VesselAnchor((20.0, 20.0), 6.0), VesselAnchor((40.0, 20.0), 5.0)
    >>> on_it = VesselAnchor((23.0, 21.0), 4.0)
    >>> distinct_lumens([[artery, artery], [beside, on_it]])[1]
    [VesselAnchor(centre_px=(40.0, 20.0), radius_px=5.0), None]
    """
    kept: list[list[VesselAnchor | None]] = []
    for lumens in found:
        own = []
        for index, lumen in enumerate(lumens):
            earlier = [other[index] for other in kept if other[index] is not None]
            same = lumen is not None and any(
                np.hypot(lumen.centre_px[0] - o.centre_px[0], lumen.centre_px[1] - o.centre_px[1])
                < max(lumen.radius_px, o.radius_px)
                for o in earlier
                if o is not None
            )
            own.append(None if same else lumen)
        kept.append(own)
    return kept


#: Frames whose fields :func:`correct_vessel_anchored` holds at once for a model with further vessels.
_FIELD_BLOCK_FRAMES = 16


def _warp_vessels(
    stack: np.ndarray,
    forces: np.ndarray,
    profiles: np.ndarray,
    model: VesselAnchoredModel,
    placements: Sequence[np.ndarray],
    scales: np.ndarray,
    fill: float,
    threads: int | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The frames ``stack`` (n, rows, cols) warped by the model's field with every vessel's part at its
    placements (one (n, 3) array of (x, y, radius) per vessel, the main one first) scaled by its
    ``scales`` (n_vessels, n), and the validity."""
    n_frames, rows, cols = stack.shape
    corrected, valid = np.empty_like(stack), np.empty(stack.shape, dtype=bool)
    for first in range(0, n_frames, _FIELD_BLOCK_FRAMES):
        block = slice(first, min(first + _FIELD_BLOCK_FRAMES, n_frames))
        fields = np.stack(
            [
                _scaled_field(model, float(forces[index]), profiles[index], (rows, cols), placements, scales, index)
                for index in range(block.start, block.stop)
            ]
        )
        corrected[block], valid[block] = _core.warp_by_field(
            np.ascontiguousarray(stack[block]), fields, fill=float(fill), threads=threads_argument(threads)
        )
    return corrected, valid


def _scaled_field(
    model: VesselAnchoredModel,
    force_n: float,
    profile: np.ndarray,
    shape: tuple[int, int],
    placements: Sequence[np.ndarray],
    scales: np.ndarray,
    index: int,
) -> np.ndarray:
    """Frame ``index``'s field (2, rows, cols), pixels: the image part plus each vessel's part on its
    placement, scaled by its entry of ``scales`` (see :func:`usdeform.correction._folds.vessel_part_scales`)."""
    stiffness = StiffnessProfile(*profile)
    field = model.image_model.displacement(force_n, stiffness, shape)
    for part, place, scale in zip(model.vessel_models, placements, scales, strict=True):
        if scale[index] > 0.0:
            lumen = VesselAnchor((float(place[index, 0]), float(place[index, 1])), float(place[index, 2]))
            field += scale[index] * part.vessel_displacement(force_n, stiffness, shape, lumen)
    return field


def checked_sweep(
    frames: np.ndarray,
    forces: np.ndarray | Sequence[float] | float,
    profiles: StiffnessProfile | Sequence[StiffnessProfile] | np.ndarray,
    model: VesselAnchoredModel,
    clamp_force: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The frames ``(n_frames, rows, cols)`` of the model's frame shape, their forces (N; see
    :func:`usdeform.regression.correction_forces`) and profiles ``(n_frames, 3)``, checked."""
    stack = frames_array(frames)
    n_frames, rows, cols = stack.shape
    if (rows, cols) != model.frame_shape:
        raise InputError(f"frames: {rows} x {cols} pixels, but the model was fitted on {model.frame_shape} frames")
    return stack, correction_forces(forces, n_frames, model, clamp=clamp_force), profiles_array(profiles, n_frames)
