"""The small end-to-end benchmark CI can afford: three withheld-effect cases from their PLUS files."""

import json

import pytest

from usdeform.gap.benchmark import run_benchmark


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
