"""Where the probe is and where tissue points appear in its image.

The *surface frame* is the phantom's own frame: origin on the undeformed surface at sweep
coordinate s = 0, x lateral (the section's x), y along the sweep (s), z up out of the tissue. A
section point (x, depth z) at sweep coordinate s is the surface point (x, s, -z). The probe frame
follows the paper: origin at the centre of the probe face, x lateral, z along the probe axis into
the tissue, y = z cross x (the elevation axis). An untilted probe at sweep coordinate s pressed
lambda mm into the tissue has ``probe_to_surface`` = rotation diag(1, -1, -1), origin (0, s, -lambda).
Pixels map to the probe frame with the paper's eq. 2 (:func:`usdeform.recording.image_to_probe_from_geometry`);
pixel (col, row) samples exactly the probe point ``image_to_probe @ [col, row, 0, 1]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .settings import ImagingSettings, TissueAcoustics

__all__ = [
    "ProbeState",
    "image_to_surface",
    "probe_to_surface",
    "section_to_surface",
    "surface_to_image",
    "tissue_reach",
]


@dataclass(frozen=True)
class ProbeState:
    """Where the probe is: sweep coordinate s (mm), indentation lambda (mm, from first contact), tilt about the
    elevation axis (degrees, in the image plane), the out-of-plane shift of the imaged tissue relative to the
    probe (mm, along the surface y axis), the height of the face's centre above the surface at first contact
    (mm; a face tilted to the surface, or convex, touches first elsewhere): the face centre is at depth
    lambda - face_height_mm, and its lateral position (mm, along the surface x axis; a probe pressing off the
    surface normal travels sideways)."""

    sweep_position_mm: float
    probe_displacement_mm: float
    tilt_deg: float = 0.0
    tissue_elevation_shift_mm: float = 0.0
    face_height_mm: float = 0.0
    lateral_mm: float = 0.0

    def at_zero_force(self) -> ProbeState:
        """The same probe position and tilt, at first contact with the undeformed surface (no lateral travel), no
        out-of-plane shift."""
        return ProbeState(self.sweep_position_mm, 0.0, self.tilt_deg, face_height_mm=self.face_height_mm)


def _transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (m, 3) points (element-wise arithmetic: no BLAS threads to contend with OpenCV's)."""
    return (
        points[:, 0:1] * matrix[:3, 0] + points[:, 1:2] * matrix[:3, 1] + points[:, 2:3] * matrix[:3, 2] + matrix[:3, 3]
    )


def probe_to_surface(probe: ProbeState) -> np.ndarray:
    """(4, 4) pose of the probe in the surface frame (see the module docstring)."""
    tilt = np.radians(probe.tilt_deg)
    about_elevation = np.array([[np.cos(tilt), 0.0, np.sin(tilt)], [0.0, 1.0, 0.0], [-np.sin(tilt), 0.0, np.cos(tilt)]])
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0]) @ about_elevation
    pose[:3, 3] = [probe.lateral_mm, probe.sweep_position_mm, probe.face_height_mm - probe.probe_displacement_mm]
    return pose


def section_to_surface(points_xz_mm: np.ndarray, elevation_mm: np.ndarray | float) -> np.ndarray:
    """Section points (m, 2) (x, depth) at sweep coordinate(s) ``elevation_mm`` -> surface frame (m, 3)."""
    points_xz_mm = np.asarray(points_xz_mm, dtype=np.float64)
    elevation = np.broadcast_to(np.asarray(elevation_mm, dtype=np.float64), points_xz_mm.shape[:1])
    return np.column_stack([points_xz_mm[:, 0], elevation, -points_xz_mm[:, 1]])


def surface_to_image(
    points_mm: np.ndarray, probe: ProbeState, settings: ImagingSettings, acoustics: TissueAcoustics
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface points (m, 3) -> where the scanner displays them.

    Returns (col_row (m, 2) pixel coordinates, depth_mm (m,) true depth below the probe face along
    its axis, elevation_mm (m,) distance from the image plane). The displayed depth is the true
    depth times ``assumed / true`` sound speed (echo time converted with the assumed speed).
    """
    surface_to_probe = np.linalg.inv(probe_to_surface(probe))
    in_probe = _transform(surface_to_probe, points_mm)
    depth = in_probe[:, 2]
    displayed = in_probe.copy()
    displayed[:, 2] = depth * (settings.assumed_sound_speed_m_s / acoustics.sound_speed_m_s)
    probe_to_image = np.linalg.inv(settings.image_to_probe)
    in_image = _transform(probe_to_image, displayed)
    return in_image[:, :2], depth, in_probe[:, 1]


def image_to_surface(
    col_row: np.ndarray, probe: ProbeState, settings: ImagingSettings, acoustics: TissueAcoustics
) -> np.ndarray:
    """Pixel coordinates (m, 2) -> surface points (m, 3): the inverse of :func:`surface_to_image` in the image plane."""
    in_probe = _transform(settings.image_to_probe, np.column_stack([col_row, np.zeros(len(col_row))]))
    in_probe[:, 2] *= acoustics.sound_speed_m_s / settings.assumed_sound_speed_m_s
    return _transform(probe_to_surface(probe), in_probe)


def tissue_reach(probe: ProbeState, settings: ImagingSettings) -> tuple[float, float]:
    """(half width, depth), mm, of the reference tissue that can appear in the image of ``probe``
    (tilt and compression included, with 5 mm to spare for lateral and axial tissue motion)."""
    depth = settings.depth_mm + abs(probe.probe_displacement_mm) + 5.0
    tilt = np.radians(abs(probe.tilt_deg))
    return settings.width_mm / 2 * np.cos(tilt) + depth * np.sin(tilt) + 5.0, depth
