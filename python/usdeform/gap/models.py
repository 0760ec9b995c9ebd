"""The calibrated simulator with library effects added: predicted measures for given effect parameters.

Reduced models of the nine effects of :mod:`usdeform.sim.effects`, each acting where the simulator
puts it:

* ``image_latency`` (delay_s): the frame at time t shows the tissue (and probe) at t - delay.
* ``force_sensor_error`` (offset_n, drift_n_per_s): measured = true + offset + drift * t (bias
  minus uncompensated probe weight, and thermal drift), linear terms of the force fit; the drift is
  bounded by ``MAX_DRIFT_N_PER_S``, 2.5 times the largest thermal drift of strain-gauge F/T sensors
  (0.02 N/s, :class:`usdeform.sim.effects.ForceSensorError`), so that a steep linear trend (which
  relaxation or hysteresis can look like over a few seconds) is not called a sensor drift.
* ``viscoelasticity`` (g, tau_s): one-term Prony quasi-linear viscoelasticity of the elastic force
  (recursive convolution, exact for lambda linear between frames).
* ``sound_speed_mismatch`` (error_m_s): true depth = displayed depth * (1540 + error) / 1540.
* ``probe_tilt`` (tilt_deg): the image plane rotated about the probe-face centre (sign as in
  :func:`usdeform.sim.imaging.probe_to_surface`); the axial force factor cos(tilt) is absorbed by
  the modulus fit.
* ``out_of_plane_motion`` (shift_mm_per_mm, jitter_mm): speckle correlation times
  E[exp(-e^2 / (2 s^2))], e ~ N(shift * dlambda, 2 jitter^2) the elevation offset of two frames
  dlambda apart and s = 1.5 mm / 2.355 the assumed elevation slice (two-way amplitude sigma of a
  1.5 mm FWHM; the fitted shift scales with the true slice thickness, which a palpation cannot tell).
  The correlation's roughness from frame to frame (``speckle_correlation_roughness``) is predicted from
  64 fixed draws of the frames' jitter: each frame's offset is its own draw, so pairs sharing a frame share it.
* ``layered_tissue`` (thickness_mm, modulus_ratio): a soft top layer, from the library's 2 x 2 grid.
* ``sliding_contact`` (no parameter): the frictionless-contact solve.
* ``lumen_pressure`` (pressure_ratio): lumen pressure / tissue modulus, from the library's two levels;
  reported in kPa through the calibrated modulus. Besides the field and the lumen area it adds the
  lumen's push on the probe face from first contact (:func:`contact_reaction`): in a near-linear
  section the pressure's own field is nearly independent of lambda and largely vanishes once the
  frames are referenced to the first frame in contact, but the push does not.

The ideal simulator's own free parameters are fitted on the fitting split with every candidate:
its compressibility (the weight of the nearly incompressible library section's field difference, least squares
of the tracked displacement: Poisson's ratio 0.45 + 0.04 * weight, within ``POISSON_WEIGHT_BOUNDS``, nu 0.40-0.499),
the elastic force (a cubic through the origin in lambda with non-negative coefficients) and the
speckle correlation baseline (a - b |dlambda|, a, b >= 0: noise and strain decorrelation; with out-of-plane
motion also the fraction w in [0, 1] of the correlation that does not decorrelate with elevation, structure
that the band-pass leaves: correlation = (a - b |dlambda|) f + w (1 - f)), both bounded linear least squares.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import lsq_linear

from .calibration import LAYER_MODULUS_RATIOS, LAYER_THICKNESSES_MM, POISSON_RATIOS, PRESSURE_RATIOS, CalibratedSection
from .measures import Prediction, correlation_roughness
from .observations import Observation

__all__ = ["EFFECTS", "EffectModel", "predict"]

_ELEVATION_SIGMA_MM = 1.5 / 2.355
_ROUGHNESS_DRAWS = 64  # draws of the frames' elevation jitter for the expected correlation roughness
_ROUGHNESS_SEED = 0
_ASSUMED_SOUND_SPEED = 1540.0


@dataclass(frozen=True)
class EffectModel:
    """A library effect: its ID, fitted parameter names, bounds and starting grid."""

    effect: str
    parameters: tuple[str, ...]
    bounds: tuple[tuple[float, float], ...]
    grid: tuple[tuple[float, ...], ...]


EFFECTS = (
    EffectModel("image_latency", ("delay_s",), ((-0.2, 0.3),), ((-0.1, 0.0, 0.05, 0.1, 0.2),)),
    EffectModel("force_sensor_error", (), (), ()),  # offset and drift enter the force fit linearly
    EffectModel(
        "viscoelasticity", ("g", "tau_s"), ((0.01, 0.7), (0.05, 30.0)), ((0.1, 0.3, 0.5), (0.2, 0.5, 1.2, 3.0, 8.0))
    ),
    EffectModel("sound_speed_mismatch", ("error_m_s",), ((-150.0, 120.0),), ((-80.0, -30.0, 30.0, 80.0),)),
    EffectModel("probe_tilt", ("tilt_deg",), ((-15.0, 15.0),), ((-8.0, -3.0, 3.0, 8.0),)),
    EffectModel(
        "out_of_plane_motion",
        ("shift_mm_per_mm", "jitter_mm"),
        ((0.0, 0.8), (0.0, 1.0)),
        ((0.05, 0.2, 0.4), (0.0, 0.2, 0.5)),
    ),
    EffectModel(
        "layered_tissue",
        ("thickness_mm", "modulus_ratio"),
        ((0.5, 16.0), (0.1, 0.8)),
        ((2.0, 5.0, 10.0), (0.2, 0.5)),
    ),
    EffectModel("sliding_contact", (), (), ()),
    EffectModel("lumen_pressure", ("pressure_ratio",), ((0.0, 0.35),), ((0.03, 0.1, 0.25),)),
)
EFFECT_BY_ID = {model.effect: model for model in EFFECTS}
LINEAR_PARAMETERS = {"force_sensor_error": ("offset_n", "drift_n_per_s")}
_POISSON_STEP = POISSON_RATIOS[1] - POISSON_RATIOS[0]
POISSON_WEIGHT_BOUNDS = ((0.40 - POISSON_RATIOS[0]) / _POISSON_STEP, (0.499 - POISSON_RATIOS[0]) / _POISSON_STEP)
MAX_DRIFT_N_PER_S = 0.05


def _qlv(elastic: np.ndarray, time_s: np.ndarray, g: float, tau_s: float) -> np.ndarray:
    """One-term Prony QLV force for an elastic force sampled at ``time_s`` (linear between samples)."""
    result = np.empty_like(elastic)
    history = elastic[0]  # tissue taken as loaded to the first sample long ago
    result[0] = elastic[0]
    for index in range(1, len(elastic)):
        step = max(time_s[index] - time_s[index - 1], 1e-9)
        decay = np.exp(-step / tau_s)
        history = decay * history + tau_s / step * (1 - decay) * (elastic[index] - elastic[index - 1])
        result[index] = (1 - g) * elastic[index] + g * history
    return result


def _linear_interpolation_weights(value: float, knots: tuple[float, ...]) -> dict[float, float]:
    """Weights on ``knots`` (first knot = 0 = ideal) of linear interpolation, extrapolating past the last."""
    knots_array = np.asarray(knots)
    upper = int(np.clip(np.searchsorted(knots_array, value, side="right"), 1, len(knots_array) - 1))
    fraction = (value - knots_array[upper - 1]) / (knots_array[upper] - knots_array[upper - 1])
    return {knots[upper - 1]: 1 - fraction, knots[upper]: fraction}


def variant_weights(effects: dict[str, dict[str, float]], section: CalibratedSection) -> dict[str, float]:
    """Weights of the library's mechanical variants for the mechanical effects in ``effects``."""
    weights: dict[str, float] = {}
    if "sliding_contact" in effects:
        weights["slide"] = 1.0
    if "layered_tissue" in effects:
        thickness = effects["layered_tissue"]["thickness_mm"]
        ratio = effects["layered_tissue"]["modulus_ratio"]
        for t, wt in _linear_interpolation_weights(thickness, (0.0, *LAYER_THICKNESSES_MM)).items():
            if t == 0.0:
                continue
            for r, wr in _linear_interpolation_weights(ratio, LAYER_MODULUS_RATIOS).items():
                name = f"layer_{t:g}_{r:g}"
                weights[name] = weights.get(name, 0.0) + wt * wr
    if "lumen_pressure" in effects and "pressure_0.05" in section.fields:
        for p, wp in _linear_interpolation_weights(
            effects["lumen_pressure"]["pressure_ratio"], (0.0, *PRESSURE_RATIOS)
        ).items():
            if p != 0.0:
                weights[f"pressure_{p:g}"] = weights.get(f"pressure_{p:g}", 0.0) + wp
    return weights


