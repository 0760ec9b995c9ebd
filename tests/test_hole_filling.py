"""Hole filling (usdeform.volume): the Rust kernel against its NumPy twin, its rules on volumes
whose answer is known by hand, thread-count independence, errors, and the PLUS configuration.

The comparison with PLUS's own hole-filled volumes is in test_plus_reconstruction.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from usdeform import reference
from usdeform.errors import FileFormatError, InputError, MemoryLimitError
from usdeform.io import read_plus_config
from usdeform.volume import (
    PLUS_MIN_KNOWN_WEIGHT,
    HoleFillingElement,
    Volume,
    VoxelGrid,
    fill_holes,
    finish_volume,
    voxel_values,
)

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def volume_of(image: np.ndarray, weight: np.ndarray | None) -> Volume:
    return Volume(image, VoxelGrid(image.shape, np.diag([0.5, 0.5, 0.5, 1.0])), weight)


def random_volume(seed: int, shape: tuple[int, int, int], hole_fraction: float) -> Volume:
    rng = np.random.default_rng(seed)
    image = (rng.random(shape) * 255).astype(np.float32)
    weight = np.where(rng.random(shape) < hole_fraction, 0.0, rng.random(shape) * 3).astype(np.float32)
    weight[rng.random(shape) < 0.05] = 1e-3  # below PLUS_MIN_KNOWN_WEIGHT: holes by default
    return volume_of(image, weight)


cube_elements = st.builds(
    HoleFillingElement,
    kind=st.sampled_from(["gaussian", "gaussian_accumulation", "distance_weight_inverse", "nearest_neighbor"]),
    size=st.sampled_from([1, 3, 5]),
    stdev=st.floats(0.3, 3.0),
    min_known_ratio=st.floats(0.0, 1.0),
)
stick_elements = st.builds(
    HoleFillingElement, kind=st.just("stick"), stick_length_limit=st.integers(1, 6), sticks_to_use=st.integers(1, 13)
)
element_lists = st.lists(st.one_of(cube_elements, stick_elements), min_size=1, max_size=3)


@SETTINGS
@given(
    seed=st.integers(0, 2**32 - 1),
    shape=st.tuples(st.integers(1, 9), st.integers(1, 9), st.integers(1, 9)),
    hole_fraction=st.floats(0.0, 0.95),
    elements=element_lists,
    voxel_type=st.sampled_from(["float32", "uint8"]),
    min_known_weight=st.sampled_from([0.0, PLUS_MIN_KNOWN_WEIGHT, 0.5]),
)
def test_kernel_matches_numpy_twin(seed, shape, hole_fraction, elements, voxel_type, min_known_weight) -> None:
    volume = random_volume(seed, shape, hole_fraction)
    assert volume.weight is not None
    ours = fill_holes(volume, elements, voxel_type=voxel_type, min_known_weight=min_known_weight, threads=2).image
    twin = reference.fill_holes(voxel_values(volume.image, voxel_type), volume.weight, elements, min_known_weight)
    assert ours.dtype == twin.dtype == np.dtype(voxel_type)
    if voxel_type == "uint8":  # truncation of values within rounding of an integer may differ by one
        assert np.abs(ours.astype(int) - twin.astype(int)).max(initial=0) <= 1
        assert (ours != twin).mean() < 0.01
    else:
        np.testing.assert_allclose(ours, twin, rtol=1e-6, atol=1e-4)
    known = (volume.weight > 0) & (volume.weight >= min_known_weight)
    np.testing.assert_array_equal(ours[known], voxel_values(volume.image, voxel_type)[known])


def test_same_volume_for_any_thread_count() -> None:
    volume = random_volume(7, (23, 19, 17), 0.6)
    elements = [
        HoleFillingElement("gaussian", size=5, stdev=1.0, min_known_ratio=0.6),
        HoleFillingElement("stick", stick_length_limit=4, sticks_to_use=3),
        HoleFillingElement("nearest_neighbor", size=7, min_known_ratio=0.0),
    ]
    results = [fill_holes(volume, elements, threads=threads).image for threads in (1, 2, 3, 8)]
    for other in results[1:]:
        np.testing.assert_array_equal(results[0].view(np.uint32), other.view(np.uint32))


def test_stick_weights_its_ends_as_plus() -> None:
    """Known planes every 4 voxels along z of a ramp 10 z + y: the z stick is the only one. A hole k
    steps above a plane has its ends b = k and f = 4 - k steps away, and PLUS weighs the forward
    (upper) end by (b + 1) / (f + b + 1) = (k + 1) / 5: the value 10 z0 + 8 (k + 1) + y."""
    z, y, _ = np.meshgrid(np.arange(13), np.arange(6), np.arange(5), indexing="ij")
    ramp = (10.0 * z + y).astype(np.float32)
    weight = np.where(z % 4 == 0, 1.0, 0.0).astype(np.float32)
    expected = np.where(z % 4 == 0, ramp, 10 * (z - z % 4) + 8 * (z % 4 + 1) + y)
    filled = fill_holes(volume_of(np.where(weight > 0, ramp, 0), weight), [HoleFillingElement("stick")])
    np.testing.assert_allclose(filled.image, expected, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(filled.weight, weight)  # coverage unchanged: the data voxels only
    as_uint8 = fill_holes(
        volume_of(np.where(weight > 0, ramp, 0), weight), [HoleFillingElement("stick")], voxel_type="uint8"
    )
    # In uint8 each stick's float value is truncated, as PLUS's cast (0.4 * 1 + 0.6 * 41 reads 24).
    below, forward_weight = 10 * (z - z % 4) + y, (z % 4 + 1) / 5
    truncated = np.floor((1 - forward_weight) * below + forward_weight * (below + 40))
    np.testing.assert_array_equal(as_uint8.image, np.where(z % 4 == 0, ramp, truncated).astype(np.uint8))
    # A limit of 1 leaves no stick (its ends would be f + b <= 0 steps apart).
    short = fill_holes(volume_of(ramp, weight), [HoleFillingElement("stick", stick_length_limit=1)])
    np.testing.assert_array_equal(short.image[weight == 0], 0)


def test_cube_kinds_and_their_ratio() -> None:
    """A linear field with its centre voxel missing: every symmetric weighting gives the centre value;
    a ratio above the known 26/27 fails and passes the hole to the next element."""
    field = np.arange(27, dtype=np.float32).reshape(3, 3, 3) * 2 + 5
    weight = np.ones((3, 3, 3), np.float32)
    weight[1, 1, 1] = 0
    volume = volume_of(field, weight)
    for kind in ("gaussian", "gaussian_accumulation", "distance_weight_inverse", "nearest_neighbor"):
        filled = fill_holes(volume, [HoleFillingElement(kind, size=3, stdev=0.7, min_known_ratio=0.96)])  # type: ignore[arg-type]
        assert filled.image[1, 1, 1] == pytest.approx(31.0, abs=1e-4), kind
    strict = HoleFillingElement("gaussian", size=3, min_known_ratio=0.97)
    assert fill_holes(volume, [strict]).image[1, 1, 1] == 0
    nearest_only = HoleFillingElement("nearest_neighbor", size=3, min_known_ratio=0.0)
    weight[1, 1, 2] = 0  # the +x neighbour missing too: the nearest are the other five faces
    expected = np.mean([field[0, 1, 1], field[2, 1, 1], field[1, 0, 1], field[1, 2, 1], field[1, 1, 0]])
    assert fill_holes(volume_of(field, weight), [strict, nearest_only]).image[1, 1, 1] == pytest.approx(expected)


def test_gaussian_accumulation_weighs_by_coverage() -> None:
    image = np.zeros((1, 1, 3), np.float32)
    image[0, 0, 0], image[0, 0, 2] = 10, 40
    weight = np.array([[[3.0, 0.0, 1.0]]], np.float32)
    element = HoleFillingElement("gaussian_accumulation", size=3, stdev=1.0, min_known_ratio=0.0)
    assert fill_holes(volume_of(image, weight), [element]).image[0, 0, 1] == pytest.approx(17.5)


def test_bad_input_is_named() -> None:
    volume = random_volume(1, (4, 4, 4), 0.5)
    assert volume.weight is not None
    stick = HoleFillingElement("stick")
    with pytest.raises(InputError, match="kind: expected one of"):
        HoleFillingElement("median")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="size: expected an odd number"):
        HoleFillingElement("gaussian", size=4)
    with pytest.raises(InputError, match="min_known_ratio"):
        HoleFillingElement("nearest_neighbor", min_known_ratio=1.5)
    with pytest.raises(InputError, match="sticks_to_use"):
        HoleFillingElement("stick", sticks_to_use=14)
    with pytest.raises(InputError, match=r"size must be odd and in 1\.\.=31"):
        fill_holes(volume, [stick, HoleFillingElement("gaussian", size=33)])
    with pytest.raises(InputError, match="has no coverage weight"):
        fill_holes(volume_of(volume.image, None), [stick])
    with pytest.raises(InputError, match="at least one"):
        fill_holes(volume, [])
    with pytest.raises(InputError, match="voxel_type"):
        fill_holes(volume, [stick], voxel_type="int16")  # type: ignore[arg-type]
    with pytest.raises(MemoryLimitError, match="over the limit"):
        fill_holes(volume, [stick], max_bytes=100)
    with pytest.raises(InputError, match="threads"):
        fill_holes(volume, [stick], threads=0)
    nan_weight = volume.weight.copy()
    nan_weight[1, 2, 3] = np.nan
    with pytest.raises(InputError, match="weight: non-finite value"):
        fill_holes(volume_of(volume.image, nan_weight), [stick])


CONFIG = """<PlusConfiguration version="2.1">
  <CoordinateDefinitions>
    <Transform From="Image" To="Probe" Matrix="0.1 0 0 0  0 0.1 0 0  0 0 0.1 0  0 0 0 1"/>
  </CoordinateDefinitions>
  <VolumeReconstruction OutputSpacing="0.5 0.5 0.5" FillHoles="{fill}">
    <HoleFilling>
{elements}
    </HoleFilling>
  </VolumeReconstruction>
