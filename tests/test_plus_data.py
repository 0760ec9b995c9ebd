"""The real PLUS spine-phantom sweep and its configurations (PlusLibData, BSD-3), read through the ``plus_data``
fixture: the shared real data kept outside the repository (``../shared/data/plus`` or ``$USDEFORM_SHARED_DATA``).

Expected values are copied from the files themselves (``grep -a`` on the .mha header, the XML
attributes), not computed with the code under test. Where the data is absent the tests that need it
skip with the reason; the configuration checks on written files run regardless.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import pytest

from usdeform.errors import FileFormatError, InputError
from usdeform.io import read_plus_config, read_sequence, read_volume, write_sequence
from usdeform.recording import Recording

SWEEP = "SpinePhantomFreehand.igs.mha"
NN_MEAN = "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml"
LN_MAXI = "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_LN_MAXI.xml"
NN_LATE = "PlusDeviceSet_VolumeReconstructionOnly_SonixRP_TRUS_D70mm_NN_LATE.xml"

# From the sweep's header (grep -a "Seq_Frame00\(00\|10\|20\)_" SpinePhantomFreehand.igs.mha).
PROBE_TO_TRACKER = {
    0: "0.231245 0.951424 -0.203269 172.641 -0.127436 -0.17751 -0.975833 -98.0022 -0.964513 0.25156 0.0801977 -22.0262 0 0 0 1",
    10: "0.231295 0.949674 -0.211237 176.808 -0.125311 -0.186235 -0.974481 -84.9811 -0.96478 0.251863 0.0759292 -21.0964 0 0 0 1",
    20: "0.238697 0.94307 -0.231609 178.871 -0.117659 -0.20866 -0.970885 -65.364 -0.96394 0.258998 0.0611545 -20.315 0 0 0 1",
}
REFERENCE_TO_TRACKER = {
    0: "0.949536 -0.208383 0.234431 264.096 -0.195717 -0.977686 -0.076326 93.8733 0.245105 0.0265923 -0.969132 3.0506 0 0 0 1",
    10: "0.949526 -0.20838 0.234476 264.096 -0.195698 -0.977685 -0.0763828 93.985 0.245161 0.0266409 -0.969116 3.12539 0 0 0 1",
    20: "0.949505 -0.208387 0.234552 264.096 -0.195715 -0.977685 -0.0763379 93.9311 0.245225 0.026578 -0.969102 3.12539 0 0 0 1",
}
TIMESTAMPS = {0: 215.102186, 10: 215.973486, 20: 216.947186}
# From the NN_MEAN configuration's <Transform From="Image" To="Probe" Matrix=...>.
IMAGE_TO_PROBE = [
    [-0.00157821, 0.0785919, -0.00803285, 15.3978],
    [-0.0839128, 0.00372697, 0.0153803, 49.5705],
    [0.0159024, 0.00714276, 0.0803604, -8.63446],
    [0, 0, 0, 1],
]


def matrix(text: str) -> np.ndarray:
    return np.array(text.split(), dtype=np.float64).reshape(4, 4)


@pytest.fixture(scope="module")
def sweep(plus_data: Path) -> Recording:
    return read_sequence(plus_data / SWEEP, config=plus_data / NN_MEAN)


def test_sweep_has_21_frames_of_616_by_820(sweep: Recording) -> None:
    assert len(sweep) == 21
    assert sweep.frames.shape == (21, 616, 820)  # header: DimSize = 820 616 21
    assert sweep.frames.dtype == np.uint8
    assert sweep.pose_valid.all()  # every ProbeToTracker/ReferenceToTracker status is OK
    assert sweep.force is None and sweep.probe_displacement is None
    for index, timestamp in TIMESTAMPS.items():
        assert sweep.timestamps[index] == timestamp


def test_sweep_poses_are_probe_to_reference(sweep: Recording) -> None:
    for index in PROBE_TO_TRACKER:
        expected = np.linalg.inv(matrix(REFERENCE_TO_TRACKER[index])) @ matrix(PROBE_TO_TRACKER[index])
        np.testing.assert_allclose(sweep.probe_to_base[index], expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(sweep.image_to_probe, IMAGE_TO_PROBE)


def test_sweep_pixels_match_the_zlib_payload(plus_data: Path, sweep: Recording) -> None:
    data = (plus_data / SWEEP).read_bytes()
    start = data.index(b"ElementDataFile = LOCAL\n") + len(b"ElementDataFile = LOCAL\n")
    pixels = np.frombuffer(zlib.decompress(data[start : start + 3466024]), np.uint8)  # CompressedDataSize = 3466024
    np.testing.assert_array_equal(sweep.frames.ravel(), pixels)
    assert 20 < sweep.frames.mean() < 120  # B-mode frames, not blank


def test_sweep_extent_matches_plus_reconstruction_origin(plus_data: Path, sweep: Recording) -> None:
    """PLUS places the output origin at the minimum of the clipped frame corners in Reference.

    With the NN_MEAN clip rectangle (origin 0 0, size 820 616) the corners are pixels (0..819, 0..615);
    the origin PLUS wrote (Offset = -74.5217 165.573 29.072, 6 significant digits) must match ours.
    """
    corners = np.array([[0, 0, 0, 1], [0, 615, 0, 1], [819, 0, 0, 1], [819, 615, 0, 1]], dtype=np.float64).T
    points = np.concatenate([(image_to_base @ corners)[:3].T for image_to_base in sweep.image_to_base])
    reference = read_volume(plus_data / "vtkVolumeReconstructorTestNNMEANvolumeRef.mha")
    np.testing.assert_allclose(points.min(axis=0), reference.grid.origin, rtol=0, atol=5e-4)
    np.testing.assert_allclose(points.min(axis=0), [-74.5217, 165.573, 29.072], rtol=0, atol=5e-4)


@pytest.mark.parametrize("name", ["sweep.seq.nrrd", "sweep.mha"])
def test_real_sweep_round_trips_exactly(tmp_path: Path, sweep: Recording, name: str) -> None:
    write_sequence(tmp_path / name, sweep)
    read = read_sequence(tmp_path / name)
    for field in ("frames", "timestamps", "probe_to_base", "pose_valid", "image_to_probe"):
        np.testing.assert_array_equal(getattr(read, field), getattr(sweep, field), err_msg=field)


def test_sweep_without_calibration_asks_for_the_config(plus_data: Path) -> None:
    with pytest.raises(FileFormatError, match="ImageToProbeTransform"):
        read_sequence(plus_data / SWEEP)


def test_reconstruction_settings_are_read_from_the_configs(plus_data: Path) -> None:
    nn_mean = read_plus_config(plus_data / NN_MEAN).reconstruction
    assert (nn_mean.interpolation, nn_mean.compounding, nn_mean.fill_holes) == ("nearest", "mean", True)
    np.testing.assert_array_equal(nn_mean.output_spacing_mm, [0.5, 0.5, 0.5])
    assert (nn_mean.clip_rectangle_origin, nn_mean.clip_rectangle_size) == ((0, 0), (820, 616))
    assert nn_mean.output_origin_mm is None and nn_mean.output_extent is None
    ln_maxi = read_plus_config(plus_data / LN_MAXI).reconstruction
    assert (ln_maxi.interpolation, ln_maxi.compounding, ln_maxi.fill_holes) == ("linear", "max", False)
    nn_late = read_plus_config(plus_data / NN_LATE).reconstruction
    assert (nn_late.interpolation, nn_late.compounding) == ("nearest", "latest")
    assert (nn_late.clip_rectangle_origin, nn_late.clip_rectangle_size) == ((192, 16), (420, 580))


def test_config_transforms_and_inverse(plus_data: Path) -> None:
    config = read_plus_config(plus_data / NN_MEAN)
    np.testing.assert_array_equal(config.image_to_probe, IMAGE_TO_PROBE)
    np.testing.assert_allclose(config.transform("Probe", "Image") @ config.image_to_probe, np.eye(4), atol=1e-12)
    assert config.transform("Phantom", "Reference")[0, 3] == 11.9823
    with pytest.raises(InputError, match="no Image->Tracker transform"):
        config.transform("Image", "Tracker")


def test_config_with_origin_and_extent_gives_a_voxel_grid(tmp_path: Path) -> None:
    path = tmp_path / "config.xml"
    path.write_text(
        '<PlusConfiguration><VolumeReconstruction OutputSpacing="0.5 1 2" OutputOrigin="-10 0 5" '
        'OutputExtent="0 9 2 5 0 0" Interpolation="LINEAR" CompoundingMode="LATEST"/></PlusConfiguration>'
    )
    settings = read_plus_config(path).reconstruction
    grid = settings.voxel_grid()
    assert grid.shape == (1, 4, 10)
    np.testing.assert_array_equal(grid.origin, [-10, 2, 5])  # extent starts at j = 2
    np.testing.assert_array_equal(grid.spacing, [0.5, 1, 2])
    assert settings.clip_rectangle_origin is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("<PlusConfiguration><CoordinateDefinitions>", "not well-formed XML"),
        (
            '<PlusConfiguration><CoordinateDefinitions><Transform From="Image" To="Probe" Matrix="1 0 0 0 0 1 0 0 0 0 1 0 0 0 1"/>'
            "</CoordinateDefinitions></PlusConfiguration>",
            "CoordinateDefinitions Transform Image->Probe Matrix: expected 16 numbers, got 15",
        ),
        (
            '<PlusConfiguration><VolumeReconstruction OutputSpacing="0.5 0.5 0.5" CompoundingMode="IMPORTANCE_MASK"/></PlusConfiguration>',
            "VolumeReconstruction CompoundingMode: unsupported value 'IMPORTANCE_MASK'",
        ),
        (
            '<PlusConfiguration><VolumeReconstruction Interpolation="LINEAR"/></PlusConfiguration>',
            "OutputSpacing is missing",
        ),
    ],
)
def test_malformed_configs_are_reported(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "config.xml"
    path.write_text(text)
    with pytest.raises(FileFormatError, match=message) as info:
        read_plus_config(path)
    assert str(path) in str(info.value)
