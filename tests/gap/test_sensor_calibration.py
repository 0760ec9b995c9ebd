"""The force sensor's gain, offset and drift from a known-weight recording (per-frame KnownLoad beside ContactForce)."""

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.gap.sensor_calibration import is_known_weight, known_weight_calibration, sensor_calibration
from usdeform.io.sequence_file import read_frame_series, write_sequence
from usdeform.recording import Recording


def _known_weight(weight_n=5.0, gain=0.04, offset=0.8, drift=0.02, seed=0, rate_hz=20.0):
    """1 s unloaded, the weight put on over 0.3 s, held 3 s, taken off, 1 s unloaded; 0.03 N of noise."""
    time = np.arange(0.0, 5.6, 1 / rate_hz)
    on = np.clip(time - 1.0, 0, 0.3) / 0.3 - np.clip(time - 4.3, 0, 0.3) / 0.3
    load = weight_n * on
    noise = 0.03 * np.random.default_rng(seed).standard_normal(len(time))
    return time, load, (1 + gain) * load + offset + drift * time + noise


@pytest.mark.parametrize(("gain", "offset", "drift"), [(0.04, 0.8, 0.02), (-0.03, -0.4, 0.0)])
def test_gain_offset_and_drift_are_fitted_with_their_uncertainties(gain, offset, drift):
    time, load, reading = _known_weight(gain=gain, offset=offset, drift=drift)
    fitted = sensor_calibration(reading, load, time, "known")
    assert fitted.gain_error == pytest.approx(gain, abs=4 * fitted.gain_error_uncertainty + 1e-3)
    assert fitted.offset_n == pytest.approx(offset, abs=4 * fitted.offset_uncertainty_n + 1e-3)
    assert fitted.drift_n_per_s == pytest.approx(drift, abs=4 * fitted.drift_uncertainty_n_per_s + 1e-3)
    assert 0 < fitted.gain_error_uncertainty < 0.01
    assert fitted.frames == len(time)


def test_a_load_that_does_not_vary_is_refused():
    time, load, reading = _known_weight()
    with pytest.raises(InputError, match="known: KnownLoad: the load varies by 0 N"):
        sensor_calibration(reading, np.full_like(load, 5.0), time, "known")


def test_the_known_load_is_read_from_the_sequence_file(tmp_path):
    time, load, reading = _known_weight()
    n = len(time)
    recording = Recording(
        frames=np.zeros((n, 8, 8), np.uint8),
        timestamps=time,
        probe_to_base=np.tile(np.eye(4), (n, 1, 1)),
        pose_valid=np.ones(n, bool),
        image_to_probe=np.diag([0.1, 0.1, 1.0, 1.0]),
        force=reading,
        probe_displacement=np.zeros(n),
    )
    path = tmp_path / "known.seq.nrrd"
    write_sequence(path, recording, compress=False)
    assert read_frame_series(path, "KnownLoad") is None and not is_known_weight(path)
    data = path.read_bytes()
    end = data.index(b"\n\n") + 1
    lines = data[:end].decode().splitlines(keepends=True)
    extra = [f"Seq_Frame{index:04d}_KnownLoad:={value:.6g}\n" for index, value in enumerate(load)]
    path.write_bytes("".join(lines + extra).encode() + data[end:])
    assert is_known_weight(path)
    np.testing.assert_allclose(read_frame_series(path, "KnownLoad"), load, atol=1e-5)
    fitted = known_weight_calibration(path)
    assert fitted.gain_error == pytest.approx(0.04, abs=0.01)
    assert fitted.recording == str(path)
