"""The two folds of an attribution's cross-fitting and the fits made in them: each fold holds the observations with
their measure layouts and uncertainties, and gives the gap of any candidate on its fitting split (the time blocks of
one parity) and on its held-out split (the others); a candidate's nonlinear parameters are fitted by a grid search
and Powell's method on the fitting split, its linear ones (the force sensor's offset and drift) by least squares."""

from __future__ import annotations

import functools
import itertools
import pickle
import tempfile
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import minimize
from scipy.stats import norm

from .calibration import CalibratedSection
from .cases import HeldOutCase
from .linear_fits import MAX_DRIFT_N_PER_S, fit_force, fixed_force, force_columns
from .measures import GROUPS, Prediction, build_layout, residual_sums
from .models import EFFECT_BY_ID, LINEAR_PARAMETERS, contact_reaction, predict
from .observations import Observation
from .processes import run_all
from .statistics import bootstrap_spread, bootstrap_weights, feature_values, gap_statistic, split_mask
from .verdicts import ALPHA, parameter_names

#: The linear parameters with a realistic range, as the half-width of that range about their neutral value, and
#: the neutral value a parameter the recordings cannot identify is held at.
LINEAR_BOUNDS = {"drift_n_per_s": MAX_DRIFT_N_PER_S}
LINEAR_NEUTRAL = {"drift_n_per_s": 0.0}
#: The recording (a record_next kind) that identifies each: a hold (or a second ramp speed) puts frames of the same
#: indentation at other times, where a drift in time and a stiffer tissue differ.
LINEAR_IDENTIFIED_BY = {"drift_n_per_s": "hold"}


def as_effects(effect_ids: tuple[str, ...], theta: np.ndarray) -> dict[str, dict[str, float]]:
    effects: dict[str, dict[str, float]] = {effect: {} for effect in effect_ids}
    for (effect, name), value in zip(parameter_names(effect_ids), theta, strict=True):
        effects[effect][name] = float(value)
    return effects


def parameter_bounds(effect_ids: tuple[str, ...]) -> list[tuple[float, float]]:
    return [bound for effect in effect_ids for bound in EFFECT_BY_ID[effect].bounds]


