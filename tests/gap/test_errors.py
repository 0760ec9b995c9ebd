"""Bad input gets a one-line error naming the file and the field."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.gap import diagnose
from usdeform.gap.command import add_diagnose_command
from usdeform.io import write_sequence


@pytest.fixture(scope="module")
def recording(palpation):
    return palpation()


def test_no_force_field(recording):
    with pytest.raises(InputError, match="recording 0: no ContactForce"):
        diagnose([dataclasses.replace(recording, force=None)], progress=False)


def test_no_probe_displacement(recording):
    with pytest.raises(InputError, match="no ProbeDisplacement"):
        diagnose([dataclasses.replace(recording, probe_displacement=None)], progress=False)


def test_too_few_frames(recording):
    short = dataclasses.replace(
        recording,
        frames=recording.frames[:5],
        timestamps=recording.timestamps[:5],
        probe_to_base=recording.probe_to_base[:5],
        pose_valid=recording.pose_valid[:5],
        force=recording.force[:5],
        probe_displacement=recording.probe_displacement[:5],
    )
    with pytest.raises(InputError, match="frames: 5 frames"):
        diagnose([short], progress=False)


def test_inconsistent_calibration(recording):
    rotated = recording.image_to_probe.copy()
    rotated[:3, :2] = rotated[:3, :2] @ np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    with pytest.raises(InputError, match="ImageToProbeTransform"):
        diagnose([dataclasses.replace(recording, image_to_probe=rotated)], progress=False)


def test_flat_force(recording):
    with pytest.raises(InputError, match="ContactForce: the force varies"):
        diagnose([dataclasses.replace(recording, force=np.full(recording.force.shape, 1.0))], progress=False)


def test_command_reports_one_line_error_naming_the_file(recording, tmp_path, capsys):
    import argparse

    from usdeform.errors import UsdeformError

    path = tmp_path / "no_force.seq.nrrd"
    write_sequence(path, dataclasses.replace(recording, force=None))
    parser = argparse.ArgumentParser()
    add_diagnose_command(parser.add_subparsers())
    args = parser.parse_args(["diagnose", str(path), "--out", str(tmp_path / "out")])
    with pytest.raises(UsdeformError) as error:
        args.run(args)
    message = str(error.value)
    assert "\n" not in message and str(path) in message and "ContactForce" in message


def test_folder_is_expanded_and_sweeps_are_left_out(recording, gap_phantom, tmp_path):
    from usdeform.gap.inputs import as_recordings
    from usdeform.sim import simulate_sweep

    sweep, _ = simulate_sweep(gap_phantom, 5.0, 20.0, 6.0, n_frames=12, rows=64, cols=64)
    write_sequence(tmp_path / "a_palpation.seq.nrrd", recording)
    write_sequence(tmp_path / "b_sweep.mha", sweep)
    (tmp_path / "notes.txt").write_text("not a sequence")
    named, sweeps, known_weights = as_recordings([tmp_path])
    assert [name for name, _ in named] == [str(tmp_path / "a_palpation.seq.nrrd")]
    assert sweeps == [str(tmp_path / "b_sweep.mha")] and known_weights == []
    with pytest.raises(InputError, match="sweeps alone"):
        as_recordings([tmp_path / "b_sweep.mha"])


def test_a_plus_configuration_supplies_the_calibration_a_file_lacks(plus_data, tmp_path):
    """PLUS keeps the Image -> Probe calibration in its XML configuration, not in the sequence file: the real
    tracked sweep (the shared PLUS data) is read only with ``--config``; then what it lacks is the force."""
    import argparse

    from usdeform.errors import UsdeformError

    sweep = plus_data / "SpinePhantomFreehand.igs.mha"
    parser = argparse.ArgumentParser()
    add_diagnose_command(parser.add_subparsers())
    without = parser.parse_args(["diagnose", str(sweep), "--out", str(tmp_path / "a")])
    with pytest.raises(UsdeformError, match=r"ImageToProbeTransform.*--config on the command line"):
        without.run(without)
    config = plus_data / "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"
    with_config = parser.parse_args(["diagnose", str(sweep), "--config", str(config), "--out", str(tmp_path / "b")])
    with pytest.raises(InputError, match="no ContactForce field"):
        with_config.run(with_config)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def _refuse_work(monkeypatch):
    """Make any observation (the first piece of work) fail the test: a refusal must come before it."""
    import usdeform.gap.diagnosis as module

    def observe(*args, **kwargs):
        raise AssertionError("the diagnosis started work on input it should have refused")

    monkeypatch.setattr(module, "observe", observe)


def test_the_same_palpation_given_twice_is_refused(recording, tmp_path, monkeypatch):
    _refuse_work(monkeypatch)
    path = tmp_path / "a.seq.nrrd"
    write_sequence(path, recording)
    with pytest.raises(InputError, match=r"a\.seq\.nrrd: given twice"):
        diagnose([path, path], progress=False)
    copy = tmp_path / "copy" / "b.mha"
    copy.parent.mkdir()
    write_sequence(copy, recording)  # the same frames under another name and format
    with pytest.raises(InputError, match=r"b\.mha: the same frames as .*a\.seq\.nrrd") as error:
        diagnose([path, copy.parent], progress=False)
    assert "\n" not in str(error.value)
    with pytest.raises(InputError, match="recording 1: the same frames as recording 0"):
        diagnose([recording, recording], progress=False)


def test_an_empty_folder_is_refused_by_name(tmp_path, monkeypatch):
    _refuse_work(monkeypatch)
    (tmp_path / "notes.txt").write_text("not a sequence")
    with pytest.raises(InputError, match=f"{tmp_path}: no PLUS sequence files"):
        diagnose([tmp_path], progress=False)


def test_a_negative_seed_is_refused(recording, monkeypatch):
    _refuse_work(monkeypatch)
    with pytest.raises(InputError, match="seed: expected a non-negative integer, got -1"):
        diagnose([recording], seed=-1, progress=False)


def _run_cli(argv, capsys):
    from usdeform.cli import main

    try:
        status = main(argv)
    except SystemExit as exit:  # argparse refuses an option's value: a usage line, then one line naming it
        status = exit.code
        return status, capsys.readouterr().err.strip().splitlines()[-1]
    error = capsys.readouterr().err.strip()
    return status, error


@pytest.mark.parametrize("case", ["existing_file", "under_a_file", "read_only", "seed"])
def test_the_command_refuses_a_bad_out_or_seed_before_reading_a_recording(case, tmp_path, capsys, monkeypatch):
    import usdeform.gap.inputs as module

    def read_sequence(*args, **kwargs):
        raise AssertionError("a recording was read before the options were checked")

    monkeypatch.setattr(module, "read_sequence", read_sequence)
    recording = tmp_path / "palpation.seq.nrrd"
    recording.write_text("never read")
    existing = tmp_path / "out.txt"
    existing.write_text("keep")
    out, extra, expected = {
        "existing_file": (existing, [], f"--out: {existing} is an existing file"),
        "under_a_file": (existing / "sub", [], f"--out: {existing / 'sub'} cannot be created: {existing} is a file"),
        "read_only": (Path("/proc/usdeform-diagnosis"), [], "--out: /proc/usdeform-diagnosis cannot be written"),
        "seed": (tmp_path / "out", ["--seed", "-1"], "--seed: expected an integer from 0 to"),
    }[case]
    status, error = _run_cli(["diagnose", str(recording), "--out", str(out), *extra], capsys)
    assert status == 2 and "\n" not in error and expected in error
    assert existing.read_text() == "keep" and not (tmp_path / "out").exists()
