"""The RF compression-pair generator (usdeform.sim.rf_compression) and the RF displacement reference
(tests/rf_reference.py) on it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates, uniform_filter

from rf_reference import axial_displacement, band_summary
from usdeform.errors import InputError
from usdeform.sim.rf_compression import CompressionMotion, rf_compression_pair


@pytest.fixture(scope="module")
def default_pair():
    return rf_compression_pair(seed=1)


@pytest.fixture(scope="module")
def varied_pair():
    """Another draw: lower frequency, more noise, depth-varying strain, a stiff inclusion, some elevational motion."""
    return rf_compression_pair(
        seed=7,
        strain=0.04,
        centre_frequency_mhz=5.0,
        fractional_bandwidth=0.55,
        attenuation_db_cm_mhz=0.5,
        noise_db=-32.0,
        tgc_fraction=0.3,
        strain_depth_gradient=0.4,
        inclusion_contrast=0.5,
        inclusion_centre_mm=(2.0, 14.0),
        out_of_plane_decorrelation=0.1,
    )


def test_shapes_and_dtypes(default_pair):
    pair = default_pair
    assert pair.pre.shape == pair.post.shape == (456, 256) and pair.pre.dtype == np.uint8
    assert pair.frames.shape == (2, 456, 256)
    assert pair.displacement_px.shape == (456, 256, 2)
    assert pair.rf_pre.shape == pair.rf_post.shape and pair.rf_pre.dtype == np.float32
    assert pair.rf_pre.shape[1] == pair.line_x_mm.size and pair.tgc_db.shape == (pair.rf_pre.shape[0],)
    assert pair.rf_depth_mm[-1] >= 456 * 0.077  # the RF reaches the bottom row
    half_width = 127.5 * 0.0745
    assert pair.line_x_mm[0] < -half_width and pair.line_x_mm[-1] > half_width  # lines around every column
    assert pair.pixel_mm == (0.077, 0.0745)


def test_same_seed_same_pair_other_seed_other_speckle():
    kwargs = dict(rows=96, cols=64, strain=0.04)
    first, again, other = (
        rf_compression_pair(seed=3, **kwargs),
        rf_compression_pair(seed=3, **kwargs),
        rf_compression_pair(seed=4, **kwargs),
    )
    assert np.array_equal(first.pre, again.pre) and np.array_equal(first.post, again.post)
    assert np.array_equal(first.rf_post, again.rf_post)
    assert np.mean(first.pre != other.pre) > 0.9
    assert np.array_equal(first.displacement_px, other.displacement_px)  # the motion does not depend on the seed


def test_intensity_falls_with_depth_like_the_real_pair(default_pair):
    """The real phantom pair: mean grey about 180 at mid-depth, 55 at the bottom. The simulated one: mid-depth
    mean in [150, 210], the bottom 2 mm at least 60 grey levels darker, and the deep RF within a few dB of
    the electronic noise."""
    pair = default_pair
    row_mean = pair.pre.mean(axis=1)
    depth = (np.arange(pair.pre.shape[0]) + 0.5) * 0.077
    mid = row_mean[(depth > depth[-1] / 2 - 2) & (depth < depth[-1] / 2 + 2)].mean()
    bottom = row_mean[depth > depth[-1] - 2].mean()
    assert 150 <= mid <= 210
    assert bottom <= min(mid - 60, 120)
    assert np.all(row_mean[depth > 8] > pair.noise_grey[depth > 8])  # still above the noise's own grey level
    # Echo-to-noise power ratio from the median power (robust to a bright structure; a Gaussian's median
    # square is 0.455 times its variance, for the noise and for fully developed speckle alike).
    for top, bottom, low, high in (
        (8.0, 12.0, 15.0, 40.0),
        (pair.rf_depth_mm[-1] - 2, pair.rf_depth_mm[-1], -10.0, 6.0),
    ):
        rows = (pair.rf_depth_mm > top) & (pair.rf_depth_mm < bottom)
        noise_power = 0.455 * np.mean(10 ** ((pair.noise_floor_db + pair.tgc_db[rows]) / 10))
        ratio = np.median(pair.rf_pre[rows].astype(float) ** 2) / noise_power - 1
        assert low < 10 * np.log10(max(ratio, 1e-3)) < high, (top, bottom, ratio)


def test_true_motion_is_the_formula(default_pair):
    """Uniform 5 % strain: the tissue at depth z moves 0.05 z towards the probe and 0.05 x sideways."""
    pair = default_pair
    rows, cols = pair.pre.shape
    x = (np.arange(cols) - (cols - 1) / 2) * 0.0745
    z = (np.arange(rows) + 0.5) * 0.077
    np.testing.assert_allclose(pair.displacement_px[..., 1], np.broadcast_to(-0.05 * z[:, None] / 0.077, (rows, cols)))
    np.testing.assert_allclose(pair.displacement_px[..., 0], np.broadcast_to(0.05 * x[None, :] / 0.0745, (rows, cols)))
    assert 15 <= -pair.displacement_px[-1, :, 1].mean() <= 25  # the regime of the real pair's deep tracks


def test_nonuniform_motion_is_incompressible_with_the_stated_strain():
    motion = CompressionMotion(
        strain=0.05,
        depth_mm=30.0,
        strain_depth_gradient=0.5,
        inclusion_contrast=0.6,
        inclusion_radius_mm=3.0,
        inclusion_centre_mm=(1.0, 12.0),
    )
    x, z = np.meshgrid(np.linspace(-9, 9, 181), np.linspace(0, 30, 301))
    dx, dz = motion.displacement_mm(x, z)
    h = 0.1
    d_dz_dz = np.gradient(dz, h, axis=0)
    d_dx_dx = np.gradient(dx, h, axis=1)
    np.testing.assert_allclose(-d_dz_dz[1:-1, 1:-1], motion.axial_strain(x, z)[1:-1, 1:-1], atol=2e-5)
    np.testing.assert_allclose(d_dx_dx[1:-1, 1:-1] + d_dz_dz[1:-1, 1:-1], 0.0, atol=4e-5)
    assert np.all(dz[0] == 0)  # the probe face does not move axially
    assert motion.axial_strain(np.array(1.0), np.array(12.0)) < 0.5 * motion.axial_strain(
        np.array(-8.0), np.array(12.0)
    )


def _patch_correlation(a: np.ndarray, b: np.ndarray, size: int = 21) -> np.ndarray:
    a, b = a.astype(float), b.astype(float)
    mean_a, mean_b = uniform_filter(a, size), uniform_filter(b, size)
    cov = uniform_filter(a * b, size) - mean_a * mean_b
    var_a = uniform_filter(a * a, size) - mean_a**2
    var_b = uniform_filter(b * b, size) - mean_b**2
    return cov / np.sqrt(np.maximum(var_a * var_b, 1e-9))


@pytest.mark.parametrize("which", ["default_pair", "varied_pair"])
def test_post_frame_shows_the_pre_tissue_where_the_truth_says(which, request):
    """Reading the post frame at p + u(p) gives back the pre frame's speckle (decorrelated by the strain and
    the noise, more with depth), and clearly better than reading it at p."""
    pair = request.getfixturevalue(which)
    rows, cols = pair.pre.shape
    r, c = np.mgrid[0:rows, 0:cols].astype(float)
    moved = map_coordinates(
        pair.post.astype(float), [r + pair.displacement_px[..., 1], c + pair.displacement_px[..., 0]], order=1
    )
    aligned = _patch_correlation(pair.pre, moved)
    unaligned = _patch_correlation(pair.pre, pair.post)
    inner = (slice(None), slice(40, cols - 40))
    for top, bottom, least in ((40, 140, 0.8), (140, 260, 0.75)):
        assert np.median(aligned[top:bottom][inner]) > least
        assert np.median(aligned[top:bottom][inner]) > np.median(unaligned[top:bottom][inner]) + 0.2


@pytest.mark.parametrize("which", ["default_pair", "varied_pair"])
def test_rf_reference_recovers_the_known_axial_motion(which, request):
    """The RF cross-correlation reference on the simulated RF: on lines near the centre (lateral motion under
    a third of the beam width) and where its peak correlation is at least 0.7, it is within 10 um of the
    truth for most windows; in the 3 mm bands where it calls itself consistent, its band median is within
    3 % of the true one."""
    pair = request.getfixturevalue(which)
    reference = axial_displacement(pair.rf_pre, pair.rf_post, pair.rf_sample_mm)
    x, z = np.meshgrid(pair.line_x_mm, reference.depth_mm)
    truth = pair.motion.displacement_mm(x, z)[1]
    central = np.abs(pair.line_x_mm) <= 4.0
    good = (reference.correlation >= 0.7) & central[None, :]
    error = np.abs(reference.displacement_mm - truth)[good]
    assert good.sum() > 0.3 * central.sum() * reference.depth_mm.size
    assert np.median(error) < 0.01
    assert np.mean(error < 0.05) > 0.95
    consistent = 0
    for band in band_summary(
        reference, 3.0, lines=slice(int(np.argmax(central)), int(central.size - np.argmax(central[::-1])))
    ):
        if band.correlation >= 0.5 and band.neighbour_agreement >= 0.5:
            consistent += 1
            rows = (reference.depth_mm >= band.top_mm) & (reference.depth_mm < band.bottom_mm)
            true_median = np.median(truth[rows][:, central])
            assert abs(band.median_mm - true_median) <= 0.03 * abs(true_median) + 0.005, band
    assert consistent >= 5


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(strain=0.0),
        dict(strain=0.5),
        dict(strain=float("nan")),
        dict(rows=8),
        dict(pixel_mm=(0.0, 0.07)),
        dict(centre_frequency_mhz=30.0),
        dict(centre_frequency_mhz=7.0, rf_sampling_mhz=10.0),
        dict(fractional_bandwidth=0.05),
        dict(attenuation_db_cm_mhz=-0.1),
        dict(inclusion_contrast=1.0),
        dict(out_of_plane_decorrelation=1.0),
        dict(seed=-1),
        dict(n_bright_structures=-1),
    ],
)
def test_bad_parameters_raise_input_error(kwargs):
    with pytest.raises(InputError):
        rf_compression_pair(**kwargs)
