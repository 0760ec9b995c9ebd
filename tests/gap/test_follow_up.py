"""The follow-up protocol: record_next.json planned from a diagnosis, read back, recorded on the simulator, and a
second diagnosis on all the recordings."""

import json

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.gap.detectability import GAIN_PROTOCOL, GAIN_REASON, ProtocolAdvice
from usdeform.gap.follow_up import (
    KINDS,
    FirstProtocol,
    FollowUpRecording,
    first_recordings,
    plan_follow_up,
    read_record_next,
    write_record_next,
)
from usdeform.gap.verdicts import CandidateResult

FIRST = FirstProtocol(position_mm=12.0, max_force_n=12.0, ramp_speed_mm_s=1.5, hold_s=2.0, count=2)
GAIN = ProtocolAdvice("force_sensor_error", GAIN_REASON, None, GAIN_PROTOCOL)


def _candidate(effect: str) -> CandidateResult:
    return CandidateResult(effect, {}, {}, 1.0, 0.5, 0.5, (0.2, 0.8), False, 0.5, 1)


def test_an_ambiguity_between_creep_and_a_late_force_stream_asks_for_a_hold_and_a_faster_ramp():
    advice = [
        ProtocolAdvice("viscoelasticity", "ambiguous with force_latency", None, ""),
        ProtocolAdvice("force_latency", "ambiguous with viscoelasticity", None, ""),
        ProtocolAdvice("sound_speed_mismatch", "undetectable", None, ""),  # not what the ambiguity is about
        GAIN,
    ]
    plan = plan_follow_up("ambiguous", [_candidate("viscoelasticity")], advice, FIRST)
    assert [entry.kind for entry in plan] == ["hold", "ramp_speed"]
    hold, ramp = plan
    assert hold.reveals == ["force_latency", "viscoelasticity"] and hold.hold_s >= 5.0
    assert ramp.reveals == ["force_latency"] and ramp.ramp_speed_mm_s == pytest.approx(3 * 1.5)
    assert hold.position_mm == ramp.position_mm == 12.0 and hold.max_force_n == 12.0
    assert [entry.name for entry in plan] == ["follow_up_01_hold", "follow_up_02_ramp_speed"]


def test_no_gap_asks_for_what_palpations_cannot_show_and_repeats_for_small_effects():
    advice = [
        ProtocolAdvice("sound_speed_mismatch", "undetectable", None, ""),
        ProtocolAdvice("sliding_contact", "undetectable", None, ""),
        ProtocolAdvice("lumen_pressure", "undetectable", 3, ""),  # three times these palpations would show it
        GAIN,
    ]
    plan = plan_follow_up("no_significant_gap", [_candidate("probe_tilt")], advice, FIRST)
    kinds = [entry.kind for entry in plan]
    # 3 x 2 palpations: 4 more, of which position, tilt and reference_target are three; one plain palpation
    assert kinds == ["palpation", "position", "tilt", "reference_target", "known_weight"]
    by_kind = {entry.kind: entry for entry in plan}
    assert by_kind["reference_target"].reveals == ["lumen_pressure", "sound_speed_mismatch"]
    assert by_kind["known_weight"].reveals == ["force_sensor_error"] and by_kind["known_weight"].known_weight_n == 12
    assert by_kind["tilt"].tilt_deg == 5.0 and by_kind["position"].position_mm == 22.0
    assert all(entry.kind in KINDS for entry in plan)


def test_a_clean_verdict_asks_for_nothing_and_an_edge_asks_for_the_effects_own_recording():
    assert plan_follow_up("explained", [_candidate("image_latency")], [GAIN], FIRST) == []
    # an unexplained gap: the best candidate's own recording, and the speed of sound's, which no palpation shows
    sound = ProtocolAdvice("sound_speed_mismatch", "undetectable", None, "")
    lumen = ProtocolAdvice("lumen_pressure", "undetectable", 3, "")
    plan = plan_follow_up("unexplained", [_candidate("image_latency")], [GAIN, sound, lumen], FIRST)
    assert [(entry.kind, entry.reveals) for entry in plan] == [
        ("ramp_speed", ["image_latency"]),
        ("reference_target", ["sound_speed_mismatch"]),
    ]
    (entry,) = plan_follow_up("at_edge_of_library", [_candidate("sound_speed_mismatch")], [GAIN], FIRST)
    assert entry.kind == "reference_target" and entry.reveals == ["sound_speed_mismatch"]


