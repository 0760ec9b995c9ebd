"""Model files: a fitted displacement model and its sampled stiffness profiles, as versioned JSON.

A model file holds everything needed to correct a sweep without refitting::

    {
      "format": "usdeform-deformation-model",
      "version": 2,
      "basis": {"name": "quadratic"}                  (or {"name": "bspline", "n_y": 6, "n_x": 8}),
      "coefficients": [[...], [...]],                  (2, 10), or (2, 3, n_y, n_x) for the B-spline basis
      "normalization": {"x_scale": ..., "y_scale": ..., "force_scale": ..., "h_scale": ...,
                        "lateral_scale": ..., "axial_scale": ...},
      "n_intervals": 64, "coupling": "stiffness", "integration": "force",
      "frame_shape": [rows, cols],                     (since version 2)
      "vessel": {"coefficients": [...], "reference": {"centre_px": [x, y], "radius_px": r},
                 "window_radii": 2.0,                  (optional: a VesselAnchoredModel's vessel part)
                 "other_vessels": [{"coefficients": [...], "reference": {...}}, ...]},  (optional: further vessels)
      "sampled_positions": [{"position_mm": [x, y, z], "profile": {"c1": ..., "c2": ..., "c3": ...},
                             "lumens": [{"centre_px": [x, y], "radius_px": r} or null, ...]}, ...],
      "provenance": {"loss": ..., "solver": "exact", "usdeform_version": "0.1.0", ...}
    }

``sampled_positions`` (optional) are where the stiffness was palpated: a position along the sweep
(mm) or in the robot base frame (mm), each with its :class:`~usdeform.regression.StiffnessProfile`
(N/mm^2, N/mm, N), and (optional) the lumens the palpation showed at contact, vessel by vessel as the
``vessel`` parts are ordered (null: not seen there; :attr:`SampledProfiles.lumens`).
Numbers are written as the shortest text that reads back to the same float64,
so a file round-trips exactly.

Version 1 files (without ``frame_shape``) still load: their frame shape is taken from the
normalisation, as ``Normalization.frame_shape`` says (``(round(y_scale) + 1, round(x_scale) + 1)``,
exact for every model fitted by this package on frames of at least 2 x 2 pixels).
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import singledispatch
from pathlib import Path
from typing import Any

import numpy as np

from .._files import atomic_output
from ..correction import SampledProfiles
from ..errors import FileFormatError, InputError
from ..regression import (
    BSPLINE_MIN_FUNCTIONS,
    BSplineDisplacementModel,
    DeformationModel,
    DisplacementModel,
    Normalization,
    QuadraticDisplacementModel,
    RegressionFit,
    StiffnessProfile,
    VesselAnchor,
    VesselAnchoredModel,
)
from ..validation import MAX_INTERVALS, regular_file

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "READABLE_VERSIONS",
    "ModelFile",
    "SampledProfiles",
    "fit_provenance",
    "load_model",
    "save_model",
]

#: The ``format`` name of a model file and the ``version`` this package writes.
FORMAT_NAME = "usdeform-deformation-model"
FORMAT_VERSION = 2
#: Every version this package reads. Version 1 files have no ``frame_shape``: it is migrated from the
#: normalisation (``round(scale) + 1`` pixels per axis, see ``Normalization.frame_shape``).
READABLE_VERSIONS = (1, 2)

#: Largest frame rows or columns, B-spline functions per axis and size of a model file.
MAX_FRAME_SIZE = 65536
_MAX_FUNCTIONS = 4096
MAX_MODEL_FILE_BYTES = 256 * 1024**2

_NORMALIZATION_FIELDS = tuple(f.name for f in dataclasses.fields(Normalization))
_PROFILE_FIELDS = ("c1", "c2", "c3")


@dataclass(frozen=True, eq=False)
class ModelFile:
    """The content of a model file: the model, its sampled profiles (None if not recorded) and the
    free-form provenance (fit loss, solver, smoothness, usdeform version, ...)."""

    model: DisplacementModel | VesselAnchoredModel
    sampled: SampledProfiles | None = None
    provenance: dict[str, Any] = field(default_factory=dict)


def fit_provenance(fit: RegressionFit) -> dict[str, Any]:
    """The provenance of a fitted model: loss (normalised units), solver, iterations, samples, smoothness."""
    return {
        "loss": fit.loss,
        "solver": fit.solver,
        "iterations": fit.iterations,
        "n_samples": fit.n_samples,
        "smoothness": fit.smoothness,
    }


def _basis_document(model: object) -> dict[str, Any]:
    if isinstance(model, BSplineDisplacementModel):
        n_y, n_x = model.n_functions
        return {"name": "bspline", "n_y": n_y, "n_x": n_x}
    if isinstance(model, QuadraticDisplacementModel):
        return {"name": "quadratic"}
    raise InputError(
        f"model: expected a QuadraticDisplacementModel or BSplineDisplacementModel, got {type(model).__name__}"
    )


@singledispatch
def _vessel_document(model: object) -> dict[str, Any] | None:
    """The ``vessel`` object of a model with a part anchored to the vessel; None for the others."""
    return None


@_vessel_document.register
def _(model: VesselAnchoredModel) -> dict[str, Any]:
    def part(coefficients: np.ndarray, reference: VesselAnchor) -> dict[str, Any]:
        return {
            "coefficients": coefficients.tolist(),
            "reference": {"centre_px": list(reference.centre_px), "radius_px": reference.radius_px},
        }

    document = {**part(model.vessel_coefficients, model.reference), "window_radii": model.window_radii}
    if model.other_vessels:
        document["other_vessels"] = [part(grid, reference) for grid, reference in model.other_vessels]
    return document


def _position_document(position: np.ndarray) -> float | list[float]:
    return float(position) if position.ndim == 0 else position.tolist()


def _dumps(value: Any, indent: str = "") -> str:
    """JSON text with two-space indentation, except that lists of numbers stay on one line."""
    inner = indent + "  "
    if isinstance(value, dict) and value:
        items = (f"{inner}{json.dumps(key)}: {_dumps(item, inner)}" for key, item in value.items())
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(value, list) and value and not all(isinstance(item, (int, float)) for item in value):
        return "[\n" + ",\n".join(inner + _dumps(item, inner) for item in value) + "\n" + indent + "]"
    return json.dumps(value, allow_nan=False)


def save_model(
    path: str | Path,
    model: DeformationModel,
    sampled_positions: SampledProfiles | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> None:
    """Write ``model`` (and where its stiffness was sampled) as a model file, atomically.

    Parameters
    ----------
    path : str or Path
        The file to write (JSON).
    model : DisplacementModel or VesselAnchoredModel
        The model, with its frame shape (a vessel-anchored model: its image part, and its vessel
        part under ``vessel``).
    sampled_positions : SampledProfiles, optional
        Where the stiffness was palpated.
    provenance : mapping, optional
        JSON values (numbers, strings, lists, objects); ``usdeform_version`` is added unless given.

    Raises
    ------
    InputError
        For an unknown model type, pixel scales that are not those of the model's frame shape, a sampled
        stiffness profile that does not rise over the fitted force range (:func:`load_model` would refuse
        the file), or a provenance that JSON cannot hold (including non-finite numbers).
    """
    basis = _basis_document(getattr(model, "image_model", model))  # InputError naming any other type
    image = model.image_model
    rows, cols = image.kernel.frame_shape
    problem = _scale_problem(image.normalization.as_array().tolist(), (rows, cols), f"the frame shape {rows} x {cols}")
    if not problem and isinstance(sampled_positions, SampledProfiles):
        problem = _profile_problem(sampled_positions, image.normalization.force_scale)
    if problem:  # refused before writing: load_model would refuse the file
        raise InputError(f"model: {problem[0]}: {problem[1]}")
    document: dict[str, Any] = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "basis": basis,
        "coefficients": image.coefficients.tolist(),
        "normalization": dict(zip(_NORMALIZATION_FIELDS, image.normalization.as_array().tolist(), strict=False)),
        "n_intervals": image.n_intervals,
        "coupling": image.coupling,
        "integration": image.integration,
        "frame_shape": list(image.kernel.frame_shape),
    }
    vessel = _vessel_document(model)
    if vessel is not None:
        document["vessel"] = vessel
    if sampled_positions is not None:
        if not isinstance(sampled_positions, SampledProfiles):
            raise InputError(f"sampled_positions: expected SampledProfiles, got {type(sampled_positions).__name__}")
        document["sampled_positions"] = [
            {
                "position_mm": _position_document(position),
                "profile": dict(zip(_PROFILE_FIELDS, profile.as_tuple(), strict=False)),
            }
            for position, profile in zip(sampled_positions.positions_mm, sampled_positions.profiles, strict=False)
        ]
        for item, lumens in zip(document["sampled_positions"], sampled_positions.lumens or (), strict=False):
            item["lumens"] = [
                None if lumen is None else {"centre_px": list(lumen.centre_px), "radius_px": lumen.radius_px}
                for lumen in lumens
            ]
    document["provenance"] = {"usdeform_version": importlib.metadata.version("usdeform"), **(provenance or {})}
    try:
        text = _dumps(document) + "\n"
    except (TypeError, ValueError) as exc:
        raise InputError(f"provenance: cannot be written as JSON ({exc})") from None
    with atomic_output(Path(path)) as handle:
        handle.write(text.encode("utf-8"))


class _Reader:
    """Checked access to the fields of one parsed model file; errors name the file and the field."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def error(self, name: str, message: str) -> FileFormatError:
        return FileFormatError(f"{self.path}: {name}: {message}")

    def object(self, name: str, value: Any, required: Sequence[str], optional: Sequence[str] = ()) -> dict:
        if not isinstance(value, dict):
            raise self.error(name, f"expected a JSON object, got {json.dumps(value)[:60]}")
        missing = [key for key in required if key not in value]
        if missing:
            raise self.error(f"{name}.{missing[0]}" if name else missing[0], "missing field")
        unknown = sorted(set(value) - set(required) - set(optional))
        if unknown:
            raise self.error(f"{name}.{unknown[0]}" if name else unknown[0], "unknown field")
        return value

    def number(self, name: str, value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(name, f"expected a number, got {json.dumps(value)[:60]}")
        try:
            number = float(value)
        except OverflowError:  # an integer beyond float64
            raise self.error(name, f"number out of range: {str(value)[:40]}") from None
        if not np.isfinite(number):
            raise self.error(name, f"non-finite number {value}")
        return number

    def integer(self, name: str, value: Any, minimum: int, maximum: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not minimum <= value <= maximum:
            raise self.error(name, f"expected an integer from {minimum} to {maximum}, got {json.dumps(value)[:60]}")
        return value

    def choice(self, name: str, value: Any, choices: Sequence[Any]) -> Any:
        if value not in choices:
            raise self.error(name, f"expected one of {', '.join(map(repr, choices))}, got {value!r}")
        return value

    def array(self, name: str, value: Any, shape: tuple[int, ...], expected: str) -> np.ndarray:
        """Nested lists of finite numbers of exactly ``shape``, as float64; ``expected`` says why
        that shape (e.g. "for the basis")."""

        def nested(part: str, value: Any, depth: int) -> Any:
            if depth == len(shape):
                return self.number(part, value)
            if not isinstance(value, list) or len(value) != shape[depth]:
                got = f"has {len(value)} items" if isinstance(value, list) else f"is {json.dumps(value)[:60]}"
                raise self.error(name, f"expected shape {shape} {expected}; {part} {got}")
            return [nested(f"{part}[{i}]", item, depth + 1) for i, item in enumerate(value)]

        return np.array(nested(name, value, 0), dtype=np.float64)


def _read_model(reader: _Reader, document: dict) -> DisplacementModel:
    basis = reader.object("basis", document["basis"], ["name"], ["n_y", "n_x"])
    name = reader.choice("basis.name", basis["name"], ("quadratic", "bspline"))
    if name == "quadratic":
        reader.object("basis", basis, ["name"])
        model_type: type[DisplacementModel] = QuadraticDisplacementModel
        shape: tuple[int, ...] = (2, 10)
    else:
        reader.object("basis", basis, ["name", "n_y", "n_x"])
        model_type = BSplineDisplacementModel
        shape = (
            2,
            3,
            reader.integer("basis.n_y", basis["n_y"], BSPLINE_MIN_FUNCTIONS, _MAX_FUNCTIONS),
            reader.integer("basis.n_x", basis["n_x"], BSPLINE_MIN_FUNCTIONS, _MAX_FUNCTIONS),
        )
    coefficients = reader.array("coefficients", document["coefficients"], shape, "for the basis")
    fields = reader.object("normalization", document["normalization"], _NORMALIZATION_FIELDS)
    scales = [reader.number(f"normalization.{key}", fields[key]) for key in _NORMALIZATION_FIELDS]
    n_intervals = reader.integer("n_intervals", document["n_intervals"], 1, MAX_INTERVALS)
    frame_shape = None  # version 1: migrated from the normalisation by the model
    if "frame_shape" in document:
        value = document["frame_shape"]
        if not isinstance(value, list) or len(value) != 2:
            raise reader.error("frame_shape", f"expected [rows, cols], got {json.dumps(value)[:60]}")
        frame_shape = (
            reader.integer("frame_shape[0]", value[0], 1, MAX_FRAME_SIZE),
            reader.integer("frame_shape[1]", value[1], 1, MAX_FRAME_SIZE),
        )
    if frame_shape is None:  # version 1: Normalization.frame_shape
        problem = _scale_problem(scales, (max(round(scales[1]), 0) + 1, max(round(scales[0]), 0) + 1), "version 1")
    else:
        problem = _scale_problem(scales, frame_shape, f"frame_shape {frame_shape[0]} x {frame_shape[1]}")
    if problem:
        raise reader.error(problem[0], f"{problem[1]}; the file is corrupt or edited")
    try:
        return model_type(
            coefficients,
            Normalization(*scales),
            n_intervals,
            document["coupling"],
            document["integration"],
            frame_shape,
        )
    except InputError as exc:
        raise FileFormatError(f"{reader.path}: {exc}") from None


#: Relative difference allowed between a pixel scale and the one the frame shape gives (the file's decimal text
#: reads back exactly; this only absorbs a file edited by hand to the same value).
_SCALE_TOLERANCE = 1e-9


def _scale_problem(scales: Sequence[float], frame_shape: tuple[int, int], source: str) -> tuple[str, str] | None:
    """(field, message) if the pixel scales are not the ones a fit on ``frame_shape`` gives (``cols - 1``,
    ``rows - 1``, at least 1): others put every pixel at the wrong normalised coordinate and correct frames
    by the displacement of another place (126 on 64 x 64 frames), or by nothing (1e-300: all-zero frames)."""
    rows, cols = frame_shape
    for key, scale, expected in (("x_scale", scales[0], max(cols - 1, 1)), ("y_scale", scales[1], max(rows - 1, 1))):
        if not abs(scale - expected) <= _SCALE_TOLERANCE * expected:
            axis = "cols" if key == "x_scale" else "rows"
            return f"normalization.{key}", f"{scale:g} disagrees with {source}, whose fit gives {expected} ({axis} - 1)"
    return None


def _profile_problem(sampled: SampledProfiles, max_force_n: float) -> tuple[str, str] | None:
    """(field, message) if a sampled stiffness profile does not rise (stiffness ``2 c1 lambda + c2 > 0``)
    from the start of the palpation up to the model's largest fitted force: a correction reads each
    frame's displacement off that rising branch."""
    for i, profile in enumerate(sampled.profiles):
        reached = profile.lambda_at(max_force_n)
        if profile.c2 <= 0 or not np.isfinite(reached) or profile.stiffness_at(reached) <= 0:
            return (
                f"sampled_positions[{i}].profile",
                f"(c1, c2, c3) = ({profile.c1:g}, {profile.c2:g}, {profile.c3:g}) does not rise over the fitted "
                f"force range 0-{max_force_n:g} N (stiffness 2 c1 lambda + c2 must stay positive)",
            )
    return None


def _read_vessel(reader: _Reader, image: DisplacementModel, vessel: Any) -> VesselAnchoredModel:
    """The vessel-anchored model of the ``vessel`` field on ``image``."""
    reader.object("vessel", vessel, ["coefficients", "reference", "window_radii"], ["other_vessels"])
    array, reference = _read_vessel_part(reader, "vessel", vessel)
    others = vessel.get("other_vessels", [])
    if not isinstance(others, list):
        raise reader.error("vessel.other_vessels", "expected a list of vessel parts")
    parts = []
    for index, other in enumerate(others):
        name = f"vessel.other_vessels[{index}]"
        reader.object(name, other, ["coefficients", "reference"])
        parts.append(_read_vessel_part(reader, name, other))
    try:
        return VesselAnchoredModel(
            image, array, reference, reader.number("vessel.window_radii", vessel["window_radii"]), tuple(parts)
        )
    except InputError as exc:
        raise FileFormatError(f"{reader.path}: vessel: {exc}") from None


def _read_vessel_part(reader: _Reader, name: str, part: dict[str, Any]) -> tuple[np.ndarray, VesselAnchor]:
    """The coefficients (2, 3, n, n) and reference lumen of the vessel part ``name``."""
    coefficients = first = part["coefficients"]
    for _ in range(2):  # the grid's size n is read from [0][0]; reader.array checks the rest against it
        first = first[0] if isinstance(first, list) and first else None
    n = len(first) if isinstance(first, list) else 0
    if not 1 <= n <= _MAX_FUNCTIONS:
        raise reader.error(f"{name}.coefficients", f"expected a (2, 3, n, n) array with n from 1 to {_MAX_FUNCTIONS}")
    array = reader.array(f"{name}.coefficients", coefficients, (2, 3, n, n), "for the vessel part")
    return array, _read_anchor(reader, f"{name}.reference", part["reference"])


def _read_anchor(reader: _Reader, name: str, item: Any) -> VesselAnchor:
    """A lumen ``{centre_px: [x, y], radius_px: r}`` (pixels)."""
    reader.object(name, item, ["centre_px", "radius_px"])
    centre = reader.array(f"{name}.centre_px", item["centre_px"], (2,), "as (x, y)")
    try:
        return VesselAnchor(tuple(centre), reader.number(f"{name}.radius_px", item["radius_px"]))
    except InputError as exc:
        raise reader.error(name, str(exc)) from None


def _read_lumens(reader: _Reader, name: str, items: Any) -> tuple[VesselAnchor | None, ...]:
    """A sampled position's lumens at contact (null: a vessel not seen there)."""
    if not isinstance(items, list):
        raise reader.error(name, "expected a list of {centre_px, radius_px} objects or nulls")
    return tuple(None if item is None else _read_anchor(reader, f"{name}[{i}]", item) for i, item in enumerate(items))


def _read_sampled(reader: _Reader, items: Any) -> SampledProfiles:
    if not isinstance(items, list) or not items:
        raise reader.error("sampled_positions", "expected a non-empty list of {position_mm, profile} objects")
    first = items[0].get("position_mm") if isinstance(items[0], dict) else None
    shape = (len(first),) if isinstance(first, list) else ()  # every position has the first one's coordinates
    positions, profiles, lumens = [], [], []
    for i, item in enumerate(items):
        name = f"sampled_positions[{i}]"
        reader.object(name, item, ["position_mm", "profile"], ["lumens"])
        lumens.append(_read_lumens(reader, f"{name}.lumens", item["lumens"]) if "lumens" in item else None)
        positions.append(reader.array(f"{name}.position_mm", item["position_mm"], shape, "like sampled_positions[0]"))
        coefficients = reader.object(f"{name}.profile", item["profile"], _PROFILE_FIELDS)
        profiles.append(
            StiffnessProfile(*(reader.number(f"{name}.profile.{key}", coefficients[key]) for key in _PROFILE_FIELDS))
        )
    try:
        return SampledProfiles(
            np.array(positions),
            tuple(profiles),
            None if None in lumens else tuple(lumens),  # type: ignore[arg-type]
        )
    except InputError as exc:
        raise reader.error("sampled_positions", str(exc)) from None


def load_model(path: str | Path) -> ModelFile:
    """Read a model file written by :func:`save_model`.

    The file is checked as a whole: besides each field, the pixel scales must be those of its
    ``frame_shape`` and every sampled stiffness profile must rise over the fitted force range.

    Raises FileFormatError naming the file and the field for invalid JSON, an unknown format or
    version, a missing or unknown field, coefficients whose shape does not fit the basis,
    non-finite or out-of-range values, and fields that disagree with each other; OSError if the
    file cannot be read.
    """
    path = regular_file(Path(path), "model file")
    reader = _Reader(path)
    text = path.read_bytes()
    if not text:
        raise FileFormatError(f"{path}: the file is empty (0 bytes)")
    if len(text) > MAX_MODEL_FILE_BYTES:
        raise FileFormatError(f"{path}: {len(text)} bytes, more than a model file holds ({MAX_MODEL_FILE_BYTES})")
    try:
        document = json.loads(text.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise FileFormatError(f"{path}: not UTF-8 text ({exc})") from None
    except json.JSONDecodeError as exc:
        raise FileFormatError(f"{path}: not JSON: {exc}") from None
    except (ValueError, RecursionError) as exc:  # integers of thousands of digits, nesting thousands deep
        raise FileFormatError(f"{path}: not a model file: {str(exc)[:100]}") from None
    required = ["format", "version", "basis", "coefficients", "normalization", "n_intervals", "coupling", "integration"]
    if not isinstance(document, dict):
        raise FileFormatError(f"{path}: expected a JSON object at the top level")
    for name in ("format", "version"):  # checked first: other versions may have other fields
        if name not in document:
            raise reader.error(name, "missing field; not a usdeform model file")
    reader.choice("format", document["format"], (FORMAT_NAME,))
    version = document["version"]
    if isinstance(version, bool) or version not in READABLE_VERSIONS:
        readable = ", ".join(map(str, READABLE_VERSIONS))
        raise reader.error("version", f"this usdeform reads versions {readable}, got {version!r}")
    if version >= 2:
        required.append("frame_shape")
    reader.object("", document, required, ["sampled_positions", "provenance", "vessel"])
    image = _read_model(reader, document)
    model = _read_vessel(reader, image, document["vessel"]) if "vessel" in document else image
    sampled = _read_sampled(reader, document["sampled_positions"]) if "sampled_positions" in document else None
    problem = sampled and _profile_problem(sampled, image.normalization.force_scale)
    if problem:
        raise reader.error(problem[0], f"{problem[1]}; the file is corrupt or edited")
    provenance = document.get("provenance", {})
    if not isinstance(provenance, dict):
        raise reader.error("provenance", "expected a JSON object")
    return ModelFile(model, sampled, provenance)
