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

from .compounding import Compounder, compound_frames, grid_for_frames
from .correction import correct_frames
from .errors import (
    FileFormatError,
    FitError,
    InputError,
    InternalError,
    MemoryLimitError,
    UsdeformError,
)
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
