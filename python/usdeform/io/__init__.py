"""File formats: PLUS sequence files, PLUS XML configurations, volume files and model files."""

from __future__ import annotations

from .model_file import ModelFile, SampledProfiles, fit_provenance, load_model, save_model
from .plus_config import PlusConfig, read_plus_config
from .sequence_file import pixel_valid_path, read_sequence, write_sequence
from .volume_file import read_volume, write_volume

__all__ = [
    "ModelFile",
    "PlusConfig",
    "SampledProfiles",
    "fit_provenance",
    "load_model",
    "pixel_valid_path",
    "read_plus_config",
    "read_sequence",
    "read_volume",
    "save_model",
    "write_sequence",
    "write_volume",
]
