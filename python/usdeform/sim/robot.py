"""The robot of a simulated recording: its clocks, its force controller and the path of a sweep.

Each nuisance of a real robotic sweep is off by default (a recording without it is bit-identical to
one made before it existed) and seeded through the recording's seed:

- :class:`ForceController` ``oscillation_n`` / ``tracking_ripple_n``: the controller holds the target
  force only within a band (a slow oscillation and a faster ripple of its tracking error);
- :class:`SweepPath` ``max_tilt_deg``: the probe rotates about its elevation axis along the path, as
  when it follows a curved body surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = ["Clocks", "ForceController", "SweepPath", "low_pass_noise"]


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
    curved surface. Range 0-15 degrees; the mechanics stay the flat indentation's (as for ProbeTilt)."""

    max_tilt_deg: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.max_tilt_deg) and abs(self.max_tilt_deg) <= 30):
            raise InputError(f"SweepPath.max_tilt_deg: expected at most 30 degrees, got {self.max_tilt_deg!r}")

    def tilt_deg(self, path_fraction: float) -> float:
        """The probe's rotation about its elevation axis, degrees, at ``path_fraction`` (0: start, 1: end)."""
        return float(self.max_tilt_deg * np.sin(np.pi * np.clip(path_fraction, 0.0, 1.0)))