</PlusConfiguration>
"""
ALL_KINDS = """
      <HoleFillingElement Type="GAUSSIAN" Size="5" Stdev="0.6667" MinimumKnownVoxelsRatio="0.50001"/>
      <HoleFillingElement Type="GAUSSIAN_ACCUMULATION" Size="3" Stdev="1.5" MinimumKnownVoxelsRatio="0.2"/>
      <HoleFillingElement Type="DISTANCE_WEIGHT_INVERSE" Size="7" MinimumKnownVoxelsRatio="0.1"/>
      <HoleFillingElement Type="NEAREST_NEIGHBOR" Size="9" MinimumKnownVoxelsRatio="0.01"/>
      <HoleFillingElement Type="STICK" StickLengthLimit="9" NumberOfSticksToUse="2"/>"""


def write_config(tmp_path: Path, elements: str, fill: str = "ON") -> Path:
    path = tmp_path / "config.xml"
    path.write_text(CONFIG.format(fill=fill, elements=elements))
    return path


def test_configuration_elements_in_order(tmp_path: Path) -> None:
    settings = read_plus_config(write_config(tmp_path, ALL_KINDS)).reconstruction
    assert settings is not None and settings.fill_holes
    assert settings.hole_filling == (
        HoleFillingElement("gaussian", size=5, stdev=0.6667, min_known_ratio=0.50001),
        HoleFillingElement("gaussian_accumulation", size=3, stdev=1.5, min_known_ratio=0.2),
        HoleFillingElement("distance_weight_inverse", size=7, min_known_ratio=0.1),
        HoleFillingElement("nearest_neighbor", size=9, min_known_ratio=0.01),
        HoleFillingElement("stick", stick_length_limit=9, sticks_to_use=2),
    )
    volume = random_volume(3, (10, 9, 8), 0.5)
    configured = finish_volume(volume, settings, voxel_type="uint8")
    direct = fill_holes(volume, settings.hole_filling, voxel_type="uint8")
    np.testing.assert_array_equal(configured.image, direct.image)
    off = read_plus_config(write_config(tmp_path, ALL_KINDS, fill="OFF")).reconstruction
    assert off is not None
    unfilled = finish_volume(volume, off, voxel_type="uint8")
    np.testing.assert_array_equal(unfilled.image, voxel_values(volume.image, "uint8"))


@pytest.mark.parametrize(
    ("elements", "message"),
    [
        ('<HoleFillingElement Type="MEDIAN" Size="3"/>', "HoleFillingElement 0: Type 'MEDIAN' is not one of"),
        ('<HoleFillingElement Type="GAUSSIAN" Size="3" MinimumKnownVoxelsRatio="0.5"/>', "needs the attribute Stdev"),
        ('<HoleFillingElement Type="STICK" StickLengthLimit="9"/>', "needs the attribute NumberOfSticksToUse"),
        (
            '<HoleFillingElement Type="NEAREST_NEIGHBOR" Size="4" MinimumKnownVoxelsRatio="0.5"/>',
            "size: expected an odd",
        ),
        ('<HoleFillingElement Type="STICK" StickLengthLimit="nine" NumberOfSticksToUse="1"/>', "cannot parse"),
        ("", "FillHoles is ON but no HoleFilling"),
    ],
)
def test_configuration_errors_name_the_element(tmp_path: Path, elements: str, message: str) -> None:
    with pytest.raises(FileFormatError, match=message):
        read_plus_config(write_config(tmp_path, elements))


def test_configuration_fan_and_clip_rectangle_mask(plus_data: Path) -> None:
    """The TRUS configuration: clip rectangle 192 16 420 580, fan -45..45 deg from apex (380, 20),
    radius 120..360 pixels."""
    settings = read_plus_config(
        plus_data / "PlusDeviceSet_VolumeReconstructionOnly_SonixRP_TRUS_D70mm_LN_MEAN.xml"
    ).reconstruction
    assert settings is not None
    assert settings.fan_angles_deg == (-45.0, 45.0)
    assert settings.fan_origin_pixel == (380.0, 20.0)
    assert settings.fan_radius_pixels == (120.0, 360.0)
    mask = settings.pixel_mask(616, 820)
    assert mask[20 + 200, 380] and mask[20 + 359, 380]  # on the axis, within the radii
    assert not mask[20 + 119, 380] and not mask[20 + 361, 380]  # nearer than start, beyond stop
    assert mask[20 + 150, 380 + 149] and not mask[20 + 150, 380 + 151]  # inside / outside 45 degrees
    # On the 45-degree edges: outside, as in PLUS, whose tan(45 deg) is just below 1.
    assert not mask[20 + 150, 380 + 150] and not mask[20 + 150, 380 - 150]
    assert not mask[20 + 200, 380 - 190]  # inside the fan, left of the clip rectangle (column 192)
    assert mask.sum() < 420 * 580


@pytest.mark.parametrize("angles", ["-95 45", "-45 90", "30 -30"])
def test_fan_angles_out_of_range_are_reported(tmp_path: Path, angles: str) -> None:
    path = tmp_path / "config.xml"
    path.write_text(
        f'<PlusConfiguration><VolumeReconstruction OutputSpacing="0.5 0.5 0.5" FanAnglesDeg="{angles}" '
        'FanOriginPixel="380 20"/></PlusConfiguration>'
    )
    with pytest.raises(FileFormatError, match=r"FanAnglesDeg .*strictly between -90 and 90"):
        read_plus_config(path)
