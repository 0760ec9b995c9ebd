"""The robot of a simulated recording: its clocks, its force controller, its force loop and the path of a sweep.

Each nuisance of a real robotic sweep is off by default (a recording without it is bit-identical to
one made before it existed) and seeded through the recording's seed:

- :class:`ForceController` ``oscillation_n`` / ``tracking_ripple_n``: the controller holds the target
  force only within a band (a slow oscillation and a faster ripple of its tracking error);
- :class:`SweepPath` ``max_tilt_deg``: the probe rotates about its elevation axis along the path, as
  when it follows a curved body surface; ``surface_radius_mm``: the surface is convex along the sweep and
  the probe turns about its lateral axis as it follows it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .effects import Effects
from .imaging import interpolation_bracket
from .phantoms import Phantom

__all__ = [
    "Clocks",
    "ElasticForce",
    "ForceController",
    "SweepPath",
    "Trajectory",
    "low_pass_noise",
    "run_force_loop",
]

_FORCE_TABLE_SPACING_MM = 1.0  # sweep positions at which the elastic force curve is tabulated
_MIN_SURFACE_RADIUS_MM = 20.0  # a surface curved more tightly than this is no longer locally flat under the probe


@dataclass(frozen=True)
class Clocks:
    """Sampling rates of the three streams, Hz, and the image clock's offset from the force clock, s.

    Defaults: 50 fps B-mode (the paper), a 1 kHz force sensor (DAQ), 250 Hz robot poses.
    """

    image_rate_hz: float = 50.0
    force_rate_hz: float = 1000.0
    pose_rate_hz: float = 250.0
    image_offset_s: float = 0.0037

    def __post_init__(self) -> None:
        for name in ("image_rate_hz", "force_rate_hz", "pose_rate_hz"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"Clocks.{name}: expected a positive rate in Hz, got {value!r}")
        if not np.isfinite(self.image_offset_s):
            raise InputError(f"Clocks.image_offset_s: expected a finite time in s, got {self.image_offset_s!r}")


def low_pass_noise(rng: np.random.Generator, n: int, rms: float, bandwidth_hz: float, rate_hz: float) -> np.ndarray:
    """(n,) first-order low-pass filtered Gaussian noise with the given stationary rms."""
    decay = np.exp(-2 * np.pi * bandwidth_hz / rate_hz)
    drive = rng.standard_normal(n) * rms * np.sqrt(1 - decay**2)
    noise = np.empty(n)
    level = rng.standard_normal() * rms
    for index in range(n):
        level = decay * level + drive[index]
        noise[index] = level
    return noise


@dataclass(frozen=True)
class ForceController:
    """1-DOF admittance force control along the probe axis, run on the force clock.

    ``d lambda_cmd / dt = gain * (F_target + e(t) - F_measured)``; with tissue stiffness k (N/mm) the
    loop's time constant is 1 / (gain k): 0.05-0.1 s for the paper's phantoms at the default gain.
    ``sensor_noise_n``: white force noise, N rms. ``position_ripple_mm``: rms of the robot's
    low-pass (``ripple_bandwidth_hz``) position error along the axis, which the controller must
    reject; it makes the realistic force ripple of a compliant robot (a few tenths of a newton).

    ``e(t)``, the tracking error of a real robot's force loop (off by default):
    ``oscillation_n * sin(2 pi oscillation_hz t + phase)`` (a slow oscillation, random phase) plus
    low-pass noise of ``tracking_ripple_n`` rms and bandwidth ``tracking_ripple_hz``. Robotic
    ultrasound systems hold their target within +/-0.5-1.5 N (e.g. 0.8 N and 0.25 N rms give about
    +/-1.2 N); the force sensor records the force actually applied.
    """

    gain_mm_per_n_s: float = 6.0
    sensor_noise_n: float = 0.03
    position_ripple_mm: float = 0.03
    ripple_bandwidth_hz: float = 3.0
    oscillation_n: float = 0.0
    oscillation_hz: float = 0.3
    tracking_ripple_n: float = 0.0
    tracking_ripple_hz: float = 4.0

    def __post_init__(self) -> None:
        for name in ("gain_mm_per_n_s", "ripple_bandwidth_hz", "oscillation_hz", "tracking_ripple_hz"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"ForceController.{name}: expected a positive number, got {value!r}")
        for name in ("sensor_noise_n", "position_ripple_mm", "oscillation_n", "tracking_ripple_n"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise InputError(f"ForceController.{name}: expected a non-negative number, got {value!r}")

    def tracking_error_n(self, rng: np.random.Generator, times_s: np.ndarray, rate_hz: float) -> np.ndarray:
        """The tracking error e(t), N, at ``times_s`` (the force clock at ``rate_hz``); zeros, with no
        draw from ``rng``, when both parts are off."""
        error = np.zeros(len(times_s))
        if self.oscillation_n > 0:
            phase = rng.uniform(0.0, 2 * np.pi)
            error += self.oscillation_n * np.sin(2 * np.pi * self.oscillation_hz * times_s + phase)
        if self.tracking_ripple_n > 0:
            error += low_pass_noise(rng, len(times_s), self.tracking_ripple_n, self.tracking_ripple_hz, rate_hz)
        return error


@dataclass(frozen=True)
class SweepPath:
    """How the probe is held along a sweep: rotated about its elevation axis (within the image plane,
    as :class:`~usdeform.sim.effects.ProbeTilt`) by ``max_tilt_deg * sin(pi u)`` degrees at the path
    fraction u in [0, 1]: upright at both ends, ``max_tilt_deg`` halfway, as when the probe follows a
    curved surface. Range 0-15 degrees; the mechanics stay the flat indentation's (as for ProbeTilt).

    ``surface_radius_mm``: the body surface is convex along the sweep with this radius (a limb or a neck:
    40-100 mm; inf: flat). The probe follows it, turning about its lateral axis by the arc it has covered,
    and presses along its own axis, the local surface normal; each section is the flat one, bent with the
    tissue (:meth:`surface_bend`)."""

    max_tilt_deg: float = 0.0
    surface_radius_mm: float = math.inf

    def __post_init__(self) -> None:
        if not (np.isfinite(self.max_tilt_deg) and abs(self.max_tilt_deg) <= 30):
            raise InputError(f"SweepPath.max_tilt_deg: expected at most 30 degrees, got {self.max_tilt_deg!r}")
        if not self.surface_radius_mm >= _MIN_SURFACE_RADIUS_MM:  # NaN fails too
            raise InputError(
                f"SweepPath.surface_radius_mm: expected at least {_MIN_SURFACE_RADIUS_MM} mm or inf (flat), "
                f"got {self.surface_radius_mm!r}"
            )

    def surface_bend(self, s_mm: float, middle_mm: float) -> np.ndarray:
        """(4, 4) rigid map of the flat surface frame near sweep position ``s_mm`` onto the curved surface
        that touches the flat one at ``middle_mm`` (mm): a rotation about the lateral axis x by the arc
        ``(s - middle) / radius`` about the centre of curvature ``radius`` below the surface (identity
        when flat). A point at depth d under sweep position s lands ``radius - d`` from that centre."""
        if math.isinf(self.surface_radius_mm):
            return np.eye(4)
        radius, angle = self.surface_radius_mm, -(s_mm - middle_mm) / self.surface_radius_mm
        about_lateral = np.eye(4)
        about_lateral[1:3, 1:3] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        to_centre, from_centre = np.eye(4), np.eye(4)
        to_centre[1:3, 3] = [-s_mm, radius]
        from_centre[1:3, 3] = [middle_mm, -radius]
        return from_centre @ about_lateral @ to_centre

    def tilt_deg(self, path_fraction: float) -> float:
        """The probe's rotation about its elevation axis, degrees, at ``path_fraction`` (0: start, 1: end)."""
        return float(self.max_tilt_deg * np.sin(np.pi * np.clip(path_fraction, 0.0, 1.0)))


