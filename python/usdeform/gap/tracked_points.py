"""The tracked points of a recording in the calibrated section: their material positions and their simulated
displacement in the image, with the probe's tilt, lateral travel and depth scale."""

from __future__ import annotations

import numpy as np

from .calibration import CalibratedSection
from .observations import Observation

__all__ = ["TrackedPoints"]


class TrackedPoints:
    """The tracked points' material positions in the calibrated section, found in the reference frame with the
    candidate's field, and the map from section displacements (relative to the probe) back to image pixels."""

    def __init__(
        self,
        observation: Observation,
        section: CalibratedSection,
        field: np.ndarray,
        image_lambda: np.ndarray,
        tilt_deg: float,
        travel_slope: float,
        depth_scale: float,
    ):
        to_probe = observation.image_to_probe
        self.scale = np.array([to_probe[0, 0], to_probe[2, 1]])
        self.offset = np.array([to_probe[0, 3], to_probe[2, 3]])
        self.cos, self.sin = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
        # the face centre's height above the surface at first contact (a tilted face touches with its edge), mm
        self.face_offset = section.spec.probe_width_mm / 2 * abs(np.tan(np.radians(tilt_deg))) if tilt_deg else 0.0
        self.travel_slope = travel_slope  # the probe's lateral travel per mm of lambda
        self.depth_scale = depth_scale
        self.points = observation.points_px
        self.section, self.image_lambda = section, image_lambda
        self.reference_index = observation.reference_index
        x_probe = self.scale[0] * self.points[:, 0] + self.offset[0]
        z_probe = (self.scale[1] * self.points[:, 1] + self.offset[1]) * depth_scale
        reference_lambda = image_lambda[self.reference_index : self.reference_index + 1]
        deformed = np.column_stack(
            [
                self.cos * x_probe + self.sin * z_probe + reference_lambda * travel_slope,
                -self.sin * x_probe + self.cos * z_probe + reference_lambda - self.face_offset,
            ]
        )
        material = deformed.copy()
        for _ in range(3):  # fixed point of X + u(X) = x
            material = deformed - np.nan_to_num(section.displacement(field, material, reference_lambda)[:, 0].T)
        self.material = material

    def sample(self, field: np.ndarray) -> np.ndarray:
        """(2, n, m) displacement, mm, of the material points in every frame from a gridded field."""
        return self.section.displacement(field, self.material, self.image_lambda)

    def _to_pixels(self, x_mm: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
        """(n, m, 2) the linear part of section (relative to the probe) to image pixels."""
        x_back = self.cos * x_mm - self.sin * z_mm
        z_back = (self.sin * x_mm + self.cos * z_mm) / self.depth_scale
        return np.stack([x_back / self.scale[0], z_back / self.scale[1]], axis=2)

    def displacement_px(self, moved_mm: np.ndarray) -> np.ndarray:
        """(n, m, 2) displacement from the reference frame, pixels, of points moved by ``moved_mm`` (2, n, m)."""
        relative_x = self.material[None, :, 0] + moved_mm[0] - self.image_lambda[:, None] * self.travel_slope
        relative_z = self.material[None, :, 1] + moved_mm[1] - (self.image_lambda[:, None] - self.face_offset)
        return self._to_pixels(relative_x, relative_z) - (self.offset / self.scale)[None, None] - self.points[None]

    def change_px(self, difference_mm: np.ndarray) -> np.ndarray:
        """(n, m, 2) change of the displacement, pixels, when a field difference (2, n, m at the material points)
        is added: the difference minus its reference-frame value (which moves the material points), to first
        order in the field's gradients."""
        relative = difference_mm - difference_mm[:, self.reference_index : self.reference_index + 1]
        return self._to_pixels(relative[0], relative[1])
