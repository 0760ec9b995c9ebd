"""PLUS sequence files: exact round trips, the PLUS header layout, and errors on malformed files."""

from __future__ import annotations

import re
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import usdeform.io._metaimage as metaimage_module
from test_recording import random_recording
from usdeform.errors import FileFormatError, InputError
from usdeform.io import read_sequence, write_sequence
from usdeform.recording import Recording

FORMATS = [
    ("rec.mha", True),
    ("rec.mha", False),
    ("rec.mhd", True),
    ("rec.mhd", False),
    ("rec.seq.nrrd", True),
    ("rec.seq.nrrd", False),
]


def assert_same_recording(actual: Recording, expected: Recording) -> None:
    for name in ("frames", "timestamps", "probe_to_base", "pose_valid", "image_to_probe"):
        np.testing.assert_array_equal(getattr(actual, name), getattr(expected, name), err_msg=name)
    for name in ("force", "probe_displacement"):
        if getattr(expected, name) is None:
            assert getattr(actual, name) is None, name
        else:
            np.testing.assert_array_equal(getattr(actual, name), getattr(expected, name), err_msg=name)
    assert actual.metadata == expected.metadata


def header_of(path: Path) -> str:
    data = path.read_bytes()
    end = data.index(b"\n\n") if data.startswith(b"NRRD") else data.index(b"ElementDataFile")
    return data[:end].decode()


@pytest.mark.parametrize(("name", "compress"), FORMATS)
def test_round_trip_is_exact(tmp_path: Path, name: str, compress: bool) -> None:
    recording = random_recording(np.random.default_rng(10), count=6, rows=11, cols=13)
    path = tmp_path / name
    write_sequence(path, recording, compress=compress)
    assert_same_recording(read_sequence(path), recording)


@pytest.mark.parametrize("name", ["rec.mha", "rec.seq.nrrd"])
def test_round_trip_without_force_or_displacement_gives_none(tmp_path: Path, name: str) -> None:
    recording = random_recording(np.random.default_rng(11), with_force=False, with_displacement=False)
    write_sequence(tmp_path / name, recording)
    assert "ContactForce" not in header_of(tmp_path / name)
    assert_same_recording(read_sequence(tmp_path / name), recording)


@settings(max_examples=25, deadline=None)
@given(
    count=st.integers(1, 4),
    rows=st.integers(1, 6),
    cols=st.integers(1, 6),
    seed=st.integers(0, 2**32 - 1),
    name=st.sampled_from(["rec.mha", "rec.seq.nrrd"]),
    compress=st.booleans(),
)
def test_round_trip_property(
    tmp_path_factory: pytest.TempPathFactory, count: int, rows: int, cols: int, seed: int, name: str, compress: bool
) -> None:
    rng = np.random.default_rng(seed)
    recording = random_recording(rng, count=count, rows=rows, cols=cols, with_force=bool(seed % 2))
    path = tmp_path_factory.mktemp("seq") / name
    write_sequence(path, recording, compress=compress)
    assert_same_recording(read_sequence(path), recording)


def test_metaimage_header_has_the_plus_layout(tmp_path: Path) -> None:
    recording = random_recording(np.random.default_rng(12), count=3, rows=4, cols=5)
    path = tmp_path / "rec.mha"
    write_sequence(path, recording, compress=True)
    data = path.read_bytes()
    lines = header_of(path).splitlines()
    assert lines[:2] == ["ObjectType = Image", "NDims = 3"]
    for line in (
        "DimSize = 5 4 3",
        "ElementType = MET_UCHAR",
        "Kinds = domain domain list",
        "UltrasoundImageOrientation = MF",
        "UltrasoundImageType = BRIGHTNESS",
        "CompressedData = True",
        "Seq_Frame0001_ProbeToReferenceTransformStatus = INVALID",
        "Seq_Frame0002_ImageStatus = OK",
        "Operator = robot 1",
    ):
        assert line in lines
    pixels_start = data.index(b"ElementDataFile = LOCAL\n") + len(b"ElementDataFile = LOCAL\n")
    compressed_size = int(next(line for line in lines if line.startswith("CompressedDataSize")).split("=")[1])
    assert compressed_size == len(data) - pixels_start
    np.testing.assert_array_equal(
        np.frombuffer(zlib.decompress(data[pixels_start:]), np.uint8), recording.frames.ravel()
    )
    transform_line = next(line for line in lines if line.startswith("Seq_Frame0002_ProbeToReferenceTransform ="))
    np.testing.assert_array_equal(
        np.array(transform_line.split("=")[1].split(), float), recording.probe_to_base[2].ravel()
    )


