"""The vessel wall as an observation: the lumen boundary tracked on frames with a known deformation,
wall constraints in the regression on the compliant-vessel phantom, and the smoothness search."""

from __future__ import annotations

import dataclasses
import functools
import warnings

import cv2
import numpy as np
import pytest

from usdeform import regression
from usdeform.correction import frame_vessel_anchor
from usdeform.correction._vessel import correct_vessel_anchored
from usdeform.errors import FitError, InputError
from usdeform.experiments.paper_2d import Paper2dConfig, evaluate, palpate
from usdeform.fitting import track_vessel_wall
from usdeform.metrics import area_mm2, pixel_size_mm
from usdeform.optical_flow import TrackedDisplacements
from usdeform.reference import warp_frame
from usdeform.reference.lumens import find_lumen, search_window, zero_force_lumen
from usdeform.regression import (
    BSplineDisplacementModel,
    Normalization,
    Observations,
    StiffnessProfile,
    VesselAnchor,
    VesselAnchoredModel,
    _basis,
    _fit,
    _observations,
    _smoothness,
    fit_regression,
)
from usdeform.sim import compliant_vessel_phantom

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


def test_the_wall_points_predicted_motion_is_the_fit_to_their_nearest_tracks() -> None:
    # The prediction's nearest tracks are found with a k-d tree: the same tracks, at the same distances, as
    # sorting every track's distance from every wall point.
    from usdeform.fitting import _vessel_wall

    rng = np.random.default_rng(4)
    grid = np.stack(np.meshgrid(np.arange(8.0, 120.0, 8.0), np.arange(8.0, 136.0, 8.0)), axis=-1).reshape(-1, 2)
    displacements = rng.normal(0.0, 2.0, (3, len(grid), 2))
    valid = rng.random((3, len(grid))) > 0.3
    tracked = TrackedDisplacements(grid, displacements, valid, np.arange(1, 4), 0, (ROWS, COLS))
    wall_points = rng.uniform(10.0, 110.0, (40, 2))
    for step in range(3):
        points, moved = grid[valid[step]], displacements[step, valid[step]]
        distances = np.linalg.norm(wall_points[:, None] - points[None], axis=2)
        nearest = np.argsort(distances, axis=1, kind="stable")[:, : _vessel_wall._NEAREST_TRACKS]
        weights = 1.0 / np.maximum(np.take_along_axis(distances, nearest, axis=1), 1.0) ** 2
        expected = []
        for k, wall_point in enumerate(wall_points):
            offsets = points[nearest[k]] - wall_point
            terms = np.column_stack([np.ones(len(offsets)), offsets])
            normal = (terms * weights[k, :, None]).T @ terms
            ridge = _vessel_wall._GRADIENT_RIDGE * np.sum(weights[k] * np.sum(offsets**2, axis=1)) / 2
            normal[1, 1] += ridge
            normal[2, 2] += ridge
            expected.append(np.linalg.solve(normal, (terms * weights[k, :, None]).T @ moved[nearest[k]])[0])
        predicted = _vessel_wall._predicted_displacements(tracked, step, wall_points)
        np.testing.assert_allclose(predicted, expected, rtol=1e-9, atol=1e-9)
    valid[1, 11:] = False
    few = TrackedDisplacements(grid, displacements, valid, np.arange(1, 4), 0, (ROWS, COLS))
    assert _vessel_wall._predicted_displacements(few, 1, wall_points) is None  # fewer tracks than it fits


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
    palpations = [palpate(phantom, 10.0, 17.0, seed, config) for seed in (0, 1)]
    assert all(p.sampled.wall is not None for p in palpations)
    tracks = [p.sampled.observations for p in palpations]
    walls = [p.sampled.wall for p in palpations]
    models = {
        "tracks": fit_regression(tracks, basis=("bspline", 8, 8)).model,
        "tracks + wall": fit_regression(tracks, basis=("bspline", 8, 8), wall_observations=walls).model,
    }
    case, _, masks = evaluate("fitted", "compliant", 10.0, 17.0, palpations[1], models)
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
        monkeypatch.setattr(_smoothness, "SMOOTHNESS_GRID", (1e-10, 1e-9, 1e-8))
        widened = fit_regression(observations, basis=("bspline", 10, 10))
    assert chosen.smoothness > 1e-6
    assert widened.smoothness == pytest.approx(chosen.smoothness)


