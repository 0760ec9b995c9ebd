"""What the paper-3d experiments simulate: the phantoms' sweeps, the configurations and the result records."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ...options import StiffnessSource
from ...sim import (
    Effects,
    ForceSensorError,
    ImageLatency,
    OutOfPlaneMotion,
    Phantom,
    Viscoelasticity,
    soft_phantom,
    stiff_phantom,
)
from ...volume import HoleFillingElement, VoxelGrid
from ..paper_2d import Method, Paper2dConfig, methods_for

__all__ = [
    "HOLE_FILLING",
    "NUISANCES",
    "PRESETS",
    "QUICK",
    "SOURCES",
    "VIEWED",
    "Paper3dConfig",
    "PhantomSweeps",
    "SweepCase",
    "Views",
    "variant_names",
    "variants",
]


PRESETS: dict[str, Callable[[], Phantom]] = {"stiff": stiff_phantom, "soft": soft_phantom}


@dataclass(frozen=True)
class PhantomSweeps:
    """Sweeps over one phantom: the ``preset`` (``"stiff"``, ``"soft"``), its stiffness variation along
    s (None: the preset's), the path (start and length, mm), the number of palpations along it, their
    highest force (N), the sweep forces (N) and the simulator's nuisance ``effects`` on palpations and
    sweeps (None: an ideal system)."""

    label: str
    preset: str
    start_mm: float
    length_mm: float
    n_palpations: int
    palpation_force_n: float
    forces_n: tuple[float, ...]
    stiffness_amplitude: float | None = None
    effects: Effects | None = None


#: A real system's nuisances, each mid-range of :mod:`usdeform.sim.effects`: 30 ms image latency, a
#: 0.3 N force bias drifting 0.005 N/s, 10 % viscoelastic relaxation (1 s), out-of-plane tissue motion
#: (0.05 mm per mm of indentation plus 0.15 mm rms jitter: speckle decorrelation between frames).
NUISANCES = Effects(
    latency=ImageLatency(0.03),
    force_sensor=ForceSensorError(bias_n=0.3, drift_n_per_s=0.005),
    viscoelasticity=Viscoelasticity(((0.1, 1.0),)),
    out_of_plane=OutOfPlaneMotion(shift_mm_per_mm=0.05, jitter_mm=0.15),
)


@dataclass(frozen=True)
class Paper3dConfig:
    """What the experiments simulate. ``frame_spacing_mm``: sweep distance between frames;
    ``voxel_mm``: voxel size; ``mesh_size_mm`` overrides the presets' mesh (quick runs)."""

    rows: int = 256
    cols: int = 256
    palpation_frames: int = 40
    frame_spacing_mm: float = 0.5
    voxel_mm: float = 0.4
    random_frames: int = 10
    phantoms: tuple[PhantomSweeps, ...] = (
        PhantomSweeps("stiff", "stiff", 20.0, 40.0, 4, 30.0, (5.0, 10.0, 15.0, 20.0, 25.0)),
        PhantomSweeps("soft", "soft", 10.0, 60.0, 3, 16.0, (2.0, 4.0, 6.0, 8.0)),
        # The paper's stiff phantom barely varies along 40 mm (+/-4 %); tissue under a real sweep
        # varies more: the same phantom with +/-30 % along s, at 15 N, compares the stiffness sources
        # (palpated to 20 N: at its softest, 30 N would press beyond the solved 11 mm).
        PhantomSweeps("stiff, +/-30 % along s", "stiff", 20.0, 40.0, 4, 20.0, (15.0,), stiffness_amplitude=0.3),
        PhantomSweeps(
            "stiff, +/-30 % along s, nuisances",
            "stiff",
            20.0,
            40.0,
            4,
            20.0,
            (15.0,),
            stiffness_amplitude=0.3,
            effects=NUISANCES,
        ),
    )
    bspline_functions: tuple[int, int] = (8, 8)
    seed: int = 0
    mesh_size_mm: float | None = None


#: A small configuration for smoke tests: coarse mesh, small frames, short paths, few forces.
QUICK = Paper3dConfig(
    rows=96,
    cols=96,
    palpation_frames=20,
    frame_spacing_mm=1.0,
    voxel_mm=0.5,
    random_frames=3,
    phantoms=(
        PhantomSweeps("stiff", "stiff", 20.0, 12.0, 2, 30.0, (25.0,)),
        PhantomSweeps("soft", "soft", 20.0, 12.0, 2, 16.0, (8.0,)),
    ),
    mesh_size_mm=4.0,
)

#: Hole filling of the volumes: STICK, as PLUS's configurations use, over at most 4 voxels (the gaps
#: between frames, not the space beyond the sweep).
HOLE_FILLING = (HoleFillingElement("stick", stick_length_limit=4),)

#: The volumes Fig. 9 shows side by side.
VIEWED = ("truth", "deformed", "paper", "spline-lambda")

#: Stiffness sources compared (see :func:`usdeform.correction.sweep_profiles`).
SOURCES: tuple[StiffnessSource, ...] = ("interpolated", "sweep")


def variants(config: Paper3dConfig) -> tuple[Method, ...]:
    """The paper's comparison and its variants (methods fitted to tracked displacements only)."""
    return tuple(
        m
        for m in methods_for(Paper2dConfig(bspline_functions=config.bspline_functions))
        if not m.truth and m.name != "spline-force"
    )


def variant_names(methods: tuple[Method, ...]) -> list[str]:
    """Every corrected variant: each method with interpolated stiffness, ``method/sweep`` with the sweep's."""
    return [m.name for m in methods] + [f"{m.name}/sweep" for m in methods if m.coupling == "stiffness"]


@dataclass
class SweepCase:
    """One sweep's results. ``frames``: per-frame metrics of the random frames, each a dict of variant
    name (``deformed``, a method, ``method/sweep``) to a list over the frames; ``volume``: per variant,
    the volume metrics; ``stiffness``: how far each source's profile misses the recorded lambda (mm);
    ``walls``: per variant, :func:`wall_errors_mm` averaged over the random frames."""

    phantom: str
    target_force_n: float
    n_frames: int
    force_range_n: tuple[float, float]
    probe_displacement_range_mm: tuple[float, float]
    frame_indices: list[int]
    frames: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    volume: dict[str, dict[str, float]] = field(default_factory=dict)
    stiffness: dict[str, dict[str, float]] = field(default_factory=dict)
    walls: dict[str, dict[str, float]] = field(default_factory=dict)


@dataclass
class Views:
    """What the figures show of one sweep: the lumen volumes and images of truth, deformed and each variant."""

    grid: VoxelGrid
    images: dict[str, np.ndarray]
    lumens: dict[str, np.ndarray]
