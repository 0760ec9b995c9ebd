"""usdeform compensation-benchmark: refusals, scoring arithmetic and end-to-end runs."""

import dataclasses
import json
import math

import pytest

from usdeform.cli import main
from usdeform.compensation_benchmark import BenchmarkSettings, case_scores, run_compensation_benchmark, summarise
from usdeform.errors import InputError

TINY = BenchmarkSettings(frame_size=64, palpation_frames=24, sweep_frames=6)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--cases", "-1"], "argument --cases: expected an integer from 1 to 10000, got '-1'"),
        (["--cases", "0"], "argument --cases: expected an integer from 1 to 10000, got '0'"),
        (["--cases", "1000000000000"], "argument --cases: expected an integer from 1 to 10000, got '1000000000000'"),
        (["--cases", "1", "--seed", "-3"], "argument --seed: expected an integer from 0 to"),
        (["--cases", "1", "--frame-size", "8"], "argument --frame-size: expected an integer from 64 to 1024, got '8'"),
        (
            ["--cases", "1", "--frame-size", "100000"],
            "argument --frame-size: expected an integer from 64 to 1024, got '100000'",
        ),
    ],
)
def test_bad_input_is_refused_in_one_line_before_any_work(arguments, message, tmp_path, capsys) -> None:
    out = tmp_path / "bench"
    with pytest.raises(SystemExit) as exit:  # argparse: a usage line, then one line naming the option
        main(["compensation-benchmark", *arguments, "--out", str(out)])
    assert exit.value.code == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]
    assert not out.exists()


def test_an_output_that_is_a_file_or_holds_cases_is_refused(tmp_path, capsys) -> None:
    existing = tmp_path / "file"
    existing.write_text("")
    assert main(["compensation-benchmark", "--cases", "1", "--out", str(existing)]) == 2
    assert "is an existing file, not a folder" in capsys.readouterr().err
    (tmp_path / "done").mkdir()
    (tmp_path / "done" / "cases.jsonl").write_text('{"case": 0}\n')
    with pytest.raises(InputError, match="already holds cases"):
        run_compensation_benchmark(1, 0, tmp_path / "done")
    with pytest.raises(InputError, match="effects: expected IDs"):
        run_compensation_benchmark(1, 0, tmp_path / "new", effects=("probe_tilt",))


def _scores(dice, area, depth):
    """Per condition a, b, c, d and e (four values: e as b, the diagnosed compensation applied; five: e's own):
    Dice, area error %, depth error mm."""
    dice, area, depth = ((*values, values[1]) if len(values) == 4 else values for values in (dice, area, depth))
    return {
        condition: {"dice": d, "area_error_pct": a, "depth_error_mm": z}
        for condition, d, a, z in zip("abcde", dice, area, depth, strict=True)
    }


def test_cost_and_recovered_share() -> None:
    row = case_scores(_scores((0.90, 0.98, 1.0, 1.0), (10.0, 4.0, 3.0, 2.0), (0.5, 0.5, 0.5, 0.5)))
    assert row["cost"]["dice"] == pytest.approx(0.10) and row["cost"]["area_error_pct"] == pytest.approx(8.0)
    assert row["recovered"]["dice"] == pytest.approx(0.8) and row["recovered"]["area_error_pct"] == pytest.approx(0.75)
    assert row["recovered_true"]["dice"] == pytest.approx(1.0)
    assert row["recovered"]["depth_error_mm"] is None  # the effect costs no depth: nothing to recover
    assert row["costly"] and not row["worse"]


@pytest.mark.parametrize(
    ("dice", "area", "costly"),
    [
        ((0.95, 0.95, 0.95, 0.96), (5.0, 5.0, 5.0, 5.0), True),  # 0.01 Dice
        ((0.95, 0.95, 0.95, 0.959), (5.0, 5.0, 5.0, 3.1), False),  # 0.009 Dice, 1.9 % area
        ((0.95, 0.95, 0.95, 0.95), (5.0, 5.0, 5.0, 3.0), True),  # 2 % area
    ],
)
def test_a_case_is_costly_from_001_dice_or_2_percent_area(dice, area, costly) -> None:
    assert case_scores(_scores(dice, area, (0.1,) * 4))["costly"] is costly


