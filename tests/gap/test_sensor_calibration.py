"""The force sensor's gain, offset and drift from a known-weight recording (per-frame KnownLoad beside ContactForce)."""

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.gap.sensor_calibration import is_known_weight, known_weight_calibration, sensor_calibration
from usdeform.io.sequence_file import read_frame_series


@pytest.mark.parametrize(("gain", "offset", "drift"), [(0.04, 0.8, 0.02), (-0.03, -0.4, 0.0)])
def test_gain_offset_and_drift_are_fitted_with_their_uncertainties(gain, offset, drift, known_weight_signals):
    time, load, reading = known_weight_signals(gain=gain, offset=offset, drift=drift)
    fitted = sensor_calibration(reading, load, time, "known")
    assert fitted.gain_error == pytest.approx(gain, abs=4 * fitted.gain_error_uncertainty + 1e-3)
    assert fitted.offset_n == pytest.approx(offset, abs=4 * fitted.offset_uncertainty_n + 1e-3)
    assert fitted.drift_n_per_s == pytest.approx(drift, abs=4 * fitted.drift_uncertainty_n_per_s + 1e-3)
    assert 0 < fitted.gain_error_uncertainty < 0.01
    assert fitted.frames == len(time)


def test_a_load_that_does_not_vary_is_refused(known_weight_signals):
    time, load, reading = known_weight_signals()
    with pytest.raises(InputError, match="known: KnownLoad: the load varies by 0 N"):
        sensor_calibration(reading, np.full_like(load, 5.0), time, "known")


def test_the_known_load_is_read_from_the_sequence_file(tmp_path, write_known_weight):
    path = tmp_path / "known.seq.nrrd"
    write_known_weight(path, with_load=False)
    assert read_frame_series(path, "KnownLoad") is None and not is_known_weight(path)
    load = write_known_weight(path)
    assert is_known_weight(path)
    np.testing.assert_allclose(read_frame_series(path, "KnownLoad"), load, atol=1e-5)
    fitted = known_weight_calibration(path)
    assert fitted.gain_error == pytest.approx(0.04, abs=0.01)
    assert fitted.recording == str(path)
