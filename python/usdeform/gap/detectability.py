"""Which library effects these recordings could reveal at all: a noise-free power check of the gap tests.

A "no significant gap" verdict says only that the recordings show no effect *that they can show*. Some
effects leave almost nothing a palpation measures: a wrong speed of sound scales displayed depths
uniformly, which neither strain nor a geometry calibrated on the same image can see; frictionless and
bonded contact of a flat probe coincide as the tissue nears incompressibility (Dundurs' second constant,
proportional to 1 - 2 nu, vanishes), so sliding moves the tracked tissue by hundredths of a millimetre. So
the diagnosis states, for each library effect, whether it would leave a significant gap in *these*
recordings (their frames, forces, tracked points and uncertainties) at the top of its realistic range.

Check: the calibrated simulator with the effect at ``LARGEST_REALISTIC`` (fitted, like every candidate, to
the recording's fitting split) stands in for the recording; the ideal simulator is fitted to it in turn, and
its expected residuals, divided by the recording's own uncertainties, go through the gap tests of the verdict
(:func:`usdeform.gap.measures.gap_tests`, both splits). No noise is added: an effect that passes would show
in about half of such recordings at that magnitude, one that fails in fewer. Image statistics (mean
intensity, near-field band) are left out: no library effect changes them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from .measures import correlation_roughness, gap_tests, residual_sums
from .models import EFFECTS, predict
from .observations import Observation

if TYPE_CHECKING:
    from .attribution import _Case

__all__ = ["LARGEST_REALISTIC", "undetectable_effects"]

# The top of each effect's realistic range (the sources are in usdeform.sim.effects); the second parameter of
# a two-parameter effect sits mid-range.
LARGEST_REALISTIC: dict[str, dict[str, float]] = {
    "image_latency": {"delay_s": 0.15},  # video paths and frame buffers, 0-0.15 s
    "force_sensor_error": {"offset_n": 1.0},  # residual bias after taring, 0-1 N
    "viscoelasticity": {"g": 0.45, "tau_s": 1.0},  # soft tissue relaxes 20-50 %; tau mid-range of 0.1-100 s
    "sound_speed_mismatch": {"error_m_s": -90.0},  # fat (~1450 m/s) against the assumed 1540 m/s
    "probe_tilt": {"tilt_deg": 10.0},  # 0-10 degrees of residual misalignment
    "out_of_plane_motion": {"shift_mm_per_mm": 0.3, "jitter_mm": 0.3},  # 0-0.3 mm/mm; jitter of 0-0.5 mm
    "layered_tissue": {"thickness_mm": 10.0, "modulus_ratio": 0.2},  # subcutaneous fat, 3-20 mm, far softer
    "sliding_contact": {"slip_fraction": 1.0},  # frictionless contact
    "lumen_pressure": {"pressure_ratio": 0.25},  # a quarter of the shear modulus: a few kPa (veins, phantoms)
}


def _expected_recording(case: _Case, effect: str) -> tuple[Observation, np.ndarray]:
    """The observation replaced by the calibrated simulation with ``effect`` at its largest realistic magnitude,
    and the expected correlation roughness of that simulation."""
    observation = case.observation
    parameters = LARGEST_REALISTIC[effect]
    if effect == "force_sensor_error":  # its parameters enter the force fit linearly: add the offset directly
        simulated = case.ideal
        force = simulated.force_n + parameters["offset_n"]
    else:
        simulated, _ = predict(observation, case.section, {effect: parameters}, case.fit)
        force = simulated.force_n
    area = observation.vessel_area_mm2
    if simulated.vessel_area_ratio is not None:
        area = simulated.vessel_area_ratio * area[observation.reference_index]
    expected = dataclasses.replace(
        observation,
        force_n=force,
        displacement_px=np.where(np.isfinite(observation.displacement_px), simulated.displacement_px, np.nan),
        correlation=np.where(np.isfinite(observation.correlation), simulated.correlation, np.nan),
        vessel_area_mm2=np.where(np.isfinite(observation.vessel_area_mm2), area, np.nan),
    )
    roughness = correlation_roughness(expected.correlation)
    if simulated.correlation_roughness is not None:
        roughness = np.where(np.isfinite(roughness), simulated.correlation_roughness, np.nan)
    return expected, roughness


def undetectable_effects(cases: Sequence[_Case], groups: np.ndarray) -> list[str]:
    """IDs of the library effects that, at the top of their realistic range, would leave no significant gap
    in the recordings of ``cases`` (each with its layout, splits and uncertainties), in library order."""
    undetectable = []
    for model in EFFECTS:
        held, fitting = [], []
        for case in cases:
            expected, roughness = _expected_recording(case, model.effect)
            ideal, _ = predict(expected, case.section, {}, case.fit)
            held_z, fitting_z = case.split_z(*residual_sums(expected, case.layout, ideal, observed_roughness=roughness))
            held.append(held_z)
            fitting.append(fitting_z)
        if not gap_tests((np.concatenate(held), np.concatenate(fitting)), groups)[0]:
            undetectable.append(model.effect)
    return undetectable
