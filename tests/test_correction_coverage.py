"""A sweep whose lumens leave the palpated depths or radii is corrected with a warning naming the frames."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

from kernel_inputs import random_anchored_model, vessel_frames
from usdeform.correction import LumenCoverageWarning, SampledProfiles, correct_recording, uncovered_lumens
from usdeform.io import load_model, save_model
from usdeform.recording import Recording
from usdeform.regression import StiffnessProfile, VesselAnchor

ROWS, COLS, N_FRAMES = 64, 64, 8
PROFILE = StiffnessProfile(0.0, 2.0, 0.0)
DEPTHS_PX = np.linspace(26.0, 46.0, N_FRAMES)  # the lumen deepens along the sweep


def _sweep() -> tuple[Recording, object]:
    rng = np.random.default_rng(11)
    model = random_anchored_model(rng, ROWS, COLS, image_scale=0.02)
    model = dataclasses.replace(model, vessel_coefficients=model.vessel_coefficients * 0.05)
    centres = np.column_stack([np.full(N_FRAMES, COLS / 2), DEPTHS_PX])
    poses = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    poses[:, 1, 3] = np.linspace(0.0, 20.0, N_FRAMES)
    recording = Recording(
        frames=vessel_frames(rng, centres, 7.0, ROWS, COLS),
        timestamps=np.arange(N_FRAMES, dtype=float),
        probe_to_base=poses,
        pose_valid=np.ones(N_FRAMES, dtype=bool),
        image_to_probe=np.diag([0.2, 0.2, 1.0, 1.0]),
        force=np.full(N_FRAMES, 0.5 * model.normalization.force_scale),
    )
    return recording, model


def _sampled(*depths_px: float) -> SampledProfiles:
    positions = np.array([[0.0, 20.0 * i / max(len(depths_px) - 1, 1), 0.0] for i in range(len(depths_px))])
    # the radii the search finds on these frames (the blurred edge makes them about 8 pixels, not 7)
    lumens = tuple((VesselAnchor((COLS / 2, depth), 8.0 + 0.5 * (i % 2)),) for i, depth in enumerate(depths_px))
    return SampledProfiles(positions, (PROFILE,) * len(depths_px), lumens)


def test_frames_whose_lumen_lies_deeper_than_every_palpation_are_named() -> None:
    recording, model = _sweep()
    with pytest.warns(LumenCoverageWarning, match=r"the vessel: in \d of 8 frames \(first: frame \d\)") as caught:
        correct_recording(recording, model, _sampled(26.0, 32.0))
    message = str(caught[0].message)
    assert "beyond the palpated 5.2-6.4 mm" in message  # rows 26-32 at 0.2 mm
    first = int(message.split("first: frame ")[1].split(")")[0])
    assert DEPTHS_PX[first] > 32.0 + 0.25 * 8.25 - 1.0  # the first frame named lies beyond the margin


def test_a_sweep_within_the_palpated_lumens_corrects_without_a_warning() -> None:
    recording, model = _sweep()
    with warnings.catch_warnings():
        warnings.simplefilter("error", LumenCoverageWarning)
        covered = correct_recording(recording, model, _sampled(26.0, 46.0))
    unrecorded = correct_recording(recording, model, dataclasses.replace(_sampled(26.0, 46.0), lumens=None))
    assert np.array_equal(covered.frames, unrecorded.frames)  # the check changes nothing it corrects


def test_radii_beyond_the_palpated_ones_are_named_and_unseen_vessels_skipped() -> None:
    palpated = [(VesselAnchor((30.0, 30.0), 10.0), None), (VesselAnchor((30.0, 30.0), 12.0), None)]
    found = [
        [VesselAnchor((30.0, 30.0), 11.0), VesselAnchor((30.0, 30.0), 14.0), VesselAnchor((30.0, 30.0), 8.5)],
        [VesselAnchor((60.0, 30.0), 5.0)] * 3,  # a further vessel no palpation showed: nothing to compare
    ]
    (uncovered,) = uncovered_lumens(found, palpated, (0.1, 0.2))
    assert uncovered.vessel == 0 and uncovered.frames == (1, 2)
    assert uncovered.radius_mm == pytest.approx((8.5 * np.sqrt(0.02), 14.0 * np.sqrt(0.02)))
    assert uncovered.palpated_depth_mm == pytest.approx((6.0, 6.0))


def test_the_model_file_keeps_the_palpated_lumens(tmp_path: Path) -> None:
    _, model = _sweep()
    sampled = SampledProfiles(
        np.zeros((2, 3)), (PROFILE, PROFILE), ((VesselAnchor((3.5, 20.25), 4.0), None), (None, None))
    )
    save_model(tmp_path / "m.json", model, sampled)
    assert load_model(tmp_path / "m.json").sampled.lumens == sampled.lumens
    save_model(tmp_path / "n.json", model, dataclasses.replace(sampled, lumens=None))
    assert load_model(tmp_path / "n.json").sampled.lumens is None


def test_a_further_vessel_is_not_placed_on_the_main_vessels_lumen() -> None:
    from test_vessel_further import two_vessel_model
    from usdeform.correction import further_lumens, sweep_lumens
    from usdeform.regression import profiles_array

    rng = np.random.default_rng(7)
    model = two_vessel_model(rng, 64, 96, 2.0)
    # Only the main lumen: the further vessel's search, from where it was palpated, finds the main one.
    frames = vessel_frames(rng, np.column_stack([np.full(6, 32.0), np.full(6, 32.0)]), 6.0, 64, 96)
    forces = np.full(6, 0.5 * model.normalization.force_scale)
    profiles = profiles_array(PROFILE, 6)
    main = sweep_lumens(frames, forces, profiles, model)
    alone = sweep_lumens(frames, forces, profiles, model.vessel_models[1])
    assert all(lumen is not None and abs(lumen.centre_px[0] - 32.0) < 3 for lumen in main + alone)
    assert further_lumens(frames, forces, profiles, model) == [[None] * 6]
    assert further_lumens(frames, forces, profiles, model, main) == [[None] * 6]