def test_mhd_stores_pixels_in_a_raw_file_beside_the_header(tmp_path: Path) -> None:
    recording = random_recording(np.random.default_rng(13))
    write_sequence(tmp_path / "rec.mhd", recording, compress=False)
    assert "ElementDataFile = rec.raw" in (tmp_path / "rec.mhd").read_text()
    np.testing.assert_array_equal(np.fromfile(tmp_path / "rec.raw", np.uint8), recording.frames.ravel())


def test_nrrd_header_has_the_plus_layout(tmp_path: Path) -> None:
    recording = random_recording(np.random.default_rng(14), count=3, rows=4, cols=5)
    path = tmp_path / "rec.seq.nrrd"
    write_sequence(path, recording)
    lines = header_of(path).splitlines()
    for line in (
        "dimension: 3",
        "sizes: 5 4 3",
        "kinds: domain domain list",
        "encoding: gzip",
        "ultrasound image orientation:=MF",
        "Seq_Frame0001_ProbeToReferenceTransformStatus:=INVALID",
        "Operator:=robot 1",
    ):
        assert line in lines


@pytest.mark.parametrize(
    ("orientation", "flip"),
    [
        ("UF", (slice(None), slice(None), slice(None, None, -1))),
        ("MNA", (slice(None), slice(None, None, -1))),
        ("UN", (slice(None), slice(None, None, -1), slice(None, None, -1))),
    ],
)
def test_frames_in_other_orientations_are_flipped_to_mf(tmp_path: Path, orientation: str, flip: tuple) -> None:
    recording = random_recording(np.random.default_rng(15))
    path = tmp_path / "rec.mha"
    write_sequence(path, recording, compress=False)
    path.write_bytes(
        path.read_bytes().replace(
            b"UltrasoundImageOrientation = MF\n", f"UltrasoundImageOrientation = {orientation}\n".encode()
        )
    )
    np.testing.assert_array_equal(read_sequence(path).frames, recording.frames[flip])


def numbers(matrix: np.ndarray) -> str:
    return " ".join(repr(float(value)) for value in matrix.ravel())