def _image_lambda(observation: Observation, delay_s: float) -> np.ndarray:
    """Lambda (mm) of the tissue each frame shows when images lag by ``delay_s``."""
    return np.interp(observation.time_s - delay_s, observation.time_s, observation.probe_displacement_mm)


def _predict_displacement(
    observation: Observation,
    section: CalibratedSection,
    field: np.ndarray,
    image_lambda: np.ndarray,
    tilt_deg: float,
    depth_scale: float,
) -> np.ndarray:
    """(n, N, 2) displacement of the tracked points from the reference frame, pixels."""
    to_probe = observation.image_to_probe
    scale_x, offset_x = to_probe[0, 0], to_probe[0, 3]
    scale_z, offset_z = to_probe[2, 1], to_probe[2, 3]
    points = observation.points_px
    x_probe = scale_x * points[:, 0] + offset_x
    z_probe = (scale_z * points[:, 1] + offset_z) * depth_scale
    cos, sin = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    reference_lambda = float(image_lambda[observation.reference_index])
    deformed = np.column_stack([cos * x_probe + sin * z_probe, -sin * x_probe + cos * z_probe + reference_lambda])
    material = deformed.copy()
    reference_lambdas = np.full(len(points), reference_lambda)
    for _ in range(3):  # fixed point of X + u(X) = x
        material = deformed - np.nan_to_num(section.displacement(field, material, reference_lambdas))
    n, m = observation.n_frames, len(points)
    all_material = np.tile(material, (n, 1))
    all_lambda = np.repeat(image_lambda, m)
    moved = all_material + section.displacement(field, all_material, all_lambda)
    relative_x = moved[:, 0]
    relative_z = moved[:, 1] - all_lambda
    x_back = cos * relative_x - sin * relative_z
    z_back = (sin * relative_x + cos * relative_z) / depth_scale
    col = (x_back - offset_x) / scale_x
    row = (z_back - offset_z) / scale_z
    predicted = np.stack([col.reshape(n, m), row.reshape(n, m)], axis=2)
    return predicted - points[None, :, :]