@dataclass
class Trajectory:
    """The controlled motion on the force clock: time (s), sweep position (mm), true lambda (mm),
    true axial force (N) and measured force (N), each (n_ticks,)."""

    time_s: np.ndarray
    sweep_position_mm: np.ndarray
    probe_displacement_mm: np.ndarray
    true_force_n: np.ndarray
    measured_force_n: np.ndarray

    def at(self, times_s: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Linear interpolation of a per-tick array at ``times_s`` (held constant outside)."""
        return np.interp(times_s, self.time_s, values)


class ElasticForce:
    """Elastic contact force F_e(s, lambda), N, tabulated every 1 mm of s from the phantom's solutions."""

    def __init__(self, phantom: Phantom, s_min_mm: float, s_max_mm: float):
        count = int(np.ceil((s_max_mm - s_min_mm) / _FORCE_TABLE_SPACING_MM)) + 1
        self._positions = np.unique(np.linspace(s_min_mm, s_max_mm, count))
        self._lambdas = phantom.probe_displacement_mm
        self._forces = np.array([phantom.solution_at(s).force_n for s in self._positions])

    def __call__(self, s_mm: float, probe_displacement_mm: float) -> float:
        if probe_displacement_mm <= 0:
            return 0.0  # not in contact
        if probe_displacement_mm > self._lambdas[-1]:
            raise InputError(
                f"the probe would press {probe_displacement_mm:.3g} mm, beyond the phantom's solved range "
                f"({self._lambdas[-1]} mm): lower the force"
            )
        lower, upper, weight = interpolation_bracket(self._positions, s_mm)
        lower_force = np.interp(probe_displacement_mm, self._lambdas, self._forces[lower])
        upper_force = np.interp(probe_displacement_mm, self._lambdas, self._forces[upper])
        return float((1 - weight) * lower_force + weight * upper_force)

    def probe_displacement_at(self, s_mm: float, force_n: float) -> float:
        """Lambda (mm) at which the elastic force at the nearest tabulated position equals ``force_n``."""
        nearest = int(np.argmin(np.abs(self._positions - s_mm)))
        return float(np.interp(force_n, self._forces[nearest], self._lambdas))


def run_force_loop(
    target_force_n: Callable[[float], float],
    sweep_position_mm: Callable[[float], float],
    tilt_deg: Callable[[float], float],
    duration_s: float,
    initial_probe_displacement_mm: float,
    elastic_force: ElasticForce,
    effects: Effects,
    controller: ForceController,
    clocks: Clocks,
    rng: np.random.Generator,
) -> Trajectory:
    """Run the force controller on the force clock from t = 0 to ``duration_s``; ``tilt_deg`` gives the
    probe's tilt (degrees) at a sweep position (mm)."""
    time_step = 1.0 / clocks.force_rate_hz
    times = np.arange(int(np.floor(duration_s * clocks.force_rate_hz)) + 1) * time_step
    ripple = low_pass_noise(
        rng, len(times), controller.position_ripple_mm, controller.ripple_bandwidth_hz, clocks.force_rate_hz
    )
    sensor_noise = rng.standard_normal(len(times)) * controller.sensor_noise_n
    tracking_error = controller.tracking_error_n(rng, times, clocks.force_rate_hz)
    relaxation = effects.relaxation(time_step)
    commanded = initial_probe_displacement_mm
    relaxation.start_loaded(elastic_force(sweep_position_mm(0.0), commanded + ripple[0]))
    lag = effects.force_sensor.lag_fraction(time_step)
    reading = None  # the lagged sensor output, noise-free
    positions, lambdas, true_forces, measured_forces = (np.empty(len(times)) for _ in range(4))
    for tick, time in enumerate(times):
        position = sweep_position_mm(time)
        tilt = tilt_deg(position)
        probe_displacement = commanded + ripple[tick]
        true_force = relaxation.step(elastic_force(position, probe_displacement)) * np.cos(np.radians(tilt))
        raw = effects.force_sensor.measured(true_force, time, tilt)
        reading = raw if reading is None else reading + lag * (raw - reading)
        measured = reading + sensor_noise[tick]
        target = target_force_n(time) + tracking_error[tick]
        commanded += time_step * controller.gain_mm_per_n_s * (target - measured)
        positions[tick], lambdas[tick], true_forces[tick], measured_forces[tick] = (
            position,
            probe_displacement,
            true_force,
            measured,
        )
    return Trajectory(times, positions, lambdas, true_forces, measured_forces)
