"""The vessel wall as an observation: the lumen boundary tracked on frames with a known deformation,
wall constraints in the regression on the compliant-vessel phantom, and the smoothness search."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from usdeform import regression
from usdeform.errors import InputError
from usdeform.experiments.paper_2d import Paper2dConfig, _evaluate, _palpate
from usdeform.metrics import area_mm2, pixel_size_mm
from usdeform.optical_flow import TrackedDisplacements
from usdeform.regression import BSplineDisplacementModel, Normalization, Observations, fit_regression
from usdeform.sim import compliant_vessel_phantom
from usdeform.stiffness import StiffnessProfile
from usdeform.vessel_wall import track_vessel_wall

ROWS, COLS = 128, 144
CENTRE = np.array([70.0, 60.0])  # x, y of the lumen's centre, pixels
RADIUS_PX = 16.0


def squash(points: np.ndarray, step: int) -> np.ndarray:
    """Where the affine deformation of frame ``step`` (0 = reference) takes ``points`` (K, 2):
    the lumen is pressed by 6 % per step axially, widened by 3 % per step laterally about its centre,
    and shifted by (1.5, 2.5) pixels per step."""
    scale = np.array([1.0 + 0.03 * step, 1.0 - 0.06 * step])
    return CENTRE + (points - CENTRE) * scale + step * np.array([1.5, 2.5])


def speckle_frames(n: int, seed: int = 0) -> np.ndarray:
    """(n, ROWS, COLS) uint8 frames: one speckle field deformed like the lumen, and an anechoic,
    elliptical lumen (the circle of RADIUS_PX at CENTRE in frame 0, then squashed)."""
    rng = np.random.default_rng(seed)
    speckle = cv2.GaussianBlur(rng.rayleigh(1.0, (ROWS, COLS)).astype(np.float32), (0, 0), 1.0)
    y, x = np.mgrid[0:ROWS, 0:COLS].astype(np.float64)
    frames = []
    for step in range(n):
        # Backward map: the reference point each pixel came from (the deformation is affine).
        scale = np.array([1.0 + 0.03 * step, 1.0 - 0.06 * step])
        source = CENTRE + (np.stack([x, y], axis=-1) - CENTRE - step * np.array([1.5, 2.5])) / scale
        tissue = cv2.remap(
            speckle, source[..., 0].astype(np.float32), source[..., 1].astype(np.float32), cv2.INTER_LINEAR
        )
        inside = np.linalg.norm(source - CENTRE, axis=-1) < RADIUS_PX
        frames.append(np.where(inside, 0.03, tissue) * 90.0)
    return np.clip(np.stack(frames), 0, 255).astype(np.uint8)


def on_ellipse(points: np.ndarray, step: int) -> np.ndarray:
    """Distance (pixels, approximately) of ``points`` from the lumen boundary of frame ``step``."""
    scale = np.array([1.0 + 0.03 * step, 1.0 - 0.06 * step])
    reference = CENTRE + (points - CENTRE - step * np.array([1.5, 2.5])) / scale
    return np.abs(np.linalg.norm(reference - CENTRE, axis=1) - RADIUS_PX) * scale.min()


def test_wall_points_land_on_the_deformed_lumen_boundary_without_tracks() -> None:
    frames = speckle_frames(5)
    wall = track_vessel_wall(frames, np.arange(5.0))
    assert wall.reference_index == 0 and wall.frame_indices.tolist() == [1, 2, 3, 4]
    # The reference points lie on the segmented lumen's edge, near the true boundary (the circle) ...
    offset = on_ellipse(wall.points_px, 0)
    assert np.median(offset) < 1.5
    assert len(wall.points_px) >= 2 * np.pi * RADIUS_PX / 2.0 * 0.9  # every 2 px along the wall
    # ... and each measured point moves to the same place relative to the deformed boundary: without
    # tracks the motion across the wall is measured (along it, the lumen's centroid shift predicts).
    for step in range(1, 5):
        measured = wall.valid[step - 1]
        assert measured.mean() >= 0.9
        moved = wall.points_px[measured] + wall.displacements_px[step - 1, measured]
        error = np.abs(on_ellipse(moved, step) - offset[measured])
        assert np.median(error) < 0.5 and np.percentile(error, 95) < 1.5


def test_wall_displacements_match_the_known_deformation_with_tracks() -> None:
    """With tissue tracks that say how the tissue moved, the whole wall displacement is recovered."""
    frames = speckle_frames(5)
    y, x = np.mgrid[4:ROWS:8, 4:COLS:8]
    points = np.column_stack([x.ravel(), y.ravel()]).astype(np.float64)
    outside = np.linalg.norm(points - CENTRE, axis=1) > RADIUS_PX + 3  # the lumen has no speckle: no tracks
    points = points[outside]
    displacements = np.stack([squash(points, step) - points for step in range(1, 5)])
    tracked = TrackedDisplacements(
        points, displacements, np.ones(displacements.shape[:2], dtype=bool), np.arange(1, 5), 0, (ROWS, COLS)
    )
    wall = track_vessel_wall(frames, np.arange(5.0), tracked=tracked)
    for step in range(1, 5):
        measured = wall.valid[step - 1]
        assert measured.mean() >= 0.9
        truth = squash(wall.points_px[measured], step) - wall.points_px[measured]
        error = np.linalg.norm(wall.displacements_px[step - 1, measured] - truth, axis=1)
        assert np.median(error) < 0.4 and np.percentile(error, 95) < 1.2


def test_a_frame_without_the_lumen_gives_no_wall_observation() -> None:
    """A collapsed (or lost) lumen leaves that frame's wall unmeasured; the other frames keep theirs."""
    frames = speckle_frames(5)
    frames[3] = speckle_frames(1, seed=9)[0]
    frames[3][np.linalg.norm(np.stack(np.mgrid[0:ROWS, 0:COLS][::-1], axis=-1) - CENTRE, axis=-1) < 40] = 110
    wall = track_vessel_wall(frames, np.arange(5.0))
    assert not wall.valid[2].any() and np.isnan(wall.displacements_px[2]).all()
    assert all(wall.valid[step].mean() >= 0.9 for step in (0, 1, 3))


