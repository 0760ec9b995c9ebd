"""NumPy twins of the FEM mechanics' kernels: the sparse symmetric solve and the element loop."""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from ..errors import InputError


class SymmetricSolver:
    """Twin of ``_core.SymmetricSolver``: the symmetric matrix of a CSC pattern (``indptr``, ``indices``)
    whose lower triangle is read, factorised by SciPy's SuperLU."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray):
        self.indptr, self.indices = np.asarray(indptr, dtype=np.int64), np.asarray(indices, dtype=np.int64)
        self.size = len(self.indptr) - 1

    def solve(self, values: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """x of A x = ``rhs``, A symmetric with the lower-triangle entries of ``values``; InputError if singular."""
        return self.factorize(values).solve(rhs)

    def factorize(self, values: np.ndarray) -> SymmetricFactor:
        """The factor of A, symmetric with the lower-triangle entries of ``values``; InputError if singular."""
        stored = scipy.sparse.csc_matrix((values, self.indices, self.indptr), shape=(self.size, self.size))
        matrix = (scipy.sparse.tril(stored) + scipy.sparse.tril(stored, -1).T).tocsc()
        try:
            return SymmetricFactor(scipy.sparse.linalg.splu(matrix))
        except RuntimeError as singular:  # SuperLU: "Factor is exactly singular"
            raise InputError("values: the matrix is singular") from singular


class SymmetricFactor:
    """Twin of ``_core.SymmetricFactor``: a SuperLU factor of a :class:`SymmetricSolver`'s matrix."""

    def __init__(self, factor: scipy.sparse.linalg.SuperLU):
        self.factor = factor

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """x of A x = ``rhs``; InputError if it is not finite (A numerically singular)."""
        with np.errstate(all="ignore"):
            solution = self.factor.solve(np.asarray(rhs, dtype=np.float64))
        if not np.all(np.isfinite(solution)):
            raise InputError("values: the matrix is singular")
        return solution


def first_piola_and_tangent(
    displacement_gradient: np.ndarray,
    shear_modulus: np.ndarray,
    yeoh_c2: np.ndarray,
    yeoh_c3: np.ndarray,
    bulk_modulus: np.ndarray,
    lumen_pressure: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First Piola-Kirchhoff stress P (2, 2, ...), tangent dP/dF (2, 2, 2, 2, ...) and J = det F (...) of the
    compressible Yeoh law in plane strain at quadrature points: F = I + ``displacement_gradient`` (2, 2, ...,
    ``[c, k] = du_c / dx_k``); the material arrays (moduli and pressure in N/mm^2) broadcast against its tail."""
    eye = np.eye(2).reshape((2, 2) + (1,) * (displacement_gradient.ndim - 2))
    F = eye + displacement_gradient
    J = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    with np.errstate(all="ignore"):  # an inverted point's values are not used
        FinvT = np.stack([np.stack([F[1, 1], -F[1, 0]]), np.stack([-F[0, 1], F[0, 0]])]) / J
        I1 = np.einsum("ij...,ij...->...", F, F) + 1.0
        J23 = np.abs(J) ** (-2.0 / 3.0)
    dI1bar = J23 * (2 * F - (2.0 / 3.0) * I1 * FinvT)
    x = J23 * I1 - 3.0
    psi1 = 0.5 * shear_modulus * (1.0 + 2.0 * yeoh_c2 * x + 3.0 * yeoh_c3 * x**2)  # dW/dI1bar
    dpsi1 = 0.5 * shear_modulus * (2.0 * yeoh_c2 + 6.0 * yeoh_c3 * x)
    volumetric = 0.5 * bulk_modulus * (J**2 - 1.0)
    P = psi1 * dI1bar + volumetric * FinvT - lumen_pressure * J * FinvT

    def outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.einsum("ij...,kl...->ijkl...", a, b)

    FinvT_FinvT = outer(FinvT, FinvT)
    FinvT_cross = np.einsum("il...,kj...->ijkl...", FinvT, FinvT)  # d(FinvT_ij)/dF_kl = -FinvT_il FinvT_kj
    delta = np.einsum("ik,jl->ijkl", np.eye(2), np.eye(2)).reshape((2, 2, 2, 2) + (1,) * (F.ndim - 2))
    d_dI1bar = -(2.0 / 3.0) * outer(dI1bar, FinvT) + J23 * (
        2 * delta - (4.0 / 3.0) * outer(FinvT, F) + (2.0 / 3.0) * I1 * FinvT_cross
    )
    A = (
        dpsi1 * outer(dI1bar, dI1bar)
        + psi1 * d_dI1bar
        + bulk_modulus * J**2 * FinvT_FinvT
        - volumetric * FinvT_cross
        - lumen_pressure * J * (FinvT_FinvT - FinvT_cross)
    )
    return P, A, J


class HyperelasticSection:
    """Twin of ``_core.HyperelasticSection``: internal forces and tangent entries of a compressible Yeoh section on
    P2 triangles, element integrals by ``einsum`` (same arguments as the kernel)."""

    def __init__(
        self,
        n_dofs: int,
        element_dofs: np.ndarray,
        gradients: np.ndarray,
        weights: np.ndarray,
        shear_modulus: np.ndarray,
        yeoh_c2: np.ndarray,
        yeoh_c3: np.ndarray,
        bulk_modulus: np.ndarray,
        lumen_pressure: np.ndarray,
        entry_slots: np.ndarray,
        n_entries: int,
    ):
        self.n_dofs, self.n_entries = n_dofs, n_entries
        self.element_dofs, self.gradients, self.weights = element_dofs, gradients, weights
        self.materials = [m[:, None] for m in (shear_modulus, yeoh_c2, yeoh_c3, bulk_modulus)]
        self.lumen_pressure = lumen_pressure[:, None]
        self.entry_slots = entry_slots

    def assemble(
        self, u: np.ndarray, pressure_fraction: float, with_tangent: bool
    ) -> tuple[np.ndarray, np.ndarray | None, float]:
        """(force (n_dofs,), tangent entries (n_entries,) or None, det F): as the kernel; det F is the first
        non-positive one in (element, point) order, else the smallest."""
        n_elements = len(self.element_dofs)
        element_u = u[self.element_dofs].reshape(n_elements, 6, 2)  # [e, i, c]
        gradient = np.einsum("eic,epik->ckep", element_u, self.gradients)
        shear, c2, c3, bulk = self.materials
        stress, tangent, det = first_piola_and_tangent(
            gradient, shear, c2, c3, bulk, pressure_fraction * self.lumen_pressure
        )
        inverted = np.flatnonzero(det.ravel() <= 0)
        if len(inverted):
            return np.zeros(self.n_dofs), None, float(det.ravel()[inverted[0]])
        element_force = np.einsum("ep,epik,ckep->eic", self.weights, self.gradients, stress)
        force = np.bincount(self.element_dofs.ravel(), element_force.ravel(), minlength=self.n_dofs)
        if not with_tangent:
            return force, None, float(det.min())
        element_tangent = np.einsum(
            "ep,epik,ckdlep,epjl->eicjd", self.weights, self.gradients, tangent, self.gradients, optimize=True
        ).reshape(n_elements, 144)
        free = self.entry_slots >= 0
        values = np.bincount(self.entry_slots[free], element_tangent[free], minlength=self.n_entries)
        return force, values, float(det.min())
