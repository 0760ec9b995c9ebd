"""One recording's fitting and held-out halves, as the attribution and the power check share them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .calibration import CalibratedSection
from .measures import FeatureLayout, Prediction
from .models import GeometryCache
from .observations import Observation
from .statistics import feature_values

__all__ = ["HeldOutCase"]


@dataclass
class HeldOutCase:
    """One recording as the attribution sees it: its observation, calibrated ideal section and the features of
    its fitting and held-out time blocks, with their standard deviations."""

    observation: Observation
    section: CalibratedSection
    layout: FeatureLayout
    fit: np.ndarray
    held: np.ndarray
    held_weights: np.ndarray
    sigma_fit: np.ndarray
    sigma_held: np.ndarray
    ideal: Prediction  # the ideal simulation, its linear parameters fitted on the fitting split
    section_parameters: dict[str, float]  # the ideal section's free parameters, fitted on the fitting split
    geometry: GeometryCache = field(default_factory=dict)  # predictions' displacement side (models.predict)

    def split_z(self, sums: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F,) z-scores of residual sums (see :func:`residual_sums`) on the held-out and on the fitting split."""
        held = feature_values(sums, counts, self.held[None].astype(float))[0] / self.sigma_held
        fitting = feature_values(sums, counts, self.fit[None].astype(float))[0] / self.sigma_fit
        return held, fitting
