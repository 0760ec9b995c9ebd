"""One palpation of the paper-2d experiments: simulated and measured, corrected by each model and
compared with the simulator's zero force, and each fitted displacement against the true one by region."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...correction import correct_frames
from ...errors import InputError
from ...fitting import SampledPosition, measure_palpation
from ...metrics import area_mm2, centroid_distance_mm, dice, pixel_size_mm, segment_vessel
from ...options import Solver
from ...recording import Recording
from ...regression import DisplacementModel, Observations, fit_regression
from ...sim import GroundTruth, Phantom, simulate_palpation
from .config import CorrectionCase, Method, Paper2dConfig

__all__ = [
    "H_TERMS",
    "Palpated",
    "configured_phantom",
    "evaluate",
    "fit_method",
    "palpate",
    "residuals_by_region",
]

#: Columns of K whose term in M contains h (h^2, xh, yh, h): the only ones a stiffness change affects.
H_TERMS = (2, 4, 5, 8)


@dataclass
class Palpated:
    """A simulated palpation, its ground truth and what the pipeline measured from it."""

    recording: Recording
    truth: GroundTruth
    sampled: SampledPosition

    @property
    def force(self) -> np.ndarray:
        """Each frame's force, N (a simulated palpation always records it)."""
        if self.recording.force is None:
            raise InputError("recording: a palpation needs per-frame force")
        return self.recording.force


def configured_phantom(preset: Phantom, config: Paper2dConfig) -> Phantom:
    """``preset`` with the configuration's mesh size, if it sets one."""
    return preset if config.mesh_size_mm is None else preset.with_section_changes(mesh_size_mm=config.mesh_size_mm)


def palpate(phantom: Phantom, position_mm: float, max_force_n: float, seed: int, config: Paper2dConfig) -> Palpated:
    """Simulate a palpation of ``phantom`` at ``position_mm`` up to ``max_force_n`` (N) and measure it as
    the pipeline does (flexible layer: the phantom's section depth)."""
    recording, truth = simulate_palpation(
        phantom, position_mm, max_force_n, n_frames=config.n_frames, seed=seed, rows=config.rows, cols=config.cols
    )
    sampled = measure_palpation(recording, flexible_layer_mm=phantom.base_section.depth_mm)
    return Palpated(recording, truth, sampled)


def _segment(frame: np.ndarray, seed_px: tuple[float, float]) -> np.ndarray:
    """The vessel mask, or an empty mask when no anechoic lumen is found (a failed correction)."""
    try:
        return segment_vessel(frame, seed_px=seed_px).mask
    except InputError:
        return np.zeros(frame.shape, dtype=bool)


def evaluate(
    experiment: str,
    phantom: str,
    position_mm: float,
    target_force_n: float,
    palpated: Palpated,
    models: dict[str, DisplacementModel],
) -> tuple[CorrectionCase, int, dict[str, np.ndarray]]:
    """Correct the palpation frame nearest ``target_force_n`` with each model; compare with zero force."""
    recording, truth = palpated.recording, palpated.truth
    index = int(np.argmin(np.abs(palpated.force - target_force_n)))
    pixel_size = pixel_size_mm(recording.image_to_probe)
    reference = segment_vessel(truth.zero_force_frames[index]).mask
    row, col = np.argwhere(reference).mean(axis=0)
    seed = (float(col), float(row))
    masks = {"deformed": _segment(recording.frames[index], seed)}
    for name, model in models.items():
        corrected = correct_frames(
            recording.frames[index], palpated.force[index], palpated.sampled.stiffness.profile, model
        )
        masks[name] = _segment(corrected, seed)
    scores = {name: dice(mask, reference) if mask.any() else 0.0 for name, mask in masks.items()}
    areas = {
        name: area_mm2(mask, pixel_size) - area_mm2(reference, pixel_size) if mask.any() else float("nan")
        for name, mask in masks.items()
    }
    centroids = {
        name: centroid_distance_mm(mask, reference, pixel_size) if mask.any() else float("nan")
        for name, mask in masks.items()
    }
    case = CorrectionCase(
        experiment, phantom, position_mm, target_force_n, float(palpated.force[index]), scores, areas, centroids
    )
    return case, index, {"reference": reference, **masks}


