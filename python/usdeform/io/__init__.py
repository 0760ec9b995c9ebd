"""File formats: PLUS sequence files, PLUS XML configurations and volume files."""

from __future__ import annotations

from .plus_config import PlusConfig, ReconstructionSettings, read_plus_config
from .sequence_file import read_sequence, write_sequence
from .volume_file import read_volume, write_volume

__all__ = [
    "PlusConfig",
    "ReconstructionSettings",
    "read_plus_config",
    "read_sequence",
    "read_volume",
    "write_sequence",
    "write_volume",
]
