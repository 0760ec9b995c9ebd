"""The grid ``usdeform reconstruct --config`` fits to the frames is PLUS's, without passing it in.

PLUS's VolumeReconstructor fits the grid to the frames with
``vtkIGSIOVolumeReconstructor::SetOutputExtentFromFrameList`` (IGSIO, the base of PLUS's
``vtkPlusVolumeReconstructor``): the clip rectangle's corners (far corner one pixel beyond the
rectangle, capped at the frame's last pixel), origin on their minimum, last plane of each axis the one
nearest to their maximum (``std::round``). Its regression volumes (``vtkVolumeReconstructorTest*volumeRef.mha``)
follow that rule; ``SpinePhantomFreehandReconstructed.mha`` was written by an older PLUS, whose
``vtkVolumeReconstructor::SetOutputExtentFromFrameList`` truncated (``int(...)``), one plane fewer along z.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from usdeform.io import read_plus_config, read_sequence, read_volume
from usdeform.volume import VoxelGrid, output_grid, plus_grid_for_frames

SWEEP = "SpinePhantomFreehand.igs.mha"
#: configuration -> the volume PLUS's regression tests reconstructed with it
REFERENCES = {
    f"PlusDeviceSet_VolumeReconstructionOnly_{setup}_{case}.xml": f"vtkVolumeReconstructorTest{reference}volumeRef.mha"
    for setup, case, reference in (
        ("SpinePhantom", "NN_MEAN", "NNMEAN"),
        ("SpinePhantom", "LN_MAXI", "LNMAXI"),
        ("SonixRP_TRUS_D70mm", "NN_LATE", "NNLATE"),
        ("SonixRP_TRUS_D70mm", "LN_MEAN", "LNMEAN"),
    )
}
OLDER_PLUS = ("PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml", "SpinePhantomFreehandReconstructed.mha")


def ours_and_plus(plus_data: Path, config_name: str, reference_name: str) -> tuple[VoxelGrid, VoxelGrid]:
    config = read_plus_config(plus_data / config_name)
    recording = read_sequence(plus_data / SWEEP, config=config)
    ours = output_grid(recording.image_to_base[recording.pose_valid], recording.shape, config.reconstruction)
    return ours, read_volume(plus_data / reference_name).grid


def assert_same_header(ours: VoxelGrid, plus: VoxelGrid) -> None:
    """Shape, spacing and direction equal; origin equal as PLUS writes it (6 significant digits)."""
    assert ours.shape == plus.shape
    np.testing.assert_array_equal(ours.spacing, plus.spacing)
    np.testing.assert_array_equal(ours.direction, plus.direction)
    np.testing.assert_array_equal([float(f"{v:.6g}") for v in ours.origin], plus.origin)


@pytest.mark.parametrize("config_name", sorted(REFERENCES))
def test_grid_is_plus_reference_grid(plus_data: Path, config_name: str) -> None:
    # Before: (104, 106, 147) for PLUS's (105, 106, 147) (SpinePhantom), (98, 92, 79) for (98, 93, 80) (SonixRP).
    assert_same_header(*ours_and_plus(plus_data, config_name, REFERENCES[config_name]))


def test_older_plus_volume_differs_only_by_its_truncated_extent(plus_data: Path) -> None:
    """Same sweep and clip rectangle (the whole frame) as NN_MEAN: the same corners, origin, x and y; the
    older PLUS truncated the extent (``last_plane="inside"``), one z plane fewer than the current PLUS's 105."""
    ours, older = ours_and_plus(plus_data, *OLDER_PLUS)
    assert (ours.shape, older.shape) == ((105, 106, 147), (104, 106, 147))
    config = read_plus_config(plus_data / OLDER_PLUS[0])
    recording = read_sequence(plus_data / SWEEP, config=config)
    rows, cols = recording.shape
    corners = np.array([[c, r, 0, 1] for c in (0, cols - 1) for r in (0, rows - 1)], dtype=np.float64).T
    points = np.concatenate([(pose @ corners)[:3].T for pose in recording.image_to_base[recording.pose_valid]])
    assert_same_header(VoxelGrid.from_bounds(points.min(axis=0), points.max(axis=0), 0.5), older)


def test_reconstruct_command_writes_plus_grid(plus_data: Path, tmp_path: Path) -> None:
    from usdeform.cli import main

    config_name = "PlusDeviceSet_VolumeReconstructionOnly_SonixRP_TRUS_D70mm_NN_LATE.xml"
    output = tmp_path / "volume.mha"
    assert (
        main(["reconstruct", str(plus_data / SWEEP), "--config", str(plus_data / config_name), "--output", str(output)])
        == 0
    )
    assert_same_header(read_volume(output).grid, read_volume(plus_data / REFERENCES[config_name]).grid)


def test_clip_rectangle_corners_as_plus_takes_them() -> None:
    """The far corner is one pixel beyond the rectangle, capped at the frame's last pixel; halves round up."""
    pose = np.eye(4)[np.newaxis]
    inside = plus_grid_for_frames(pose, (10, 20), 1.0, clip_rectangle=((2, 3), (5, 4)))
    np.testing.assert_array_equal(inside.origin, [2, 3, 0])
    assert inside.shape == (1, 5, 6)  # columns 2..7, rows 3..7
    at_edge = plus_grid_for_frames(pose, (10, 20), 1.0, clip_rectangle=((15, 6), (5, 4)))
    assert at_edge.shape == (1, 4, 5)  # columns 15..19, rows 6..9: capped
    assert plus_grid_for_frames(pose, (10, 20), 1.0).shape == (1, 10, 20)
    assert plus_grid_for_frames(pose, (10, 20), 2.0).shape == (1, 6, 11)  # 9.5 and 4.5 steps round up
