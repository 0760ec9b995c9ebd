"""Volume files: round trips with spacing, origin and direction, weights, PLUS references, errors."""

from __future__ import annotations

from pathlib import Path

import nrrd
import numpy as np
import pytest

from test_recording import random_rigid
from usdeform.errors import FileFormatError, InputError
from usdeform.io import read_volume, write_volume
from usdeform.volume import Volume, VoxelGrid


def oblique_volume(dtype: type, with_weight: bool = True) -> Volume:
    """A (4, 5, 6) volume on a rotated, anisotropic grid with an arbitrary origin."""
    rng = np.random.default_rng(30)
    index_to_world = random_rigid(rng, 1)[0] @ np.diag([0.3, 0.5, 1.25, 1.0])
    grid = VoxelGrid((4, 5, 6), index_to_world)
    if dtype == np.uint8:
        image = rng.integers(0, 256, size=grid.shape, dtype=np.uint8)
    else:
        image = rng.normal(size=grid.shape).astype(dtype)
    weight = rng.uniform(0, 3, size=grid.shape).astype(np.float32) if with_weight else None
    return Volume(image=image, grid=grid, weight=weight)


@pytest.mark.parametrize("name", ["vol.nrrd", "vol.mha", "vol.mhd"])
@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
@pytest.mark.parametrize("compress", [True, False])
def test_round_trip_keeps_image_and_geometry(tmp_path: Path, name: str, dtype: type, compress: bool) -> None:
    volume = oblique_volume(dtype, with_weight=False)
    write_volume(tmp_path / name, volume, compress=compress)
    read = read_volume(tmp_path / name)
    assert read.image.dtype == dtype
    np.testing.assert_array_equal(read.image, volume.image)
    np.testing.assert_allclose(read.index_to_world, volume.index_to_world, rtol=0, atol=1e-12)
    assert read.weight is None


@pytest.mark.parametrize("name", ["vol.nrrd", "vol.mha"])
def test_weight_is_written_only_when_asked(tmp_path: Path, name: str) -> None:
    volume = oblique_volume(np.float32)
    write_volume(tmp_path / name, volume)
    assert [p.name for p in tmp_path.iterdir()] == [name]
    weight_name = "weight" + Path(name).suffix
    write_volume(tmp_path / name, volume, weight_path=tmp_path / weight_name)
    read = read_volume(tmp_path / name, weight_path=tmp_path / weight_name)
    np.testing.assert_array_equal(read.weight, volume.weight)
    np.testing.assert_array_equal(read.image, volume.image)


def test_metaimage_header_lists_axis_directions_as_itk_reads_them(tmp_path: Path) -> None:
    volume = oblique_volume(np.float32, with_weight=False)
    write_volume(tmp_path / "vol.mha", volume, compress=False)
    header = dict(
        line.split(" = ", 1)
        for line in (tmp_path / "vol.mha").read_bytes().split(b"ElementDataFile")[0].decode().splitlines()
    )
    assert header["DimSize"] == "6 5 4"
    assert header["ElementType"] == "MET_FLOAT"
    assert header["AnatomicalOrientation"] == "RAI"
    np.testing.assert_allclose(np.array(header["ElementSpacing"].split(), float), [0.3, 0.5, 1.25])
    np.testing.assert_array_equal(np.array(header["Offset"].split(), float), volume.grid.origin)
    # ITK's MetaImageIO takes the i-th group of three numbers as the direction of axis i.
    directions = np.array(header["TransformMatrix"].split(), float).reshape(3, 3)
    np.testing.assert_allclose(directions, volume.grid.direction.T, atol=1e-15)


def test_nrrd_header_declares_lps_space(tmp_path: Path) -> None:
    volume = oblique_volume(np.uint8, with_weight=False)
    write_volume(tmp_path / "vol.nrrd", volume)
    header = nrrd.read_header(str(tmp_path / "vol.nrrd"))
    assert header["space"] == "left-posterior-superior"
    assert list(header["kinds"]) == ["domain", "domain", "domain"]
    np.testing.assert_allclose(header["space directions"], volume.index_to_world[:3, :3].T, atol=1e-15)


