"""The batch manifest's ``compensate`` and ``force_compensation`` (issue 42): as ``fit/correct --compensate``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import test_batch
from test_compensation import _diagnosis
from usdeform.batch import plan_tasks, read_manifest, run_batch
from usdeform.errors import FileFormatError
from usdeform.io import load_model, read_sequence

# The two palpations and sweeps of the batch tests, and their local cluster of two workers.
recordings, client = test_batch.recordings, test_batch.client

DELAY_S = 0.01  # half a sweep's frame interval: the first frame of each recording is dropped


def _manifest(folder: Path, text: str, name: str = "cohort.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def test_batch_compensates_as_the_command_line_does(recordings, client, tmp_path: Path) -> None:
    from usdeform.cli import main

    (tmp_path / "diag").mkdir()
    explained = _diagnosis(tmp_path / "diag", "explained", "image_latency", {"delay_s": DELAY_S})
    at_edge = _diagnosis(tmp_path / "diag", "at_edge_of_library", "image_latency", {"delay_s": DELAY_S})
    palpations = [str(recordings / "palpation-15.seq.nrrd"), str(recordings / "palpation-45.mha")]
    sweep = recordings / "sweep-b.seq.nrrd"
    manifest = _manifest(
        tmp_path,
        f"""
[options]
flexible_layer_mm = 60.0
volume = false
compensate = "diag/{explained.name}"   # relative to the manifest

[[subjects]]
id = "explained"
palpations = {json.dumps(palpations)}
sweeps = ["{sweep}"]

