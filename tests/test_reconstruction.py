"""Reconstruction stages: correct-then-compound in one call equals the two steps; frame-shape checks."""

from __future__ import annotations

import numpy as np
import pytest

from kernel_inputs import random_model
from usdeform.errors import InputError
from usdeform.propagation import SampledProfiles
from usdeform.reconstruction import (
    compound_recording,
    correct_and_compound,
    correct_recording,
    interpolate_in_time,
    sweep_profiles,
)
from usdeform.recording import Recording
from usdeform.stiffness import StiffnessProfile

ROWS, COLS, N_FRAMES = 24, 20, 9


def sweep(rng: np.random.Generator, rows: int = ROWS, cols: int = COLS) -> Recording:
    probe_to_base = np.stack([np.eye(4)] * N_FRAMES)
    probe_to_base[:, 1, 3] = np.linspace(0.0, 8.0, N_FRAMES)  # the probe slides along y
    pose_valid = np.ones(N_FRAMES, bool)
    pose_valid[[2, 5]] = False  # tracking dropped out
    return Recording(
        frames=rng.integers(0, 256, (N_FRAMES, rows, cols), dtype=np.uint8),
        timestamps=np.arange(N_FRAMES) * 0.1,
        probe_to_base=probe_to_base,
        pose_valid=pose_valid,
        image_to_probe=np.diag([0.3, 0.3, 1.0, 1.0]),
        force=rng.uniform(1.0, 6.0, N_FRAMES),
    )


SAMPLED = SampledProfiles(
    np.array([[0.0, 0.0, 0.0], [0.0, 8.0, 0.0]]), (StiffnessProfile(0.1, 2.0, 0.0), StiffnessProfile(0.0, 4.0, 0.0))
)


def test_correct_and_compound_equals_the_two_steps() -> None:
    rng = np.random.default_rng(3)
    recording, model = sweep(rng), random_model(rng, ROWS, COLS)
    fused = correct_and_compound(recording, model, SAMPLED, spacing_mm=0.4)
    two_steps, n_compounded = compound_recording(correct_recording(recording, model, SAMPLED), spacing_mm=0.4)
    assert n_compounded == N_FRAMES - 2
    assert fused.grid.shape == two_steps.grid.shape
    np.testing.assert_array_equal(fused.weight, two_steps.weight)
    np.testing.assert_allclose(fused.image, two_steps.image, atol=1e-4)


def test_frames_without_a_pose_take_the_position_interpolated_in_time() -> None:
    profiles = sweep_profiles(sweep(np.random.default_rng(0)), SAMPLED)
    positions = interpolate_in_time(
        np.arange(N_FRAMES) * 0.1, np.arange(N_FRAMES) * 0.1, np.linspace(0, 8, N_FRAMES)[:, np.newaxis]
    )
    assert profiles.shape == (N_FRAMES, 3)
    np.testing.assert_allclose(profiles[0], SAMPLED.profiles[0].as_tuple())
    np.testing.assert_allclose(profiles[-1], SAMPLED.profiles[1].as_tuple())
    assert positions[2, 0] == pytest.approx(2.0)


def test_a_sweep_of_another_frame_shape_is_refused() -> None:
    rng = np.random.default_rng(1)
    model = random_model(rng, ROWS, COLS)
    wrong = sweep(rng, rows=ROWS + 4)
    with pytest.raises(InputError, match=f"sweep: frames of {ROWS + 4} x {COLS} pixels, but the model was fitted"):
        correct_recording(wrong, model, SAMPLED)
    with pytest.raises(InputError, match=f"frames: expected frames of the model's frame shape {ROWS} x {COLS}"):
        correct_and_compound(wrong, model, SAMPLED)
