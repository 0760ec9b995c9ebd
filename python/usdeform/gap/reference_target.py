"""A reflector fixed in the world found in a palpation's frames, and the ratio of its image motion to the probe's
displacement: assumed / true speed of sound.

A flat reflector that does not move with the tissue (the phantom's base plate, the table under it, a wire plane)
lies ``D - lambda`` below a level probe face pressed ``lambda`` into the tissue, and the scanner displays it at
``(D - lambda) * c_assumed / c_true``: its displayed depth falls by ``c_assumed / c_true`` mm per mm of probe
displacement, whatever the tissue does. A probe tilted by a few degrees to the reflector's normal changes that by
``1 - cos(tilt)`` (0.4 % at 5 degrees).

Finding it: every frame's mean grey level per row (the reflector spans the image), each frame's row profile shifted
by ``lambda * ratio`` so that what is fixed in the world lines up, for ratios over real tissue's speeds of sound
(1400-1700 m/s); the sharpest band of the stacked profile is the reflector when it stands out of the rows beside it
by far more than the profile's row-to-row noise (a test that holds on bright, even saturated, deep tissue). With a
known depth (the header key ``ReferenceTargetDepth``, or ``diagnose --reference-depth-mm``) only the rows where that
depth could be displayed are searched. Each frame's reflector row is then the peak near the band (a Gaussian
through the peak row and its neighbours, sub-pixel), and the ratio the least-squares slope of displayed depth
against lambda. :func:`reference_targets` is what the diagnosis reports of each reflector asked for.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError

__all__ = [
    "ASSUMED_SOUND_SPEED_M_S",
    "REFERENCE_DEPTH_KEY",
    "ReferenceTrack",
    "reference_sentence",
    "reference_targets",
    "sound_speed_m_s",
    "track_reference",
]

ASSUMED_SOUND_SPEED_M_S = 1540.0
REFERENCE_DEPTH_KEY = "ReferenceTargetDepth"
_SPEEDS_M_S = (1400.0, 1700.0)  # the speeds of sound searched (soft tissue spans 1450-1640 m/s)
_RATIO_STEP = 0.001
_SEARCH_PX = 3  # rows either side of the band's predicted row where a frame's peak is looked for
_MIN_CONTRAST = 20.0  # the band's sharpness over the stacked profile's row-to-row noise: a reflector, not speckle
_FLOOR = 1e-3  # grey level the peak's logarithms are taken above
_MIN_TRACKED_FRACTION = 0.8  # frames in which the reflector must be found


@dataclass(frozen=True)
class ReferenceTrack:
    """The reflector of one recording: ``depth_mm`` (n,) its displayed depth below the probe face per frame (NaN
    where not found), ``ratio`` the slope of its displayed depth against the probe displacement (assumed / true
    speed of sound) with its standard error, ``world_depth_mm`` its depth below the unloaded surface as displayed
    (true depth times the ratio) and whether the depth was given."""

    depth_mm: np.ndarray
    ratio: float
    ratio_error: float
    world_depth_mm: float
    depth_given: bool


def sound_speed_m_s(ratio: float) -> float:
    """The tissue's speed of sound, m/s, from the reflector's image motion per mm of probe displacement."""
    return ASSUMED_SOUND_SPEED_M_S / ratio


def _row_profiles(frames: np.ndarray) -> np.ndarray:
    """(n, rows) mean grey level of every row of every frame."""
    return np.asarray(frames, dtype=np.float64).mean(axis=2)


def _stacked(profiles: np.ndarray, shifts_px: np.ndarray) -> np.ndarray:
    """(rows,) mean of the row profiles each shifted down by ``shifts_px`` (n,) rows (linear interpolation; NaN
    where a shifted profile has no data)."""
    rows = np.arange(profiles.shape[1], dtype=float)
    shifted = [
        np.interp(rows - shift, rows, profile, left=np.nan, right=np.nan)
        for profile, shift in zip(profiles, shifts_px, strict=True)
    ]
    stacked = np.array(shifted)
    count = np.isfinite(stacked).sum(axis=0)
    return np.where(count > 0, np.nansum(stacked, axis=0) / np.maximum(count, 1), np.nan)


def _row_noise(profile: np.ndarray) -> float:
    """Robust standard deviation of a profile's row-to-row differences (median absolute deviation, scaled)."""
    steps = np.diff(profile)
    steps = steps[np.isfinite(steps)]
    return float(1.4826 * np.median(np.abs(steps - np.median(steps)))) if len(steps) else np.inf


def _peak(profile: np.ndarray, centre: float, half_width: int) -> float:
    """Sub-pixel row of the brightest row of ``profile`` within ``half_width`` rows of ``centre`` (a Gaussian through
    the peak and its neighbours), NaN when the window leaves the image or the peak lies on its edge."""
    low, high = int(np.floor(centre)) - half_width, int(np.ceil(centre)) + half_width
    if low < 1 or high > len(profile) - 2:
        return np.nan
    index = low + int(np.argmax(profile[low : high + 1]))
    if index in (low, high):
        return np.nan
    # a Gaussian through the peak and its neighbours: a parabola through their logarithms (less pixel-locking)
    left, middle, right = np.log(np.maximum(profile[index - 1 : index + 2], _FLOOR))
    curvature = left - 2 * middle + right
    return float(index + (0.5 * (left - right) / curvature if curvature < 0 else 0.0))


