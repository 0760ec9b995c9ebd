"""A small end-to-end run of the kernels on synthetic frames: correct a sweep, compound, write volumes.

The sweep is made here with a known displacement model: zero-force frames of a straight vessel in
speckle are compressed by the model at each frame's force (a force-controlled sweep around 8 N on a
stiffening tissue), then corrected back with the same model and compounded. It checks the plumbing
(correction + compounding + volume files) on data whose answer is known; the physical simulator
(``usdeform.sim``) is the data for the method's experiments.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .compounding import Compounder, grid_for_frames
from .correction import correct_frames
from .io import write_volume
from .regression import Normalization, QuadraticDisplacementModel
from .stiffness import StiffnessProfile

__all__ = ["DemoResult", "run_demo"]

PROBE_WIDTH_MM, IMAGE_DEPTH_MM = 37.5, 40.0


@dataclass(frozen=True)
class DemoResult:
    """Where the volumes went and the vessel cross-section area (mm^2) in the middle frame."""

    corrected_path: Path
    deformed_path: Path
    coverage_path: Path
    area_zero_force_mm2: float
    area_deformed_mm2: float
    area_corrected_mm2: float
    seconds: float


def _compression_model(rows: int, cols: int) -> QuadraticDisplacementModel:
    """Tissue moving up towards the probe more with depth (axial compression; the top row fixed) and
    bulging sideways away from the centre line, both growing with force and softer tissue."""
    coefficients = np.zeros((2, 10))
    coefficients[0, [3, 7]] = [0.3, -0.15]  # xy, y: lateral bulge, zero on the centre column
    coefficients[1, [1, 5, 7]] = [0.4, -0.8, -1.0]  # y^2, yh, y: upward motion growing with depth
    normalization = Normalization.for_frames(
        rows, cols, max_force_n=10.0, max_h_mm=4.0, lateral_scale=0.04 * cols, axial_scale=0.08 * rows
    )
    return QuadraticDisplacementModel(coefficients, normalization, n_intervals=64)


def _vessel_frames(n_frames: int, rows: int, cols: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Zero-force frames: smoothed speckle, an anechoic lumen whose depth drifts along the sweep."""
    speckle = rng.rayleigh(1.0, (n_frames, rows, cols)).astype(np.float32)
    y, x = np.mgrid[0:rows, 0:cols]
    frames, masks = np.empty((n_frames, rows, cols), np.uint8), np.empty((n_frames, rows, cols), bool)
    for index in range(n_frames):
        centre_y = rows * (0.45 + 0.05 * np.sin(index / n_frames * np.pi))
        lumen = (x - cols / 2) ** 2 + (y - centre_y) ** 2 < (0.16 * rows) ** 2
        image = cv2.GaussianBlur(speckle[index], (0, 0), 1.0) * (1.0 - 0.9 * lumen)
        frames[index] = np.clip(image * 90, 0, 255).astype(np.uint8)
        masks[index] = lumen
    return frames, masks


def _compress(
    frames: np.ndarray, forces: np.ndarray, profile: StiffnessProfile, model: QuadraticDisplacementModel
) -> np.ndarray:
    """Deformed frames: the zero-force pixel at x appears at x + D(x), so the deformed frame at p is
    the zero-force frame at the fixed point x = p - D(x) (three iterations)."""
    rows, cols = frames.shape[1:]
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float32)
    out = np.empty_like(frames)
    for index, (frame, force) in enumerate(zip(frames, forces, strict=False)):
        lateral, axial = model.displacement(force, profile, (rows, cols)).astype(np.float32)
        source_x, source_y = x.copy(), y.copy()
        for _ in range(3):
            shift_x = cv2.remap(lateral, source_x, source_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            shift_y = cv2.remap(axial, source_x, source_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            source_x, source_y = x - shift_x, y - shift_y
        out[index] = cv2.remap(frame, source_x, source_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return out


def _lumen_area_mm2(frame: np.ndarray, pixel_area_mm2: float) -> float:
    """Area of the dark blob containing the frame centre column's darkest smoothed point, mm^2."""
    smooth = cv2.GaussianBlur(frame, (0, 0), 2.0)
    dark = (smooth < 0.35 * np.median(smooth)).astype(np.uint8)
    count, _labels, stats, _ = cv2.connectedComponentsWithStats(dark)
    if count < 2:
        return 0.0
    return float(stats[1:, cv2.CC_STAT_AREA].max()) * pixel_area_mm2


def run_demo(output_dir: str | Path, n_frames: int = 200, size: int = 128, seed: int = 0) -> DemoResult:
    """Make, correct and compound a synthetic sweep; write the volumes (NRRD) into ``output_dir``."""
    start = time.perf_counter()
    output = Path(output_dir)
    output.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rows = cols = size
    model = _compression_model(rows, cols)
    profile = StiffnessProfile(c1=0.05, c2=1.2, c3=0.0)  # stiffening tissue, N/mm^2 and N/mm
    forces = 8.0 + 0.5 * np.sin(np.linspace(0, 6 * np.pi, n_frames)) + rng.normal(0, 0.1, n_frames)
    zero_force, _ = _vessel_frames(n_frames, rows, cols, rng)
    deformed = _compress(zero_force, forces, profile, model)

    image_to_probe = np.array(
        [
            [PROBE_WIDTH_MM / cols, 0, 0, -PROBE_WIDTH_MM / 2],
            [0, 0, -1, 0],
            [0, IMAGE_DEPTH_MM / rows, 0, 0],
            [0, 0, 0, 1],
        ]
    )
    probe_to_base = np.repeat(np.eye(4)[np.newaxis], n_frames, axis=0)
    probe_to_base[:, 1, 3] = np.linspace(0.0, 40.0, n_frames)  # a 40 mm sweep along the base y axis
    image_to_base = probe_to_base @ image_to_probe
    grid = grid_for_frames(image_to_base, (rows, cols), spacing_mm=0.4)

    corrected_volume = Compounder(grid, "linear", "mean")
    corrected_volume.add_corrected_frames(deformed, image_to_base, forces, profile, model)
    deformed_volume = Compounder(grid, "linear", "mean")
    deformed_volume.add_frames(deformed, image_to_base)

    paths = (output / "corrected.nrrd", output / "deformed.nrrd", output / "coverage.nrrd")
    volume = corrected_volume.volume()
    write_volume(paths[0], volume, weight_path=paths[2])
    write_volume(paths[1], deformed_volume.volume())

    middle = n_frames // 2
    corrected_middle = correct_frames(deformed[middle], forces[middle], profile, model)
    pixel_area = (PROBE_WIDTH_MM / cols) * (IMAGE_DEPTH_MM / rows)
    return DemoResult(
        *paths,
        _lumen_area_mm2(zero_force[middle], pixel_area),
        _lumen_area_mm2(deformed[middle], pixel_area),
        _lumen_area_mm2(corrected_middle, pixel_area),
        time.perf_counter() - start,
    )
