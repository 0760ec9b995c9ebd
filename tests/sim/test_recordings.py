"""Simulated palpations and sweeps on the finite-element mechanics (a small, coarse phantom)."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.recording import Recording, image_to_probe_from_geometry
from usdeform.sim.imaging import TissueAcoustics
from usdeform.sim.phantoms import Phantom, coarse_phantom
from usdeform.sim.recordings import DEFAULT_SURFACE_TO_BASE, _SharedOnce, simulate_palpation, simulate_sweep

SPARSE_SPECKLE = TissueAcoustics(scatterer_density_per_mm3=6.0)  # fewer scatterers: faster, for non-speckle checks


@pytest.fixture(scope="module")
def phantom() -> Phantom:
    return coarse_phantom()


@pytest.fixture(scope="module")
def palpation(phantom):
    """8 frames at 256 x 256, force ramped up to 8 N."""
    return simulate_palpation(phantom, 20.0, 8.0, n_frames=8, seed=11)


def test_palpation_is_deterministic_for_a_seed(phantom):
    def run(seed):
        return simulate_palpation(phantom, 20.0, 6.0, n_frames=3, seed=seed, rows=96, cols=96, acoustics=SPARSE_SPECKLE)

    (first, first_truth), (again, again_truth), (other, _) = run(3), run(3), run(4)
    assert np.array_equal(first.frames, again.frames) and np.array_equal(first.force, again.force)
    assert np.array_equal(first_truth.displacement_px, again_truth.displacement_px, equal_nan=True)
    assert not np.array_equal(first.frames, other.frames) and not np.array_equal(first.force, other.force)


def test_frames_are_the_same_for_any_number_of_rendering_threads(phantom):
    """A sweep (frames at many mechanics positions, each its own zero-force frame) and a palpation (one section,
    one zero-force frame): every output array the same with 1, 2 and 5 threads (more threads than frames in a
    block of the palpation); a bad thread count is refused before any work."""

    def sweep(threads):
        return simulate_sweep(
            phantom, 10.0, 6.0, 5.0, n_frames=9, seed=5, rows=64, cols=64, acoustics=SPARSE_SPECKLE, threads=threads
        )

    def palpation(threads):
        return simulate_palpation(
            phantom, 20.0, 6.0, n_frames=4, seed=3, rows=64, cols=64, acoustics=SPARSE_SPECKLE, threads=threads
        )

    for simulate in (sweep, palpation):
        (first, first_truth), *others = [simulate(threads) for threads in (1, 2, 5)]
        for recording, truth in others:
            assert np.array_equal(recording.frames, first.frames)
            assert np.array_equal(recording.probe_to_base, first.probe_to_base)
            for name in ("zero_force_frames", "vessel_mask", "zero_force_vessel_mask", "displacement_px"):
                assert np.array_equal(getattr(truth, name), getattr(first_truth, name), equal_nan=True), name
    with pytest.raises(InputError, match="threads"):
        palpation(0)


def test_a_shared_value_is_made_once_per_key_and_dropped_after_its_last_use():
    """Eight threads asking for three keys (each key's uses counted): each value is made once, with the inputs of
    the first thread to ask, every thread gets that value, and a key's entry is gone after its last release."""
    made = []
    start = threading.Barrier(8)

    def make(key, first_input):
        made.append(key)
        return (key, first_input)

    keys = ["a", "b", "a", "c", "a", "b", "c", "a"]
    shared = _SharedOnce(make, keys)

    def use(index):
        start.wait()
        value = shared.get(keys[index], index)
        shared.release(keys[index])
        return value

    with ThreadPoolExecutor(8) as pool:
        values = list(pool.map(use, range(8)))
    assert sorted(made) == ["a", "b", "c"]
    for key, (value_key, first_input) in zip(keys, values, strict=True):
        assert value_key == key and keys[first_input] == key
        assert values[keys.index(key)] == (value_key, first_input)  # every use of a key got the same value
    assert shared._entries == {}


def test_palpation_streams_are_sampled_like_a_real_recording(palpation):
    recording, truth = palpation
    assert isinstance(recording, Recording) and recording.frames.shape == (8, 256, 256)
    assert recording.metadata == {}
    # Frames of a 50 fps stream spread over the 1.6 s ramp (8 N at 5 N/s).
    frame_periods = np.diff(recording.timestamps) * 50.0
    np.testing.assert_allclose(frame_periods, np.rint(frame_periods), atol=1e-9)
    assert recording.timestamps[-1] == pytest.approx(1.6, abs=0.03)
    # The force follows the ramp with a short control lag and ripple; lambda grows with it.
    assert recording.force[0] == pytest.approx(0.0, abs=0.2)
    np.testing.assert_allclose(recording.force, 5.0 * recording.timestamps, atol=0.6)
    assert np.all(np.diff(recording.probe_displacement) > 0)
    np.testing.assert_allclose(recording.probe_displacement, truth.probe_displacement_mm, atol=0.02)
    np.testing.assert_allclose(recording.force, truth.force_n, atol=0.2)
    # Probe pointing down into the phantom, pressed lambda below the surface, fixed x and y.
    expected_rotation = DEFAULT_SURFACE_TO_BASE[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(
        recording.probe_to_base[:, :3, :3], np.broadcast_to(expected_rotation, (8, 3, 3)), atol=1e-12
    )
    np.testing.assert_allclose(
        recording.probe_to_base[:, 2, 3], DEFAULT_SURFACE_TO_BASE[2, 3] - recording.probe_displacement
    )
    np.testing.assert_allclose(recording.probe_to_base[:, 1, 3], DEFAULT_SURFACE_TO_BASE[1, 3] + 20.0)
    np.testing.assert_array_equal(recording.image_to_probe, image_to_probe_from_geometry(256, 256))


def test_up_down_ramp_returns_to_low_force(phantom):
    recording, _ = simulate_palpation(
        phantom, 20.0, 6.0, n_frames=5, ramp="up-down", seed=1, rows=64, cols=64, acoustics=SPARSE_SPECKLE
    )
    assert recording.force.max() == pytest.approx(6.0, abs=0.6)
    assert recording.force[-1] < 0.5 and recording.force[2] > 5.0


def test_ground_truth_masks_line_up_with_the_rendered_lumen(palpation):
    recording, truth = palpation
    for index in (0, 7):
        inner = cv2.erode(truth.vessel_mask[index].astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        assert (recording.frames[index][inner] < 40).mean() > 0.98
        inner_zero = cv2.erode(truth.zero_force_vessel_mask[index].astype(np.uint8), np.ones((7, 7), np.uint8)).astype(
            bool
        )
        assert (truth.zero_force_frames[index][inner_zero] < 40).mean() > 0.98
    # Pressing squashes the lumen: smaller, flatter, nearer the top of the image.
    assert truth.vessel_mask[7].sum() < 0.9 * truth.zero_force_vessel_mask[7].sum()
    rows_deformed = np.argwhere(truth.vessel_mask[7])[:, 0]
    rows_zero = np.argwhere(truth.zero_force_vessel_mask[7])[:, 0]
    assert rows_deformed.mean() < rows_zero.mean() - 5
    # The zero-force frame is the same speckle without the deformation.
    assert np.corrcoef(truth.zero_force_frames[0].ravel(), recording.frames[0].ravel())[0, 1] > 0.9


def test_backward_mapping_with_the_true_displacement_undoes_the_deformation(palpation):
    recording, truth = palpation
    rows, cols = np.mgrid[0:256, 0:256].astype(np.float32)
    displacement = np.nan_to_num(truth.displacement_px[7])
    warped = cv2.remap(recording.frames[7], cols + displacement[..., 0], rows + displacement[..., 1], cv2.INTER_LINEAR)
    inner = (slice(10, 190), slice(10, 246))  # the bottom rows see tissue the deformed frame does not show
    correlation = np.corrcoef(warped[inner].ravel(), truth.zero_force_frames[7][inner].ravel())[0, 1]
    assert correlation > 0.85


def test_lucas_kanade_between_nearby_forces_recovers_the_fem_displacement(palpation):
    """Measured on this palpation, frames 4 -> 5 (4.2 -> 5.1 N, motions up to 2.1 px, 699 points):
    median LK error 0.037 px, 90th percentile 0.074 px (frames 0 -> 7, 0 -> 7.6 N, motions up to
    17 px, with maxLevel=3: 0.13 px and 0.42 px)."""
    recording, truth = palpation
    before, after = 4, 5
    grid_rows, grid_cols = np.mgrid[16:240:8, 16:240:8]
    points = np.column_stack([grid_cols.ravel(), grid_rows.ravel()]).astype(np.float64)
    # Truth: the zero-force pixel p seen at q = p + D_before(p) moves to p + D_after(p).
    zero_force = points.copy()
    for _ in range(50):
        zero_force = points - _sample(truth.displacement_px[before], zero_force)
    expected = zero_force + _sample(truth.displacement_px[after], zero_force) - points
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(
        recording.frames[before],
        recording.frames[after],
        points.astype(np.float32)[:, None, :],
        None,
        winSize=(21, 21),
        maxLevel=2,
    )
    near_lumen = cv2.dilate(truth.vessel_mask[before].astype(np.uint8), np.ones((15, 15), np.uint8))
    usable = (
        (status.ravel() == 1)
        & (near_lumen[grid_rows.ravel(), grid_cols.ravel()] == 0)
        & np.isfinite(expected).all(axis=1)
    )
    error = np.linalg.norm(tracked[:, 0, :] - points - expected, axis=1)[usable]
    assert usable.sum() > 500 and np.abs(expected[usable]).max() > 1.0
    assert np.median(error) < 0.07
    assert np.percentile(error, 90) < 0.15


def _sample(field: np.ndarray, points_col_row: np.ndarray) -> np.ndarray:
    """Bilinear samples (m, 2) of a (rows, cols, 2) field at (col, row) points."""
    samples = cv2.remap(
        field.astype(np.float32),
        points_col_row[:, 0].astype(np.float32)[None],
        points_col_row[:, 1].astype(np.float32)[None],
        cv2.INTER_LINEAR,
    )
    return samples[0].astype(np.float64)


def test_sweep_moves_along_base_y_under_force_control(phantom):
    # 6 mm in 19 frame periods (0.38 s): 16 mm/s.
    recording, truth = simulate_sweep(
        phantom, 40.0, 6.0, 6.0, n_frames=20, seed=2, rows=96, cols=96, acoustics=SPARSE_SPECKLE
    )
    assert len(recording) == 20
    np.testing.assert_allclose(np.diff(recording.timestamps), 0.02, atol=1e-9)
    positions = recording.probe_to_base[:, 1, 3] - DEFAULT_SURFACE_TO_BASE[1, 3]
    assert positions[0] == pytest.approx(40.0, abs=0.02) and positions[-1] == pytest.approx(46.0, abs=0.02)
    np.testing.assert_allclose(np.diff(positions), 6.0 / 19, rtol=0.05)
    np.testing.assert_allclose(truth.sweep_position_mm, positions, atol=0.01)  # pose clock: 250 Hz samples
    np.testing.assert_allclose(recording.probe_to_base[:, 0, 3], DEFAULT_SURFACE_TO_BASE[0, 3])
    np.testing.assert_allclose(
        recording.probe_to_base[:, :3, 2], np.broadcast_to([0.0, 0.0, -1.0], (20, 3)), atol=1e-12
    )
    # Force control: the force stays near the target with ripple; lambda is the elastic one at that force.
    assert np.abs(recording.force - 6.0).max() < 0.5 and np.std(recording.force) > 0.01
    elastic = [phantom.solution_at(s).probe_displacement_at_force(6.0) for s in positions]
    np.testing.assert_allclose(recording.probe_displacement, elastic, atol=0.2)
    assert truth.vessel_mask.any(axis=(1, 2)).all()


def test_bad_arguments_name_themselves(phantom):
    with pytest.raises(InputError, match="ramp"):
        simulate_palpation(phantom, 20.0, 5.0, ramp="down")
    with pytest.raises(InputError, match="n_frames"):
        simulate_palpation(phantom, 20.0, 1.0, n_frames=500, rows=32, cols=32)
    with pytest.raises(InputError, match="max_force_n"):
        simulate_palpation(phantom, 20.0, -1.0)
    with pytest.raises(InputError, match="sweep position"):
        simulate_sweep(phantom, 50.0, 30.0, 5.0, n_frames=5)
    with pytest.raises(InputError, match="surface_to_base"):
        simulate_palpation(phantom, 20.0, 5.0, surface_to_base=np.eye(3))
    with pytest.raises(InputError, match="solved range"):
        simulate_palpation(phantom, 20.0, 40.0, n_frames=2, rows=32, cols=32, acoustics=SPARSE_SPECKLE)


@pytest.mark.parametrize("frames", ["0", "1", "-3"])
def test_simulate_refuses_too_few_frames_before_writing(frames, tmp_path, capsys):
    from usdeform.cli import main

    out = tmp_path / "sim"
    with pytest.raises(SystemExit) as exit:  # argparse refuses the value: a usage line, then one line naming it
        main(["simulate", "palpation", "--preset", "stiff", "--at", "10", "--frames", frames, "--output", str(out)])
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert exit.value.code == 2 and f"argument --frames: expected an integer from 2 to 100000, got '{frames}'" in error
    assert not out.exists()
