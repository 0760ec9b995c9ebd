"""Plain NumPy twins of the Rust kernels (OpenCV's segmentation in the lumen search's), written for
clarity rather than speed.

Each function computes what one kernel of ``usdeform._core`` computes, straight from the paper's
formulas, so that the tests can hold the two to the same answers and the benchmarks can time them
against each other. Conventions are those of the kernels: pixel ``(x, y)`` = ``(column, row)``,
displacements ``(lateral, axial)`` in pixels, volumes ``(z, y, x)``.
"""

from __future__ import annotations

from .compounding import compound_frames, fill_holes, volume_region
from .correction import (
    anchored_displacement,
    field_for_terms,
    force_integrals,
    integrated_displacement,
    regression_rate,
    stiffness_integral,
    warp_anchored_frames,
    warp_frame,
    warp_frames,
)
from .imaging import splat_bilinear
from .lumens import sweep_lumens
from .mechanics import HyperelasticSection, SymmetricSolver
from .patch_match import block_match, patch_correlation
from .tracking import affine_lucas_kanade
from .transport import crc64

__all__ = [
    "HyperelasticSection",
    "SymmetricSolver",
    "affine_lucas_kanade",
    "anchored_displacement",
    "block_match",
    "compound_frames",
    "crc64",
    "field_for_terms",
    "fill_holes",
    "force_integrals",
    "integrated_displacement",
    "patch_correlation",
    "regression_rate",
    "splat_bilinear",
    "stiffness_integral",
    "sweep_lumens",
    "volume_region",
    "warp_anchored_frames",
    "warp_frame",
    "warp_frames",
]
