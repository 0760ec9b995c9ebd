"""Type stub of the compiled kernels (rust/python/src/). Checked against the binary by the tests.

The option types mirror :mod:`usdeform.options`.
"""

from typing import Literal, final, overload

import numpy as np
import numpy.typing as npt

__all__ = [
    "BYTES_PER_VOXEL",
    "Accumulator",
    "HyperelasticSection",
    "LumenSearch",
    "Model",
    "SymmetricFactor",
    "SymmetricSolver",
    "VesselPart",
    "_panic_for_tests",
    "affine_lucas_kanade",
    "block_match",
    "crc64",
    "fill_holes",
    "force_integrals",
    "patch_correlation",
    "splat_bilinear",
    "sweep_lumens",
    "warp_by_field",
    "warp_frames",
]

_Basis = Literal["quadratic", "bspline"]
_Coupling = Literal["stiffness", "force"]
_Integration = Literal["force", "displacement"]
_Interpolation = Literal["nearest", "linear"]
_Compounding = Literal["mean", "max", "latest"]
_Frames = npt.NDArray[np.uint8] | npt.NDArray[np.float32]

BYTES_PER_VOXEL: int

@final
class SymmetricSolver:
    """A symmetric sparse pattern in CSC form (``indptr`` (n + 1,), ``indices`` (nnz,), int64; both
    triangles stored, the lower one read, every diagonal entry present), factorised symbolically."""

    def __new__(cls, indptr: npt.NDArray[np.int64], indices: npt.NDArray[np.int64]) -> SymmetricSolver: ...
    @property
    def size(self) -> int: ...
    def solve(self, values: npt.NDArray[np.float64], rhs: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """x (n,) of A x = ``rhs`` (n,), A of this pattern with entries ``values`` (nnz,); LDL^T."""
    def factorize(self, values: npt.NDArray[np.float64]) -> SymmetricFactor:
        """The LDL^T factor of A of this pattern with entries ``values`` (nnz,), for several solves."""

@final
class SymmetricFactor:
    """The LDL^T factor of one matrix of a :class:`SymmetricSolver`'s pattern."""

    def solve(self, rhs: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """x (n,) of A x = ``rhs`` (n,) for the factorised A."""

@final
class HyperelasticSection:
    """A section of the compressible Yeoh material on P2 triangles: ``element_dofs`` (n_elements, 12) int64,
    ``gradients`` (n_elements, n_points, 6, 2) in 1/mm, ``weights`` (n_elements, n_points) in mm^2, the materials
    (n_elements,) in N/mm^2, ``entry_slots`` (n_elements, 144) int64 (-1: outside the free-free block)."""

    def __new__(
        cls,
        n_dofs: int,
        element_dofs: npt.NDArray[np.int64],
        gradients: npt.NDArray[np.float64],
        weights: npt.NDArray[np.float64],
        shear_modulus: npt.NDArray[np.float64],
        yeoh_c2: npt.NDArray[np.float64],
        yeoh_c3: npt.NDArray[np.float64],
        bulk_modulus: npt.NDArray[np.float64],
        lumen_pressure: npt.NDArray[np.float64],
        entry_slots: npt.NDArray[np.int64],
        n_entries: int,
    ) -> HyperelasticSection: ...
    def assemble(
        self, u: npt.NDArray[np.float64], pressure_fraction: float, with_tangent: bool
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64] | None, float]:
        """(internal forces (n_dofs,) in N/mm, tangent entries (n_entries,) or None, det F: not positive for an
        inverted element, else the smallest)."""

@final
class Model:
    """``coefficients``: (2, 10) for the quadratic basis, (2, 3, n_y, n_x) (component, force term
    1/h/h^2, y function, x function; n_y, n_x >= 4) for the B-spline basis."""

    def __new__(
        cls,
        basis: _Basis,
        coefficients: npt.NDArray[np.float64],
        normalization: npt.NDArray[np.float64],
        *,
        n_intervals: int,
        coupling: _Coupling,
        integration: _Integration,
        frame_shape: tuple[int, int],
    ) -> Model: ...
    @property
    def basis(self) -> _Basis: ...
    @property
    def frame_shape(self) -> tuple[int, int]: ...
    @property
    def n_intervals(self) -> int: ...
    @property
    def coupling(self) -> _Coupling: ...
    @property
    def integration(self) -> _Integration: ...
    def rate(self, h_mm: float, rows: int, cols: int) -> npt.NDArray[np.float64]: ...
    def displacement(
        self, force_n: float, profile: tuple[float, float, float], rows: int, cols: int
    ) -> npt.NDArray[np.float64]: ...
    def force_integrals(self, force_n: float, profile: tuple[float, float, float]) -> tuple[float, float, float]: ...

@final
class VesselPart:
    """The vessel part of a vessel-anchored model: ``coefficients`` (2, 3, n, n) (component, force term
    1/h/h^2, y and x inner function), the reference lumen's radius (pixels) and the window's half-width
    in lumen radii."""

    def __new__(
        cls, coefficients: npt.NDArray[np.float64], reference_radius_px: float, window_radii: float
    ) -> VesselPart: ...
    def displacement(
        self,
        model: Model,
        force_n: float,
        profile: tuple[float, float, float],
        anchor: tuple[float, float, float] | None,
        rows: tuple[int, int],
        cols: tuple[int, int],
    ) -> npt.NDArray[np.float64]:
        """``D(x, y, F)`` (2, window rows, window columns), pixels: ``model``'s image part plus this part on
        ``anchor`` (x, y, radius; None: the image part alone), on the rows and columns (start, stop)."""

@final
class LumenSearch:
    """The lumen search's settings with a model's reference lumen (x, y, radius), pixels."""

    def __new__(
        cls,
        reference: tuple[float, float, float],
        *,
        window_radii: float,
        tolerance_px: float,
        max_iterations: int,
        smoothing_sigma_px: float,
        threshold_fraction: float,
        min_contrast: float,
        min_area_px: int,
    ) -> LumenSearch: ...

def sweep_lumens(
    frames: _Frames,
    forces: npt.NDArray[np.float64],
    profiles: npt.NDArray[np.float64],
    model: Model,
    vessel: VesselPart,
    search: LumenSearch,
    *,
    last_found: tuple[float, float, float] | None,
    frames_missed: int,
) -> tuple[list[tuple[float, float, float] | None], tuple[float, float, float] | None, int]:
    """Each frame's zero-force lumen (x, y, radius) or None, and where the search stands after the last
    frame (last_found, frames_missed)."""

def force_integrals(
    force_n: float,
    profile: tuple[float, float, float],
    normalization: npt.NDArray[np.float64],
    n_intervals: int,
    integration: _Integration = "force",
) -> tuple[float, float, float]: ...
@overload
def warp_frames(
    frames: _Frames,
    forces: npt.NDArray[np.float64],
    profiles: npt.NDArray[np.float64],
    model: Model,
    *,
    fill: float = 0.0,
    threads: int | None = None,
    return_mask: Literal[False] = False,
    vessel: VesselPart | None = None,
    anchors: npt.NDArray[np.float64] | None = None,
) -> _Frames: ...
@overload
def warp_frames(
    frames: _Frames,
    forces: npt.NDArray[np.float64],
    profiles: npt.NDArray[np.float64],
    model: Model,
    *,
    fill: float = 0.0,
    threads: int | None = None,
    return_mask: Literal[True],
    vessel: VesselPart | None = None,
    anchors: npt.NDArray[np.float64] | None = None,
) -> tuple[_Frames, npt.NDArray[np.bool_]]: ...
def warp_by_field(
    frames: _Frames,
    displacements: npt.NDArray[np.float64],
    *,
    fill: float = 0.0,
    threads: int | None = None,
) -> tuple[_Frames, npt.NDArray[np.bool_]]: ...
def _panic_for_tests() -> None: ...

@final
class Accumulator:
    def __new__(
        cls,
        shape: tuple[int, int, int],
        index_to_world: npt.NDArray[np.float64],
        interpolation: _Interpolation,
        compounding: _Compounding,
        max_bytes: int,
    ) -> Accumulator: ...
    def insert(
        self,
        frames: _Frames,
        image_to_world: npt.NDArray[np.float64],
        *,
        valid: npt.NDArray[np.bool_] | None = None,
        threads: int | None = None,
    ) -> None: ...
    def insert_corrected(
        self,
        frames: _Frames,
        image_to_world: npt.NDArray[np.float64],
        forces: npt.NDArray[np.float64],
        profiles: npt.NDArray[np.float64],
        model: Model,
        *,
        fill: float = 0.0,
        exclude_invalid: bool = True,
        threads: int | None = None,
        vessel: VesselPart | None = None,
        anchors: npt.NDArray[np.float64] | None = None,
    ) -> None: ...
    def insert_anchored(
        self,
        frames: _Frames,
        image_to_world: npt.NDArray[np.float64],
        forces: npt.NDArray[np.float64],
        profiles: npt.NDArray[np.float64],
        model: Model,
        vessel: VesselPart,
        search: LumenSearch,
        *,
        last_found: tuple[float, float, float] | None,
        frames_missed: int,
        fill: float = 0.0,
        exclude_invalid: bool = True,
        threads: int | None = None,
    ) -> tuple[tuple[float, float, float] | None, int]:
        """``sweep_lumens`` then ``insert_corrected`` with each frame's vessel part on its lumen (or the
        last found before it), the search on a thread of its own while found frames are inserted;
        returns where the search stands after the last frame (last_found, frames_missed)."""
    def volume(self) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]: ...
    def volume_region(
        self, lo: tuple[int, int, int], hi: tuple[int, int, int]
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]: ...
    @property
    def frames_inserted(self) -> int: ...
    @property
    def shape(self) -> tuple[int, int, int]: ...