def test_record_next_round_trips_and_bad_fields_are_refused_by_file_and_field(tmp_path):
    advice = [ProtocolAdvice("image_latency", "ambiguous with force_latency", None, "")]
    plan = plan_follow_up("ambiguous", [_candidate("image_latency")], advice, FIRST)
    path = tmp_path / "record_next.json"
    write_record_next(path, plan)
    document = json.loads(path.read_text())
    assert document["format"] == "usdeform.record_next" and document["version"] == 1
    assert read_record_next(path) == plan
    good = path.read_text()
    for field, value, message in [
        ("kind", "dance", "kind: expected one of"),
        ("max_force_n", -3.0, "max_force_n: -3.0 is outside"),
        ("hold_s", "long", "hold_s: expected a number"),
        ("tilt_deg", float("nan"), "tilt_deg: expected a number"),
        ("name", "../escape", "name: expected a file stem"),
    ]:
        broken = json.loads(good)
        broken["recordings"][0][field] = value
        path.write_text(json.dumps(broken))
        with pytest.raises(InputError, match=rf"record_next.json: recordings\[0\]: {message}"):
            read_record_next(path)
    path.write_text("{")
    with pytest.raises(InputError, match="not a readable JSON file"):
        read_record_next(path)


def test_follow_up_folder_without_a_diagnosis_is_refused(tmp_path):
    with pytest.raises(InputError, match="is not a folder"):
        first_recordings(tmp_path / "missing")
    (tmp_path / "diagnosis.json").write_text(json.dumps({"verdict": "explained", "recordings": [str(tmp_path / "x")]}))
    with pytest.raises(InputError, match="no longer exists"):
        first_recordings(tmp_path)


def test_the_simulator_records_the_ramp_speed_hold_and_tilt_asked_for(gap_phantom):
    from usdeform.gap.follow_up_sim import FollowUpSettings, simulate_follow_up

    advice = [ProtocolAdvice("probe_tilt", "undetectable", None, "")]
    first = FirstProtocol(position_mm=10.0, max_force_n=8.0, ramp_speed_mm_s=2.0, hold_s=1.0, count=1)
    plan = plan_follow_up("no_significant_gap", [_candidate("image_latency")], advice, first)
    settings = FollowUpSettings(frames_per_s=5.0, rows=48, cols=48, seed=2)
    recorded = {item.entry.kind: item for item in simulate_follow_up(plan, gap_phantom, None, settings)}
    assert set(recorded) == {"ramp_speed", "tilt", "known_weight"}
    ramp = recorded["ramp_speed"].recording
    lam, time = ramp.probe_displacement, ramp.timestamps
    top = int(np.argmax(lam >= 0.9 * lam.max()))  # the end of the loading ramp, before the hold
    speed = (lam[top] - lam[0]) / (time[top] - time[0])
    assert speed == pytest.approx(6.0, rel=0.3)  # 3 x 2 mm/s (the force loop lags a fast ramp a little)
    tilted = recorded["tilt"].recording
    axis = tilted.probe_to_base[tilted.pose_valid][0][:3, 2]
    assert np.degrees(np.arccos(abs(axis[2]))) == pytest.approx(5.0, abs=0.5)  # the pose records the tilt
    weight = recorded["known_weight"]
    assert not weight.recording.frames.any() and weight.recording.force is not None
    assert weight.frame_series["KnownLoad"].max() == pytest.approx(plan[-1].known_weight_n, rel=1e-3)


def test_a_simulated_known_weight_shows_the_sensor_error_of_the_effects(gap_phantom, tmp_path):
    """The known weight the simulator records reads the load through the effects' sensor error: the calibration
    of its file gives back the offset (bias less the probe's uncompensated weight), the drift and the gain."""
    from usdeform.gap.follow_up_sim import FollowUpSettings, record_follow_up
    from usdeform.gap.sensor_calibration import known_weight_calibration, sensor_finding
    from usdeform.sim import ForceSensorError

    entry = FollowUpRecording(
        "follow_up_01_known_weight", "known_weight", 10.0, 8.0, 2.0, 0.0, 0.0, None, 10.0, ["force_sensor_error"], ""
    )
    sensor = ForceSensorError(bias_n=0.7, drift_n_per_s=0.02, uncompensated_weight_n=0.3, gain_error=0.05)
    settings = FollowUpSettings(frames_per_s=20.0, rows=32, cols=32, seed=4)
    ((_, path),) = record_follow_up([entry], tmp_path, gap_phantom, [sensor], settings)
    fitted = known_weight_calibration(path)
    assert fitted.offset_n == pytest.approx(0.4, abs=3 * fitted.offset_uncertainty_n + 0.02)
    assert fitted.gain_error == pytest.approx(0.05, abs=3 * fitted.gain_error_uncertainty + 0.005)
    assert fitted.drift_n_per_s == pytest.approx(0.02, abs=3 * fitted.drift_uncertainty_n_per_s + 0.002)
    assert sensor_finding([fitted.to_json()]) == "error"
    ((_, clean),) = record_follow_up([entry], tmp_path / "clean", gap_phantom, None, settings)
    assert sensor_finding([known_weight_calibration(clean).to_json()]) == "clean"


