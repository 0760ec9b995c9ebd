"""Vessel parts that fold the zero-force map, attenuated until it no longer folds.

A frame is corrected by reading the zero-force pixel ``p`` from the deformed frame at ``p + D(p)``. Tissue
does not pass through itself, so this map is one-to-one: its Jacobian determinant
``det(I + grad D)`` stays positive. Inside a lumen the palpations give no observations (no echoes to
track), so a vessel part can be free to fold there, above all where the sweep's lumen differs from the
palpated ones (another depth or radius). Folded pixels copy the wall's echoes into the lumen. Where a
frame's vessel part folds the map within its window, :func:`vessel_part_scales` scales it down by the
first of :data:`ATTENUATION_STEPS` that unfolds it (0: the image part alone), so that the correction
is never a map no tissue can make.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from ..regression import StiffnessProfile, VesselAnchor, VesselAnchoredModel

__all__ = ["ATTENUATION_STEPS", "FoldedVesselWarning", "fold_determinant", "vessel_part_scales"]

#: Factors a frame's vessel part is scaled by, largest first, until the map no longer folds in its window.
ATTENUATION_STEPS = (1.0, 0.75, 0.5, 0.25, 0.0)


class FoldedVesselWarning(UserWarning):
    """A vessel part folded the zero-force map in some frames and was attenuated there."""


def fold_determinant(field: np.ndarray) -> np.ndarray:
    """``det(I + grad D)`` of a displacement field ``(2, rows, cols)`` (pixels; lateral, axial) at each
    pixel (central differences): at or below 0 where the map ``p -> p + D(p)`` folds."""
    d_lateral_dy, d_lateral_dx = np.gradient(field[0])
    d_axial_dy, d_axial_dx = np.gradient(field[1])
    determinant: np.ndarray = (1.0 + d_lateral_dx) * (1.0 + d_axial_dy) - d_lateral_dy * d_axial_dx
    return determinant


def _part_window(lumen: VesselAnchor, shape: tuple[int, int], window_radii: float) -> tuple[slice, slice] | None:
    """The frame's rows and columns a vessel part on ``lumen`` reaches (None: none of the frame)."""
    half = window_radii * lumen.radius_px
    x, y = lumen.centre_px
    rows = slice(max(int(np.floor(y - half)), 0), min(int(np.ceil(y + half)) + 1, shape[0]))
    cols = slice(max(int(np.floor(x - half)), 0), min(int(np.ceil(x + half)) + 1, shape[1]))
    if rows.stop - rows.start < 3 or cols.stop - cols.start < 3:
        return None
    return rows, cols


def vessel_part_scales(
    forces: np.ndarray, profiles: np.ndarray, model: VesselAnchoredModel, placements: Sequence[np.ndarray]
) -> np.ndarray:
    """Each vessel part's scale in each frame, ``(n_vessels, n_frames)``: the first of
    :data:`ATTENUATION_STEPS` at which the image part plus the scaled vessel part does not fold the map
    (:func:`fold_determinant` positive) within the part's window, wherever the image part alone does not.
    ``placements``: one ``(n_frames, 3)`` array of ``(x, y, radius)`` pixels per vessel of
    ``model.vessel_models``. Warns
    (:class:`FoldedVesselWarning`) with the frames attenuated."""
    scales = np.ones((len(placements), len(forces)))
    for vessel, (part, placed) in enumerate(zip(model.vessel_models, placements, strict=True)):
        for index, (x, y, radius) in enumerate(placed):
            lumen = VesselAnchor((float(x), float(y)), float(radius))
            window = _part_window(lumen, model.frame_shape, part.window_radii)
            if window is None:
                continue
            profile = StiffnessProfile(*profiles[index])
            image = part.displacement_on(float(forces[index]), profile, None, window)
            vessel_field = part.displacement_on(float(forces[index]), profile, lumen, window) - image
            unfolded = fold_determinant(image) > 0.0  # the vessel part is not blamed for the image part's folds
            for scale in ATTENUATION_STEPS:
                if scale == 0.0 or (fold_determinant(image + scale * vessel_field)[unfolded] > 0.0).all():
                    scales[vessel, index] = scale
                    break
    for vessel, row in enumerate(scales):
        attenuated = np.flatnonzero(row < 1.0)
        if attenuated.size:
            name = "the vessel's part" if vessel == 0 else f"further vessel {vessel}'s part"
            warnings.warn(
                f"{name} folds the zero-force map in {attenuated.size} of "
                f"{row.size} frames (first: frame {attenuated[0]}): attenuated there to {row.min():.2f}-"
                f"{row[attenuated].max():.2f} of itself, the image part left whole",
                FoldedVesselWarning,
                stacklevel=3,
            )
    return scales