def test_smoothness_search_optimum_is_inside_the_weights_it_tried() -> None:
    observations = [noisy_smooth_observations(np.random.default_rng(5))]
    fit = fit_regression(observations, basis=("bspline", 10, 10), smoothness=1.0)
    assert isinstance(fit.model, BSplineDisplacementModel)
    palpations = _observations._samples(
        observations,
        normalization=fit.model.normalization,
        coupling="stiffness",
        integration="force",
        spatial_vector=_fit._spatial_basis(("bspline", 10, 10))[0],
        n_terms=300,
    )
    samples = _observations._Samples.weighted(palpations, [], 0.0)
    best, errors = _smoothness._cross_validated_smoothness(samples, _basis._roughness((10, 10)), 5)
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


# --- The vessel-anchored model: a collapse that follows the lumen --------------------------------

FRAME = (96, 112)  # rows, cols
FORCES = np.linspace(1.0, 10.0, 8)
PROFILE = StiffnessProfile(0.0, 2.0, 0.0)


def collapse_field(x: np.ndarray, y: np.ndarray, lumen: VesselAnchor, force_n: float) -> np.ndarray:
    """A known field (2, *x.shape), pixels: a smooth compression tied to the image (axial strain
    growing with depth, a slight lateral spread) plus an oval collapse of the lumen that scales with
    its radius (the roof moves down, the floor up, the sides out), decaying over about a radius."""
    q_x, q_y = (x - lumen.centre_px[0]) / lumen.radius_px, (y - lumen.centre_px[1]) / lumen.radius_px
    decay = np.exp(-0.5 * (q_x**2 + q_y**2))
    fraction = force_n / 10.0
    lateral = 0.02 * (x - FRAME[1] / 2) + 0.2 * lumen.radius_px * q_x * decay
    axial = -0.04 * y - 0.6 * lumen.radius_px * q_y * decay
    return fraction * np.stack([lateral, axial])


def collapse_observations(lumen: VesselAnchor) -> tuple[Observations, Observations]:
    """Tracks on a grid outside the lumen and wall points on its boundary, from :func:`collapse_field`."""
    rows, cols = FRAME
    y, x = np.mgrid[2:rows:4, 2:cols:4].astype(np.float64)
    outside = np.hypot(x - lumen.centre_px[0], y - lumen.centre_px[1]) > lumen.radius_px + 2
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    ring = np.column_stack(
        [lumen.centre_px[0] + lumen.radius_px * np.cos(angles), lumen.centre_px[1] + lumen.radius_px * np.sin(angles)]
    )
    groups = []
    for points in (np.column_stack([x[outside], y[outside]]), ring):
        moved = np.stack([collapse_field(points[:, 0], points[:, 1], lumen, f).T for f in FORCES])
        valid = np.ones(moved.shape[:2], dtype=bool)
        groups.append(Observations(points, moved, valid, FORCES, 0.0, PROFILE, FRAME, lumen))
    return groups[0], groups[1]


FITTED_LUMEN = VesselAnchor((50.0, 40.0), 10.0)
MOVED_LUMEN = VesselAnchor((70.0, 58.0), 12.0)  # 20 px aside, 18 px deeper, a fifth larger


def error_near(model_field: np.ndarray, lumen: VesselAnchor) -> float:
    """RMS difference (pixels) between a model's field at the highest force and the known one, over
    the tissue within two radii of ``lumen``."""
    rows, cols = FRAME
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    distance = np.hypot(x - lumen.centre_px[0], y - lumen.centre_px[1])
    near = (distance >= lumen.radius_px) & (distance <= 2 * lumen.radius_px)
    truth = collapse_field(x, y, lumen, FORCES[-1])
    return float(np.sqrt(np.mean(np.sum((model_field - truth)[:, near] ** 2, axis=0))))


@pytest.fixture(scope="module")
def collapse_fits() -> dict[str, regression.RegressionFit]:
    tracks, wall = collapse_observations(FITTED_LUMEN)
    options = {"basis": ("bspline", 8, 8), "wall_observations": [wall]}
    return {anchor: fit_regression([tracks], anchor=anchor, **options) for anchor in ("image", "vessel")}


