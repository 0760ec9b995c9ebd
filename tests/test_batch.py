"""Batches on a local Dask cluster of two worker processes: a normal batch (outputs equal to the
command line's), bad recordings reported without stopping it, the rerun that reuses finished work, a
worker killed mid-write, the manifest's validation, and the diagnosis unit."""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import importlib.util
import json
import os
import shutil
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from usdeform.batch import Options, TaskSpec, plan_tasks, read_manifest, read_results, run_batch, run_task
from usdeform.errors import FileFormatError
from usdeform.io import load_model, read_sequence, read_volume, write_sequence
from usdeform.regression import VesselAnchoredModel

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> Path:
    """Two palpations (s = 15 and 45 mm, up to 8 N) and two 10-frame sweeps at 8 N of the coarse test
    phantom, 96 x 96 pixels, as PLUS sequence files, and a truncated copy of a sweep (bad.mha)."""
    from usdeform.sim import coarse_phantom, simulate_palpation, simulate_sweep

    phantom = coarse_phantom()
    folder = tmp_path_factory.mktemp("recordings")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("USDEFORM_CACHE_DIR", str(tmp_path_factory.mktemp("usdeform-cache")))
        for name, s_mm, seed in (("palpation-15.seq.nrrd", 15.0, 11), ("palpation-45.mha", 45.0, 12)):
            palpation, _ = simulate_palpation(phantom, s_mm, 8.0, n_frames=8, seed=seed, rows=96, cols=96)
            write_sequence(folder / name, palpation)
        for name, start_mm, seed in (("sweep-a.mha", 20.0, 3), ("sweep-b.seq.nrrd", 30.0, 4)):
            sweep, _ = simulate_sweep(phantom, start_mm, 20.0, 8.0, n_frames=10, seed=seed, rows=96, cols=96)
            write_sequence(folder / name, sweep)
    data = (folder / "sweep-a.mha").read_bytes()
    (folder / "bad.mha").write_bytes(data[: len(data) // 2])
    return folder


@pytest.fixture(scope="module")
def client():
    from usdeform.batch import batch_client

    with batch_client(n_workers=2, dashboard_address=":0") as client:
        yield client


def _write_manifest(folder: Path, text: str, name: str = "cohort.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def _cohort(recordings: Path, folder: Path) -> Path:
    """Three subjects: a good one with two sweeps, one with a truncated sweep, one whose palpation is
    the truncated file (its fit fails, so its sweep is skipped)."""
    palpations = f'["{recordings}/palpation-15.seq.nrrd", "{recordings}/palpation-45.mha"]'
    return _write_manifest(
        folder,
        f"""
[options]
flexible_layer_mm = 60.0

[[subjects]]
id = "good"
palpations = {palpations}
sweeps = ["{recordings}/sweep-a.mha", "{recordings}/sweep-b.seq.nrrd"]

[[subjects]]
id = "bad-sweep"
palpations = {palpations}
sweeps = ["{recordings}/bad.mha", "{recordings}/sweep-a.mha"]
options = {{ volume = false }}

[[subjects]]
id = "bad-fit"
palpations = ["{recordings}/bad.mha"]
sweeps = ["{recordings}/sweep-a.mha"]
""",
    )


def _records(result) -> dict[str, dict]:
    return {record["id"]: record for record in result.records}


def _partial_files(folder: Path) -> list[Path]:
    return sorted(folder.rglob("*.part"))


def test_batch_matches_the_command_line_and_reports_bad_recordings(recordings, client, tmp_path: Path) -> None:
    from usdeform.cli import main

    result = run_batch(read_manifest(_cohort(recordings, tmp_path)), tmp_path / "out", client=client)
    records = _records(result)
    assert {key: record["status"] for key, record in records.items()} == {
        "good/fit": "done",
        "good/sweep/sweep-a": "done",
        "good/sweep/sweep-b": "done",
        "bad-sweep/fit": "done",
        "bad-sweep/sweep/bad": "failed",
        "bad-sweep/sweep/sweep-a": "done",
        "bad-fit/fit": "failed",
        "bad-fit/sweep/sweep-a": "skipped",
    }
    assert result.summary == {"done": 5, "failed": 2, "skipped": 1, "pending": 0, "reused": 0}
    assert "FileFormatError" in records["bad-sweep/sweep/bad"]["error"]
    assert "bad.mha" in records["bad-sweep/sweep/bad"]["error"]
    assert records["bad-fit/sweep/sweep-a"]["error"].startswith("bad-fit/fit failed: FileFormatError")
    assert len({record["worker"] for record in records.values() if record["status"] == "done"}) == 2
    # The results manifest on disk is the returned one.
    assert read_results(result.results_path) == records
    assert json.loads(result.results_path.read_text())["summary"] == result.summary

    # Same outputs as `usdeform fit` and `usdeform correct` on the same recordings.
    out = tmp_path / "out" / "good"
    palpations = [str(recordings / "palpation-15.seq.nrrd"), str(recordings / "palpation-45.mha")]
    cli_model, cli_sweep, cli_volume = tmp_path / "m.json", tmp_path / "c.seq.nrrd", tmp_path / "v.nrrd"
    assert main(["fit", *palpations, "--output", str(cli_model), "--flexible-layer-mm", "60"]) == 0
    cli_args = ["correct", str(recordings / "sweep-b.seq.nrrd"), "--model", str(cli_model)]
    assert main([*cli_args, "--output", str(cli_sweep), "--volume", str(cli_volume)]) == 0
    batch_model, cli_fit = load_model(out / "model.json").model, load_model(cli_model).model
    assert isinstance(batch_model, VesselAnchoredModel) and isinstance(cli_fit, VesselAnchoredModel)
    assert np.array_equal(batch_model.image_model.coefficients, cli_fit.image_model.coefficients)
    assert np.array_equal(batch_model.vessel_coefficients, cli_fit.vessel_coefficients)
    assert np.array_equal(read_sequence(out / "sweep-b.corrected.seq.nrrd").frames, read_sequence(cli_sweep).frames)
    assert np.array_equal(read_volume(out / "sweep-b.volume.nrrd").image, read_volume(cli_volume).image)
    assert not (tmp_path / "out" / "bad-sweep" / "sweep-a.volume.nrrd").exists()  # volume = false
    assert (tmp_path / "out" / "bad-sweep" / "sweep-a.corrected.seq.nrrd").exists()
    assert _partial_files(tmp_path / "out") == []


def test_rerun_reuses_finished_work_and_redoes_what_changed(recordings, client, tmp_path: Path) -> None:
    inputs = tmp_path / "inputs"
    shutil.copytree(recordings, inputs)
    manifest = read_manifest(_cohort(inputs, tmp_path))
    out = tmp_path / "out"
    first = _records(run_batch(manifest, out, client=client))
    written = {path: path.stat().st_mtime_ns for path in out.rglob("*.nrrd")}

    second = run_batch(manifest, out, client=client)
    assert second.summary == {"done": 5, "failed": 2, "skipped": 1, "pending": 0, "reused": 5}
    assert {path: path.stat().st_mtime_ns for path in out.rglob("*.nrrd")} == written
    for key, record in first.items():  # finished tasks keep the first run's record; the others ran again
        again = _records(second)[key]
        assert again["status"] == record["status"]
        if record["status"] == "done":
            assert again == {**record, "reused": True}

    # Repair the bad recording, change one sweep and delete one output: exactly those run again,
    # and the sweeps of the subject whose fit now succeeds run for the first time.
    shutil.copy(inputs / "palpation-45.mha", inputs / "bad.mha")
    write_sequence(inputs / "sweep-b.seq.nrrd", read_sequence(inputs / "sweep-a.mha"))
    (out / "bad-sweep" / "sweep-a.corrected.seq.nrrd").unlink()
    third = _records(run_batch(manifest, out, client=client))
    assert all(record["status"] == "done" for record in third.values()), third
    rerun = {key for key, record in third.items() if not record["reused"]}
    assert rerun == {
        "good/sweep/sweep-b",
        "bad-sweep/sweep/bad",
        "bad-sweep/sweep/sweep-a",
        "bad-fit/fit",
        "bad-fit/sweep/sweep-a",
    }
    # The changed sweep now holds sweep-a's frames, so its output equals sweep-a's.
    assert np.array_equal(
        read_sequence(out / "good" / "sweep-b.corrected.seq.nrrd").frames,
        read_sequence(out / "good" / "sweep-a.corrected.seq.nrrd").frames,
    )

    # A changed option redoes the tasks it affects (all of the subject's sweeps) and nothing else.
    changed = manifest.subjects[0]
    changed = dataclasses.replace(changed, options=dataclasses.replace(changed.options, spacing_mm=0.75))
    manifest = dataclasses.replace(manifest, subjects=(changed, *manifest.subjects[1:]))
    fourth = _records(run_batch(manifest, out, client=client))
    assert {key for key, record in fourth.items() if not record["reused"]} == {
        "good/sweep/sweep-a",
        "good/sweep/sweep-b",
    }


def _stall_one_write(marker: str) -> None:
    """In a worker: make the next reconstruction of sweep 'stall' start writing its corrected sequence
    (a temporary file, as every writer does), record the worker's pid in ``marker`` and hang."""
    from usdeform._files import atomic_output
    from usdeform.batch import stages

    reconstruct = stages.reconstruct_sweep

    def stalling(sweep_path, model_path, options, corrected_path, *outputs):  # outputs: the volume, its coverage
        if sweep_path.name == "stall.mha" and not os.path.exists(marker):
            with atomic_output(corrected_path) as handle:
                handle.write(b"NRRD0004\n# half of a file")
                handle.flush()
                Path(marker).write_text(str(os.getpid()))
                time.sleep(120)
        return reconstruct(sweep_path, model_path, options, corrected_path, *outputs)

    stages.reconstruct_sweep = stalling


def test_a_killed_worker_has_its_task_retried_and_leaves_no_partial_output(recordings, tmp_path: Path) -> None:
    from usdeform.batch import batch_client

    shutil.copy(recordings / "sweep-a.mha", tmp_path / "stall.mha")
    manifest = read_manifest(
        _write_manifest(
            tmp_path,
            f"""
[[subjects]]
id = "s"
palpations = ["{recordings}/palpation-15.seq.nrrd", "{recordings}/palpation-45.mha"]
sweeps = ["{tmp_path}/stall.mha", "{recordings}/sweep-a.mha"]
options = {{ flexible_layer_mm = 60.0 }}
""",
        )
    )
    marker = tmp_path / "stalled-worker-pid"
    with batch_client(n_workers=2, dashboard_address=":0") as client:
        client.run(_stall_one_write, str(marker))
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            running = pool.submit(run_batch, manifest, tmp_path / "out", client=client)
            deadline = time.monotonic() + 60
            while not marker.exists() and time.monotonic() < deadline:
                time.sleep(0.1)
            assert marker.exists(), "the stalling task never started"
            partial = [path for path in _partial_files(tmp_path / "out") if path.name.startswith(".stall.")]
            assert len(partial) == 1 and partial[0].name.startswith(".stall.corrected.seq.nrrd.")
            killed = int(marker.read_text())
            os.kill(killed, signal.SIGKILL)
            result = running.result(timeout=90)
    records = _records(result)
    assert all(record["status"] == "done" for record in records.values()), records
    assert not records["s/sweep/stall"]["worker"].endswith(f":{killed}")
    out = tmp_path / "out" / "s"
    assert _partial_files(tmp_path / "out") == []
    assert np.array_equal(
        read_sequence(out / "stall.corrected.seq.nrrd").frames, read_sequence(out / "sweep-a.corrected.seq.nrrd").frames
    )
    assert read_volume(out / "stall.volume.nrrd").image.shape == read_volume(out / "sweep-a.volume.nrrd").image.shape


def _fail_fits_once(folder: str) -> None:
    """In a worker: the next fit of palpations under ``folder`` raises an unexpected error (not the
    recording's fault) once per marker file, as a flaky file system might."""
    from usdeform.batch import stages

    fit = stages.fit_position

    def flaky(palpation_paths, *args, **kwargs):  # fit_position's other arguments, whatever they are
        marker = Path(folder) / "failed-once"
        if str(palpation_paths[0]).startswith(folder) and not marker.exists():
            marker.write_text(str(os.getpid()))
            raise RuntimeError("transient failure")
        return fit(palpation_paths, *args, **kwargs)

    stages.fit_position = flaky


def test_unexpected_errors_are_retried_by_dask(recordings, client, tmp_path: Path) -> None:
    shutil.copy(recordings / "palpation-15.seq.nrrd", tmp_path / "palpation.seq.nrrd")
    text = f'[[subjects]]\nid = "x"\npalpations = ["{tmp_path}/palpation.seq.nrrd"]\n'
    manifest = read_manifest(_write_manifest(tmp_path, text + "options = { flexible_layer_mm = 60.0 }\n"))
    client.run(_fail_fits_once, str(tmp_path))
    record = _records(run_batch(manifest, tmp_path / "out", client=client, retries=1))["x/fit"]
    assert record["status"] == "done" and (tmp_path / "failed-once").exists()

    (tmp_path / "failed-once").unlink()
    record = _records(run_batch(manifest, tmp_path / "out-no-retry", client=client, retries=0))["x/fit"]
    assert (record["status"], record["error"], record["worker"]) == ("failed", "RuntimeError: transient failure", None)


def test_command_on_a_running_scheduler_with_csv_manifest(recordings, client, tmp_path: Path, capsys) -> None:
    from usdeform.batch.command import add_batch_command
    from usdeform.errors import UsdeformError

    manifest = tmp_path / "cohort.csv"
    manifest.write_text(
        "subject,palpations,sweeps,flexible_layer_mm,volume\n"
        f"one,{recordings}/palpation-15.seq.nrrd;{recordings}/palpation-45.mha,{recordings}/sweep-a.mha,60,false\n"
        f"two,{recordings}/bad.mha,{recordings}/sweep-a.mha,60,\n"
    )
    parser = argparse.ArgumentParser()
    add_batch_command(parser.add_subparsers())
    args = parser.parse_args(
        ["batch", str(manifest), "--out", str(tmp_path / "out"), "--scheduler", client.scheduler.address]
    )
    with pytest.raises(UsdeformError, match="2 of 4 tasks did not finish"):
        args.run(args)
    captured = capsys.readouterr()
    assert "2 done (0 reused from the last run), 1 failed, 1 skipped" in captured.out
    assert "4 tasks on 2 workers" in captured.err
    assert "two/fit: failed: FileFormatError" in captured.err
    assert (tmp_path / "out" / "one" / "sweep-a.corrected.seq.nrrd").exists()


def test_futures_api_and_dashboard_link(recordings, client, tmp_path: Path) -> None:
    from usdeform.batch import dashboard_link, submit_batch

    link = dashboard_link(client)
    assert (link is not None) == (importlib.util.find_spec("bokeh") is not None)
    assert link is None or link.startswith("http")

    manifest = read_manifest(
        _write_manifest(
            tmp_path,
            f'[options]\nflexible_layer_mm = 60.0\n[[subjects]]\nid = "x"\n'
            f'palpations = ["{recordings}/palpation-15.seq.nrrd"]\nsweeps = ["{recordings}/sweep-a.mha"]\n',
        )
    )
    futures = submit_batch(client, manifest, tmp_path / "out")
    assert list(futures) == ["x/fit", "x/sweep/sweep-a"]
    records = client.gather(list(futures.values()))
    assert [record["status"] for record in records] == ["done", "done"]
    assert records[1]["inputs"][1]["path"] == str(tmp_path / "out" / "x" / "model.json")


def test_manifest_formats_read_the_same_subjects(tmp_path: Path) -> None:
    (tmp_path / "p1").mkdir()
    toml = _write_manifest(
        tmp_path,
        """
[options]
flexible_layer_mm = 60
basis = "bspline:8x6"

[[subjects]]
id = "p1"
palpations = ["p1/a.mha", "p1/b.mha"]
sweeps = ["p1/s.seq.nrrd"]
diagnosis = true
[subjects.options]
compounding = "max"
anchor = "image"
""",
    )
    csv = _write_manifest(
        tmp_path,
        "subject,palpations,sweeps,diagnosis,flexible_layer_mm,basis,compounding,anchor\n"
        "p1,p1/a.mha; p1/b.mha,p1/s.seq.nrrd,true,60,bspline:8x6,max,image\n\n",
        "cohort.csv",
    )
    from_toml, from_csv = read_manifest(toml), read_manifest(csv)
    assert from_toml.subjects == from_csv.subjects
    subject = from_toml.subjects[0]
    assert subject.palpations == (tmp_path / "p1" / "a.mha", tmp_path / "p1" / "b.mha")
    assert subject.diagnosis == subject.palpations
    assert subject.options == Options(flexible_layer_mm=60.0, basis="bspline:8x6", compounding="max", anchor="image")
    assert subject.options.fit_method().anchor == "image"
    assert Options(flexible_layer_mm=60.0).fit_method().anchor == "vessel"  # the recommended method's
    tasks = plan_tasks(from_toml, tmp_path / "out")
    assert [task.id for task in tasks] == ["p1/fit", "p1/sweep/s", "p1/diagnosis"]
    assert tasks[1].outputs == (
        tmp_path / "out" / "p1" / "s.corrected.seq.nrrd",
        tmp_path / "out" / "p1" / "s.volume.nrrd",
    )


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        ("m.csv", "subject,palpations,speed\n", r"line 1: unknown column\(s\) speed"),
        ("m.csv", "subject,palpations,flexible_layer_mm\na,x.mha,60\nb,y.mha,thick\n", r"line 3: flexible_layer_mm"),
        ("m.csv", "subject,palpations,flexible_layer_mm\na,x.mha,60,extra\n", r"line 2: more cells"),
        ("m.csv", "subject,palpations,flexible_layer_mm\na,x.mha,60\na,y.mha,60\n", r"subject 'a' is listed twice"),
        ("m.csv", "subject,palpations,volume\na,x.mha,maybe\n", r"line 2: volume: expected true or false"),
        ("m.toml", '[[subjects]]\nid = "a"\npalpations = [x.mha]\n', r"not valid TOML: .*line 3"),
        (
            "m.toml",
            '[options]\nflexible_layer_mm = 60\n[[subjects]]\nid = "a"\npalpations = ["x.mha"]\n'
            '[[subjects]]\nid = "b"\npalpations = ["y.mha"]\noptions = { smoothnes = 1 }\n',
            r"subjects\[1\] \(id 'b'\): options: unknown option\(s\) smoothnes",
        ),
        ("m.toml", '[[subjects]]\nid = "a"\npalpations = ["x.mha"]\n', r"subjects\[0\].*flexible_layer_mm: required"),
        ("m.toml", '[options]\nbasis = "bspline:2x8"\n[[subjects]]\nid="a"\npalpations=["x"]\n', r"options: basis:"),
        ("m.toml", '[options]\ncoupling = "strain"\n', r"options: coupling: expected one of stiffness, force"),
        ("m.toml", '[options]\nanchor = "lumen"\n', r"options: anchor: expected one of image, vessel"),
        ("m.toml", '[[subjects]]\nid = "../a"\npalpations = ["x.mha"]\n', r"subjects\[0\].*id: expected a name"),
        (
            "m.toml",
            '[options]\nflexible_layer_mm = 60\n[[subjects]]\nid = "a"\npalpations = ["x.mha"]\n'
            'sweeps = ["one/s.mha", "two/s.seq.nrrd"]\n',
            r"two sweeps named 's'",
        ),
        ("m.toml", '[options]\nflexible_layer_mm = 60\n[[subjects]]\nid = "a"\npalpations = []\n', "at least one"),
        ("m.toml", "[options]\nflexible_layer_mm = -1\n", r"options: flexible_layer_mm: expected a finite number > 0"),
    ],
)
def test_manifest_errors_name_the_line_or_field(tmp_path: Path, name: str, text: str, message: str) -> None:
    path = _write_manifest(tmp_path, text, name)
    with pytest.raises(FileFormatError, match=message) as caught:
        read_manifest(path)
    assert str(path) in str(caught.value)


def test_diagnosis_unit_reports_a_missing_gap_module_and_writes_the_diagnosis(tmp_path: Path, monkeypatch) -> None:
    import types

    task = TaskSpec(
        "p/diagnosis",
        "diagnosis",
        "p",
        (tmp_path / "a.mha",),
        tuple(tmp_path / "p" / name for name in ("diagnosis.json", "record_next.json", "report.html")),
        Options(),
    )
    monkeypatch.setitem(sys.modules, "usdeform.gap", None)  # an installation without the module
    record = run_task(task)
    assert record["status"] == "failed"
    assert "usdeform.gap is not available" in record["error"]

    calls = []

    class Diagnosis:
        def to_json(self) -> dict:
            return {"verdict": "explained", "effects": []}

    def diagnose(recordings, *, seed, progress):
        calls.append((recordings, seed, progress))
        return Diagnosis()

    def write_report(diagnosis, out):  # as usdeform.gap.report writes them
        for name in ("diagnosis.json", "record_next.json", "report.html"):
            (out / name).write_text(json.dumps(diagnosis.to_json()))

    monkeypatch.setitem(sys.modules, "usdeform.gap", types.SimpleNamespace(diagnose=diagnose))
    monkeypatch.setitem(sys.modules, "usdeform.gap.report", types.SimpleNamespace(write_report=write_report))
    (tmp_path / "a.mha").write_bytes(b"recording")
    (tmp_path / "p").mkdir(exist_ok=True)
    record = run_task(task)
    assert record["status"] == "done", record
    assert calls == [([str(tmp_path / "a.mha")], 0, False)]
    assert json.loads((tmp_path / "p" / "diagnosis.json").read_text())["verdict"] == "explained"
    assert record["details"] == {"verdict": "explained"}
    assert run_task(task, previous=record)["reused"] is True


def test_without_dask_the_batch_says_how_to_install_it(monkeypatch) -> None:
    from usdeform.batch import batch_client

    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ImportError, match=r"pip install 'usdeform\[cluster\]'"), batch_client():
        pass


