"""Palpation phases (usdeform.fitting) and fitting on the loading ramp from contact (issue 42)."""

import dataclasses
import json

import numpy as np
import pytest

from usdeform.cli import main
from usdeform.errors import FitError, InputError
from usdeform.fitting import FIT_METHODS, detect_phases, fit_measured, fit_palpations, fit_stiffness, measure_positions
from usdeform.io import write_sequence
from usdeform.recording import Recording

LAYER_MM = 50.0  # the coarse phantom's depth
APPROACH_FRAMES = 12
APPROACH_MM = 5.0
SENSOR_NOISE_N = 0.03  # the simulator's force-sensor noise, N rms


def with_approach(recording: Recording, seed: int = 0, bias_n: float = 0.0) -> Recording:
    """``recording`` with APPROACH_FRAMES frames in front: the probe moving APPROACH_MM down to the surface
    (black frames, force at the sensor's noise plus ``bias_n``), ProbeDisplacement counted from the first
    frame as ``usdeform import-bag`` writes it."""
    rng = np.random.default_rng(seed)
    travelled = np.linspace(0.0, APPROACH_MM, APPROACH_FRAMES, endpoint=False)
    poses = np.repeat(recording.probe_to_base[:1], APPROACH_FRAMES, axis=0)
    poses[:, :3, 3] -= (APPROACH_MM - travelled)[:, None] * recording.probe_to_base[0, :3, 2]
    step_s = float(np.diff(recording.timestamps).mean())
    assert recording.force is not None and recording.probe_displacement is not None
    return Recording(
        frames=np.concatenate([np.zeros((APPROACH_FRAMES, *recording.shape), np.uint8), recording.frames]),
        timestamps=np.concatenate(
            [step_s * np.arange(APPROACH_FRAMES), recording.timestamps + APPROACH_FRAMES * step_s]
        ),
        probe_to_base=np.concatenate([poses, recording.probe_to_base]),
        pose_valid=np.ones(APPROACH_FRAMES + len(recording), dtype=bool),
        image_to_probe=recording.image_to_probe,
        force=np.concatenate([rng.normal(0.0, SENSOR_NOISE_N, APPROACH_FRAMES), recording.force]) + bias_n,
        probe_displacement=np.concatenate([travelled, recording.probe_displacement + APPROACH_MM]),
    )


@pytest.fixture(scope="module")
def palpations(tmp_path_factory):
    """Coarse-phantom palpations to 8 N: a 30-frame loading ramp, and 60 frames up, held 2 s and down,
    elastic and creeping (viscoelastic g 0.3, tau 2 s)."""
    from usdeform.sim import Viscoelasticity, coarse_phantom, simulate_palpation

    phantom = coarse_phantom()
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("USDEFORM_CACHE_DIR", str(tmp_path_factory.mktemp("usdeform-cache")))
        ramp, _ = simulate_palpation(phantom, 20.0, 8.0, n_frames=30, seed=11, rows=96, cols=96)
        held = {
            name: simulate_palpation(phantom, 20.0, 8.0, 60, "up-hold-down", 11, effects, 96, 96, hold_s=2.0)[0]
            for name, effects in (("elastic", ()), ("creeping", (Viscoelasticity(((0.3, 2.0),)),)))
        }
    return {"ramp": ramp, **held}


def test_a_loading_ramp_from_contact_is_fitted_exactly_as_recorded(palpations, small_palpation) -> None:
    for recording in (palpations["ramp"], small_palpation[0]):
        phases = detect_phases(recording, "ramp")
        assert phases.is_loading_ramp and phases.displacement_zero_mm == 0.0
        assert phases.loading_recording(recording) is recording
    recording = palpations["ramp"]
    fitted = fit_palpations([recording], LAYER_MM, method="paper")
    measured, sampled = measure_positions([recording], LAYER_MM, wall=FIT_METHODS["paper"].wall)
    today = fit_measured(measured, FIT_METHODS["paper"])
    assert np.array_equal(fitted.fit.fitted.coefficients, today.fitted.coefficients)
    assert fitted.sampled.profiles == sampled.profiles
    assert np.array_equal(fitted.sampled.positions_mm, sampled.positions_mm)
    assert fitted.provenance["palpation_phases"][0]["fitted_frames"] == [0, len(recording)]


@pytest.mark.parametrize("bias_n", [0.0, 2.0])
def test_an_approach_in_front_is_dropped_and_the_displacement_counted_from_contact(palpations, bias_n) -> None:
    ramp = palpations["ramp"]
    recording = with_approach(ramp, bias_n=bias_n)
    with pytest.raises(FitError, match="non-positive stiffness"):  # what fit did before: the whole palpation
        fit_stiffness(recording.force, recording.probe_displacement)
    phases = detect_phases(recording, "approached")
    # Contact: the last frame at the noise level, at most 3 frames into the ramp (its first frames in
    # contact carry less force than the noise threshold).
    assert APPROACH_FRAMES <= phases.contact_frame <= APPROACH_FRAMES + 3
    assert phases.approach == (0, phases.contact_frame) and phases.loading == (phases.contact_frame, len(recording))
    assert phases.baseline_force_n == pytest.approx(bias_n, abs=3 * SENSOR_NOISE_N)
    loading = phases.loading_recording(recording)
    assert loading.probe_displacement[0] == 0.0
    assert phases.displacement_zero_mm == pytest.approx(APPROACH_MM, abs=0.3)
    approached = fit_stiffness(loading.force, loading.probe_displacement).profile
    alone = fit_stiffness(ramp.force, ramp.probe_displacement).profile
    lam = np.linspace(0.5, ramp.probe_displacement.max(), 20)
    assert np.allclose(approached.stiffness_at(lam), alone.stiffness_at(lam), rtol=0.1)