def test_the_vessel_anchored_collapse_moves_and_scales_with_the_lumen(collapse_fits) -> None:
    """Fitted where the lumen is at one place, the vessel-anchored model predicts the collapse of a
    lumen 27 px away and a fifth larger; the image-anchored one keeps it where it was fitted."""
    anchored, image = collapse_fits["vessel"].fitted, collapse_fits["image"].fitted
    assert isinstance(anchored, VesselAnchoredModel) and isinstance(image, BSplineDisplacementModel)
    assert anchored.reference == FITTED_LUMEN
    force = float(FORCES[-1])
    # At the fitted place both follow the field (the collapse moves the wall by up to 3.5 px; the
    # image grid's knots, 16 px apart, follow it less closely).
    assert error_near(anchored.displacement(force, PROFILE, FRAME), FITTED_LUMEN) < 0.3
    assert error_near(image.displacement(force, PROFILE, FRAME), FITTED_LUMEN) < 1.0
    # The paper's quadratic can carry the vessel part too (unpenalised under it).
    quadratic = fit_regression([collapse_observations(FITTED_LUMEN)[0]], anchor="vessel").fitted
    assert isinstance(quadratic, VesselAnchoredModel)
    assert isinstance(quadratic.image_model, regression.QuadraticDisplacementModel)
    # Where the lumen moved to, only the anchored model does.
    moved_anchored = error_near(anchored.displacement(force, PROFILE, FRAME, MOVED_LUMEN), MOVED_LUMEN)
    moved_image = error_near(image.displacement(force, PROFILE, FRAME), MOVED_LUMEN)
    # (Fitted at one place only, the data cannot tell the two parts apart where both reach, and the
    # image grid keeps some of the collapse: the anchored error is not zero.)
    assert moved_image > 1.5
    assert moved_anchored < 0.5 * moved_image and moved_anchored < 1.6
    # The vessel part vanishes outside its window (two radii around the lumen).
    vessel_part = anchored.vessel_displacement(force, PROFILE, FRAME, MOVED_LUMEN)
    y, x = np.mgrid[0 : FRAME[0], 0 : FRAME[1]]
    far = np.maximum(np.abs(x - 70.0), np.abs(y - 58.0)) > 2 * 12.0
    assert np.abs(vessel_part[:, far]).max() == 0.0 and np.abs(vessel_part).max() > 1.0


def lumen_frame(lumen: VesselAnchor, seed: int = 3) -> np.ndarray:
    """A zero-force uint8 frame: speckle with an anechoic disc at ``lumen``."""
    rng = np.random.default_rng(seed)
    speckle = cv2.GaussianBlur(rng.rayleigh(1.0, FRAME).astype(np.float32), (0, 0), 1.0) * 90.0
    y, x = np.mgrid[0 : FRAME[0], 0 : FRAME[1]]
    speckle[np.hypot(x - lumen.centre_px[0], y - lumen.centre_px[1]) < lumen.radius_px] = 3.0
    return np.clip(speckle, 0, 255).astype(np.uint8)


def pressed(frame: np.ndarray, lumen: VesselAnchor, force_n: float) -> np.ndarray:
    """``frame`` deformed by :func:`collapse_field`: the deformed pixel p shows the zero-force point q
    with ``q + D(q) = p`` (solved by fixed-point iteration)."""
    y, x = np.mgrid[0 : FRAME[0], 0 : FRAME[1]].astype(np.float64)
    source_x, source_y = x.copy(), y.copy()
    for _ in range(30):
        lateral, axial = collapse_field(source_x, source_y, lumen, force_n)
        source_x, source_y = x - lateral, y - axial
    return cv2.remap(frame, source_x.astype(np.float32), source_y.astype(np.float32), cv2.INTER_LINEAR)


