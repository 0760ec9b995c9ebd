"""The Recording data model: validation, helpers and the paper's eq. 2 calibration."""

from __future__ import annotations

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.recording import Recording, image_to_probe_from_geometry


def random_rigid(rng: np.random.Generator, count: int) -> np.ndarray:
    """(count, 4, 4) random rotations (QR of Gaussian matrices) with translations in +-200 mm."""
    q, r = np.linalg.qr(rng.normal(size=(count, 3, 3)))
    q *= np.sign(np.diagonal(r, axis1=1, axis2=2))[:, np.newaxis, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = q
    poses[:, :3, 3] = rng.uniform(-200, 200, size=(count, 3))
    return poses


def random_recording(
    rng: np.random.Generator,
    count: int = 5,
    rows: int = 7,
    cols: int = 9,
    with_force: bool = True,
    with_displacement: bool = True,
) -> Recording:
    """A random recording with arbitrary (full-precision) float values and one invalid pose."""
    pose_valid = np.ones(count, dtype=bool)
    pose_valid[count // 2] = False
    return Recording(
        frames=rng.integers(0, 256, size=(count, rows, cols), dtype=np.uint8),
        timestamps=np.cumsum(rng.uniform(0.0, 0.1, size=count)) + rng.uniform(0, 1e4),
        probe_to_base=random_rigid(rng, count),
        pose_valid=pose_valid,
        image_to_probe=image_to_probe_from_geometry(rows, cols, 40.0, 37.5, rng.uniform(0, 3)),
        force=rng.uniform(0, 20, size=count) if with_force else None,
        probe_displacement=rng.uniform(0, 10, size=count) if with_displacement else None,
        metadata={"Operator": "robot 1", "ProbeModel": "C5-2 / 3.5 MHz"},
    )


def recording_kwargs(rng: np.random.Generator) -> dict:
    recording = random_recording(rng)
    return {name: getattr(recording, name) for name in recording.__dataclass_fields__}


def test_valid_recording_exposes_read_only_arrays_and_helpers() -> None:
    rng = np.random.default_rng(0)
    recording = random_recording(rng, count=4, rows=3, cols=5)
    assert len(recording) == 4
    assert recording.shape == (3, 5)
    assert recording.frames.flags.c_contiguous
    for name in ("frames", "timestamps", "probe_to_base", "pose_valid", "image_to_probe", "force"):
        with pytest.raises(ValueError):
            getattr(recording, name)[0] = 0
    expected = np.stack([pose @ recording.image_to_probe for pose in recording.probe_to_base])
    np.testing.assert_allclose(recording.image_to_base, expected, rtol=0, atol=1e-12)


def test_non_contiguous_frames_are_stored_contiguous() -> None:
    kwargs = recording_kwargs(np.random.default_rng(1))
    frames = np.asfortranarray(kwargs["frames"])
    recording = Recording(**{**kwargs, "frames": frames})
    assert recording.frames.flags.c_contiguous
    np.testing.assert_array_equal(recording.frames, frames)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"frames": np.zeros((5, 7, 9), dtype=np.float32)}, "frames: expected dtype uint8"),
        ({"frames": np.zeros((7, 9), dtype=np.uint8)}, "frames: expected a non-empty (n, rows, cols)"),
        ({"timestamps": np.zeros(4)}, "timestamps: expected shape (5,)"),
        ({"timestamps": [0.0, 1.0, 2.0, 1.5, 3.0]}, "timestamps: must be non-decreasing, frame 3"),
        ({"timestamps": [0.0, 1.0, np.nan, 2.0, 3.0]}, "timestamps: non-finite value at frame 2"),
        ({"pose_valid": np.ones(5, dtype=np.uint8)}, "pose_valid: expected dtype bool"),
        ({"probe_to_base": np.zeros((5, 3, 4))}, "probe_to_base: expected shape (5, 4, 4)"),
        ({"image_to_probe": np.zeros((4, 4))}, "image_to_probe: last row must be [0, 0, 0, 1]"),
        ({"force": [1.0, 2.0, 3.0, np.inf, 5.0]}, "force: non-finite value at frame 3"),
        ({"probe_displacement": np.zeros(6)}, "probe_displacement: expected shape (5,)"),
        ({"metadata": {"Bad=Key": "x"}}, "metadata: key 'Bad=Key'"),
        ({"metadata": {"Key": "two\nlines"}}, "metadata['Key']: value must be one line"),
    ],
)
def test_invalid_input_is_rejected_with_a_message_naming_it(change: dict, message: str) -> None:
    kwargs = recording_kwargs(np.random.default_rng(2))
    with pytest.raises(InputError) as info:
        Recording(**{**kwargs, **change})
    assert message in str(info.value)


