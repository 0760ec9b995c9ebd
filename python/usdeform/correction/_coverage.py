"""Whether a sweep's lumens lie within what the palpations covered.

A vessel-anchored model learns each vessel's collapse on the palpations' lumens: at their depths and
radii. Its vessel part is scaled with the lumen's radius and placed on each sweep frame's own lumen, so
a sweep whose vessel runs deeper, shallower, wider or narrower than every palpation saw is corrected
by extrapolation. :func:`uncovered_lumens` finds the frames where that happens, per vessel, comparing
each frame's zero-force lumen (:func:`~usdeform.correction.sweep_lumens`) with the palpations' lumens
at contact (:attr:`~usdeform.correction.SampledProfiles.lumens`), both at zero force.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..regression import VesselAnchor

__all__ = [
    "DEPTH_MARGIN_RADII",
    "RADIUS_MARGIN_FRACTION",
    "LumenCoverageWarning",
    "UncoveredLumens",
    "uncovered_lumens",
]

#: Depth beyond the palpated lumens' centres, in their mean radius, a sweep's lumen may lie before it
#: counts as uncovered (the vessel part's basis is laid out in units of the radius).
DEPTH_MARGIN_RADII = 0.25
#: Fraction of the palpated radii's range ends a sweep's lumen radius may go beyond before it counts as
#: uncovered (about the lumen segmentation's precision on a radius of 10-20 pixels).
RADIUS_MARGIN_FRACTION = 0.1


class LumenCoverageWarning(UserWarning):
    """A sweep's lumen lies deeper, shallower, wider or narrower than the palpations' lumens."""


@dataclass(frozen=True)
class UncoveredLumens:
    """Frames of one vessel whose zero-force lumen lies outside the palpated range.

    ``vessel``: the vessel's index (0 the main one, then the further ones); ``frames``: the frames' indices, of
    the sweep's ``n_frames``; ``depth_mm`` and ``radius_mm``: (min, max) of the sweep's lumens over those frames;
    ``palpated_depth_mm`` and ``palpated_radius_mm``: (min, max) of the palpations' lumens. Depth is the lumen
    centre's row times the pixel height (mm below the image's top row)."""

    vessel: int
    frames: tuple[int, ...]
    n_frames: int
    depth_mm: tuple[float, float]
    radius_mm: tuple[float, float]
    palpated_depth_mm: tuple[float, float]
    palpated_radius_mm: tuple[float, float]

    def message(self) -> str:
        """The warning's text."""
        name = "the vessel" if self.vessel == 0 else f"further vessel {self.vessel}"
        return (
            f"{name}: in {len(self.frames)} of {self.n_frames} frames (first: frame {self.frames[0]}) its lumen "
            f"lies at {self.depth_mm[0]:.1f}-{self.depth_mm[1]:.1f} mm depth with radius {self.radius_mm[0]:.1f}-"
            f"{self.radius_mm[1]:.1f} mm, beyond the palpated {self.palpated_depth_mm[0]:.1f}-"
            f"{self.palpated_depth_mm[1]:.1f} mm and {self.palpated_radius_mm[0]:.1f}-"
            f"{self.palpated_radius_mm[1]:.1f} mm: its collapse is extrapolated there; palpate where the vessel "
            "is deepest, shallowest, widest and narrowest too"
        )


def uncovered_lumens(
    found: Sequence[Sequence[VesselAnchor | None]],
    palpated: Sequence[Sequence[VesselAnchor | None]],
    pixel_mm: tuple[float, float],
) -> list[UncoveredLumens]:
    """Per vessel, the sweep frames whose lumen lies outside the palpated depths and radii.

    Parameters
    ----------
    found : sequence of sequences of VesselAnchor or None
        Per vessel (main, then further), each frame's zero-force lumen (None: not found), pixels.
    palpated : sequence of sequences of VesselAnchor or None
        Per palpated position, its lumens at contact vessel by vessel (as
        :attr:`~usdeform.correction.SampledProfiles.lumens`), pixels.
    pixel_mm : (float, float)
        Pixel width and height, mm.

    Returns
    -------
    list of UncoveredLumens
        One per vessel with such frames (none for a vessel no palpation showed: nothing to compare).

    Examples
    --------
    >>> palpated = [(VesselAnchor((50.0, 40.0), 10.0),), (VesselAnchor((50.0, 60.0), 12.0),)]
    >>> found = [[VesselAnchor((50.0, 50.0), 11.0), VesselAnchor((50.0, 90.0), 11.0), None]]
    >>> [u.frames for u in uncovered_lumens(found, palpated, (0.1, 0.1))]
    [(1,)]
    """
    width, height = pixel_mm
    result = []
    for vessel, lumens in enumerate(found):
        seen = [at[vessel] for at in palpated if vessel < len(at) and at[vessel] is not None]
        if not seen:
            continue
        depths = np.array([lumen.centre_px[1] for lumen in seen if lumen is not None])
        radii = np.array([lumen.radius_px for lumen in seen if lumen is not None])
        margin = DEPTH_MARGIN_RADII * float(radii.mean())
        outside = [
            index
            for index, lumen in enumerate(lumens)
            if lumen is not None
            and (
                not depths.min() - margin <= lumen.centre_px[1] <= depths.max() + margin
                or not (1 - RADIUS_MARGIN_FRACTION) * radii.min()
                <= lumen.radius_px
                <= (1 + RADIUS_MARGIN_FRACTION) * radii.max()
            )
        ]
        if not outside:
            continue
        depth = np.array([lumens[i].centre_px[1] for i in outside]) * height  # type: ignore[union-attr]
        radius = np.array([lumens[i].radius_px for i in outside]) * np.sqrt(width * height)  # type: ignore[union-attr]
        result.append(
            UncoveredLumens(
                vessel,
                tuple(outside),
                len(lumens),
                (float(depth.min()), float(depth.max())),
                (float(radius.min()), float(radius.max())),
                (float(depths.min() * height), float(depths.max() * height)),
                (float(radii.min() * np.sqrt(width * height)), float(radii.max() * np.sqrt(width * height))),
            )
        )
    return result
