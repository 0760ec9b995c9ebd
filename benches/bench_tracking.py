"""Tracking benchmark: the landed tracker against this one on the cases that break trackers.

Usage: ``python benches/bench_tracking.py [--before-rev main] [--skip-palpation] [--only palpation ...]``

* Single large steps (:func:`usdeform.sim.tracking_cases.compression_pair`, 0.077 mm pixels,
  464 x 256): the real pair's 5 % strain (23 px at the bottom) and two 40 px steps, each without
  scatterer jitter and at the decorrelation of real data (jitter 0.02 mm, correlation length 1 mm:
  the 25 x 25 patch peak correlation of the pair equals that of consecutive frames of the real PLUS
  SpinePhantom freehand sweep, 0.53), plus low texture (a lumen in view; noise-dominated depth).
  Per case and tracker: kept fraction of the points in textured tissue (more than 7 px from the
  lumen, true end point inside the frame), median / 99th percentile error of the kept tracks, their
  signed mean error (lateral, axial), fraction of kept tracks more than 3 px wrong, and the time.
* The real compression pair's regime (:func:`usdeform.sim.rf_compression.rf_compression_pair`, a generator
  written apart from the tracker): per 3 mm depth band, kept tracks and their sign against the truth.
* The calibration: the patch correlation of the sweep's and the simulated frames, and its floor
  (the same measure on unrelated frames), and how much of the correlation above the floor is left.
* Bias or noise: the signed mean error of the kept tracks over four seeds per case.
* The error a window allows: Lucas-Kanade started at the true position, per window size,
  translation-only (OpenCV) and affine (:func:`usdeform.optical_flow._lucas_kanade._affine_lucas_kanade`).
* The coarse motion estimate, chosen by measurement: OpenCV's DIS and Farneback dense flows against
  the half-resolution block matching of :mod:`usdeform.optical_flow`, error at grid points.
* A simulated 50-frame 256 x 256 palpation (stiff preset, 20 N; FEM cached in ~/.cache/usdeform):
  time per palpation (median of 3, OpenCV on 2 threads; wall and this process's CPU), the tracks kept
  in every frame as by the first tracker, and accuracy at the highest force; and the
  same palpation with only every 5th frame (frames skipped: steps 5 times larger).

"before" is ``usdeform.optical_flow`` (module or package) at ``--before-rev`` (read with git), "after" the
installed package; both run in the same process on the same inputs.
"""

from __future__ import annotations

import argparse
import functools
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from landed import landed_module
from usdeform import optical_flow
from usdeform.io import read_plus_config, read_sequence
from usdeform.optical_flow._block_matching import _coarse_flow
from usdeform.optical_flow._lucas_kanade import _LK_CRITERIA, _affine_lucas_kanade
from usdeform.sim import TissueAcoustics, simulate_palpation, stiff_phantom
from usdeform.sim.imaging import ImagingSettings
from usdeform.sim.rf_compression import rf_compression_pair
from usdeform.sim.tracking_cases import CompressionPair, compression_pair, peak_patch_correlation

