"""The option types of the package, as ``typing.Literal`` (mirrored in ``_core.pyi``).

Each type has a tuple of its values beside it, for checks and command-line choices:

>>> from usdeform.options import COUPLINGS
>>> COUPLINGS
('stiffness', 'force')
"""

from __future__ import annotations

from typing import Literal, TypeVar, get_args

from .errors import InputError

__all__ = [
    "ANCHORS",
    "BASES",
    "COMPOUNDINGS",
    "COUPLINGS",
    "INTEGRATIONS",
    "INTERPOLATIONS",
    "SOLVERS",
    "STIFFNESS_SOURCES",
    "WALL_MODES",
    "Anchor",
    "Basis",
    "Compounding",
    "Coupling",
    "Integration",
    "Interpolation",
    "Solver",
    "StiffnessSource",
    "WallMode",
    "checked_option",
]

#: The spatial basis of a displacement model: the paper's quadratic or a cubic B-spline.
Basis = Literal["quadratic", "bspline"]
#: How a model couples force and tissue: ``h = F / k`` (the paper) or ``h = F`` (Sun et al. 2010).
Coupling = Literal["stiffness", "force"]
#: What the rate is integrated over: force (paper eq. 8) or probe displacement (``dlambda = dF / k``).
Integration = Literal["force", "displacement"]
#: The regression's solver: the exact least-squares solution or the paper's ADAM.
Solver = Literal["exact", "adam"]
#: What a displacement model's field is tied to: the image (probe) alone, or in part to the vessel's
#: lumen, which the field follows along the sweep (:class:`usdeform.regression.VesselAnchoredModel`).
Anchor = Literal["image", "vessel"]
#: Whether a palpation's vessel wall is measured and fitted: where a lumen is found in the
#: lowest-force frame ("auto"), always (an error without a lumen: "require"), or not at all ("off").
WallMode = Literal["auto", "require", "off"]
#: How a pixel is splatted into the volume: to the nearest voxel or trilinearly over 8.
Interpolation = Literal["nearest", "linear"]
#: How the values landing in a voxel are combined.
Compounding = Literal["mean", "max", "latest"]
#: Where a sweep frame's stiffness comes from: the palpated profiles mixed by inverse distance
#: (paper eqs. 13-14), or that profile rescaled to the frame's own ContactForce and ProbeDisplacement.
StiffnessSource = Literal["interpolated", "sweep"]

ANCHORS: tuple[Anchor, ...] = get_args(Anchor)
BASES: tuple[Basis, ...] = get_args(Basis)
COUPLINGS: tuple[Coupling, ...] = get_args(Coupling)
INTEGRATIONS: tuple[Integration, ...] = get_args(Integration)
SOLVERS: tuple[Solver, ...] = get_args(Solver)
INTERPOLATIONS: tuple[Interpolation, ...] = get_args(Interpolation)
COMPOUNDINGS: tuple[Compounding, ...] = get_args(Compounding)
STIFFNESS_SOURCES: tuple[StiffnessSource, ...] = get_args(StiffnessSource)
WALL_MODES: tuple[WallMode, ...] = get_args(WallMode)

_Option = TypeVar("_Option", bound=str)


def checked_option(name: str, value: str, choices: tuple[_Option, ...]) -> _Option:
    """``value`` as one of ``choices``, or InputError naming the option ``name``.

    Examples
    --------
    >>> checked_option("compounding", "max", COMPOUNDINGS)
    'max'
    """
    for choice in choices:
        if value == choice:
            return choice
    raise InputError(f"{name}: expected one of {', '.join(map(repr, choices))}, got {value!r}")
