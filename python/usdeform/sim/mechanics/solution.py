"""Solutions: the stored P2 displacement fields evaluated anywhere, and the cached solve."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree
from skfem import Basis, ElementTriP2, MeshTri

from ..._files import atomic_output, mark_used, prune_cache
from ...errors import InputError
from .fem import _solve_uncached
from .section import SectionSpec

_MAX_INVERSE_ITERATIONS = 20
MAX_INDENTATION_FRACTION = 0.4
"""The deepest probe displacement a section is solved to, as a fraction of its depth."""


# ----------------------------------------------------------------------------------------------
# Solutions: evaluation of the stored P2 displacement fields


def _barycentric(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (m, 3) of ``points`` (m, 2) in triangles ``corners`` (m, 3, 2)."""
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    rel = points - corners[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    l1 = (rel[:, 0] * e2[:, 1] - rel[:, 1] * e2[:, 0]) / det
    l2 = (e1[:, 0] * rel[:, 1] - e1[:, 1] * rel[:, 0]) / det
    return np.column_stack([1 - l1 - l2, l1, l2])


class _TriangleLocator:
    """Finds the triangle of a linear mesh that contains each query point.

    The answers to the last ``_REMEMBERED`` distinct queries are kept: a field is evaluated at the same points
    for several lambda steps (a grid sampled step by step, with the lumen's wall between), and locating them is
    most of an evaluation's time.
    """

    _INSIDE_TOLERANCE = 1e-7
    _REMEMBERED = 4

    def __init__(self, nodes: np.ndarray, elements: np.ndarray):
        self.nodes, self.elements = nodes, elements  # (n, 2), (n_elements, 3)
        self.tree = cKDTree(nodes[elements].mean(axis=1))
        self._answers: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...] = ()  # (points, found, bary), newest last

    def locate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(element index or -1 when outside, barycentric coordinates (m, 3)) of each point (read-only arrays)."""
        answers = self._answers  # replaced whole, never changed in place: a reader sees one consistent tuple
        for query, found, coordinates in answers:
            if np.array_equal(query, points):
                return found, coordinates
        found, coordinates = self._locate(points)
        found.flags.writeable = coordinates.flags.writeable = False
        self._answers = (*answers[1 - self._REMEMBERED :], (np.array(points, copy=True), found, coordinates))
        return found, coordinates

    def _locate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        found = np.full(len(points), -1)
        coordinates = np.zeros((len(points), 3))
        pending = np.arange(len(points))
        for n_candidates in (8, 48, 256):
            if len(pending) == 0:
                break
            n_candidates = min(n_candidates, len(self.elements))
            _, candidates = self.tree.query(points[pending], n_candidates)
            candidates = candidates.reshape(len(pending), n_candidates)
            bary = _barycentric(
                np.repeat(points[pending], n_candidates, axis=0), self.nodes[self.elements[candidates.ravel()]]
            ).reshape(len(pending), n_candidates, 3)
            best = bary.min(axis=2).argmax(axis=1)
            best_bary = bary[np.arange(len(pending)), best]
            inside = best_bary.min(axis=1) >= -self._INSIDE_TOLERANCE
            found[pending[inside]] = candidates[np.arange(len(pending)), best][inside]
            coordinates[pending[inside]] = np.clip(best_bary[inside], 0.0, 1.0)
            pending = pending[~inside]
        return found, coordinates


class _FieldHistory:
    """One finite-element solve: the reference mesh and the P2 displacement at every lambda step."""

    def __init__(self, nodes: np.ndarray, elements: np.ndarray, displacement_dofs: np.ndarray):
        mesh = MeshTri(nodes, elements)
        scalar_basis = Basis(mesh, ElementTriP2(), intorder=1)
        self.nodes = nodes.T.copy()  # (n_nodes, 2)
        self.elements = elements.T.copy()  # (n_elements, 3)
        self.element_dofs = scalar_basis.element_dofs.T.copy()  # (n_elements, 6) scalar P2 dofs
        # Barycentric position of each element dof (0, 1/2 or 1 per coordinate) selects its shape function.
        corners = self.nodes[self.elements]
        dof_points = scalar_basis.doflocs.T[self.element_dofs]  # (n_elements, 6, 2)
        self.dof_barycentric = (
            np.round(2 * _barycentric(dof_points.reshape(-1, 2), np.repeat(corners, 6, axis=0))).reshape(-1, 6, 3) / 2
        )
        # Vector dofs are interleaved (x, z) per scalar dof: (n_steps, n_scalar_dofs, 2).
        self.history = displacement_dofs.reshape(len(displacement_dofs), -1, 2)
        self.locator = _TriangleLocator(self.nodes, self.elements)

    def shape_values(self, elements: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """P2 shape function values (m, 6) at barycentric coordinates ``bary`` (m, 3)."""
        nodes = self.dof_barycentric[elements]  # (m, 6, 3)
        lam = bary[:, None, :]
        factor = np.where(nodes == 1.0, lam * (2 * lam - 1), np.where(nodes == 0.5, 2 * lam, 1.0))
        return factor.prod(axis=2)

    def vertex_displacement(self, step_weights: dict[int, float]) -> np.ndarray:
        """Displacement (n_nodes, 2) of the mesh vertices (the first scalar dofs are the vertices)."""
        return sum(weight * self.history[step][: len(self.nodes)] for step, weight in step_weights.items())


def _check_points(points_mm: np.ndarray, name: str = "points_mm") -> np.ndarray:
    points = np.asarray(points_mm, dtype=float)
    if points.ndim != 2 or points.shape[1] != 2:
        raise InputError(f"{name} must have shape (m, 2) (x lateral, z depth; mm), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise InputError(f"{name} must be finite")
    return points


class MechanicsSolution:
    """Solved (or blended / scaled) displacement fields and contact forces of one section.

    ``probe_displacement_mm`` (n_steps,) starts at 0 and increases; ``force_n`` (n_steps,) is the
    contact force in N (compression positive). Displacements are evaluated at points of the
    reference (undeformed) section frame: x lateral mm (0 at the probe centre), z depth mm (0 at
    the undeformed surface, positive down); between solved steps they are linear in lambda.
    ``newton_iterations`` (n_steps,) counts the Newton iterations of each step of a direct solve as full
    Newton counts them (see ``fem._SectionProblem._newton``; None for blends of several solves).
    """

    def __init__(
        self,
        spec: SectionSpec,
        probe_displacement_mm: np.ndarray,
        force_n: np.ndarray,
        fields: Sequence[tuple[_FieldHistory, float]],
        newton_iterations: np.ndarray | None = None,
    ):
        self.spec = spec
        self.probe_displacement_mm = np.array(probe_displacement_mm, dtype=float)
        self.force_n = np.array(force_n, dtype=float)
        self.probe_displacement_mm.setflags(write=False)
        self.force_n.setflags(write=False)
        self.newton_iterations = newton_iterations
        self._fields = tuple(fields)

    # -- derived solutions -----------------------------------------------------------------

    def scaled(self, factor: float) -> MechanicsSolution:
        """The solution of ``spec.scaled(factor)``: same displacements, ``factor`` times the force."""
        return MechanicsSolution(
            self.spec.scaled(factor),
            self.probe_displacement_mm,
            self.force_n * factor,
            self._fields,
            self.newton_iterations,
        )

    @staticmethod
    def blend(solutions: Sequence[MechanicsSolution], weights: Sequence[float], spec: SectionSpec) -> MechanicsSolution:
        """Weighted mean of solutions on the same lambda steps (fields and forces), labelled ``spec``.

        An approximation for a section whose vessel lies between those of the blended solutions.
        """
        weight_array = np.asarray(weights, dtype=float)
        if (
            len(solutions) != len(weight_array)
            or len(solutions) == 0
            or np.any(weight_array < 0)
            or not np.isclose(weight_array.sum(), 1)
        ):
            raise InputError("blend needs one non-negative weight per solution, summing to 1")
        steps = solutions[0].probe_displacement_mm
        if any(not np.array_equal(s.probe_displacement_mm, steps) for s in solutions):
            raise InputError("blended solutions must share their lambda steps")
        used = [(s, float(w)) for s, w in zip(solutions, weight_array, strict=True) if w > 0]
        fields = [(field, w * fw) for s, w in used for field, fw in s._fields]
        force = np.sum([w * s.force_n for s, w in used], axis=0)
        return MechanicsSolution(spec, steps, force, fields, used[0][0].newton_iterations if len(used) == 1 else None)

    # -- lambda and force --------------------------------------------------------------------

    def _step_weights(self, probe_displacement_mm: float) -> dict[int, float]:
        lam = float(probe_displacement_mm)
        steps = self.probe_displacement_mm
        if not (np.isfinite(lam) and steps[0] <= lam <= steps[-1] * (1 + 1e-12)):
            raise InputError(f"probe displacement {lam} mm is outside the solved range [{steps[0]}, {steps[-1]}] mm")
        upper = int(np.clip(np.searchsorted(steps, lam, side="right"), 1, len(steps) - 1))
        fraction = min(1.0, (lam - steps[upper - 1]) / (steps[upper] - steps[upper - 1]))
        return {upper - 1: 1.0 - fraction, upper: fraction}

    def force_at(self, probe_displacement_mm):
        """Contact force (N) at probe displacement(s) lambda (mm), piecewise linear between steps."""
        lam = np.asarray(probe_displacement_mm, dtype=float)
        if np.any(~np.isfinite(lam)) or np.any(lam < 0) or np.any(lam > self.probe_displacement_mm[-1] * (1 + 1e-12)):
            raise InputError(f"probe displacement outside the solved range [0, {self.probe_displacement_mm[-1]}] mm")
        return np.interp(lam, self.probe_displacement_mm, self.force_n)

    def probe_displacement_at_force(self, force_n):
        """Probe displacement (mm) at contact force(s) (N): the inverse of :meth:`force_at`."""
        force = np.asarray(force_n, dtype=float)
        if np.any(np.diff(self.force_n) <= 0):
            raise InputError("the force is not strictly increasing in lambda, so it cannot be inverted")
        if np.any(~np.isfinite(force)) or np.any(force < self.force_n[0]) or np.any(force > self.force_n[-1]):
            raise InputError(f"force outside the solved range [{self.force_n[0]:.4g}, {self.force_n[-1]:.4g}] N")
        return np.interp(force, self.force_n, self.probe_displacement_mm)

    # -- fields --------------------------------------------------------------------------------

    def _evaluate(self, points: np.ndarray, step_weights: dict[int, float]) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (m, 2; NaN outside) and the element of the first solve holding each point (-1 outside)."""
        result = np.zeros_like(points)
        first_elements = np.full(len(points), -1)
        for index, (field, field_weight) in enumerate(self._fields):
            elements, bary = field.locator.locate(points)
            inside = elements >= 0
            result[~inside] = np.nan
            if index == 0:
                first_elements = elements
            shape = field.shape_values(elements[inside], bary[inside])  # (m, 6)
            dofs = field.element_dofs[elements[inside]]  # (m, 6)
            for step, weight in step_weights.items():
                if weight:
                    result[inside] += field_weight * weight * np.einsum("mk,mkc->mc", shape, field.history[step][dofs])
        return result, first_elements

    def displacement(
        self, points_mm: np.ndarray, probe_displacement_mm: float, outside: Literal["raise", "nan"] = "raise"
    ) -> np.ndarray:
        """Displacement (m, 2) in mm of reference points (m, 2) at probe displacement lambda (mm).

        Points outside the section raise :class:`InputError` (``outside="raise"``) or get NaN.
        """
        points = _check_points(points_mm)
        result, _ = self._evaluate(points, self._step_weights(probe_displacement_mm))
        missing = np.isnan(result[:, 0])
        if outside == "raise" and np.any(missing):
            raise InputError(
                f"{missing.sum()} of {len(points)} points lie outside the section (x in [{-self.spec.width_mm / 2}, "
                f"{self.spec.width_mm / 2}], z in [0, {self.spec.depth_mm}] mm), first: {points[missing][0].tolist()}"
            )
        return result

    def deformed_position_inverse(
        self, points_mm: np.ndarray, probe_displacement_mm: float, outside: Literal["raise", "nan"] = "nan"
    ) -> np.ndarray:
        """Reference positions (m, 2), mm, of material points found at ``points_mm`` after pressing.

        Solves X + u(X) = x (to 1e-6 mm) by Newton's method from the deformed-mesh estimate, with
        the piecewise-linear deformation gradient of the mesh as Jacobian. Points outside the
        deformed section get NaN (default; e.g. image pixels above the tissue) or raise. For a
        blend, the estimate and the Jacobian come from the first blended solve (quasi-Newton).
        """
        points = _check_points(points_mm)
        step_weights = self._step_weights(probe_displacement_mm)
        field = self._fields[0][0]
        vertex_displacement = field.vertex_displacement(step_weights)
        deformed = _TriangleLocator(field.nodes + vertex_displacement, field.elements)
        deformed_elements, bary = deformed.locate(points)
        missing = deformed_elements < 0
        if np.any(missing) and outside == "raise":
            raise InputError(f"{missing.sum()} of {len(points)} points lie outside the deformed section")
        reference = np.full_like(points, np.nan)
        active = np.flatnonzero(~missing)
        reference[active] = np.einsum(
            "mk,mkc->mc", bary[active], field.nodes[field.elements[deformed_elements[active]]]
        )
        low, high = np.array([-self.spec.width_mm / 2, 0.0]), np.array([self.spec.width_mm / 2, self.spec.depth_mm])
        for _ in range(_MAX_INVERSE_ITERATIONS):
            displacement, elements = self._evaluate(reference[active], step_weights)
            residual = np.nan_to_num(points[active] - reference[active] - displacement)
            unconverged = np.abs(residual).max(axis=1) >= 1e-6
            active, residual, elements = active[unconverged], residual[unconverged], elements[unconverged]
            if len(active) == 0:
                break
            elements = np.where(elements < 0, deformed_elements[active], elements)
            ref_corners = field.nodes[field.elements[elements]]
            def_corners = ref_corners + vertex_displacement[field.elements[elements]]
            dX = np.stack([ref_corners[:, 1] - ref_corners[:, 0], ref_corners[:, 2] - ref_corners[:, 0]], axis=2)
            dx = np.stack([def_corners[:, 1] - def_corners[:, 0], def_corners[:, 2] - def_corners[:, 0]], axis=2)
            step = np.linalg.solve(dx @ np.linalg.inv(dX), residual[..., None])[..., 0]
            reference[active] = np.clip(reference[active] + step, low, high)
        return reference

    def lumen_boundary(self, probe_displacement_mm: float, n_points: int = 128, vessel: int = 0) -> np.ndarray:
        """Deformed lumen wall (n_points, 2), mm: the reference circle of lumen ``vessel`` of ``spec`` (0: the main
        vessel, then its ``extra_vessels``) moved by the field."""
        if int(n_points) < 3:
            raise InputError(f"n_points must be at least 3, got {n_points}")
        centre_x, centre_depth, radius, _ = self.spec.lumens[vessel]
        angles = 2 * np.pi * np.arange(int(n_points)) / int(n_points)
        circle = np.column_stack([centre_x + radius * np.cos(angles), centre_depth + radius * np.sin(angles)])
        return circle + self.displacement(circle, probe_displacement_mm)

    def lumen_area_mm2(self, probe_displacement_mm: float, n_points: int = 256, vessel: int = 0) -> float:
        """Area (mm^2) enclosed by the deformed wall of lumen ``vessel``."""
        x, z = self.lumen_boundary(probe_displacement_mm, n_points, vessel).T
        return float(0.5 * abs(np.dot(x, np.roll(z, -1)) - np.dot(z, np.roll(x, -1))))


