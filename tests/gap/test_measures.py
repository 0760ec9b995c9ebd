"""Each gap measure on constructed inputs whose answer is known."""

import dataclasses

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.gap.linear_fits import qlv
from usdeform.gap.measures import GROUPS, Prediction, build_layout, residual_sums
from usdeform.gap.observations import (
    Observation,
    _in_contact,
    _motion_compensated_correlation,
    _phases,
    correlation_partners,
    observe,
)
from usdeform.gap.statistics import critical_z, feature_values, gap_statistic, significant_groups
from usdeform.recording import image_to_probe_from_geometry
from usdeform.sim import Viscoelasticity
from usdeform.sim.effects import _RelaxationIntegrator


def _observation(n=60, n_points=48, rng=None):
    """A load-hold-unload observation with made-up but consistent content (64 x 64 pixel frames)."""
    rng = rng or np.random.default_rng(0)
    time = np.arange(n) * 0.1
    lam = np.interp(time, [0, 2, 4, 6], [0, 5, 5, 0])
    force = 2.0 * lam
    cols, rows = np.meshgrid(np.linspace(4, 60, 8), np.linspace(4, 60, 6))
    points = np.column_stack([cols.ravel(), rows.ravel()])[:n_points]
    displacement = np.zeros((n, len(points), 2))
    displacement[..., 1] = -lam[:, None] * (1 - points[None, :, 1] / 64)
    return Observation(
        name="constructed",
        time_s=time,
        force_n=force,
        probe_displacement_mm=lam,
        phase=_phases(force, lam),
        block=(time / 0.3).astype(int),
        image_to_probe=image_to_probe_from_geometry(64, 64, 40.0, 37.5),
        frame_shape=(64, 64),
        points_px=points,
        displacement_px=displacement,
        reference_index=0,
        correlation=np.where(correlation_partners(lam) >= 0, 0.9, np.nan),
        correlation_partner=correlation_partners(lam),
        vessel_area_mm2=np.full(n, 50.0),
        vessel_center_probe_mm=np.array([0.0, 20.0]),
        vessel_radius_mm=4.0,
        intensity_depth_mm=np.linspace(2.5, 37.5, 8),
        intensity=np.full((n, 8), 100.0),
    )


def _exact(observation):
    return Prediction(
        force_n=observation.force_n.copy(),
        displacement_px=observation.displacement_px.copy(),
        correlation=observation.correlation.copy(),
        vessel_area_ratio=np.ones(observation.n_frames),
    )


def _values(observation, layout, prediction):
    sums, counts = residual_sums(observation, layout, prediction)
    return feature_values(sums, counts, np.ones((1, observation.n_frames)))[0]


def _value_of(observation, layout, prediction, name):
    return _values(observation, layout, prediction)[np.array(layout.names) == name][0]


def test_the_displacement_sums_of_a_read_only_displacement_are_remembered_with_the_prediction():
    """A read-only displacement's residual sums are kept in the prediction's shared list and returned as copies,
    the same as computed afresh; a writeable displacement (which a caller may change) or another observation is not
    served from it."""
    observation = _observation()
    prediction = _exact(observation)
    prediction.displacement_px[..., 1] *= 1.1
    layout = build_layout(observation, prediction)
    fresh = residual_sums(observation, layout, prediction)
    assert prediction.displacement_sums == []  # writeable: not remembered
    prediction.displacement_px.setflags(write=False)
    first = residual_sums(observation, layout, prediction)
    assert len(prediction.displacement_sums) == 1
    shared = dataclasses.replace(prediction, force_n=prediction.force_n + 1.0)  # the same geometry, another force
    assert shared.displacement_sums is prediction.displacement_sums
    second = residual_sums(observation, layout, shared)
    assert len(prediction.displacement_sums) == 1
    for got in (first, second):
        np.testing.assert_array_equal(got[1], fresh[1])
    np.testing.assert_array_equal(first[0], fresh[0])
    first[0][:] = np.nan  # the caller's copy, not the remembered sums
    again = residual_sums(observation, layout, prediction)
    np.testing.assert_array_equal(again[0], fresh[0])
    other = dataclasses.replace(observation, displacement_px=observation.displacement_px * 0.5)
    residual_sums(other, layout, prediction)
    assert len(prediction.displacement_sums) == 2


def test_phases_split_load_hold_unload():
    lam = np.concatenate([np.linspace(0, 5, 20), np.full(10, 5.0), np.linspace(5, 0, 20)])
    phase = _phases(2 * lam, lam)
    assert (phase[:19] == 0).all() and (phase[19:30] == 1).all() and (phase[31:] == 2).all()


def test_exact_prediction_has_zero_residual_and_no_gap():
    observation = _observation()
    layout = build_layout(observation, _exact(observation))
    values = _values(observation, layout, _exact(observation))
    assert np.nanmax(np.abs(values)) == 0
    assert gap_statistic(values[None], layout.floors, layout.groups)[0] == 0


