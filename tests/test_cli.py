"""The command line: the README's demo command and PLUS reconstruction, end to end."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from usdeform.cli import main
from usdeform.io import read_volume

PLUS_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "plus"


def test_demo_writes_volumes_and_the_correction_restores_the_vessel(tmp_path: Path, capsys) -> None:
    assert main(["demo", "--output", str(tmp_path), "--frames", "60", "--size", "96"]) == 0
    printed = capsys.readouterr().out
    found = re.search(r"zero force ([\d.]+) mm\^2, deformed ([\d.]+) mm\^2, corrected ([\d.]+) mm\^2", printed)
    assert found, printed
    zero_force, deformed_area, corrected_area = map(float, found.groups())
    assert abs(corrected_area - zero_force) < 0.5 * abs(deformed_area - zero_force)
    corrected, deformed, coverage = (read_volume(tmp_path / name) for name in
                                     ("corrected.nrrd", "deformed.nrrd", "coverage.nrrd"))
    assert corrected.image.shape == deformed.image.shape == coverage.image.shape
    assert np.array_equal(corrected.index_to_world, deformed.index_to_world)
    covered = coverage.image > 0
    assert covered.mean() > 0.5
    assert not np.array_equal(corrected.image[covered], deformed.image[covered])


def test_reconstruct_the_real_plus_sweep(tmp_path: Path, capsys) -> None:
    output, coverage = tmp_path / "spine.nrrd", tmp_path / "coverage.nrrd"
    code = main(["reconstruct", str(PLUS_DATA / "SpinePhantomFreehand.igs.mha"), "--config",
                 str(PLUS_DATA / "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml"),
                 "--output", str(output), "--coverage", str(coverage)])
    assert code == 0
    assert "compounded 21 of 21 frames" in capsys.readouterr().out
    volume, weight = read_volume(output), read_volume(coverage)
    assert volume.image.shape == weight.image.shape
    assert (weight.image > 0).sum() > 10_000
    assert volume.image[weight.image > 0].mean() > 1.0


def test_missing_file_is_a_clear_error_not_a_traceback(tmp_path: Path, capsys) -> None:
    assert main(["reconstruct", str(tmp_path / "missing.mha"), "--output", str(tmp_path / "v.nrrd")]) == 2
    assert "usdeform: error:" in capsys.readouterr().err
    assert not (tmp_path / "v.nrrd").exists()


def test_bad_option_exits_with_usage() -> None:
    with pytest.raises(SystemExit):
        main(["reconstruct", "x.mha", "--output", "v.nrrd", "--compounding", "median"])
