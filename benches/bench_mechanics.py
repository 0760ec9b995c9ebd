"""Benchmark of the FEM section solve (`usdeform.sim.mechanics`) with its Rust LDL^T against SciPy's solvers.

Workload: the sections a sim-to-real calibration solves cold for one recording (`usdeform.gap.calibration`:
a 2.5 mm P2 mesh, 150 mm wide, lambda in 0.75 mm steps to 10 mm): the ideal section, a thinner one with
sliding contact, a pressurised lumen and strain-stiffening, and a layered one. Every contender solves the
whole workload with the package's own assembly; only the linear solve of each Newton step differs:

* ``rust-ldlt``: the package (``usdeform._core.SymmetricSolver``: faer's supernodal LDL^T, ordering and
  symbolic factorisation once per section);
* ``scipy-superlu-symmetric``: what a SciPy user would write at best: ``splu`` with the minimum-degree
  ordering of A + A^T and SuperLU's symmetric mode, refactorised at every step;
* ``scipy-spsolve``: ``spsolve`` with its defaults (the package's solver before the Rust one; also the
  NumPy twin ``usdeform.reference.SymmetricSolver``).

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
from usdeform.sim.mechanics import Layer, SectionSpec, fem


class SuperLUSymmetric:
    """SciPy's SuperLU with the ordering and mode suited to a symmetric matrix (both triangles stored)."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray):
        self.indptr, self.indices, self.size = indptr, indices, len(indptr) - 1

    def solve(self, values: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        matrix = scipy.sparse.csc_matrix((values, self.indices, self.indptr), shape=(self.size, self.size))
        factor = scipy.sparse.linalg.splu(matrix, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        return factor.solve(rhs)


CONTENDERS = {
    "rust-ldlt": _core.SymmetricSolver,
    "scipy-superlu-symmetric": SuperLUSymmetric,
    "scipy-spsolve": reference.SymmetricSolver,
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
    with mock.patch.object(fem, "_core", SimpleNamespace(SymmetricSolver=CONTENDERS[contender])):
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
    package = "rust-ldlt"
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
    print(f"{'contender':<26}{'seconds':>9}{'x package':>11}{'max |dF| N':>13}")
    for contender, result in results.items():
        print(
            f"{contender:<26}{result['seconds']:>9.2f}{result['ratio_to_package']:>11.2f}"
            f"{result['max_force_difference_n']:>13.1e}"
        )


if __name__ == "__main__":
    main()
