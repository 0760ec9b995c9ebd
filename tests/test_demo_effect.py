"""``usdeform demo --effect``: the palpations and the sweep simulated with a physical effect, diagnosed blind, and one
line saying what the corrected vessel scores with the effect uncompensated and compensated with the diagnosis."""

from __future__ import annotations

import contextlib
import html
import io
import json
from pathlib import Path

import numpy as np
import pytest

from usdeform.cli import main
from usdeform.demo import DemoConfig, pipeline
from usdeform.demo.report import compensation_change, effect_line
from usdeform.errors import InputError
from usdeform.sim import Effects, ForceSensorError


def test_a_bad_effect_is_refused_before_any_work(tmp_path: Path, capsys) -> None:
    assert main(["demo", "--output", str(tmp_path / "d"), "--quick", "--effect", "force-sensor:bias=2"]) == 2
    error = capsys.readouterr().err
    assert "--effect" in error and "bias_n" in error  # the option, and the parameters it takes
    assert not (tmp_path / "d").exists()
    with pytest.raises(InputError, match=r"--effect.*unknown effect 'tide'"):
        DemoConfig(effects=("tide",))


def test_effects_are_parsed_as_usdeform_simulate_parses_them() -> None:
    assert DemoConfig().simulated_effects() == Effects()  # none: the simulator's default, as before --effect
    parsed = DemoConfig(effects=("force-sensor:bias_n=2",)).simulated_effects()
    assert parsed.force_sensor == ForceSensorError(bias_n=2.0)


def test_without_an_effect_nothing_is_diagnosed(quick_demo) -> None:
    result, output, printed = quick_demo
    assert result.effect_outcome is None and effect_line(result) is None
    assert not (output / "diagnosis.json").exists()
    assert 'id="effect"' not in (output / "report.html").read_text() and "Effect " not in printed


@pytest.mark.slow
def test_a_force_sensor_bias_is_diagnosed_and_compensated(tmp_path: Path) -> None:
    output, results, printed = tmp_path / "demo", [], io.StringIO()
    run_demo = pipeline.run_demo

    def keep_result(*args, **kwargs):
        results.append(run_demo(*args, **kwargs))
        return results[-1]

    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(printed):
        patch.setattr(pipeline, "run_demo", keep_result)
        command = ["demo", "--quick", "--output", str(output), "--effect", "force-sensor:bias_n=2"]
        assert main(command) == 0
    (result,) = results
    outcome = result.effect_outcome
    line = effect_line(result)
    assert outcome is not None and line is not None
    diagnosis = json.loads((output / "diagnosis.json").read_text())
    assert diagnosis == outcome.diagnosis
    assert outcome.refusal == "", outcome.refusal
    assert outcome.record is not None and "force_sensor_error" in outcome.record["effects"]
    assert outcome.frame_metrics is not None and outcome.volume_metrics is not None
    for name in ("corrected", "compensated"):
        for metric in ("dice", "area"):
            assert np.isfinite(outcome.frame_metrics.mean(metric, name)), (metric, name)
        assert np.isfinite(outcome.volume_metrics.vessel_volume_mm3[name]), name
    assert (output / "compensated.nrrd").exists() and (output / "vessel_compensated.nrrd").exists()
    assert "compensation gives back +" in line and "compensation-benchmark" in line
    assert line in printed.getvalue().splitlines()
    page = (output / "report.html").read_text()
    assert f'<p id="effect">{html.escape(line)}</p>' in page
    assert {"diagnosis", "compensated fit and correction"} <= set(result.timings_s)


@pytest.mark.parametrize(
    ("dice_change", "area_change", "expected"),
    [
        (0.14, -16.4, "compensation gives back +0.140 Dice, |area error| -16.4 mm²"),
        (-0.012, 1.5, "compensation made it worse, -0.012 Dice, |area error| +1.5 mm²: check the diagnosis's"),
    ],
)
def test_the_line_says_whether_compensation_gave_back_or_made_worse(dice_change, area_change, expected):
    assert compensation_change(dice_change, area_change).startswith(expected)