def fill_holes(
    image: npt.NDArray[np.uint8] | npt.NDArray[np.float32],
    weight: npt.NDArray[np.float32],
    elements: list[tuple[str, int, float, float, int, int]],
    min_known_weight: float,
    max_bytes: int,
    threads: int | None = None,
) -> npt.NDArray[np.uint8] | npt.NDArray[np.float32]: ...
def affine_lucas_kanade(
    before: npt.NDArray[np.float32],
    gradient_x: npt.NDArray[np.float32],
    gradient_y: npt.NDArray[np.float32],
    after: npt.NDArray[np.float32],
    start: npt.NDArray[np.float32],
    initial: npt.NDArray[np.float32],
    window_px: tuple[int, int],
    *,
    max_iterations: int = 30,
    epsilon: float = 0.01,
    threads: int | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_], npt.NDArray[np.float64]]:
    """Where the (width, height) ``window_px`` window of ``before`` around each (N, 2) point ``start``
    lies in ``after`` under an affine warp, from ``initial`` (N, 2): (tracked (N, 2), ok (N,),
    correlation (N,)). ``before``, its pixel-unit gradients and ``after`` are (rows, cols) float32."""

def patch_correlation(
    before: npt.NDArray[np.uint8],
    after: npt.NDArray[np.uint8],
    start: npt.NDArray[np.float32],
    end: npt.NDArray[np.float32],
    window_px: tuple[int, int],
    *,
    threads: int | None = None,
) -> npt.NDArray[np.float64]:
    """(N,) normalised correlation of the (width, height) ``window_px`` patches of the (rows, cols) uint8
    ``before`` around the (N, 2) points ``start`` and of ``after`` around ``end``, sampled as ``cv2.remap``
    (bilinear, 8 bits, edge replicated); zero-mean patches, 0 where one is flat; without the GIL."""