def test_force_offset_appears_in_every_force_bin_and_cancels_in_hysteresis():
    observation = _observation()
    prediction = _exact(observation)
    layout = build_layout(observation, prediction)
    prediction.force_n = prediction.force_n - 0.7
    values = _values(observation, layout, prediction)
    names = np.array(layout.names)
    np.testing.assert_allclose(
        values[names == "force_residual_n"][np.isfinite(values[names == "force_residual_n"])], 0.7
    )
    assert values[names == "force_hysteresis_n"][0] == pytest.approx(0.0, abs=1e-12)
    assert values[names == "force_relaxation_n"][0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("delay_s", [0.03, 0.08, -0.05])
def test_image_delay_measures_a_known_lag_and_ignores_an_elastic_misfit(delay_s):
    observation = _observation()
    # the recording's image lags the simulation, which follows the robot's lambda, by delay_s
    lam = np.interp(observation.time_s + delay_s, observation.time_s, observation.probe_displacement_mm)
    prediction = _exact(observation)  # the constructed field is linear in lambda
    prediction.displacement_px[..., 1] = -lam[:, None] * (1 - observation.points_px[None, :, 1] / 64)
    layout = build_layout(observation, prediction)
    names = np.array(layout.names)
    assert _value_of(observation, layout, prediction, "image_delay_s") == pytest.approx(delay_s, rel=0.1)
    # a displacement field 10 % too stiff everywhere is the same on loading and unloading: no delay beyond a
    # tenth of the floor (the first unloading frame's nearest loading frame is a frame of lambda away)
    stiff = _exact(observation)
    stiff.displacement_px = observation.displacement_px * 0.9
    floor = layout.floors[names == "image_delay_s"][0]
    assert floor >= 0.005
    assert _value_of(observation, layout, stiff, "image_delay_s") == pytest.approx(0.0, abs=0.1 * floor)


def test_residual_map_locates_a_known_pattern():
    observation = _observation()
    layout = build_layout(observation, _exact(observation))
    # A residual only in the shallowest depth band, axial component.
    prediction = _exact(observation)
    top = observation.points_px[:, 1] < 16
    prediction.displacement_px[1:, top, 1] -= 2.0
    values = _values(observation, layout, prediction)
    axial = [i for i, name in enumerate(layout.names) if name == "displacement_axial_px"]
    shallow = [i for i in axial if layout.regions[i].startswith("depth 0-")]
    assert np.allclose(values[shallow], 2.0)
    assert np.allclose(values[sorted(set(axial) - set(shallow))], 0.0)


def test_gap_statistic_weights_groups_equally_and_group_test_flags_a_shift():
    groups = np.array([0, 0, 0, 0, 1])
    values = np.array([[1.0, 1.0, 1.0, 1.0, 3.0]])
    assert gap_statistic(values, np.ones(5), groups)[0] == pytest.approx((1.0 + 9.0) / 2)
    rng = np.random.default_rng(1)
    noise = rng.standard_normal(60)
    labels = np.repeat([0, 1], 30)
    assert not any(significant_groups(noise, labels).values())
    shifted = noise + np.where(labels == 1, 1.5, 0.0)
    assert significant_groups(shifted, labels) == {GROUPS[0]: False, GROUPS[1]: True}
    assert critical_z(1) == pytest.approx(1.96, abs=0.01)


def test_gap_tests_combine_the_evidence_of_both_splits():
    from usdeform.gap.statistics import gap_tests

    rng = np.random.default_rng(2)
    groups = np.repeat(np.arange(6), 30)
    z_crit = critical_z(len(groups))
    quiet = 0.5 * rng.standard_normal(len(groups))
    gap, significant = gap_tests((quiet, quiet), groups)
    assert not gap and not significant.any()

    def with_measure_40(value):
        z = quiet.copy()
        z[40] = value
        return z

    # each split alone below the Bonferroni level, together beyond it (a delay seen on both halves of a recording)
    both = with_measure_40(0.8 * z_crit)
    gap, significant = gap_tests((both, both), groups)
    assert gap and np.flatnonzero(significant).tolist() == [40]
    # a sensor offset shows in the few frames at first contact, most of which fell in the fitting split
    gap, significant = gap_tests((with_measure_40(-0.5 * z_crit), with_measure_40(-1.3 * z_crit)), groups)
    assert gap and np.flatnonzero(significant).tolist() == [40]
    # contradicting splits cancel; a split without samples (NaN) leaves the other's score as it is
    assert not gap_tests((with_measure_40(0.9 * z_crit), with_measure_40(-0.9 * z_crit)), groups)[0]
    assert gap_tests((with_measure_40(np.nan), with_measure_40(1.1 * z_crit)), groups)[0]
    assert not gap_tests((with_measure_40(np.nan), with_measure_40(0.9 * z_crit)), groups)[0]
    # a group that differs jointly names its measures beyond |z| = 2; a measure without samples never differs
    shifted = quiet + np.where(groups == 3, 1.2, 0.0)
    shifted[95] = np.nan
    gap, significant = gap_tests((shifted, shifted), groups)
    assert gap and significant.any() and set(groups[significant]) == {3} and not significant[95]


def test_speckle_correlation_is_one_for_a_shifted_copy_and_low_for_new_speckle():
    rng = np.random.default_rng(2)
    speckle = (rng.rayleigh(40, (96, 96))).clip(0, 255).astype(np.uint8)
    import cv2

    speckle = cv2.GaussianBlur(speckle, (0, 0), 1.0)
    shifted = np.roll(speckle, 2, axis=0)
    assert _motion_compensated_correlation(speckle, shifted) > 0.9
    other = cv2.GaussianBlur(rng.rayleigh(40, (96, 96)).clip(0, 255).astype(np.uint8), (0, 0), 1.0)
    # the flow fits new speckle a little (it warps to match it), so unrelated speckle stays near 0.2, not 0
    assert abs(_motion_compensated_correlation(speckle, other)) < 0.3


def test_qlv_matches_the_simulator_integrator_and_relaxes_to_the_long_term_modulus():
    time = np.arange(0, 20, 0.01)
    elastic = np.interp(time, [0, 1, 20], [0, 10, 10])
    fitted = qlv(elastic, time, 0.3, 0.5)
    integrator = _RelaxationIntegrator(Viscoelasticity(((0.3, 0.5),)), 0.01)
    integrator.start_loaded(elastic[0])
    reference = np.array([elastic[0]] + [integrator.step(value) for value in elastic[1:]])
    np.testing.assert_allclose(fitted, reference, atol=1e-9)
    assert fitted[-1] == pytest.approx(7.0, rel=1e-3)


def test_force_offset_shows_in_the_near_contact_measure():
    observation = _observation()
    layout = build_layout(observation, _exact(observation))
    biased = _exact(observation)
    biased.force_n = biased.force_n - 0.7  # the simulation reads 0.7 N less: a sensor bias in the recording
    values = _values(observation, layout, biased)
    near = [layout.contact_force_offset, layout.contact_force_offset + 1]
    assert [layout.names[i] for i in near] == ["force_near_contact_n"] * 2
    np.testing.assert_allclose(values[near], 0.7)


def test_outward_slip_of_the_top_row_shows_in_the_contact_slip_measure():
    observation = _observation()
    layout = build_layout(observation, _exact(observation))
    slid = _exact(observation)
    top = observation.points_px[:, 1] == observation.points_px[:, 1].min()
    outward = np.sign(observation.points_px[:, 0] - 32.0)
    # the recording's top row spreads outwards by 0.5 px per mm of lambda; the simulation (stuck) does not
    observation.displacement_px[:, top, 0] += 0.5 * observation.probe_displacement_mm[:, None] * outward[top]
    values = _values(observation, layout, slid)
    slip = values[layout.slip_offset : layout.slip_offset + 3]
    assert (slip > 0).all() and slip[2] > slip[0]
    # a uniform lateral bulge of all rows is no slip
    bulged = _observation()
    bulged.displacement_px[..., 0] += (
        0.3 * bulged.probe_displacement_mm[:, None] * np.sign(bulged.points_px[:, 0] - 32.0)
    )
    layout = build_layout(bulged, _exact(_observation()))
    values = _values(bulged, layout, _exact(_observation()))
    np.testing.assert_allclose(values[layout.slip_offset : layout.slip_offset + 3], 0.0, atol=1e-12)


def test_near_field_bands_across_the_image_are_flagged_and_speckle_is_not():
    import dataclasses

    from usdeform.gap.diagnosis import _near_field_band_measure
    from usdeform.gap.observations import ROW_PROFILE_STRIPS

    rng = np.random.default_rng(5)
    n, rows = 60, 400  # 0.1 mm rows, 40 mm deep
    base = _observation(n=n)
    # static speckle averaged over a strip's columns (80 independent cells across a 40 mm image, contrast 0.5
    # after log compression): mean 80, sd 40 / sqrt(cells per strip)
    speckle = rng.normal(80.0, 40.0 / np.sqrt(80 / ROW_PROFILE_STRIPS), size=(ROW_PROFILE_STRIPS, rows))
    smooth = np.stack([np.convolve(s, np.ones(3) / 3, mode="same") for s in speckle])
    strips = np.repeat(smooth[None], n, axis=0) + rng.normal(0, 5, size=(n, ROW_PROFILE_STRIPS, rows))
    geometry = dict(image_to_probe=image_to_probe_from_geometry(rows, rows, 40.0, 40.0), frame_shape=(rows, rows))
    clean = dataclasses.replace(base, row_profile_strips=strips, **geometry)
    [measure] = _near_field_band_measure(clean, np.random.default_rng(0), critical_z(100))
    assert not measure.significant
    depth = np.arange(rows) * 0.1
    bands = 40 * np.exp(-0.5 * ((depth[:, None] - 2.0 * np.arange(1, 6)) / 0.25) ** 2).sum(axis=1) * np.exp(-depth / 6)
    banded = dataclasses.replace(clean, row_profile_strips=strips + bands)
    [measure] = _near_field_band_measure(banded, np.random.default_rng(0), critical_z(100))
    assert measure.significant and measure.value > 0


def test_a_uniform_axial_scale_shows_in_the_axial_displacement_scale_only():
    observation = _observation()
    observation.displacement_px[..., 0] = (
        0.3 * observation.probe_displacement_mm[:, None] * np.sign(observation.points_px[:, 0] - 32.0)
    )
    layout = build_layout(observation, _exact(observation))
    simulated = _exact(observation)
    observation.displacement_px[..., 1] *= 1.05  # depths displayed 5 % deeper (a slower tissue than assumed)
    values = _values(observation, layout, simulated)
    columns = np.arange(layout.scale_offset, layout.scale_offset + 6)
    names = [layout.names[i] for i in columns]
    assert names == ["displacement_scale_lateral", "displacement_scale_axial"] * 3
    np.testing.assert_allclose(values[columns[1::2]], 0.05, rtol=1e-9)
    np.testing.assert_allclose(values[columns[0::2]], 0.0, atol=1e-12)


def test_sensor_drift_is_bounded_and_offset_free():
    from usdeform.gap.linear_fits import MAX_DRIFT_N_PER_S, fit_force, force_columns

    observation = _observation()
    design = force_columns(observation, {"force_sensor_error": {}})
    elastic = 0.4 * observation.probe_displacement_mm + 0.05 * observation.probe_displacement_mm**2
    small = fit_force(design, elastic - 0.8 + 0.01 * observation.time_s)
    np.testing.assert_allclose(small, [0.4, 0.05, 0.0, -0.8, 0.01], atol=1e-6)
    steep = fit_force(design, elastic + 0.5 * observation.time_s)  # a trend no thermal drift makes
    assert steep[4] == pytest.approx(MAX_DRIFT_N_PER_S)


def test_near_contact_takes_the_lowest_lambda_frames_of_a_fast_ramp():
    observation = _observation()  # lambda 0-5 mm in 2 s at 10 frames/s: 5 loading frames below 1 mm
    layout = build_layout(observation, _exact(observation))
    _, counts = residual_sums(observation, layout, _exact(observation))
    loading_frames = np.flatnonzero(counts[:, layout.contact_force_offset])
    assert len(loading_frames) == 8
    assert (observation.phase[loading_frames] == 0).all()
    assert (
        observation.probe_displacement_mm[loading_frames].max()
        <= np.sort(observation.probe_displacement_mm[observation.phase == 0])[7]
    )


def test_correlation_partners_pair_frames_by_lambda_separation():
    lam = np.array([0.0, 0.5, 1.0, 1.6, 2.0, 4.1, 3.05])
    partners = correlation_partners(lam)
    assert partners[0].tolist() == [-1, 0, 1, 2, 3, 4, 5]  # the previous frame
    assert partners[1].tolist() == [-1, -1, 0, 1, 2, -1, 4]  # 1 mm apart, within 0.25 mm
    assert partners[2].tolist() == [-1, -1, -1, 0, 0, 4, 2]  # 2 mm apart, within 0.5 mm (frame 3: 1.6 mm)
    assert partners[3].tolist() == [-1, -1, -1, -1, -1, 0, 0]  # 4 mm apart, within 1 mm (frame 6: 3.05 mm)


def test_speckle_correlation_ignores_structure_that_does_not_decorrelate():
    import cv2

    depth_profile = np.linspace(200, 20, 96)[:, None] * np.ones((1, 96))  # gain and attenuation, no speckle

    def frame(seed):
        speckle = cv2.GaussianBlur(np.random.default_rng(seed).rayleigh(12, (96, 96)), (0, 0), 1.0)
        return (depth_profile + speckle).clip(0, 255).astype(np.uint8)

    first, second = frame(4), frame(5)  # same structure, new speckle
    raw = np.corrcoef(first.ravel().astype(float), second.ravel().astype(float))[0, 1]
    assert raw > 0.9  # the depth profile dominates the plain coefficient
    assert abs(_motion_compensated_correlation(first, second)) < 0.2
    assert _motion_compensated_correlation(first, first) == pytest.approx(1.0)


def test_tracks_are_referenced_to_the_first_frame_in_contact():

    lam = np.array([-0.4, -0.1, 0.05, 1.0, 2.0])
    points = np.array([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0]])
    displacement = np.zeros((5, 3, 2))
    displacement[:, :, 1] = np.array([0.0, 1.0, 2.0, 5.0, 9.0])[:, None]  # from the lifted-off frame 0
    displacement[2, 2] = np.nan  # point 2 lost in the new reference frame
    rebased_points, rebased, reference = _in_contact(points, displacement, lam, "recording")
    assert reference == 2
    assert rebased_points.tolist() == [[10.0, 22.0], [30.0, 42.0]]
    assert np.isnan(rebased[:2]).all()  # out of contact: no deformation information
    assert rebased[2:, :, 1].tolist() == [[0.0, 0.0], [3.0, 3.0], [7.0, 7.0]]
    with pytest.raises(InputError, match="recording: ProbeDisplacement"):
        _in_contact(points, displacement, np.full(5, -1.0), "recording")