def contact_reaction(
    observation: Observation, section: CalibratedSection, effects: dict[str, dict[str, float]]
) -> np.ndarray:
    """(n,) force, N, the mechanical effects add at first contact, on every frame in contact (lambda > 0).

    A pressurised lumen bulges the surface into the probe, which carries its push from the moment it
    touches: a step at contact that the elastic cubic (through the origin) cannot take up, and that a
    sensor offset only imitates in contact (the offset reads out of contact too). Through QLV when on.
    """
    step = section.contact_reaction_n(variant_weights(effects, section))
    reaction = np.where(observation.probe_displacement_mm > 0, step, 0.0)
    if step and "viscoelasticity" in effects:
        reaction = _qlv(
            reaction, observation.time_s, effects["viscoelasticity"]["g"], effects["viscoelasticity"]["tau_s"]
        )
    return reaction


def force_columns(observation: Observation, effects: dict[str, dict[str, float]]) -> np.ndarray:
    """(n, k) design of the force fit: cubic elastic terms (through QLV if on) and sensor terms."""
    lam = np.clip(observation.probe_displacement_mm, 0.0, None)
    columns = [lam**power for power in (1, 2, 3)]
    if "viscoelasticity" in effects:
        g, tau = effects["viscoelasticity"]["g"], effects["viscoelasticity"]["tau_s"]
        columns = [_qlv(column, observation.time_s, g, tau) for column in columns]
    if "force_sensor_error" in effects:
        columns += [np.ones_like(lam), observation.time_s]
    return np.column_stack(columns)