# ----------------------------------------------------------------------------------------------
# Solving with an on-disk cache


def cache_dir() -> Path:
    """Directory of cached mechanics solutions: ``$USDEFORM_CACHE_DIR`` or ``~/.cache/usdeform``, ``/mechanics``; it
    holds at most ``$USDEFORM_CACHE_MAX_MB``, the least recently used solutions removed first
    (:func:`usdeform._files.prune_cache`)."""
    root = os.environ.get("USDEFORM_CACHE_DIR") or Path.home() / ".cache" / "usdeform"
    return Path(root) / "mechanics"


def _check_probe_displacements(probe_displacement_mm: np.ndarray, spec: SectionSpec) -> np.ndarray:
    lam = np.asarray(probe_displacement_mm, dtype=float)
    if lam.ndim != 1 or len(lam) < 2:
        raise InputError(f"probe_displacement_mm must be 1-D with at least 2 steps, got shape {lam.shape}")
    if not np.all(np.isfinite(lam)) or lam[0] != 0.0 or np.any(np.diff(lam) <= 0):
        raise InputError("probe_displacement_mm must start at 0 and increase strictly (mm)")
    if lam[-1] > MAX_INDENTATION_FRACTION * spec.depth_mm:
        raise InputError(
            f"probe displacement {lam[-1]} mm exceeds {100 * MAX_INDENTATION_FRACTION:g} % of the section depth "
            f"{spec.depth_mm} mm"
        )
    return lam


