"""Benchmark of the FEM section solve (`usdeform.sim.mechanics`): its Rust element loop and LDL^T against NumPy's
and SciPy's.

Workload: the sections a sim-to-real calibration solves cold for one recording (`usdeform.gap.calibration`:
a 2.5 mm P2 mesh, 150 mm wide, lambda in 0.75 mm steps to 10 mm): the ideal section, a thinner one with
sliding contact, a pressurised lumen and strain-stiffening, and a layered one. Every contender solves the
whole workload with the package's Newton iterations (the tangent factorised until the last, small steps of a load
step, which reuse its factor); the element loop (internal forces and tangent) and the linear factorisation and
solve differ:

* ``rust-loop+rust-ldlt``: the package (``usdeform._core.HyperelasticSection``, then
  ``usdeform._core.SymmetricSolver``: faer's supernodal LDL^T, ordering and symbolic factorisation once per
  section);
* ``numpy-loop+rust-ldlt``: the element loop as a NumPy user would write it at best (batched matrix products
  over elements and points, ``np.bincount`` scatter: :class:`NumpyElementLoop`);
* ``rust-loop+scipy-superlu-symmetric``: what a SciPy user would write at best for the solve: ``splu`` with
  the minimum-degree ordering of A + A^T and SuperLU's symmetric mode, factorised where the package factorises;
* ``numpy-loop+scipy-splu``: NumPy's loop and the NumPy twin ``usdeform.reference.SymmetricSolver`` (SciPy's
  ``splu`` with its defaults, as ``spsolve`` factorises).

The contenders run in rounds, one after the other in each round, and each keeps its fastest round (on a
shared machine, the least disturbed run). Prints seconds per workload, the ratio of each contender's time
to the package's, and the largest difference of the contact forces from the package's.

    python benches/bench_mechanics.py           # the workload above, 3 rounds
    python benches/bench_mechanics.py --quick   # a coarse mesh, 1 round (the tests use it)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # SuperLU's BLAS calls: one core, as the solves run

import argparse
import json
import time
from dataclasses import replace
from types import SimpleNamespace
from unittest import mock

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from usdeform import _core, reference
from usdeform.reference.mechanics import first_piola_and_tangent
from usdeform.sim.mechanics import Layer, SectionSpec, fem


class SuperLUSymmetric:
    """SciPy's SuperLU with the ordering and mode suited to a symmetric matrix (both triangles stored)."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray):
        self.indptr, self.indices, self.size = indptr, indices, len(indptr) - 1

    def factorize(self, values: np.ndarray) -> scipy.sparse.linalg.SuperLU:
        """The factor of the matrix with entries ``values``; its ``solve(rhs)`` solves with it."""
        matrix = scipy.sparse.csc_matrix((values, self.indices, self.indptr), shape=(self.size, self.size))
        return scipy.sparse.linalg.splu(matrix, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})


class NumpyElementLoop:
    """The element loop of ``_core.HyperelasticSection`` (same arguments) in batched NumPy: the gradients as
    strain-displacement matrices B (elements, points, 12, 4), forces as sum w B P and tangents as sum w B A B^T by
    matrix products, the material law of :func:`usdeform.reference.mechanics.first_piola_and_tangent`."""

    def __init__(self, n_dofs, element_dofs, gradients, weights, shear, c2, c3, bulk, pressure, entry_slots, n_entries):
        n_elements, n_points = weights.shape
        self.strain = np.zeros((n_elements, n_points, 12, 4))
        for i in range(6):
            for c in range(2):
                self.strain[:, :, 2 * i + c, 2 * c : 2 * c + 2] = gradients[:, :, i, :]
        self.weighted = self.strain * weights[:, :, None, None]
        self.stacked_transposes = self.strain.transpose(0, 1, 3, 2).reshape(n_elements, -1, 12)
        self.materials = [values[:, None] for values in (shear, c2, c3, bulk)]
        self.pressure = pressure[:, None]
        self.n_dofs, self.n_entries, self.element_dofs = n_dofs, n_entries, element_dofs
        self.free = np.flatnonzero(entry_slots.ravel() >= 0)
        self.slots = entry_slots.ravel()[self.free]

    def assemble(self, u: np.ndarray, pressure_fraction: float, with_tangent: bool):
        n_elements, n_points = self.strain.shape[:2]
        element_u = u[self.element_dofs][:, None, None, :]
        gradient = (element_u @ self.strain).reshape(n_elements, n_points, 2, 2).transpose(2, 3, 0, 1)
        stress, tangent, det = first_piola_and_tangent(gradient, *self.materials, pressure_fraction * self.pressure)
        if det.min() <= 0:
            return None, None, float(det.min())
        stress_vector = stress.reshape(4, n_elements, n_points).transpose(1, 2, 0)[..., None]
        element_force = (self.weighted @ stress_vector).sum(axis=1)
        force = np.bincount(self.element_dofs.ravel(), element_force.ravel(), minlength=self.n_dofs)
        if not with_tangent:
            return force, None, float(det.min())
        matrix = tangent.reshape(4, 4, n_elements, n_points).transpose(2, 3, 0, 1)
        left = (self.weighted @ matrix).transpose(0, 2, 1, 3).reshape(n_elements, 12, 4 * n_points)
        element_tangent = left @ self.stacked_transposes
        values = np.bincount(self.slots, element_tangent.reshape(-1)[self.free], minlength=self.n_entries)
        return force, values, float(det.min())