def _correlation_steps(observation: Observation) -> np.ndarray:
    """(pairs, n) lambda difference (mm) of every correlated pair of frames, NaN where a frame has no partner."""
    partner = observation.correlation_partner
    lam = observation.probe_displacement_mm
    return np.where(partner >= 0, lam - lam[np.maximum(partner, 0)], np.nan)


def _correlation_factor(steps: np.ndarray, effects: dict[str, dict[str, float]]) -> np.ndarray:
    """Expected out-of-plane decorrelation factor of frame pairs ``steps`` (mm of lambda) apart (1 when off)."""
    if "out_of_plane_motion" not in effects:
        return np.ones_like(steps)
    shift = effects["out_of_plane_motion"]["shift_mm_per_mm"]
    jitter = effects["out_of_plane_motion"]["jitter_mm"]
    variance = _ELEVATION_SIGMA_MM**2 + 2 * jitter**2
    return _ELEVATION_SIGMA_MM / np.sqrt(variance) * np.exp(-((shift * steps) ** 2) / (2 * variance))


def _correlation_factor_draws(
    observation: Observation, steps: np.ndarray, effects: dict[str, dict[str, float]]
) -> np.ndarray:
    """(draws, pairs, n) out-of-plane decorrelation factor of every frame pair for ``_ROUGHNESS_DRAWS`` draws of the
    frames' jitter (fixed draws: the same for every candidate, so the fit sees a smooth objective)."""
    if "out_of_plane_motion" not in effects:
        return np.ones((1, *steps.shape))
    shift = effects["out_of_plane_motion"]["shift_mm_per_mm"]
    jitter = effects["out_of_plane_motion"]["jitter_mm"]
    unit = np.random.default_rng(_ROUGHNESS_SEED).standard_normal((_ROUGHNESS_DRAWS, observation.n_frames))
    partner = np.maximum(observation.correlation_partner, 0)
    offset = shift * steps[None] + jitter * (unit[:, None, :] - unit[:, partner])
    return np.exp(-(offset**2) / (2 * _ELEVATION_SIGMA_MM**2))


def fit_force(design: np.ndarray, force_n: np.ndarray) -> np.ndarray:
    """Least squares of the force design with non-negative elastic terms (the first three columns).

    An elastic indentation force rises from zero at contact with a stiffness that does not fall
    (geometric stiffening under the probe; neo-Hookean or stiffening tissue), so its cubic
    coefficients are non-negative; the sensor offset is free and the drift (fifth column, when
    present) within +-``MAX_DRIFT_N_PER_S``.
    """
    lower = np.full(design.shape[1], -np.inf)
    upper = np.full(design.shape[1], np.inf)
    lower[:3] = 0.0
    if design.shape[1] == 5:
        lower[4], upper[4] = -MAX_DRIFT_N_PER_S, MAX_DRIFT_N_PER_S
    scale = np.maximum(np.abs(design).max(axis=0), 1e-12)
    result = lsq_linear(design / scale, force_n, bounds=(lower * scale, upper * scale))
    return result.x / scale


