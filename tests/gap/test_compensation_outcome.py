"""What the named effect costs the correction and what compensating it gives back (diagnosis.json's
``compensation``), on simulated palpations with hand-written diagnoses."""

import dataclasses

import numpy as np
import pytest

from usdeform.gap.correction_outcome import compensation_outcome
from usdeform.gap.observations import observe
from usdeform.sim import ForceSensorError, ImageLatency


@pytest.fixture(scope="module")
def biased(palpation):
    recording = palpation([ForceSensorError(bias_n=2.0)])
    return observe(recording, "palpation"), recording


def _diagnosis(effect, parameters, verdict="explained", significant=True):
    return {
        "verdict": verdict,
        "named": [effect],
        "effects": [{"effect": effect, "parameters": parameters, "uncertainty": {}, "significant": significant}],
    }


KEYS = ("dice_uncompensated", "dice_compensated", "area_error_pct_uncompensated", "area_error_pct_compensated")


def test_a_supported_compensation_is_measured_on_each_recording(biased):
    observation, recording = biased
    entry = compensation_outcome(
        [observation], [recording], _diagnosis("force_sensor_error", {"offset_n": 2.0, "drift_n_per_s": 0.0})
    )
    assert entry["supported"] and entry["refusal"] == ""
    assert entry["effects"] == {"force_sensor_error": {"offset_n": 2.0, "drift_n_per_s": 0.0}}
    (row,) = entry["recordings"]
    assert row["recording"] == "palpation" and all(np.isfinite(row[key]) for key in KEYS)
    assert 0.5 < row["dice_compensated"] <= 1
    assert entry["summary"].startswith("Compensation of force_sensor_error at its fitted size (--compensate ")
    assert f"Dice {row['dice_compensated']:.3f}" in entry["summary"]


def test_a_compensation_that_changes_nothing_says_so_and_scores_the_same(biased):
    observation, recording = biased
    entry = compensation_outcome(
        [observation], [recording], _diagnosis("force_sensor_error", {"offset_n": 0.0, "drift_n_per_s": 0.0})
    )
    (row,) = entry["recordings"]
    assert row["dice_compensated"] == row["dice_uncompensated"]
    assert row["area_error_pct_compensated"] == row["area_error_pct_uncompensated"]
    assert "costs this correction less than that" in entry["summary"]


def test_an_unsupported_compensation_is_measured_as_forced_and_says_why(biased):
    observation, recording = biased
    diagnosis = _diagnosis("force_sensor_error", {"offset_n": 2.0, "drift_n_per_s": 0.0}, verdict="at_edge_of_library")
    entry = compensation_outcome([observation], [recording], diagnosis)
    supported = compensation_outcome(
        [observation], [recording], _diagnosis("force_sensor_error", {"offset_n": 2.0, "drift_n_per_s": 0.0})
    )
    assert not entry["supported"] and "at_edge_of_library" in entry["refusal"]
    assert entry["recordings"] == supported["recordings"]
    assert "--force-compensation, as the diagnosis does not support it" in entry["summary"]


def test_a_sound_speed_compensation_rescales_the_area_and_leaves_the_overlap(palpation):
    recording = palpation()
    observation = observe(recording, "palpation")
    entry = compensation_outcome([observation], [recording], _diagnosis("sound_speed_mismatch", {"error_m_s": 60.0}))
    (row,) = entry["recordings"]
    assert row["dice_compensated"] == row["dice_uncompensated"]  # the same frames, forces and pixels
    # the same corrected lumen, its rows 1600 / 1540 times deeper than displayed: area ratio to the reference
    ratio = 1 + row["area_error_pct_compensated"] / 100
    expected = 100 * ratio * (1 - 1540 / 1600)
    assert row["area_error_pct_compensated"] - row["area_error_pct_uncompensated"] == pytest.approx(expected)


def test_a_re_pairing_that_drops_frames_is_measured_on_the_frames_kept(palpation):
    recording = palpation([ImageLatency(0.1)])
    observation = observe(recording, "palpation")
    entry = compensation_outcome([observation], [recording], _diagnosis("image_latency", {"delay_s": 0.1}))
    (row,) = entry["recordings"]
    assert all(np.isfinite(row[key]) for key in KEYS)


@pytest.mark.parametrize(
    ("diagnosis", "said"),
    [
        ({"verdict": "no_significant_gap", "named": [], "effects": []}, "there is nothing to compensate"),
        (_diagnosis("layered_tissue", {"ratio": 0.3}), "layered_tissue: an effect of the tissue itself"),
        (
            {
                "verdict": "ambiguous",
                "named": ["force_sensor_error", "viscoelasticity"],
                "effects": [
                    {"effect": "force_sensor_error", "parameters": {"offset_n": 1.0, "drift_n_per_s": 0.0}},
                    {"effect": "viscoelasticity", "parameters": {"g": 0.2, "tau_s": 1.0}},
                ],
            },
            "verdict 'ambiguous'",
        ),
    ],
)
def test_no_compensation_is_measured_where_none_applies_and_the_line_says_why(biased, diagnosis, said):
    observation, recording = biased
    entry = compensation_outcome([observation], [recording], diagnosis)
    assert entry["recordings"] == [] and entry["effects"] == {} and not entry["supported"]
    assert entry["summary"].startswith("Compensation") and said in entry["summary"]


def test_a_recording_without_a_lumen_to_score_is_reported_not_measured(biased):
    observation, recording = biased
    blank = dataclasses.replace(observation, reference_frame=np.full_like(observation.reference_frame, 128))
    entry = compensation_outcome(
        [blank], [recording], _diagnosis("force_sensor_error", {"offset_n": 2.0, "drift_n_per_s": 0.0})
    )
    (row,) = entry["recordings"]
    assert not any(key in row for key in KEYS) and "anechoic" in row["error"]
    assert entry["summary"] == (
        "Compensation of force_sensor_error: not measured (no recording has a lumen to score, or a fit failed)."
    )
