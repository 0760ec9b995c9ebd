"""A synthetic sweep and a model to correct it with: for trying the live service without a robot,
for its tests and its benchmark (no simulator run: a few milliseconds to make)."""

from __future__ import annotations

import numpy as np

from ..correction import SampledProfiles
from ..recording import Recording, image_to_probe_from_geometry
from ..regression import Normalization, QuadraticDisplacementModel, StiffnessProfile

__all__ = ["synthetic_scan"]


def synthetic_scan(
    n_frames: int = 60,
    rows: int = 96,
    cols: int = 96,
    *,
    seed: int = 0,
    step_mm: float = 0.4,
    rate_hz: float = 30.0,
    force_n: float = 6.0,
) -> tuple[QuadraticDisplacementModel, SampledProfiles, Recording]:
    """A model (quadratic, in image coordinates, fitted range 0-20 N), the stiffness sampled at two
    positions 40 mm apart, and a sweep along the probe's elevation axis: speckle over a dark vessel,
    ``step_mm`` between frames stamped ``1 / rate_hz`` apart, force ``force_n`` +- 10 % with the probe
    displacement its stiffness gives.

    Examples
    --------
    >>> model, sampled, sweep = synthetic_scan(4, 32, 48)
    >>> sweep.frames.shape, model.frame_shape, sweep.probe_displacement is not None
    ((4, 32, 48), (32, 48), True)
    """
    rng = np.random.default_rng(seed)
    coefficients = np.zeros((2, 10))
    coefficients[0, 4] = 0.8  # lateral: x h
    coefficients[1, 5] = 2.0  # axial: y h
    coefficients[1, 8] = 1.0  # axial: h
    model = QuadraticDisplacementModel(
        coefficients, Normalization.for_frames(rows, cols, max_force_n=20.0, max_h_mm=8.0), frame_shape=(rows, cols)
    )
    profiles = (StiffnessProfile(0.05, 1.2, 0.0), StiffnessProfile(0.08, 1.5, 0.0))
    sampled = SampledProfiles(np.array([[0.0, 0.0, 0.0], [0.0, 40.0, 0.0]]), profiles)
    force = force_n * (1.0 + 0.1 * np.sin(np.arange(n_frames) / 7.0))
    weight = np.clip(np.arange(n_frames) * step_mm / 40.0, 0.0, 1.0)
    displacement = np.array(
        [
            StiffnessProfile(
                *((1 - w) * np.array(profiles[0].as_tuple()) + w * np.array(profiles[1].as_tuple()))
            ).lambda_at(f)
            for w, f in zip(weight, force, strict=True)
        ]
    )
    probe_to_base = np.tile(np.eye(4), (n_frames, 1, 1))
    probe_to_base[:, 1, 3] = np.arange(n_frames) * step_mm
    probe_to_base[:, 2, 3] = displacement
    y, x = np.mgrid[0:rows, 0:cols]
    vessel = ((x - cols / 2) / (cols / 6)) ** 2 + ((y - rows * 0.55) / (rows / 8)) ** 2 < 1.0
    speckle = rng.rayleigh(60.0, size=(n_frames, rows, cols))
    frames = np.clip(np.where(vessel, 0.15, 1.0) * speckle, 0, 255).astype(np.uint8)
    return (
        model,
        sampled,
        Recording(
            frames,
            np.arange(n_frames) / rate_hz,
            probe_to_base,
            np.ones(n_frames, dtype=bool),
            image_to_probe_from_geometry(rows, cols),
            force=force,
            probe_displacement=displacement,
        ),
    )
