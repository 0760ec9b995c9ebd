"""One palpated position: stiffness, tracks and regression observations from a simulated palpation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.fitting import measure_palpation


def test_palpation_gives_stiffness_tracks_and_boundary_observations(small_palpation) -> None:
    recording, _truth = small_palpation
    sampled = measure_palpation(recording, flexible_layer_mm=50.0, boundary_points=16)
    assert sampled.stiffness.r_squared[2] > 0.99
    assert np.all(sampled.stiffness.stiffness_n_per_mm > 0)
    assert 0.5 < sampled.tracked.kept_fraction <= 1.0
    observations = sampled.observations
    n_tracks = len(sampled.tracked.points_px)
    assert observations.points_px.shape == (n_tracks + 2 * 16, 2)
    assert observations.reference_force_n == pytest.approx(recording.force.min())
    # The bottom boundary row moves up (negative axial) by lambda / L_T of the image height.
    bottom = observations.points_px[:, 1] == recording.frames.shape[1] - 1
    last = -1
    expected = (
        -(
            recording.probe_displacement[sampled.tracked.frame_indices[last]]
            - recording.probe_displacement[sampled.tracked.reference_index]
        )
        / 50.0
        * (recording.frames.shape[1] - 1)
    )
    np.testing.assert_allclose(observations.displacements_px[last, bottom, 1], expected)
    assert sampled.seconds > 0


def test_palpation_without_force_is_rejected(small_palpation) -> None:
    recording, _ = small_palpation
    with pytest.raises(InputError, match="force and probe displacement"):
        measure_palpation(dataclasses.replace(recording, force=None), flexible_layer_mm=50.0)
