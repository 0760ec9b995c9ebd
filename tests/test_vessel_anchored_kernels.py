"""The compiled vessel-anchored correction (issue 41) against its NumPy twins and the per-frame path
it replaced: the field on a window, the fused warp, the compounder, and a whole sweep's lumens."""

from __future__ import annotations

import warnings
from functools import partial

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kernel_inputs import (
    anchored_sweep_case,
    random_anchored_model,
    random_frames,
    random_profile,
    vessel_frames,
)
from test_kernels_equivalence import assert_warped_alike
from usdeform import _core, reference
from usdeform.correction import correct_frames, frame_vessel_anchor, sweep_lumens, vessel_placements
from usdeform.correction._folds import FoldedVesselWarning, vessel_part_scales
from usdeform.correction._frames import correct_like
from usdeform.correction._vessel import correct_vessel_anchored
from usdeform.errors import InputError
from usdeform.regression import LumenTrack, StiffnessProfile, VesselAnchor, profiles_array
from usdeform.volume import Compounder, VoxelGrid

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
seeds = st.integers(0, 2**32 - 1)
sizes = st.integers(4, 48)


def random_anchors(rng: np.random.Generator, n: int, rows: int, cols: int) -> np.ndarray:
    """(n, 3) lumens (x, y, radius), some reaching past the frame's edges."""
    return np.column_stack(
        [rng.uniform(-5, cols + 5, n), rng.uniform(-5, rows + 5, n), rng.uniform(0.5, max(rows, cols) / 3, n)]
    )


@SETTINGS
@given(seed=seeds, rows=sizes, cols=sizes, with_lumen=st.booleans())
def test_field_on_a_window_matches_reference(seed: int, rows: int, cols: int, with_lumen: bool) -> None:
    rng = np.random.default_rng(seed)
    model = random_anchored_model(rng, rows, cols)
    force, profile = rng.uniform(0, model.normalization.force_scale), random_profile(rng)
    x, y, radius = random_anchors(rng, 1, rows, cols)[0]
    lumen = VesselAnchor((x, y), radius) if with_lumen else None
    top, left = rng.integers(0, rows), rng.integers(0, cols)
    window = (slice(top, rng.integers(top + 1, rows + 1)), slice(left, rng.integers(left + 1, cols + 1)))
    got = model.displacement_on(force, profile, lumen, window)
    expected = reference.anchored_displacement(model, force, profile, lumen, window)
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-9)


@SETTINGS
@given(
    seed=seeds,
    n_frames=st.integers(1, 4),
    rows=sizes,
    cols=sizes,
    dtype=st.sampled_from([np.uint8, np.float32]),
    fill=st.floats(0, 255),
)
def test_fused_warp_matches_reference(seed: int, n_frames: int, rows: int, cols: int, dtype: type, fill: float) -> None:
    rng = np.random.default_rng(seed)
    model = random_anchored_model(rng, rows, cols)
    frames = random_frames(rng, n_frames, rows, cols, dtype)
    forces = rng.uniform(0, model.normalization.force_scale, n_frames)
    profiles = profiles_array([random_profile(rng) for _ in range(n_frames)], n_frames)
    anchors = random_anchors(rng, n_frames, rows, cols)
    kernel, vessel = model.image_model.kernel, model.vessel_kernel
    call = partial(_core.warp_frames, frames, forces, profiles, kernel, fill=fill, return_mask=True, vessel=vessel)
    got, valid = call(anchors=anchors)
    one, one_valid = call(anchors=anchors, threads=1)
    assert np.array_equal(one, got) and np.array_equal(one_valid, valid)  # the same for any thread count
    expected, expected_valid = reference.warp_anchored_frames(frames, forces, profiles, model, anchors, fill=fill)
    assert np.count_nonzero(valid != expected_valid) <= max(1, 1e-3 * valid.size)
    assert_warped_alike(got, expected)


def _fused_case(seed: int, n_frames: int):
    """A model, a sweep of 40 x 36 frames whose lumen drifts, a grid, poses into it, forces, a profile."""
    centres = np.column_stack([np.linspace(14, 22, n_frames), np.full(n_frames, 19.0)])
    grid = VoxelGrid((20, 22, 24), np.diag([1.5, 1.5, 1.5, 1.0]))
    model, frames, poses, forces, profile = anchored_sweep_case(np.random.default_rng(seed), 40, 36, centres, 5.0, grid)
    return model, frames, grid, poses, forces, profile


def test_fused_compounding_is_the_warp_then_the_insertion() -> None:
    model, frames, grid, poses, forces, profile = _fused_case(3, 70)  # more than one chunk of frames
    corrected, valid = correct_frames(frames, forces, profile, model, return_mask=True)
    separate = Compounder(grid, "linear", "mean")
    separate.add_frames(corrected, poses, valid=valid)
    volumes = []
    for threads in (1, 2):
        fused = Compounder(grid, "linear", "mean")
        fused.add_corrected_frames(frames, poses, forces, profile, model, threads=threads)
        volumes.append(fused.volume())
    expected = separate.volume()
    for volume in volumes:
        assert np.array_equal(volume.image, expected.image) and np.array_equal(volume.weight, expected.weight)