def test_lumen_pressure_pushes_on_the_probe_from_first_contact_only():
    from usdeform.gap.calibration import LIBRARY_SHEAR_MODULUS_KPA, CalibratedSection
    from usdeform.gap.models import contact_reaction, predict

    observation = _observation()
    lam = observation.probe_displacement_mm.copy()
    lam[:3] = [-0.2, 0.0, 0.1]  # out of contact, touching, in contact
    observation = dataclasses.replace(observation, probe_displacement_mm=lam)
    steps = np.linspace(0.0, 6.0, 5)
    field = np.zeros((2, len(steps), 3, 3))
    ramp = 2.0 * steps
    section = CalibratedSection(
        spec=None,  # type: ignore[arg-type]
        grid_x_mm=np.linspace(-30, 30, 3),
        grid_z_mm=np.linspace(0, 40, 3),
        lambda_mm=steps,
        fields={"ideal": field, "poisson_ratio=0.49": field, "pressure_0.05": field, "pressure_0.2": field},
        lumen_area_mm2={
            name: np.full(len(steps), 50.0) for name in ("ideal", "poisson_ratio=0.49", "pressure_0.05", "pressure_0.2")
        },
        force_n={"ideal": ramp, "pressure_0.05": ramp + 0.1, "pressure_0.2": ramp + 0.4},
        shear_modulus_kpa=2 * LIBRARY_SHEAR_MODULUS_KPA,
        has_vessel=True,
    )
    assert not contact_reaction(observation, section, {}).any()
    reaction = contact_reaction(observation, section, {"lumen_pressure": {"pressure_ratio": 0.1}})
    # 0.1 lies a third of the way from 0.05 to 0.2: 0.2 N at the library modulus, twice that at the calibrated one
    assert reaction[:2] == pytest.approx([0.0, 0.0])
    assert reaction[2:] == pytest.approx(np.full(len(lam) - 2, 0.4))
    # the elastic cubic is fitted to what the reaction leaves, so the prediction carries the step
    fit = np.ones(len(lam), bool)
    recorded = dataclasses.replace(observation, force_n=np.clip(2.0 * lam, 0, None) + reaction)
    prediction, _ = predict(recorded, section, {"lumen_pressure": {"pressure_ratio": 0.1}}, fit)
    assert prediction.force_n == pytest.approx(recorded.force_n, abs=1e-4)


