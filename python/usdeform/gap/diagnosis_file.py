"""diagnosis.json read as data: the one reader for ``fit/correct --compensate`` and ``live --image-delay``.

The file is checked against the part of the contract (:mod:`usdeform.gap`) a reader acts on, with a pydantic schema:
``verdict`` one of the verdicts, ``named`` effect IDs of the library (or pairs ``a+b``) each with an entry in
``effects``, and every effect's ``parameters`` and ``uncertainty`` finite numbers, each of its ``unidentified``
parameters one of them mapped to a record_next kind. ``unsolved_sections`` entries have a recording, section, error
and effect, ``resolved_sections`` entries a recording, section and how; ``sensor_calibration`` entries are
:class:`usdeform.gap.sensor_calibration.SensorCalibration` with non-negative uncertainties. A parameter the library fits
(:data:`usdeform.gap.models.EFFECTS`) must lie within the library's bounds, the force sensor's linear terms within
:data:`LINEAR_BOUNDS`, an uncertainty must not be negative. Each bad case is an :class:`~usdeform.errors.InputError`
naming the file and the field. The other keys pass as written.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..errors import FileFormatError, InputError
from .follow_up import KINDS
from .models import EFFECT_BY_ID
from .verdicts import VERDICTS

__all__ = ["LINEAR_BOUNDS", "check_diagnosis", "diagnosis_path", "read_diagnosis"]

#: Bounds of the force sensor's linear terms, beyond any sensor's bias (N) and drift (N/s).
LINEAR_BOUNDS = {"offset_n": (-50.0, 50.0), "drift_n_per_s": (-1.0, 1.0)}
_TOLERANCE = 1e-6  # relative: a bound written and read back through JSON


class _Effect(BaseModel):
    model_config = ConfigDict(extra="allow", allow_inf_nan=False, strict=True)

    effect: str
    parameters: dict[str, float] = Field(default_factory=dict)
    uncertainty: dict[str, float | None] = Field(default_factory=dict)
    significant: bool = False
    unidentified: dict[str, str] = Field(default_factory=dict)


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    recording: str
    section: str
    error: str | None = None
    effect: str | None = None
    how: str | None = None


class _SensorCalibration(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)

    recording: str
    gain_error: float
    gain_error_uncertainty: float = Field(ge=0)
    offset_n: float
    offset_uncertainty_n: float = Field(ge=0)
    drift_n_per_s: float | None
    drift_uncertainty_n_per_s: float | None = Field(ge=0)
    frames: int = Field(ge=1)


class _Diagnosis(BaseModel):
    model_config = ConfigDict(extra="allow", allow_inf_nan=False, strict=True)

    verdict: str
    named: list[str] = Field(default_factory=list)
    effects: list[_Effect]
    unsolved_sections: list[_Section] = Field(default_factory=list)
    resolved_sections: list[_Section] = Field(default_factory=list)
    sensor_calibration: list[_SensorCalibration] = Field(default_factory=list)


def diagnosis_path(path: str | Path) -> Path:
    """``path``, or ``path/diagnosis.json`` for the folder of ``usdeform diagnose``."""
    path = Path(path)
    return path / "diagnosis.json" if path.is_dir() else path


def _field(location: tuple[Any, ...]) -> str:
    """A pydantic error location as a field path: ``effects[2].parameters.delay_s``."""
    text = ""
    for part in location:
        text += f"[{part}]" if isinstance(part, int) else f".{part}" if text else str(part)
    return text or "(the document)"


def _bounds(member: str, name: str) -> tuple[float, float] | None:
    model = EFFECT_BY_ID[member]
    if name in model.parameters:
        low, high = model.bounds[model.parameters.index(name)]
        return float(low), float(high)
    if member == "force_sensor_error":
        return LINEAR_BOUNDS.get(name)
    return None


def _check_effect(source: str, index: int, entry: _Effect) -> None:
    where = f"effects[{index}]"
    members = entry.effect.split("+")
    unknown = [member for member in members if member not in EFFECT_BY_ID]
    if unknown or len(members) > 2:
        raise InputError(f"{source}: {where}.effect: {entry.effect!r} is no effect of the library or pair of them")
    for name, value in entry.parameters.items():
        ranges = [bounds for member in members if (bounds := _bounds(member, name)) is not None]
        for low, high in ranges[:1]:
            slack = _TOLERANCE * max(abs(low), abs(high), 1.0)
            if not low - slack <= value <= high + slack:
                raise InputError(
                    f"{source}: {where}.parameters.{name}: {value!r} is outside the library's range {low:g}..{high:g}"
                )
    for name, kind in entry.unidentified.items():
        if name not in entry.parameters:
            raise InputError(f"{source}: {where}.unidentified.{name}: no such parameter in 'parameters'")
        if kind not in KINDS:
            raise InputError(f"{source}: {where}.unidentified.{name}: expected a recording kind, got {kind!r}")
    for name, error in entry.uncertainty.items():
        if error is not None and error < 0:
            raise InputError(f"{source}: {where}.uncertainty.{name}: expected a non-negative number, got {error!r}")


def check_diagnosis(document: object, source: str) -> dict[str, Any]:
    """``document`` (a parsed diagnosis.json) checked (module docstring); returns it. ``source`` names it in errors."""
    missing = [key for key in ("verdict", "effects") if not isinstance(document, dict) or key not in document]
    if missing or not isinstance(document, dict):
        raise InputError(f"{source}: not a diagnosis.json ('usdeform diagnose' writes one): no {' or '.join(missing)}")
    try:
        parsed = _Diagnosis.model_validate(document)
    except ValidationError as error:
        first = error.errors()[0]
        raise InputError(f"{source}: {_field(first['loc'])}: {first['msg'].lower()}") from None
    if parsed.verdict not in VERDICTS:
        raise InputError(f"{source}: verdict: expected one of {', '.join(VERDICTS)}, got {parsed.verdict!r}")
    for index, entry in enumerate(parsed.effects):
        _check_effect(source, index, entry)
    for key in ("unsolved_sections", "resolved_sections"):
        for index, section in enumerate(getattr(parsed, key)):
            needed = ("error", "effect") if key == "unsolved_sections" else ("how",)
            absent = [name for name in needed if getattr(section, name) is None]
            if absent:
                raise InputError(f"{source}: {key}[{index}]: no {' or '.join(absent)}")
    listed = {entry.effect for entry in parsed.effects}
    for index, name in enumerate(parsed.named):
        if name not in listed:
            raise InputError(f"{source}: named[{index}]: {name!r} has no entry in 'effects'")
    return document


def read_diagnosis(path: str | Path) -> dict[str, Any]:
    """The diagnosis.json at ``path`` (or in the folder ``path``), read and checked (module docstring)."""
    file = diagnosis_path(path)
    try:
        document = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as error:
        raise FileFormatError(f"{file}: not a readable diagnosis.json ({error})") from None
    return check_diagnosis(document, str(file))