def test_correction_finds_each_frames_own_lumen_and_restores_it(collapse_fits) -> None:
    """A frame whose lumen lies elsewhere than in the fitted palpation: correction finds its zero-force
    lumen (centre and radius within a pixel) and restores its area; the vessel part left at the fitted
    place does not."""
    from usdeform.correction import correct_frames
    from usdeform.metrics import dice, segment_vessel

    model = collapse_fits["vessel"].fitted
    assert isinstance(model, VesselAnchoredModel)
    zero_force = lumen_frame(MOVED_LUMEN)
    deformed = pressed(zero_force, MOVED_LUMEN, float(FORCES[-1]))
    truth = segment_vessel(zero_force).mask
    assert segment_vessel(deformed).mask.sum() < 0.75 * truth.sum()  # the lumen is pressed
    corrected, valid, anchors = correct_vessel_anchored(deformed[None], FORCES[-1], PROFILE, model)
    (found,) = anchors
    assert found is not None and valid.shape == corrected.shape
    segmented = VesselAnchor.of_mask(truth)  # the segmentation's edge lies a little outside the disc
    assert np.hypot(*np.subtract(found.centre_px, segmented.centre_px)) < 1.0
    assert abs(found.radius_px - segmented.radius_px) < 1.0
    restored = segment_vessel(corrected[0], found.centre_px).mask
    assert dice(restored, truth) > 0.92 and abs(restored.sum() / truth.sum() - 1) < 0.1
    # correct_frames dispatches to the same correction.
    assert np.array_equal(correct_frames(deformed, FORCES[-1], PROFILE, model), corrected[0])
    # The vessel part left at the fitted lumen corrects the moved one worse.
    field = model.displacement(float(FORCES[-1]), PROFILE, FRAME)
    y, x = np.mgrid[0 : FRAME[0], 0 : FRAME[1]].astype(np.float32)
    unmoved = cv2.remap(deformed, x + field[0].astype(np.float32), y + field[1].astype(np.float32), cv2.INTER_LINEAR)
    assert dice(segment_vessel(unmoved, found.centre_px).mask, truth) < dice(restored, truth) - 0.1


def test_vessel_anchoring_rejects_what_it_cannot_use(collapse_fits) -> None:
    tracks, _ = collapse_observations(FITTED_LUMEN)
    with pytest.raises(InputError, match=r"^solver: the B-spline basis and the vessel-anchored model"):
        fit_regression([tracks], anchor="vessel", solver="adam")
    with pytest.raises(InputError, match=r"^anchor: expected one of"):
        fit_regression([tracks], basis=("bspline", 8, 8), anchor="lumen")  # type: ignore[arg-type]
    without = dataclasses.replace(tracks, vessel=None)
    with pytest.raises(FitError, match=r"^observations: anchor='vessel' needs the lumen"):
        fit_regression([without], basis=("bspline", 8, 8), anchor="vessel")
    with pytest.raises(FitError, match=r"^model: this fit is vessel-anchored"):
        _ = collapse_fits["vessel"].model
    with pytest.raises(InputError, match=r"^radius_px"):
        VesselAnchor((1.0, 2.0), 0.0)
    with pytest.raises(InputError, match=r"^mask: the lumen mask is empty"):
        VesselAnchor.of_mask(np.zeros((4, 4), dtype=bool))
    model = collapse_fits["vessel"].fitted
    assert isinstance(model, VesselAnchoredModel)
    with pytest.raises(InputError, match=r"^vessel_coefficients: expected shape"):
        VesselAnchoredModel(model.image_model, np.zeros((2, 3, 4, 5)), FITTED_LUMEN)
    with pytest.raises(InputError, match=r"^frames: 20 x 20 pixels"):
        correct_vessel_anchored(np.zeros((20, 20), dtype=np.uint8), 5.0, PROFILE, model)
    frames = np.stack([lumen_frame(MOVED_LUMEN)] * 2)
    with pytest.raises(InputError, match=r"^anchors\[1\]: expected a VesselAnchor or None, got tuple"):
        correct_vessel_anchored(frames, 5.0, PROFILE, model, anchors=[None, (50.0, 40.0, 9.0)])
    negative = frames.astype(np.float32)
    negative[1, 3, 3] = -1.0
    with pytest.raises(InputError, match=r"^frames\[1\]: B-mode intensities must be finite and non-negative"):
        correct_vessel_anchored(negative, 5.0, PROFILE, model)
    with pytest.raises(InputError, match=r"^frame: expected a 96 x 112 frame of uint8 or float32, got float64"):
        frame_vessel_anchor(frames[0].astype(np.float64), 5.0, PROFILE, model)
    with pytest.raises(InputError, match=r"^force_n: .*outside the model's fitted range"):
        frame_vessel_anchor(frames[0], 1e6, PROFILE, model)
    absurd = dataclasses.replace(model, vessel_coefficients=np.full(model.vessel_coefficients.shape, 1e9))
    with pytest.raises(InputError, match=r"^model: vessel_coefficients: displacements up to"):
        correct_vessel_anchored(frames, 5.0, PROFILE, absurd)
    from usdeform.correction import correct_frames
    from usdeform.volume import Compounder, VoxelGrid

    with pytest.raises(InputError, match=r"^threads: expected"):
        correct_frames(frames, 5.0, PROFILE, model, threads="all")  # type: ignore[arg-type]
    compounder = Compounder(VoxelGrid.from_bounds(np.zeros(3), np.full(3, 10.0), 1.0))
    with pytest.raises(InputError, match=r"^model: expected a DisplacementModel or VesselAnchoredModel"):
        compounder.add_corrected_frames(frames, np.stack([np.eye(4)] * 2), 5.0, PROFILE, object())  # type: ignore[arg-type]


