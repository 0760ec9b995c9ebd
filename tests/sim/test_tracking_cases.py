"""Large-step compression pairs: the true motion follows the stated formula and the frames show it."""

from __future__ import annotations

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.sim.imaging import TissueAcoustics
from usdeform.sim.tracking_cases import compression_pair, peak_patch_correlation


def test_true_motion_follows_the_formula():
    """Axial: towards the probe by offset + strain * depth; lateral: lateral_ratio * strain * distance
    from the centre column (pixels are square here, so the formula holds in pixels)."""
    pair = compression_pair(0.05, offset_px=10.0, lateral_ratio=0.4, rows=200, cols=120, seed=1)
    rows, cols = np.mgrid[0:200, 0:120].astype(np.float64)
    centre = 60.0  # the probe axis (x = 0) is at column cols / 2 (paper eq. 2)
    np.testing.assert_allclose(pair.displacement_px[..., 1], -(10.0 + 0.05 * rows), atol=1e-6)
    np.testing.assert_allclose(pair.displacement_px[..., 0], 0.4 * 0.05 * (cols - centre), atol=1e-6)
    assert pair.frames.shape == (2, 200, 120) and pair.frames.dtype == np.uint8
    assert not pair.lumen.any()


def test_the_frames_show_the_stated_motion():
    """Without jitter the second frame is the first moved by the true motion: patches correlate
    at 0.8 around the true position and not at all around the unmoved one."""
    pair = compression_pair(0.05, rows=240, cols=160, seed=2)
    moved = peak_patch_correlation(pair.frames[0], pair.frames[1], pair.displacement_px)
    still = peak_patch_correlation(pair.frames[0], pair.frames[1], np.zeros_like(pair.displacement_px))
    assert moved > 0.75 and still < 0.5


def test_lumen_and_determinism():
    first = compression_pair(0.03, rows=200, cols=160, lumen=True, seed=3)
    again = compression_pair(0.03, rows=200, cols=160, lumen=True, seed=3)
    np.testing.assert_array_equal(first.frames, again.frames)
    assert first.lumen.sum() == pytest.approx(np.pi * (3.0 / 0.077) ** 2, rel=0.05)
    assert first.frames[0][first.lumen].mean() < 0.4 * first.frames[0][~first.lumen].mean()
    jittered = compression_pair(
        0.03, rows=200, cols=160, lumen=True, seed=3, acoustics=TissueAcoustics(scatterer_jitter_mm=0.02)
    )
    assert not np.array_equal(first.frames[1], jittered.frames[1])


@pytest.mark.parametrize(
    "arguments, match",
    [
        ({"strain": -0.1}, "strain"),
        ({"offset_px": -1.0}, "offset_px"),
        ({"pixel_mm": 0.0}, "pixel_mm"),
        ({"seed": -1}, "seed"),
    ],
)
def test_bad_arguments_are_rejected(arguments, match):
    with pytest.raises(InputError, match=match):
        compression_pair(**arguments)
    with pytest.raises(InputError, match="same shape"):
        peak_patch_correlation(np.zeros((30, 30)), np.zeros((30, 31)))