class Fold:
    """One fold: the observations, their layouts and uncertainties, and the gap of any candidate on its fitting
    split (the blocks of parity ``fitting_split``) and on its held-out split (the others)."""

    def __init__(
        self, observations: list[Observation], sections: list[CalibratedSection], seed: int, fitting_split: int
    ):
        rng = np.random.default_rng((seed, fitting_split))
        self.cases: list[HeldOutCase] = []
        for observation, section in zip(observations, sections, strict=True):
            fit, held = split_mask(observation, fitting_split), split_mask(observation, 1 - fitting_split)
            ideal, ideal_linear = predict(observation, section, {}, fit)
            layout = build_layout(observation, ideal)
            sums, counts = residual_sums(observation, layout, ideal)
            sigmas = []
            for mask in (fit, held):
                boot = feature_values(sums, counts, bootstrap_weights(observation, mask, rng))
                sigmas.append(np.sqrt(bootstrap_spread(boot) ** 2 + layout.floors**2))
            held_weights = bootstrap_weights(observation, held, rng)
            self.cases.append(
                HeldOutCase(
                    observation,
                    section,
                    layout,
                    fit,
                    held,
                    held_weights,
                    sigmas[0],
                    sigmas[1],
                    ideal,
                    ideal_linear.section_parameters,
                )
            )
        self.groups = np.concatenate([case.layout.groups for case in self.cases])
        self.n_features = len(self.groups)

    def predictions(self, effects: dict[str, dict[str, float]]) -> list[Prediction]:
        return [predict(case.observation, case.section, effects, case.fit, case.geometry)[0] for case in self.cases]

    def z_fit(self, effects: dict[str, dict[str, float]]) -> np.ndarray:
        """(F,) z-scores of the measures on the fitting split with ``effects`` added."""
        return self.fit_values(self.predictions(effects))

    def fit_values(self, predictions: list[Prediction]) -> np.ndarray:
        """(F,) z-scores of the measures of ``predictions`` on the fitting split."""
        parts = []
        for case, prediction in zip(self.cases, predictions, strict=True):
            parts.append(case.split_z(*residual_sums(case.observation, case.layout, prediction))[1])
        return np.concatenate(parts)

    def fit_gap(self, effects: dict[str, dict[str, float]]) -> float:
        z = self.z_fit(effects)
        return float(gap_statistic(z[None], np.ones_like(z), self.groups)[0])

    def held_values(self, predictions: list[Prediction]) -> tuple[np.ndarray, np.ndarray]:
        """Held-out measure values: point estimate (F,) and bootstrap rows (B, F), in z units.

        A resample that draws none of a measure's frames (a short phase, the frames near contact) keeps the
        measure at its point estimate: otherwise the measure, and with it perhaps its whole group, drops out
        of that resample's gap, which then jumps by the group's share whatever the candidate does.
        """
        points, boots = [], []
        for case, prediction in zip(self.cases, predictions, strict=True):
            sums, counts = residual_sums(case.observation, case.layout, prediction)
            point = case.split_z(sums, counts)[0]
            boot = feature_values(sums, counts, case.held_weights) / case.sigma_held
            points.append(point)
            boots.append(np.where(np.isnan(boot), point[None, :], boot))
        return np.concatenate(points), np.concatenate(boots, axis=1)

    def held_gap(
        self, point: np.ndarray, boot: np.ndarray, groups: tuple[str, ...] | None = None
    ) -> tuple[float, np.ndarray]:
        """Held-out gap of the measure values ``point`` (F,) and its bootstrap rows ``boot`` (B, F), over the
        measures of ``groups`` only when given (0 when none of them is measured)."""
        keep = np.ones(self.n_features, bool) if groups is None else np.isin(self.groups, _group_indices(groups))
        ones = np.ones(int(keep.sum()))
        if not keep.any():
            return 0.0, np.zeros(len(boot))
        statistic = gap_statistic(point[None, keep], ones, self.groups[keep])[0]
        return float(statistic), gap_statistic(boot[:, keep], ones, self.groups[keep])


def _group_indices(groups: tuple[str, ...]) -> list[int]:
    return [GROUPS.index(group) for group in groups]


@dataclass
class HeldOut:
    """A candidate's held-out measure values in each fold: (point (F,), bootstrap rows (B, F)) per fold."""

    folds: list[Fold]
    values: list[tuple[np.ndarray, np.ndarray]]

    @classmethod
    def of(cls, folds: list[Fold], fold_predictions: list[list[Prediction]]) -> HeldOut:
        """The held-out values of the predictions fitted in each fold."""
        return cls(folds, [fold.held_values(p) for fold, p in zip(folds, fold_predictions, strict=True)])

    def gap(self, groups: tuple[str, ...] | None = None) -> tuple[float, np.ndarray]:
        """Cross-fitted held-out gap (the folds' mean) and its bootstrap rows (the folds' rows averaged row by
        row: independent draws), over the measures of ``groups`` only when given."""
        gaps = [fold.held_gap(point, boot, groups) for fold, (point, boot) in zip(self.folds, self.values, strict=True)]
        return float(np.mean([gap[0] for gap in gaps])), np.mean([gap[1] for gap in gaps], axis=0)

    @property
    def first_fold_z(self) -> np.ndarray:
        """(F,) the first fold's held-out z-scores (the fold the measure table reports)."""
        return self.values[0][0]


