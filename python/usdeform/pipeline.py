"""The method's two runs on files, the one door that ``usdeform fit``, ``usdeform correct`` and the batch runner use.

:func:`fit_model` fits one position's palpations (PLUS sequence files) and writes the model file (and its
report); :func:`correct_sweep` corrects one sweep with a model file and writes the corrected sequence (and
its volume and coverage). Both take one :class:`PipelineSettings`, which holds every option of both
commands with the commands' defaults; the command line builds it from its flags and a batch manifest
(:class:`usdeform.batch.Options`) from its options, so every option exists in both. Every output is
written atomically, and the outputs of one run replace the old ones together or not at all.

>>> settings = PipelineSettings(flexible_layer_mm=40.0, wall_weight=0.5, fill_holes="gaussian")
>>> settings.fit_method().basis
('bspline', 8, 8)
>>> CHOICES["voxel_type"]
('float32', 'uint8')
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from ._files import outputs_together
from .compensation import Compensation, apply_compensation, compensation_option
from .correction import (
    STIFFNESS_SOURCE_CHOICES,
    STIFFNESS_SOURCE_FIELD,
    SampledProfiles,
    StiffnessSourceChoice,
    correct_recording,
)
from .errors import InputError
from .fitting import (
    FIT_METHODS,
    FitMethod,
    FitReport,
    FittedPalpations,
    MethodName,
    assess_fit,
    fit_method,
    fit_palpations,
    write_fit_report,
)
from .io import load_model, read_sequence, save_model, write_sequence, write_volume
from .options import (
    ANCHORS,
    COMPOUNDINGS,
    COUPLINGS,
    DEFAULT_COMPRESSION_LEVEL,
    INTEGRATIONS,
    INTERPOLATIONS,
    SOLVERS,
    WALL_MODES,
    Anchor,
    Compounding,
    Coupling,
    Integration,
    Interpolation,
    Solver,
    WallMode,
    checked_option,
)
from .recording import Recording
from .volume import DEFAULT_SPACING_MM, HoleFillingElement, HoleFillingKind, Volume, VoxelType, compound_recording

__all__ = [
    "CHOICES",
    "FILL_HOLES",
    "FIT_FIELDS",
    "SETTINGS_FIELDS",
    "SWEEP_FIELDS",
    "VOLUME_FIELDS",
    "CorrectedSweep",
    "FillHoles",
    "FittedModel",
    "PipelineSettings",
    "compounding_keywords",
    "correct_sweep",
    "fit_model",
    "hole_filling_steps",
]

#: ``fill_holes``: no hole filling ("off"), or one step of a PLUS HoleFillingElement type with PLUS's parameters.
FillHoles = Literal["off"] | HoleFillingKind
FILL_HOLES: tuple[FillHoles, ...] = ("off", *get_args(HoleFillingKind))


def _declared(stage: str, choices: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The metadata of a setting: the ``stage`` it belongs to ("fit", "sweep": the correction, "volume": the
    sweep's volume, "file": how files are written, "compensation") and, for an option that is one of a few,
    its ``choices``. :data:`CHOICES` and the ``*_FIELDS`` tuples are read from it."""
    return {"stage": stage, "choices": choices}