def test_worse_and_summary_medians_over_costly_cases() -> None:
    worse = case_scores(_scores((0.95, 0.944, 0.95, 0.96), (5.0,) * 4, (0.1,) * 4))
    assert worse["worse"]  # compensation lost 0.006 Dice
    assert not case_scores(_scores((0.95, 0.946, 0.95, 0.96), (5.0,) * 4, (0.1,) * 4))["worse"]
    rows = [
        {"effect": "viscoelasticity", "compensation": "applied", **case_scores(s)}
        for s in (
            _scores((0.90, 1.0, 1.0, 1.0), (5.0,) * 4, (0.1,) * 4),  # recovers all
            _scores((0.90, 0.95, 1.0, 1.0), (5.0,) * 4, (0.1,) * 4),  # half
            _scores((0.90, 0.90, 1.0, 1.0), (5.0,) * 4, (0.1,) * 4),  # none
            _scores((0.995, 0.9, 1.0, 1.0), (5.0,) * 4, (0.1,) * 4),  # costs 0.005 Dice only: left out
        )
    ]
    entry = summarise(rows)["effects"]["viscoelasticity"]
    assert entry["cases"] == 4 and entry["costly"] == 3 and entry["worse"] == 1
    assert entry["recovered"]["dice"] == pytest.approx(0.5) and entry["recovered_true"]["dice"] == pytest.approx(1.0)
    assert entry["recovered"]["area_error_pct"] is None


def test_forced_compensation_is_scored_apart_from_the_gate() -> None:
    # refused (b scores as a), forced recovers 90 % of the Dice and makes nothing worse; another forced one loses
    refused = case_scores(_scores((0.90, 0.90, 1.0, 1.0, 0.99), (5.0,) * 5, (0.1,) * 5))
    assert refused["recovered"]["dice"] == pytest.approx(0.0) and refused["recovered_forced"]["dice"] == pytest.approx(
        0.9
    )
    assert not refused["worse"] and not refused["worse_forced"]
    lost = case_scores(_scores((0.90, 0.90, 1.0, 1.0, 0.89), (5.0,) * 5, (0.1,) * 5))
    assert lost["worse_forced"] and not lost["worse"]
    rows = [{"effect": "force_sensor_error", "compensation": "refused", **row} for row in (refused, lost)]
    entry = summarise(rows)["effects"]["force_sensor_error"]
    assert entry["recovered_forced"]["dice"] == pytest.approx(0.4) and entry["worse_forced"] == 1
    assert entry["recovered"]["dice"] == pytest.approx(0.0) and entry["worse"] == 0


def _estimate(dice_uncompensated: float, dice_compensated: float, area_uncompensated: float, area_compensated: float):
    return [
        {
            "recording": "palpation 1",
            "dice_uncompensated": dice_uncompensated,
            "dice_compensated": dice_compensated,
            "area_error_pct_uncompensated": area_uncompensated,
            "area_error_pct_compensated": area_compensated,
        },
        {"recording": "palpation 2", "error": "no lumen in the lowest-force frame"},  # not scored: left out
    ]