def test_partial_slip_weights_the_frictionless_solve():
    from usdeform.gap.calibration import LIBRARY_SHEAR_MODULUS_KPA, CalibratedSection
    from usdeform.gap.models import predict, variant_weights

    observation = _observation()
    steps = np.linspace(0.0, 6.0, 5)
    grid_x, grid_z = np.linspace(-30, 30, 7), np.linspace(0, 45, 7)
    bonded = np.zeros((2, len(steps), len(grid_z), len(grid_x)))
    bonded[1] = -steps[:, None, None] * (1 - grid_z[None, :, None] / 45)  # compression, no lateral motion
    frictionless = bonded.copy()
    frictionless[0] = 0.05 * steps[:, None, None] * grid_x[None, None, :] * np.exp(-grid_z[None, :, None] / 10)
    section = CalibratedSection(
        spec=None,  # type: ignore[arg-type]
        grid_x_mm=grid_x,
        grid_z_mm=grid_z,
        lambda_mm=steps,
        fields={"ideal": bonded, "slide": frictionless},
        lumen_area_mm2={name: np.full(len(steps), 50.0) for name in ("ideal", "slide")},
        force_n={"ideal": 2.0 * steps, "slide": 2.0 * steps},
        shear_modulus_kpa=LIBRARY_SHEAR_MODULUS_KPA,
        has_vessel=True,
    )
    assert variant_weights({"sliding_contact": {"slip_fraction": 0.3}}, section) == {"slide": 0.3}
    fit = np.ones(observation.n_frames, bool)
    lateral = {
        slip: predict(observation, section, {"sliding_contact": {"slip_fraction": slip}}, fit)[0].displacement_px[
            ..., 0
        ]
        for slip in (0.0, 0.5, 1.0)
    }
    spread = lateral[1.0] - lateral[0.0]
    assert np.nanmax(np.abs(spread)) > 1.0  # pixels: full slip spreads the tissue outwards
    # partial slip lies between, nearly proportionally (the material points are found with each field)
    assert np.nanmax(np.abs(lateral[0.5] - lateral[0.0] - 0.5 * spread)) < 0.05 * np.nanmax(np.abs(spread))


