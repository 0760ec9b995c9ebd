"""The calibrated simulator with library effects added: predicted measures for given effect parameters.

Reduced models of the effects of :mod:`usdeform.sim.effects` (ten: the image's and the force stream's delays
apart), each acting where the simulator puts it:

* ``image_latency`` (delay_s): the frame at time t shows the tissue (and probe) at t - delay.
* ``force_latency`` (delay_s): the force stamped t is the force at t - delay, against the pose and the images
  (a force stream stamped on arrival, or to first order a sensor's first-order lag of that time constant): the
  force columns are evaluated at lambda(t - delay), so the force residual follows the rate of loading, a loop in
  force against displacement without creep during a hold (a delayed pose stream is this and an image latency of
  the same delay: the pair).
* ``force_sensor_error`` (offset_n, drift_n_per_s): measured = true + offset + drift * t (bias
  minus uncompensated probe weight, and thermal drift), linear terms of the force fit; the drift is
  bounded by ``MAX_DRIFT_N_PER_S``, 1.5 times the top of the thermal drift of strain-gauge F/T sensors
  after power-up (0.1 N/s, :class:`usdeform.sim.effects.ForceSensorError`), so that a drift anywhere in
  that range is fitted inside the bound and a steeper linear trend (which relaxation or hysteresis can
  look like over a few seconds) is not called a sensor drift. A gain (scale) error of the sensor is not
  a parameter: it multiplies the elastic force, which the fit takes up as a stiffer or softer tissue.
* ``viscoelasticity`` (g, tau_s): one-term Prony quasi-linear viscoelasticity of the elastic force
  (recursive convolution, exact for lambda linear between frames).
* ``sound_speed_mismatch`` (error_m_s): true depth = displayed depth * (1540 + error) / 1540; a reflector fixed in
  the world (:mod:`usdeform.gap.reference_target`) moves up the image by the image's lambda * 1540 / (1540 + error).
* ``probe_tilt`` (tilt_deg, travel_along_axis): the face and the surface inclined to each other, a probe tilted
  over the surface or a surface inclined under the probe (a palpation sees only the relative tilt, in the probe's
  frame): the image plane rotated about the probe-face centre (sign as in
  :func:`usdeform.sim.imaging.probe_to_surface`), the face meeting the surface progressively from its lower edge
  (the field of the library's section pressed by a face tilted ``TILT_VARIANT_DEG`` the same way, its difference
  to the ideal field in proportion to the tilt) and the face centre ``probe_width / 2 * |tan(tilt)|`` above the
  surface at first contact. The probe travels at ``travel_along_axis * tilt`` to the surface normal: 0 along the
  normal (a robot that presses along it), 1 along its own axis (a robot that presses along its tool axis, or a
  level probe pressing vertically into an inclined surface): the face drags the tissue under it sideways by
  lambda tan(travel) (the field difference of a flat face pressed ``TILT_VARIANT_DEG`` off the normal, in
  proportion to tan(travel)) and the image moves with it. The axial force factor cos(tilt) and the force's
  slower rise are absorbed by the elastic force fit.
* ``out_of_plane_motion`` (shift_mm_per_mm, jitter_mm, drift_mm_per_s): speckle correlation times
  E[exp(-e^2 / (2 s^2))], e ~ N(shift * dlambda + drift * dt, 2 jitter^2) the elevation offset of two frames
  dlambda and dt apart (a motion in proportion to the indentation and one drifting with time) and
  s = 1.5 mm / 2.355 the assumed elevation slice (two-way amplitude sigma of a 1.5 mm FWHM; the fitted shift
  scales with the true slice thickness, which a palpation cannot tell).
  The correlation's roughness from frame to frame (``speckle_correlation_roughness``) is predicted from
  64 fixed draws of the frames' jitter: each frame's offset is its own draw, so pairs sharing a frame share it.
* ``layered_tissue`` (thickness_mm, modulus_ratio): a soft top layer, from the library's 2 x 2 grid.
* ``sliding_contact`` (slip_fraction): how far the contact is from bonded (0) towards frictionless (1): the
  frictionless solve's difference to the bonded one, weighted (a gel-lubricated probe slips partly: Coulomb
  friction keeps a stick zone under the face's centre). How far tissue slips under a flat face depends on the
  face's width, even in sign near its edges, so the frictionless section is solved at the wider face variant
  too and the two are combined bilinearly with the calibrated width
  (:meth:`usdeform.gap.calibration.CalibratedSection.joint_weights`).
* ``lumen_pressure`` (pressure_ratio): lumen pressure / tissue modulus, from the library's two levels;
  reported in kPa through the calibrated modulus. Besides the field and the lumen area it adds the
  lumen's push on the probe face from first contact (:func:`contact_reaction`): in a near-linear
  section the pressure's own field is nearly independent of lambda and largely vanishes once the
  frames are referenced to the first frame in contact, but the push does not.

The ideal simulator's own free parameters are fitted on the fitting split with every candidate:
the ideal section's (compressibility, tissue thickness, strain stiffening, lumen compliance, probe face width:
``CalibratedSection.parameters``, the weights of their variants' field differences by bounded least squares of
the tracked displacement, to first order in the field: the material points stay those of the candidate's field),
the elastic force (a cubic through the origin in lambda with non-negative coefficients) and the
speckle correlation baseline (a - b |dlambda| - c dlambda^2, a, b >= 0: noise and in-plane decorrelation, whose
curvature c, of either sign, depends on the speckle and on the tissue's sub-resolution micro-motion, which
saturates with compression: no simulator's image model can be trusted to get its shape right, and a linear
baseline let a curved null be read as a steady out-of-plane drift; with out-of-plane motion also the fraction
w in [0, 1] of the correlation that does not decorrelate with elevation, structure that the band-pass leaves:
correlation = (a - b |dlambda| - c dlambda^2) f + w (1 - f)), both bounded linear least squares. Against that
baseline a steady out-of-plane drift shows only where its Gaussian decorrelation bends beyond a parabola over
the correlated separations, and frame-to-frame jitter in the correlation's roughness.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .calibration import (
    LAYER_MODULUS_RATIOS,
    LAYER_THICKNESSES_MM,
    LIBRARY_MESH_MM,
    PRESSURE_RATIOS,
    TILT_VARIANT_DEG,
    TRAVEL_VARIANT,
    CalibratedSection,
    tilt_variant_name,
)
from .linear_fits import (
    bounded_linear_fit,
    fit_force,
    fit_section_parameters,
    fixed_force,
    force_columns,
    force_lambda,
    qlv,
)
from .measures import Prediction, correlation_roughness
from .observations import Observation
from .statistics import split_mask
from .tracked_points import TrackedPoints

__all__ = [
    "BASE_MARGIN_MM",
    "EDGE_FRACTION",
    "EFFECTS",
    "EffectModel",
    "GeometryCache",
    "predict",
    "surveyed_depth_mm",
    "without_points_near_base",
]

_ELEVATION_SIGMA_MM = 1.5 / 2.355
_COHERENT_PULL = 1e-3  # weight of the coherent fraction's pull to zero in the correlation fit (see predict)
_ROUGHNESS_DRAWS = 64  # draws of the frames' elevation jitter for the expected correlation roughness
_ROUGHNESS_SEED = 0
_ASSUMED_SOUND_SPEED = 1540.0
BASE_MARGIN_MM = 2 * LIBRARY_MESH_MM  # tracked points this close to the calibrated rigid base are left out


@dataclass(frozen=True)
class EffectModel:
    """A library effect: its ID, fitted parameter names, bounds and starting grid.

    edges: per parameter, the (low, high) range within which a fit is a clean one (default: the bounds); a fit
    within ``EDGE_FRACTION`` of an edge, or beyond it, is reported at the edge of the library (the data ask for
    more than the library's form of the effect gives). An end that is a physical limit, not a library's (an effect
    switched off, a frictionless contact), is -inf or inf. log_scale: the parameters whose edge distance is
    measured in log units (a time constant spans decades).
    """

    effect: str
    parameters: tuple[str, ...]
    bounds: tuple[tuple[float, float], ...]
    grid: tuple[tuple[float, ...], ...]
    edges: tuple[tuple[float, float], ...] = ()
    log_scale: tuple[str, ...] = ()

    def edge_of(self, name: str) -> tuple[float, float]:
        """The (low, high) clean range of parameter ``name`` (see the class docstring)."""
        index = self.parameters.index(name)
        return self.edges[index] if self.edges else self.bounds[index]


_INF = float("inf")
EDGE_FRACTION = 0.02  # a fit within 2 % of its range (log range for log_scale) of an edge is at that edge
EFFECTS = (
    # a delay of up to 0.3 s either way: a pose stream that lags the images and the force shows as a negative image
    # and force delay, so that side is as wide as the other
    EffectModel("image_latency", ("delay_s",), ((-0.3, 0.3),), ((-0.2, -0.1, 0.0, 0.05, 0.1, 0.2),)),
    EffectModel("force_sensor_error", (), (), ()),  # offset and drift enter the force fit linearly
    EffectModel(
        "viscoelasticity",
        ("g", "tau_s"),
        ((0.01, 0.7), (0.05, 30.0)),
        ((0.1, 0.3, 0.5), (0.2, 0.5, 1.2, 3.0, 8.0)),
        edges=((-_INF, 0.7), (0.05, 30.0)),
        log_scale=("tau_s",),
    ),
    # soft tissues' speed of sound lies within about 1450-1640 m/s (fat to muscle and tendon-rich tissue; Duck,
    # *Physical Properties of Tissue*, 1990): fitted over 1430-1650 m/s so that all of it lies inside the edges; a
    # wider fit let the error take up the section's own misfit on thin tissue (to -150 m/s on recordings made
    # without any sound-speed error). A reflector fixed in the world measures it directly (reference_motion).
    EffectModel("sound_speed_mismatch", ("error_m_s",), ((-110.0, 110.0),), ((-80.0, -30.0, 30.0, 80.0),)),
    # travel_along_axis 0 and 1 are the two forms (along the normal, along the probe's axis), not library edges
    EffectModel(
        "probe_tilt",
        ("tilt_deg", "travel_along_axis"),
        ((-15.0, 15.0), (0.0, 1.0)),
        ((-8.0, -3.0, 3.0, 8.0), (0.0, 1.0)),
        edges=((-15.0, 15.0), (-_INF, _INF)),
    ),
    # drift: a holder's slip, breathing or a settling patient move the tissue across the slice, up to a few tenths
    # of a millimetre per second (usdeform.sim.effects.OutOfPlaneMotion)
    EffectModel(
        "out_of_plane_motion",
        ("shift_mm_per_mm", "jitter_mm", "drift_mm_per_s"),
        ((0.0, 0.8), (0.0, 1.0), (-0.5, 0.5)),
        ((0.05, 0.2, 0.4), (0.0, 0.2, 0.5), (0.0, 0.2)),
        edges=((-_INF, 0.8), (-_INF, 1.0), (-0.5, 0.5)),
    ),
    # the softest layer solved is 0.2 of the tissue's modulus: below it the fit extrapolates the library
    EffectModel(
        "layered_tissue",
        ("thickness_mm", "modulus_ratio"),
        ((0.5, 16.0), (0.1, 0.8)),
        ((2.0, 5.0, 10.0), (0.2, 0.5)),
        edges=((-_INF, 16.0), (LAYER_MODULUS_RATIOS[0], _INF)),
    ),
    EffectModel("sliding_contact", ("slip_fraction",), ((0.0, 1.0),), ((0.5, 1.0),), edges=((-_INF, _INF),)),
    EffectModel("lumen_pressure", ("pressure_ratio",), ((0.0, 0.35),), ((0.03, 0.1, 0.25),), edges=((-_INF, 0.35),)),
    EffectModel("force_latency", ("delay_s",), ((-0.3, 0.3),), ((-0.2, -0.1, 0.05, 0.1, 0.2),)),
)
EFFECT_BY_ID = {model.effect: model for model in EFFECTS}
LINEAR_PARAMETERS = {"force_sensor_error": ("offset_n", "drift_n_per_s")}


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
        weights["slide"] = effects["sliding_contact"]["slip_fraction"]
    if "layered_tissue" in effects:
        thickness = effects["layered_tissue"]["thickness_mm"]
        ratio = effects["layered_tissue"]["modulus_ratio"]
        for t, wt in _linear_interpolation_weights(thickness, (0.0, *LAYER_THICKNESSES_MM)).items():
            if t == 0.0:
                continue
            for r, wr in _linear_interpolation_weights(ratio, LAYER_MODULUS_RATIOS).items():
                name = f"layer_{t:g}_{r:g}"
                weights[name] = weights.get(name, 0.0) + wt * wr
    if "probe_tilt" in effects:
        tilt = effects["probe_tilt"]["tilt_deg"]
        name = tilt_variant_name(float(np.copysign(TILT_VARIANT_DEG, tilt)))
        if tilt and name in section.fields:
            weights[name] = abs(tilt) / TILT_VARIANT_DEG
        slope = _travel_slope(effects)
        if slope and TRAVEL_VARIANT in section.fields:
            weights[TRAVEL_VARIANT] = slope / np.tan(np.radians(TILT_VARIANT_DEG))
    if "lumen_pressure" in effects and "pressure_0.05" in section.fields:
        for p, wp in _linear_interpolation_weights(
            effects["lumen_pressure"]["pressure_ratio"], (0.0, *PRESSURE_RATIOS)
        ).items():
            if p != 0.0:
                weights[f"pressure_{p:g}"] = weights.get(f"pressure_{p:g}", 0.0) + wp
    # a section left out of the library (it could not be solved) takes its effect out: nothing to weight
    return {name: weight for name, weight in weights.items() if name in section.fields}


def _travel_slope(effects: dict[str, dict[str, float]]) -> float:
    """Lateral travel of the probe per mm of lambda (tan of its angle to the surface normal, towards +x)."""
    tilt = effects.get("probe_tilt", {})
    return float(np.tan(np.radians(tilt.get("tilt_deg", 0.0) * tilt.get("travel_along_axis", 0.0))))


def _image_lambda(observation: Observation, delay_s: float) -> np.ndarray:
    """Lambda (mm) of the tissue each frame shows when images lag by ``delay_s``."""
    return np.interp(observation.time_s - delay_s, observation.time_s, observation.probe_displacement_mm)


def contact_reaction(
    observation: Observation, section: CalibratedSection, effects: dict[str, dict[str, float]]
) -> np.ndarray:
    """(n,) force, N, the mechanical effects add at first contact, on every frame in contact (lambda > 0).

    A pressurised lumen bulges the surface into the probe, which carries its push from the moment it
    touches: a step at contact that the elastic cubic (through the origin) cannot take up, and that a
    sensor offset only imitates in contact (the offset reads out of contact too). Through QLV when on.
    """
    step = section.contact_reaction_n(variant_weights(effects, section))
    reaction = np.where(force_lambda(observation, effects) > 0, step, 0.0)
    if step and "viscoelasticity" in effects:
        reaction = qlv(
            reaction, observation.time_s, effects["viscoelasticity"]["g"], effects["viscoelasticity"]["tau_s"]
        )
    return reaction


def _correlation_steps(observation: Observation) -> np.ndarray:
    """(pairs, n) lambda difference (mm) of every correlated pair of frames, NaN where a frame has no partner."""
    partner = observation.correlation_partner
    lam = observation.probe_displacement_mm
    return np.where(partner >= 0, lam - lam[np.maximum(partner, 0)], np.nan)


def _correlation_time_steps(observation: Observation) -> np.ndarray:
    """(pairs, n) time difference (s) of every correlated pair of frames, NaN where a frame has no partner."""
    partner = observation.correlation_partner
    return np.where(partner >= 0, observation.time_s - observation.time_s[np.maximum(partner, 0)], np.nan)


def _elevation_offset(observation: Observation, steps: np.ndarray, effects: dict[str, dict[str, float]]) -> np.ndarray:
    """(pairs, n) mean elevation offset, mm, of every correlated pair of frames: shift * dlambda + drift * dt."""
    motion = effects["out_of_plane_motion"]
    offset = motion["shift_mm_per_mm"] * steps
    drift = motion.get("drift_mm_per_s", 0.0)
    return offset + drift * _correlation_time_steps(observation) if drift else offset


def _correlation_factor(
    observation: Observation, steps: np.ndarray, effects: dict[str, dict[str, float]]
) -> np.ndarray:
    """Expected out-of-plane decorrelation factor of frame pairs ``steps`` (mm of lambda) apart (1 when off)."""
    if "out_of_plane_motion" not in effects:
        return np.ones_like(steps)
    jitter = effects["out_of_plane_motion"]["jitter_mm"]
    variance = _ELEVATION_SIGMA_MM**2 + 2 * jitter**2
    offset = _elevation_offset(observation, steps, effects)
    return _ELEVATION_SIGMA_MM / np.sqrt(variance) * np.exp(-(offset**2) / (2 * variance))


def _correlation_factor_draws(
    observation: Observation, steps: np.ndarray, effects: dict[str, dict[str, float]]
) -> np.ndarray:
    """(draws, pairs, n) out-of-plane decorrelation factor of every frame pair for ``_ROUGHNESS_DRAWS`` draws of the
    frames' jitter (fixed draws: the same for every candidate, so the fit sees a smooth objective)."""
    if "out_of_plane_motion" not in effects:
        return np.ones((1, *steps.shape))
    jitter = effects["out_of_plane_motion"]["jitter_mm"]
    unit = np.random.default_rng(_ROUGHNESS_SEED).standard_normal((_ROUGHNESS_DRAWS, observation.n_frames))
    partner = np.maximum(observation.correlation_partner, 0)
    offset = _elevation_offset(observation, steps, effects)[None] + jitter * (unit[:, None, :] - unit[:, partner])
    return np.exp(-(offset**2) / (2 * _ELEVATION_SIGMA_MM**2))


@dataclass
class FittedLinear:
    """Parameters fitted linearly with a prediction: the force terms, the correlation baseline and the ideal
    section's free parameters (name -> value, see ``CalibratedSection.parameters``)."""

    force_coefficients: np.ndarray
    correlation_coefficients: np.ndarray
    section_parameters: dict[str, float]


@dataclass
class _DisplacementPart:
    """The displacement side of a prediction: tracked displacement, pixels (n, N, 2), the fitted section
    parameters' variant weights and values, and the lambda, mm, of the tissue each frame shows."""

    displacement: np.ndarray
    parameter_weights: dict[str, float]
    parameter_values: dict[str, float]
    image_lambda: np.ndarray
    # residual sums of the displacement, shared by the predictions made from this part (Prediction.displacement_sums)
    residual_sums: list = dataclasses.field(default_factory=list)


GeometryCache = dict[tuple, _DisplacementPart]
_GEOMETRY_CACHE_ENTRIES = 64  # per recording and split: a fit's evaluations revisit the same geometry


def _displacement_part(
    observation: Observation,
    section: CalibratedSection,
    weights: dict[str, float],
    delay: float,
    tilt: float,
    travel_slope: float,
    depth_scale: float,
    fit_mask: np.ndarray,
) -> _DisplacementPart:
    """The tracked points' simulated displacement with the effects' variant ``weights``, image delay (s), tilt
    (degrees) and depth scale, the section's free parameters fitted on the frames of ``fit_mask``."""
    image_lambda = _image_lambda(observation, delay)
    field = section.field(weights) if weights else section.fields["ideal"]
    tracked = TrackedPoints(observation, section, field, image_lambda, tilt, travel_slope, depth_scale)
    sampled = {"ideal": tracked.sample(section.fields["ideal"])}

    def sample(name: str) -> np.ndarray:
        if name not in sampled:
            sampled[name] = tracked.sample(section.fields[name])
        return sampled[name]

    def change(name: str) -> np.ndarray:
        """(2, n, m) field change, mm, per unit weight of the parameter variant ``name``: its library terms summed
        in order."""
        (library, c), *rest = section.parameter_change(name, weights).items()
        total = c * sample(library)
        for library, c in rest:
            total += c * sample(library)
        return total

    ideal = sampled["ideal"]
    displacement = tracked.displacement_px(tracked.sample(field) if weights else ideal)  # no variant: ideal once
    changes = {name: tracked.change_px(change(name)) for name in section.parameter_variants()}
    parameter_weights, parameter_values = fit_section_parameters(
        observation, displacement, changes, fit_mask, section.parameters
    )
    for name, weight in parameter_weights.items():
        displacement = displacement + weight * changes[name]
    displacement.setflags(write=False)  # shared by the predictions a cache serves it to
    return _DisplacementPart(displacement, parameter_weights, parameter_values, image_lambda)


def predict(
    observation: Observation,
    section: CalibratedSection,
    effects: dict[str, dict[str, float]],
    fit_mask: np.ndarray,
    cache: GeometryCache | None = None,
) -> tuple[Prediction, FittedLinear]:
    """The calibrated simulation of ``observation`` with ``effects`` (ID -> parameters) added.

    The linear parameters (elastic force, sensor terms, correlation baseline) are fitted on the
    frames of ``fit_mask`` (the fitting split). ``cache``: the displacement side of earlier predictions of this
    observation, section and split, keyed by what it depends on (the mechanical variants' weights, image delay,
    tilt and depth scale): effects of the force or the speckle alone leave it unchanged, so a fit of theirs
    computes it once.
    """
    design = force_columns(observation, effects)
    reaction = contact_reaction(observation, section, effects) + fixed_force(observation, effects)
    coefficients = fit_force(design[fit_mask], (observation.force_n - reaction)[fit_mask])
    force = design @ coefficients + reaction

    delay = effects.get("image_latency", {}).get("delay_s", 0.0)
    tilt = effects.get("probe_tilt", {}).get("tilt_deg", 0.0)
    depth_scale = (_ASSUMED_SOUND_SPEED + effects.get("sound_speed_mismatch", {}).get("error_m_s", 0.0)) / (
        _ASSUMED_SOUND_SPEED
    )
    weights = variant_weights(effects, section)
    travel_slope = _travel_slope(effects)
    key = (delay, tilt, travel_slope, depth_scale, tuple(sorted(weights.items())))
    part = cache.get(key) if cache is not None else None
    if part is None:
        part = _displacement_part(observation, section, weights, delay, tilt, travel_slope, depth_scale, fit_mask)
        if cache is not None:
            if len(cache) >= _GEOMETRY_CACHE_ENTRIES:
                cache.pop(next(iter(cache)))
            cache[key] = part
    displacement, image_lambda = part.displacement, part.image_lambda
    weights.update(part.parameter_weights)

    steps = _correlation_steps(observation)
    factor = _correlation_factor(observation, steps, effects)
    distance = np.abs(steps)
    ok = fit_mask[None, :] & np.isfinite(observation.correlation) & np.isfinite(steps)
    columns = [factor, -(factor * distance), -(factor * distance**2)]
    lower, upper = [0.0, 0.0, -np.inf], [np.inf, np.inf, np.inf]
    correlation_design = np.column_stack([column[ok] for column in columns])
    target = observation.correlation[ok]
    if "out_of_plane_motion" in effects:
        # The part of the band-passed image that stays correlated across the slice. Without a steady shift
        # the factor is constant and this part trades one for one with the baseline's level; a slight pull
        # to zero takes the decorrelating reading, as for speckle.
        correlation_design = np.vstack(
            [np.column_stack([correlation_design, (1 - factor)[ok]]), [0.0, 0.0, 0.0, _COHERENT_PULL]]
        )
        target = np.append(target, 0.0)
        lower, upper = [*lower, 0.0], [*upper, 1.0]
    correlation_coefficients = bounded_linear_fit(correlation_design, target, np.array(lower), np.array(upper))
    level, slope, curvature = correlation_coefficients[:3]
    coherent = correlation_coefficients[3] if len(correlation_coefficients) == 4 else 0.0
    baseline = level - slope * distance - curvature * distance**2
    correlation = factor * baseline + coherent * (1 - factor)
    draws = _correlation_factor_draws(observation, steps, effects)
    roughness = np.mean(correlation_roughness(draws * baseline + coherent * (1 - draws)), axis=0)

    area_ratio = None
    if section.has_vessel:
        area = section.lumen_area(section.joint_weights(weights))
        at_frames = np.interp(np.clip(image_lambda, 0, None), section.lambda_mm, area)
        area_ratio = at_frames / at_frames[observation.reference_index]
    reference_motion = image_lambda / depth_scale if observation.reference is not None else None
    prediction = Prediction(
        force, displacement, correlation, area_ratio, roughness, part.residual_sums, reference_motion
    )
    return prediction, FittedLinear(coefficients, correlation_coefficients, part.parameter_values)


def surveyed_depth_mm(observation: Observation, survey: CalibratedSection) -> float:
    """The tissue depth, mm, fitted alone on the fitting split with the survey library (``calibrate(...,
    survey=True)``: the ideal section at 60 mm and its 35 and 90 mm variants), to solve the full library around."""
    _, linear = predict(observation, survey, {}, split_mask(observation, 0))
    return linear.section_parameters["depth_mm"]


def without_points_near_base(observation: Observation, section: CalibratedSection) -> Observation:
    """``observation`` without the tracked points within ``BASE_MARGIN_MM`` of the calibrated rigid base or below it.

    The section's base is rigid and bonded to the tissue; a real one (bone under muscle, the table or box under a
    phantom) slides and yields, and the library's two elements next to it are its coarsest part: tissue there
    moves as neither says whatever the effects are (thin phantoms were attributed to a wrong speed of sound).
    The base's depth is the ideal simulation's, fitted on the fitting split; a point's depth is taken in the
    reference frame plus that frame's indentation (an upper bound). All points are kept when none would be.
    """
    _, linear = predict(observation, section, {}, split_mask(observation, 0))
    indentation_mm = max(float(observation.probe_displacement_mm[observation.reference_index]), 0.0)
    depth_mm = observation.row_depth_mm(observation.points_px[:, 1]) + indentation_mm
    keep = depth_mm < linear.section_parameters["depth_mm"] - BASE_MARGIN_MM
    if keep.all() or not keep.any():
        return observation
    return dataclasses.replace(
        observation, points_px=observation.points_px[keep], displacement_px=observation.displacement_px[:, keep]
    )
