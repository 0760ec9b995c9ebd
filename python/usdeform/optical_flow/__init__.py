"""Pixel displacement during a palpation (the module moved into this package; its parts follow)."""

from __future__ import annotations

from ._tracking import (  # noqa: F401 (private names other modules and the tests import)
    _LK_CRITERIA,
    REJECTION_REASONS,
    TrackedDisplacements,
    _affine_lucas_kanade,
    _as_uint8_frames,
    _checked_order,
    _coarse_flow,
    _lucas_kanade,
    _nanmedian,
    _window_offsets,
    boundary_constraints,
    concatenate,
    track_palpation,
)

__all__ = ["REJECTION_REASONS", "TrackedDisplacements", "boundary_constraints", "concatenate", "track_palpation"]