@dataclass(frozen=True)
class PipelineSettings:
    """Every option of a fit (as ``usdeform fit``), a sweep's correction and volume (as ``usdeform correct``)
    and the diagnosis both compensate, with the command line's defaults. Lengths in mm, memory in GiB.

    ``flexible_layer_mm`` is required to fit. ``method`` names a fit method; ``basis``, ``coupling``,
    ``integration``, ``wall`` and ``anchor`` replace its settings (None: the method's). ``wall_weight``
    weighs the vessel wall's mean squared error against the tracks'. ``stiffness_source`` and
    ``clamp_force`` are :func:`~usdeform.correction.correct_recording`'s. ``compression_level`` is the
    volume files' compression level (1 fastest, ISA-L's deflate; 2-9 zlib's). ``compensate`` is the path of a
    diagnosis.json whose effects are undone on every recording first, ``force_compensation`` applies it even
    where it does not support that. Each field declares its stage and choices once (:data:`CHOICES`,
    :data:`FIT_FIELDS`, :data:`SWEEP_FIELDS` and :data:`VOLUME_FIELDS` are read from them; the batch manifest's
    options are these fields)."""

    flexible_layer_mm: float | None = field(default=None, metadata=_declared("fit"))
    method: MethodName = field(default="recommended", metadata=_declared("fit", tuple(FIT_METHODS)))
    basis: str | None = field(default=None, metadata=_declared("fit"))
    solver: Solver = field(default="exact", metadata=_declared("fit", SOLVERS))
    coupling: Coupling | None = field(default=None, metadata=_declared("fit", COUPLINGS))
    integration: Integration | None = field(default=None, metadata=_declared("fit", INTEGRATIONS))
    wall: WallMode | None = field(default=None, metadata=_declared("fit", WALL_MODES))
    anchor: Anchor | None = field(default=None, metadata=_declared("fit", ANCHORS))
    smoothness: float | None = field(default=None, metadata=_declared("fit"))
    wall_weight: float = field(default=1.0, metadata=_declared("fit"))
    stiffness_source: StiffnessSourceChoice = field(
        default="auto", metadata=_declared("sweep", STIFFNESS_SOURCE_CHOICES)
    )
    clamp_force: bool = field(default=False, metadata=_declared("sweep"))
    spacing_mm: float = field(default=DEFAULT_SPACING_MM, metadata=_declared("volume"))
    interpolation: Interpolation = field(default="nearest", metadata=_declared("volume", INTERPOLATIONS))
    compounding: Compounding = field(default="mean", metadata=_declared("volume", COMPOUNDINGS))
    max_gib: float = field(default=4.0, metadata=_declared("volume"))
    fill_holes: FillHoles = field(default="off", metadata=_declared("volume", FILL_HOLES))
    voxel_type: VoxelType = field(default="float32", metadata=_declared("volume", get_args(VoxelType)))
    compression_level: int = field(default=DEFAULT_COMPRESSION_LEVEL, metadata=_declared("file"))
    compensate: Path | None = field(default=None, metadata=_declared("compensation"))
    force_compensation: bool = field(default=False, metadata=_declared("compensation"))

    def fit_method(self) -> FitMethod:
        """The named fit method with the settings given here in place of its own."""
        return fit_method(
            self.method,
            basis=self.basis,
            coupling=self.coupling,
            integration=self.integration,
            wall=self.wall,
            anchor=self.anchor,
        )

    def compensation(self, option: str = "compensate", force_option: str = "force_compensation") -> Compensation | None:
        """The compensation ``compensate`` and ``force_compensation`` ask for (None: none), read by
        :func:`usdeform.compensation.compensation_option`; InputError naming ``option`` (or
        ``force_option``) and the file when it is missing or refused."""
        return compensation_option(self.compensate, self.force_compensation, option=option, force_option=force_option)

    @classmethod
    def from_arguments(cls, arguments: object) -> PipelineSettings:
        """The settings from the parsed options of ``usdeform fit`` or ``correct`` (``arguments``: the parsed
        namespace; the other command's settings at their defaults). A diagnosis to compensate is read here, so
        that a refused one is named by its flag before any work."""
        settings = cls(**{name: getattr(arguments, name) for name in SETTINGS_FIELDS if hasattr(arguments, name)})
        settings.compensation(option="--compensate", force_option="--force-compensation")
        return settings

    def compounding_keywords(self) -> dict[str, Any]:
        """The keyword arguments of :func:`~usdeform.volume.compound_recording` these settings give."""
        return compounding_keywords(**{name: getattr(self, name) for name in VOLUME_FIELDS})


#: The names of :class:`PipelineSettings`' fields.
SETTINGS_FIELDS = tuple(setting.name for setting in dataclasses.fields(PipelineSettings))
#: The values of each option that is one of a few, by its settings name (the command line's choices, the
#: batch manifest's check).
CHOICES: dict[str, tuple[str, ...]] = {
    setting.name: setting.metadata["choices"]
    for setting in dataclasses.fields(PipelineSettings)
    if setting.metadata["choices"] is not None
}


def _stage_fields(stage: str) -> tuple[str, ...]:
    return tuple(setting.name for setting in dataclasses.fields(PipelineSettings) if setting.metadata["stage"] == stage)