def test_a_tilt_weights_the_progressive_contact_and_the_oblique_push():
    from usdeform.gap.calibration import (
        TILT_VARIANT_DEG,
        TRAVEL_VARIANT,
        ideal_section,
        tilt_variant_name,
        variant_specs,
    )
    from usdeform.gap.models import variant_weights

    spec, parameters, has_vessel = ideal_section(_observation())
    variants = variant_specs(spec, parameters, has_vessel)
    # the image's tilt t is a face tilted -t: a positive tilt lowers the face's -x edge, which touches first
    assert variants[tilt_variant_name(TILT_VARIANT_DEG)].face_tilt_deg == -TILT_VARIANT_DEG
    assert variants[tilt_variant_name(-TILT_VARIANT_DEG)].face_tilt_deg == TILT_VARIANT_DEG
    assert variants[TRAVEL_VARIANT].face_travel_deg == TILT_VARIANT_DEG and variants[TRAVEL_VARIANT].face_tilt_deg == 0
    section = dataclasses.make_dataclass("Fields", ["fields"])(fields=dict.fromkeys(variants))
    along_normal = variant_weights({"probe_tilt": {"tilt_deg": -4.0, "travel_along_axis": 0.0}}, section)
    assert along_normal == {tilt_variant_name(-TILT_VARIANT_DEG): 0.5}
    along_axis = variant_weights({"probe_tilt": {"tilt_deg": -4.0, "travel_along_axis": 1.0}}, section)
    assert along_axis[tilt_variant_name(-TILT_VARIANT_DEG)] == 0.5
    assert along_axis[TRAVEL_VARIANT] == pytest.approx(np.tan(np.radians(-4.0)) / np.tan(np.radians(TILT_VARIANT_DEG)))
    assert variant_weights({"probe_tilt": {"tilt_deg": 0.0, "travel_along_axis": 1.0}}, section) == {}


def test_tracked_points_see_the_probe_move_along_a_tilt_and_an_oblique_push():
    """Tissue that does not move is found at its pixels in the reference frame and, later, moved against the probe
    by its travel (along the surface normal, and sideways when it presses obliquely), seen along the tilted axes."""
    from usdeform.gap.calibration import LIBRARY_SHEAR_MODULUS_KPA, CalibratedSection, ideal_section
    from usdeform.gap.tracked_points import TrackedPoints

    observation = _observation()
    steps = np.linspace(0.0, 6.0, 5)
    grid_x, grid_z = np.linspace(-40, 40, 9), np.linspace(0, 50, 9)
    still = np.zeros((2, len(steps), len(grid_z), len(grid_x)))
    section = CalibratedSection(
        spec=ideal_section(observation)[0],
        grid_x_mm=grid_x,
        grid_z_mm=grid_z,
        lambda_mm=steps,
        fields={"ideal": still},
        lumen_area_mm2={"ideal": np.full(len(steps), 50.0)},
        force_n={"ideal": 2.0 * steps},
        shear_modulus_kpa=LIBRARY_SHEAR_MODULUS_KPA,
        has_vessel=True,
    )
    lam = observation.probe_displacement_mm
    for tilt, slope in ((0.0, 0.0), (6.0, 0.0), (-6.0, np.tan(np.radians(-6.0)))):
        tracked = TrackedPoints(observation, section, still, lam, tilt, slope, 1.0)
        displacement = tracked.displacement_px(tracked.sample(still))
        reference = displacement[observation.reference_index]
        np.testing.assert_allclose(reference[np.isfinite(reference)], 0.0, atol=1e-9)
        # tissue that does not move: the probe's own motion shows, down the normal (and sideways with an oblique
        # push): the tissue moves by (-slope, -1) times the step in the section, seen along the probe's axes
        moved = (displacement[-1] - displacement[observation.reference_index]) * [
            observation.image_to_probe[0, 0],
            observation.image_to_probe[2, 1],
        ]
        step = lam[-1] - lam[observation.reference_index]
        cos, sin = np.cos(np.radians(tilt)), np.sin(np.radians(tilt))
        expected = step * np.array([-slope * cos + sin, -slope * sin - cos])
        np.testing.assert_allclose(np.nanmedian(moved, axis=0), expected, atol=1e-6)