def test_fused_compounding_checks_every_frame_before_inserting_any() -> None:
    """The lumen search and the insertion overlap, chunk by chunk; a bad pose or force far into the
    sweep is still refused before anything is inserted, and named by its frame in the whole sweep."""
    model, frames, grid, poses, forces, profile = _fused_case(5, 50)
    bad_poses = poses.copy()
    bad_poses[41, 0, 3] = np.nan
    compounder = Compounder(grid, "nearest", "mean")
    with pytest.raises(InputError, match=r"frame 41: the transform holds non-finite values"):
        compounder.add_corrected_frames(frames, bad_poses, forces, profile, model)
    bad_forces = forces.copy()
    bad_forces[45] = np.inf
    with pytest.raises(InputError, match=r"forces"):
        compounder.add_corrected_frames(frames, poses, bad_forces, profile, model)
    negative = frames.astype(np.float32)
    negative[47, 0, 0] = -1.0
    with pytest.raises(InputError, match=r"^frames\[47\]: B-mode intensities must be finite and non-negative"):
        compounder.add_corrected_frames(negative, poses, forces, profile, model)
    assert compounder.frames_inserted == 0
    assert not compounder.volume().weight.any()


def assert_same_lumens(found: list, twin_found: list) -> None:
    """The same frames without a lumen, and the same centre and radius (pixels) on the others."""
    assert [a is None for a in found] == [a is None for a in twin_found]
    for anchor, twin in zip(found, twin_found, strict=True):
        if anchor is not None and twin is not None:
            np.testing.assert_allclose(
                [*anchor.centre_px, anchor.radius_px], [*twin.centre_px, twin.radius_px], atol=1e-9
            )


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    dtype=st.sampled_from([np.uint8, np.float32]),
    radius=st.floats(3.0, 14.0),
    start_x=st.floats(-10.0, 80.0),
    missed=st.integers(0, 3),
)
def test_lumen_search_matches_the_twin_on_random_sweeps(
    seed: int, dtype: type, radius: float, start_x: float, missed: int
) -> None:
    """On random sweeps (lumens of random size drifting in from and out past the frame's edges,
    uint8 or float32, a search going on from a random earlier state), the compiled search finds what
    its twin finds and leaves the search in the same state."""
    rng = np.random.default_rng(seed)
    rows, cols, n_frames = 48, 56, 8
    model = random_anchored_model(rng, rows, cols, image_scale=0.05)
    centres = np.column_stack([start_x + np.arange(n_frames) * rng.uniform(-4, 4), rng.uniform(0, rows, n_frames)])
    frames = vessel_frames(rng, centres, radius, rows, cols).astype(dtype)
    forces = rng.uniform(0.2, 0.8, n_frames) * model.normalization.force_scale
    profiles = profiles_array([random_profile(rng) for _ in range(n_frames)], n_frames)
    # an earlier lumen anywhere near the frame, some just beside it (a window of a column or two)
    earlier = VesselAnchor(
        (float(rng.uniform(-30, cols + 30)), float(rng.uniform(-30, rows + 30))), float(rng.uniform(1, 10))
    )
    tracks = [LumenTrack(earlier, missed), LumenTrack(earlier, missed)]
    found = sweep_lumens(frames, forces, profiles, model, track=tracks[0])
    twin_found = reference.sweep_lumens(frames, forces, profiles, model, track=tracks[1])
    assert_same_lumens(found, twin_found)
    assert tracks[0].frames_missed == tracks[1].frames_missed
    assert_same_lumens([tracks[0].last_found], [tracks[1].last_found])


@pytest.mark.parametrize("near_x", [-6.6, -5.5, 77.8])
def test_a_search_window_a_column_wide_is_searched_again_in_the_whole_frame(near_x: float) -> None:
    """A lumen expected just beside the frame leaves a window one or two columns wide: too narrow to
    hold a lumen, so the whole frame is searched, as the twin does (no error; the lumen found there
    does not overlap the one expected, so none is taken)."""
    frames, forces, profiles, model = _sweep(4)
    near = VesselAnchor((near_x, 20.0), 2.6)
    found = frame_vessel_anchor(frames[0], float(forces[0]), StiffnessProfile(*profiles[0]), model, near=near)
    twin = reference.sweep_lumens(frames[:1], forces[:1], profiles[:1], model, track=LumenTrack(near))
    assert_same_lumens([found], twin)


