"""The small end-to-end benchmark CI can afford: three withheld-effect cases from their PLUS files."""

import json

import pytest

from usdeform.errors import InputError
from usdeform.gap.benchmark import run_benchmark


@pytest.mark.slow
@pytest.mark.gap_benchmark
def test_small_benchmark(tmp_path):
    summary = run_benchmark(3, seed=7, out=tmp_path, progress=False)
    assert (tmp_path / "benchmark.md").read_text().startswith("# Gap benchmark")
    rows = [json.loads(line) for line in (tmp_path / "cases.jsonl").read_text().splitlines()]
    assert [row["hidden"] for row in rows] == ["image_latency", "force_sensor_error", "viscoelasticity"]
    for index in range(3):
        assert (tmp_path / f"case_{index:03d}" / "palpation.seq.nrrd").exists()
        assert (tmp_path / f"case_{index:03d}" / "diagnosis.json").exists()
    # These three effects have strong signatures: the diagnosis must name at least two of them.
    assert summary["top1_identification"][0] >= 2 / 3
    # every single-effect case is either left without a gap or counted among those where one was seen
    seen = summary["top1_where_gap_seen"][1]
    assert seen + round(summary["single_no_significant_gap"][0] * 3) == 3
    # every single-effect case is either flagged undetectable by the diagnosis or counted among the detectable
    flagged = summary["single_flagged_undetectable"]
    assert flagged[1] == 3 and summary["top1_where_detectable"][1] + round(flagged[0] * 3) == 3
    assert all(isinstance(row["flagged_undetectable"], bool) for row in rows)
    # time per case is measured by `usdeform gap-benchmark` (its table), not asserted here: CI machines are shared
    assert all(row["diagnosis_s"] > 0 and row["total_s"] >= row["diagnosis_s"] for row in rows)


class _Stop(Exception):
    """Stands in for the run being killed part-way."""


def _fake_run(monkeypatch, stop_at=None):
    """Replace generation and diagnosis by fast stand-ins; record each case's first generation draw."""
    import usdeform.gap.benchmark as benchmark

    draws = {}

    def generate_case(index, kind, effect, rng, directory):
        draws[index] = int(rng.integers(0, 2**62))
        directory.mkdir(parents=True, exist_ok=True)
        hidden = [effect] if effect else []
        magnitudes = {name: float("nan") for name in hidden}
        case = benchmark.BenchmarkCase(index, kind, hidden, {}, magnitudes, directory / "palpation.seq.nrrd", 0, 10)
        return case, None

    class Diagnosis:
        follow_up = ()  # nothing more to record

        def to_json(self):
            return {"verdict": "no_significant_gap", "effects": [], "measures": [], "undetectable": []}

    def diagnose(paths, seed, progress):
        if paths[0].parent.name == stop_at:
            raise _Stop
        draws[paths[0].parent.name] = seed
        return Diagnosis()

    monkeypatch.setattr(benchmark, "generate_case", generate_case)
    monkeypatch.setattr(benchmark, "diagnose", diagnose)
    return draws


def test_a_resumed_benchmark_runs_only_the_missing_cases_with_the_same_seeds(tmp_path, monkeypatch):
    whole = _fake_run(monkeypatch)
    run_benchmark(5, seed=3, out=tmp_path / "whole", progress=False)

    first = _fake_run(monkeypatch, stop_at="case_003")
    with pytest.raises(_Stop):
        run_benchmark(5, seed=3, out=tmp_path / "cut", progress=False)
    assert set(first) == {0, 1, 2, 3, "case_000", "case_001", "case_002"}
    log = tmp_path / "cut" / "cases.jsonl"
    log.write_text(log.read_text() + '{"case": 3, "ki')  # a line cut short by the kill

    with pytest.raises(InputError, match="--resume"):
        run_benchmark(5, seed=3, out=tmp_path / "cut", progress=False)
    with pytest.raises(InputError, match="seed 3, not 4"):
        run_benchmark(5, seed=4, out=tmp_path / "cut", progress=False, resume=True)

    rest = _fake_run(monkeypatch)
    summary = run_benchmark(5, seed=3, out=tmp_path / "cut", progress=False, resume=True)
    assert set(rest) == {3, 4, "case_003", "case_004"}
    assert {key: whole[key] for key in rest} == rest  # the same generation and diagnosis streams
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert [row["case"] for row in rows] == [0, 1, 2, 3, 4] and summary["cases"] == 5
    stored = json.loads((tmp_path / "cut" / "benchmark.json").read_text())["cases"]
    assert [row["case"] for row in stored] == [0, 1, 2, 3, 4]


def test_tilt_cases_draw_every_form_and_the_convex_face_is_out_of_the_library():
    import numpy as np

    from usdeform.gap.benchmark import _ROUND, OOL_KINDS, draw_effect
    from usdeform.gap.models import EFFECT_BY_ID

    rng = np.random.default_rng(3)
    forms = set()
    for _ in range(40):
        tilt, parameters, magnitude = draw_effect("probe_tilt", rng, 20.0, 10.0)
        assert 3.0 <= magnitude == abs(tilt.relative_deg) <= 10.0
        forms.add((tilt.surface_inclination_deg != 0, tilt.travel_along_axis))
        assert set(parameters) in ({"tilt_deg", "travel_along_axis"}, {"surface_inclination_deg", "travel_along_axis"})
    assert forms == {(False, 0.0), (False, 1.0), (True, 0.0), (True, 1.0)}
    assert "convex_probe_face" in OOL_KINDS and "convex_probe_face" not in EFFECT_BY_ID
    assert ("out_of_library", "convex_probe_face") in _ROUND


def test_the_command_line_recorded_is_the_one_given_to_main(tmp_path, monkeypatch):
    """The benchmark records the arguments main() was called with, not the interpreter's own (python -c ...)."""
    import usdeform.gap.benchmark as benchmark
    from usdeform.cli import main

    recorded = {}

    def fake_run_benchmark(cases, seed, out, command, resume, follow_up_round):
        recorded["command"] = command
        return {"cases": cases, "top1_identification": [1.0, cases]}

    monkeypatch.setattr(benchmark, "run_benchmark", fake_run_benchmark)
    out = tmp_path / "my out"
    assert main(["gap-benchmark", "--cases", "2", "--seed", "5", "--out", str(out)]) == 0
    assert recorded["command"] == f"usdeform gap-benchmark --cases 2 --seed 5 --out '{out}'"