@pytest.mark.slow
def test_two_rounds_of_diagnosis_from_the_command_line(gap_phantom, tmp_path, capsys):
    """One short palpation with 15 % creep (1 s hold, 60 frames of 128 x 128): round 0 cannot tell it from a late
    force stream; what its record_next.json asks for is recorded on the simulator and round 1 (--follow-up) decides
    on all of it, naming creep. A round 0 that names creep at once asks for nothing."""
    from usdeform.cli import main
    from usdeform.gap.follow_up_sim import FollowUpSettings, record_follow_up
    from usdeform.io import write_sequence
    from usdeform.sim import Viscoelasticity, simulate_palpation

    effects = [Viscoelasticity(((0.15, 1.0),))]
    recording, _ = simulate_palpation(gap_phantom, 10.0, 12.0, 60, "up-hold-down", 3, effects, 128, 128, hold_s=1.0)
    first = tmp_path / "first.seq.nrrd"
    write_sequence(first, recording)
    assert main(["diagnose", str(first), "--out", str(tmp_path / "round0")]) == 0
    round0 = json.loads((tmp_path / "round0" / "diagnosis.json").read_text())
    assert round0["recordings"] == [str(first.resolve())]
    plan = read_record_next(tmp_path / "round0" / "record_next.json")
    assert (plan != []) == (round0["verdict"] in ("no_significant_gap", "ambiguous", "at_edge_of_library"))
    if not plan:
        assert round0["named"] == ["viscoelasticity"]
        return
    assert "Record next" in (tmp_path / "round0" / "report.html").read_text()
    settings = FollowUpSettings(frames_per_s=12.0, rows=128, cols=128, seed=1)
    written = record_follow_up(plan, tmp_path / "new", gap_phantom, effects, settings)
    new = [str(path) for _, path in written if path is not None]
    arguments = ["diagnose", *new, "--follow-up", str(tmp_path / "round0"), "--out", str(tmp_path / "round1")]
    assert main(arguments) == 0
    round1 = json.loads((tmp_path / "round1" / "diagnosis.json").read_text())
    assert round1["recordings"] == [str(first.resolve()), *[str(type(first)(path).resolve()) for path in new]]
    assert round1["verdict"] in ("explained", "explained_in_part") and round1["named"] == ["viscoelasticity"]
    assert "wrote" in capsys.readouterr().out


def test_a_follow_up_recording_that_fails_to_write_leaves_none_of_them(gap_phantom, tmp_path, monkeypatch):
    """The recordings of a protocol are written together: when the second cannot be written, the first is not left
    behind, and neither is the folder the run made."""
    from usdeform.gap import follow_up_sim

    advice = [ProtocolAdvice("probe_tilt", "undetectable", None, "")]
    first = FirstProtocol(position_mm=10.0, max_force_n=8.0, ramp_speed_mm_s=2.0, hold_s=0.0, count=1)
    plan = plan_follow_up("no_significant_gap", [_candidate("image_latency")], advice, first)
    written, write = [], follow_up_sim.write_sequence

    def second_fails(path, recording, **options):
        if written:
            raise OSError(28, "No space left on device", str(path))
        write(path, recording, **options)
        written.append(path)

    monkeypatch.setattr(follow_up_sim, "write_sequence", second_fails)
    settings = follow_up_sim.FollowUpSettings(frames_per_s=5.0, rows=48, cols=48, seed=2)
    with pytest.raises(OSError, match="No space left"):
        follow_up_sim.record_follow_up(plan, tmp_path / "new" / "round1", gap_phantom, None, settings)
    assert written and not (tmp_path / "new").exists()
