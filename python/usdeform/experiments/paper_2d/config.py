"""What the paper-2d experiments simulate and compare: the configuration, the methods and the result records."""

from __future__ import annotations

from dataclasses import dataclass, field

from ...options import Basis, Coupling, Integration, Solver

__all__ = ["QUICK", "CorrectionCase", "Method", "Paper2dConfig", "Paper2dResults", "methods_for"]


@dataclass(frozen=True)
class Paper2dConfig:
    """What the experiments simulate: frame size, palpation length, positions (mm along the
    phantom) and evaluation forces (N). ``mesh_size_mm`` overrides the presets' mesh (quick runs)."""

    rows: int = 256
    cols: int = 256
    n_frames: int = 50
    stiff_fit_position_mm: float = 10.0
    stiff_other_positions_mm: tuple[float, ...] = (32.0, 54.0, 76.0)
    soft_positions_mm: tuple[float, ...] = (10.0, 35.0, 60.0)
    stiff_forces_n: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 25.0)
    soft_forces_n: tuple[float, ...] = (2.0, 4.0, 6.0, 8.0)
    stiff_max_force_n: float = 30.0
    soft_max_force_n: float = 16.0
    solver: Solver = "exact"
    bspline_functions: tuple[int, int] = (8, 8)
    seed: int = 0
    mesh_size_mm: float | None = None


@dataclass(frozen=True)
class Method:
    """A correction method: the model's spatial ``basis``, ``coupling`` and ``integration``, and
    whether it is fitted to the tracked displacements or to the simulator's true field (``truth``)."""

    name: str
    basis: Basis | tuple[str, int, int]
    coupling: Coupling
    integration: Integration
    truth: bool
    description: str


def methods_for(config: Paper2dConfig) -> tuple[Method, ...]:
    """The compared methods; ``paper`` and ``force`` are the paper's comparison."""
    spline = ("bspline", *config.bspline_functions)
    size = "x".join(str(n) for n in config.bspline_functions)
    return (
        Method("paper", "quadratic", "stiffness", "force", False, "the paper's model (eq. 8, over force)"),
        Method("force", "quadratic", "force", "force", False, "force-based baseline of Sun et al. 2010 (h = F)"),
        Method(
            "paper-lambda",
            "quadratic",
            "stiffness",
            "displacement",
            False,
            "the paper's model integrated over probe displacement (dlambda = dF/k) instead of force",
        ),
        Method("spline", spline, "stiffness", "force", False, f"cubic B-spline basis {size}, coupled as the paper"),
        Method("spline-force", spline, "force", "force", False, f"cubic B-spline basis {size}, h = F"),
        Method(
            "spline-lambda",
            spline,
            "stiffness",
            "displacement",
            False,
            f"cubic B-spline basis {size}, integrated over probe displacement",
        ),
        Method("oracle", "quadratic", "stiffness", "force", True, "the paper's model fitted to the true field"),
        Method("oracle-spline", spline, "stiffness", "force", True, f"B-spline {size} fitted to the true field"),
    )


#: A small, fast configuration for smoke tests (coarse mesh, small frames, one position each).
QUICK = Paper2dConfig(
    rows=128,
    cols=128,
    n_frames=30,
    stiff_other_positions_mm=(40.0,),
    soft_positions_mm=(40.0,),
    stiff_forces_n=(10.0, 25.0),
    soft_forces_n=(4.0, 8.0),
    mesh_size_mm=4.0,
)


@dataclass(frozen=True)
class CorrectionCase:
    """One evaluated frame: Dice, area error (mm^2, frame minus zero force) and centroid distance (mm)
    of the deformed frame and of the frame corrected by each method."""

    experiment: str
    phantom: str
    position_mm: float
    target_force_n: float
    force_n: float
    dice: dict[str, float]
    area_error_mm2: dict[str, float]
    centroid_error_mm: dict[str, float]


@dataclass
class Paper2dResults:
    """What :func:`~usdeform.experiments.paper_2d.run_paper_2d` measured: TABLE I per solver, the
    correction cases (TABLE II), the stiffness fits, the fitted-against-true diagnosis and the fitting
    time per position (s)."""

    table_1: dict[str, dict] = field(default_factory=dict)
    cases: list[CorrectionCase] = field(default_factory=list)
    stiffness: dict[str, dict] = field(default_factory=dict)
    diagnosis: dict[str, dict] = field(default_factory=dict)
    fit_seconds_per_position: float = 0.0
