"""Random inputs shared by the kernel tests: models, stiffness profiles, frames, poses."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from usdeform.regression import (
    BSplineDisplacementModel,
    Normalization,
    QuadraticDisplacementModel,
    StiffnessProfile,
    VesselAnchor,
    VesselAnchoredModel,
)
from usdeform.volume import VoxelGrid


def random_model(rng: np.random.Generator, rows: int, cols: int, n_intervals: int = 32) -> QuadraticDisplacementModel:
    """A model whose displacements reach a few pixels to a few tens of pixels."""
    normalization = Normalization.for_frames(
        rows,
        cols,
        max_force_n=rng.uniform(5, 40),
        max_h_mm=rng.uniform(2, 15),
        lateral_scale=rng.uniform(-8, 8),
        axial_scale=rng.uniform(-20, 20),
    )
    return QuadraticDisplacementModel(rng.normal(size=(2, 10)), normalization, n_intervals, frame_shape=(rows, cols))


def random_bspline_model(
    rng: np.random.Generator, rows: int, cols: int, n_intervals: int = 32, max_functions: int = 9
) -> BSplineDisplacementModel:
    """A cubic B-spline model of random size (4 to ``max_functions`` functions per axis) on the
    normalisation of :func:`random_model`."""
    normalization = random_model(rng, rows, cols, n_intervals).normalization
    n_y, n_x = rng.integers(4, max_functions + 1, 2)
    return BSplineDisplacementModel(
        rng.normal(size=(2, 3, n_y, n_x)), normalization, n_intervals, frame_shape=(rows, cols)
    )


def random_profile(rng: np.random.Generator) -> StiffnessProfile:
    """A stiffening (c1 >= 0) profile whose rising branch covers every force >= 0."""
    return StiffnessProfile(rng.uniform(0.0, 0.5), rng.uniform(0.5, 4.0), rng.uniform(-0.5, 0.1))


def random_frames(rng: np.random.Generator, n_frames: int, rows: int, cols: int, dtype: type) -> np.ndarray:
    if dtype == np.uint8:
        return rng.integers(0, 256, (n_frames, rows, cols), dtype=np.uint8)
    return rng.normal(100.0, 40.0, (n_frames, rows, cols)).astype(np.float32)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def random_sweep_poses(rng: np.random.Generator, n_frames: int, rows: int, cols: int, grid: VoxelGrid) -> np.ndarray:
    """Poses of a roughly linear sweep through the middle of ``grid``, pixel size about one voxel,
    with random orientation (edge cases: frames partly outside the grid)."""
    spacing = grid.spacing
    # A random sub-voxel offset keeps pixel centres off exact voxel boundaries, where the rounding
    # of the nearest voxel would hinge on the last bit of the arithmetic.
    centre_index = (np.array(grid.shape[::-1]) - 1) / 2.0 + rng.uniform(-0.5, 0.5, 3)
    centre = grid.index_to_world @ np.append(centre_index, 1.0)
    rotation = random_rotation(rng)
    pixel_mm = rng.uniform(0.5, 1.5) * spacing.mean()
    step = rng.normal(size=3) * spacing.mean() * 0.7
    poses = np.zeros((n_frames, 4, 4))
    for index in range(n_frames):
        pose = np.eye(4)
        pose[:3, :3] = rotation * pixel_mm
        pose[:3, 3] = centre[:3] - rotation @ (np.array([cols, rows, 0]) * pixel_mm / 2) + step * (index - n_frames / 2)
        poses[index] = pose
    return poses


def random_tracking_pair(
    rng: np.random.Generator, rows: int, cols: int, n_points: int, speckle_px: float = 1.5
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """Inputs of the affine Lucas-Kanade kernel: ``(before, gradient_x, gradient_y, after)`` float32
    (smoothed speckle; ``after`` the same under a random affine motion of a few per cent strain and a few
    pixels, plus noise), and ``start``, ``initial`` (n_points, 2) float32, some near or beyond the edges,
    ``initial`` about 1 px from where the motion takes ``start`` (the last (n_points, 2), float64)."""
    margin = 30
    noise = rng.normal(size=(rows + 2 * margin, cols + 2 * margin)).astype(np.float32)
    texture = cv2.GaussianBlur(noise, (0, 0), speckle_px) * (60.0 * speckle_px) + 100.0
    before = np.ascontiguousarray(texture[margin : margin + rows, margin : margin + cols])
    # after(x') = before(B x' + c): a point x of before moves to B^-1 (x - c).
    inverse_linear, inverse_shift = np.eye(2) + rng.uniform(-0.06, 0.06, (2, 2)), rng.uniform(-3, 3, 2)
    to_texture = np.column_stack([inverse_linear, inverse_shift + margin])  # before's origin at (margin, margin)
    after = cv2.warpAffine(texture, to_texture, (cols, rows), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    after = (after + rng.normal(0, 2.0, after.shape)).astype(np.float32)
    gradient_x, gradient_y = (
        np.asarray(cv2.Scharr(before, cv2.CV_32F, dx, 1 - dx, scale=1.0 / 32.0), dtype=np.float32) for dx in (1, 0)
    )
    start = rng.uniform([-4, -4], [cols + 3, rows + 3], (n_points, 2))
    moved = np.linalg.solve(inverse_linear, (start - inverse_shift).T).T
    initial = moved + rng.normal(0, 1.0, moved.shape)
    return (before, gradient_x, gradient_y, after), start.astype(np.float32), initial.astype(np.float32), moved


def random_anchored_model(
    rng: np.random.Generator, rows: int, cols: int, image_scale: float = 1.0, n_intervals: int = 32
) -> VesselAnchoredModel:
    """A vessel-anchored model: a random B-spline image part (coefficients times ``image_scale``) and
    a vessel part of 1 to 5 inner functions per axis whose collapse reaches a few pixels, on a
    reference lumen of an eighth of the frame in its middle."""
    image = random_bspline_model(rng, rows, cols, n_intervals)
    image = replace(image, coefficients=image.coefficients * image_scale)
    n_inner = int(rng.integers(1, 6))
    reference = VesselAnchor((cols / 2, rows / 2), max(min(rows, cols) / 8, 1.0))
    return VesselAnchoredModel(image, rng.normal(0, 0.3, (2, 3, n_inner, n_inner)), reference)


def vessel_frames(
    rng: np.random.Generator, centres_px: np.ndarray, radius_px: float, rows: int, cols: int
) -> np.ndarray:
    """Speckle frames (uint8, blurred gamma noise about 120) with an anechoic round lumen of
    ``radius_px`` at each ``(x, y)`` of ``centres_px`` (n_frames, 2): a sweep the lumen search follows."""
    speckle = rng.gamma(2.0, 60.0, (len(centres_px), rows, cols)).astype(np.float32)
    y, x = np.mgrid[0:rows, 0:cols]
    frames = []
    for image, (cx, cy) in zip(speckle, centres_px, strict=True):
        blurred = cv2.GaussianBlur(image, (0, 0), 1.0)
        blurred[(x - cx) ** 2 + (y - cy) ** 2 < radius_px**2] *= 0.08
        frames.append(np.clip(blurred, 0, 255).astype(np.uint8))
    return np.stack(frames)


def anchored_sweep_case(
    rng: np.random.Generator, rows: int, cols: int, centres: np.ndarray, radius: float, grid: VoxelGrid
) -> tuple:
    """A vessel-anchored model, a sweep whose lumen (``radius`` px) lies at ``centres`` (n, 2; one far outside
    the frame: no lumen), poses into ``grid``, forces within the model's range and a profile."""
    n_frames = len(centres)
    model = random_anchored_model(rng, rows, cols, image_scale=0.1)
    frames = vessel_frames(rng, centres, radius, rows, cols)
    poses = random_sweep_poses(rng, n_frames, rows, cols, grid)
    forces = rng.uniform(0.2, 0.8, n_frames) * model.normalization.force_scale
    return model, frames, poses, forces, random_profile(rng)
