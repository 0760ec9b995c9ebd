"""The option types of the package, as ``typing.Literal`` (mirrored in ``_core.pyi``), and its numeric options.

Each type has a tuple of its values beside it, for checks and command-line choices:

>>> from usdeform.options import COUPLINGS
>>> COUPLINGS
('stiffness', 'force')

Each numeric option has one :class:`Number` in :data:`NUMBERS`, which both the command line (its
``argparse`` type) and the batch manifest parse with, so that a value one accepts the other accepts:

>>> NUMBERS["max_gib"].parse_text("inf")
Traceback (most recent call last):
...
usdeform.errors.InputError: max_gib: expected a finite number > 0 and at most 1099511627776, got 'inf'
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, TypeVar, get_args

from .errors import InputError

__all__ = [
    "ANCHORS",
    "BASES",
    "COMPOUNDINGS",
    "COUPLINGS",
    "DEFAULT_COMPRESSION_LEVEL",
    "INTEGRATIONS",
    "INTERPOLATIONS",
    "NUMBERS",
    "SOLVERS",
    "STIFFNESS_SOURCES",
    "WALL_MODES",
    "Anchor",
    "Basis",
    "Compounding",
    "Coupling",
    "Integration",
    "Interpolation",
    "Number",
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


@dataclass(frozen=True)
class Number:
    """A numeric option: finite, in ``[minimum, maximum]`` (``minimum`` excluded when ``above``), an integer
    when ``integer``. ``name`` is its name in a manifest and the API (``spacing_mm``); errors name it, or
    the label the caller gives (the command line's flag, a manifest's line)."""

    name: str
    minimum: float
    maximum: float
    above: bool = False
    integer: bool = False

    def expected(self) -> str:
        if self.integer:
            low = int(self.minimum) + 1 if self.above else int(self.minimum)
            return f"an integer from {low} to {int(self.maximum)}"
        return f"a finite number {'>' if self.above else '>='} {self.minimum:g} and at most {self.maximum:.13g}"

    def check(self, value: object, label: str | None = None, *, error: type[InputError] = InputError) -> float:
        """``value`` (a number, not text) as a float (an int for integer options), or ``error`` naming ``label``."""
        kinds = (int,) if self.integer else (int, float)
        if isinstance(value, bool) or not isinstance(value, kinds):
            raise error(f"{label or self.name}: expected {self.expected()}, got {value!r}"[:200])
        number: float = value
        if not self.integer:
            try:
                number = float(value)
            except OverflowError:  # an integer beyond float64
                number = math.inf
        above_minimum = number > self.minimum if self.above else number >= self.minimum
        if not (above_minimum and number <= self.maximum and (self.integer or math.isfinite(number))):
            raise error(f"{label or self.name}: expected {self.expected()}, got {value!r}"[:200])
        return number

    def parse_text(self, text: str, label: str | None = None, *, error: type[InputError] = InputError) -> float:
        """The number written ``text`` (a command-line argument, a CSV cell), checked as :meth:`check`."""
        try:
            value: float = int(text.strip()) if self.integer else float(text)
        except (ValueError, OverflowError):
            raise error(f"{label or self.name}: expected {self.expected()}, got {text!r}"[:200]) from None
        try:
            return self.check(value, label, error=error)
        except InputError:
            raise error(f"{label or self.name}: expected {self.expected()}, got {text!r}"[:200]) from None

    def argument(self) -> Callable[[str], float]:
        """The ``argparse`` type of the option: argparse names the flag and exits with status 2."""

        def parse(text: str) -> float:
            try:
                return self.parse_text(text)
            except InputError as exc:
                raise argparse.ArgumentTypeError(str(exc).removeprefix(f"{self.name}: ")) from None

        parse.__name__ = self.name  # argparse's "invalid <name> value" names the option, not "parse"
        return parse


#: Largest memory limit, GiB (a limit; a grid must also fit the machine, MemoryLimitError).
MAX_GIB = 2.0**40

#: The numeric options of the command line and the batch manifest, by their manifest / API name.
NUMBERS: dict[str, Number] = {
    number.name: number
    for number in (
        Number("spacing_mm", 0.0, 1000.0, above=True),
        Number("max_gib", 0.0, MAX_GIB, above=True),
        Number("flexible_layer_mm", 0.0, 1000.0, above=True),
        Number("smoothness", 0.0, 1e12, above=True),
        Number("wall_weight", 0.0, 1e12),
        Number("diagnosis_seed", 0, 2**63 - 1, integer=True),
        Number("retries", 0, 100, integer=True),
        Number("workers", 1, 4096, integer=True),
        Number("kernel_threads", 1, 4096, integer=True),
        Number("tolerance_s", 0.0, 3600.0, above=True),
        Number("depth_mm", 0.0, 1000.0, above=True),
        Number("width_mm", 0.0, 1000.0, above=True),
        Number("force_n", 0.0, 1000.0, above=True),
        Number("seed", 0, 2**32 - 1, integer=True),
        # the compression level of volume files (1: ISA-L's deflate, 2-9: zlib's levels): every level is a standard
        # gzip (NRRD) or zlib (MetaImage) stream to a reader (3D Slicer, ITK and PLUS inflate any level)
        Number("compression_level", 1, 9, integer=True),
    )
}

#: Level 1 (ISA-L's deflate; 2-9 are zlib's levels), from ``benches/bench_volume_compression.py`` (a float32 volume
#: of 137 x 100 x 125 voxels compounded from a 100-frame 256 x 256 sweep at 0.3 mm, 2 cores): a .nrrd took 0.032 s for
#: 2.81 MB at level 1, 0.118 s for 2.86 MB at 2, 0.76 s for 2.71 MB at 6 (zlib's default) and 3.0 s for 2.56 MB at 9
#: (uncompressed: 0.011 s, 6.85 MB); .mha alike. The volume cast to uint8: 1.34 MB at every level, 0.006 s at level 1
#: and 0.04-0.05 s at 2-9. Written frame sequences use level 1 too.
DEFAULT_COMPRESSION_LEVEL = 1