def test_wall_tracking_rejects_bad_input() -> None:
    frames = speckle_frames(3)
    with pytest.raises(InputError, match=r"^frames\[0\] \(the lowest-force frame\)"):
        track_vessel_wall(np.full_like(frames, 120), np.arange(3.0))
    with pytest.raises(InputError, match=r"^spacing_px"):
        track_vessel_wall(frames, np.arange(3.0), spacing_px=0.0)
    tracked = TrackedDisplacements(
        np.zeros((1, 2)), np.zeros((1, 1, 2)), np.ones((1, 1), dtype=bool), np.array([1]), 0, (ROWS, COLS)
    )
    with pytest.raises(InputError, match=r"^tracked"):
        track_vessel_wall(frames, np.arange(3.0), tracked=tracked)


def test_wall_constraints_undo_more_of_the_compliant_vessels_collapse() -> None:
    """On the compliant-vessel phantom (about a third of the lumen area lost at 17 N) the B-spline fit
    with the wall as observations leaves a smaller area error at the highest force than without."""
    config = Paper2dConfig(n_frames=30)
    phantom = compliant_vessel_phantom()
    palpations = [_palpate(phantom, 10.0, 17.0, seed, config) for seed in (0, 1)]
    assert all(p.sampled.wall is not None for p in palpations)
    tracks = [p.sampled.observations for p in palpations]
    walls = [p.sampled.wall for p in palpations]
    models = {
        "tracks": fit_regression(tracks, basis=("bspline", 8, 8)).model,
        "tracks + wall": fit_regression(tracks, basis=("bspline", 8, 8), wall_observations=walls).model,
    }
    case, _, masks = _evaluate("fitted", "compliant", 10.0, 17.0, palpations[1], models)
    reference_area = area_mm2(masks["reference"], pixel_size_mm(palpations[1].recording.image_to_probe))
    relative = {name: abs(error) / reference_area for name, error in case.area_error_mm2.items()}
    assert relative["deformed"] > 0.25  # the phantom shows the collapse
    assert relative["tracks + wall"] < 0.5 * relative["tracks"]
    assert case.dice["tracks + wall"] > case.dice["tracks"]


