"""The pipeline both doors use (usdeform.pipeline): every option of ``usdeform fit`` and ``usdeform correct`` is a
batch manifest option with the same default, each manifest option reaches the pipeline, a bad value is refused
naming the field, and the command line and the batch write identical outputs for the same options."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from usdeform.batch import Options, plan_tasks, read_manifest, run_task
from usdeform.batch import stages as batch_stages
from usdeform.cli import build_parser, main
from usdeform.errors import FileFormatError, InputError
from usdeform.io import load_model, read_sequence, read_volume, write_sequence
from usdeform.pipeline import FIT_FIELDS, SETTINGS_FIELDS, PipelineSettings, correct_sweep

#: The manifest options that ``usdeform fit`` and ``usdeform correct`` had alone: (TOML value, CSV cell, value read).
LATER_OPTIONS: dict[str, tuple[str, str, object]] = {
    "wall_weight": ("0.25", "0.25", 0.25),
    "stiffness_source": ('"interpolated"', "interpolated", "interpolated"),
    "clamp_force": ("true", "yes", True),
    "fill_holes": ('"gaussian"', "gaussian", "gaussian"),
    "voxel_type": ('"uint8"', "uint8", "uint8"),
    "coverage": ("true", "true", True),
}

#: A value of each of them that is refused: (TOML value, CSV cell, what the error says after the field's name).
BAD_VALUES: dict[str, tuple[str, str, str]] = {
    "wall_weight": ("-1", "-1", "expected a finite number >= 0"),
    "stiffness_source": ('"guess"', "guess", "expected one of auto, interpolated, sweep, got 'guess'"),
    "clamp_force": ('"maybe"', "maybe", "expected true or false, got 'maybe'"),
    "fill_holes": ('"blur"', "blur", "expected one of off, gaussian, .*, got 'blur'"),
    "voxel_type": ('"int16"', "int16", "expected one of float32, uint8, got 'int16'"),
    "coverage": ("1", "sometimes", "expected true or false, got "),
}

MANIFEST_OPTIONS = tuple(field.name for field in dataclasses.fields(Options))
FIT_ARGV = ["fit", "p.mha", "--output", "m.json", "--flexible-layer-mm", "30"]
CORRECT_ARGV = ["correct", "s.mha", "--model", "m.json", "--output", "c.seq.nrrd"]


def _manifest(folder: Path, form: str, options: dict[str, tuple[str, str]]) -> Path:
    """A one-subject manifest (palpation p.mha, sweep s.mha, flexible layer 60 mm) with ``options``:
    name -> (TOML value, CSV cell)."""
    if form == "toml":
        lines = "".join(f"{name} = {toml}\n" for name, (toml, _) in options.items())
        text = f'[options]\nflexible_layer_mm = 60\n{lines}[[subjects]]\nid = "a"\npalpations = ["p.mha"]\n'
        text += 'sweeps = ["s.mha"]\n'
    else:
        header = "".join(f",{name}" for name in options)
        cells = "".join(f",{cell}" for _, cell in options.values())
        text = f"subject,palpations,sweeps,flexible_layer_mm{header}\na,p.mha,s.mha,60{cells}\n"
    path = folder / f"cohort.{form}"
    path.write_text(text)
    return path


def test_every_option_of_fit_and_correct_is_a_manifest_option_with_the_same_default() -> None:
    for argv in (FIT_ARGV, CORRECT_ARGV):
        parsed = build_parser(argv[0]).parse_args(argv)
        given = {"command", "run", "palpations", "sweep", "model", "output", "flexible_layer_mm"}
        options = set(vars(parsed)) - given
        assert options <= set(MANIFEST_OPTIONS), options - set(MANIFEST_OPTIONS)
        for name in options & set(SETTINGS_FIELDS):
            assert getattr(parsed, name) == getattr(Options(), name) == getattr(PipelineSettings(), name), name
    assert set(SETTINGS_FIELDS) <= set(MANIFEST_OPTIONS)


@pytest.mark.parametrize("name", LATER_OPTIONS)
@pytest.mark.parametrize("form", ["toml", "csv"])
def test_each_manifest_option_reaches_the_pipeline(tmp_path: Path, monkeypatch, form: str, name: str) -> None:
    toml, cell, value = LATER_OPTIONS[name]
    (subject,) = read_manifest(_manifest(tmp_path, form, {name: (toml, cell)})).subjects
    assert getattr(subject.options, name) == value
    calls: dict[str, tuple] = {}

    class Run:
        def details(self) -> dict:
            return {}

    def spy(step: str):
        def call(*args, **kwargs):
            calls[step] = (args, kwargs)
            return Run()

        return call

    monkeypatch.setattr(batch_stages, "fit_model", spy("fit"))
    monkeypatch.setattr(batch_stages, "correct_sweep", spy("sweep"))
    fit, sweep = plan_tasks(read_manifest(tmp_path / f"cohort.{form}"), tmp_path / "out")
    for task, needed in ((fit, None), (sweep, {"status": "done"})):
        record = run_task(task, needed=needed)
        assert record["status"] == "done", record
    # the fit's settings, or the sweep's, carry the value; the task's record too (a change of it redoes the task)
    step, record_options = ("fit", fit.option_values()) if name in FIT_FIELDS else ("sweep", sweep.option_values())
    args, _ = calls[step]
    settings = args[1] if step == "fit" else args[2]
    assert getattr(settings, name) == value and record_options[name] == value
    if name == "coverage":
        assert args[5] == tmp_path / "out" / "a" / "s.coverage.nrrd"
        assert sweep.outputs[-1] == args[5]


@pytest.mark.parametrize("name", BAD_VALUES)
@pytest.mark.parametrize("form", ["toml", "csv"])
def test_a_bad_value_of_a_manifest_option_is_refused_naming_it(tmp_path: Path, form: str, name: str) -> None:
    toml, cell, message = BAD_VALUES[name]
    path = _manifest(tmp_path, form, {name: (toml, cell)})
    with pytest.raises(FileFormatError, match=rf"{name}: {message}") as caught:
        read_manifest(path)
    assert str(path) in str(caught.value)


@pytest.mark.parametrize("form", ["toml", "csv"])
def test_a_coverage_needs_the_volume(tmp_path: Path, form: str) -> None:
    path = _manifest(tmp_path, form, {"volume": ("false", "false"), "coverage": ("true", "true")})
    with pytest.raises(FileFormatError, match=r"coverage: needs volume = true"):
        read_manifest(path)
    with pytest.raises(InputError, match="coverage_path: needs volume_path"):
        correct_sweep(tmp_path / "s.mha", tmp_path / "m.json", PipelineSettings(), tmp_path / "c.mha", None, path)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> Path:
    """A palpation (s = 20 mm, up to 8 N) and an 8-frame sweep at 8 N over s = 15-30 mm of the coarse test
    phantom, 96 x 96 pixels, as PLUS sequence files."""
    from usdeform.sim import coarse_phantom, simulate_palpation, simulate_sweep

    phantom, folder = coarse_phantom(), tmp_path_factory.mktemp("recordings")
    write_sequence(
        folder / "palpation.seq.nrrd", simulate_palpation(phantom, 20.0, 8.0, n_frames=8, rows=96, cols=96)[0]
    )
    write_sequence(folder / "sweep.mha", simulate_sweep(phantom, 15.0, 15.0, 8.0, n_frames=8, rows=96, cols=96)[0])
    return folder


def test_the_command_line_and_the_batch_write_the_same_outputs_for_the_same_options(
    recordings: Path, tmp_path: Path
) -> None:
    options = {
        "method": ('"paper"', "--method", "paper"),
        "wall": ('"auto"', "--wall", "auto"),
        "wall_weight": ("0.5", "--wall-weight", "0.5"),
        "stiffness_source": ('"interpolated"', "--stiffness-source", "interpolated"),
        "clamp_force": ("true", "--clamp-force", None),
        "spacing_mm": ("0.7", "--spacing", "0.7"),
        "interpolation": ('"linear"', "--interpolation", "linear"),
        "compounding": ('"max"', "--compounding", "max"),
        "fill_holes": ('"nearest_neighbor"', "--fill-holes", "nearest_neighbor"),
        "voxel_type": ('"uint8"', "--voxel-type", "uint8"),
        "compression_level": ("3", "--compression-level", "3"),
    }
    fit_flags = {"method", "wall", "wall_weight"}
    flags = {name: [flag, *([value] if value else [])] for name, (_, flag, value) in options.items()}
    palpation, sweep = str(recordings / "palpation.seq.nrrd"), str(recordings / "sweep.mha")
    cli = {name: tmp_path / name for name in ("model.json", "c.seq.nrrd", "v.nrrd", "w.nrrd")}
    fit_argv = ["fit", palpation, "--output", str(cli["model.json"]), "--flexible-layer-mm", "40"]
    assert main(fit_argv + [part for name in fit_flags for part in flags[name]]) == 0
    correct_argv = ["correct", sweep, "--model", str(cli["model.json"]), "--output", str(cli["c.seq.nrrd"])]
    correct_argv += ["--volume", str(cli["v.nrrd"]), "--coverage", str(cli["w.nrrd"])]
    assert main(correct_argv + [part for name in options.keys() - fit_flags for part in flags[name]]) == 0

    lines = "".join(f"{name} = {toml}\n" for name, (toml, _, _) in options.items())
    manifest = tmp_path / "cohort.toml"
    manifest.write_text(
        f'[options]\nflexible_layer_mm = 40\ncoverage = true\n{lines}[[subjects]]\nid = "a"\n'
        f'palpations = ["{palpation}"]\nsweeps = ["{sweep}"]\n'
    )
    fit, correct = plan_tasks(read_manifest(manifest), tmp_path / "out")
    fit_record = run_task(fit)
    assert fit_record["status"] == "done", fit_record
    assert run_task(correct, needed=fit_record)["status"] == "done"

    out = tmp_path / "out" / "a"
    assert json.loads((out / "model.json").read_text()) == json.loads(cli["model.json"].read_text())
    assert json.loads(cli["model.json"].read_text())["provenance"]["wall_weight"] == 0.5
    batch_model, cli_model = load_model(out / "model.json").model, load_model(cli["model.json"]).model
    assert np.array_equal(batch_model.coefficients, cli_model.coefficients)
    batch_sweep, cli_sweep = read_sequence(out / "sweep.corrected.seq.nrrd"), read_sequence(cli["c.seq.nrrd"])
    assert np.array_equal(batch_sweep.frames, cli_sweep.frames)
    assert batch_sweep.metadata == cli_sweep.metadata and cli_sweep.metadata["StiffnessSource"] == "interpolated"
    for batch_name, cli_name in (("sweep.volume.nrrd", "v.nrrd"), ("sweep.coverage.nrrd", "w.nrrd")):
        batch_volume, cli_volume = read_volume(out / batch_name), read_volume(cli[cli_name])
        assert np.array_equal(batch_volume.image, cli_volume.image)
        assert np.array_equal(batch_volume.grid.index_to_world, cli_volume.grid.index_to_world)
    assert read_volume(out / "sweep.volume.nrrd").image.dtype == np.uint8