MANIFEST_NUMBERS = ("flexible_layer_mm", "smoothness", "spacing_mm", "max_gib", "diagnosis_seed", "compression_level")


def _manifest_with(form: str, name: str, value: str) -> str:
    """A one-subject manifest (TOML or CSV) setting option ``name`` to ``value`` (TOML or CSV text)."""
    layer = "" if name == "flexible_layer_mm" else "60"
    if form == "toml":
        options = ("flexible_layer_mm = 60\n" if layer else "") + f"{name} = {value}\n"
        return f'[options]\n{options}[[subjects]]\nid = "a"\npalpations = ["x.mha"]\n'
    columns = "subject,palpations" + (",flexible_layer_mm" if layer else "") + f",{name}"
    return f"{columns}\na,x.mha{',' + layer if layer else ''},{value}\n"


@pytest.mark.parametrize(
    ("name", "value"),
    [
        (name, value)
        for name in MANIFEST_NUMBERS
        for value in ("inf", "-inf", "nan", "-1", "1e300", "0")
        if not (value == "0" and name == "diagnosis_seed")  # seed 0 is valid
    ],
)
@pytest.mark.parametrize("form", ["toml", "csv"])
def test_every_numeric_option_of_a_manifest_is_checked_when_it_is_read(
    tmp_path: Path, form: str, name: str, value: str
) -> None:
    """Issue 43: ``max_gib = inf`` passed the manifest check, then failed inside Dask naming no field."""
    path = _write_manifest(tmp_path, _manifest_with(form, name, value), f"m.{form}")
    with pytest.raises(FileFormatError, match=rf"{name}: expected (a finite number|an integer)") as caught:
        read_manifest(path)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize("value", ["inf", "nan", "-1", "0", "1e-9", "0.5", "3", "1e300", "x", "2.5e3"])