#: The settings a fit depends on.
FIT_FIELDS = _stage_fields("fit")
#: The settings of a sweep's volume (``compression_level`` changes the file, not the volume).
VOLUME_FIELDS = _stage_fields("volume")
#: The settings a sweep's correction and volume depend on.
SWEEP_FIELDS = (*_stage_fields("sweep"), *VOLUME_FIELDS)


def hole_filling_steps(kind: FillHoles) -> tuple[HoleFillingElement, ...]:
    """``fill_holes`` as hole-filling steps: none for ``"off"``, else one step of that kind with PLUS's defaults."""
    if kind == "off":
        return ()
    return (HoleFillingElement(checked_option("fill_holes", kind, get_args(HoleFillingKind))),)


def compounding_keywords(
    *,
    spacing_mm: float | None,
    interpolation: Interpolation | None,
    compounding: Compounding | None,
    max_gib: float,
    fill_holes: FillHoles | None,
    voxel_type: VoxelType,
) -> dict[str, Any]:
    """The keyword arguments of :func:`~usdeform.volume.compound_recording` for these volume options;
    None: the PLUS configuration's, else the default (0.5 mm, nearest, mean, no hole filling). Memory in GiB."""
    return {
        "spacing_mm": spacing_mm,
        "interpolation": interpolation,
        "compounding": compounding,
        "max_bytes": int(max_gib * 1024**3),
        "hole_filling": None if fill_holes is None else hole_filling_steps(fill_holes),
        "voxel_type": voxel_type,
    }


@dataclass(frozen=True)
class FittedModel:
    """What :func:`fit_model` fitted (``fitted``: the model, its measurements and provenance), the fit's
    report (``report``) and the files it wrote (``written``: the model file, then the report's)."""

    fitted: FittedPalpations
    report: FitReport
    written: tuple[Path, ...]

    def details(self) -> dict[str, Any]:
        """A JSON summary: per-palpation stiffness (N/m, mean and SD), each palpation's phases (which frames
        were fitted), the fit's loss, the report's warnings and, with a compensation, the model's
        ``provenance.compensation`` (the diagnosis, its effects and parameters, whether forced, and one
        note per palpation saying what changed)."""
        fitted = self.fitted
        return {
            "stiffness_n_per_m": [list(position.stiffness.stiffness_mean_sd_n_per_m) for position in fitted.measured],
            "palpation_phases": [phases.to_json() for phases in fitted.phases],
            "loss": fitted.fit.loss,
            "warnings": list(self.report.warnings),
            **({"compensation": fitted.provenance["compensation"]} if "compensation" in fitted.provenance else {}),
        }


def _read_palpations(
    paths: Sequence[Path], labels: Sequence[str], progress: Callable[[str], None] | None
) -> list[Recording]:
    """The palpations at ``paths``; InputError naming both ``labels`` where two have the same frames (a copy
    under another name would be fitted as a second palpation at that place)."""
    recordings, first_with = [], dict[bytes, str]()
    for path, label in zip(paths, labels, strict=True):
        if progress is not None:
            progress(f"reading {path.name}")
        recordings.append(read_sequence(path))
        digest = hashlib.sha256(np.ascontiguousarray(recordings[-1].frames).data).digest()
        if digest in first_with:
            raise InputError(f"{label}: {path} has the same frames as {first_with[digest]}; give each once")
        first_with[digest] = f"{label} ({path})"
    return recordings