def test_slip_and_face_width_combine_bilinearly_through_their_joint_solve():
    from usdeform.gap.calibration import (
        LIBRARY_SHEAR_MODULUS_KPA,
        CalibratedSection,
        ideal_section,
        joint_name,
        section_parameters,
        variant_specs,
    )

    rng = np.random.default_rng(5)
    face = "probe_width_mm=50"
    joint = joint_name("slide", face)
    fields = {name: rng.normal(size=(2, 4, 5, 6)) for name in ("ideal", "slide", face, joint)}
    section = CalibratedSection(
        spec=None,  # type: ignore[arg-type]
        grid_x_mm=np.linspace(-30, 30, 6),
        grid_z_mm=np.linspace(0, 40, 5),
        lambda_mm=np.linspace(0, 6, 4),
        fields=fields,
        lumen_area_mm2={name: rng.uniform(40, 60, 4) for name in fields},
        force_n={name: np.zeros(4) for name in fields},
        shear_modulus_kpa=LIBRARY_SHEAR_MODULUS_KPA,
        has_vessel=True,
        parameters=section_parameters(37.5),
    )
    ideal, slide, wide, both = (fields[name] for name in ("ideal", "slide", face, joint))
    for slip, width in [(0.0, 0.0), (1.0, 1.0), (0.3, 0.6), (1.0, -0.2)]:
        interaction = slip * width * (both - wide - slide + ideal)
        expected = ideal + slip * (slide - ideal) + width * (wide - ideal) + interaction
        weights = section.joint_weights({"slide": slip, face: width})
        assert section.field(weights) == pytest.approx(expected)
        # the parameter's change per unit weight, as the section-parameter fit sees it, gives the same field
        change = sum(c * fields[name] for name, c in section.parameter_change(face, {"slide": slip}).items())
        assert section.field(section.joint_weights({"slide": slip})) + width * change == pytest.approx(expected)
    assert section.field(section.joint_weights({"slide": 1.0, face: 1.0})) == pytest.approx(both)
    # the library solves the frictionless section at the wider face too
    observation = _observation()
    spec, parameters, has_vessel = ideal_section(observation)
    specs = variant_specs(spec, parameters, has_vessel)
    assert specs[joint].contact == "slide" and specs[joint].probe_width_mm == 50.0


def test_correlation_roughness_ignores_trends_and_shows_per_frame_draws():
    from usdeform.gap.measures import correlation_roughness

    trend = np.linspace(0.99, 0.8, 20)[None]
    assert np.nanmax(correlation_roughness(trend)) == pytest.approx(0.0, abs=1e-12)
    jumpy = trend + 0.03 * (-1.0) ** np.arange(20)
    assert np.nanmean(correlation_roughness(jumpy)) == pytest.approx(0.06)
    gaps = trend.copy()
    gaps[0, 5] = np.nan
    assert np.isnan(correlation_roughness(gaps)[0, 4:7]).all()
    # in the measures: a recording whose correlation jumps from frame to frame differs from a smooth prediction
    observation = _observation()
    rough = dataclasses.replace(
        observation, correlation=observation.correlation + 0.03 * (-1.0) ** np.arange(observation.n_frames)
    )
    layout = build_layout(rough, _exact(observation))
    values = _values(rough, layout, _exact(observation))
    columns = [i for i, name in enumerate(layout.names) if name.startswith("speckle_correlation_roughness")]
    assert len(columns) == 4 and np.all(values[columns] > 3 * layout.floors[columns])
    assert _values(observation, layout, _exact(observation))[columns] == pytest.approx(0.0, abs=1e-12)


def test_out_of_plane_jitter_predicts_correlation_roughness_and_drift_does_not():
    from usdeform.gap.calibration import CalibratedSection
    from usdeform.gap.models import predict

    observation = _observation()
    steps = np.linspace(0.0, 6.0, 5)
    section = CalibratedSection(
        spec=None,  # type: ignore[arg-type]
        grid_x_mm=np.linspace(-30, 30, 3),
        grid_z_mm=np.linspace(0, 40, 3),
        lambda_mm=steps,
        fields={"ideal": np.zeros((2, len(steps), 3, 3)), "poisson_ratio=0.49": np.zeros((2, len(steps), 3, 3))},
        lumen_area_mm2={"ideal": np.full(len(steps), 50.0), "poisson_ratio=0.49": np.full(len(steps), 50.0)},
        force_n={"ideal": 2.0 * steps},
        shear_modulus_kpa=20.0,
        has_vessel=True,
    )
    fit = np.ones(observation.n_frames, bool)

    def roughness(shift, jitter):
        effects = {"out_of_plane_motion": {"shift_mm_per_mm": shift, "jitter_mm": jitter}}
        return np.nanmean(predict(observation, section, effects, fit)[0].correlation_roughness)

    assert roughness(0.0, 0.0) == pytest.approx(0.0, abs=1e-6)
    assert roughness(0.2, 0.0) < 0.005  # a steady drift changes the correlation smoothly
    assert 0.01 < roughness(0.0, 0.1) < roughness(0.0, 0.2)