def test_a_vessel_anchored_model_round_trips_through_a_model_file(collapse_fits, tmp_path) -> None:
    import json

    from usdeform.errors import FileFormatError
    from usdeform.io import load_model, save_model

    model = collapse_fits["vessel"].fitted
    assert isinstance(model, VesselAnchoredModel)
    path = tmp_path / "anchored.json"
    save_model(path, model, provenance={"anchor": "vessel"})
    loaded = load_model(path).model
    assert isinstance(loaded, VesselAnchoredModel)
    assert np.array_equal(loaded.vessel_coefficients, model.vessel_coefficients)
    assert np.array_equal(loaded.image_model.coefficients, model.image_model.coefficients)
    assert (loaded.reference, loaded.window_radii) == (model.reference, model.window_radii)
    force = float(FORCES[-1])
    assert np.array_equal(
        loaded.displacement(force, PROFILE, FRAME, MOVED_LUMEN), model.displacement(force, PROFILE, FRAME, MOVED_LUMEN)
    )
    document = json.loads(path.read_text())
    document["vessel"]["coefficients"] = [[[[0.0] * 3] * 2] * 3] * 2  # rows of 3, not 2 x 2
    path.write_text(json.dumps(document))
    with pytest.raises(FileFormatError, match=r"vessel\.coefficients"):
        load_model(path)
    document["vessel"] = {"coefficients": model.vessel_coefficients.tolist(), "reference": {}, "window_radii": 2.0}
    path.write_text(json.dumps(document))
    with pytest.raises(FileFormatError, match=r"vessel\.reference\.centre_px: missing field"):
        load_model(path)


def test_fit_and_correct_with_a_vessel_anchored_model(tmp_path, capsys) -> None:
    """``usdeform fit --anchor vessel`` writes a vessel-anchored model; a sweep is corrected with it
    (its lumen found frame by frame), and the fused volume equals compounding the corrected sweep."""
    from usdeform.cli import main
    from usdeform.correction import correct_recording
    from usdeform.correction._sweep import correct_and_compound
    from usdeform.io import load_model, write_sequence
    from usdeform.sim import coarse_phantom, simulate_palpation
    from usdeform.volume import compound_recording

    paths, recordings = [], []
    for s_mm, seed in ((15.0, 11), (45.0, 12)):
        palpation, _ = simulate_palpation(coarse_phantom(), s_mm, 8.0, n_frames=8, seed=seed, rows=96, cols=96)
        paths.append(str(tmp_path / f"palpation-{s_mm:.0f}.mha"))
        write_sequence(paths[-1], palpation)
        recordings.append(palpation)
    output = tmp_path / "model.json"
    command = ["fit", *paths, "--output", str(output), "--flexible-layer-mm", "50", "--basis", "bspline:6x6"]
    assert main([*command, "--wall", "require", "--anchor", "vessel"]) == 0
    capsys.readouterr()
    model_file = load_model(output)
    assert isinstance(model_file.model, VesselAnchoredModel) and model_file.provenance["anchor"] == "vessel"
    assert model_file.sampled is not None
    sweep = recordings[1]
    corrected = correct_recording(sweep, model_file.model, model_file.sampled)
    assert corrected.frames.shape == sweep.frames.shape and corrected.pixel_valid is not None
    assert corrected.pixel_valid.mean() > 0.8 and not np.array_equal(corrected.frames, sweep.frames)
    fused = correct_and_compound(sweep, model_file.model, model_file.sampled, spacing_mm=1.0)
    two_step, _ = compound_recording(corrected, spacing_mm=1.0)
    assert np.array_equal(fused.image, two_step.image)
    # Without the wall no lumen is measured: nothing to anchor on, the model is fitted in image coordinates.
    assert main([*command, "--wall", "off", "--anchor", "vessel"]) == 0
    off = load_model(output)
    assert isinstance(off.model, BSplineDisplacementModel) and off.provenance["anchor"] == "image"


