"""usdeform: deformation-aware robotic 3D ultrasound."""

from __future__ import annotations

from .errors import (
    FileFormatError,
    FitError,
    InputError,
    InternalError,
    MemoryLimitError,
    UsdeformError,
)
from .volume import Volume, VoxelGrid

__all__ = [
    "FileFormatError",
    "FitError",
    "InputError",
    "InternalError",
    "MemoryLimitError",
    "UsdeformError",
    "Volume",
    "VoxelGrid",
]