def _true_observations(palpated: Palpated, spacing_px: int = 8) -> Observations:
    """The simulator's true displacement from zero force on a grid, as regression observations."""
    truth, recording = palpated.truth, palpated.recording
    rows, cols = recording.frames.shape[1:]
    y, x = np.mgrid[spacing_px // 2 : rows : spacing_px, spacing_px // 2 : cols : spacing_px]
    displacements = truth.displacement_px[:, y.ravel(), x.ravel(), :].astype(np.float64)
    valid = np.all(np.isfinite(displacements), axis=2)
    points = np.stack([x.ravel(), y.ravel()], axis=1).astype(np.float64)
    return Observations(
        points,
        np.where(valid[..., None], displacements, np.nan),
        valid,
        palpated.force,
        0.0,
        palpated.sampled.stiffness.profile,
        (rows, cols),
    )


def _stiffness_independent_part_removed(model: DisplacementModel) -> DisplacementModel:
    """``model`` without the terms that integrate to a multiple of F whatever the stiffness: the
    quadratic's columns without h, the B-spline's force term ``1``."""
    coefficients = model.coefficients.copy()
    if coefficients.ndim == 2:
        coefficients[:, [t for t in range(10) if t not in H_TERMS]] = 0.0
    else:
        coefficients[:, 0] = 0.0
    return replace(model, coefficients=coefficients)


def residuals_by_region(model: DisplacementModel, palpated: Palpated, index: int) -> dict[str, float]:
    """Mean |fitted - true| displacement (pixels) near the vessel and elsewhere, and R^2 per component."""
    truth = palpated.truth
    true_field = np.moveaxis(truth.displacement_px[index].astype(np.float64), -1, 0)
    fitted = model.displacement(palpated.force[index], palpated.sampled.stiffness.profile, true_field.shape[1:])
    tissue = np.all(np.isfinite(true_field), axis=0)
    lumen = truth.zero_force_vessel_mask[index]
    rows, cols = lumen.shape
    y, x = np.mgrid[0:rows, 0:cols]
    centre = np.argwhere(lumen).mean(axis=0) if lumen.any() else np.array([rows / 2, cols / 2])
    radius = np.sqrt(lumen.sum() / np.pi) if lumen.any() else rows / 8
    distance = np.hypot(y - centre[0], x - centre[1])
    near = tissue & (distance < 2 * radius)
    error = np.linalg.norm(fitted - np.nan_to_num(true_field), axis=0)
    r_squared = {}
    for component, name in enumerate(("lateral", "axial")):
        values = true_field[component][tissue]
        r_squared[name] = float(
            1 - np.sum((fitted[component][tissue] - values) ** 2) / np.sum((values - values.mean()) ** 2)
        )
    # The terms without h integrate to a multiple of F whatever the stiffness; only the h terms
    # respond to a new stiffness profile. Their share of the displacement bounds how much
    # propagation by stiffness can change the prediction.
    h_only = _stiffness_independent_part_removed(model)
    from_h = h_only.displacement(palpated.force[index], palpated.sampled.stiffness.profile, true_field.shape[1:])
    share = (
        float(np.linalg.norm(from_h[:, tissue]) / np.linalg.norm(fitted[:, tissue]))
        if model.integration == "force"
        else float("nan")
    )  # integrated over lambda, every term follows k
    return {
        "near_vessel_px": float(error[near].mean()),
        "elsewhere_px": float(error[tissue & ~near].mean()),
        "r2_lateral": r_squared["lateral"],
        "r2_axial": r_squared["axial"],
        "h_terms_share": share,
    }


def fit_method(method: Method, palpations: list[Palpated], solver: Solver) -> DisplacementModel:
    """The model of ``method`` fitted on ``palpations`` (tracked or, for an oracle, true displacements);
    the B-spline bases always by the exact solver."""
    observations = [_true_observations(p) if method.truth else p.sampled.observations for p in palpations]
    return fit_regression(
        observations,
        solver=solver if method.basis == "quadratic" else "exact",
        coupling=method.coupling,
        integration=method.integration,
        basis=method.basis,
    ).model
