"""PLUS XML device-set configurations: calibration transforms and volume reconstruction settings.

Reads the two parts of a ``<PlusConfiguration>`` this package uses: the ``<CoordinateDefinitions>``
transforms (``<Transform From="Image" To="Probe" Matrix="16 numbers, row-major"/>``, mm) and the
``<VolumeReconstruction>`` attributes with its ``<HoleFilling>`` steps, following PLUS's
vtkPlusVolumeReconstructor::ReadConfiguration.
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FileFormatError, InputError
from ..validation import MAX_AXIS_SIZE, check_calibration, regular_file
from ..volume import HoleFillingElement, HoleFillingKind, ReconstructionSettings
from ._common import parse_numbers

__all__ = ["PlusConfig", "read_plus_config"]

_INTERPOLATION = {"NEAREST_NEIGHBOR": "nearest", "LINEAR": "linear"}
_COMPOUNDING = {"MEAN": "mean", "MAXIMUM": "max", "LATEST": "latest"}
# PLUS HoleFillingElement Type -> (kind, the attributes PLUS requires for it).
_HOLE_FILLING: dict[str, tuple[HoleFillingKind, tuple[str, ...]]] = {
    "GAUSSIAN": ("gaussian", ("Size", "Stdev", "MinimumKnownVoxelsRatio")),
    "GAUSSIAN_ACCUMULATION": ("gaussian_accumulation", ("Size", "Stdev", "MinimumKnownVoxelsRatio")),
    "DISTANCE_WEIGHT_INVERSE": ("distance_weight_inverse", ("Size", "MinimumKnownVoxelsRatio")),
    "NEAREST_NEIGHBOR": ("nearest_neighbor", ("Size", "MinimumKnownVoxelsRatio")),
    "STICK": ("stick", ("StickLengthLimit", "NumberOfSticksToUse")),
}
# Attribute -> (HoleFillingElement field, integer).
_HOLE_FILLING_FIELDS = {
    "Size": ("size", True),
    "Stdev": ("stdev", False),
    "MinimumKnownVoxelsRatio": ("min_known_ratio", False),
    "StickLengthLimit": ("stick_length_limit", True),
    "NumberOfSticksToUse": ("sticks_to_use", True),
}


@dataclass(frozen=True, eq=False)
class PlusConfig:
    """The CoordinateDefinitions ``transforms`` ((from, to) -> 4x4 from_to_to, mm) and ``reconstruction``."""

    transforms: dict[tuple[str, str], np.ndarray]
    reconstruction: ReconstructionSettings | None

    def transform(self, source: str, target: str) -> np.ndarray:
        """The 4x4 ``source``-to-``target`` transform, defined directly or as the inverse of target-to-source."""
        if (source, target) in self.transforms:
            return self.transforms[(source, target)].copy()
        if (target, source) in self.transforms:
            return np.linalg.inv(self.transforms[(target, source)])
        defined = ", ".join(f"{a}->{b}" for a, b in self.transforms) or "none"
        raise InputError(f"no {source}->{target} transform in the configuration (defined: {defined})")

    @property
    def image_to_probe(self) -> np.ndarray:
        """The Image -> Probe calibration (pixel (col, row, 0, 1) -> probe mm), (4, 4) float64."""
        return self.transform("Image", "Probe")


def _numbers(
    path: Path, element: ElementTree.Element, name: str, count: int, integer: bool = False
) -> np.ndarray | None:
    text = element.get(name)
    if text is None:
        return None
    return parse_numbers(path, f"{element.tag} {name}", text, count, integer=integer)


def _choice(path: Path, element: ElementTree.Element, name: str, choices: dict[str, str]) -> str | None:
    text = element.get(name)
    if text is None:
        return None
    if text.strip().upper() not in choices:
        raise FileFormatError(
            f"{path}: {element.tag} {name}: unsupported value {text!r}, expected one of {sorted(choices)}"
        )
    return choices[text.strip().upper()]


def _read_transforms(path: Path, root: ElementTree.Element) -> dict[tuple[str, str], np.ndarray]:
    transforms: dict[tuple[str, str], np.ndarray] = {}
    for element in root.iterfind(".//CoordinateDefinitions/Transform"):
        source, target = element.get("From"), element.get("To")
        if not source or not target:
            raise FileFormatError(f"{path}: CoordinateDefinitions Transform: needs From and To attributes")
        field = f"CoordinateDefinitions Transform {source}->{target} Matrix"
        text = element.get("Matrix")
        if text is None:
            raise FileFormatError(f"{path}: {field} is missing")
        matrix = parse_numbers(path, field, text, 16).reshape(4, 4)
        if not np.array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0]):
            raise FileFormatError(f"{path}: {field}: last row must be 0 0 0 1, got {matrix[3].tolist()}")
        if {source, target} == {"Image", "Probe"}:
            image_to_probe = matrix if source == "Image" else _inverse(path, field, matrix)
            check_calibration(image_to_probe, f"{path}: {field}", error=FileFormatError)
        transforms[(source, target)] = matrix
    return transforms


def _inverse(path: Path, field: str, matrix: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(matrix)
    except np.linalg.LinAlgError:
        raise FileFormatError(f"{path}: {field}: the matrix is singular") from None


def _compounding(path: Path, element: ElementTree.Element) -> str:
    mode = _choice(path, element, "CompoundingMode", _COMPOUNDING)
    if mode is not None:
        return mode
    # PLUS's deprecated attributes: Calculation="MAXIMUM" -> max, Compounding="OFF" -> latest, else mean.
    if (element.get("Calculation") or "").strip().upper() == "MAXIMUM":
        return "max"
    if (element.get("Compounding") or "").strip().upper() == "OFF":
        return "latest"
    return "mean"


def _read_hole_filling(path: Path, reconstruction: ElementTree.Element) -> tuple[HoleFillingElement, ...]:
    elements = []
    for index, element in enumerate(reconstruction.iterfind("HoleFilling/HoleFillingElement")):
        where = f"{path}: HoleFillingElement {index}"
        kind_name = (element.get("Type") or "").strip().upper()
        if kind_name not in _HOLE_FILLING:
            raise FileFormatError(f"{where}: Type {element.get('Type')!r} is not one of {sorted(_HOLE_FILLING)}")
        kind, required = _HOLE_FILLING[kind_name]
        fields: dict[str, Any] = {}
        for attribute in required:
            text = element.get(attribute)
            if text is None:
                raise FileFormatError(f"{where}: Type {kind_name} needs the attribute {attribute}")
            field, integer = _HOLE_FILLING_FIELDS[attribute]
            number = parse_numbers(path, f"HoleFillingElement {index} {attribute}", text, 1, integer=integer)[0]
            fields[field] = int(number) if integer else float(number)
        try:
            elements.append(HoleFillingElement(kind, **fields))
        except InputError as error:
            raise FileFormatError(f"{where}: {error}") from None
    return tuple(elements)


def _read_reconstruction(path: Path, root: ElementTree.Element) -> ReconstructionSettings | None:
    element = root.find(".//VolumeReconstruction")
    if element is None:
        return None
    spacing = _numbers(path, element, "OutputSpacing", 3)
    if spacing is None:
        raise FileFormatError(f"{path}: VolumeReconstruction OutputSpacing is missing")
    if np.any(spacing <= 0):
        raise FileFormatError(f"{path}: VolumeReconstruction OutputSpacing: must be positive, got {spacing.tolist()}")
    clip_origin = _numbers(path, element, "ClipRectangleOrigin", 2, integer=True)
    clip_size = _numbers(path, element, "ClipRectangleSize", 2, integer=True)
    clip: tuple[tuple[int, int] | None, tuple[int, int] | None] = (None, None)
    if clip_size is not None and np.all(clip_size > 0):  # PLUS clips only with a positive size
        origin = (0, 0) if clip_origin is None else (int(clip_origin[0]), int(clip_origin[1]))
        clip = (origin, (int(clip_size[0]), int(clip_size[1])))
    extent = _numbers(path, element, "OutputExtent", 6, integer=True)
    output_extent = None
    if extent is not None:
        i0, i1, j0, j1, k0, k1 = (int(v) for v in extent)
        counts = [i1 - i0 + 1, j1 - j0 + 1, k1 - k0 + 1]
        if min(counts) < 1 or max(counts) > MAX_AXIS_SIZE:
            raise FileFormatError(
                f"{path}: VolumeReconstruction OutputExtent: expected 'i0 i1 j0 j1 k0 k1' with 1 to {MAX_AXIS_SIZE} "
                f"voxels along each axis, got {extent.tolist()}"
            )
        output_extent = (i0, i1, j0, j1, k0, k1)
    fan_angles = _numbers(path, element, "FanAnglesDeg", 2)
    fan_origin = _numbers(path, element, "FanOriginPixel", 2)
    fan_radius = [_numbers(path, element, f"FanRadius{end}Pixel", 1) for end in ("Start", "Stop")]
    if fan_angles is not None and fan_origin is None:
        raise FileFormatError(f"{path}: VolumeReconstruction FanAnglesDeg needs FanOriginPixel")
    if fan_angles is not None and not (-90 < fan_angles[0] <= fan_angles[1] < 90):
        raise FileFormatError(
            f"{path}: VolumeReconstruction FanAnglesDeg {fan_angles[0]:g} {fan_angles[1]:g}: expected "
            "min <= max, both strictly between -90 and 90 degrees"
        )
    fill_holes = (element.get("FillHoles") or "OFF").strip().upper() == "ON"
    hole_filling = _read_hole_filling(path, element)
    if fill_holes and not hole_filling:
        raise FileFormatError(f"{path}: VolumeReconstruction FillHoles is ON but no HoleFilling/HoleFillingElement")
    return ReconstructionSettings(
        output_spacing_mm=spacing,
        interpolation=_choice(path, element, "Interpolation", _INTERPOLATION) or "nearest",
        compounding=_compounding(path, element),
        fill_holes=fill_holes,
        hole_filling=hole_filling,
        clip_rectangle_origin=clip[0],
        clip_rectangle_size=clip[1],
        output_origin_mm=_numbers(path, element, "OutputOrigin", 3),
        output_extent=output_extent,
        fan_angles_deg=None if fan_angles is None else (float(fan_angles[0]), float(fan_angles[1])),
        fan_origin_pixel=(0.0, 0.0) if fan_origin is None else (float(fan_origin[0]), float(fan_origin[1])),
        fan_radius_pixels=(
            0.0 if fan_radius[0] is None else float(fan_radius[0][0]),
            np.inf if fan_radius[1] is None else float(fan_radius[1][0]),
        ),
    )


def read_plus_config(path: str | Path) -> PlusConfig:
    """Read the CoordinateDefinitions transforms and VolumeReconstruction settings of a PLUS XML file.

    Raises FileFormatError naming the file and the element/attribute for malformed XML, matrices
    or settings.
    """
    path = regular_file(Path(path), "configuration")
    try:
        root = ElementTree.parse(path).getroot()
    except ElementTree.ParseError as exc:
        raise FileFormatError(f"{path}: not well-formed XML ({exc})") from None
    return PlusConfig(transforms=_read_transforms(path, root), reconstruction=_read_reconstruction(path, root))