CONTENDERS = {  # (element loop, linear solve)
    "rust-loop+rust-ldlt": (_core.HyperelasticSection, _core.SymmetricSolver),
    "numpy-loop+rust-ldlt": (NumpyElementLoop, _core.SymmetricSolver),
    "rust-loop+scipy-superlu-symmetric": (_core.HyperelasticSection, SuperLUSymmetric),
    "numpy-loop+scipy-splu": (NumpyElementLoop, reference.SymmetricSolver),
}


def workload(quick: bool) -> list[tuple[SectionSpec, np.ndarray]]:
    """The calibration's kinds of section, each with its lambda steps (mm)."""
    ideal = SectionSpec(
        width_mm=150.0, depth_mm=60.0, vessel_depth_mm=20.0, vessel_radius_mm=4.0, mesh_size_mm=2.5, poisson_ratio=0.47
    )
    sections = [
        ideal,
        replace(ideal, depth_mm=40.0, vessel_depth_mm=15.0, contact="slide", lumen_pressure_kpa=2.0, yeoh_c2=1.0),
        replace(
            ideal, depth_mm=50.0, layers=(Layer(thickness_mm=5.0, shear_modulus_kpa=30.0),), yeoh_c2=-0.17, yeoh_c3=0.02
        ),
    ]
    if quick:
        sections = [replace(spec, mesh_size_mm=4.0, vessel_radius_mm=6.0) for spec in sections[:2]]
    return [(spec, np.linspace(0.0, 10.0 if not quick else 4.0, 15 if not quick else 5)) for spec in sections]


def run(contender: str, sections: list[tuple[SectionSpec, np.ndarray]]) -> tuple[float, list[np.ndarray]]:
    """Seconds for the whole workload and the contact forces (N) of each section."""
    element_loop, solver = CONTENDERS[contender]
    with mock.patch.object(fem, "_core", SimpleNamespace(HyperelasticSection=element_loop, SymmetricSolver=solver)):
        start = time.perf_counter()
        forces = [fem._solve_uncached(spec, steps)["force_n"] for spec, steps in sections]
        return time.perf_counter() - start, forces


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a coarse mesh and one round (smoke run)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    arguments = parser.parse_args()
    sections = workload(arguments.quick)
    rounds = 1 if arguments.quick else arguments.rounds
    best: dict[str, float] = {}
    forces: dict[str, list[np.ndarray]] = {}
    for _ in range(rounds):
        for contender in CONTENDERS:
            seconds, forces[contender] = run(contender, sections)
            best[contender] = min(best.get(contender, np.inf), seconds)
    package = "rust-loop+rust-ldlt"
    results = {
        contender: {
            "seconds": best[contender],
            "ratio_to_package": best[contender] / best[package],
            "max_force_difference_n": max(
                float(np.abs(a - b).max()) for a, b in zip(forces[contender], forces[package], strict=True)
            ),
        }
        for contender in CONTENDERS
    }
    if arguments.json:
        print(json.dumps(results, indent=1))
        return
    print(f"{len(sections)} sections, fastest of {rounds} round(s)")
    print(f"{'contender':<36}{'seconds':>9}{'x package':>11}{'max |dF| N':>13}")
    for contender, result in results.items():
        print(
            f"{contender:<36}{result['seconds']:>9.2f}{result['ratio_to_package']:>11.2f}"
            f"{result['max_force_difference_n']:>13.1e}"
        )


if __name__ == "__main__":
    main()
