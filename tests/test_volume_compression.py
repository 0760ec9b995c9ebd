"""The compression level of volume files (write_volume's compression_level, the batch manifest's option)."""

import gzip
import zlib
from pathlib import Path

import numpy as np
import pytest
from isal import isal_zlib

from usdeform.batch import read_manifest
from usdeform.errors import FileFormatError, InputError
from usdeform.io import read_volume, write_volume
from usdeform.io.volume_file import DEFAULT_COMPRESSION_LEVEL
from usdeform.volume import Volume, VoxelGrid


def expected_stream(raw: bytes, level: int, window_bits: int) -> bytes:
    """The deflate stream of ``raw`` at ``level``: ISA-L's at level 1, zlib's above."""
    if level == 1:
        return isal_zlib.compress(raw, 1, wbits=window_bits)
    compressor = zlib.compressobj(level, zlib.DEFLATED, window_bits)
    return compressor.compress(raw) + compressor.flush()


def speckle_volume(dtype) -> Volume:
    """A 12 x 20 x 16 volume of smoothed noise (compressible, unlike white noise) with an oblique grid."""
    rng = np.random.default_rng(4)
    noise = rng.random((12, 20, 16))
    smooth = (noise + np.roll(noise, 1, axis=2) + np.roll(noise, 1, axis=1)) / 3
    image = (255 * smooth).astype(dtype)
    index_to_world = np.array([[0.5, 0.1, 0, 3.0], [0, 0.5, 0, -2.0], [0, 0, 0.8, 40.0], [0, 0, 0, 1]])
    return Volume(image, VoxelGrid(image.shape, index_to_world), weight=smooth.astype(np.float32))


def payload(path: Path) -> bytes:
    """The bytes after a NRRD header (blank line) or a MetaImage one (``ElementDataFile = LOCAL`` line)."""
    data = path.read_bytes()
    marker = b"\n\n" if path.suffix == ".nrrd" else b"ElementDataFile = LOCAL\n"
    return data[data.index(marker) + len(marker) :]


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
@pytest.mark.parametrize("level", [1, 3, 6, 9])
@pytest.mark.parametrize("suffix", [".nrrd", ".mha"])
def test_each_level_round_trips_and_is_the_level_written(tmp_path, suffix, level, dtype):
    volume = speckle_volume(dtype)
    path, weight_path = tmp_path / f"v{suffix}", tmp_path / f"w{suffix}"
    write_volume(path, volume, weight_path=weight_path, compression_level=level)
    back = read_volume(path, weight_path=weight_path)
    assert back.image.dtype == dtype and np.array_equal(back.image, volume.image)
    assert np.array_equal(back.weight, volume.weight)
    np.testing.assert_allclose(back.index_to_world, volume.index_to_world, atol=1e-12)
    stream = payload(path)
    raw = np.ascontiguousarray(volume.image, dtype=volume.image.dtype.newbyteorder("<")).tobytes()
    if suffix == ".nrrd":
        assert b"encoding: gzip" in path.read_bytes()[:1000]
        assert gzip.decompress(stream) == raw and stream == expected_stream(raw, level, 31)
    else:
        assert b"CompressedData = True" in path.read_bytes()[:1000]
        assert zlib.decompress(stream) == raw and stream == expected_stream(raw, level, 15)


def test_the_default_level_is_the_fast_one_and_compress_false_writes_raw(tmp_path):
    volume = speckle_volume(np.float32)
    write_volume(tmp_path / "default.mha", volume)
    write_volume(tmp_path / "one.mha", volume, compression_level=1)
    assert DEFAULT_COMPRESSION_LEVEL == 1
    assert (tmp_path / "default.mha").read_bytes() == (tmp_path / "one.mha").read_bytes()
    write_volume(tmp_path / "raw.nrrd", volume, compress=False, compression_level=9)
    assert b"encoding: raw" in (tmp_path / "raw.nrrd").read_bytes()[:1000]
    assert payload(tmp_path / "raw.nrrd") == volume.image.astype("<f4").tobytes()


@pytest.mark.parametrize("level", [0, 10, -1, 2.5, True, "3", None])
@pytest.mark.parametrize("compress", [True, False])
def test_a_bad_level_is_refused_naming_the_option(tmp_path, level, compress):
    with pytest.raises(InputError, match=r"^compression_level: expected an integer from 1 to 9, got "):
        write_volume(tmp_path / "v.nrrd", speckle_volume(np.uint8), compress=compress, compression_level=level)
    assert not list(tmp_path.iterdir())


def test_the_batch_manifest_takes_a_level_and_refuses_a_bad_one(tmp_path):
    subject = '[[subjects]]\nid = "a"\npalpations = ["p.mha"]\n'
    toml = tmp_path / "cohort.toml"
    toml.write_text(f"[options]\nflexible_layer_mm = 60.0\ncompression_level = 6\n{subject}")
    assert read_manifest(toml).subjects[0].options.compression_level == 6
    toml.write_text(f"[options]\nflexible_layer_mm = 60.0\n{subject}")
    assert read_manifest(toml).subjects[0].options.compression_level == DEFAULT_COMPRESSION_LEVEL
    toml.write_text(f"[options]\nflexible_layer_mm = 60.0\ncompression_level = 0\n{subject}")
    with pytest.raises(FileFormatError, match=r"options: compression_level: expected an integer from 1 to 9, got 0"):
        read_manifest(toml)
    csv = tmp_path / "cohort.csv"
    csv.write_text("subject,palpations,flexible_layer_mm,compression_level\na,p.mha,60,9\nb,p.mha,60,\n")
    assert [s.options.compression_level for s in read_manifest(csv).subjects] == [9, DEFAULT_COMPRESSION_LEVEL]
    csv.write_text("subject,palpations,flexible_layer_mm,compression_level\na,p.mha,60,fast\n")
    with pytest.raises(FileFormatError, match=r"line 2: compression_level: expected an integer from 1 to 9"):
        read_manifest(csv)


def test_the_command_line_writes_the_level_asked_for_and_refuses_a_bad_one(tmp_path, capsys):
    from usdeform.cli import main
    from usdeform.io import write_sequence
    from usdeform.live.synthetic import synthetic_scan

    _, _, sweep = synthetic_scan(6, 32, 48)
    write_sequence(tmp_path / "sweep.seq.nrrd", sweep)
    for level in (9, None):
        out = tmp_path / f"v{level}.nrrd"
        chosen = ["--compression-level", str(level)] if level else []
        assert main(["reconstruct", str(tmp_path / "sweep.seq.nrrd"), "--output", str(out), *chosen]) == 0
        raw = np.ascontiguousarray(read_volume(out).image, dtype="<f4").tobytes()
        assert payload(out) == expected_stream(raw, level or DEFAULT_COMPRESSION_LEVEL, 31)
    with pytest.raises(SystemExit) as exit_info:
        main(
            [
                "reconstruct",
                str(tmp_path / "sweep.seq.nrrd"),
                "--output",
                str(tmp_path / "x.nrrd"),
                "--compression-level",
                "0",
            ]
        )
    assert exit_info.value.code == 2
    assert "argument --compression-level: expected an integer from 1 to 9, got '0'" in capsys.readouterr().err