def block_match(
    before: npt.NDArray[np.float32],
    after: npt.NDArray[np.float32],
    patch: int,
    spacing: int,
    search: int,
    *,
    threads: int | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """Block matching of (rows, cols) float32 frames (``cv2.matchTemplate``'s ``TM_CCOEFF_NORMED``): the
    ``patch``-sided blocks of ``before`` on nodes ``spacing`` apart searched over +-``search`` pixels of
    ``after``; (flow (node rows, node cols, 2) (dx, dy), peak (node rows, node cols), on the search range's
    edge (node rows, node cols)); without the GIL."""

def crc64(data: npt.NDArray[np.uint8], crc: int = 0) -> int:
    """The OpenIGTLink CRC-64 (ECMA-182 polynomial, not reflected, initial value 0, no final XOR) of
    ``data`` (n,) continued from ``crc`` (the CRC of the bytes before it); without the GIL."""

def splat_bilinear(
    fine_col: npt.NDArray[np.float64],
    fine_row: npt.NDArray[np.float64],
    weight_real: npt.NDArray[np.float64],
    weight_imag: npt.NDArray[np.float64],
    grid_shape: tuple[int, int],
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """(real, imag) float32 grids of ``grid_shape``: the weights splatted bilinearly at (col, row) (cells), summed
    in np.bincount's order; non-finite values refused; without the GIL."""
