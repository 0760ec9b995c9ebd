"""Benchmark of the Rust kernels against a strong NumPy + OpenCV pipeline, the NumPy twins and plain Python.

Workload W1 (default): a sweep of 400 frames of 256 x 256 uint8 pixels, each corrected to zero force
and compounded (nearest voxel, mean) into a 200^3 voxel grid, with the package's DEFAULT settings (a
vessel-anchored model: a cubic B-spline 8 x 8 image part plus a 7 x 7 vessel part placed on each
frame's lumen, found in speckle frames showing a lumen of 29 pixels' radius that drifts across the
sweep; with 2 threads the package's lumen search runs on one while the other warps and inserts) and with
the FASTEST (the quadratic regression in image coordinates, on random frames). Every
contender runs the whole workload, with 1 and 2 threads where it can use them; only the plain Python
loops run one frame and are extrapolated (the table says so). Each contender runs in its own process,
so that its peak memory (resident set above the process before the run) is its own. The contenders
run in rounds, one after the other in each round, and each keeps its fastest round: on a shared
machine that is the run least disturbed by other processes, and every contender had the same chances
(the slow NumPy twins and Python loops run in the first round only). Each timed call of the other
contenders follows an untimed one in the same process, so that start-up (thread pools, lazy
initialisation, the process's first page faults) is not counted. Prints frames/s, the ratio of the
Rust kernel of the stage to each contender, frames per CPU second of the process (on a shared machine,
about the speed a single-threaded contender would have on a core of its own), peak memory, and the
memory-bandwidth floor of the fused path from a measured copy bandwidth.

    python benches/bench_kernels.py            # W1
    python benches/bench_kernels.py --quick    # small smoke run (the tests use it)
"""

from __future__ import annotations

import os

# OpenBLAS worker threads spin after any linear-algebra call and take a core from the kernels being
# timed; the thread counts here are set per contender.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from python_loop import correct_and_compound
from usdeform import reference
from usdeform.correction import correct_frames, vessel_placements
from usdeform.regression import (
    BSplineDisplacementModel,
    DeformationModel,
    Normalization,
    QuadraticDisplacementModel,
    StiffnessProfile,
    VesselAnchor,
    VesselAnchoredModel,
)
from usdeform.volume import Compounder, VoxelGrid


@dataclass(frozen=True)
class Workload:
    """A synthetic force-controlled sweep along the base y axis through a cubic voxel grid."""

    frames: np.ndarray
    image_to_world: np.ndarray
    grid: VoxelGrid
    model: QuadraticDisplacementModel
    forces: np.ndarray
    profile: StiffnessProfile
    #: The default settings' model and its frames (speckle with a drifting lumen).
    anchored: VesselAnchoredModel
    vessel_frames: np.ndarray

    @property
    def profiles(self) -> np.ndarray:
        return np.tile(self.profile.as_tuple(), (len(self.frames), 1))


def make_workload(n_frames: int, rows: int, cols: int, voxels: int, seed: int = 0) -> Workload:
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, (n_frames, rows, cols), dtype=np.uint8)
    image_to_probe = np.array([[37.5 / cols, 0, 0, -37.5 / 2], [0, 0, -1, 0], [0, 40.0 / rows, 0, 0], [0, 0, 0, 1]])
    probe_to_base = np.repeat(np.eye(4)[np.newaxis], n_frames, axis=0)
    probe_to_base[:, 1, 3] = np.linspace(-20, 20, n_frames)  # 40 mm sweep
    spacing = 50.0 / voxels
    grid = VoxelGrid(
        (voxels,) * 3,
        np.diag([spacing, spacing, spacing, 1.0])
        + np.array([[0, 0, 0, -25], [0, 0, 0, -25], [0, 0, 0, -5], [0, 0, 0, 0]]),
    )
    normalization = Normalization.for_frames(
        rows, cols, max_force_n=20.0, max_h_mm=10.0, lateral_scale=cols * 0.02, axial_scale=rows * 0.06
    )
    model = QuadraticDisplacementModel(
        rng.normal(0, 0.3, (2, 10)), normalization, n_intervals=64, frame_shape=(rows, cols)
    )
    forces = rng.uniform(4, 16, n_frames)
    anchored, vessel_frames = _default_settings(rng, n_frames, rows, cols, normalization)
    return Workload(
        frames,
        probe_to_base @ image_to_probe,
        grid,
        model,
        forces,
        StiffnessProfile(0.08, 0.6, 0.0),
        anchored,
        vessel_frames,
    )