def test_ras_nrrd_is_converted_to_lps(tmp_path: Path) -> None:
    image = np.arange(24, dtype=np.uint8).reshape(2, 3, 4)
    header = {
        "space": "right-anterior-superior",
        "space directions": np.diag([0.5, 0.6, 0.7]),
        "space origin": np.array([10.0, 20.0, 30.0]),
    }
    nrrd.write(str(tmp_path / "ras.nrrd"), image, header, index_order="C")
    read = read_volume(tmp_path / "ras.nrrd")
    np.testing.assert_array_equal(read.image, image)
    np.testing.assert_allclose(
        read.index_to_world, [[-0.5, 0, 0, -10], [0, -0.6, 0, -20], [0, 0, 0.7, 30], [0, 0, 0, 1]]
    )


def test_writing_rejects_unsupported_input(tmp_path: Path) -> None:
    volume = oblique_volume(np.float32, with_weight=False)
    with pytest.raises(InputError, match="uint8 or float32"):
        write_volume(tmp_path / "vol.nrrd", Volume(volume.image.astype(np.float64), volume.grid))
    with pytest.raises(InputError, match="no weight to write"):
        write_volume(tmp_path / "vol.nrrd", volume, weight_path=tmp_path / "w.nrrd")
    with pytest.raises(InputError, match=r"must end in .nrrd, .mha or .mhd"):
        write_volume(tmp_path / "vol.vtk", volume)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["vol.nrrd", "vol.mha"])
def test_truncated_volume_is_a_file_error(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    write_volume(path, oblique_volume(np.float32, with_weight=False), compress=False)
    path.write_bytes(path.read_bytes()[:-8])
    with pytest.raises(FileFormatError, match="pixel data") as info:
        read_volume(path)
    assert str(path) in str(info.value)


def test_mismatched_weight_grid_is_a_file_error(tmp_path: Path) -> None:
    volume = oblique_volume(np.float32)
    write_volume(tmp_path / "vol.mha", volume)
    write_volume(tmp_path / "other.mha", Volume(volume.image, VoxelGrid(volume.grid.shape, np.eye(4))))
    with pytest.raises(FileFormatError, match="weight grid differs"):
        read_volume(tmp_path / "vol.mha", weight_path=tmp_path / "other.mha")


@pytest.mark.parametrize(
    ("name", "shape", "origin"),
    [
        # DimSize (x y z) and Offset as printed in each file's header.
        ("vtkVolumeReconstructorTestNNMEANvolumeRef.mha", (105, 106, 147), (-74.5217, 165.573, 29.072)),
        ("vtkVolumeReconstructorTestLNMAXIvolumeRef.mha", (105, 106, 147), (-74.5217, 165.573, 29.072)),
        ("vtkVolumeReconstructorTestNNLATEvolumeRef.mha", (98, 93, 80), (-57.0272, 168.545, 30.5384)),
        ("vtkVolumeReconstructorTestLNMEANvolumeRef.mha", (98, 93, 80), (-57.0272, 168.545, 30.5384)),
    ],
)
def test_reads_plus_reference_volumes(
    plus_data: Path, name: str, shape: tuple[int, int, int], origin: tuple[float, float, float]
) -> None:
    path = plus_data / name
    volume = read_volume(path)
    assert volume.image.shape == shape
    assert volume.image.dtype == np.uint8
    np.testing.assert_array_equal(volume.grid.spacing, [0.5, 0.5, 0.5])
    np.testing.assert_array_equal(volume.grid.origin, origin)
    np.testing.assert_array_equal(volume.grid.direction, np.eye(3))
    # Uncompressed (CompressedData = False): the voxels are the file's last bytes, x fastest.
    raw = np.frombuffer(path.read_bytes()[-volume.image.size :], np.uint8)
    np.testing.assert_array_equal(volume.image.ravel(), raw)