def test_tracker_transforms_give_probe_to_reference(tmp_path: Path) -> None:
    """A PLUS tracker recording: probe_to_base = inv(ReferenceToTracker) @ ProbeToTracker."""
    recording = random_recording(np.random.default_rng(16), count=2)
    path = tmp_path / "rec.mha"
    write_sequence(path, recording, compress=False)
    reference_to_tracker = np.array([[0, -1, 0, 10.0], [1, 0, 0, -20.0], [0, 0, 1, 30.0], [0, 0, 0, 1]])
    header = path.read_bytes()
    for i in range(2):
        probe_to_tracker = reference_to_tracker @ recording.probe_to_base[i]
        old = f"Seq_Frame{i:04d}_ProbeToReferenceTransform = ".encode()
        start = header.index(old)
        end = header.index(b"\n", start)
        new = (
            f"Seq_Frame{i:04d}_ProbeToTrackerTransform = {numbers(probe_to_tracker)}\n"
            f"Seq_Frame{i:04d}_ReferenceToTrackerTransform = {numbers(reference_to_tracker)}\n"
            f"Seq_Frame{i:04d}_ReferenceToTrackerTransformStatus = {'OK' if i == 0 else 'MISSING'}"
        ).encode()
        header = header[:start] + new + header[end:]
    header = header.replace(b"ProbeToReferenceTransformStatus", b"ProbeToTrackerTransformStatus")
    path.write_bytes(header)
    read = read_sequence(path)
    np.testing.assert_allclose(read.probe_to_base, recording.probe_to_base, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(read.pose_valid, [True, False])


def corrupt(path: Path, old: bytes, new: bytes) -> None:
    data = path.read_bytes()
    assert old in data
    path.write_bytes(data.replace(old, new, 1))


def drop_line(path: Path, prefix: bytes) -> None:
    data = path.read_bytes()
    start = data.index(prefix)
    path.write_bytes(data[:start] + data[data.index(b"\n", start) + 1 :])


@pytest.fixture
def written(tmp_path: Path, request: pytest.FixtureRequest) -> Path:
    name, compress = request.param
    path = tmp_path / name
    write_sequence(path, random_recording(np.random.default_rng(17), count=4, rows=20, cols=30), compress=compress)
    return path


@pytest.mark.parametrize(
    "written", [("rec.mha", True), ("rec.mha", False), ("rec.seq.nrrd", True), ("rec.seq.nrrd", False)], indirect=True
)
def test_truncated_pixel_data_is_reported(written: Path) -> None:
    written.write_bytes(written.read_bytes()[:-100])
    with pytest.raises(FileFormatError, match="pixel data") as info:
        read_sequence(written)
    assert str(written) in str(info.value)


@pytest.mark.parametrize("written", [("rec.mha", True)], indirect=True)
def test_corrupt_zlib_data_is_reported(written: Path) -> None:
    data = bytearray(written.read_bytes())
    start = data.index(b"ElementDataFile = LOCAL\n") + 30
    data[start : start + 50] = bytes(50)
    written.write_bytes(bytes(data))
    with pytest.raises(FileFormatError, match="pixel data"):
        read_sequence(written)


@pytest.mark.parametrize("written", [("rec.mha", False)], indirect=True)
def test_file_truncated_inside_the_header_is_reported(written: Path) -> None:
    written.write_bytes(written.read_bytes()[:500])
    with pytest.raises(FileFormatError, match="no ElementDataFile"):
        read_sequence(written)


@pytest.mark.parametrize("written", [("rec.mha", True)], indirect=True)
def test_missing_dimsize_is_reported(written: Path) -> None:
    drop_line(written, b"DimSize = ")
    with pytest.raises(FileFormatError, match="DimSize is missing"):
        read_sequence(written)


@pytest.mark.parametrize("written", [("rec.mha", True)], indirect=True)
def test_bad_header_line_is_reported(written: Path) -> None:
    corrupt(written, b"Kinds = domain domain list\n", b"Kinds domain domain list\n")
    with pytest.raises(FileFormatError, match=r"header line \d+: expected 'Name = value'"):
        read_sequence(written)


@pytest.mark.parametrize("written", [("rec.mha", True), ("rec.seq.nrrd", True)], indirect=True)
def test_unparsable_transform_names_the_field(written: Path) -> None:
    separator = b":=" if written.suffix == ".nrrd" else b" = "
    corrupt(
        written,
        b"Seq_Frame0001_ProbeToReferenceTransform" + separator,
        b"Seq_Frame0001_ProbeToReferenceTransform" + separator + b"abc ",
    )
    with pytest.raises(FileFormatError, match="Seq_Frame0001_ProbeToReferenceTransform: expected 16 numbers, got 17"):
        read_sequence(written)
    corrupt(written, b"abc ", b"")
    corrupt(written, b"Seq_Frame0001_Timestamp" + separator, b"Seq_Frame0001_Timestamp" + separator + b"x")
    with pytest.raises(FileFormatError, match="Seq_Frame0001_Timestamp: cannot parse"):
        read_sequence(written)


@pytest.mark.parametrize("written", [("rec.mha", True), ("rec.seq.nrrd", False)], indirect=True)
def test_missing_transform_names_the_frame(written: Path) -> None:
    drop_line(written, b"Seq_Frame0002_ProbeToReferenceTransform" + (b":=" if written.suffix == ".nrrd" else b" = "))
    with pytest.raises(
        FileFormatError, match="frame 2: field Seq_Frame0002_ProbeToReferenceTransform is missing"
    ) as info:
        read_sequence(written)
    assert str(written) in str(info.value)


@pytest.mark.parametrize("written", [("rec.mha", True)], indirect=True)
def test_missing_force_of_one_frame_names_the_frame(written: Path) -> None:
    drop_line(written, b"Seq_Frame0003_ContactForce = ")
    with pytest.raises(FileFormatError, match="frame 3: field Seq_Frame0003_ContactForce is missing"):
        read_sequence(written)


@pytest.mark.parametrize("written", [("rec.mha", True)], indirect=True)
def test_field_of_a_frame_beyond_the_image_is_reported(written: Path) -> None:
    corrupt(written, b"ElementDataFile = LOCAL\n", b"Seq_Frame0099_Timestamp = 1\nElementDataFile = LOCAL\n")
    with pytest.raises(FileFormatError, match="Seq_Frame0099_Timestamp: frame 99 is beyond the 4 frames"):
        read_sequence(written)


@pytest.mark.parametrize("written", [("rec.mha", True)], indirect=True)
def test_missing_calibration_without_config_is_reported(written: Path) -> None:
    data = written.read_bytes()
    for i in range(4):
        data = data.replace(
            f"Seq_Frame{i:04d}_ImageToProbeTransform = ".encode(), f"Seq_Frame{i:04d}_Unused = ".encode()
        )
    written.write_bytes(data)
    with pytest.raises(
        FileFormatError, match="no Seq_FrameNNNN_ImageToProbeTransform field; pass the PLUS configuration"
    ):
        read_sequence(written)


@pytest.mark.parametrize("written", [("rec.mha", True)], indirect=True)
def test_decreasing_timestamps_in_a_file_are_a_file_error(written: Path) -> None:
    drop_line(written, b"Seq_Frame0002_Timestamp = ")
    corrupt(written, b"Seq_Frame0002_ImageStatus", b"Seq_Frame0002_Timestamp = -1\nSeq_Frame0002_ImageStatus")
    with pytest.raises(FileFormatError, match="timestamps: must be non-decreasing, frame 2"):
        read_sequence(written)


def test_failed_write_leaves_the_previous_file_and_no_temporary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "rec.mha"
    first = random_recording(np.random.default_rng(18))
    write_sequence(path, first)
    before = path.read_bytes()
    atomic_output = metaimage_module.atomic_output

    @contextmanager
    def failing_atomic_output(target: Path) -> Iterator[BinaryIO]:
        """Fails after part of the file went to the temporary file."""
        with atomic_output(target) as handle:
            handle.write(b"ObjectType = Image\n")
            raise OSError("disk full")
            yield handle

    monkeypatch.setattr(metaimage_module, "atomic_output", failing_atomic_output)
    with pytest.raises(OSError, match="disk full"):
        write_sequence(path, random_recording(np.random.default_rng(19)))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.mha"]


def test_writing_rejects_bad_paths_and_reserved_metadata(tmp_path: Path) -> None:
    recording = random_recording(np.random.default_rng(20))
    with pytest.raises(InputError, match=r"must end in \.mha, \.mhd, \.seq\.nrrd or \.nrrd"):
        write_sequence(tmp_path / "rec.png", recording)
    with pytest.raises(InputError, match="recording: expected a Recording"):
        write_sequence(tmp_path / "rec.mha", recording.frames)
    for key in ("DimSize", "Seq_Frame0000_Extra", "kinds"):
        reserved = Recording(
            **{**{n: getattr(recording, n) for n in recording.__dataclass_fields__}, "metadata": {key: "1"}}
        )
        with pytest.raises(InputError, match=f"metadata: key '{key}'"):
            write_sequence(tmp_path / "rec.mha", reserved)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["sweep.mha", "sweep.seq.nrrd"])