def _default_settings(
    rng: np.random.Generator, n_frames: int, rows: int, cols: int, normalization: Normalization
) -> tuple[VesselAnchoredModel, np.ndarray]:
    """A vessel-anchored model (image part: cubic B-spline 8 x 8; vessel part: 7 x 7, a collapse of a few
    pixels) and speckle frames (uint8) whose anechoic lumen (radius 0.11 of the frame, as the demo's)
    drifts across a third of the frame and back."""
    radius = 0.11 * rows
    centres = np.column_stack(
        [cols * (0.5 + 0.15 * np.sin(np.linspace(0, 2 * np.pi, n_frames))), np.full(n_frames, 0.45 * rows)]
    )
    image_part = BSplineDisplacementModel(rng.normal(0, 0.1, (2, 3, 8, 8)), normalization, 64, frame_shape=(rows, cols))
    model = VesselAnchoredModel(image_part, rng.normal(0, 0.1, (2, 3, 7, 7)), VesselAnchor(tuple(centres[0]), radius))
    y, x = np.mgrid[0:rows, 0:cols]
    frames = np.empty((n_frames, rows, cols), dtype=np.uint8)
    for index, (cx, cy) in enumerate(centres):
        speckle = cv2.GaussianBlur(rng.gamma(2.0, 60.0, (rows, cols)).astype(np.float32), (0, 0), 1.0)
        speckle[(x - cx) ** 2 + (y - cy) ** 2 < radius**2] *= 0.08
        frames[index] = np.clip(speckle, 0, 255)
    return model, frames