def fit_model(
    palpation_paths: Sequence[Path],
    settings: PipelineSettings,
    model_path: Path,
    *,
    report_dir: Path | None = None,
    labels: Sequence[str] | None = None,
    progress: Callable[[str], None] | None = None,
) -> FittedModel:
    """Fit a deformation model to one position's palpations (PLUS sequence files) and write it to
    ``model_path`` (and, with ``report_dir``, the fit's ``report.html`` and ``report.json`` there).

    ``labels`` name the palpations in errors (default ``palpation 1``, ...). ``progress`` is called with
    the step that starts: reading each palpation, then measuring them and the regression. The model file's
    provenance is the fit's with ``method`` and the palpations' paths.

    Raises InputError for settings or palpations at fault (naming the setting or the palpation).
    """
    if settings.flexible_layer_mm is None:
        raise InputError("flexible_layer_mm: required to fit a model")
    method = settings.fit_method()
    compensation = settings.compensation()
    names = [str(path) for path in palpation_paths]
    labels = [f"palpation {index + 1}" for index in range(len(names))] if labels is None else labels
    recordings = _read_palpations(palpation_paths, labels, progress)
    if progress is not None:
        progress(f"measuring {len(recordings)} palpations, regression")
    fitted = fit_palpations(
        recordings,
        settings.flexible_layer_mm,
        method=method,
        names=names,
        solver=settings.solver,
        smoothness=settings.smoothness,
        wall_weight=settings.wall_weight,
        compensation=compensation,
    )
    report = assess_fit(fitted, names=names)
    provenance = {**fitted.provenance, "method": settings.method, "palpations": names}
    written: tuple[Path, ...] = (model_path,)
    with outputs_together():  # the model and its report replace the old ones together, or neither does
        save_model(model_path, fitted.fit.fitted, fitted.sampled, provenance)
        if report_dir is not None:
            written += write_fit_report(report, report_dir)
    return FittedModel(fitted, report, written)


@dataclass(frozen=True)
class CorrectedSweep:
    """What :func:`correct_sweep` did: the sweep as corrected (``recording``, after any compensation), the
    ``corrected`` recording, the model's ``sampled`` positions, the compensation's record (None: none),
    and with a volume the ``volume`` and how many frames it compounded (``n_compounded``)."""

    recording: Recording
    corrected: Recording
    sampled: SampledProfiles
    compensation: dict[str, Any] | None
    volume: Volume | None
    n_compounded: int | None

    @property
    def stiffness_source(self) -> str:
        """The stiffness source the correction used ("interpolated" or "sweep")."""
        return str(self.corrected.metadata[STIFFNESS_SOURCE_FIELD])

    def details(self) -> dict[str, Any]:
        """A JSON summary: frames, force range (N), the stiffness source used, the volume's shape and, with a
        compensation, its record (the diagnosis, its effects and parameters, whether forced, a note saying
        what changed)."""
        force = self.recording.force
        assert force is not None  # checked by correct_recording
        return {
            "frames": len(self.recording),
            "force_range_n": [float(force.min()), float(force.max())],
            "stiffness_source": self.stiffness_source,
            **({"compensation": self.compensation} if self.compensation is not None else {}),
            **({"volume_shape": list(self.volume.grid.shape)} if self.volume is not None else {}),
        }


def correct_sweep(
    sweep_path: Path,
    model_path: Path,
    settings: PipelineSettings,
    corrected_path: Path,
    volume_path: Path | None = None,
    coverage_path: Path | None = None,
) -> CorrectedSweep:
    """Correct a sweep (PLUS sequence file with ContactForce) to zero force with a model file (``usdeform
    fit``'s), write the corrected sequence to ``corrected_path`` and, with ``volume_path``, compound it
    into a volume there (and its coverage to ``coverage_path``, which needs ``volume_path``).

    Raises InputError for settings or inputs at fault (naming the setting or the file).
    """
    if coverage_path is not None and volume_path is None:
        raise InputError("coverage_path: needs volume_path")
    compensation = settings.compensation()
    model_file = load_model(model_path)
    if model_file.sampled is None:
        raise InputError(
            f"{model_path}: sampled_positions: correcting a sweep needs the palpations' 3-D positions "
            "in the base frame, as 'usdeform fit' records them"
        )
    recording, compensated = apply_compensation(compensation, read_sequence(sweep_path), str(sweep_path))
    corrected = correct_recording(
        recording,
        model_file.model,
        model_file.sampled,
        stiffness_source=settings.stiffness_source,
        clamp_force=settings.clamp_force,
        name=str(sweep_path),
    )
    volume, n_compounded = None, None
    with outputs_together():  # the sequence and its volume replace the old ones together, or neither does
        write_sequence(corrected_path, corrected)
        if volume_path is not None:
            volume, n_compounded = compound_recording(
                corrected, name=str(sweep_path), **settings.compounding_keywords()
            )
            write_volume(volume_path, volume, weight_path=coverage_path, compression_level=settings.compression_level)
    return CorrectedSweep(recording, corrected, model_file.sampled, compensated, volume, n_compounded)
