"""A corrected sequence file keeps its pixel validity mask: the companion file, read back and compounded."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from usdeform.cli import main
from usdeform.errors import FileFormatError
from usdeform.io import pixel_valid_path, read_sequence, read_volume, write_sequence
from usdeform.recording import Recording
from usdeform.volume import compound_recording


def _recording(n: int = 3, rows: int = 12, cols: int = 10) -> Recording:
    rng = np.random.default_rng(4)
    return Recording(
        frames=rng.integers(0, 255, (n, rows, cols), dtype=np.uint8),
        timestamps=np.arange(n, dtype=float),
        probe_to_base=np.tile(np.eye(4), (n, 1, 1)),
        pose_valid=np.ones(n, dtype=bool),
        image_to_probe=np.diag([0.2, 0.2, 1.0, 1.0]),
        force=np.full(n, 2.0),
    )


@pytest.mark.parametrize(
    ("name", "companion_name"),
    [("c.seq.nrrd", "c.valid.seq.nrrd"), ("c.mha", "c.valid.mha"), ("c.nrrd", "c.valid.nrrd")],
)
def test_the_mask_is_written_beside_the_frames_and_read_back(tmp_path: Path, name: str, companion_name: str) -> None:
    recording = _recording()
    valid = np.ones(recording.frames.shape, dtype=bool)
    valid[0, :3] = False
    valid[2, :, -2:] = False
    write_sequence(tmp_path / name, dataclasses.replace(recording, pixel_valid=valid))
    companion = pixel_valid_path(tmp_path / name)
    assert companion.name == companion_name and companion.is_file()
    back = read_sequence(tmp_path / name)
    assert back.pixel_valid is not None and np.array_equal(back.pixel_valid, valid)
    assert "PixelValidFile" not in back.metadata  # a layout field, rewritten on each write
    mask = read_sequence(companion)  # a sequence of its own: 1 where the frame holds data
    assert np.array_equal(mask.frames, valid.astype(np.uint8)) and mask.pixel_valid is None
    assert np.array_equal(mask.probe_to_base, recording.probe_to_base)


def test_a_recording_without_invalid_pixels_writes_no_companion(tmp_path: Path) -> None:
    recording = _recording()
    write_sequence(tmp_path / "c.seq.nrrd", dataclasses.replace(recording, pixel_valid=np.ones((3, 12, 10), bool)))
    assert not pixel_valid_path(tmp_path / "c.seq.nrrd").exists()
    assert read_sequence(tmp_path / "c.seq.nrrd").pixel_valid is None


def test_a_missing_or_mismatched_companion_is_refused_naming_it(tmp_path: Path) -> None:
    recording = _recording()
    valid = np.ones(recording.frames.shape, dtype=bool)
    valid[1, 0, 0] = False
    write_sequence(tmp_path / "c.seq.nrrd", dataclasses.replace(recording, pixel_valid=valid))
    companion = pixel_valid_path(tmp_path / "c.seq.nrrd")
    write_sequence(companion, _recording(n=2))
    with pytest.raises(FileFormatError, match=r"c\.valid\.seq\.nrrd: 2 frames"):
        read_sequence(tmp_path / "c.seq.nrrd")
    companion.unlink()
    with pytest.raises(FileFormatError, match=r"PixelValidFile: 'c\.valid\.seq\.nrrd' is no file beside it"):
        read_sequence(tmp_path / "c.seq.nrrd")


@pytest.fixture(scope="module")
def corrected(tmp_path_factory) -> Path:
    """A palpation and an 8-frame sweep at 8 N of the coarse test phantom, fitted and corrected by the
    command line, with a volume."""
    from usdeform.sim import coarse_phantom, simulate_palpation, simulate_sweep

    phantom, folder = coarse_phantom(), tmp_path_factory.mktemp("corrected")
    write_sequence(folder / "p.seq.nrrd", simulate_palpation(phantom, 20.0, 8.0, n_frames=8, rows=96, cols=96)[0])
    write_sequence(folder / "s.seq.nrrd", simulate_sweep(phantom, 15.0, 15.0, 8.0, n_frames=8, rows=96, cols=96)[0])
    fit = ["fit", str(folder / "p.seq.nrrd"), "--output", str(folder / "m.json"), "--flexible-layer-mm", "40"]
    assert main(fit) == 0
    correct = ["correct", str(folder / "s.seq.nrrd"), "--model", str(folder / "m.json")]
    assert main([*correct, "--output", str(folder / "c.seq.nrrd"), "--volume", str(folder / "v.nrrd")]) == 0
    return folder


def test_correct_writes_the_pixels_without_data_and_compounding_the_file_leaves_them_out(corrected: Path) -> None:
    recording = read_sequence(corrected / "c.seq.nrrd")
    assert pixel_valid_path(corrected / "c.seq.nrrd").is_file()
    valid = recording.pixel_valid
    assert valid is not None and 0 < (~valid).sum() < valid.size // 4  # the pressed-up bottom rows
    assert (recording.frames[~valid] == 0).all()
    written = read_volume(corrected / "v.nrrd")
    again, _ = compound_recording(recording)
    assert np.array_equal(again.image, written.image)
    unmasked, _ = compound_recording(dataclasses.replace(recording, pixel_valid=None))
    assert not np.array_equal(unmasked.image, written.image)  # the mask matters to the volume
