"""A vessel part that folds the zero-force map is attenuated until it no longer folds (correction._folds)."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from kernel_inputs import random_anchored_model, vessel_frames
from usdeform import _core
from usdeform.correction._folds import FoldedVesselWarning, fold_determinant, vessel_part_scales
from usdeform.correction._vessel import correct_vessel_anchored
from usdeform.regression import StiffnessProfile, VesselAnchoredModel, profiles_array

ROWS, COLS, N_FRAMES = 64, 96, 3
PROFILE = StiffnessProfile(0.0, 2.0, 0.0)


def test_fold_determinant_is_one_for_a_shift_and_negative_where_the_map_folds():
    shift = np.stack([np.full((ROWS, COLS), 2.5), np.full((ROWS, COLS), -1.0)])
    assert np.allclose(fold_determinant(shift), 1.0)
    y = np.mgrid[:ROWS, :COLS][0].astype(float)
    squeeze = np.stack([np.zeros((ROWS, COLS)), -0.5 * (y - ROWS / 2)])  # halves the axial distances
    assert np.allclose(fold_determinant(squeeze), 0.5)
    reverse = np.stack([np.zeros((ROWS, COLS)), -2.5 * (y - ROWS / 2)])  # p -> p + D(p) turns the column over
    assert (fold_determinant(reverse) < 0).all()


def _model_and_sweep(vessel_scale: float) -> tuple[VesselAnchoredModel, np.ndarray, np.ndarray, list[np.ndarray]]:
    model = random_anchored_model(np.random.default_rng(5), ROWS, COLS, image_scale=0.05)
    model = dataclasses.replace(model, vessel_coefficients=model.vessel_coefficients * vessel_scale)
    lumen = model.reference
    placements = [np.array([[*lumen.centre_px, lumen.radius_px]] * N_FRAMES)]
    forces = np.linspace(0.4, 0.9, N_FRAMES) * model.normalization.force_scale
    return model, forces, profiles_array(PROFILE, N_FRAMES), placements


def test_a_vessel_part_that_does_not_fold_the_map_is_left_whole():
    model, forces, profiles, placements = _model_and_sweep(0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scales = vessel_part_scales(forces, profiles, model, placements)
    assert (scales == 1.0).all()


def test_a_vessel_part_that_folds_the_map_is_attenuated_until_it_does_not_with_a_warning():
    model, forces, profiles, placements = _model_and_sweep(40.0)
    whole = model.displacement(float(forces[-1]), PROFILE, model.frame_shape)
    assert fold_determinant(whole).min() < 0  # the part as fitted folds the map
    with pytest.warns(FoldedVesselWarning, match=f"in {N_FRAMES} of {N_FRAMES} frames"):
        scales = vessel_part_scales(forces, profiles, model, placements)
    assert scales.shape == (1, N_FRAMES) and (scales < 1.0).all()
    image = model.image_model.displacement(float(forces[-1]), PROFILE, model.frame_shape)
    vessel = model.vessel_displacement(float(forces[-1]), PROFILE, model.frame_shape, model.reference)
    unfolded = fold_determinant(image) > 0
    assert (fold_determinant(image + scales[0, -1] * vessel)[unfolded] > 0).all()


def test_the_sweep_is_warped_with_the_attenuated_part():
    model, forces, profiles, placements = _model_and_sweep(40.0)
    centres = np.repeat([model.reference.centre_px], N_FRAMES, axis=0)
    frames = vessel_frames(np.random.default_rng(6), centres, model.reference.radius_px, ROWS, COLS)
    with pytest.warns(FoldedVesselWarning):
        corrected, _, _ = correct_vessel_anchored(frames, forces, profiles, model, anchors=[model.reference] * N_FRAMES)
        scales = vessel_part_scales(forces, profiles, model, placements)
    fields = np.stack(
        [
            model.image_model.displacement(float(force), PROFILE, model.frame_shape)
            + scale * model.vessel_displacement(float(force), PROFILE, model.frame_shape, model.reference)
            for force, scale in zip(forces, scales[0], strict=True)
        ]
    )
    expected, _ = _core.warp_by_field(frames, fields, fill=0.0, threads=1)
    assert np.abs(corrected.astype(int) - expected.astype(int)).max() <= 1


def test_a_dark_layer_is_not_taken_for_a_lumen_in_a_palpation():
    from usdeform.fitting._sampling import MAX_LUMEN_ELONGATION, _open_lumens
    from usdeform.metrics import lumen_seeds

    rows, cols = 128, 160
    frame = vessel_frames(np.random.default_rng(7), np.array([[80.0, 80.0]]), 9.0, rows, cols)[0]
    frame[20:30, 35:125] = frame[20:30, 35:125] // 12  # a hypoechoic band (fat under the skin), 90 x 10 px
    assert 90 / 10 > MAX_LUMEN_ELONGATION
    seeds = lumen_seeds(frame)
    assert len(seeds) == 2 and seeds[0][1] < 40  # the band is the largest dark region
    kept = _open_lumens(frame)
    assert len(kept) == 1 and np.hypot(kept[0][0] - 80.0, kept[0][1] - 80.0) < 2.0