def test_invalid_poses_holding_nan_round_trip_as_invalid(tmp_path: Path, name: str) -> None:
    """Tracking dropouts: a pose marked invalid may hold NaN; it is written as identity (as PLUS does)."""
    recording = random_recording(np.random.default_rng(4), count=3)
    probe_to_base = recording.probe_to_base.copy()
    probe_to_base[1] = np.nan
    dropout = Recording(
        recording.frames,
        recording.timestamps,
        probe_to_base,
        np.array([True, False, True]),
        recording.image_to_probe,
        recording.force,
        recording.probe_displacement,
    )
    write_sequence(tmp_path / name, dropout)
    read = read_sequence(tmp_path / name)
    np.testing.assert_array_equal(read.pose_valid, [True, False, True])
    np.testing.assert_array_equal(read.probe_to_base[[0, 2]], recording.probe_to_base[[0, 2]])
    np.testing.assert_array_equal(read.probe_to_base[1], np.eye(4))


@pytest.mark.parametrize(("name", "compress"), FORMATS)
def test_further_numbers_per_frame_are_written_and_read_back(tmp_path: Path, name: str, compress: bool) -> None:
    from usdeform.io.sequence_file import read_frame_series

    recording = random_recording(np.random.default_rng(3), count=5, rows=6, cols=7)
    load = np.array([0.0, 2.5, 5.0, 2.5, 1e-7])
    path = tmp_path / name
    write_sequence(path, recording, compress=compress, frame_series={"KnownLoad": load})
    np.testing.assert_allclose(read_frame_series(path, "KnownLoad"), load, rtol=1e-12)
    assert_same_recording(read_sequence(path), recording)


@pytest.mark.parametrize(
    ("series", "message"),
    [
        ({"Known Load": [0.0] * 5}, "'Known Load' is no field name"),
        ({"ContactForce": [0.0] * 5}, "'ContactForce' is a per-frame field the recording itself writes"),
        ({"KnownLoad": [0.0] * 4}, "KnownLoad: expected 5 finite numbers, one a frame, got shape (4,)"),
        ({"KnownLoad": [0.0, 1.0, np.nan, 0.0, 0.0]}, "KnownLoad: expected 5 finite numbers"),
        ({"KnownLoad": ["x"] * 5}, "KnownLoad: expected numbers"),
    ],
)
def test_further_numbers_per_frame_are_checked_before_writing(tmp_path: Path, series, message) -> None:
    path = tmp_path / "rec.seq.nrrd"
    with pytest.raises(InputError, match=f"frame_series: {re.escape(message)}"):
        write_sequence(path, random_recording(np.random.default_rng(3), count=5, rows=6, cols=7), frame_series=series)
    assert not path.exists()