def _fit(problem: Fold, effect_ids: tuple[str, ...], start: np.ndarray | None) -> tuple[np.ndarray, float]:
    """Fitted nonlinear parameters of ``effect_ids`` on the fitting split and the fitting gap."""
    bounds = parameter_bounds(effect_ids)
    if not bounds:
        return np.zeros(0), problem.fit_gap(as_effects(effect_ids, np.zeros(0)))

    lower, upper = [b[0] for b in bounds], [b[1] for b in bounds]
    best: list = [np.inf, None]  # the best point evaluated: Powell's final point can be worse than its start

    def objective(theta: np.ndarray) -> float:
        theta = np.clip(theta, lower, upper)
        value = problem.fit_gap(as_effects(effect_ids, theta))
        value = value if np.isfinite(value) else 1e12
        if value < best[0]:
            best[:] = [value, theta.copy()]
        return value

    if start is None:
        grids = [g for effect in effect_ids for g in EFFECT_BY_ID[effect].grid]
        candidates = [np.array(point) for point in itertools.product(*grids)]
        start = min(candidates, key=objective)
    else:
        objective(np.asarray(start, dtype=float))
    minimize(
        objective,
        start,
        method="Powell",
        bounds=bounds,
        options={"maxfev": 40 * len(bounds), "xtol": 1e-3, "ftol": 1e-4},
    )
    return best[1], float(best[0])


def parameter_uncertainty(problem: Fold, effect_ids: tuple[str, ...], theta: np.ndarray) -> np.ndarray:
    """Standard errors of the nonlinear parameters from the Gauss-Newton curvature of the z-scores."""
    if len(theta) == 0:
        return np.zeros(0)
    base = problem.z_fit(as_effects(effect_ids, theta))
    ok = np.isfinite(base)
    jacobian = []
    for index, (low, high) in enumerate(parameter_bounds(effect_ids)):
        step = 1e-3 * (high - low)
        shifted = theta.copy()
        shifted[index] = theta[index] + step if theta[index] + step <= high else theta[index] - step
        delta = shifted[index] - theta[index]
        jacobian.append((problem.z_fit(as_effects(effect_ids, shifted)) - base) / delta)
    matrix = np.stack(jacobian, axis=1)[ok]
    matrix = matrix[np.isfinite(matrix).all(axis=1)]
    dof = max(len(matrix) - len(theta), 1)
    scale = max(1.0, float(np.nansum(base[ok] ** 2)) / dof)
    try:
        covariance = np.linalg.pinv(matrix.T @ matrix) * scale
    except np.linalg.LinAlgError:
        return np.full(len(theta), np.nan)
    return np.sqrt(np.clip(np.diag(covariance), 0, None))


def linear_parameters(problem: Fold, effects: dict[str, dict[str, float]]) -> tuple[dict, dict]:
    """Fitted values and standard errors of the linear parameters of ``effects`` (the force sensor's offset, and its
    drift unless ``effects`` holds it fixed), the mean over the fold's recordings (each fits its own). The standard
    errors are those of the unbounded least-squares problem: they carry how nearly collinear a sensor term is with
    the elastic force, which is what decides whether the recordings identify it (:func:`unidentified_linear`)."""
    values: dict[str, float] = {}
    errors: dict[str, float] = {}
    if "force_sensor_error" not in effects:
        return values, errors
    names = [name for name in LINEAR_PARAMETERS["force_sensor_error"] if name not in effects["force_sensor_error"]]
    estimates, variances = [], []
    for case in problem.cases:
        observation = case.observation
        design = force_columns(observation, effects)[case.fit]
        reaction = contact_reaction(observation, case.section, effects) + fixed_force(observation, effects)
        target = (observation.force_n - reaction)[case.fit]
        coefficients = fit_force(design, target)
        residual = target - design @ coefficients
        sigma2 = float(residual @ residual) / max(len(target) - design.shape[1], 1)
        estimates.append(coefficients[3:])
        variances.append([sigma2 / _unexplained_square(design, column) for column in range(3, design.shape[1])])
    estimate = np.mean(estimates, axis=0)
    error = np.sqrt(np.mean(variances, axis=0) / len(estimates))
    for name, value, sigma in zip(names, estimate, error, strict=True):
        values[name], errors[name] = float(value), float(sigma)
    return values, errors