def _sweep(seed: int, n_frames: int = 30, rows: int = 64, cols: int = 72):
    """A sweep whose lumen drifts and vanishes for a few frames, with a model placed on it."""
    rng = np.random.default_rng(seed)
    model = random_anchored_model(rng, rows, cols, image_scale=0.05)
    centres = np.column_stack([np.linspace(24, 46, n_frames), 30 + 3 * np.sin(np.arange(n_frames) / 4)])
    frames = vessel_frames(rng, centres, 8.0, rows, cols)
    frames[n_frames // 2 : n_frames // 2 + 3] = vessel_frames(rng, centres[:3], 0.0, rows, cols)  # no lumen
    forces = rng.uniform(0.2, 0.8, n_frames) * model.normalization.force_scale
    profiles = profiles_array([random_profile(rng) for _ in range(n_frames)], n_frames)
    return frames, forces, profiles, model


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_sweep_matches_the_numpy_twin_of_the_per_frame_path(seed: int, dtype: type) -> None:
    """The compiled lumen search and its twin (``reference.sweep_lumens``: OpenCV's remap and
    ``segment_vessel`` frame by frame, with the NumPy twin of the field) find the same lumens; the
    frames warped in one call agree with the twin's frame-by-frame warp."""
    frames, forces, profiles, model = _sweep(seed)
    frames = frames.astype(dtype)
    corrected, valid, found = correct_vessel_anchored(frames, forces, profiles, model)
    twin_found = reference.sweep_lumens(
        frames, forces, profiles, model, partial(reference.anchored_displacement, model)
    )
    assert sum(anchor is None for anchor in found) >= 3  # the frames without a lumen
    assert_same_lumens(found, twin_found)
    placed = vessel_placements(found, model)
    with warnings.catch_warnings():  # a random vessel part may fold the map: the correction attenuated it there
        warnings.simplefilter("ignore", FoldedVesselWarning)
        scales = vessel_part_scales(forces, profiles, model, [placed])[0]
    expected, expected_valid = reference.warp_anchored_frames(frames, forces, profiles, model, placed, scales=scales)
    assert np.count_nonzero(valid != expected_valid) <= max(1, 1e-3 * valid.size)
    assert_warped_alike(corrected, expected)
    masks = (frames < 40).astype(np.uint8) * 255
    like = correct_like(masks, frames, forces, profiles, model)  # the masks warped on the same lumens
    assert np.array_equal(like, correct_vessel_anchored(masks, forces, profiles, model, anchors=found)[0])


def test_vessel_arguments_are_checked() -> None:
    rng = np.random.default_rng(0)
    model = random_anchored_model(rng, 16, 16)
    frames, forces, profiles = np.zeros((2, 16, 16), np.uint8), np.ones(2), np.tile((0.1, 1.0, 0.0), (2, 1))
    call = partial(_core.warp_frames, frames, forces, profiles, model.image_model.kernel)
    with pytest.raises(InputError, match="vessel, anchors"):
        call(anchors=np.ones((2, 3)))
    with pytest.raises(InputError, match="anchors: expected shape"):
        call(vessel=model.vessel_kernel, anchors=np.ones((3, 3)))
    with pytest.raises(InputError, match="radius of anchor 1"):
        call(vessel=model.vessel_kernel, anchors=np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 0.0]]))
    with pytest.raises(InputError, match="anchors"):
        call(vessel=model.vessel_kernel, anchors=np.array([[1.0, np.nan, 1.0], [1.0, 1.0, 1.0]]))
    with pytest.raises(InputError, match="window"):
        model.displacement_on(1.0, random_profile(rng), None, (slice(0, 17), slice(0, 4)))
    with pytest.raises(InputError, match="vessel_coefficients"):
        _core.VesselPart(np.ones((2, 3, 2, 3)), 1.0, 2.0)
    with pytest.raises(InputError, match="reference_radius_px"):
        _core.VesselPart(np.ones((2, 3, 2, 2)), 0.0, 2.0)


def test_a_sweep_corrected_in_parts_with_a_lumen_track_equals_one_call() -> None:
    """The live service corrects a scan batch after batch: with a LumenTrack each part's search goes on from the
    last lumen found (and the frames missed since), so the parts give the frames, lumens and placements of one
    call, also across frames where the lumen is not seen."""
    rng = np.random.default_rng(11)
    rows, cols, n_frames = 64, 80, 24
    model = random_anchored_model(rng, rows, cols)
    centres = np.column_stack([np.linspace(30, 50, n_frames), np.linspace(30, 36, n_frames)])
    frames = vessel_frames(rng, centres, 8.0, rows, cols)
    frames[9:12] = np.clip(rng.gamma(2.0, 60.0, (3, rows, cols)), 0, 255).astype(np.uint8)  # lumen unseen
    forces = rng.uniform(2.0, 8.0, n_frames)
    profiles = np.tile([0.05, 1.2, 0.0], (n_frames, 1))
    whole, whole_valid, whole_lumens = correct_vessel_anchored(frames, forces, profiles, model)
    assert any(lumen is None for lumen in whole_lumens) and whole_lumens[-1] is not None
    track = LumenTrack()
    parts = [
        correct_vessel_anchored(frames[a:b], forces[a:b], profiles[a:b], model, track=track)
        for a, b in ((0, 5), (5, 10), (10, 11), (11, 24))
    ]
    assert np.array_equal(np.concatenate([part[0] for part in parts]), whole)
    assert np.array_equal(np.concatenate([part[1] for part in parts]), whole_valid)
    assert [lumen for part in parts for lumen in part[2]] == whole_lumens
    assert track.last_found == whole_lumens[-1] and track.frames_missed == 0
    with pytest.raises(InputError, match="track: the lumens are given"):
        correct_vessel_anchored(frames, forces, profiles, model, anchors=whole_lumens, track=LumenTrack())