def test_pose_checks_name_the_frame_and_skip_invalid_poses() -> None:
    kwargs = recording_kwargs(np.random.default_rng(3))
    poses = np.array(kwargs["probe_to_base"])
    invalid = int(np.flatnonzero(~kwargs["pose_valid"])[0])
    poses[invalid] = 0.0  # an unusable pose may hold anything
    Recording(**{**kwargs, "probe_to_base": poses})
    poses[4, 3, 0] = 0.5
    with pytest.raises(InputError, match=r"probe_to_base: frame 4: last row must be \[0, 0, 0, 1\]"):
        Recording(**{**kwargs, "probe_to_base": poses})
    poses[4, 3, 0] = 0.0
    poses[1, 0, 2] = np.nan
    with pytest.raises(InputError, match="probe_to_base: non-finite value at frame 1"):
        Recording(**{**kwargs, "probe_to_base": poses})


@pytest.mark.parametrize("indices", [[4, 0, 2], np.array([True, False, True, True, False]), slice(1, 4)])
def test_select_picks_frames_of_every_per_frame_array(indices: object) -> None:
    kwargs = recording_kwargs(np.random.default_rng(4))
    recording = Recording(**{**kwargs, "timestamps": np.zeros(5)})  # equal times: any order is non-decreasing
    picked = np.arange(5)[indices]
    subset = recording.select(indices)
    assert len(subset) == len(picked)
    np.testing.assert_array_equal(subset.frames, recording.frames[picked])
    np.testing.assert_array_equal(subset.probe_to_base, recording.probe_to_base[picked])
    np.testing.assert_array_equal(subset.pose_valid, recording.pose_valid[picked])
    np.testing.assert_array_equal(subset.force, recording.force[picked])
    np.testing.assert_array_equal(subset.probe_displacement, recording.probe_displacement[picked])
    np.testing.assert_array_equal(subset.image_to_probe, recording.image_to_probe)
    assert subset.metadata == recording.metadata


def test_select_keeps_missing_force_and_rejects_empty_or_bad_selections() -> None:
    recording = random_recording(np.random.default_rng(5), with_force=False, with_displacement=False)
    assert recording.select([1, 2]).force is None
    assert recording.select([1, 2]).probe_displacement is None
    with pytest.raises(InputError, match="selects no frame"):
        recording.select([])
    with pytest.raises(InputError, match="indices"):
        recording.select([7])


def test_eq2_calibration_maps_image_corners_to_the_probe_face() -> None:
    rows, cols = 400, 300
    image_to_probe = image_to_probe_from_geometry(rows, cols, depth_mm=40.0, width_mm=37.5, offset_mm=1.5)
    expected = np.array(
        [[37.5 / 300, 0, 0, -18.75], [0, 0, -1, 0], [0, 40.0 / 400, 0, 1.5], [0, 0, 0, 1]], dtype=np.float64
    )
    np.testing.assert_array_equal(image_to_probe, expected)
    top_left = image_to_probe @ [0, 0, 0, 1]
    bottom_right = image_to_probe @ [cols, rows, 0, 1]
    np.testing.assert_allclose(top_left, [-18.75, 0, 1.5, 1])  # centre of the probe face, offset by epsilon
    np.testing.assert_allclose(bottom_right, [18.75, 0, 41.5, 1])  # full width, full depth
    np.testing.assert_allclose(image_to_probe @ [0, 0, 1, 0], [0, -1, 0, 0])  # image normal -> probe -y


def test_eq2_calibration_rejects_bad_geometry() -> None:
    with pytest.raises(InputError, match="rows, cols"):
        image_to_probe_from_geometry(0, 10)
    with pytest.raises(InputError, match="depth_mm"):
        image_to_probe_from_geometry(10, 10, depth_mm=-1.0)
