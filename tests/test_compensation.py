"""Compensation of diagnosed recording effects (usdeform.compensation; fit/correct --compensate, issue 42)."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from usdeform.cli import main
from usdeform.compensation import ASSUMED_SOUND_SPEED_M_S, NOT_COMPENSATED, read_compensation
from usdeform.errors import InputError
from usdeform.io import load_model, write_sequence
from usdeform.recording import Recording


def _diagnosis(folder: Path, verdict: str, effect: str, parameters: dict, significant: bool = True) -> Path:
    """A diagnosis.json of the contract of usdeform.gap with one effect."""
    path = folder / f"{verdict}-{effect}.json"
    named = [effect] if verdict in ("explained", "explained_in_part", "at_edge_of_library") else []
    document = {
        "verdict": verdict,
        "named": named,
        "summary": "",
        "effects": [
            {
                "effect": effect,
                "parameters": parameters,
                "uncertainty": {key: 0.01 for key in parameters},
                "significant": significant,
            }
        ],
    }
    path.write_text(json.dumps(document))
    return path


@pytest.fixture(scope="module")
def delayed(tmp_path_factory):
    """A coarse-phantom palpation imaged 0.1 s late, and its ground truth."""
    from usdeform.sim import ImageLatency, coarse_phantom, simulate_palpation

    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("USDEFORM_CACHE_DIR", str(tmp_path_factory.mktemp("usdeform-cache")))
        return simulate_palpation(
            coarse_phantom(), 20.0, 8.0, 40, "up-down", 3, [ImageLatency(image_delay_s=0.1)], 48, 48
        )


def test_image_delay_re_pairs_frames_with_their_acquisition_time(delayed, tmp_path) -> None:
    recording, truth = delayed
    compensation = read_compensation(_diagnosis(tmp_path, "explained", "image_latency", {"delay_s": 0.1}))
    assert not compensation.forced and compensation.uncertainty == {"image_latency": {"delay_s": 0.01}}
    compensated, note = compensation.apply(recording, "delayed.seq.nrrd")
    kept = np.flatnonzero(recording.timestamps - 0.1 >= recording.timestamps[0])
    assert len(compensated) == kept.size and "delayed.seq.nrrd: compensated: frames re-paired" in note
    assert np.array_equal(compensated.frames, recording.frames[kept])
    before = np.abs(recording.force[kept] - truth.force_n[kept])
    after = np.abs(compensated.force - truth.force_n[kept])
    assert after.mean() < 0.3 * before.mean()
    lam_error = np.abs(compensated.probe_displacement - truth.probe_displacement_mm[kept])
    assert (
        lam_error.mean() < 0.3 * np.abs(recording.probe_displacement[kept] - truth.probe_displacement_mm[kept]).mean()
    )


def test_force_sensor_offset_and_drift_are_subtracted(small_palpation, tmp_path) -> None:
    recording, _ = small_palpation
    elapsed = recording.timestamps - recording.timestamps[0]
    biased = dataclasses.replace(recording, force=recording.force + 2.0 + 0.05 * elapsed)
    parameters = {"offset_n": 2.0, "drift_n_per_s": 0.05}
    compensation = read_compensation(_diagnosis(tmp_path, "explained", "force_sensor_error", parameters))
    compensated, note = compensation.apply(biased)
    assert np.allclose(compensated.force, recording.force, atol=1e-12)
    assert "offset 2 N and drift 0.05 N/s subtracted" in note


def test_viscoelastic_force_is_replaced_by_the_elastic_force_its_history_implies(tmp_path) -> None:
    from usdeform.gap.linear_fits import qlv  # the diagnosis's relaxation model, which the compensation inverts

    rng = np.random.default_rng(2)
    times = np.cumsum(rng.uniform(0.02, 0.2, 60))
    elastic = np.concatenate([np.linspace(0.0, 12.0, 25), np.full(20, 12.0), np.linspace(12.0, 1.0, 15)])
    recording = Recording(
        frames=np.zeros((60, 4, 4), np.uint8),
        timestamps=times,
        probe_to_base=np.tile(np.eye(4), (60, 1, 1)),
        pose_valid=np.ones(60, dtype=bool),
        image_to_probe=np.diag([0.1, 0.1, 0.1, 1.0]),
        force=qlv(elastic, times, 0.3, 2.0),
        probe_displacement=np.zeros(60),
    )
    compensation = read_compensation(_diagnosis(tmp_path, "explained", "viscoelasticity", {"g": 0.3, "tau_s": 2.0}))
    compensated, note = compensation.apply(recording)
    assert np.allclose(compensated.force, elastic, atol=1e-9)
    assert "elastic force its history implies (relaxation g 0.3, tau 2 s)" in note


def test_sound_speed_mismatch_rescales_the_depth_axis(small_palpation, tmp_path) -> None:
    recording, _ = small_palpation
    compensation = read_compensation(_diagnosis(tmp_path, "explained", "sound_speed_mismatch", {"error_m_s": 40.0}))
    compensated, _ = compensation.apply(recording)
    scale = (ASSUMED_SOUND_SPEED_M_S + 40.0) / ASSUMED_SOUND_SPEED_M_S
    assert np.allclose(compensated.image_to_probe[:3, 1], recording.image_to_probe[:3, 1] * scale)
    assert np.array_equal(compensated.image_to_probe[:, [0, 2, 3]], recording.image_to_probe[:, [0, 2, 3]])


@pytest.mark.parametrize(
    ("verdict", "significant", "expected"),
    [
        ("at_edge_of_library", True, r"verdict 'at_edge_of_library', not 'explained' or 'explained_in_part'"),
        ("explained", False, r"image_latency not significant"),
        ("explained_in_part", False, r"image_latency not significant"),
        (
            "no_significant_gap",
            False,
            r"verdict 'no_significant_gap', not 'explained' or 'explained_in_part'; it names no effect",
        ),
    ],
)
def test_unsupported_compensations_are_refused_unless_forced(tmp_path, verdict, significant, expected) -> None:
    path = _diagnosis(tmp_path, verdict, "image_latency", {"delay_s": 0.05}, significant)
    with pytest.raises(
        InputError, match=rf"does not support compensating image_latency \({expected}.*--force-compensation"
    ):
        read_compensation(path)
    forced = read_compensation(path, force=True)
    assert forced.forced and forced.effects == {"image_latency": {"delay_s": 0.05}}


def test_an_effect_explained_in_part_is_compensated_and_the_note_says_a_residual_remains(
    tmp_path, small_palpation
) -> None:
    recording, _ = small_palpation
    compensation = read_compensation(
        _diagnosis(tmp_path, "explained_in_part", "force_sensor_error", {"offset_n": 0.5, "drift_n_per_s": 0.0})
    )
    assert not compensation.forced and compensation.verdict == "explained_in_part"
    compensated, note = compensation.apply(recording, "p.mha")
    assert np.allclose(compensated.force, recording.force - 0.5)
    assert note.startswith("p.mha: compensated (the diagnosis explains the gap only in part: a residual it cannot")


@pytest.mark.parametrize(
    ("effect", "parameters", "expected"),
    [
        ("lumen_pressure", {"pressure_kpa": 4.0}, "lumen_pressure: an effect of the tissue itself, which changes no"),
        ("probe_tilt", {"tilt_deg": 5.0}, "probe_tilt: not compensated here"),
    ],
)
def test_effects_no_recording_compensation_undoes_are_refused_even_forced(
    tmp_path, effect, parameters, expected
) -> None:
    with pytest.raises(InputError, match=expected):
        read_compensation(_diagnosis(tmp_path, "explained", effect, parameters), force=True)


def test_a_pair_undoes_its_recording_member_and_says_the_tissue_member_is_not_undone(tmp_path, small_palpation):
    recording, _ = small_palpation
    parameters = {"offset_n": 0.7, "drift_n_per_s": 0.0, "thickness_mm": 9.6, "modulus_ratio": 0.8}
    compensation = read_compensation(_diagnosis(tmp_path, "explained", "force_sensor_error+layered_tissue", parameters))
    assert compensation.effects == {"force_sensor_error": {"offset_n": 0.7, "drift_n_per_s": 0.0}}
    assert compensation.not_undone == {"layered_tissue": NOT_COMPENSATED["layered_tissue"]}
    assert compensation.to_json()["not_undone"] == compensation.not_undone
    compensated, note = compensation.apply(recording, "p.mha")
    assert np.allclose(compensated.force, recording.force - 0.7)
    assert note.endswith("; layered_tissue not undone (" + NOT_COMPENSATED["layered_tissue"] + ")")
    both = {"thickness_mm": 9.6, "modulus_ratio": 0.8, "pressure_kpa": 3.0}
    refusal = r"layered_tissue: an effect of the tissue itself.*; lumen_pressure: an effect"
    with pytest.raises(InputError, match=refusal):
        read_compensation(_diagnosis(tmp_path, "explained", "layered_tissue+lumen_pressure", both), force=True)


def test_a_file_that_is_no_diagnosis_is_refused(tmp_path) -> None:
    (tmp_path / "other.json").write_text('{"format": "usdeform-model"}')
    with pytest.raises(InputError, match=r"other\.json: not a diagnosis\.json"):
        read_compensation(tmp_path / "other.json")
    with pytest.raises(InputError, match=r"missing\.json: not a readable diagnosis\.json"):
        read_compensation(tmp_path / "missing.json")


def test_fit_and_correct_compensate_and_refuse_from_the_command_line(small_palpation, tmp_path, capsys) -> None:
    recording, _ = small_palpation
    elapsed = recording.timestamps - recording.timestamps[0]
    palpation = tmp_path / "biased.seq.nrrd"
    write_sequence(palpation, dataclasses.replace(recording, force=recording.force + 1.5 + 0.02 * elapsed))
    supported = _diagnosis(tmp_path, "explained", "force_sensor_error", {"offset_n": 1.5, "drift_n_per_s": 0.02})
    model = tmp_path / "model.json"
    fit = ["fit", str(palpation), "--flexible-layer-mm", "50", "--method", "paper", "--output", str(model)]
    assert main([*fit, "--compensate", str(supported)]) == 0
    assert f"{palpation}: compensated: force-sensor offset 1.5 N" in capsys.readouterr().out
    compensation = load_model(model).provenance["compensation"]
    assert compensation["effects"] == {"force_sensor_error": {"offset_n": 1.5, "drift_n_per_s": 0.02}}
    assert compensation["forced"] is False and compensation["diagnosis"] == str(supported)

    refused = _diagnosis(tmp_path, "ambiguous", "force_sensor_error", {"offset_n": 1.5, "drift_n_per_s": 0.02})
    assert main([*fit, "--compensate", str(refused)]) == 2
    assert "does not support compensating force_sensor_error" in capsys.readouterr().err
    assert main([*fit, "--force-compensation"]) == 2
    assert "--force-compensation: needs --compensate" in capsys.readouterr().err

    corrected = tmp_path / "corrected.seq.nrrd"
    correct = ["correct", str(palpation), "--model", str(model), "--output", str(corrected)]
    assert main([*correct, "--compensate", str(refused)]) == 2
    assert main([*correct, "--compensate", str(refused), "--force-compensation"]) == 0
    assert f"{palpation}: compensated (forced: the diagnosis does not support it)" in capsys.readouterr().out
