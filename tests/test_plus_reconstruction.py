"""Our compounding of the real PLUS sweep against the volumes PLUS reconstructed from it.

The sweep is read with each configuration (calibration, clip rectangle, interpolation,
compounding) and compounded onto the grid of PLUS's reference volume (the configurations give no
OutputOrigin/OutputExtent: PLUS fitted the grid to the frames, and test_plus_data checks that its
origin is the corner of our frames). Thresholds come from a run (numbers in each case's comment),
with margin; they fail for a wrong calibration, pose composition or pixel convention.

Known differences, so the comparison is on voxels both volumes hold:
- NN_MEAN: PLUS filled holes (STICK, FillHoles="ON"), so many PLUS voxels lie between our slices.
- LN_MAXI: PLUS's trilinear MAXIMUM updates only the corners with weight >= 0.125
  (vtkPlusPasteSliceIntoVolumeHelperCommon.h), a subset of the corners we splat to.
- PLUS stores uint8 and its means read ~4 grey levels lower (slope 0.98) than the exact mean, which
  an independent NumPy nearest-neighbour mean reproduces from our side to 1e-5.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from usdeform.compounding import Compounder
from usdeform.io import read_plus_config, read_sequence, read_volume
from usdeform.volume import Volume, VoxelGrid

DATA = Path(__file__).resolve().parent / "data" / "plus"
SWEEP = DATA / "SpinePhantomFreehand.igs.mha"


def reconstruct(config_path: Path, reference: Volume) -> Volume:
    config = read_plus_config(config_path)
    recording = read_sequence(SWEEP, config=config)
    settings = config.reconstruction
    (col0, row0), (cols, rows) = settings.clip_rectangle_origin, settings.clip_rectangle_size
    frames = recording.frames[:, row0 : row0 + rows, col0 : col0 + cols]
    clip_to_image = np.eye(4)
    clip_to_image[:2, 3] = [col0, row0]  # pixel (c, r) of the clipped frame is pixel (c + col0, r + row0)
    valid = recording.pose_valid
    compounder = Compounder(reference.grid, settings.interpolation, settings.compounding)
    compounder.add_frames(np.ascontiguousarray(frames[valid]), (recording.image_to_base @ clip_to_image)[valid])
    return compounder.volume()


def test_nearest_mean_matches_plus() -> None:
    reference = read_volume(DATA / "vtkVolumeReconstructorTestNNMEANvolumeRef.mha")
    ours = reconstruct(DATA / "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml", reference)
    ours_nonzero = ours.image >= 0.5
    plus_nonzero = reference.image > 0
    both = ours_nonzero & plus_nonzero
    # Run: 0.906 of our non-zero voxels are non-zero in PLUS's volume.
    assert both.sum() / ours_nonzero.sum() > 0.85
    difference = np.abs(ours.image[both] - reference.image[both])
    # Run: correlation 0.9988, mean |difference| 5.05 and median 3.9 grey levels.
    assert np.corrcoef(ours.image[both], reference.image[both])[0, 1] > 0.995
    assert difference.mean() < 7.0
    assert np.median(difference) < 5.0


def test_linear_maximum_matches_plus() -> None:
    reference = read_volume(DATA / "vtkVolumeReconstructorTestLNMAXIvolumeRef.mha")
    ours = reconstruct(DATA / "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_LN_MAXI.xml", reference)
    plus_nonzero = reference.image > 0
    # Run: every non-zero PLUS voxel is covered by our splats (1.0); PLUS fills no holes here.
    assert (plus_nonzero & (ours.weight > 0)).sum() / plus_nonzero.sum() > 0.999
    both = plus_nonzero & (ours.image >= 0.5)
    difference = np.abs(ours.image[both] - reference.image[both])
    # Run: correlation 0.9915, mean |difference| 6.6 and median 2 grey levels.
    assert np.corrcoef(ours.image[both], reference.image[both])[0, 1] > 0.98
    assert difference.mean() < 9.0
    assert np.median(difference) <= 3.0


def test_comparison_detects_a_misplaced_sweep() -> None:
    """The NN_MEAN bounds fail for a sweep placed 1 mm (2 voxels) off along x (run: correlation 0.964, mean 13.6)."""
    reference = read_volume(DATA / "vtkVolumeReconstructorTestNNMEANvolumeRef.mha")
    shifted = np.array(reference.grid.index_to_world)
    shifted[0, 3] += 1.0
    moved = Volume(reference.image, VoxelGrid(reference.grid.shape, shifted))
    ours = reconstruct(DATA / "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml", moved)
    both = (ours.image >= 0.5) & (reference.image > 0)
    assert np.corrcoef(ours.image[both], reference.image[both])[0, 1] < 0.995
    assert np.abs(ours.image[both] - reference.image[both]).mean() > 7.0