@pytest.mark.parametrize(
    ("name", "argv"),
    [
        ("spacing_mm", ["reconstruct", "x.mha", "--output", "v.nrrd", "--spacing"]),
        ("max_gib", ["reconstruct", "x.mha", "--output", "v.nrrd", "--max-gib"]),
        ("flexible_layer_mm", ["fit", "x.mha", "--output", "m.json", "--flexible-layer-mm"]),
        ("smoothness", ["fit", "x.mha", "--output", "m.json", "--flexible-layer-mm", "30", "--smoothness"]),
    ],
)
def test_the_command_line_and_a_manifest_accept_the_same_numbers(
    tmp_path: Path, capsys, name: str, argv: list[str], value: str
) -> None:
    from usdeform.cli import build_parser

    try:
        build_parser(argv[0]).parse_args([*argv, value])
        command_line = True
    except SystemExit:
        command_line = False
    assert "Traceback" not in capsys.readouterr().err
    try:
        read_manifest(_write_manifest(tmp_path, _manifest_with("csv", name, value), "m.csv"))
        manifest = True
    except FileFormatError as error:
        assert name in str(error)
        manifest = False
    assert command_line == manifest


@pytest.mark.parametrize("field", ["palpations", "sweeps", "diagnosis"])
def test_a_recording_listed_twice_in_a_subject_is_refused(tmp_path: Path, field: str) -> None:
    """The same recording twice (also as ``a.mha`` and ``./a.mha``) would be fitted or written twice."""
    lists = {"palpations": '["p.mha"]', "sweeps": "[]", "diagnosis": "false"}
    lists[field] = '["a.mha", "./a.mha"]'
    text = '[options]\nflexible_layer_mm = 60\n[[subjects]]\nid = "s"\n' + "".join(
        f"{name} = {value}\n" for name, value in lists.items()
    )
    path = _write_manifest(tmp_path, text)
    with pytest.raises(FileFormatError, match=rf"subjects\[0\] \(id 's'\): {field}: .*a\.mha is listed twice"):
        read_manifest(path)


def test_a_symlink_loop_in_a_manifest_is_named(tmp_path: Path) -> None:
    (tmp_path / "a.mha").symlink_to("b.mha")
    (tmp_path / "b.mha").symlink_to("a.mha")
    path = _write_manifest(
        tmp_path, '[options]\nflexible_layer_mm = 60\n[[subjects]]\nid = "s"\npalpations = ["a.mha"]\n'
    )
    with pytest.raises(FileFormatError, match=r"palpations: .*a\.mha is a loop of symbolic links"):
        read_manifest(path)
    (tmp_path / "m.toml").symlink_to("n.toml")
    (tmp_path / "n.toml").symlink_to("m.toml")
    with pytest.raises(FileFormatError, match=r"m\.toml is a loop of symbolic links"):
        read_manifest(tmp_path / "m.toml")