def test_a_frame_without_a_lumen_keeps_the_vessel_part_where_the_sweep_last_saw_it(collapse_fits) -> None:
    """In a sweep, a frame whose lumen is not found (pressed shut, a shadow) is corrected with the
    vessel part on the previous frame's lumen, not on the fitted one."""
    model = collapse_fits["vessel"].fitted
    assert isinstance(model, VesselAnchoredModel)
    force = float(FORCES[-1])
    deformed = pressed(lumen_frame(MOVED_LUMEN), MOVED_LUMEN, force)
    shut = pressed(lumen_frame(MOVED_LUMEN, seed=4), MOVED_LUMEN, force)
    shut[shut < 40] = 120  # no anechoic region left
    shadowed = shut.copy()
    shadowed[70:90, 4:24] = 3  # a dark region far from the lumen: not taken for it
    corrected, _, anchors = correct_vessel_anchored(np.stack([deformed, shut, shadowed]), force, PROFILE, model)
    assert anchors[0] is not None and anchors[1:] == [None, None]
    for index, frame in ((1, shut), (2, shadowed)):
        expected, _ = warp_frame(frame, model.displacement(force, PROFILE, FRAME, anchors[0]), 0.0)
        assert np.array_equal(corrected[index], expected)
    at_reference, _ = warp_frame(shut, model.displacement(force, PROFILE, FRAME), 0.0)
    assert not np.array_equal(corrected[1], at_reference)
    # Searched alone (no lumen seen before it), the shadow is the nearest dark region: found.
    assert frame_vessel_anchor(shadowed, force, PROFILE, model) is not None
    assert frame_vessel_anchor(shadowed, force, PROFILE, model, near=anchors[0]) is None


def test_a_vessel_that_moved_on_while_unseen_is_found_again(collapse_fits) -> None:
    """After a frame without a lumen the region the lumen is expected in grows: a lumen 30 px on (more
    than the two radii a lumen may move between consecutive frames) is found again."""
    model = collapse_fits["vessel"].fitted
    assert isinstance(model, VesselAnchoredModel)
    force = float(FORCES[-1])
    moved_on = VesselAnchor((MOVED_LUMEN.centre_px[0] - 30.0, MOVED_LUMEN.centre_px[1]), MOVED_LUMEN.radius_px)
    before = pressed(lumen_frame(MOVED_LUMEN), MOVED_LUMEN, force)
    shut = before.copy()
    shut[shut < 40] = 120  # no anechoic region left
    after = pressed(lumen_frame(moved_on, seed=5), moved_on, force)
    _, _, anchors = correct_vessel_anchored(np.stack([before, shut, after]), force, PROFILE, model)
    assert anchors[0] is not None and anchors[1] is None and anchors[2] is not None
    assert np.hypot(*np.subtract(anchors[2].centre_px, moved_on.centre_px)) < 3.0
    # Right after a frame with the lumen, the same jump is not taken for the lumen.
    _, _, direct = correct_vessel_anchored(np.stack([before, after]), force, PROFILE, model)
    assert direct[1] is None


def test_given_anchors_place_the_vessel_part_without_a_search(collapse_fits) -> None:
    """Masks (or other images of the same frames) are warped with the lumens found in the frames."""
    model = collapse_fits["vessel"].fitted
    assert isinstance(model, VesselAnchoredModel)
    force = float(FORCES[-1])
    deformed = pressed(lumen_frame(MOVED_LUMEN), MOVED_LUMEN, force)[None]
    _, _, anchors = correct_vessel_anchored(deformed, force, PROFILE, model)
    mask = np.where(deformed < 40, 255, 0).astype(np.uint8)  # no dark lumen to find in it: 0 outside
    warped, _, given = correct_vessel_anchored(mask, force, PROFILE, model, anchors=anchors)
    searched_field = model.displacement(force, PROFILE, FRAME, anchors[0])
    assert given == anchors and np.array_equal(warped[0], warp_frame(mask[0], searched_field, 0.0)[0])
    with pytest.raises(InputError, match=r"^anchors: expected one per frame \(1\), got 2"):
        correct_vessel_anchored(deformed, force, PROFILE, model, anchors=[None, None])


