"""What the diagnosis hands the user: sections left out or re-solved, unidentified parameters, the force sensor on a
known weight (diagnosis.json, report.html, record_next.json), and the options that feed it."""

import json

import pytest

from usdeform.errors import InputError
from usdeform.gap.diagnosis import Diagnosis
from usdeform.gap.diagnosis_file import check_diagnosis
from usdeform.gap.follow_up import FirstProtocol, plan_follow_up
from usdeform.gap.verdicts import CandidateResult

FIRST = FirstProtocol(position_mm=12.0, max_force_n=12.0, ramp_speed_mm_s=1.5, hold_s=0.0, count=2)


def _sensor_candidate() -> CandidateResult:
    return CandidateResult(
        "force_sensor_error",
        {"offset_n": 1.98, "drift_n_per_s": 0.0},
        {"offset_n": 0.05, "drift_n_per_s": 0.2},
        2.0,
        0.2,
        0.9,
        (0.8, 0.95),
        True,
        0.2,
        1,
        unidentified={"drift_n_per_s": "hold"},
    )


def _diagnosis() -> Diagnosis:
    return Diagnosis(
        verdict="explained",
        summary="s",
        effects=[_sensor_candidate()],
        measures=[],
        calibration=[],
        gap_before=2.0,
        critical_z=3.0,
        named=["force_sensor_error"],
        unsolved_sections=[{"recording": "a", "section": "stiff_layer", "error": "Newton failed", "effect": "x"}],
        resolved_sections=[{"recording": "a", "section": "base", "how": "finer steps"}],
        sensor_calibration=[
            {
                "recording": "w.seq.nrrd",
                "gain_error": 0.04,
                "gain_error_uncertainty": 0.002,
                "offset_n": 0.8,
                "offset_uncertainty_n": 0.01,
                "drift_n_per_s": None,
                "drift_uncertainty_n_per_s": None,
                "frames": 112,
            }
        ],
    )


def test_the_new_keys_reach_diagnosis_json_and_are_checked_by_the_reader():
    document = json.loads(json.dumps(_diagnosis().to_json()))
    assert document["effects"][0]["unidentified"] == {"drift_n_per_s": "hold"}
    assert document["unsolved_sections"][0]["section"] == "stiff_layer"
    assert document["resolved_sections"][0]["how"] == "finer steps"
    assert document["sensor_calibration"][0]["gain_error"] == 0.04
    assert check_diagnosis(document, "d.json") is document
    bad = json.loads(json.dumps(document))
    bad["effects"][0]["unidentified"] = {"drift_n_per_s": "weigh it"}
    with pytest.raises(InputError, match=r"effects\[0\].unidentified.drift_n_per_s: expected a recording kind"):
        check_diagnosis(bad, "d.json")
    bad["effects"][0]["unidentified"] = {"delay_s": "hold"}
    with pytest.raises(InputError, match=r"unidentified\.delay_s: no such parameter"):
        check_diagnosis(bad, "d.json")
    bad = json.loads(json.dumps(document))
    del bad["unsolved_sections"][0]["error"]
    with pytest.raises(InputError, match=r"unsolved_sections\[0\]: no error"):
        check_diagnosis(bad, "d.json")
    bad = json.loads(json.dumps(document))
    bad["sensor_calibration"][0]["gain_error_uncertainty"] = -1.0
    with pytest.raises(InputError, match=r"sensor_calibration\[0\].gain_error_uncertainty"):
        check_diagnosis(bad, "d.json")


def test_the_report_shows_the_sections_the_unidentified_drift_and_the_known_weight(tmp_path):
    from usdeform.gap.report import write_report

    write_report(_diagnosis(), tmp_path)
    page = (tmp_path / "report.html").read_text()
    assert "stiff_layer" in page and "finer steps" in page and "Newton failed" in page
    assert "drift_n_per_s: a hold recording" in page
    assert "Force sensor on a known weight" in page and "w.seq.nrrd" in page
    plan = json.loads((tmp_path / "record_next.json").read_text())["recordings"]
    assert plan == []  # the Diagnosis was built by hand: follow_up is what diagnose plans