[[subjects]]
id = "forced"
palpations = {json.dumps(palpations)}
options = {{ compensate = "diag/{at_edge.name}", force_compensation = true }}
""",
    )
    result = run_batch(read_manifest(manifest), tmp_path / "out", client=client)
    records = {record["id"]: record for record in result.records}
    assert {key: record["status"] for key, record in records.items()} == {
        "explained/fit": "done",
        "explained/sweep/sweep-b": "done",
        "forced/fit": "done",
    }, records

    # The same model and corrected sweep as `usdeform fit/correct --compensate` on the same recordings.
    cli_model, cli_sweep = tmp_path / "m.json", tmp_path / "c.seq.nrrd"
    fit = ["fit", *palpations, "--output", str(cli_model), "--flexible-layer-mm", "60"]
    assert main([*fit, "--compensate", str(explained)]) == 0
    correct = ["correct", str(sweep), "--model", str(cli_model), "--output", str(cli_sweep)]
    assert main([*correct, "--compensate", str(explained)]) == 0
    out = tmp_path / "out" / "explained"
    batch_model, cli_fit = load_model(out / "model.json"), load_model(cli_model)
    assert np.array_equal(batch_model.model.image_model.coefficients, cli_fit.model.image_model.coefficients)
    assert np.array_equal(batch_model.model.vessel_coefficients, cli_fit.model.vessel_coefficients)
    assert batch_model.provenance["compensation"] == cli_fit.provenance["compensation"]
    corrected, cli_corrected = read_sequence(out / "sweep-b.corrected.seq.nrrd"), read_sequence(cli_sweep)
    assert len(corrected) == len(read_sequence(sweep)) - 1  # the first frame was acquired before the recording
    assert np.array_equal(corrected.frames, cli_corrected.frames)
    assert np.array_equal(corrected.timestamps, cli_corrected.timestamps)

    # The results manifest records what was compensated, and the diagnosis as an input and an option.
    fitted = records["explained/fit"]
    assert fitted["details"]["compensation"] == batch_model.provenance["compensation"]
    assert fitted["details"]["compensation"]["effects"] == {"image_latency": {"delay_s": DELAY_S}}
    assert fitted["details"]["compensation"]["forced"] is False
    assert [note.split(": compensated: ")[0] for note in fitted["details"]["compensation"]["notes"]] == palpations
    assert fitted["inputs"][-1]["path"] == fitted["options"]["compensate"] == str(explained)
    swept = records["explained/sweep/sweep-b"]
    assert swept["details"]["frames"] == len(corrected)
    assert swept["details"]["compensation"]["diagnosis"] == str(explained)
    assert swept["details"]["compensation"]["notes"] == [
        f"{sweep}: compensated: frames re-paired with the force and pose of their acquisition time (image delay "
        "10 ms, force delay 0 ms; 1 frame(s) outside the recorded span dropped)"
    ]
    assert swept["inputs"][-1]["path"] == swept["options"]["compensate"] == str(explained)
    forced = records["forced/fit"]["details"]["compensation"]
    assert forced["forced"] is True and forced["diagnosis"] == str(at_edge)
    assert forced["verdict"] == "at_edge_of_library"
    assert "compensated (forced: the diagnosis does not support it)" in forced["notes"][0]


def test_an_unsupported_diagnosis_is_refused_when_the_manifest_is_read_unless_forced(tmp_path: Path) -> None:
    unsupported = _diagnosis(tmp_path, "at_edge_of_library", "image_latency", {"delay_s": DELAY_S})
    text = f'[options]\nflexible_layer_mm = 60\ncompensate = "{unsupported.name}"\n[[subjects]]\nid = "a"\n'
    path = _manifest(tmp_path, text + 'palpations = ["x.mha"]\n')
    with pytest.raises(FileFormatError) as caught:
        read_manifest(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: subjects[0] (id 'a'): compensate: {unsupported}: ")
    refusal = "verdict 'at_edge_of_library', not 'explained' or 'explained_in_part'"
    assert f"does not support compensating image_latency ({refusal})" in message
    assert message.endswith("force_compensation applies it anyway")

    # Forced in the subject's options, the default compensate applies; CSV reads the same.
    path = _manifest(tmp_path, text + 'palpations = ["x.mha"]\noptions = { force_compensation = true }\n')
    csv = _manifest(
        tmp_path,
        f"subject,palpations,flexible_layer_mm,compensate,force_compensation\na,x.mha,60,{unsupported.name},yes\n",
        "cohort.csv",
    )
    subject = read_manifest(path).subjects[0]
    assert read_manifest(csv).subjects == (subject,)
    assert subject.options.compensate == unsupported and subject.options.force_compensation is True
    compensation = subject.options.compensation()
    assert compensation is not None and compensation.forced
    assert compensation.effects == {"image_latency": {"delay_s": DELAY_S}}
    fit, *_ = plan_tasks(read_manifest(path), tmp_path / "out")
    assert fit.inputs == (tmp_path / "x.mha", unsupported)
    assert fit.option_values()["compensate"] == str(unsupported)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ('compensate = "missing.json"', r"compensate: .*missing\.json: not a readable diagnosis\.json"),
        ('compensate = ""', r"compensate: expected the path of a diagnosis\.json"),
        ("force_compensation = true", r"force_compensation: needs compensate"),
        ('force_compensation = "yes"', r"force_compensation: expected true or false"),
    ],
    ids=["missing", "empty", "forced-without-file", "not-a-boolean"],
)
def test_a_missing_or_malformed_compensation_is_refused_before_any_work(
    tmp_path: Path, capsys, options: str, message: str
) -> None:
    from usdeform.cli import main

    subject = f'[[subjects]]\nid = "a"\npalpations = ["x.mha"]\noptions = {{ {options} }}\n'
    path = _manifest(tmp_path, "[options]\nflexible_layer_mm = 60\n" + subject)
    with pytest.raises(FileFormatError, match=rf"subjects\[0\] \(id 'a'\): (options: )?{message}") as caught:
        read_manifest(path)
    assert str(path) in str(caught.value)
    assert main(["batch", str(path), "--out", str(tmp_path / "out")]) == 2
    assert str(caught.value) in capsys.readouterr().err
    assert not (tmp_path / "out" / "results.json").exists()