def test_section_parameters_are_the_bounded_least_squares_fit_with_one_side_per_parameter():
    from usdeform.gap.calibration import SECTION_PARAMETERS
    from usdeform.gap.linear_fits import fit_section_parameters

    poisson, depth, lumen = SECTION_PARAMETERS[:3]
    observation = _observation()
    rng = np.random.default_rng(1)
    shape = observation.displacement_px.shape
    displacement = rng.normal(size=shape)
    changes = {
        "poisson_ratio=0.49": rng.normal(size=shape),
        "depth_mm=35": rng.normal(size=shape),
        "depth_mm=90": rng.normal(size=shape),
        "lumen_stiffness_ratio=0.005": rng.normal(size=shape),
    }
    fit = np.arange(observation.n_frames) % 2 == 0
    recorded = displacement + 0.6 * changes["poisson_ratio=0.49"] + 0.3 * changes["depth_mm=90"]
    recorded[~fit] += 5.0  # the held-out frames do not enter the fit
    recorded[0, 0] = np.nan  # nor untracked points
    weights, values = fit_section_parameters(
        dataclasses.replace(observation, displacement_px=recorded), displacement, changes, fit, SECTION_PARAMETERS
    )
    assert weights["poisson_ratio=0.49"] == pytest.approx(0.6)
    assert weights["depth_mm=90"] == pytest.approx(0.3)
    assert "depth_mm=35" not in weights  # one side of a two-sided parameter
    assert weights["lumen_stiffness_ratio=0.005"] == pytest.approx(0.0, abs=1e-9)
    assert values["poisson_ratio"] == pytest.approx(0.45 + 0.6 * 0.04)
    assert values["depth_mm"] == pytest.approx(1 / (1 / 60 + 0.3 * (1 / 90 - 1 / 60)))
    assert values["lumen_stiffness_ratio"] == pytest.approx(0.05)
    # beyond the range: held at its end; a parameter whose variants were not solved keeps its library value
    far = displacement + 9.0 * changes["poisson_ratio=0.49"] - 3.0 * changes["depth_mm=35"]
    weights, values = fit_section_parameters(
        dataclasses.replace(observation, displacement_px=far), displacement, changes, fit, SECTION_PARAMETERS
    )
    assert values["poisson_ratio"] == pytest.approx(poisson.bounds[1])
    assert weights["depth_mm=35"] == pytest.approx(0.0, abs=1e-9) or "depth_mm=35" not in weights
    assert values["depth_mm"] >= 60.0  # a negative weight on the thin side is the other side's business
    zero = {name: np.zeros(shape) for name in changes}
    weights, values = fit_section_parameters(observation, displacement, zero, fit, SECTION_PARAMETERS)
    assert weights == {} and values == {parameter.name: parameter.library for parameter in SECTION_PARAMETERS}
    assert depth.value(90.0, depth.weight_bounds(90.0)[1]) == pytest.approx(90.0)
    assert lumen.value(0.005, 0.5) == pytest.approx(np.sqrt(0.05 * 0.005))


def test_the_probe_face_is_a_free_parameter_from_the_image_width_up():
    from usdeform.gap.calibration import SECTION_PARAMETERS, ideal_section, section_parameters, variant_specs

    *fixed, probe = section_parameters(37.5 + 1e-9)
    assert tuple(fixed) == SECTION_PARAMETERS
    assert (probe.name, probe.library, probe.variants, probe.bounds) == ("probe_width_mm", 37.5, (50.0,), (35.0, 57.5))
    assert section_parameters(40.2)[-1].library == 40.5  # snapped up: recordings of one probe share solves
    assert probe.value(50.0, probe.weight_bounds(50.0)[1]) == pytest.approx(57.5)
    assert probe.value(50.0, probe.weight_bounds(50.0)[0]) == pytest.approx(35.0)  # one variant: both sides
    # the ideal section of an observation imaged 45 mm wide: a 45 mm face, every variant 3 faces of 57.5 mm wide
    wide = dataclasses.replace(_observation(), image_to_probe=image_to_probe_from_geometry(64, 64, 40.0, 45.0))
    spec, parameters, has_vessel = ideal_section(wide)
    assert has_vessel and spec.probe_width_mm == 45.0 and parameters[-1].variants == (57.5,)
    variants = variant_specs(spec, parameters, has_vessel)
    assert variants["probe_width_mm=57.5"].probe_width_mm == 57.5
    assert {variant.width_mm for variant in variants.values()} == {3 * 57.5}
    assert {"lumen_stiffness_ratio=0.005", "pressure_0.05"} <= set(variants)
    no_lumen = variant_specs(spec, parameters, has_vessel=False)
    assert not any(name.startswith(("lumen", "pressure")) for name in no_lumen)
    assert len(no_lumen) == len(variants) - 4


