"""usdeform: deformation-aware robotic 3D ultrasound.

One package per stage of the method (Jiang et al., RA-L 2021): :mod:`~usdeform.fitting` (palpations:
stiffness, phases, vessel wall, the fit and its report), :mod:`~usdeform.optical_flow` (pixel
displacements), :mod:`~usdeform.regression` (the displacement model), :mod:`~usdeform.correction`
(frames and sweeps warped to zero force), :mod:`~usdeform.volume` (frames into a volume, as PLUS) and
:mod:`~usdeform.metrics`; option types in :mod:`~usdeform.options`. Files: :mod:`usdeform.io`; the
simulator: :mod:`usdeform.sim`; NumPy twins of the Rust kernels: :mod:`usdeform.reference`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .errors import (
    FileFormatError,
    FitError,
    InputError,
    InternalError,
    MemoryLimitError,
    UsdeformError,
)

if TYPE_CHECKING:
    from .correction import correct_frames
    from .fitting import fit_stiffness
    from .recording import Recording
    from .regression import (
        BSplineDisplacementModel,
        DisplacementModel,
        Normalization,
        Observations,
        QuadraticDisplacementModel,
        StiffnessProfile,
        fit_regression,
    )
    from .volume import Compounder, Volume, VoxelGrid, compound_frames, grid_for_frames

# The stages are imported on first use (PEP 562), so that ``import usdeform`` (and the command line, which
# installs its Ctrl-C handler first thing) loads NumPy and the errors only.
_LAZY = {
    "Compounder": "volume",
    "compound_frames": "volume",
    "grid_for_frames": "volume",
    "correct_frames": "correction",
    "Recording": "recording",
    "BSplineDisplacementModel": "regression",
    "DisplacementModel": "regression",
    "Normalization": "regression",
    "Observations": "regression",
    "QuadraticDisplacementModel": "regression",
    "fit_regression": "regression",
    "StiffnessProfile": "regression",
    "fit_stiffness": "fitting",
    "Volume": "volume",
    "VoxelGrid": "volume",
}


def __getattr__(name: str) -> object:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})


__all__ = [
    "BSplineDisplacementModel",
    "Compounder",
    "DisplacementModel",
    "FileFormatError",
    "FitError",
    "InputError",
    "InternalError",
    "MemoryLimitError",
    "Normalization",
    "Observations",
    "QuadraticDisplacementModel",
    "Recording",
    "StiffnessProfile",
    "UsdeformError",
    "Volume",
    "VoxelGrid",
    "compound_frames",
    "correct_frames",
    "fit_regression",
    "fit_stiffness",
    "grid_for_frames",
]
