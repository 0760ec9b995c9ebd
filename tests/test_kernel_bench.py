"""The kernel benchmark: its NumPy + OpenCV contender computes what the kernels compute, and it runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from usdeform.correction import correct_frames
from usdeform.volume import Compounder

BENCHES = Path(__file__).resolve().parents[1] / "benches"
sys.path.insert(0, str(BENCHES))

from bench_kernels import CONTENDERS, NumpyOpenCVPipeline, make_workload  # noqa: E402


@pytest.fixture(scope="module")
def workload():
    return make_workload(n_frames=20, rows=64, cols=64, voxels=40, seed=3)


def test_pipeline_warp_and_mask_match_the_kernel(workload) -> None:
    w = workload
    pipeline = NumpyOpenCVPipeline(w.model, w.grid, w.frames.shape[1:])
    corrected, valid = correct_frames(w.frames, w.forces, w.profile, w.model, return_mask=True)
    for index in range(len(w.frames)):
        warped, warped_valid = pipeline.warp(w.frames[index], float(w.forces[index]), w.profile)
        assert 0 < valid[index].mean() < 1
        # Only sources within float32 rounding of the frame's border may be judged differently.
        assert np.count_nonzero((warped_valid > 0) != valid[index]) <= 2
        both = valid[index] & (warped_valid > 0)
        # OpenCV quantises the bilinear weights to 1/32 pixel.
        difference = np.abs(warped[both].astype(int) - corrected[index][both].astype(int))
        assert difference.max() <= 8 and difference.mean() < 1.0


def test_pipeline_compounding_matches_the_fused_kernel(workload) -> None:
    w = workload
    pipeline = NumpyOpenCVPipeline(w.model, w.grid, w.frames.shape[1:])
    image, weight = pipeline.compound(w.frames, w.image_to_world, w.forces, w.profile)
    compounder = Compounder(w.grid, "nearest", "mean")
    compounder.add_corrected_frames(w.frames, w.image_to_world, w.forces, w.profile, w.model)
    volume = compounder.volume()
    assert volume.weight.sum() > 1000
    # float32 voxel positions may round a pixel into the neighbouring voxel, rarely.
    assert np.count_nonzero(weight != volume.weight) <= 1e-3 * weight.size
    same = (weight == volume.weight) & (weight > 0)
    assert np.abs(image[same] - volume.image[same]).mean() < 1.0
    _, uncorrected_weight = pipeline.compound(w.frames, w.image_to_world)
    plain = Compounder(w.grid, "nearest", "mean")
    plain.add_frames(w.frames, w.image_to_world)
    assert np.count_nonzero(uncorrected_weight != plain.volume().weight) <= 1e-3 * weight.size


def test_quick_benchmark_times_every_contender() -> None:
    result = subprocess.run(
        [sys.executable, str(BENCHES / "bench_kernels.py"), "--quick"],
        check=True,
        capture_output=True,
        text=True,
        timeout=600,
    )
    table = [line for line in result.stdout.splitlines() if line.startswith("| ") and "frames/s" not in line]
    expected_rows = sum(len(contender.threads) for contender in CONTENDERS)
    assert len(table) == expected_rows
    for line in table:
        cells = line.split("|")
        frames_per_second, frames_per_cpu_second = float(cells[4]), float(cells[6])
        assert frames_per_second > 0 and frames_per_cpu_second > 0
    assert "floor of the fused path" in result.stdout
    assert "fastest of 2 round(s)" in result.stdout
    assert result.stdout.count("warp: rust / cv2.remap on precomputed maps") == 2
    # The slow contenders run in the first round only.
    assert result.stderr.count("round 2: ") == sum(contender.rounds is None for contender in CONTENDERS)