def _unexplained_square(design: np.ndarray, column: int) -> float:
    """The squared norm of what of ``design``'s ``column`` the other columns cannot take up (its residual in least
    squares on them): the information the design has on that column's coefficient, sigma^2 over its variance. Near
    zero where the column is nearly collinear with the others (a pseudo-inverse would drop that direction and
    report a small error)."""
    others = np.delete(design, column, axis=1)
    scale = np.maximum(np.abs(others).max(axis=0), 1e-12)
    solution = np.linalg.lstsq(others / scale, design[:, column], rcond=None)[0]
    residual = design[:, column] - (others / scale) @ solution
    return max(float(residual @ residual), 1e-300)


def unidentified_linear(errors: list[dict[str, float]]) -> list[str]:
    """The bounded linear parameters (:data:`LINEAR_BOUNDS`) that the recordings do not identify: in some fold
    (``errors``: each fold's standard errors) the two-sided 95 % interval of the unbounded fit is wider than the
    parameter's realistic range on either side of its neutral value, so a value at the top of that range could not
    be told from none. On palpations that only load at a steady force rate, time is a function of the indentation
    and a sensor drift is a stiffer tissue: its error there is several times its range."""
    z = float(norm.isf(ALPHA / 2))
    return [
        name
        for name, bound in LINEAR_BOUNDS.items()
        if any(z * fold_errors.get(name, 0.0) >= bound for fold_errors in errors)
    ]


def fit_folds(folds: list[Fold], effect_ids: tuple[str, ...], starts: list[np.ndarray] | None) -> list[np.ndarray]:
    """Fitted nonlinear parameters of ``effect_ids`` in each fold; a fold without a start of its own starts at the
    previous fold's fit (the grid search runs once: the two splits interleave and their optima lie close)."""
    thetas: list[np.ndarray] = []
    for index, fold in enumerate(folds):
        start = starts[index] if starts is not None else (thetas[-1] if thetas else None)
        thetas.append(_fit(fold, effect_ids, start)[0])
    return thetas


def fit_in_fold(folds: list[Fold], index: int, effect_ids: tuple[str, ...], start: np.ndarray) -> np.ndarray:
    """Fitted nonlinear parameters of ``effect_ids`` in fold ``index`` from ``start``."""
    return _fit(folds[index], effect_ids, start)[0]


#: The folds a worker process last read (:func:`_on_saved_folds`), by the path they were read from.
_SAVED_FOLDS: dict[str, list[Fold]] = {}


def _on_saved_folds(path: str, function: Callable[..., Any], *args: Any) -> Any:
    """``function(folds, *args)`` with the folds pickled at ``path``, read once per process."""
    if path not in _SAVED_FOLDS:
        _SAVED_FOLDS.clear()
        _SAVED_FOLDS[path] = pickle.loads(Path(path).read_bytes())
    return function(_SAVED_FOLDS[path], *args)


def fit_all(
    folds: list[Fold], function: Callable[..., Any], jobs: Sequence[tuple], pool: Executor | None, progress=None
) -> list[Any]:
    """``function(folds, *job)`` (:func:`fit_folds` or :func:`fit_in_fold`) for each of ``jobs``, in ``pool``'s
    processes (None: here), which read the folds from a temporary file; the fits are the same either way."""
    if pool is None:
        return run_all(None, functools.partial(function, folds), jobs, progress)
    with tempfile.TemporaryDirectory(prefix="usdeform-folds-") as folder:
        path = Path(folder) / "folds.pickle"
        path.write_bytes(pickle.dumps(folds, protocol=pickle.HIGHEST_PROTOCOL))
        return run_all(pool, _on_saved_folds, [(str(path), function, *job) for job in jobs], progress)
