"""Type stub of the compiled kernels (rust/python/src/lib.rs). Checked against the binary by the tests.

``coefficients`` everywhere: shape (2, 10) for the paper's quadratic model, or (2, 3, n_y, n_x)
(component, force term 1/h/h^2, y function, x function; n_y, n_x >= 4) for the cubic B-spline model.
"""

from typing import final

import numpy as np
import numpy.typing as npt

__all__ = [
    "BYTES_PER_VOXEL",
    "Accumulator",
    "_panic_for_tests",
    "fill_holes",
    "force_integrals",
    "integrated_displacement",
    "regression_rate",
    "warp_frames",
]

BYTES_PER_VOXEL: int

def regression_rate(
    coefficients: npt.NDArray[np.float64],
    normalization: npt.NDArray[np.float64],
    h_mm: float,
    rows: int,
    cols: int,
) -> npt.NDArray[np.float64]: ...
def force_integrals(
    force_n: float,
    profile: tuple[float, float, float],
    normalization: npt.NDArray[np.float64],
    n_intervals: int,
    integration: str = "force",
) -> tuple[float, float, float]: ...
def integrated_displacement(
    coefficients: npt.NDArray[np.float64],
    normalization: npt.NDArray[np.float64],
    force_n: float,
    profile: tuple[float, float, float],
    n_intervals: int,
    rows: int,
    cols: int,
    integration: str = "force",
) -> npt.NDArray[np.float64]: ...
def warp_frames(
    frames: npt.NDArray[np.uint8] | npt.NDArray[np.float32],
    forces: npt.NDArray[np.float64],
    profiles: npt.NDArray[np.float64],
    coefficients: npt.NDArray[np.float64],
    normalization: npt.NDArray[np.float64],
    n_intervals: int,
    integration: str = "force",
    fill: float = 0.0,
    threads: int | None = None,
) -> npt.NDArray[np.uint8] | npt.NDArray[np.float32]: ...
def _panic_for_tests() -> None: ...

@final
class Accumulator:
    def __new__(
        cls,
        shape: tuple[int, int, int],
        index_to_world: npt.NDArray[np.float64],
        interpolation: str,
        compounding: str,
        max_bytes: int,
    ) -> Accumulator: ...
    def insert(
        self,
        frames: npt.NDArray[np.uint8] | npt.NDArray[np.float32],
        image_to_world: npt.NDArray[np.float64],
        threads: int | None = None,
    ) -> None: ...
    def insert_corrected(
        self,
        frames: npt.NDArray[np.uint8] | npt.NDArray[np.float32],
        image_to_world: npt.NDArray[np.float64],
        forces: npt.NDArray[np.float64],
        profiles: npt.NDArray[np.float64],
        coefficients: npt.NDArray[np.float64],
        normalization: npt.NDArray[np.float64],
        n_intervals: int,
        integration: str = "force",
        fill: float = 0.0,
        threads: int | None = None,
    ) -> None: ...
    def volume(self) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]: ...
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
