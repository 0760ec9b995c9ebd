"""usdeform: deformation-aware robotic 3D ultrasound.

The pipeline, one module per stage (Jiang et al., RA-L 2021): :mod:`~usdeform.stiffness` (palpation
force-displacement fit), :mod:`~usdeform.optical_flow` (pixel displacements), :mod:`~usdeform.sampling`
(one palpated position), :mod:`~usdeform.regression` (the coupled quadratic model),
:mod:`~usdeform.propagation` (stiffness along a sweep), :mod:`~usdeform.correction` (warping to zero
force), :mod:`~usdeform.compounding` (frames into a volume), :mod:`~usdeform.reconstruction` (recordings into
volumes, with or without correction) and :mod:`~usdeform.metrics`; option types in
:mod:`~usdeform.options`. Files:
:mod:`usdeform.io`; the simulator: :mod:`usdeform.sim`; NumPy twins of the Rust kernels:
:mod:`usdeform.reference`.
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
    from .compounding import Compounder, compound_frames, grid_for_frames
    from .correction import correct_frames
    from .recording import Recording
    from .regression import (
        BSplineDisplacementModel,
        DisplacementModel,
        Normalization,
        Observations,
        QuadraticDisplacementModel,
        fit_regression,
    )
    from .stiffness import StiffnessProfile, fit_stiffness
    from .volume import Volume, VoxelGrid

# The stages are imported on first use (PEP 562), so that ``import usdeform`` (and the command line, which
# installs its Ctrl-C handler first thing) loads NumPy and the errors only.
_LAZY = {
    "Compounder": "compounding",
    "compound_frames": "compounding",
    "grid_for_frames": "compounding",
    "correct_frames": "correction",
    "Recording": "recording",
    "BSplineDisplacementModel": "regression",
    "DisplacementModel": "regression",
    "Normalization": "regression",
    "Observations": "regression",
    "QuadraticDisplacementModel": "regression",
    "fit_regression": "regression",
    "StiffnessProfile": "stiffness",
    "fit_stiffness": "stiffness",
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