def test_the_diagnosis_cost_estimate_is_checked_against_the_measured_cost_within_a_factor_of_15() -> None:
    # the sweep: the effect costs 0.06 Dice and 6 points of area error
    scores = _scores((0.93, 0.99, 0.99, 0.99), (8.0, 2.0, 2.0, 2.0), (0.1,) * 4)
    right = case_scores(scores, _estimate(0.90, 0.95, -9.0, 3.0))  # estimates 0.05 Dice, 6 points
    assert right["estimated_cost"] == pytest.approx({"dice": 0.05, "area_error_pct": 6.0})
    assert right["estimate_within"] == {"dice": True, "area_error_pct": True}
    sixfold = case_scores(scores, _estimate(0.95, 0.96, 4.0, 3.0))  # "less than 0.01 Dice": six times too small
    assert sixfold["estimate_within"] == {"dice": False, "area_error_pct": False}
    unscored = case_scores(scores, [{"recording": "palpation 1", "error": "re-pairing kept 3 frames"}])
    assert unscored["estimated_cost"] == {"dice": None, "area_error_pct": None}
    assert unscored["estimate_within"] == {"dice": None, "area_error_pct": None}
    cheap = case_scores(_scores((0.99, 0.99, 0.99, 0.995), (2.0,) * 4, (0.1,) * 4), _estimate(0.9, 0.95, 1, 1))
    assert cheap["estimate_within"]["dice"] is None  # costs under 0.01 Dice: no cost to estimate
    rows = [{"effect": "force_sensor_error", "compensation": "applied", **row} for row in (right, sixfold, unscored)]
    entry = summarise(rows)["effects"]["force_sensor_error"]
    assert entry["estimate_within"] == {"dice": [1, 1], "area_error_pct": [1, 1]}


def _sensor_diagnosis(verdict: str, offset_n: float):
    """A stand-in for usdeform.gap.diagnose (minutes): a diagnosis with ``verdict`` that names a significant
    force-sensor offset of ``offset_n``."""

    class Diagnosed:
        def to_json(self):
            effect = {"effect": "force_sensor_error", "significant": True}
            return {
                "verdict": verdict,
                "named": ["force_sensor_error"],
                "effects": [{**effect, "parameters": {"offset_n": offset_n, "drift_n_per_s": 0.0}}],
            }

    return lambda *args, **kwargs: Diagnosed()


def test_null_case_compensated_comes_out_unchanged_bit_for_bit(tmp_path, monkeypatch) -> None:
    """One tiny null case; the diagnosis (minutes) replaced by one that names a zero force-sensor error."""
    monkeypatch.setattr("usdeform.compensation_benchmark.cases.diagnose", _sensor_diagnosis("explained", 0.0))
    summary = run_compensation_benchmark(1, 5, tmp_path, settings=TINY, effects=(None,), progress=False)
    (row,) = [json.loads(line) for line in (tmp_path / "cases.jsonl").read_text().splitlines()]
    assert row["compensation"] == "applied" and row["unchanged"] == {"b": True, "c": True}
    assert row["scores"]["a"] == row["scores"]["b"] == row["scores"]["d"]
    assert summary["effects"]["none"]["unchanged"] == {"b": 1, "c": 1}
    assert "Null cases unchanged bit for bit when compensated: 1 of 1" in (tmp_path / "benchmark.md").read_text()
    assert json.loads((tmp_path / "case_000" / "diagnosis.json").read_text())["verdict"] == "explained"
    assert 0.5 < row["scores"]["a"]["dice"] <= 1


def test_a_resumed_run_keeps_the_finished_cases_and_scores_as_an_uninterrupted_one(tmp_path, monkeypatch) -> None:
    """Two tiny null cases run at once, and one then the other with --resume: the same rows; another seed or other
    settings are refused on resume, before any work."""
    monkeypatch.setattr("usdeform.compensation_benchmark.cases.diagnose", _sensor_diagnosis("explained", 0.0))
    whole = run_compensation_benchmark(2, 5, tmp_path / "whole", settings=TINY, effects=(None,), progress=False)
    run_compensation_benchmark(1, 5, tmp_path / "parts", settings=TINY, effects=(None,), progress=False)
    parts = run_compensation_benchmark(
        2, 5, tmp_path / "parts", settings=TINY, effects=(None,), progress=False, resume=True
    )
    assert parts == whole

    def rows(folder: str) -> list[dict]:
        found = [json.loads(line) for line in (tmp_path / folder / "cases.jsonl").read_text().splitlines()]
        return [{k: v for k, v in row.items() if not k.endswith("_s")} for row in found]  # times differ

    assert rows("parts") == rows("whole") and [row["case"] for row in rows("parts")] == [0, 1]
    with pytest.raises(InputError, match="was run with seed 5, not 6"):
        run_compensation_benchmark(2, 6, tmp_path / "parts", settings=TINY, resume=True)
    with pytest.raises(InputError, match="was run with the settings"):
        run_compensation_benchmark(
            2, 5, tmp_path / "parts", settings=dataclasses.replace(TINY, sweep_frames=8), resume=True
        )


