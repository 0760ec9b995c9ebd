"""Measured displacements (:class:`Observations`) and the samples a fit is made of.

A fit's loss is a sum over its samples (a tracked point at a frame); they are kept per palpation,
point and frame (:class:`_Palpation`), never as a design matrix, and give the normal equations
directly.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..options import Coupling, Integration
from ._basis import VESSEL_KNOT_SPACING_RADII, VESSEL_WINDOW_RADII, VesselAnchor, _second_differences, vessel_basis
from ._model import N_INTERVALS, Normalization, force_terms
from ._stiffness_profile import StiffnessProfile


@dataclass(frozen=True, eq=False)
class Observations:
    """Measured displacements of one palpation, from its reference (lowest-force) frame.

    ``points_px`` (N, 2) are the tracked points' (x, y) in the reference frame; ``displacements_px``
    (M, N, 2) their (lateral, axial) displacement to each of M frames, trusted where ``valid`` (M, N);
    ``forces_n`` (M,) the frames' forces and ``reference_force_n`` the reference frame's (N);
    ``profile`` the palpation's stiffness profile; ``frame_shape`` ``(rows, cols)`` of the frames the
    points were tracked on (None: not known; :func:`fit_regression` then needs it); ``vessel`` the
    lumen in the reference frame (None: none seen), which a vessel-anchored fit places its window on;
    ``other_vessels`` the further lumens of that frame (a vein beside the artery), left to right, each
    with a vessel part of its own in a vessel-anchored fit.
    """

    points_px: np.ndarray
    displacements_px: np.ndarray
    valid: np.ndarray
    forces_n: np.ndarray
    reference_force_n: float
    profile: StiffnessProfile
    frame_shape: tuple[int, int] | None = None
    vessel: VesselAnchor | None = None
    other_vessels: tuple[VesselAnchor, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "other_vessels", tuple(self.other_vessels))
        if self.other_vessels and self.vessel is None:
            raise InputError("other_vessels: further lumens need the main one (vessel)")
        for index, lumen in enumerate(self.other_vessels):
            if not isinstance(lumen, VesselAnchor):
                raise InputError(f"other_vessels[{index}]: expected a VesselAnchor, got {type(lumen).__name__}")
        points = np.asarray(self.points_px, dtype=np.float64)
        displacements = np.asarray(self.displacements_px, dtype=np.float64)
        valid = np.asarray(self.valid, dtype=bool)
        forces = np.asarray(self.forces_n, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2:
            raise InputError(f"points_px: expected shape (n_points, 2), got {points.shape}")
        expected = (forces.shape[0], points.shape[0], 2) if forces.ndim == 1 else None
        if expected is None or displacements.shape != expected or valid.shape != expected[:2]:
            raise InputError(
                f"displacements_px, valid, forces_n: expected shapes (M, N, 2), (M, N), (M,) with "
                f"N = {points.shape[0]} points, got {displacements.shape}, {valid.shape}, {forces.shape}"
            )
        if not np.all(np.isfinite(displacements[valid])) or not np.all(np.isfinite(forces)):
            raise InputError("displacements_px, forces_n: non-finite values where valid")
        if not np.isfinite(self.reference_force_n):
            raise InputError(f"reference_force_n: expected a finite force, got {self.reference_force_n}")
        if self.frame_shape is not None:
            if len(self.frame_shape) != 2 or min(self.frame_shape) < 1:
                raise InputError(f"frame_shape: expected (rows, cols) of at least one pixel, got {self.frame_shape!r}")
            object.__setattr__(self, "frame_shape", (int(self.frame_shape[0]), int(self.frame_shape[1])))
        for name, value in (
            ("points_px", points),
            ("displacements_px", displacements),
            ("valid", valid),
            ("forces_n", forces),
        ):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "reference_force_n", float(self.reference_force_n))


def _normalization_for(
    observations: Sequence[Observations], frame_shape: tuple[int, int], coupling: Coupling, integration: Integration
) -> Normalization:
    """Scales mapping the data onto [0, 1]: pixel coordinates, force, h (and lambda when integrating
    over it) and each displacement component."""
    max_force = max(float(np.max(np.abs(o.forces_n))) for o in observations)
    max_h = 0.0
    for o in observations:
        profile = o.profile if coupling == "stiffness" else StiffnessProfile.UNIT
        lam = profile.lambda_at(o.forces_n)
        max_h = max(max_h, float(np.max(np.abs(o.forces_n) / profile.stiffness_at(lam))))
        if integration == "displacement":
            max_h = max(max_h, float(np.max(np.abs(lam - profile.lambda_at(0.0)))))
    measured = np.concatenate([o.displacements_px[o.valid] for o in observations])
    lateral, axial = (float(np.max(np.abs(measured[:, c]))) if measured.size else 1.0 for c in (0, 1))
    rows, cols = frame_shape
    return Normalization.for_frames(rows, cols, max_force or 1.0, max_h or 1.0, lateral or 1.0, axial or 1.0)


SpatialVector = Callable[[np.ndarray, np.ndarray, tuple[float, float, float]], np.ndarray]


@dataclass(frozen=True)
class _Palpation:
    """One palpation's samples, kept per tracked point and per frame (the design matrix is never
    held: a sample's row has ``integrals[f, t] * spatial[t][p]`` in the columns ``columns[t]``,
    summed over the force terms t).

    ``spatial`` (3 arrays, (n_points, len(columns[t]))): each point's terms for the force integrals
    (1, 0, 0), (0, 1, 0), (0, 0, 1) in the ``columns`` of the ``n_terms`` each term touches (a
    third of them for the B-spline basis); ``integrals`` (n_frames, 3) each frame's force integrals
    from the reference force; ``targets`` (n_frames, n_points, 2) the normalised displacements (0
    where not valid); ``valid`` (n_frames, n_points); ``positions`` (n_points, 2) the points'
    normalised reference positions. Each row and target is weighted by ``row_scale / row_divisor``
    (the palpation's weight in the loss is its square); the two are kept apart because the design
    rows are multiplied by their ratio and the targets by one and divided by the other, a rounding
    that ADAM's iterates amplify."""

    spatial: tuple[np.ndarray, ...]
    columns: tuple[np.ndarray, ...]
    n_terms: int
    integrals: np.ndarray
    targets: np.ndarray
    valid: np.ndarray
    positions: np.ndarray
    row_scale: float = 1.0
    row_divisor: float = 1.0

    @property
    def weight(self) -> float:
        """The weight of this palpation's squared errors in the loss."""
        return (self.row_scale / self.row_divisor) ** 2

    def design(self) -> tuple[np.ndarray, np.ndarray]:
        """The dense weighted design rows and targets of the valid samples (frame by frame):
        (n_samples, n_terms) and (n_samples, 2)."""
        frames, points = np.nonzero(self.valid)
        design = np.zeros((len(frames), self.n_terms))
        for t in range(3):
            design[:, self.columns[t]] += self.integrals[frames, t, None] * self.spatial[t][points]
        # The rows times the ratio, the targets times row_scale and then divided by row_divisor (see above).
        factor = self.row_scale / self.row_divisor
        return design * factor, self.targets[self.valid] * self.row_scale / self.row_divisor

    def normal_equations(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """``A^T A``, ``A^T b`` and ``b^T b`` of the samples of ``points`` (a boolean mask), from each
        point's sums over its frames: a row is a point's spatial terms weighted by the frame's force
        integrals, so ``A^T A = sum_p sum_tu S_tu[p] spatial[t][p]^T spatial[u][p]`` with
        ``S_tu[p]`` the sum over the point's valid frames of ``integrals[f, t] integrals[f, u]``:
        O(points x terms^2) instead of O(samples x terms^2) and no design matrix."""
        valid = self.valid[:, points].astype(np.float64)
        targets = self.targets[:, points]
        products = valid.T @ (self.integrals[:, :, None] * self.integrals[:, None, :]).reshape(-1, 9)
        moments = np.einsum("ft,fpc->ptc", self.integrals, targets)
        gram, moment = np.zeros((self.n_terms, self.n_terms)), np.zeros((self.n_terms, 2))
        spatial = [terms[points] for terms in self.spatial]
        for t in range(3):
            moment[self.columns[t]] += spatial[t].T @ moments[:, t]
            for u in range(t, 3):
                block = spatial[t].T @ (products[:, 3 * t + u, None] * spatial[u])
                gram[np.ix_(self.columns[t], self.columns[u])] += block
                if u != t:
                    gram[np.ix_(self.columns[u], self.columns[t])] += block.T
        return gram * self.weight, moment * self.weight, float(np.sum(targets**2)) * self.weight

    def squared_error(self, coefficients: np.ndarray) -> float:
        """The weighted ``sum((A K^T - b)^2)`` over the valid samples, from each point's prediction
        per force term."""
        predicted = sum(
            self.integrals[:, t, None, None] * (self.spatial[t] @ coefficients[:, self.columns[t]].T) for t in range(3)
        )
        return float(np.sum(((predicted - self.targets) * self.valid[:, :, None]) ** 2)) * self.weight


@dataclass(frozen=True)
class _Samples:
    """The weighted samples of a fit: its palpations (tracks and wall), with the samples counted."""

    palpations: tuple[_Palpation, ...]
    n_samples: int

    @classmethod
    def weighted(cls, tracked: Sequence[_Palpation], wall: Sequence[_Palpation], wall_weight: float) -> _Samples:
        """Tracked and wall samples weighted so that the squared error sums to the tracks' mean plus
        ``wall_weight`` times the wall's mean."""
        n_tracked, n_wall = (sum(int(p.valid.sum()) for p in group) for group in (tracked, wall))
        return cls(
            tuple(dataclasses.replace(p, row_divisor=np.sqrt(max(n_tracked, 1))) for p in tracked)
            + (tuple(dataclasses.replace(p, row_scale=np.sqrt(wall_weight / n_wall)) for p in wall) if n_wall else ()),
            n_tracked + n_wall,
        )

    @property
    def sampled_points(self) -> list[np.ndarray]:
        """Per palpation, which points have at least one valid sample."""
        return [np.any(p.valid, axis=0) for p in self.palpations]

    def design(self) -> tuple[np.ndarray, np.ndarray]:
        """The dense weighted design matrix and targets (rows frame by frame, palpation by palpation)."""
        parts = [p.design() for p in self.palpations]
        return np.concatenate([design for design, _ in parts]), np.concatenate([targets for _, targets in parts])

    def normal_equations(self, points: Sequence[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, float]:
        """``A^T A``, ``A^T b``, ``b^T b`` of the weighted samples (of ``points``, one mask per palpation)."""
        points = self.sampled_points if points is None else points
        n_terms = self.palpations[0].n_terms
        gram, moment, energy = np.zeros((n_terms, n_terms)), np.zeros((n_terms, 2)), 0.0
        for palpation, mask in zip(self.palpations, points, strict=True):
            part = palpation.normal_equations(mask)
            gram, moment, energy = gram + part[0], moment + part[1], energy + part[2]
        return gram, moment, energy

    def squared_error(self, coefficients: np.ndarray) -> float:
        """The weighted squared error ``sum((A K^T - b)^2)`` of ``coefficients`` (2, n_terms)."""
        return sum(p.squared_error(coefficients) for p in self.palpations)


@dataclass(frozen=True)
class _VesselPart:
    """The vessel-anchored terms of a fit: windows of ``n_functions`` clamped cubic B-splines per axis
    (the inner ones free) on each palpation's lumen, scaled from ``reference``'s radius."""

    reference: VesselAnchor
    n_functions: int
    window_radii: float = VESSEL_WINDOW_RADII
    slot: int = 0

    @property
    def n_inner(self) -> int:
        """Free functions per axis."""
        return self.n_functions - 4

    def terms(self, observations: Observations) -> np.ndarray:
        """(n_points, n_inner^2) spatial terms at the observations' points; zero without a lumen."""
        lumen = _lumen_of(observations, self.slot)
        if lumen is None:
            return np.zeros((len(observations.points_px), self.n_inner**2))
        x, y = observations.points_px[:, 0], observations.points_px[:, 1]
        spatial = vessel_basis(x, y, lumen, self.reference.radius_px, self.n_functions, self.window_radii)
        return spatial.T

    def roughness(self) -> np.ndarray:
        """``R^T R`` of the second differences of each force term's window grid, its outer two rings
        held at zero (the part vanishes at the window's edge), over the inner coefficients (read-only)."""
        return _window_roughness(self.n_functions)

    @classmethod
    def for_lumens(cls, lumens: Sequence[VesselAnchor], slot: int = 0) -> _VesselPart:
        """The part of vessel ``slot`` for the palpations' lumens of it: their mean as reference; knots
        :data:`VESSEL_KNOT_SPACING_RADII` apart over a window of :data:`VESSEL_WINDOW_RADII`."""
        centres = np.array([lumen.centre_px for lumen in lumens])
        reference = VesselAnchor(tuple(centres.mean(axis=0)), float(np.mean([lumen.radius_px for lumen in lumens])))
        return cls(reference, round(2 * VESSEL_WINDOW_RADII / VESSEL_KNOT_SPACING_RADII) + 3, slot=slot)

    @classmethod
    def for_observations(cls, observations: Sequence[Observations]) -> list[_VesselPart]:
        """One part per vessel the observations show: the main lumen's, then one per further lumen
        (``other_vessels``, matched by their order); none where no observations show a lumen."""
        parts = []
        for slot in range(1 + max((len(o.other_vessels) for o in observations), default=0)):
            lumens = [lumen for o in observations if (lumen := _lumen_of(o, slot)) is not None]
            if lumens:
                parts.append(cls.for_lumens(lumens, slot))
        return parts


def _lumen_of(observations: Observations, slot: int) -> VesselAnchor | None:
    """The observations' lumen of vessel ``slot``: ``vessel`` for 0, else ``other_vessels[slot - 1]``; None: unseen."""
    if slot == 0:
        return observations.vessel
    others = observations.other_vessels
    return others[slot - 1] if slot <= len(others) else None


@functools.cache
def _window_roughness(n_functions: int) -> np.ndarray:
    """:meth:`_VesselPart.roughness` of a window of ``n_functions`` per axis (read-only, computed once
    per window; its entries are small integers, exact whatever the BLAS)."""
    inner = np.arange(2, n_functions - 2)
    kept = (inner[:, None] * n_functions + inner[None, :]).ravel()
    penalty = _second_differences((n_functions, n_functions))
    columns = np.concatenate([term * n_functions**2 + kept for term in range(3)])
    restricted = penalty[:, columns]
    roughness = restricted.T @ restricted
    roughness.setflags(write=False)
    return roughness


def _samples(
    observations: Sequence[Observations],
    normalization: Normalization,
    coupling: Coupling,
    integration: Integration,
    spatial_vector: SpatialVector,
    n_terms: int,
    vessels: Sequence[_VesselPart] = (),
) -> list[_Palpation]:
    """Each palpation's samples (unweighted), so that the loss of K (2, n_terms) is the mean over the
    valid samples of ``sum((A @ K.T - b)^2)`` with a sample's row A the integrated
    ``spatial_vector`` at the frame's force minus that at the reference force (displacements are
    measured from the reference frame) and b its normalised displacement. With ``vessels`` the row
    goes on with each vessel part's terms at the palpation's own lumen of it (zero without one)."""
    palpations = []
    for o in observations:
        profile = o.profile if coupling == "stiffness" else StiffnessProfile.UNIT
        x_n = o.points_px[:, 0] / normalization.x_scale
        y_n = o.points_px[:, 1] / normalization.y_scale
        # The terms are linear in the force integrals (1, h, h^2): evaluate the basis once per term.
        units = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        terms = [spatial_vector(x_n, y_n, unit).T for unit in units]
        for vessel in vessels:
            local = vessel.terms(o)
            terms = [np.hstack([term, np.kron(unit, local)]) for term, unit in zip(terms, units, strict=True)]
        columns = tuple(np.flatnonzero(np.any(term != 0, axis=0)) for term in terms)
        spatial = tuple(term[:, used] for term, used in zip(terms, columns, strict=True))
        reference = np.array(force_terms(o.reference_force_n, profile, normalization, N_INTERVALS, integration))
        integrals = np.array(
            [force_terms(force, profile, normalization, N_INTERVALS, integration) for force in o.forces_n]
        ).reshape(-1, 3)
        scales = [normalization.lateral_scale, normalization.axial_scale]
        targets = np.where(o.valid[:, :, None], o.displacements_px / scales, 0.0)
        palpations.append(
            _Palpation(
                spatial, columns, n_terms, integrals - reference, targets, o.valid.copy(), np.column_stack([x_n, y_n])
            )
        )
    return palpations