def track_reference(
    frames: np.ndarray,
    probe_displacement_mm: np.ndarray,
    image_to_probe: np.ndarray,
    name: str,
    depth_mm: float | None = None,
) -> ReferenceTrack:
    """The reflector fixed in the world in ``frames`` (n, rows, cols) of a palpation with probe displacements
    ``probe_displacement_mm`` (n,), its rows at depth ``image_to_probe[2, 1] * row + image_to_probe[2, 3]`` mm;
    ``depth_mm``: its depth below the unloaded surface when known. Raises InputError naming ``name`` when no
    reflector is found (see the module docstring)."""
    lam = np.asarray(probe_displacement_mm, dtype=float)
    row_mm, row0_mm = float(image_to_probe[2, 1]), float(image_to_probe[2, 3])
    profiles = _row_profiles(frames)
    rows = profiles.shape[1]
    ratios = np.arange(
        ASSUMED_SOUND_SPEED_M_S / _SPEEDS_M_S[1], ASSUMED_SOUND_SPEED_M_S / _SPEEDS_M_S[0] + 1e-9, _RATIO_STEP
    )
    allowed = np.ones(rows, bool)
    if depth_mm is not None:  # the rows where it is displayed at lambda 0, depth * ratio deep, for any ratio searched
        row_depths = np.arange(rows) * row_mm + row0_mm
        allowed = (row_depths >= depth_mm * ratios.min() - 2 * row_mm) & (
            row_depths <= depth_mm * ratios.max() + 2 * row_mm
        )
    best = (-np.inf, 0.0, 0.0)
    for ratio in ratios:
        # lambda moves a world-fixed reflector up by lambda * ratio mm; shift it back down
        stacked = _stacked(profiles, lam * ratio / row_mm)
        candidates = np.where(allowed & np.isfinite(stacked), stacked, -np.inf)
        row = int(np.argmax(candidates))
        sharp = candidates[row] - 0.5 * (stacked[max(row - 2, 0)] + stacked[min(row + 2, rows - 1)])
        if np.isfinite(sharp) and sharp > best[0]:
            best = (float(sharp), float(ratio), float(row))
    sharpness, ratio, world_row = best
    if not np.isfinite(sharpness) or sharpness <= _MIN_CONTRAST * _row_noise(_stacked(profiles, lam * ratio / row_mm)):
        raise InputError(
            f"{name}: frames: no reflector fixed in the world found (a bright band that moves with the probe)"
        )
    tracked = np.array(
        [
            _peak(profile, world_row - value * ratio / row_mm, _SEARCH_PX)
            for profile, value in zip(profiles, lam, strict=True)
        ]
    )
    ok = np.isfinite(tracked)
    if ok.mean() < _MIN_TRACKED_FRACTION or np.ptp(lam[ok]) <= 0:
        raise InputError(
            f"{name}: frames: the reflector fixed in the world is lost in {np.sum(~ok)} of {len(ok)} frames"
        )
    depth = np.where(ok, tracked * row_mm + row0_mm, np.nan)
    design = np.column_stack([np.ones(ok.sum()), lam[ok]])
    coefficients, residual, *_ = np.linalg.lstsq(design, depth[ok], rcond=None)
    sigma2 = float(residual[0]) / max(ok.sum() - 2, 1) if len(residual) else 0.0
    slope_error = float(np.sqrt(sigma2 * np.linalg.inv(design.T @ design)[1, 1]))
    fitted_ratio = -float(coefficients[1])
    return ReferenceTrack(
        depth_mm=depth,
        ratio=fitted_ratio,
        ratio_error=slope_error,
        world_depth_mm=float(coefficients[0]),
        depth_given=depth_mm is not None,
    )


def reference_targets(observations: Sequence[Any]) -> list[dict[str, Any]]:
    """Per observation (:class:`usdeform.gap.observations.Observation`) with a reflector fixed in the world asked
    for: ``recording``, ``found``, and the speed of sound
    its image motion gives (``sound_speed_m_s``, ``sound_speed_uncertainty_m_s``) with the reflector's displayed depth
    below the unloaded surface (``reflector_depth_mm``), or the ``note`` saying why it was not found."""
    targets: list[dict[str, Any]] = []
    for observation in observations:
        track = observation.reference
        if track is not None:
            speed = sound_speed_m_s(track.ratio)
            targets.append(
                {
                    "recording": observation.name,
                    "found": True,
                    "sound_speed_m_s": speed,
                    "sound_speed_uncertainty_m_s": speed * track.ratio_error / track.ratio,
                    "reflector_depth_mm": track.world_depth_mm,
                }
            )
        elif observation.reference_note:
            targets.append({"recording": observation.name, "found": False, "note": observation.reference_note})
    return targets


def reference_sentence(targets: list[dict[str, Any]]) -> str:
    """The reference targets whose reflector was not found ("" when none)."""
    missed = [Path(target["recording"]).name for target in targets if not target["found"]]
    if not missed:
        return ""
    return (
        f" No reflector fixed in the world was found in {', '.join(missed)}: used as plain palpations, they cannot "
        "show the speed of sound."
    )
