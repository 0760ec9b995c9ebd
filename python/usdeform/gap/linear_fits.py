"""The parts of a prediction (:func:`usdeform.gap.models.predict`) fitted linearly: the force design (elastic cubic,
through one-term Prony QLV when on, and the sensor's offset and drift) with its bounded fit, and the ideal section's
free parameters fitted by bounded least squares of the tracked displacement."""

from __future__ import annotations

import itertools

import numpy as np
from scipy.optimize import lsq_linear

from .calibration import SectionParameter
from .observations import Observation

__all__ = [
    "MAX_DRIFT_N_PER_S",
    "bounded_linear_fit",
    "fit_force",
    "fit_section_parameters",
    "fixed_force",
    "force_columns",
    "force_lambda",
    "qlv",
]

#: The bound of a force sensor's fitted drift, N/s: 1.5 times the top of the thermal drift of strain-gauge F/T sensors
#: after power-up (0.1 N/s, :class:`usdeform.sim.effects.ForceSensorError`).
MAX_DRIFT_N_PER_S = 0.15
_LINEAR_FIT_ENTRIES = 256  # bounded linear fits remembered by bounded_linear_fit (per process)
_LINEAR_FITS: dict[tuple, np.ndarray] = {}  # (design shape, bytes of design, target, lower, upper) -> solution


def qlv(elastic: np.ndarray, time_s: np.ndarray, g: float, tau_s: float) -> np.ndarray:
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


def force_lambda(observation: Observation, effects: dict[str, dict[str, float]]) -> np.ndarray:
    """(n,) lambda, mm, of the tissue whose force each frame's force sample reads: lambda(t - delay) with a force
    latency, else the frame's own."""
    if "force_latency" not in effects:
        return observation.probe_displacement_mm
    delay = effects["force_latency"]["delay_s"]
    return np.interp(observation.time_s - delay, observation.time_s, observation.probe_displacement_mm)


def force_columns(observation: Observation, effects: dict[str, dict[str, float]]) -> np.ndarray:
    """(n, k) design of the force fit: cubic elastic terms (through QLV if on) and sensor terms."""
    lam = np.clip(force_lambda(observation, effects), 0.0, None)
    columns = [lam**power for power in (1, 2, 3)]
    if "viscoelasticity" in effects:
        g, tau = effects["viscoelasticity"]["g"], effects["viscoelasticity"]["tau_s"]
        columns = [qlv(column, observation.time_s, g, tau) for column in columns]
    if "force_sensor_error" in effects:
        columns.append(np.ones_like(lam))
        if "drift_n_per_s" not in effects["force_sensor_error"]:
            columns.append(observation.time_s)
    return np.column_stack(columns)


def fixed_force(observation: Observation, effects: dict[str, dict[str, float]]) -> np.ndarray:
    """(n,) force, N, of the sensor terms held fixed rather than fitted: a drift given in ``effects`` (a drift the
    recordings cannot identify is held at its neutral value, 0)."""
    return effects.get("force_sensor_error", {}).get("drift_n_per_s", 0.0) * observation.time_s


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
    return bounded_linear_fit(design / scale, force_n, lower * scale, upper * scale) / scale


def bounded_linear_fit(design: np.ndarray, target: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """``lsq_linear(design, target, bounds=(lower, upper)).x``, the solutions of the last ``_LINEAR_FIT_ENTRIES``
    distinct problems remembered: an effect that changes the displacement alone poses the same force and
    correlation fits at every evaluation."""
    arrays = [np.asarray(array, dtype=float) for array in (design, target, lower, upper)]
    key = (design.shape, *(array.tobytes() for array in arrays))
    if key not in _LINEAR_FITS:
        if len(_LINEAR_FITS) >= _LINEAR_FIT_ENTRIES:
            _LINEAR_FITS.pop(next(iter(_LINEAR_FITS)))
        _LINEAR_FITS[key] = lsq_linear(arrays[0], arrays[1], bounds=(arrays[2], arrays[3])).x
    return _LINEAR_FITS[key].copy()


def fit_section_parameters(
    observation: Observation,
    displacement: np.ndarray,
    changes: dict[str, np.ndarray],
    fit_mask: np.ndarray,
    parameters: tuple[SectionParameter, ...],
) -> tuple[dict[str, float], dict[str, float]]:
    """The free ``parameters`` of the ideal section, fitted by bounded least squares of the
    fitting split's tracked displacement (pixels) to ``displacement`` plus weighted ``changes`` (variant name ->
    (n, m, 2) change of the displacement with that variant's field difference).

    A two-sided parameter takes one side at a time (each combination of sides is fitted; the best kept).
    Returns the weights of the variants and the parameters' values (library values where no variant was solved).
    """
    residual = observation.displacement_px - displacement
    names = list(changes)
    ok = fit_mask[:, None, None] & np.isfinite(residual)
    for name in names:
        ok &= np.isfinite(changes[name])
    columns = np.column_stack([changes[name][ok] for name in names]) if names else np.zeros((int(ok.sum()), 0))
    gram, projection = columns.T @ columns, columns.T @ residual[ok]
    sides: list[list[float | None]] = [
        [value for value in parameter.variants if parameter.variant_name(value) in changes] for parameter in parameters
    ]
    best: tuple[float, dict[str, float]] = (np.inf, {})
    for choice in itertools.product(*[side or [None] for side in sides]):
        chosen = [
            (parameter, value)
            for parameter, value in zip(parameters, choice, strict=True)
            if value is not None and gram[(i := names.index(parameter.variant_name(value))), i] > 0
        ]
        index = [names.index(parameter.variant_name(value)) for parameter, value in chosen]
        weights = _bounded_least_squares(
            gram[np.ix_(index, index)],
            projection[index],
            np.array([parameter.weight_bounds(value) for parameter, value in chosen]).reshape(-1, 2),
        )
        cost = float(weights @ gram[np.ix_(index, index)] @ weights - 2 * weights @ projection[index])
        if cost < best[0]:
            best = (
                cost,
                {
                    parameter.variant_name(value): float(w)
                    for (parameter, value), w in zip(chosen, weights, strict=True)
                },
            )
    variant_weights = best[1]
    values = {}
    for parameter in parameters:
        values[parameter.name] = parameter.library
        for value in parameter.variants:
            weight = variant_weights.get(parameter.variant_name(value), 0.0)
            if weight:
                values[parameter.name] = parameter.value(value, weight)
    return variant_weights, values


def _bounded_least_squares(gram: np.ndarray, projection: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Minimiser of w' G w - 2 p' w within ``bounds`` (k, 2), through the Cholesky factor of G (a k x k problem
    whatever the number of tracked samples behind G and p)."""
    if len(projection) == 0:
        return np.zeros(0)
    regularised = gram + np.eye(len(gram)) * 1e-12 * max(np.trace(gram), 1e-300)
    upper = np.linalg.cholesky(regularised).T  # G = U' U
    target = np.linalg.solve(upper.T, projection)
    return lsq_linear(upper, target, bounds=(bounds[:, 0], bounds[:, 1]), method="bvls").x