REAL_LEVEL = TissueAcoustics(scatterer_jitter_mm=0.02, jitter_correlation_mm=1.0)
PLUS = (  # the PLUS data folder, kept outside the repository: $USDEFORM_SHARED_DATA/plus or ../shared/data/plus
    Path(
        sys.modules["os"].environ.get("USDEFORM_SHARED_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data"
    )
    / "plus"
)


def cases() -> dict[str, CompressionPair]:
    deep_dark = ImagingSettings(rows=464, cols=256, depth_mm=464 * 0.077, width_mm=256 * 0.077, tgc_db_per_cm=1.0)
    return {
        "5 % strain, 23 px, no jitter": compression_pair(0.05, seed=1),
        "5 % strain, 23 px, real decorrelation": compression_pair(0.05, acoustics=REAL_LEVEL, seed=1),
        "5 % + 17 px offset, 40 px, no jitter": compression_pair(0.05, offset_px=17, seed=2),
        "5 % + 17 px offset, 40 px, real decorrelation": compression_pair(
            0.05, offset_px=17, acoustics=REAL_LEVEL, seed=2
        ),
        "8.6 % strain, 40 px, lumen, no jitter": compression_pair(0.086, lumen=True, seed=3),
        "8.6 % strain, 40 px, lumen, real decorrelation": compression_pair(
            0.086, lumen=True, acoustics=REAL_LEVEL, seed=3
        ),
        "5 % strain, 0.3 mm out of plane, real decorrelation": compression_pair(
            0.05, elevation_shift_mm=0.3, acoustics=REAL_LEVEL, seed=5
        ),
        "5 % strain, noise-dominated depth (1 dB/cm TGC)": compression_pair(
            0.05, settings=deep_dark, acoustics=TissueAcoustics(attenuation_db_per_cm_mhz=0.7), seed=6
        ),
    }


def score(
    pair: CompressionPair, tracked: optical_flow.TrackedDisplacements
) -> tuple[float, float, float, float, np.ndarray]:
    """(kept fraction in textured tissue whose true end point stays 10 px inside the frame, median
    error, p99 error, fraction of kept tracks > 3 px wrong, signed mean error (dx, dy)), as in
    tests/test_tracking_large_steps.py."""
    points = np.rint(tracked.points_px).astype(int)
    truth = pair.displacement_px[points[:, 1], points[:, 0]]
    end = tracked.points_px + truth
    rows, cols = pair.frames.shape[1:]
    inside = (end >= 10).all(axis=1) & (end[:, 0] <= cols - 11) & (end[:, 1] <= rows - 11)
    near_lumen = cv2.dilate(pair.lumen.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    textured = inside & ~near_lumen[points[:, 1], points[:, 0]]
    kept = tracked.valid[-1]
    signed = tracked.displacements_px[-1, kept] - truth[kept]
    error = np.linalg.norm(signed, axis=1)
    if len(error) == 0:
        return float(kept[textured].mean()), np.nan, np.nan, np.nan, np.full(2, np.nan)
    return (
        float(kept[textured].mean()),
        float(np.median(error)),
        float(np.percentile(error, 99)),
        float(np.mean(error > 3)),
        signed.mean(axis=0),
    )


def timed(run: Callable[[], optical_flow.TrackedDisplacements]) -> tuple[optical_flow.TrackedDisplacements, float]:
    result, seconds, _ = timed_with_cpu(run)
    return result, seconds


def timed_with_cpu(
    run: Callable[[], optical_flow.TrackedDisplacements],
) -> tuple[optical_flow.TrackedDisplacements, float, float]:
    """The result, its wall time and the CPU time of this process (all threads), s."""
    start, start_cpu = time.perf_counter(), time.process_time()
    result = run()
    return result, time.perf_counter() - start, time.process_time() - start_cpu


def bench_pairs(trackers: dict[str, Callable]) -> None:
    print(
        "| case | patch corr. | tracker | kept (textured) | median px | p99 px | mean dx, dy px "
        "| kept > 3 px wrong | ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, pair in cases().items():
        correlation = peak_patch_correlation(pair.frames[0], pair.frames[1], pair.displacement_px)
        for label, track in trackers.items():
            tracked, seconds = timed(functools.partial(track, pair.frames, np.array([0.0, 1.0])))
            kept, median, p99, wrong, mean = score(pair, tracked)
            print(
                f"| {name} | {correlation:.2f} | {label} | {kept:.3f} | {median:.3f} | {p99:.2f} | "
                f"{mean[0]:+.3f}, {mean[1]:+.3f} | {100 * wrong:.2f} % | {1e3 * seconds:.0f} |"
            )


RF_DRAWS = {
    "5 %, 7 MHz, 0.7 dB/cm/MHz": {"strain": 0.05, "rows": 460, "seed": 0},
    "6 %, 5 MHz, steep fall (1.0 dB/cm/MHz, no TGC)": {
        "strain": 0.06,
        "rows": 460,
        "centre_frequency_mhz": 5.0,
        "attenuation_db_cm_mhz": 1.0,
        "tgc_fraction": 0.0,
        "noise_db": -45.0,
        "seed": 1,
    },
    "4 %, 7.5 MHz, inclusion, 0.9 dB/cm/MHz": {
        "strain": 0.04,
        "rows": 460,
        "centre_frequency_mhz": 7.5,
        "attenuation_db_cm_mhz": 0.9,
        "tgc_fraction": 0.0,
        "noise_db": -40.0,
        "inclusion_contrast": 0.6,
        "seed": 2,
    },
    "5 %, full size, 0.3 mm lines, dark bottom (grey 40)": {
        "rows": 519,
        "cols": 508,
        "white_level_db": 8.0,
        "line_pitch_mm": 0.3,
        "seed": 7,
    },
    "5 %, full size 519 x 508, 0.3 mm lines, bottom grey 55": {
        "rows": 519,
        "cols": 508,
        "white_level_db": 5.0,
        "line_pitch_mm": 0.3,
        "seed": 1,
    },
}


def bench_rf_regime(trackers: dict[str, Callable]) -> None:
    """The real compression pair's regime (:func:`usdeform.sim.rf_compression.rf_compression_pair`: RF lines,
    envelope, 50 dB log compression, attenuation leaving dim deep speckle; one step of 4-6 % strain, 15-27 px at
    depth): per 3 mm depth band, the true and tracked median axial step, tracks kept and kept with the wrong sign
    (true step over 2 px), and over the frame the median error and the kept tracks more than 3 px wrong."""
    print("\n| RF pair | tracker | band mm | true dy px | tracked dy px | kept / in band | wrong sign |")
    print("|---|---|---|---|---|---|---|")
    summary = []
    for name, parameters in RF_DRAWS.items():
        pair = rf_compression_pair(**parameters)
        for label, track in trackers.items():
            tracked, seconds = timed(functools.partial(track, np.stack([pair.pre, pair.post]), np.array([0.0, 1.0])))
            points = np.rint(tracked.points_px).astype(int)
            truth = pair.displacement_px[points[:, 1], points[:, 0]]
            kept = tracked.valid[0]
            step = tracked.displacements_px[0]
            depth_mm = tracked.points_px[:, 1] * pair.pixel_mm[0]
            for low in np.arange(8.0, depth_mm.max(), 3.0):
                band = (depth_mm >= low) & (depth_mm < low + 3.0)
                wrong = kept & band & (np.sign(step[:, 1]) != np.sign(truth[:, 1])) & (np.abs(truth[:, 1]) > 2)
                tracked_dy = f"{np.median(step[kept & band, 1]):.2f}" if (kept & band).any() else "-"
                print(
                    f"| {name} | {label} | {low:.0f}-{low + 3:.0f} | {np.median(truth[band, 1]):.2f} | {tracked_dy} | "
                    f"{(kept & band).sum()} / {band.sum()} | {wrong.sum()} |"
                )
            error = np.linalg.norm(step[kept] - truth[kept], axis=1)
            summary.append((name, label, kept.mean(), np.median(error), 100 * np.mean(error > 3), seconds))
    print("\n| RF pair | tracker | kept | median px | kept > 3 px wrong | s |")
    print("|---|---|---|---|---|---|")
    for name, label, kept_fraction, median, wrong_percent, seconds in summary:
        print(f"| {name} | {label} | {kept_fraction:.3f} | {median:.3f} | {wrong_percent:.2f} % | {seconds:.2f} |")


def bench_calibration() -> None:
    """The decorrelation level against the real sweep: median peak patch correlation (searched +-4 px),
    its floor (unrelated frames: the sweep's frames 10 apart, one of them mirrored; two simulated
    pairs of different seeds, one mirrored) and the fraction of the correlation above the floor that
    is left, (corr - floor) / (1 - floor)."""
    recording = read_sequence(
        PLUS / "SpinePhantomFreehand.igs.mha",
        config=read_plus_config(PLUS / "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"),
    )
    frames = recording.frames
    n = len(frames)
    real_floor = float(np.median([peak_patch_correlation(frames[i], frames[(i + 10) % n][:, ::-1]) for i in range(n)]))
    plain, other = compression_pair(0.05, seed=1), compression_pair(0.05, seed=2)
    simulated_floor = peak_patch_correlation(plain.frames[0], other.frames[0][:, ::-1])
    print("\n| frames | patch corr. | floor | left above the floor |")
    print("|---|---|---|---|")
    for gap in (1, 2, 5):
        real = float(np.median([peak_patch_correlation(frames[i], frames[i + gap]) for i in range(n - gap)]))
        left = (real - real_floor) / (1 - real_floor)
        print(f"| real PLUS sweep, frames {gap} apart | {real:.3f} | {real_floor:.3f} | {left:.2f} |")
    for label, acoustics in (("no", TissueAcoustics()), ("real", REAL_LEVEL)):
        pair = compression_pair(0.05, acoustics=acoustics, seed=1)
        simulated = peak_patch_correlation(pair.frames[0], pair.frames[1], pair.displacement_px)
        left = (simulated - simulated_floor) / (1 - simulated_floor)
        print(f"| 5 % strain pair, {label} decorrelation | {simulated:.3f} | {simulated_floor:.3f} | {left:.2f} |")


def bench_bias() -> None:
    """Signed mean error (lateral dx, axial dy) of the kept tracks over four seeds per case: a bias is the
    same sign in every seed; noise (errors correlated over a window, so a case's mean over ~1500 tracks
    still moves by a few hundredths of a pixel) changes sign."""
    print("\n| case (after) | mean dx per seed, px | mean dy per seed, px |")
    print("|---|---|---|")
    for label, acoustics in (("no", TissueAcoustics()), ("real", REAL_LEVEL)):
        for offset in (0.0, 17.0):
            means = []
            for seed in (11, 12, 13, 14):
                pair = compression_pair(0.05, offset_px=offset, acoustics=acoustics, seed=seed)
                means.append(score(pair, optical_flow.track_palpation(pair.frames, [0, 1]))[4])
            dx, dy = (" ".join(f"{mean[axis]:+.3f}" for mean in means) for axis in (0, 1))
            print(f"| 5 % strain + {offset:.0f} px, {label} decorrelation | {dx} | {dy} |")


def bench_window_limit() -> None:
    """How well the true motion can be found at all: Lucas-Kanade (full resolution, no pyramid)
    started at the true end point of every textured grid point converges to the nearest optimum of
    its window; its distance from the truth is the random error of that window on this speckle,
    whatever the search before it. Under decorrelation the speckle in the second frame is partly
    new, so this error is not zero even for a perfect initial estimate."""
    print(
        "\n| case | window (w x h) | translation LK from the truth: median px | p99 px "
        "| affine LK: median px | p99 px |"
    )
    print("|---|---|---|---|---|---|")
    for name, pair in cases().items():
        if "lumen" in name or "noise" in name:
            continue
        before, after = pair.frames
        rows, cols = np.mgrid[32 : before.shape[0] - 32 : 8, 32 : before.shape[1] - 32 : 8]
        start = np.column_stack([cols.ravel(), rows.ravel()]).astype(np.float32)
        end = start + pair.displacement_px[rows.ravel(), cols.ravel()].astype(np.float32)
        inside = (end >= 10).all(axis=1) & (end[:, 0] <= before.shape[1] - 11) & (end[:, 1] <= before.shape[0] - 11)
        start, end = start[inside, None], end[inside, None]
        for window in ((21, 21), (31, 31), (41, 41), (51, 31), (51, 51), (61, 61)):
            found, _, _ = cv2.calcOpticalFlowPyrLK(
                before,
                after,
                start,
                end.copy(),
                winSize=window,
                maxLevel=0,
                criteria=_LK_CRITERIA,
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
            )
            error = np.linalg.norm(np.asarray(found)[:, 0] - end[:, 0], axis=1)
            affine, _, _ = _affine_lucas_kanade(before, after, start[:, 0], end[:, 0], window)
            affine_error = np.linalg.norm(affine - end[:, 0], axis=1)
            print(
                f"| {name} | {window[0]} x {window[1]} | {np.median(error):.3f} | {np.percentile(error, 99):.2f} | "
                f"{np.median(affine_error):.3f} | {np.percentile(affine_error, 99):.2f} |"
            )


def bench_coarse_estimates() -> None:
    def dis(preset: int) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        return lambda a, b: np.asarray(cv2.DISOpticalFlow.create(preset).calc(a, b, np.empty(0, np.float32)))

    def block_matching(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        coarse = _coarse_flow(a, b, 48.0)
        rows, cols = np.mgrid[0 : a.shape[0], 0 : a.shape[1]]
        points = np.column_stack([cols.ravel(), rows.ravel()]).astype(np.float64)
        return coarse.at(points).reshape((*a.shape, 2))

    estimates = {
        "DIS medium": dis(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM),
        "DIS fast": dis(cv2.DISOPTICAL_FLOW_PRESET_FAST),
        "Farneback 31 px, 5 levels": lambda a, b: np.asarray(
            cv2.calcOpticalFlowFarneback(a, b, np.empty(0, np.float32), 0.5, 5, 31, 5, 7, 1.5, 0)
        ),
        "block matching, half resolution": block_matching,
    }
    print("\n| coarse estimate | case | median px | points > 3 px wrong | ms |")
    print("|---|---|---|---|---|")
    rows, cols = np.mgrid[24:440:8, 24:232:8]
    for name, pair in list(cases().items())[:6]:
        for label, estimate in estimates.items():
            start = time.perf_counter()
            flow = estimate(pair.frames[0], pair.frames[1])
            seconds = time.perf_counter() - start
            textured = ~pair.lumen[rows, cols]
            error = np.linalg.norm(flow[rows, cols] - pair.displacement_px[rows, cols], axis=-1)[textured]
            wrong = 100 * np.mean(error > 3)
            print(f"| {label} | {name} | {np.median(error):.2f} | {wrong:.1f} % | {1e3 * seconds:.0f} |")


def bench_palpation(trackers: dict[str, Callable]) -> None:
    recording, truth = simulate_palpation(stiff_phantom(), 20.0, 20.0, n_frames=50, seed=3)
    assert recording.force is not None
    print(
        "\n| palpation | tracker | s per palpation (wall) | CPU s | kept to the highest force | tracks kept as before "
        "| median px | p90 px | p99 px |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for label_frames, chosen in (("50 frames", slice(None)), ("every 5th frame (10)", slice(None, None, 5))):
        frames, force = recording.frames[chosen], recording.force[chosen]
        displacement = truth.displacement_px[chosen]
        first_valid = None
        for label, track in trackers.items():
            seconds, cpu_seconds = [], []
            for _ in range(3):
                tracked, elapsed, cpu = timed_with_cpu(functools.partial(track, frames, force))
                seconds.append(elapsed)
                cpu_seconds.append(cpu)
            first_valid = tracked.valid if first_valid is None else first_valid
            same = int(np.count_nonzero((tracked.valid == first_valid).all(axis=0)))
            last, reference = tracked.frame_indices[-1], tracked.reference_index
            points = tracked.points_px
            # True motion of the tissue seen at p in the reference frame (see tests/test_optical_flow.py).
            zero_force = points.copy()
            for _ in range(50):
                zero_force = points - sample(displacement[reference], zero_force)
            expected = zero_force + sample(displacement[last], zero_force) - points
            keep = tracked.valid[-1] & np.isfinite(expected).all(axis=1)
            error = np.linalg.norm(tracked.displacements_px[-1, keep] - expected[keep], axis=1)
            print(
                f"| {label_frames} | {label} | {np.median(seconds):.2f} | {np.median(cpu_seconds):.2f} | "
                f"{tracked.kept_fraction:.3f} | {same} of {len(first_valid.T)} | "
                f"{np.median(error):.3f} | {np.percentile(error, 90):.2f} | {np.percentile(error, 99):.2f} |"
            )


SECTIONS = ("pairs", "rf", "calibration", "bias", "window", "coarse", "palpation")


def sample(field: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, 2) of a (rows, cols, 2) field at (x, y) points."""
    x, y = (points[:, i].astype(np.float32)[None] for i in (0, 1))
    return cv2.remap(field.astype(np.float32), x, y, cv2.INTER_LINEAR)[0].astype(np.float64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--before-rev",
        default="HEAD~0",
        help="git revision of the landed tracker (default: where this branch left main)",
    )
    parser.add_argument("--skip-palpation", action="store_true", help="skip the FEM palpation (needs the stiff preset)")
    parser.add_argument(
        "--only", nargs="+", choices=SECTIONS, default=list(SECTIONS), help="run these parts only (default: all)"
    )
    args = parser.parse_args()
    cv2.setNumThreads(2)
    if args.before_rev == "HEAD~0":
        root = Path(__file__).resolve().parents[1]
        merge_base = ["git", "-C", str(root), "merge-base", "HEAD", "main"]
        args.before_rev = subprocess.run(merge_base, check=True, capture_output=True, text=True).stdout.strip()[:10]
    landed = landed_module(args.before_rev, "optical_flow")
    trackers = {f"before ({args.before_rev})": landed.track_palpation, "after": optical_flow.track_palpation}
    parts = {
        "pairs": lambda: bench_pairs(trackers),
        "rf": lambda: bench_rf_regime(trackers),
        "calibration": bench_calibration,
        "bias": bench_bias,
        "window": bench_window_limit,
        "coarse": bench_coarse_estimates,
        "palpation": lambda: None if args.skip_palpation else bench_palpation(trackers),
    }
    for name in SECTIONS:
        if name in args.only:
            parts[name]()
    sys.stdout.flush()


if __name__ == "__main__":
    main()