def test_the_recommended_method_falls_back_to_the_image_without_a_lumen() -> None:
    """``recommended`` anchors on the vessel; where no palpation shows a lumen (none found, or the wall
    not measured) it fits in image coordinates."""
    from types import SimpleNamespace

    from usdeform.fitting import FIT_METHODS, fit_measured

    tracks, wall = collapse_observations(FITTED_LUMEN)
    assert FIT_METHODS["recommended"].anchor == "vessel"
    with_lumen = [SimpleNamespace(observations=tracks, wall=wall, other_walls=())]
    without = [SimpleNamespace(observations=dataclasses.replace(tracks, vessel=None), wall=None, other_walls=())]
    recommended = FIT_METHODS["recommended"]
    assert isinstance(fit_measured(with_lumen, recommended).fitted, VesselAnchoredModel)  # type: ignore[arg-type]
    assert isinstance(fit_measured(without, recommended).fitted, BSplineDisplacementModel)  # type: ignore[arg-type]
    off = dataclasses.replace(recommended, wall="off")
    assert isinstance(fit_measured(without, off).fitted, BSplineDisplacementModel)  # type: ignore[arg-type]


def test_a_lumen_larger_than_its_search_window_is_found_whole() -> None:
    """The lumen is searched in a window of a few radii around where it is expected; a lumen reaching
    the window's edge (expected much smaller than it is) is searched again in the whole frame."""

    frame = lumen_frame(MOVED_LUMEN)
    unmoved = lambda window: np.zeros((2, window[0].stop - window[0].start, window[1].stop - window[1].start))  # noqa: E731
    whole = find_lumen(frame, unmoved, MOVED_LUMEN.centre_px)
    expected_small = VesselAnchor(MOVED_LUMEN.centre_px, MOVED_LUMEN.radius_px / 4)
    window = search_window(expected_small, FRAME)
    assert window[0].stop - window[0].start < 2 * MOVED_LUMEN.radius_px  # the lumen does not fit in it
    windowed = find_lumen(frame, unmoved, MOVED_LUMEN.centre_px, window)
    assert whole is not None and windowed is not None
    assert np.hypot(*np.subtract(whole.centre_px, windowed.centre_px)) < 1e-9
    assert abs(whole.radius_px - windowed.radius_px) < 1e-9
    # Expected about right, the window holds it: the same lumen.
    fitting = find_lumen(frame, unmoved, MOVED_LUMEN.centre_px, search_window(MOVED_LUMEN, FRAME))
    assert fitting is not None and abs(fitting.radius_px - whole.radius_px) < 0.5
    # A lumen expected outside the frame (a caller's guess): the whole frame is searched.
    assert search_window(VesselAnchor((-100.0, 500.0), 5.0), FRAME) == (slice(0, FRAME[0]), slice(0, FRAME[1]))


def test_the_compiled_search_finds_a_lumen_larger_than_its_window_whole(collapse_fits) -> None:
    """The same with the compiled search (:func:`frame_vessel_anchor`, a model that moves nothing):
    a lumen expected a quarter of its size, its window too small to hold it, is found whole."""
    anchored = collapse_fits["vessel"].fitted
    still = dataclasses.replace(
        anchored,
        image_model=dataclasses.replace(
            anchored.image_model, coefficients=np.zeros_like(anchored.image_model.coefficients)
        ),
        vessel_coefficients=np.zeros_like(anchored.vessel_coefficients),
    )
    frame = lumen_frame(MOVED_LUMEN)
    whole = frame_vessel_anchor(frame, 5.0, PROFILE, still)  # from the fitted lumen, in the whole frame
    expected_small = VesselAnchor(MOVED_LUMEN.centre_px, MOVED_LUMEN.radius_px / 4)
    windowed = frame_vessel_anchor(frame, 5.0, PROFILE, still, near=expected_small)
    field_on = functools.partial(still.displacement_on, 5.0, PROFILE)
    twin = zero_force_lumen(frame, still, None, field_on)
    assert whole is not None and windowed is not None and twin is not None
    assert np.hypot(*np.subtract(whole.centre_px, MOVED_LUMEN.centre_px)) < 0.5
    for found in (whole, windowed):
        np.testing.assert_allclose([*found.centre_px, found.radius_px], [*twin.centre_px, twin.radius_px], atol=1e-9)
