"""Reconstructed volumes to and from NRRD (.nrrd) and MetaImage (.mha/.mhd) files.

World coordinates are written unchanged, in the PLUS Reference (robot base) frame, mm, and declared
as ITK/DICOM LPS: MetaImage files carry ``AnatomicalOrientation = RAI`` as PLUS writes them (MetaIO's
RAI is DICOM LPS) and NRRD files ``space: left-posterior-superior``, so 3D Slicer (which converts LPS
files to its internal RAS) shows a .mha and a .nrrd of the same volume at the same place, and PLUS's
own volumes line up with ours. NRRD ``right-anterior-superior`` files are converted to LPS on reading.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._files import outputs_together
from ..errors import FileFormatError, InputError
from ..options import DEFAULT_COMPRESSION_LEVEL, NUMBERS
from ..volume import Volume, VoxelGrid
from ._common import format_numbers, is_nrrd_file, parse_numbers, read_nrrd, write_nrrd
from ._metaimage import read_metaimage, write_metaimage

__all__ = ["COMPRESSION_LEVEL", "DEFAULT_COMPRESSION_LEVEL", "VOLUME_SUFFIXES", "read_volume", "write_volume"]

#: The suffixes :func:`write_volume` writes.
VOLUME_SUFFIXES = (".nrrd", ".mha", ".mhd")

#: The compression level of volumes: 1 (fastest) to 9 (smallest) (:data:`usdeform.options.NUMBERS`).
COMPRESSION_LEVEL = NUMBERS["compression_level"]

_VOLUME_DTYPES = (np.dtype(np.uint8), np.dtype(np.float32))
_LPS_SPACES = (None, "left-posterior-superior", "LPS")
_RAS_SPACES = ("right-anterior-superior", "RAS")
_RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


def _checked_array(name: str, array: np.ndarray) -> np.ndarray:
    array = np.asarray(array)
    if array.dtype not in _VOLUME_DTYPES:
        raise InputError(f"{name}: volumes are written as uint8 or float32, got {array.dtype}; cast it first")
    return array


def _write_image(path: Path, image: np.ndarray, index_to_world: np.ndarray, level: int | None) -> None:
    """Write one image; ``level``: the compression level (:func:`~usdeform.io._common.deflate`), None for
    uncompressed data."""
    suffix = path.suffix.lower()
    if suffix == ".nrrd":
        header = {
            "dimension": 3,
            "space": "left-posterior-superior",
            "space directions": index_to_world[:3, :3].T,  # one row per file axis (x, y, z)
            "kinds": ["domain", "domain", "domain"],
            "endian": "little",
            "space origin": index_to_world[:3, 3],
        }
        write_nrrd(path, image, header, level is not None, level or DEFAULT_COMPRESSION_LEVEL)
    elif suffix in (".mha", ".mhd"):
        spacing = np.linalg.norm(index_to_world[:3, :3], axis=0)
        direction = index_to_world[:3, :3] / spacing
        fields = [
            ("ElementSpacing", format_numbers(spacing)),
            ("Offset", format_numbers(index_to_world[:3, 3])),
            # MetaIO lists the direction of axis i as the i-th row (ITK's MetaImageIO reads it so).
            ("TransformMatrix", format_numbers(direction.T.ravel())),
            ("CenterOfRotation", "0 0 0"),
            ("AnatomicalOrientation", "RAI"),
        ]
        write_metaimage(path, image, fields, level is not None, level or DEFAULT_COMPRESSION_LEVEL)
    else:
        raise InputError(f"path: {path} must end in .nrrd, .mha or .mhd")


def write_volume(
    path: str | Path,
    volume: Volume,
    compress: bool = True,
    weight_path: str | Path | None = None,
    *,
    compression_level: int = DEFAULT_COMPRESSION_LEVEL,
) -> None:
    """Write ``volume.image`` (uint8 or float32, (z, y, x)) with its spacing, origin and direction.

    The format follows the suffix: .nrrd (NRRD, gzip when ``compress``) or .mha/.mhd (MetaImage,
    zlib when ``compress``), at ``compression_level`` (1 fastest to 9 smallest: ISA-L's deflate at 1,
    zlib's levels above; see :data:`DEFAULT_COMPRESSION_LEVEL` for the measured trade-off).
    ``weight_path``, if given, receives ``volume.weight`` as a second file on the same grid. Files are
    written to temporary files and renamed together, never left half-written or from different calls.
    """
    if not isinstance(volume, Volume):
        raise InputError(f"volume: expected a Volume, got {type(volume).__name__}")
    checked_level = int(COMPRESSION_LEVEL.check(compression_level))  # checked even when not compressing
    level = checked_level if compress else None
    image = _checked_array("volume.image", volume.image)
    if weight_path is None:
        _write_image(Path(path), image, volume.index_to_world, level)
        return
    if volume.weight is None:
        raise InputError("weight_path: the volume has no weight to write")
    weight = _checked_array("volume.weight", volume.weight)
    if Path(weight_path).resolve() == Path(path).resolve():
        raise InputError(f"weight_path: {weight_path} is the volume's own path")
    with outputs_together():
        _write_image(Path(path), image, volume.index_to_world, level)
        _write_image(Path(weight_path), weight, volume.index_to_world, level)


def _read_nrrd_volume(path: Path) -> tuple[np.ndarray, np.ndarray]:
    header, image = read_nrrd(path)
    if image.ndim != 3:
        raise FileFormatError(f"{path}: dimension: expected a 3-D volume, got {image.ndim} dimensions")
    kinds = [str(kind).lower() for kind in header.get("kinds", ["domain"] * 3)]
    if any(kind not in ("domain", "space") for kind in kinds):
        raise FileFormatError(f"{path}: kinds: expected three spatial axes, got {' '.join(kinds)!r}")
    index_to_world = np.eye(4)
    if "space directions" in header:
        directions = np.asarray(header["space directions"], dtype=np.float64)
        if directions.shape != (3, 3) or not np.all(np.isfinite(directions)):
            raise FileFormatError(f"{path}: space directions: expected three 3-D vectors, got {directions.tolist()}")
        index_to_world[:3, :3] = directions.T
    else:
        spacings = np.asarray(header.get("spacings", [1.0, 1.0, 1.0]), dtype=np.float64)
        index_to_world[:3, :3] = np.diag(spacings)
    index_to_world[:3, 3] = np.asarray(header.get("space origin", np.zeros(3)), dtype=np.float64)
    space = header.get("space")
    if space in _RAS_SPACES:
        index_to_world = _RAS_TO_LPS @ index_to_world
    elif space not in _LPS_SPACES:
        raise FileFormatError(f"{path}: space: unsupported space {space!r}, expected left-posterior-superior or RAS")
    return image, index_to_world


def _metaimage_numbers(path: Path, fields: dict[str, str], names: tuple[str, ...], default: list[float]) -> np.ndarray:
    """The first of the synonymous MetaImage fields ``names`` present (or ``default``)."""
    for name in names:
        if name in fields:
            return parse_numbers(path, name, fields[name], len(default))
    return np.array(default, dtype=np.float64)


def _read_metaimage_volume(path: Path) -> tuple[np.ndarray, np.ndarray]:
    image = read_metaimage(path)
    if image.pixels.ndim != 3:
        raise FileFormatError(f"{path}: NDims: expected a 3-D volume, got {image.pixels.ndim}")
    spacing = _metaimage_numbers(path, image.fields, ("ElementSpacing", "ElementSize"), [1.0, 1.0, 1.0])
    origin = _metaimage_numbers(path, image.fields, ("Offset", "Position", "Origin"), [0.0, 0.0, 0.0])
    direction_rows = _metaimage_numbers(
        path, image.fields, ("TransformMatrix", "Rotation", "Orientation"), [1, 0, 0, 0, 1, 0, 0, 0, 1]
    )
    index_to_world = np.eye(4)
    index_to_world[:3, :3] = direction_rows.reshape(3, 3).T * spacing
    index_to_world[:3, 3] = origin
    return np.array(image.pixels), index_to_world


def _read_image(path: Path) -> tuple[np.ndarray, np.ndarray]:
    return _read_nrrd_volume(path) if is_nrrd_file(path) else _read_metaimage_volume(path)


def read_volume(path: str | Path, weight_path: str | Path | None = None) -> Volume:
    """Read a volume written by :func:`write_volume`, by PLUS or by 3D Slicer (.nrrd, .mha, .mhd).

    The image keeps the file's element type, indexed (z, y, x); ``weight_path``, if given, is read as
    the weight and must lie on the same grid. Raises FileFormatError naming the file and the field.
    """
    path = Path(path)
    image, index_to_world = _read_image(path)
    try:
        grid = VoxelGrid(image.shape, index_to_world)
    except InputError as exc:
        raise FileFormatError(f"{path}: geometry: {exc}") from None
    weight = None
    if weight_path is not None:
        weight_path = Path(weight_path)
        weight, weight_to_world = _read_image(weight_path)
        if weight.shape != image.shape or not np.allclose(weight_to_world, index_to_world, rtol=0, atol=1e-9):
            raise FileFormatError(f"{weight_path}: weight grid differs from the image grid of {path}")
    return Volume(image=image, grid=grid, weight=weight)
