"""The load-hold-unload palpation protocol added to usdeform.sim.simulate_palpation for the gap diagnosis."""

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.sim import simulate_palpation


def test_up_hold_down_holds_the_force_then_unloads(gap_phantom):
    recording, truth = simulate_palpation(
        gap_phantom, 10.0, 8.0, n_frames=60, ramp="up-hold-down", hold_s=2.0, seed=1, rows=64, cols=64
    )
    time = recording.timestamps
    assert time[-1] == pytest.approx(2 * 8.0 / 5.0 + 2.0, abs=0.05)
    holding = (time > 1.6 + 0.4) & (time < 1.6 + 2.0)  # after the controller settles
    assert np.all(np.abs(recording.force[holding] - 8.0) < 0.5)
    assert recording.force[-1] < 1.0 and truth.probe_displacement_mm[-1] < truth.probe_displacement_mm.max() / 4


def test_hold_needs_the_hold_protocol(gap_phantom):
    with pytest.raises(InputError, match="hold_s"):
        simulate_palpation(gap_phantom, 10.0, 8.0, n_frames=10, ramp="up-down", hold_s=1.0, rows=32, cols=32)
    with pytest.raises(InputError, match="ramp"):
        simulate_palpation(gap_phantom, 10.0, 8.0, n_frames=10, ramp="hold", rows=32, cols=32)