def test_a_refused_compensation_is_also_scored_forced(tmp_path, monkeypatch) -> None:
    """One tiny null case; a diagnosis that names a 1 N sensor offset at the edge of the library: --compensate
    refuses it (b scores as a), --force-compensation applies it (e)."""
    monkeypatch.setattr("usdeform.compensation_benchmark.cases.diagnose", _sensor_diagnosis("at_edge_of_library", 1.0))
    run_compensation_benchmark(1, 5, tmp_path, settings=TINY, effects=(None,), progress=False)
    (row,) = [json.loads(line) for line in (tmp_path / "cases.jsonl").read_text().splitlines()]
    assert row["compensation"] == "refused" and "at_edge_of_library" in row["refusal"]
    assert row["scores"]["b"] == row["scores"]["a"] and row["scores"]["e"] != row["scores"]["a"]
    assert row["diagnosed_parameters"] == {"force_sensor_error": {"offset_n": 1.0, "drift_n_per_s": 0.0}}
    assert "| forced (e) |" in (tmp_path / "benchmark.md").read_text()


@pytest.mark.slow
def test_end_to_end_with_the_blind_diagnosis(tmp_path) -> None:
    """A force-sensor case and a null case on tiny frames, diagnosed blind; same seed, same rows."""
    settings = BenchmarkSettings(frame_size=64, palpation_frames=40, sweep_frames=6)
    effects = ("force_sensor_error", None)
    summary = run_compensation_benchmark(2, 3, tmp_path, settings=settings, effects=effects, progress=False)
    rows = [json.loads(line) for line in (tmp_path / "cases.jsonl").read_text().splitlines()]
    assert [row["effect"] for row in rows] == ["force_sensor_error", "none"]
    assert set(summary["effects"]) == {"force_sensor_error", "none"}
    sensor, null = rows
    assert sensor["compensation"] in ("applied", "refused") and sensor["verdict"]
    assert all(math.isfinite(sensor["scores"][c]["dice"]) for c in "acd")
    assert null["unchanged"]["c"]  # the empty true compensation changes nothing
    assert null["unchanged"]["b"] == (null["compensation"] == "refused" or null["named"] == [])
    document = json.loads((tmp_path / "benchmark.json").read_text())
    assert document["summary"] == summary and len(document["cases"]) == 2
    assert "| force_sensor_error | 1 |" in (tmp_path / "benchmark.md").read_text()
    assert sensor["parameters"].keys() == {"bias_n", "drift_n_per_s", "uncompensated_weight_n"}


def test_truth_pixel_of_a_sound_speed_case_is_the_true_size() -> None:
    """The simulator displays depths scaled by 1540 / true speed: a truth pixel is (1540 + error) / 1540 as deep."""
    import numpy as np

    from usdeform.compensation_benchmark.cases import _Case, _true_pixel_mm
    from usdeform.recording import Recording

    image_to_probe = np.diag([0.2, 0.3, 1.0, 1.0])
    poses = np.tile(np.eye(4), (2, 1, 1))
    sweep = Recording(np.zeros((2, 8, 8), np.uint8), np.arange(2.0), poses, np.ones(2, bool), image_to_probe)
    case = _Case(0, "sound_speed_mismatch", {"error_m_s": -44.0}, (), (0, 0, 0), 0)
    assert _true_pixel_mm(case, sweep) == pytest.approx((0.2, 0.3 * 1496 / 1540))
    assert _true_pixel_mm(dataclasses.replace(case, effect=None, parameters={}), sweep) == pytest.approx((0.2, 0.3))