@pytest.mark.parametrize("name", ["elastic", "creeping"])
def test_hold_and_unloading_are_not_fitted(palpations, name) -> None:
    recording = palpations[name]
    phases = detect_phases(recording, name)
    assert phases.approach == (0, 0) and phases.contact_frame == 0
    start, stop = phases.loading
    hold_start, hold_stop = phases.hold
    # 60 frames over 1.6 s up, 2 s held, 1.6 s down: the hold is about frames 18-41.
    assert stop == hold_start and 15 <= hold_start <= 20 and 38 <= hold_stop <= 44
    assert phases.unloading == (hold_stop, len(recording))
    force = recording.force
    assert np.all(force[start + 1 : stop] > force[start]) and force[stop - 1] > 0.85 * force.max()
    assert force[hold_stop:].max() < force.max() and force[-1] < 0.25 * force.max()
    loading = phases.loading_recording(recording)
    assert np.all(fit_stiffness(loading.force, loading.probe_displacement).stiffness_n_per_mm > 0)


def test_a_creeping_palpation_is_fitted_on_its_loading_ramp(palpations) -> None:
    recording = palpations["creeping"]
    fitted = fit_palpations([recording], LAYER_MM, names=["creep.seq.nrrd"], method="paper")
    stop = fitted.phases[0].loading[1]
    assert len(fitted.loading_recordings[0]) == stop
    assert np.array_equal(fitted.measured[0].stiffness.force_n, recording.force[:stop])
    described = fitted.provenance["palpation_phases"][0]
    assert described["name"] == "creep.seq.nrrd" and described["fitted_frames"] == [0, stop]
    assert described["hold"] == list(fitted.phases[0].hold)


def test_bad_palpations_are_refused_by_name_before_any_measurement(palpations, monkeypatch) -> None:
    import usdeform.fitting

    ramp = palpations["ramp"]
    rng = np.random.default_rng(5)
    flat = dataclasses.replace(ramp, force=rng.normal(0.0, SENSOR_NOISE_N, len(ramp)))
    unloading = dataclasses.replace(ramp, force=ramp.force[::-1].copy())
    no_force = dataclasses.replace(ramp, force=None)

    def measured(*args, **kwargs):
        raise AssertionError("a palpation was measured before every palpation's phases were checked")

    monkeypatch.setattr(usdeform.fitting, "measure_positions", measured)
    for bad, expected in (
        (flat, r"flat\.seq\.nrrd: no contact: the force never rises out of the sensor's noise"),
        (unloading, r"flat\.seq\.nrrd: no loading ramp: the force is highest at frame 0"),
        (no_force, r"flat\.seq\.nrrd: a palpation needs per-frame ContactForce"),
    ):
        with pytest.raises(InputError, match=expected):
            fit_palpations([ramp, bad], LAYER_MM, names=["good.seq.nrrd", "flat.seq.nrrd"])


def test_a_short_ramp_is_no_loading_ramp(palpations) -> None:
    ramp = palpations["ramp"]
    # Three frames of rising force, then held: too few frames for the stiffness fit, with and without an approach.
    held = np.minimum(np.arange(len(ramp), dtype=float), 3.0)
    with pytest.raises(InputError, match=r"short: no loading ramp: the force is highest at frame 3 \(3 N\)"):
        detect_phases(dataclasses.replace(ramp, force=held), "short")
    approached = with_approach(ramp)
    force = approached.force.copy()
    force[APPROACH_FRAMES:] = held
    with pytest.raises(
        InputError, match=rf"short: no loading ramp: 3 frame\(s\) from contact \(frame {APPROACH_FRAMES}\)"
    ):
        detect_phases(dataclasses.replace(approached, force=force), "short")


def test_fit_command_reports_the_phases_and_writes_them_to_the_model(palpations, tmp_path, capsys) -> None:
    path = tmp_path / "approached.seq.nrrd"
    write_sequence(path, with_approach(palpations["ramp"]))
    model, report = tmp_path / "model.json", tmp_path / "report"
    assert main(["fit", str(path), "--flexible-layer-mm", "50", "--method", "paper", "--output", str(model),
                 "--report", str(report)]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert f"{path}: approach 0-" in out and "fitted on the loading ramp (frames" in out
    assert "probe displacement re-zeroed there" in out
    (phases,) = json.loads(model.read_text())["provenance"]["palpation_phases"]
    assert phases["approach"] == [0, phases["contact_frame"]] and phases["contact_frame"] >= APPROACH_FRAMES
    assert json.loads((report / "report.json").read_text())["palpation_phases"] == [phases]
    assert "Palpation phases" in (report / "report.html").read_text()