class NumpyOpenCVPipeline:
    """Correction and compounding as a user would write them with NumPy and OpenCV.

    The model's field in image coordinates is linear in the three force integrals, so its three basis
    fields are evaluated once per model; per frame one matrix product gives the sampling map
    (interleaved x, y), one ``cv2.remap`` warps the frame, ``cv2.inRange`` on the map marks the pixels
    sampled from inside the frame (the others are left out), and one ``cv2.transform`` gives every
    pixel's float32 voxel position. The flat voxel indices of the whole sweep are counted with one
    ``np.bincount`` pair. Same conventions as the kernels (nearest voxel ``floor(index + 0.5)``,
    mean compounding).

    A vessel-anchored model's lumens are searched first with the same steps as the package's compiled
    search, written in Python with OpenCV (its twin, :func:`usdeform.reference.sweep_lumens`: per search
    one ``cv2.remap`` of the window and :func:`usdeform.metrics.segment_vessel`), with the field from NumPy
    (:meth:`displacement_on`: the basis fields on the window plus the model's NumPy
    ``vessel_displacement``); each frame's map then adds the vessel part on its lumen, evaluated
    within the vessel part's window only.
    """

    def __init__(self, model: DeformationModel, grid: VoxelGrid, frame_shape: tuple[int, int]) -> None:
        rows, cols = frame_shape
        self.model, self.grid, self.frame_shape = model.image_model, grid, frame_shape
        self.anchored = model if isinstance(model, VesselAnchoredModel) else None
        # (3, rows, cols, 2): the field of each force term, (x, y) interleaved as cv2.remap takes it.
        fields = [np.moveaxis(reference.field_for_terms(self.model, frame_shape, terms), 0, -1) for terms in np.eye(3)]
        self.fields = np.stack(fields)
        self.basis = self.fields.reshape(3, -1).astype(np.float32)
        y, x = np.mgrid[0:rows, 0:cols].astype(np.float32)
        self.pixels_xy = np.stack([x, y], axis=-1)  # (rows, cols, 2): the identity map
        self.world_to_index = np.linalg.inv(grid.index_to_world)
        nz, ny, nx = grid.shape
        self.n_voxels = nz * ny * nx
        # Largest float32 below each voxel count: inRange is inclusive.
        self.upper = tuple(float(np.nextafter(np.float32(n), np.float32(0))) for n in (nx, ny, nz))

    def terms(self, force_n: float, profile: StiffnessProfile) -> tuple[float, float, float]:
        """The force integrals of the frame (the model's coupling applied)."""
        coupled = profile if self.model.coupling == "stiffness" else StiffnessProfile.UNIT
        return reference.force_integrals(force_n, coupled, self.model.normalization, self.model.integration)

    def displacement_on(
        self, force_n: float, profile: StiffnessProfile, lumen: VesselAnchor | None, window: tuple[slice, slice]
    ) -> np.ndarray:
        """The vessel-anchored model's field on ``window``, (2, window rows, window columns), pixels."""
        assert self.anchored is not None
        terms = self.terms(force_n, profile)
        field = np.moveaxis(np.tensordot(terms, self.fields[:, window[0], window[1]], 1), -1, 0)
        if lumen is None:
            return field
        return field + self.anchored.vessel_displacement(force_n, profile, self.frame_shape, lumen, window=window)

    def maps(self, force_n: float, profile: StiffnessProfile, lumen: np.ndarray | None = None) -> np.ndarray:
        """The frame's sampling map, float32 (rows, cols, 2) of (x, y); with the vessel part on ``lumen``
        ((x, y, radius), pixels) of a vessel-anchored model."""
        maps = (np.asarray(self.terms(force_n, profile), dtype=np.float32) @ self.basis).reshape(self.pixels_xy.shape)
        maps += self.pixels_xy
        if self.anchored is not None and lumen is not None:
            (cx, cy, radius), (rows, cols) = lumen, self.frame_shape
            half = self.anchored.window_radii * radius
            window = (
                slice(max(int(np.floor(cy - half)), 0), max(min(int(np.ceil(cy + half)) + 1, rows), 0)),
                slice(max(int(np.floor(cx - half)), 0), max(min(int(np.ceil(cx + half)) + 1, cols), 0)),
            )
            anchor = VesselAnchor((cx, cy), radius)
            vessel = self.anchored.vessel_displacement(force_n, profile, self.frame_shape, anchor, window=window)
            maps[window] += np.moveaxis(vessel, 0, -1).astype(np.float32)
        return maps

    def warp(
        self,
        frame: np.ndarray,
        force_n: float,
        profile: StiffnessProfile,
        fill: float = 0.0,
        lumen: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One frame warped to zero force and its validity mask (255: sampled inside the frame, else 0)."""
        rows, cols = self.frame_shape
        maps = self.maps(force_n, profile, lumen)
        warped = cv2.remap(frame, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=fill)
        return warped, cv2.inRange(maps, (0.0, 0.0), (cols - 1.0, rows - 1.0))

    def flat_voxels(self, image_to_world: np.ndarray, valid: np.ndarray | None, out: np.ndarray) -> None:
        """Each pixel's flat nearest-voxel index into ``out``; the voxel count for pixels off the
        grid or invalid."""
        pixel_to_index = (self.world_to_index @ image_to_world)[:3, [0, 1, 3]]
        pixel_to_index[:, 2] += 0.5  # nearest voxel: floor(index + 0.5)
        position = cv2.transform(self.pixels_xy, pixel_to_index.astype(np.float32))
        inside = cv2.inRange(position, (0.0, 0.0, 0.0), self.upper)
        if valid is not None:
            np.bitwise_and(inside, valid, out=inside)
        voxel = position.astype(np.int32).reshape(-1, 3)  # truncation is floor where inside
        _, ny, nx = self.grid.shape
        np.multiply(voxel[:, 2], np.int64(ny * nx), out=out)
        out += voxel[:, 1] * np.int64(nx)
        out += voxel[:, 0]
        np.copyto(out, self.n_voxels, where=inside.ravel() == 0)

    def compound(
        self,
        frames: np.ndarray,
        image_to_world: np.ndarray,
        forces: np.ndarray | None = None,
        profile: StiffnessProfile | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(image, weight), float32 (z, y, x): frames corrected (when ``forces`` are given) and
        compounded, nearest voxel, mean."""
        flat = np.empty(frames.size, dtype=np.int64)
        values = np.empty(frames.size)  # float64, as np.bincount takes its weights
        size = frames[0].size
        lumens = None
        if self.anchored is not None and forces is not None and profile is not None:
            profiles = np.tile(profile.as_tuple(), (len(frames), 1))
            lumens = vessel_placements(
                reference.sweep_lumens(frames, forces, profiles, self.anchored, self.displacement_on), self.anchored
            )
        for index, frame in enumerate(frames):
            part = slice(index * size, (index + 1) * size)
            valid = None
            if forces is not None and profile is not None:
                lumen = None if lumens is None else lumens[index]
                frame, valid = self.warp(frame, float(forces[index]), profile, lumen=lumen)
            values[part] = frame.ravel()
            self.flat_voxels(image_to_world[index], valid, flat[part])
        n = self.n_voxels
        weight = np.bincount(flat, minlength=n + 1)[:n].astype(np.float32)
        sums = np.bincount(flat, weights=values, minlength=n + 1)[:n]
        image = np.zeros(n, dtype=np.float32)
        np.divide(sums, weight, out=image, where=weight > 0, casting="unsafe")
        return image.reshape(self.grid.shape), weight.reshape(self.grid.shape)


def reference_correct_and_compound(workload: Workload, frames_per_chunk: int = 50) -> np.ndarray:
    """The NumPy twins on the whole sweep: warp, then compound in chunks of frames (the twin holds
    every splat of its input at once), the chunks' means combined by their weights."""
    w = workload
    sums, weights = np.zeros(w.grid.shape), np.zeros(w.grid.shape)
    for start in range(0, len(w.frames), frames_per_chunk):
        part = slice(start, start + frames_per_chunk)
        corrected = reference.warp_frames(w.frames[part], w.forces[part], w.profiles[part], w.model)
        image, weight = reference.compound_frames(corrected, w.image_to_world[part], w.grid, "nearest", "mean")
        sums += image * weight
        weights += weight
    return np.divide(sums, weights, out=np.zeros_like(sums), where=weights > 0)


@dataclass(frozen=True)
class Contender:
    stage: str
    name: str
    threads: tuple[int, ...]
    #: Builds the timed call from the workload and a thread count (setup outside the timing).
    build: Callable[[Workload, int], Callable[[], object]]
    #: Rounds it runs in (None: --rounds); the slow ones run in the first round only.
    rounds: int | None = None
    #: Frames the call covers when not the whole sweep (extrapolated in the table).
    frames: int | None = None


def _rust_fused(w: Workload, threads: int) -> Callable[[], object]:
    def run() -> None:
        compounder = Compounder(w.grid, "nearest", "mean")
        compounder.add_corrected_frames(w.frames, w.image_to_world, w.forces, w.profile, w.model, threads=threads)
        compounder.volume()

    return run


def _rust_default(w: Workload, threads: int) -> Callable[[], object]:
    def run() -> None:
        compounder = Compounder(w.grid, "nearest", "mean")
        compounder.add_corrected_frames(
            w.vessel_frames, w.image_to_world, w.forces, w.profile, w.anchored, threads=threads
        )
        compounder.volume()

    return run


def _pipeline_default(w: Workload, threads: int) -> Callable[[], object]:
    pipeline = NumpyOpenCVPipeline(w.anchored, w.grid, w.frames.shape[1:])
    return lambda: pipeline.compound(w.vessel_frames, w.image_to_world, w.forces, w.profile)


def _pipeline_fused(w: Workload, threads: int) -> Callable[[], object]:
    pipeline = NumpyOpenCVPipeline(w.model, w.grid, w.frames.shape[1:])
    return lambda: pipeline.compound(w.frames, w.image_to_world, w.forces, w.profile)


def _python_loops(w: Workload, threads: int) -> Callable[[], object]:
    return lambda: correct_and_compound(w.frames[:1], w.image_to_world[:1], w.forces[:1], w.profile, w.model, w.grid)


def _rust_warp(w: Workload, threads: int) -> Callable[[], object]:
    return lambda: correct_frames(w.frames, w.forces, w.profile, w.model, threads=threads)


def _rust_warp_bspline(w: Workload, threads: int) -> Callable[[], object]:
    rng = np.random.default_rng(1)
    spline = BSplineDisplacementModel(
        rng.normal(0, 0.1, (2, 3, 8, 8)), w.model.normalization, w.model.n_intervals, frame_shape=w.frames.shape[1:]
    )
    return lambda: correct_frames(w.frames, w.forces, w.profile, spline, threads=threads)


def _pipeline_warp(w: Workload, threads: int) -> Callable[[], object]:
    pipeline = NumpyOpenCVPipeline(w.model, w.grid, w.frames.shape[1:])
    return lambda: [
        pipeline.warp(frame, float(force), w.profile) for frame, force in zip(w.frames, w.forces, strict=True)
    ]


def _remap_only(w: Workload, threads: int) -> Callable[[], object]:
    pipeline = NumpyOpenCVPipeline(w.model, w.grid, w.frames.shape[1:])
    maps = [pipeline.maps(float(force), w.profile) for force in w.forces]

    def run() -> None:
        for frame, frame_maps in zip(w.frames, maps, strict=True):
            cv2.remap(frame, frame_maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    return run


def _rust_compound(w: Workload, threads: int) -> Callable[[], object]:
    def run() -> None:
        compounder = Compounder(w.grid, "nearest", "mean")
        compounder.add_frames(w.frames, w.image_to_world, threads=threads)
        compounder.volume()

    return run


def _pipeline_compound(w: Workload, threads: int) -> Callable[[], object]:
    pipeline = NumpyOpenCVPipeline(w.model, w.grid, w.frames.shape[1:])
    return lambda: pipeline.compound(w.frames, w.image_to_world)


DEFAULT = "DEFAULT: vessel-anchored correct + compound"
FUSED = "FASTEST: image-coord. correct + compound"
WARP = "warp to zero force (image coordinates)"
COMPOUND = "compound (nearest, mean)"
BOTH = (1, 2)
CONTENDERS = [
    Contender(DEFAULT, "rust fused, compiled lumen search", BOTH, _rust_default),
    Contender(DEFAULT, "numpy + opencv pipeline, lumen search in opencv", BOTH, _pipeline_default),
    Contender(FUSED, "rust fused", BOTH, _rust_fused),
    Contender(FUSED, "numpy + opencv pipeline", BOTH, _pipeline_fused),
    Contender(
        FUSED, "numpy twins (usdeform.reference)", (1,), lambda w, t: lambda: reference_correct_and_compound(w), 1
    ),
    Contender(FUSED, "python loops, 1 frame extrapolated", (1,), _python_loops, 1, frames=1),
    Contender(WARP, "rust", BOTH, _rust_warp),
    Contender(WARP, "rust, cubic B-spline 8 x 8 basis", BOTH, _rust_warp_bspline),
    Contender(WARP, "numpy basis fields + cv2.remap + mask", BOTH, _pipeline_warp),
    Contender(WARP, "cv2.remap alone, maps precomputed", BOTH, _remap_only),
    Contender(
        WARP,
        "numpy twin (usdeform.reference)",
        (1,),
        lambda w, t: lambda: reference.warp_frames(w.frames, w.forces, w.profiles, w.model),
        1,
    ),
    Contender(COMPOUND, "rust", BOTH, _rust_compound),
    Contender(COMPOUND, "numpy + opencv (cv2.transform + bincount)", BOTH, _pipeline_compound),
]


def resident_bytes() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def run_contender(args: argparse.Namespace) -> dict[str, object]:
    """Time one contender at each of its thread counts (in this process): wall and process CPU
    seconds; its peak memory."""
    contender = CONTENDERS[args.child]
    workload = make_workload(args.frames, args.size, args.size, args.voxels)
    before = resident_bytes()
    seconds = {}
    for threads in contender.threads:
        cv2.setNumThreads(threads)
        run = contender.build(workload, threads)
        if contender.rounds is None:
            run()  # untimed: start-up (thread pools, lazy initialisation) and the process's first page faults
        cpu_start = time.process_time()
        seconds[threads] = (_timed(run), time.process_time() - cpu_start)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"seconds": seconds, "peak_bytes": max(peak - before, 0)}


def copy_bandwidth(n_bytes: int = 256 * 1024**2, repeats: int = 5) -> float:
    """Memory bandwidth, bytes/s read plus written, of the fastest of ``repeats`` large copies."""
    source = np.ones(n_bytes // 8)
    target = np.empty_like(source)
    best = min(_timed(lambda: np.copyto(target, source)) for _ in range(repeats))
    return 2 * n_bytes / best


def _timed(run: Callable[[], object]) -> float:
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--size", type=int, default=256, help="frame rows = cols")
    parser.add_argument("--voxels", type=int, default=200, help="voxels per grid axis")
    parser.add_argument("--rounds", type=int, default=5, help="rounds of every contender; the fastest is kept")
    parser.add_argument("--quick", action="store_true", help="small workload, for a smoke test")
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)  # run one contender, print JSON
    args = parser.parse_args()
    if args.quick:
        args.frames, args.size, args.voxels, args.rounds = 24, 64, 48, 2
    if args.child is not None:
        print(json.dumps(run_contender(args)))
        return
    workload_args = [f"--frames={args.frames}", f"--size={args.size}", f"--voxels={args.voxels}"]
    fastest: dict[tuple[int, int], tuple[float, float]] = {}  # (contender, threads): wall, CPU seconds
    peaks: dict[int, int] = {}
    for round_index in range(args.rounds):
        for index, contender in enumerate(CONTENDERS):
            if round_index >= (contender.rounds or args.rounds):
                continue
            command = [sys.executable, __file__, *workload_args, f"--child={index}"]
            output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
            result = json.loads(output.splitlines()[-1])
            for threads, (wall, cpu) in result["seconds"].items():
                key = (index, int(threads))
                fastest[key] = min((wall, cpu), fastest.get(key, (np.inf, np.inf)))
            peaks[index] = max(result["peak_bytes"], peaks.get(index, 0))
            print(f"  round {round_index + 1}: {contender.stage}: {contender.name}", file=sys.stderr)
    results = [
        (CONTENDERS[index], threads, (CONTENDERS[index].frames or args.frames) / seconds, peaks[index])
        for (index, threads), (seconds, _) in fastest.items()
    ]
    cpu_rates = [(CONTENDERS[index].frames or args.frames) / cpu for (index, _), (_, cpu) in fastest.items()]

    bandwidth = copy_bandwidth()
    # The fused path reads each uint8 pixel once and reads and writes an 8-byte voxel cell per pixel.
    bytes_per_frame = args.size * args.size * (1 + 16)
    print(
        f"workload: {args.frames} frames of {args.size} x {args.size} uint8 into a {args.voxels}^3 grid, "
        f"every contender on the whole sweep unless stated; {os.cpu_count()} cores; fastest of "
        f"{args.rounds} round(s)"
    )
    print(
        f"memory bandwidth (copy, read + write): {bandwidth / 1e9:.1f} GB/s; floor of the fused path at "
        f"{bytes_per_frame / 1e6:.2f} MB per frame (1 B read per pixel, 16 B per voxel cell read and "
        f"written): {bandwidth / bytes_per_frame:.0f} frames/s"
    )
    rust_rate: dict[tuple[str, int], float] = {}
    for c, t, rate, _ in results:
        if c.name.startswith("rust"):
            rust_rate.setdefault((c.stage, t), rate)
    print(f"| {'stage':43s} | {'implementation':44s} | threads | frames/s | rust / this | frames per CPU s | peak MB |")
    print(f"|{'-' * 45}|{'-' * 46}|---------|----------|-------------|------------------|---------|")
    for (contender, threads, rate, peak), cpu_rate in zip(results, cpu_rates, strict=True):
        ratio = rust_rate[(contender.stage, threads)] / rate
        print(
            f"| {contender.stage:43s} | {contender.name:44s} | {threads:7d} | {rate:8.1f} | {ratio:10.2f}x | "
            f"{cpu_rate:16.1f} | {peak / 1e6:7.0f} |"
        )
    for stage, label in ((DEFAULT, "default"), (FUSED, "fastest")):
        pipeline_1 = next(r for c, t, r, _ in results if c.stage == stage and c.name.startswith("numpy +") and t == 1)
        for threads in BOTH:
            print(
                f"{label}: rust at {threads} thread(s) / numpy + opencv pipeline at 1 thread: "
                f"{rust_rate[(stage, threads)] / pipeline_1:.2f}x"
            )
    remap = {t: r for c, t, r, _ in results if c.name.startswith("cv2.remap alone")}
    for threads in BOTH:
        print(
            f"warp: rust / cv2.remap on precomputed maps, both at {threads} thread(s): "
            f"{rust_rate[(WARP, threads)] / remap[threads]:.2f}x"
        )


if __name__ == "__main__":
    main()