def noisy_smooth_observations(rng: np.random.Generator) -> Observations:
    """Tracks of a smooth (quadratic-like) B-spline field with 1 px noise on a 64 x 56 frame."""
    rows, cols = 64, 56
    coefficients = np.zeros((2, 3, 10, 10))
    grid_y, grid_x = np.mgrid[0:10, 0:10] / 9.0
    coefficients[:, 0] = [4 * grid_x * grid_y, 3 * grid_y**2]
    model = BSplineDisplacementModel(coefficients, Normalization.for_frames(rows, cols, 20, 9, 4, 9))
    profile = StiffnessProfile(0.06, 1.3, 0.0)
    y, x = np.mgrid[2:rows:4, 2:cols:4]
    points = np.column_stack([x.ravel(), y.ravel()]).astype(np.float64)
    forces = np.linspace(1.0, 18.0, 12)
    fields = [model.displacement(f, profile, (rows, cols))[:, y.ravel(), x.ravel()].T for f in (0.3, *forces)]
    displacements = np.stack([f - fields[0] for f in fields[1:]]) + rng.normal(0, 1.0, (12, len(points), 2))
    return Observations(
        points, displacements, np.ones((12, len(points)), dtype=bool), forces, 0.3, profile, (rows, cols)
    )


def test_smoothness_search_widens_until_its_optimum_is_inside(monkeypatch) -> None:
    observations = [noisy_smooth_observations(np.random.default_rng(4))]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "end of the searched range" warning
        chosen = fit_regression(observations, basis=("bspline", 10, 10))
        # A grid far below the optimum: the search widens upwards and finds the same weight.
        monkeypatch.setattr(regression, "SMOOTHNESS_GRID", (1e-10, 1e-9, 1e-8))
        widened = fit_regression(observations, basis=("bspline", 10, 10))
    assert chosen.smoothness > 1e-6
    assert widened.smoothness == pytest.approx(chosen.smoothness)


def test_smoothness_search_optimum_is_inside_the_weights_it_tried() -> None:
    observations = [noisy_smooth_observations(np.random.default_rng(5))]
    fit = fit_regression(observations, basis=("bspline", 10, 10), smoothness=1.0)
    assert isinstance(fit.model, BSplineDisplacementModel)
    palpations = regression._samples(
        observations,
        normalization=fit.model.normalization,
        n_intervals=64,
        coupling="stiffness",
        integration="force",
        spatial_vector=regression._spatial_basis(("bspline", 10, 10))[0],
        n_terms=300,
    )
    samples = regression._Samples.weighted(palpations, [], 0.0)
    best, errors = regression._cross_validated_smoothness(samples, regression._roughness((10, 10)), 5)
    optimum = min(errors, key=errors.__getitem__)
    assert best == 10.0**optimum
    assert min(errors) < optimum < max(errors)


def test_fit_command_fits_the_wall_where_asked(tmp_path, capsys) -> None:
    """``usdeform fit --wall require`` fits each palpation's wall (recorded in the model file's
    provenance); ``--wall off`` fits the tracks alone."""
    from usdeform.cli import main
    from usdeform.io import load_model, write_sequence
    from usdeform.sim import coarse_phantom, simulate_palpation

    paths = []
    for s_mm, seed in ((15.0, 11), (45.0, 12)):
        palpation, _ = simulate_palpation(coarse_phantom(), s_mm, 8.0, n_frames=8, seed=seed, rows=96, cols=96)
        paths.append(str(tmp_path / f"palpation-{s_mm:.0f}.mha"))
        write_sequence(paths[-1], palpation)
    fitted = {}
    for wall in ("require", "off"):
        model = tmp_path / f"model-{wall}.json"
        command = ["fit", *paths, "--output", str(model), "--flexible-layer-mm", "50", "--basis", "bspline:6x6"]
        assert main([*command, "--wall", wall, "--wall-weight", "2"]) == 0
        printed = capsys.readouterr().out
        provenance = load_model(model).provenance
        assert (provenance["wall"], provenance["wall_weight"]) == (wall, 2.0)
        fitted[wall] = provenance
        if wall == "require":
            assert printed.count("wall points") == 2, printed
    assert fitted["require"]["wall_palpations"] == 2 and fitted["off"]["wall_palpations"] == 0
    assert fitted["require"]["n_samples"] > fitted["off"]["n_samples"]
    with pytest.raises(SystemExit):
        main(["fit", *paths, "--output", str(tmp_path / "m.json"), "--flexible-layer-mm", "50", "--wall", "maybe"])
