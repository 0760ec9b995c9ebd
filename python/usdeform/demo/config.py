"""The demo's settings (:class:`DemoConfig`, the phantoms in :data:`PRESETS`) and what a run measures
(:class:`DemoResult`: per-frame and volume scores, an effect's diagnosis and compensation, timings)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..correction import SampledProfiles
from ..errors import InputError
from ..fitting import FIT_METHODS, MethodName, SampledPosition
from ..recording import Recording
from ..regression import DeformationModel, RegressionFit
from ..sim import Effects, GroundTruth, Phantom, compliant_vessel_phantom, soft_phantom, stiff_phantom
from ..sim.command import parse_effects
from ..volume import Volume

__all__ = ["PRESETS", "DemoConfig", "DemoResult", "EffectOutcome", "FrameMetrics", "VolumeMetrics"]

PresetName = Literal["soft", "stiff", "compliant-vessel"]


#: The phantoms the demo can scan, and the sweep force (N) each is scanned at by default (about half
#: of the palpations' highest force, within the paper's range for each phantom).
PRESETS: dict[str, tuple[Callable[[], Phantom], float]] = {
    "soft": (soft_phantom, 8.0),
    "stiff": (stiff_phantom, 20.0),
    "compliant-vessel": (compliant_vessel_phantom, 12.0),
}


@dataclass(frozen=True)
class DemoConfig:
    """What the demo simulates and how it corrects.

    Parameters
    ----------
    preset : {"soft", "stiff", "compliant-vessel"}
        The phantom (:data:`PRESETS`).
    force_n : float, optional
        Target force of the sweep, N; default: the preset's.
    method : {"recommended", "paper"}
        The model the volumes are corrected with (:data:`FIT_METHODS`); the other is scored beside it.
    seed : int
        Seed of every random draw (same seed, same output).
    quick : bool
        Smaller frames, fewer frames and a shorter path (a smoke run of a few tens of seconds).
    mesh_size_mm : float
        Finite-element mesh of the phantom, mm (the presets use 2 mm; 3 mm keeps the demo's cold
        start short and changes the preset's forces by a few per cent).
    effects : tuple of str
        Physical effects the palpations and the sweep are simulated with, as ``usdeform simulate --effect``
        takes them (``NAME[:PARAMETER=VALUE,...]``, :func:`usdeform.sim.command.parse_effects`). With any, the
        palpations are also diagnosed blind and the sweep corrected again with the compensation the
        diagnosis supports (:class:`EffectOutcome`).
    """

    preset: PresetName = "soft"
    force_n: float | None = None
    method: MethodName = "recommended"
    seed: int = 0
    quick: bool = False
    mesh_size_mm: float = 3.0
    effects: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise InputError(f"preset: expected one of {sorted(PRESETS)}, got {self.preset!r}")
        if self.method not in FIT_METHODS:
            raise InputError(f"method: expected one of {sorted(FIT_METHODS)}, got {self.method!r}")
        if self.force_n is not None and not (np.isfinite(self.force_n) and self.force_n > 0):
            raise InputError(f"force_n: expected a positive force in N, got {self.force_n!r}")
        if int(self.seed) != self.seed or self.seed < 0:
            raise InputError(f"seed: expected a non-negative integer, got {self.seed!r}")
        if not (np.isfinite(self.mesh_size_mm) and self.mesh_size_mm > 0):
            raise InputError(f"mesh_size_mm: expected a positive size in mm, got {self.mesh_size_mm!r}")
        self.simulated_effects()

    def simulated_effects(self) -> Effects:
        """The parsed ``effects`` (none: an empty Effects, the simulator's default); InputError naming
        ``effects`` (--effect) for a text :func:`usdeform.sim.command.parse_effects` refuses."""
        try:
            return parse_effects(self.effects)
        except InputError as error:
            raise InputError(f"effects (--effect): {error}") from None

    def phantom(self) -> Phantom:
        """The preset's phantom on the demo's mesh."""
        return PRESETS[self.preset][0]().with_section_changes(mesh_size_mm=self.mesh_size_mm)

    @property
    def frame_size(self) -> int:
        """Rows = columns of the frames, pixels."""
        return 128 if self.quick else 256

    @property
    def palpation_positions_mm(self) -> tuple[float, ...]:
        """Where the robot palpates, mm along the phantom (the sweep's start, middle and end; the stiffness
        scale of the presets is 1 + a sin(2 pi s / 80 mm): soft +15 %, 0, -15 % here)."""
        return (20.0, 40.0, 60.0)

    @property
    def palpation_frames(self) -> int:
        """Frames per palpation."""
        return 24 if self.quick else 40

    @property
    def sweep_frames(self) -> int:
        """Frames of the sweep (50 fps; one every 0.4 mm, closer than the voxels, so no voxel plane is missed)."""
        return 60 if self.quick else 100

    @property
    def spacing_mm(self) -> float:
        """Voxel size of the volumes, mm."""
        return 0.8 if self.quick else 0.5


@dataclass(frozen=True)
class FrameMetrics:
    """Per-frame scores of the sweep's vessel against the zero-force truth.

    ``dice``, ``area_error_mm2`` (frame minus truth) and ``centroid_error_mm`` map ``deformed`` and
    each method of :data:`FIT_METHODS` to ``(n_frames,)`` arrays. The vessel of a deformed frame is the
    simulator's lumen mask; that of a corrected frame is the same mask warped by the correction (what
    the corrected image shows, without a segmentation's own error).
    """

    sweep_position_mm: np.ndarray
    force_n: np.ndarray
    truth_area_mm2: np.ndarray
    dice: dict[str, np.ndarray]
    area_error_mm2: dict[str, np.ndarray]
    centroid_error_mm: dict[str, np.ndarray]

    def mean(self, metric: Literal["dice", "area", "centroid"], name: str) -> float:
        """Mean over the frames of ``dice``, ``|area error|`` (mm^2) or the centroid error (mm)."""
        values = {"dice": self.dice, "area": self.area_error_mm2, "centroid": self.centroid_error_mm}[metric][name]
        return float(np.nanmean(np.abs(values)))


@dataclass(frozen=True)
class VolumeMetrics:
    """The vessel in the three volumes (``deformed``, ``corrected``, ``truth``).

    ``vessel_volume_mm3``: lumen volume over the sweep slices all three cover. ``depth_mm``: the
    centre line's depth below the unloaded surface, per slice along the sweep at ``slice_y_mm`` (base
    y, mm; NaN where the volume has no vessel). ``depth_error_mm``: mean |depth - truth| over the
    slices.
    """

    vessel_volume_mm3: dict[str, float]
    slice_y_mm: np.ndarray
    depth_mm: dict[str, np.ndarray]
    depth_error_mm: dict[str, float]

    def mean_depth_mm(self, name: str) -> float:
        """Mean centre-line depth of one volume, mm."""
        return float(np.nanmean(self.depth_mm[name]))


@dataclass(frozen=True)
class EffectOutcome:
    """The blind diagnosis of the demo's palpations (simulated with effects) and what its compensation gave back.

    ``diagnosis``: its ``diagnosis.json`` (:meth:`usdeform.gap.Diagnosis.to_json`; None when it failed).
    ``refusal``: why the sweep was not compensated (the InputError of
    :func:`usdeform.compensation.compensation_option`, or the diagnosis's failure); "" when it was. The rest
    is None when refused: ``record``, the compensation applied to every recording
    (:func:`usdeform.compensation.apply_compensation`'s record); ``kept``, the sweep frames the compensated
    sweep keeps (indices; a re-pairing in time drops frames); ``frame_metrics``, the ``corrected``
    (uncompensated, the demo's method) and ``compensated`` lumens against the zero-force truth on the kept
    frames; ``volume_metrics``, the compounded ``corrected``, ``compensated`` and ``truth`` vessels on the
    sweep slices all three cover.
    """

    diagnosis: dict[str, Any] | None
    refusal: str
    record: dict[str, Any] | None = None
    kept: np.ndarray | None = None
    frame_metrics: FrameMetrics | None = None
    volume_metrics: VolumeMetrics | None = None


@dataclass
class DemoResult:
    """What the demo made: the inputs, the fits, the scores, the volumes, the timings and the files.

    ``corrected_masks`` maps each method to the sweep's lumen masks warped by its correction (what its
    corrected frames show); ``volumes`` and ``vessel_volumes`` map ``deformed``, ``corrected`` and
    ``truth`` to the compounded images and lumen masks (0-255) on one grid. ``effect_outcome``: the
    diagnosis and compensation of the simulated effects (None without effects).
    """

    config: DemoConfig
    phantom: Phantom
    sweep_force_n: float
    palpations: list[tuple[Recording, GroundTruth]]
    measured: list[SampledPosition]
    sampled: SampledProfiles
    fits: dict[str, RegressionFit]
    sweep: Recording
    sweep_truth: GroundTruth
    corrected: Recording
    corrected_masks: dict[str, np.ndarray]
    frame_metrics: FrameMetrics
    volumes: dict[str, Volume]
    vessel_volumes: dict[str, Volume]
    volume_metrics: VolumeMetrics
    timings_s: dict[str, float] = field(default_factory=dict)
    files: dict[str, Path] = field(default_factory=dict)
    effect_outcome: EffectOutcome | None = None

    @property
    def model(self) -> DeformationModel:
        """The model the volumes were corrected with."""
        return self.fits[self.config.method].fitted