def test_the_sweep_is_recorded_under_a_robot_force_loop() -> None:
    """The sweep's force wanders about its target as a robot's does (so an image delay pairs a frame with another
    force), at a robot's sweep speed; a frame step below 1 is refused."""
    import numpy as np

    from usdeform.compensation_benchmark.cases import _draw_case, _simulate

    settings = dataclasses.replace(TINY, sweep_frames=30)
    case = _draw_case(0, "image_latency", np.random.default_rng(1), 0, settings)
    _, sweep, _ = _simulate(case, settings, with_effect=False)
    assert np.diff(sweep.timestamps) == pytest.approx(settings.sweep_frame_step / 50.0)
    assert 0.2 < np.std(sweep.force) < 1.5 and abs(np.mean(sweep.force) - settings.sweep_force_n) < 0.5
    with pytest.raises(InputError, match="sweep_frame_step: expected an integer from 1 to 50, got 0"):
        dataclasses.replace(TINY, sweep_frame_step=0).check()


@pytest.mark.slow
def test_the_follow_up_round_compensates_from_the_diagnosis_of_all_recordings(tmp_path, monkeypatch) -> None:
    """One tiny null case; round 0 (a stand-in) asks for a hold and a known weight; the simulator records both into
    the case's folder, and round 1, given the two palpations and the two files, is the diagnosis compensated from."""
    from usdeform.gap.follow_up import FollowUpRecording

    hold = FollowUpRecording(
        "follow_up_01_hold", "hold", 15.0, 10.0, 2.0, 5.0, 0.0, None, None, ["viscoelasticity"], ""
    )
    weight = FollowUpRecording(
        "follow_up_02_known_weight", "known_weight", 15.0, 10.0, 2.0, 0.0, 0.0, None, 10.0, [], ""
    )
    seen = []

    class Diagnosed:
        def __init__(self, verdict, follow_up):
            self.verdict, self.follow_up = verdict, follow_up

        def to_json(self):
            effect = {
                "effect": "force_sensor_error",
                "significant": True,
                "parameters": {"offset_n": 0.0, "drift_n_per_s": 0.0},
            }
            return {"verdict": self.verdict, "named": ["force_sensor_error"], "effects": [effect]}

    def diagnose(recordings, **kwargs):
        seen.append(len(recordings))
        return Diagnosed("ambiguous", [hold, weight]) if len(seen) == 1 else Diagnosed("explained", [])

    monkeypatch.setattr("usdeform.compensation_benchmark.cases.diagnose", diagnose)
    run_compensation_benchmark(1, 5, tmp_path, settings=TINY, effects=(None,), progress=False)
    (row,) = [json.loads(line) for line in (tmp_path / "cases.jsonl").read_text().splitlines()]
    assert seen == [2, 4] and row["follow_up"]["recordings"] == 2 and row["follow_up"]["not_recorded"] == []
    files = sorted(path.name for path in (tmp_path / "case_000" / "follow_up").iterdir())
    assert files == ["follow_up_01_hold.seq.nrrd", "follow_up_02_known_weight.seq.nrrd"]
    assert row["verdict_round0"] == "ambiguous" and row["verdict"] == "explained" and row["compensation"] == "applied"
    assert row["follow_up"]["seconds"] > 5.0 and row["follow_up"]["palpations"] == 1  # longer than its hold
    assert (tmp_path / "case_000" / "diagnosis_round0.json").exists()
    assert "ambiguous -> explained" in (tmp_path / "benchmark.md").read_text()
