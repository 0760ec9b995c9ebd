"""One section of the calibration's FEM library solved and gridded, and what the library does when a section cannot
be solved.

A section that Newton cannot follow (an element inverted at the face's corner, a contact set that does not settle)
never ends a diagnosis:

1. it is solved again with load steps ``_FINER_STEPS`` times smaller (a finer continuation from the start);
2. failing that, it is solved only up to the recording's own largest indentation (plus one library step, finely),
   the library's spare steps beyond it extrapolated linearly: no frame reads them;
3. failing that, it is left out. A variant of an effect takes its effect out of the library with it (the effect is
   not fitted, and the diagnosis says so); a variant of a free parameter of the section only takes that side of the
   parameter's range away; without its ideal section a recording cannot be calibrated, which is an input error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..sim import MechanicsSolution, SectionSpec, solve_section
from ..sim.mechanics import MechanicsConvergenceError

__all__ = ["SPARE_FACTOR", "SPARE_MM", "LibraryEntry", "UnsolvedSection", "effect_of_variant", "library_entry"]

_FINER_STEPS = 4  # a section that fails is solved again with load steps this many times smaller
SPARE_FACTOR, SPARE_MM = 1.15, 0.5  # the library's top step over the recorded indentation (calibration)


@dataclass(frozen=True)
class LibraryEntry:
    """A library section gridded at the library's steps: field (2, ns, nz, nx), mm; lumen area (ns,), mm^2; force
    (ns,), N, at the library modulus; ``resolved``: how it was solved ("" at the library's steps, "finer steps",
    "to the recorded indentation")."""

    field: np.ndarray
    lumen_area_mm2: np.ndarray
    force_n: np.ndarray
    resolved: str = ""


@dataclass(frozen=True)
class UnsolvedSection:
    """A library section of ``recording`` left out: its variant name, why (the solver's message) and the library
    effect taken out with it ("" for a variant of a free parameter of the section)."""

    recording: str
    section: str
    error: str
    effect: str

    def as_dict(self) -> dict[str, str]:
        return {"recording": self.recording, "section": self.section, "error": self.error, "effect": self.effect}


def effect_of_variant(name: str) -> str:
    """The library effect a variant of the calibration's library models ("" for the ideal section, a free
    parameter's variant or a joint solve of an effect's and a parameter's variant, which the models use only where
    solved)."""
    if "," in name or "=" in name or name == "ideal":
        return ""
    for prefix, effect in (
        ("slide", "sliding_contact"),
        ("layer_", "layered_tissue"),
        ("tilt_", "probe_tilt"),
        ("travel_", "probe_tilt"),
        ("pressure_", "lumen_pressure"),
    ):
        if name.startswith(prefix):
            return effect
    raise ValueError(f"unknown library variant {name!r}")


def _grid(solution: MechanicsSolution, steps: np.ndarray, grid_x: np.ndarray, grid_z: np.ndarray) -> np.ndarray:
    """(2, ns, nz, nx) displacement of the grid points at ``steps``; zero below the section's rigid base, where a
    thinner variant has bone or the phantom's support."""
    xx, zz = np.meshgrid(grid_x, grid_z)
    points = np.column_stack([xx.ravel(), zz.ravel()])
    values = np.stack([solution.displacement(points, float(lam), outside="nan") for lam in steps])
    values[:, points[:, 1] >= solution.spec.depth_mm] = 0.0
    return np.ascontiguousarray(values.reshape(len(steps), len(grid_z), len(grid_x), 2).transpose(3, 0, 1, 2))


def _entry(solution: MechanicsSolution, steps: np.ndarray, grid_x: np.ndarray, grid_z: np.ndarray, resolved: str):
    """The entry of ``solution`` at the library's ``steps``; steps beyond the solved range extrapolated linearly
    from its last two steps."""
    top = float(solution.probe_displacement_mm[-1])
    inside = steps[steps <= top + 1e-9]
    field = _grid(solution, inside, grid_x, grid_z)
    area = np.array([solution.lumen_area_mm2(float(v)) for v in inside])
    force = np.asarray(solution.force_at(inside), dtype=float)
    if len(inside) < len(steps):
        slope_steps = inside[-2:]
        run = slope_steps[1] - slope_steps[0]
        beyond = (steps[len(inside) :] - slope_steps[1]) / run
        field = np.concatenate(
            [field, field[:, -1:] + beyond[None, :, None, None] * (field[:, -1:] - field[:, -2:-1])], axis=1
        )
        area = np.concatenate([area, area[-1] + beyond * (area[-1] - area[-2])])
        force = np.concatenate([force, force[-1] + beyond * (force[-1] - force[-2])])
    return LibraryEntry(field, area, force, resolved)


def library_entry(
    variant: SectionSpec, steps: np.ndarray, grid_x: np.ndarray, grid_z: np.ndarray
) -> LibraryEntry | str:
    """One library section solved (or read from the cache) and gridded at ``steps`` (mm), or, when it cannot be
    solved in any of the module docstring's ways, the solver's message."""
    recorded_top = (float(steps[-1]) - SPARE_MM) / SPARE_FACTOR
    step = float(steps[1] - steps[0])
    finer = np.linspace(0.0, float(steps[-1]), _FINER_STEPS * (len(steps) - 1) + 1)
    to_recorded = finer[finer <= recorded_top + step + 1e-9]
    attempts = [(steps, ""), (finer, "finer steps")]
    if len(to_recorded) >= 3 and len(to_recorded) < len(finer):
        attempts.append((to_recorded, "to the recorded indentation"))
    message = ""
    for attempt_steps, resolved in attempts:
        try:
            solution = solve_section(variant, attempt_steps)
        except MechanicsConvergenceError as failure:
            message = str(failure)
            continue
        return _entry(solution, steps, grid_x, grid_z, resolved)
    return message