def _write_atomically(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` to ``path`` (.npz) with the package's atomic writer: readers never see a partial file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as handle:
        np.savez(handle, **arrays)  # type: ignore[arg-type]  # numpy's stub mistypes **kwds


_MAX_SOLUTIONS_IN_MEMORY = 32
_loaded_solutions: dict[tuple[Path, str], MechanicsSolution] = {}  # solutions loaded in this process


def solution_is_cached(spec: SectionSpec, probe_displacement_mm: np.ndarray) -> bool:
    """Whether :func:`solve_section` of ``spec`` at these steps would read the cache rather than solve."""
    key = spec.cache_key(_check_probe_displacements(probe_displacement_mm, spec))
    path = cache_dir() / f"{key}.npz"
    return (path, key) in _loaded_solutions or path.exists()


def solve_section(spec: SectionSpec, probe_displacement_mm: np.ndarray, *, use_cache: bool = True) -> MechanicsSolution:
    """Solve the section at the lambda steps ``probe_displacement_mm`` (mm, from 0, increasing).

    Results are cached on disk (see :func:`cache_dir`), keyed by a hash of every parameter, and
    the last few loaded solutions in memory (treat their arrays as read-only).
    Raises :class:`InputError` for bad steps, :class:`MechanicsConvergenceError` if Newton fails.
    """
    if not isinstance(spec, SectionSpec):
        raise InputError(f"spec must be a SectionSpec, got {type(spec).__name__}")
    lam = _check_probe_displacements(probe_displacement_mm, spec)
    key = spec.cache_key(lam)
    path = cache_dir() / f"{key}.npz"
    if use_cache and (path, key) in _loaded_solutions:
        return _loaded_solutions[(path, key)]
    arrays = None
    if use_cache and path.exists():
        try:
            with np.load(path) as stored:
                arrays = {name: stored[name] for name in stored.files}
            mark_used(path)
        except (OSError, ValueError, KeyError):
            arrays = None  # unreadable cache entry: solve again and overwrite it
    if arrays is None:
        arrays = _solve_uncached(spec, lam)
        if use_cache:
            _write_atomically(path, arrays)
            prune_cache(path.parent, keep=path)
    field = _FieldHistory(arrays["nodes"], arrays["elements"], arrays["displacement_dofs"])
    solution = MechanicsSolution(spec, lam, arrays["force_n"], [(field, 1.0)], arrays["newton_iterations"])
    if use_cache:
        if len(_loaded_solutions) >= _MAX_SOLUTIONS_IN_MEMORY:
            _loaded_solutions.pop(next(iter(_loaded_solutions)))
        _loaded_solutions[(path, key)] = solution
    return solution
