"""The sweeps of ``usdeform experiment clinical-3d``: sections and paths shaped like clinical scans."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ...sim import Phantom, SweepPath, artery_vein_phantom, branching_phantom

__all__ = ["QUICK", "Clinical3dConfig", "Scenario", "default_scenarios"]


@dataclass(frozen=True)
class Scenario:
    """One sweep: its phantom (``"flat"``: artery and vein at a constant depth over a bone at 32 mm;
    ``"deepening"``: both vessels 14 mm deeper at the far end and the artery 1.5 mm wider, over a bone at
    40 mm; ``"branching"``: an artery and a side branch leaving it), the force (N) and the surface's radius
    along the sweep (mm; inf: flat)."""

    label: str
    phantom: str
    force_n: float
    surface_radius_mm: float = math.inf

    def make_phantom(self) -> Phantom:
        """The scenario's phantom (see the class docstring)."""
        if self.phantom == "deepening":
            return artery_vein_phantom(40.0, vessel_shift_depth_mm=14.0, vessel_radius_change_mm=1.5)
        if self.phantom == "branching":
            return branching_phantom()
        return artery_vein_phantom()

    @property
    def vessel_names(self) -> tuple[str, str]:
        """The names of the section's lumens, the main one first."""
        return ("artery", "branch") if self.phantom == "branching" else ("artery", "vein")

    @property
    def path(self) -> SweepPath:
        """How the probe follows the surface."""
        return SweepPath(surface_radius_mm=self.surface_radius_mm)


def default_scenarios() -> tuple[Scenario, ...]:
    """Every shape the experiment covers: forces of 3, 8 and 15 N, a curved path, deepening vessels and a
    branch."""
    return (
        Scenario("artery and vein, 3 N", "flat", 3.0),
        Scenario("artery and vein, 8 N", "flat", 8.0),
        Scenario("artery and vein, 15 N", "flat", 15.0),
        Scenario("curved surface (60 mm), 8 N", "flat", 8.0, 60.0),
        Scenario("vessels 12-28 mm deep, widening, 6 N", "deepening", 6.0),
        Scenario("vessels 12-28 mm deep, curved (80 mm), 10 N", "deepening", 10.0, 80.0),
        Scenario("a branch leaving the artery, 8 N", "branching", 8.0),
    )


@dataclass(frozen=True)
class Clinical3dConfig:
    """The experiment's settings: the scenarios, frame size (pixels), palpations per phantom (evenly along the
    sweep, to ``palpation_force_n``), frames per palpation and per sweep, the sweep's start and length (mm),
    every ``measured_step``-th sweep frame measured, and the seed."""

    scenarios: tuple[Scenario, ...] = default_scenarios()
    rows: int = 160
    cols: int = 160
    n_palpations: int = 3
    palpation_force_n: float = 16.0
    palpation_frames: int = 30
    sweep_frames: int = 60
    start_mm: float = 5.0
    length_mm: float = 50.0
    measured_step: int = 3
    seed: int = 63


#: A smoke run: two scenarios on small frames.
QUICK = Clinical3dConfig(
    scenarios=default_scenarios()[1:2] + default_scenarios()[3:4],
    rows=128,
    cols=128,
    palpation_frames=20,
    sweep_frames=30,
)