def test_the_library_is_solved_at_the_ladder_rung_nearest_the_surveyed_depth():
    from usdeform.gap.calibration import DEPTH_LADDER_MM, SECTION_PARAMETERS, ideal_section, library_variants

    observation = _observation()  # lumen 4 mm in radius 20 mm deep, 5 mm of indentation
    spec, parameters, has_vessel = ideal_section(observation)
    assert spec.depth_mm == 60.0 and parameters[1] == SECTION_PARAMETERS[1]
    survey = library_variants(observation, spec, parameters, has_vessel, survey=True)
    assert set(survey) == {"ideal", "depth_mm=35", "depth_mm=90"}
    assert len(library_variants(observation, spec, parameters, has_vessel)) > len(survey)
    spec, parameters, has_vessel = ideal_section(observation, 47.8)
    depth = parameters[1]
    assert spec.depth_mm == depth.library == 50.0 and depth.variants == (45.0, 55.0)
    assert depth.bounds == (DEPTH_LADDER_MM[0], DEPTH_LADDER_MM[-1]) == SECTION_PARAMETERS[1].bounds
    assert depth.value(55.0, depth.weight_bounds(55.0)[1]) == pytest.approx(90.0)  # the whole range stays open
    variants = library_variants(observation, spec, parameters, has_vessel)
    assert variants["depth_mm=45"].depth_mm == 45.0 and variants["poisson_ratio=0.49"].depth_mm == 50.0
    assert ideal_section(observation, 140.0)[1][1].variants == (80.0,)  # the ladder's end: one neighbour
    # no rung thinner than the lumen (with 3 mm below it) or than the indentation can take (40 %)
    assert ideal_section(observation, 10.0)[0].depth_mm == 30.0
    deep = dataclasses.replace(observation, vessel_center_probe_mm=np.array([0.0, 40.0]))
    assert ideal_section(deep, 30.0)[0].depth_mm == 50.0  # 40 + 4 + 3 = 47 mm at least
    pressed = dataclasses.replace(observation, probe_displacement_mm=2.6 * observation.probe_displacement_mm)
    assert ideal_section(pressed, 30.0)[0].depth_mm == 40.0  # 13 mm * 1.15 + 0.5 mm is 40 % of 38.6 mm


def test_every_library_section_can_be_solved_to_the_recorded_indentation():
    # 12.5 mm of indentation: the survey's 35 mm variant cannot take it (the solver stops at 40 % of a section's
    # depth), so the library leaves it out instead of failing on it, as it did on a palpation of an independent
    # generator when the library's limit was 45 %
    from usdeform.gap.calibration import _top_lambda_mm, ideal_section, library_variants
    from usdeform.sim.mechanics.solution import _check_probe_displacements

    observation = _observation()  # 5 mm of indentation
    pressed = dataclasses.replace(observation, probe_displacement_mm=2.5 * observation.probe_displacement_mm)
    steps = np.array([0.0, _top_lambda_mm(pressed)])
    for depth_mm in (None, 30.0, 47.8):
        spec, parameters, has_vessel = ideal_section(pressed, depth_mm)
        for survey in (True, False):
            for variant in library_variants(pressed, spec, parameters, has_vessel, survey=survey).values():
                _check_probe_displacements(steps, variant)  # raises InputError where the solver would
    assert set(library_variants(pressed, *ideal_section(pressed), survey=True)) == {"ideal", "depth_mm=90"}


def test_gridded_field_interpolation_matches_scipy_trilinear():
    from scipy.ndimage import map_coordinates

    from usdeform.gap.calibration import CalibratedSection

    rng = np.random.default_rng(2)
    steps = np.array([0.0, 0.8, 1.6, 2.4, 3.2])
    field = rng.normal(size=(2, len(steps), 6, 7))
    section = CalibratedSection(
        spec=None,  # type: ignore[arg-type]
        grid_x_mm=np.linspace(-3.0, 3.0, 7),
        grid_z_mm=np.linspace(0.0, 5.0, 6),
        lambda_mm=steps,
        fields={"ideal": field},
        lumen_area_mm2={},
        force_n={},
        shear_modulus_kpa=20.0,
        has_vessel=False,
    )
    points = np.column_stack([rng.uniform(-3.0, 3.0, 40), rng.uniform(0.0, 5.0, 40)])
    lambdas = np.concatenate([rng.uniform(0.0, 3.2, 9), [0.0, 3.2, -0.5]])  # ends, and before contact (clipped)
    result = section.displacement(field, points, lambdas)
    step = np.interp(np.clip(lambdas, 0, None), steps, np.arange(len(steps)))
    for k, lam_index in enumerate(step):
        coordinates = np.vstack([np.full(len(points), lam_index), points[:, 1], points[:, 0] + 3.0])
        for component in (0, 1):
            expected = map_coordinates(field[component], coordinates, order=1)
            np.testing.assert_allclose(result[component, k], expected, atol=1e-12)
    outside = section.displacement(field, np.array([[3.5, 1.0], [0.0, -0.1], [0.0, 5.0]]), np.array([1.0]))
    assert np.isnan(outside[:, 0, :2]).all() and np.isfinite(outside[:, 0, 2]).all()


@pytest.mark.slow
def test_speckle_correlation_does_not_depend_on_the_pixel_size(palpation):
    """The same palpation at twice the pixels per mm (as a scanner's scan conversion interpolates it): the flow, the
    warp and the fine scale work in pixels, so without merging fine pixels the correlation 4 mm apart dropped
    from 0.92 to 0.80 (and a null was attributed to out-of-plane motion)."""
    import cv2

    recording = palpation()
    finer = np.stack(
        [cv2.resize(f, (2 * f.shape[1], 2 * f.shape[0]), interpolation=cv2.INTER_LINEAR) for f in recording.frames]
    )
    pixel_centres = np.array([[0.5, 0, 0, -0.25], [0, 0.5, 0, -0.25], [0, 0, 1, 0], [0, 0, 0, 1]])
    upsampled = dataclasses.replace(recording, frames=finer, image_to_probe=recording.image_to_probe @ pixel_centres)
    original, fine = observe(recording, "original").correlation, observe(upsampled, "finer").correlation
    both = np.isfinite(original) & np.isfinite(fine)
    assert both.sum() > 100
    assert np.abs(original - fine)[both].mean() < 0.005
