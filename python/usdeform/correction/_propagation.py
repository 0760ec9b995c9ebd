"""Propagation: the fitted model at other positions and tissues (paper eqs. 12-14).

The regression couples force and tissue only through ``h = F / k``, so a model fitted at one
sampling position is carried to another position, or another tissue, by giving it that place's
stiffness profile (eq. 12). Along a sweep, positions between the sampled ones get a stiffness
profile mixed from the sampled profiles with the paper's normalised inverse-distance weights
(eqs. 13-14); a position that coincides with a sampled one takes that profile exactly.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..regression import StiffnessProfile, VesselAnchor

__all__ = [
    "SampledProfiles",
    "interpolate_profile",
    "inverse_distance_weights",
    "probe_surface_positions",
    "profiles_along_sweep",
]


def _positions(name: str, positions: np.ndarray) -> np.ndarray:
    array = np.asarray(positions, dtype=np.float64)
    array = array[:, np.newaxis] if array.ndim == 1 else array
    if array.ndim != 2 or array.shape[0] == 0:
        raise InputError(
            f"{name}: expected (n,) arc lengths or (n, d) positions in mm, got shape {np.shape(positions)}"
        )
    if not np.all(np.isfinite(array)):
        raise InputError(f"{name}: contains non-finite values")
    return array


def inverse_distance_weights(position_mm: np.ndarray | float, sampled_positions_mm: np.ndarray) -> np.ndarray:
    """Weights of the sampled positions for ``position_mm`` (eq. 14), summing to 1.

    ``w_i`` is proportional to ``(sum_j L_j) / L_i`` with ``L_i`` the distance (mm) to sampled position
    i; if the position coincides with a sampled one, that one gets weight 1 and the others 0.

    Parameters
    ----------
    position_mm : float or ndarray
        An arc length along the sweep, or a (d,) position, mm.
    sampled_positions_mm : ndarray
        (n,) arc lengths or (n, d) positions of the palpations, mm.

    Returns
    -------
    ndarray
        (n,) weights.

    Examples
    --------
    >>> inverse_distance_weights(10.0, np.array([0.0, 40.0])).tolist()
    [0.75, 0.25]
    """
    sampled = _positions("sampled_positions_mm", sampled_positions_mm)
    position = _positions("position_mm", np.atleast_1d(np.asarray(position_mm, dtype=np.float64)).reshape(1, -1))
    if position.shape[1] != sampled.shape[1]:
        raise InputError(f"position_mm: has {position.shape[1]} coordinates, the sampled positions {sampled.shape[1]}")
    distances = np.linalg.norm(sampled - position, axis=1)
    hits = np.flatnonzero(distances == 0.0)
    if hits.size:
        weights = np.zeros(len(sampled))
        weights[hits[0]] = 1.0
        return weights
    raw = distances.sum() / distances
    return raw / raw.sum()


def interpolate_profile(
    position_mm: np.ndarray | float, sampled_positions_mm: np.ndarray, profiles: Sequence[StiffnessProfile]
) -> StiffnessProfile:
    """The stiffness profile at ``position_mm`` (eq. 13): ``k'(lambda) = sum_i w_i k_i(lambda)``.

    Both the stiffness and the force-displacement curve are linear in (c1, c2, c3), so the mixed
    profile has the weighted coefficients.

    Parameters
    ----------
    position_mm : float or ndarray
        Where the profile is wanted, mm (as for :func:`inverse_distance_weights`).
    sampled_positions_mm : ndarray
        The palpated positions, mm.
    profiles : sequence of StiffnessProfile
        One per palpated position.

    Returns
    -------
    StiffnessProfile
    """
    if len(profiles) != len(np.atleast_1d(sampled_positions_mm)):
        raise InputError(
            f"profiles: expected one per sampled position ({len(np.atleast_1d(sampled_positions_mm))}), "
            f"got {len(profiles)}"
        )
    weights = inverse_distance_weights(position_mm, sampled_positions_mm)
    coefficients = weights @ np.array([p.as_tuple() for p in profiles])
    return StiffnessProfile(*coefficients)


def profiles_along_sweep(
    positions_mm: np.ndarray, sampled_positions_mm: np.ndarray, profiles: Sequence[StiffnessProfile]
) -> np.ndarray:
    """Each frame's stiffness profile from the palpated ones (eqs. 13-14).

    Parameters
    ----------
    positions_mm : ndarray
        (n_frames,) arc lengths or (n_frames, d) positions of the frames, mm.
    sampled_positions_mm : ndarray
        The palpated positions, mm, in the same coordinates.
    profiles : sequence of StiffnessProfile
        One per palpated position.

    Returns
    -------
    ndarray
        (n_frames, 3) of ``(c1, c2, c3)``.
    """
    positions = _positions("positions_mm", positions_mm)
    return np.array([interpolate_profile(p, sampled_positions_mm, profiles).as_tuple() for p in positions])


@dataclass(frozen=True, eq=False)
class SampledProfiles:
    """Palpated positions and their stiffness profiles, and the profiles of the frames between them.

    Parameters
    ----------
    positions_mm : ndarray
        (n,) arc lengths along the sweep or (n, d) positions in the base frame, mm.
    profiles : tuple of StiffnessProfile
        One per position.
    lumens : tuple of tuples of VesselAnchor or None, optional
        Per position, the palpation's lumens at contact (its lowest-force frame), vessel by vessel as
        a vessel-anchored model orders its parts (the main vessel, then the further ones; None: that
        vessel not seen there); pixels. What the model was fitted on: a sweep whose lumens lie beyond
        them is corrected by extrapolation (:func:`~usdeform.correction.uncovered_lumens`). None: not
        recorded.

    Examples
    --------
    >>> sampled = SampledProfiles(np.array([0.0, 40.0]), (StiffnessProfile(0, 2, 0), StiffnessProfile(0, 4, 0)))
    >>> sampled.along(np.array([0.0, 10.0])).tolist()
    [[0.0, 2.0, 0.0], [0.0, 2.5, 0.0]]
    """

    positions_mm: np.ndarray
    profiles: tuple[StiffnessProfile, ...]
    lumens: tuple[tuple[VesselAnchor | None, ...], ...] | None = None

    def __post_init__(self) -> None:
        positions = np.array(self.positions_mm, dtype=np.float64)
        profiles = tuple(self.profiles)
        lumens = None if self.lumens is None else tuple(tuple(at) for at in self.lumens)
        if lumens is not None and (
            len(lumens) != len(profiles)
            or any(lumen is not None and not isinstance(lumen, VesselAnchor) for at in lumens for lumen in at)
        ):
            raise InputError(
                f"lumens: expected one tuple of VesselAnchor or None per position ({len(profiles)}), got {len(lumens)}"
            )
        if positions.ndim not in (1, 2) or positions.shape[0] == 0 or 0 in positions.shape:
            raise InputError(f"positions_mm: expected (n,) or (n, d) positions in mm, got shape {positions.shape}")
        if not np.all(np.isfinite(positions)):
            raise InputError("positions_mm: contains non-finite values")
        if len(profiles) != positions.shape[0] or not all(isinstance(p, StiffnessProfile) for p in profiles):
            raise InputError(
                f"profiles: expected one StiffnessProfile per position ({positions.shape[0]}), "
                f"got {len(profiles)} items"
            )
        positions.setflags(write=False)
        object.__setattr__(self, "positions_mm", positions)
        object.__setattr__(self, "profiles", profiles)
        object.__setattr__(self, "lumens", lumens)

    def along(self, positions_mm: np.ndarray) -> np.ndarray:
        """Per-frame ``(c1, c2, c3)``, (n_frames, 3), at ``positions_mm`` by the paper's inverse-distance
        weights (see :func:`profiles_along_sweep`)."""
        return profiles_along_sweep(positions_mm, self.positions_mm, self.profiles)


def probe_surface_positions(probe_to_base: np.ndarray) -> np.ndarray:
    """Probe positions in the base frame without their component along the probe axis, so that how
    deep the probe pressed does not count in the distances of the stiffness weights.

    Parameters
    ----------
    probe_to_base : ndarray
        ``(n, 4, 4)`` probe poses, mm.

    Returns
    -------
    ndarray
        ``(n, 3)`` positions, mm.
    """
    translation, axis = probe_to_base[:, :3, 3], probe_to_base[:, :3, 2]
    axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
    return translation - np.sum(translation * axis, axis=1, keepdims=True) * axis
