"""Benchmark of the Rust kernels against the NumPy reference, plain Python loops and OpenCV.

Workload (default): a sweep of 400 frames of 256 x 256 uint8 pixels, each corrected to zero force
with the quadratic regression and compounded into a 200^3 voxel grid. Rust runs the whole workload;
the NumPy reference and the Python loops run a subset of frames and are extrapolated per pixel
(stated in the table). Prints throughput in pixels per second and the ratios.

    python benches/bench_kernels.py            # full workload
    python benches/bench_kernels.py --quick    # small smoke run
"""

from __future__ import annotations

import os

# OpenBLAS worker threads spin after any linear-algebra call and take a core from the kernels being
# timed; nothing here needs a threaded BLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import statistics
import time
from collections.abc import Callable

import cv2
import numpy as np

from python_loop import correct_and_compound
from usdeform import reference
from usdeform.compounding import Compounder
from usdeform.correction import correct_frames
from usdeform.options import INTERPOLATIONS, Interpolation
from usdeform.regression import BSplineDisplacementModel, Normalization, QuadraticDisplacementModel
from usdeform.stiffness import StiffnessProfile
from usdeform.volume import VoxelGrid


def median_seconds(run: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def make_workload(n_frames: int, rows: int, cols: int, voxels: int, seed: int = 0):
    """A synthetic force-controlled sweep along the base y axis through a cubic voxel grid."""
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, (n_frames, rows, cols), dtype=np.uint8)
    image_to_probe = np.array([[37.5 / cols, 0, 0, -37.5 / 2], [0, 0, -1, 0], [0, 40.0 / rows, 0, 0], [0, 0, 0, 1]])
    probe_to_base = np.repeat(np.eye(4)[np.newaxis], n_frames, axis=0)
    probe_to_base[:, 1, 3] = np.linspace(-20, 20, n_frames)  # 40 mm sweep
    image_to_world = probe_to_base @ image_to_probe
    spacing = 50.0 / voxels
    grid = VoxelGrid(
        (voxels,) * 3,
        np.diag([spacing, spacing, spacing, 1.0])
        + np.array([[0, 0, 0, -25], [0, 0, 0, -25], [0, 0, 0, -5], [0, 0, 0, 0]]),
    )
    normalization = Normalization.for_frames(
        rows, cols, max_force_n=20.0, max_h_mm=10.0, lateral_scale=cols * 0.02, axial_scale=rows * 0.06
    )
    model = QuadraticDisplacementModel(rng.normal(0, 0.3, (2, 10)), normalization, n_intervals=64)
    forces = rng.uniform(4, 16, n_frames)
    profile = StiffnessProfile(0.08, 0.6, 0.0)
    return frames, image_to_world, grid, model, forces, profile


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--size", type=int, default=256, help="frame rows = cols")
    parser.add_argument("--voxels", type=int, default=200, help="voxels per grid axis")
    parser.add_argument("--numpy-frames", type=int, default=20, help="frames the NumPy reference runs")
    parser.add_argument("--loop-frames", type=int, default=1, help="frames the Python loops run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="small workload, for a smoke test")
    args = parser.parse_args()
    if args.quick:
        args.frames, args.size, args.voxels, args.numpy_frames, args.repeats = 24, 64, 48, 4, 1
    frames, image_to_world, grid, model, forces, profile = make_workload(args.frames, args.size, args.size, args.voxels)
    n_frames, rows, cols = frames.shape
    pixels = frames.size
    subset = slice(0, min(args.numpy_frames, n_frames))
    subset_pixels = frames[subset].size
    profiles = np.tile(profile.as_tuple(), (n_frames, 1))
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float32)

    rows_out: list[tuple[str, str, float]] = []

    def record(stage: str, implementation: str, seconds: float, n_pixels: int) -> None:
        rows_out.append((stage, implementation, n_pixels / seconds))

    # 1. Regression evaluation: D(x, y, F) of every frame on the pixel grid.
    record(
        "regression D(x,y,F)",
        "rust",
        median_seconds(lambda: [model.displacement(f, profile, (rows, cols)) for f in forces], args.repeats),
        pixels,
    )
    record(
        "regression D(x,y,F)",
        "numpy reference",
        median_seconds(
            lambda: [reference.integrated_displacement(model, f, profile, (rows, cols)) for f in forces[subset]],
            args.repeats,
        ),
        subset_pixels,
    )

    # 2. Warping to zero force.
    record(
        "warp",
        "rust (regression on the fly)",
        median_seconds(lambda: correct_frames(frames, forces, profile, model), args.repeats),
        pixels,
    )
    spline = BSplineDisplacementModel(
        np.random.default_rng(1).normal(0, 0.1, (2, 3, 8, 8)), model.normalization, model.n_intervals
    )
    record(
        "warp",
        "rust, cubic B-spline 8 x 8 basis",
        median_seconds(lambda: correct_frames(frames, forces, profile, spline), args.repeats),
        pixels,
    )

    def numpy_map_then_remap() -> None:
        for frame, force in zip(frames, forces, strict=False):
            lateral, axial = model.displacement(force, profile, (rows, cols))
            cv2.remap(
                frame,
                x + lateral.astype(np.float32),
                y + axial.astype(np.float32),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0,
            )

    def numpy_map_reference_then_remap() -> None:
        for frame, force in zip(frames, forces, strict=False):
            lateral, axial = reference.integrated_displacement(model, force, profile, (rows, cols))
            cv2.remap(
                frame,
                x + lateral.astype(np.float32),
                y + axial.astype(np.float32),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0,
            )

    maps = [
        (x + d[0].astype(np.float32), y + d[1].astype(np.float32))
        for d in (model.displacement(f, profile, (rows, cols)) for f in forces)
    ]

    def remap_only() -> None:
        for frame, (map_x, map_y) in zip(frames, maps, strict=False):
            cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    record(
        "warp",
        "numpy map (reference) + cv2.remap",
        median_seconds(numpy_map_reference_then_remap, args.repeats),
        pixels,
    )
    record("warp", "numpy map (rust D) + cv2.remap", median_seconds(numpy_map_then_remap, args.repeats), pixels)
    record("warp", "cv2.remap alone (map precomputed)", median_seconds(remap_only, args.repeats), pixels)
    record(
        "warp",
        "numpy reference",
        median_seconds(
            lambda: reference.warp_frames(frames[subset], forces[subset], profiles[subset], model),
            args.repeats,
        ),
        subset_pixels,
    )

    # 3. Compounding of uncorrected frames.
    for interpolation in INTERPOLATIONS:
        stage = f"compound {interpolation} mean"

        def rust_compound(interpolation: Interpolation = interpolation) -> None:
            compounder = Compounder(grid, interpolation, "mean")
            compounder.add_frames(frames, image_to_world)
            compounder.volume()

        record(stage, "rust", median_seconds(rust_compound, args.repeats), pixels)
        record(
            stage,
            "numpy reference",
            median_seconds(
                lambda interpolation=interpolation: reference.compound_frames(
                    frames[subset], image_to_world[subset], grid, interpolation, "mean"
                ),
                1,
            ),
            subset_pixels,
        )

    # 4. Fused correction + compounding (the reconstruction of a sweep).
    def rust_fused() -> None:
        compounder = Compounder(grid, "nearest", "mean")
        compounder.add_corrected_frames(frames, image_to_world, forces, profile, model)
        compounder.volume()

    def numpy_fused() -> None:
        corrected = reference.warp_frames(frames[subset], forces[subset], profiles[subset], model)
        reference.compound_frames(corrected, image_to_world[subset], grid, "nearest", "mean")

    loop_subset = slice(0, args.loop_frames)
    stage = "correct + compound (nearest, mean)"
    record(stage, "rust fused", median_seconds(rust_fused, args.repeats), pixels)
    record(stage, "numpy reference", median_seconds(numpy_fused, 1), subset_pixels)
    record(
        stage,
        "python loops",
        median_seconds(
            lambda: correct_and_compound(
                frames[loop_subset], image_to_world[loop_subset], forces[loop_subset], profile, model, grid
            ),
            1,
        ),
        frames[loop_subset].size,
    )

    print(
        f"workload: {n_frames} frames of {rows} x {cols} uint8, grid {grid.shape[0]}^3 voxels; "
        f"numpy reference on {subset.stop} frames, python loops on {args.loop_frames} frame(s), "
        f"extrapolated per pixel; {os.cpu_count()} cores"
    )
    print(f"{'stage':38s} {'implementation':38s} {'Mpixel/s':>10s} {'rust / this':>12s}")
    rust_rate = {}
    for stage, implementation, rate in rows_out:
        if implementation.startswith("rust"):
            rust_rate.setdefault(stage, rate)
    for stage, implementation, rate in rows_out:
        ratio = rust_rate[stage] / rate
        print(f"{stage:38s} {implementation:38s} {rate / 1e6:10.2f} {ratio:11.1f}x")


if __name__ == "__main__":
    main()