def _fit_compressibility(
    observation: Observation, displacement: np.ndarray, compressible: np.ndarray, fit_mask: np.ndarray
) -> float:
    """Weight w of the nearly incompressible section's displacement difference (least squares on the fitting
    split's tracked displacement, pixels), within ``POISSON_WEIGHT_BOUNDS``."""
    basis = compressible - displacement
    residual = observation.displacement_px - displacement
    ok = fit_mask[:, None, None] & np.isfinite(residual) & np.isfinite(basis)
    energy = float(np.sum(np.where(ok, basis, 0.0) ** 2))
    if energy <= 0:
        return 0.0
    return float(np.clip(np.sum(np.where(ok, residual * basis, 0.0)) / energy, *POISSON_WEIGHT_BOUNDS))


@dataclass
class FittedLinear:
    """Linear parameters fitted with a prediction: the force terms, the correlation baseline and the
    compressibility (as Poisson's ratio)."""

    force_coefficients: np.ndarray
    correlation_coefficients: np.ndarray
    poisson_ratio: float


def predict(
    observation: Observation,
    section: CalibratedSection,
    effects: dict[str, dict[str, float]],
    fit_mask: np.ndarray,
) -> tuple[Prediction, FittedLinear]:
    """The calibrated simulation of ``observation`` with ``effects`` (ID -> parameters) added.

    The linear parameters (elastic force, sensor terms, correlation baseline) are fitted on the
    frames of ``fit_mask`` (the fitting split).
    """
    design = force_columns(observation, effects)
    reaction = contact_reaction(observation, section, effects)
    coefficients = fit_force(design[fit_mask], (observation.force_n - reaction)[fit_mask])
    force = design @ coefficients + reaction

    delay = effects.get("image_latency", {}).get("delay_s", 0.0)
    tilt = effects.get("probe_tilt", {}).get("tilt_deg", 0.0)
    depth_scale = (_ASSUMED_SOUND_SPEED + effects.get("sound_speed_mismatch", {}).get("error_m_s", 0.0)) / (
        _ASSUMED_SOUND_SPEED
    )
    weights = variant_weights(effects, section)
    image_lambda = _image_lambda(observation, delay)
    displacement = _predict_displacement(observation, section, section.field(weights), image_lambda, tilt, depth_scale)
    compressible = _predict_displacement(
        observation, section, section.field({**weights, "poisson": 1.0}), image_lambda, tilt, depth_scale
    )
    poisson_weight = _fit_compressibility(observation, displacement, compressible, fit_mask)
    displacement = displacement + poisson_weight * (compressible - displacement)
    weights["poisson"] = poisson_weight

    steps = _correlation_steps(observation)
    factor = _correlation_factor(steps, effects)
    distance = np.abs(steps)
    ok = fit_mask[None, :] & np.isfinite(observation.correlation) & np.isfinite(steps)
    columns = [factor, -(factor * distance)]
    if "out_of_plane_motion" in effects:
        columns.append(1 - factor)  # the part of the band-passed image that stays correlated across the slice
    correlation_design = np.column_stack([column[ok] for column in columns])
    upper = [np.inf, np.inf, 1.0][: len(columns)]
    correlation_coefficients = lsq_linear(
        correlation_design, observation.correlation[ok], bounds=(np.zeros(len(columns)), upper)
    ).x
    coherent = correlation_coefficients[2] if len(columns) == 3 else 0.0
    baseline = correlation_coefficients[0] - correlation_coefficients[1] * distance
    correlation = factor * baseline + coherent * (1 - factor)
    draws = _correlation_factor_draws(observation, steps, effects)
    roughness = np.mean(correlation_roughness(draws * baseline + coherent * (1 - draws)), axis=0)

    area_ratio = None
    if section.has_vessel:
        area = section.lumen_area(weights)
        at_frames = np.interp(np.clip(image_lambda, 0, None), section.lambda_mm, area)
        area_ratio = at_frames / at_frames[observation.reference_index]
    return Prediction(force, displacement, correlation, area_ratio, roughness), FittedLinear(
        coefficients, correlation_coefficients, POISSON_RATIOS[0] + poisson_weight * _POISSON_STEP
    )