def test_an_unidentified_parameter_asks_for_the_recording_it_names_whatever_the_verdict():
    explained = plan_follow_up("explained", [_sensor_candidate()], [], FIRST, ["force_sensor_error"])
    assert [(entry.kind, entry.reveals) for entry in explained] == [("hold", ["force_sensor_error"])]
    assert explained[0].hold_s >= 5.0
    clean = CandidateResult(
        "force_sensor_error", {"offset_n": 1.0}, {"offset_n": 0.1}, 2, 0.2, 0.9, (0.8, 1), True, 0, 1
    )
    assert plan_follow_up("explained", [clean], [], FIRST, ["force_sensor_error"]) == []
    edge = plan_follow_up("at_edge_of_library", [_sensor_candidate()], [], FIRST)
    assert {entry.kind for entry in edge} == {"hold", "known_weight"}


def test_the_summary_names_what_the_recordings_could_not_identify():
    from usdeform.gap.diagnosis import _unidentified_sentence

    text = _unidentified_sentence([_sensor_candidate()], ["force_sensor_error"])
    assert "drift_n_per_s of force_sensor_error (a hold recording would identify it)" in text
    assert _unidentified_sentence([_sensor_candidate()], []) == text  # the best candidate without a naming


def test_known_weight_files_go_to_the_calibration_not_the_palpations(palpation, tmp_path, write_known_weight):
    from usdeform.gap.inputs import as_recordings
    from usdeform.io import write_sequence

    write_sequence(tmp_path / "a_palpation.seq.nrrd", palpation())
    write_known_weight(tmp_path / "b_known_weight.seq.nrrd")
    named, sweeps, known = as_recordings([tmp_path])
    assert [name for name, _ in named] == [str(tmp_path / "a_palpation.seq.nrrd")] and sweeps == []
    assert known == [tmp_path / "b_known_weight.seq.nrrd"]
    with pytest.raises(InputError, match="at least one palpation"):
        as_recordings([tmp_path / "b_known_weight.seq.nrrd"])


@pytest.mark.parametrize("value", ["0.5", "301", "nan", "deep"])
def test_reference_depth_option_is_checked_against_its_physical_range(value, tmp_path, capsys):
    from usdeform.cli import main

    with pytest.raises(SystemExit) as exit:
        main(["diagnose", str(tmp_path / "a.seq.nrrd"), "--out", str(tmp_path / "o"), "--reference-depth-mm", value])
    assert exit.value.code == 2 and "--reference-depth-mm" in capsys.readouterr().err


def test_the_simulated_reference_target_over_the_base_carries_its_depth(gap_phantom):
    from usdeform.gap.follow_up_sim import FollowUpSettings, simulate_follow_up

    sound = CandidateResult("sound_speed_mismatch", {}, {}, 2, 0.2, 0.9, (0.8, 1), True, 0, 1)
    entry = plan_follow_up("at_edge_of_library", [sound], [], FIRST)
    entry = [item for item in entry if item.kind == "reference_target"]
    assert entry and entry[0].reference_depth_mm is None
    recorded = simulate_follow_up(entry, gap_phantom, None, FollowUpSettings(frames_per_s=3.0, rows=48, cols=48))
    depth = float(recorded[0].recording.metadata["ReferenceTargetDepth"])
    assert depth == pytest.approx(gap_phantom.section_at(12.0).depth_mm, abs=1e-3)


def test_the_summary_gives_the_sensor_on_a_known_weight():
    from usdeform.gap.diagnosis import _sensor_sentence

    calibration = _diagnosis().sensor_calibration
    text = _sensor_sentence(calibration, ["lumen_pressure"])
    assert "gain error 0.04 +/- 0.002 and offset 0.8 +/- 0.01 N (w.seq.nrrd)" in text
    assert "a sensor error, which the palpations show too: explanations without it are ruled out" in text
    assert "ruled out (lumen_pressure)" in text
    assert "which the palpations do not show: it rules no explanation out" in _sensor_sentence(calibration, [])
    assert _sensor_sentence([], []) == ""
