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


def _calibration(offset, offset_error=0.01, drift=0.0, drift_error=0.001, gain=0.0):
    return {
        "recording": "known.seq.nrrd",
        "gain_error": gain,
        "gain_error_uncertainty": 0.002,
        "offset_n": offset,
        "offset_uncertainty_n": offset_error,
        "drift_n_per_s": drift,
        "drift_uncertainty_n_per_s": drift_error,
        "frames": 100,
    }


@pytest.mark.parametrize(
    ("calibrations", "finding"),
    [
        ([], None),
        ([_calibration(0.6)], "error"),  # an offset well beyond 0.1 N and 3 standard errors
        ([_calibration(0.0, drift=0.03)], "error"),  # a drift of 0.03 N/s
        ([_calibration(0.02)], "clean"),
        ([_calibration(0.02, gain=0.1)], "clean"),  # a gain error: no palpation shows it, it rules nothing out
        ([_calibration(0.15, offset_error=0.1)], None),  # beyond 0.1 N but within 3 standard errors: not shown
        ([_calibration(0.05, offset_error=0.03)], None),  # 0.05 + 3 x 0.03 > 0.1: not shown small either
        ([_calibration(0.02, drift=None, drift_error=None)], None),  # the drift was not identified
        ([_calibration(0.02), _calibration(0.5)], "error"),
    ],
)
def test_what_known_weights_show_of_the_sensor(calibrations, finding):
    from usdeform.gap.sensor_calibration import sensor_finding

    assert sensor_finding(calibrations) == finding


def test_the_simulated_known_weight_shows_the_sensor_error_it_was_given(known_weight_signals):
    from usdeform.gap.sensor_calibration import sensor_finding

    for offset, finding in ((0.6, "error"), (0.0, "clean")):
        time, load, reading = known_weight_signals(gain=0.0, offset=offset, drift=0.0)
        assert sensor_finding([sensor_calibration(reading, load, time, "known").to_json()]) == finding
