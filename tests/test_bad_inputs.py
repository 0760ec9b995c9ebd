"""A catalogue of bad inputs through the API and the command line (issue 11).

Each case asserts the exception class (or exit status 2 on the command line), that the message
names the file, field or argument at fault (and the frame, where one frame is at fault), that the
command line prints one line and no traceback, and that no output (not even a temporary file) is
left behind.
"""

from __future__ import annotations

import bz2
import gzip
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import warnings
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from usdeform import _core
from usdeform.cli import main
from usdeform.correction import correct_frames
from usdeform.errors import FileFormatError, InputError, MemoryLimitError, UsdeformError
from usdeform.io import (
    SampledProfiles,
    load_model,
    read_plus_config,
    read_sequence,
    read_volume,
    save_model,
    write_sequence,
    write_volume,
)
from usdeform.recording import Recording, image_to_probe_from_geometry
from usdeform.regression import Normalization, QuadraticDisplacementModel, StiffnessProfile
from usdeform.validation import ForceClampWarning, memory_bytes
from usdeform.volume import Compounder, HoleFillingElement, Volume, VoxelGrid, fill_holes

ROWS = COLS = 32
N_FRAMES = 8
MAX_FORCE_N = 10.0
PROFILE = StiffnessProfile(0.05, 1.5, 0.0)


def good_recording() -> Recording:
    rng = np.random.default_rng(0)
    poses = np.repeat(np.eye(4)[np.newaxis], N_FRAMES, axis=0)
    poses[:, 1, 3] = np.linspace(0.0, 14.0, N_FRAMES)
    return Recording(
        frames=rng.integers(0, 256, (N_FRAMES, ROWS, COLS), dtype=np.uint8),
        timestamps=np.arange(N_FRAMES) * 0.1,
        probe_to_base=poses,
        pose_valid=np.ones(N_FRAMES, dtype=bool),
        image_to_probe=image_to_probe_from_geometry(ROWS, COLS, depth_mm=20.0, width_mm=20.0),
        force=np.linspace(2.0, 8.0, N_FRAMES),
        probe_displacement=np.linspace(1.0, 3.0, N_FRAMES),
    )


def good_model(coefficients: float = 0.1, rows: int = ROWS, cols: int = COLS) -> QuadraticDisplacementModel:
    normalization = Normalization.for_frames(rows, cols, MAX_FORCE_N, 4.0, lateral_scale=2.0, axial_scale=3.0)
    return QuadraticDisplacementModel(np.full((2, 10), coefficients), normalization, 64, frame_shape=(rows, cols))


SAMPLED = SampledProfiles(np.array([[0.0, 0.0, 0.0], [0.0, 14.0, 0.0]]), (PROFILE, PROFILE))
CONFIG = """<PlusConfiguration version="2.1">
  <CoordinateDefinitions>
    <Transform From="Image" To="Probe" Matrix="{matrix}" />
  </CoordinateDefinitions>
  <VolumeReconstruction OutputSpacing="{spacing}" {extra} />
</PlusConfiguration>
"""
GOOD_CALIBRATION = " ".join(str(v) for v in image_to_probe_from_geometry(ROWS, COLS, 20.0, 20.0).ravel())


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Good inputs: sweep.mha (raw), sweep.seq.nrrd (raw), sweep.gz.seq.nrrd, volume.nrrd, model.json, config.xml."""
    folder = tmp_path_factory.mktemp("good")
    recording = good_recording()
    write_sequence(folder / "sweep.mha", recording, compress=False)
    write_sequence(folder / "sweep.seq.nrrd", recording, compress=False)
    write_sequence(folder / "sweep.gz.seq.nrrd", recording, compress=True)
    grid = VoxelGrid((4, 5, 6), np.diag([0.5, 0.5, 0.5, 1.0]))
    volume = Volume(np.ones(grid.shape, np.float32), grid, np.ones(grid.shape, np.float32))
    write_volume(folder / "volume.nrrd", volume, compress=False, weight_path=folder / "weight.nrrd")
    write_volume(folder / "volume.mha", volume, compress=False)
    save_model(folder / "model.json", good_model(), SAMPLED)
    (folder / "config.xml").write_text(CONFIG.format(matrix=GOOD_CALIBRATION, spacing="0.5 0.5 0.5", extra=""))
    return folder


# ---------------------------------------------------------------------------------------------
# Helpers that make a bad file from a good one.


def edit_metaimage(source: Path, target: Path, **changes: str | None) -> Path:
    """Copy a MetaImage file, changing (or with None removing) header fields."""
    raw = source.read_bytes()
    end = raw.index(b"ElementDataFile")
    end = raw.index(b"\n", end) + 1
    lines = raw[:end].decode().splitlines()
    out = []
    for line in lines:
        name = line.partition("=")[0].strip()
        if name in changes:
            value = changes.pop(name)
            if value is not None:
                out.append(f"{name} = {value}")
        else:
            out.append(line)
    extra = [f"{name} = {value}" for name, value in changes.items() if value is not None]
    out = out[:-1] + extra + out[-1:]  # new fields before ElementDataFile
    target.write_bytes(("\n".join(out) + "\n").encode() + raw[end:])
    return target


def edit_nrrd(source: Path, target: Path, data: bytes | None = None, **changes: str | None) -> Path:
    """Copy a NRRD file, changing header fields (``data_file`` for ``data file``); ``data`` replaces the payload."""
    raw = source.read_bytes()
    end = raw.index(b"\n\n") + 2
    lines = raw[: end - 2].decode().splitlines()
    spaced = ("data_file", "byte_skip", "line_skip", "space_directions")
    changes = {name.replace("_", " ") if name in spaced else name: value for name, value in changes.items()}
    out = []
    for line in lines:
        separator = ":=" if ":=" in line else ":"
        name = line.partition(separator)[0].strip()
        if name in changes:
            value = changes.pop(name)
            if value is not None:
                out.append(f"{name}{separator} {value}" if separator == ":" else f"{name}:={value}")
        else:
            out.append(line)
    out += [f"{name}: {value}" for name, value in changes.items() if value is not None]
    target.write_bytes(("\n".join(out) + "\n\n").encode() + (raw[end:] if data is None else data))
    return target


def matrix_text(matrix: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in np.asarray(matrix).ravel())


def pose(rotation: np.ndarray, last_row: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0)) -> str:
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[3] = last_row
    return matrix_text(matrix)


SHEAR = np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
REFLECTION = np.diag([1.0, 1.0, -1.0])


def calibration(scale_x: float, scale_y: float, skew: float = 0.0) -> str:
    matrix = np.eye(4)
    matrix[:3, 0] = [scale_x, 0.0, 0.0]
    matrix[:3, 1] = [scale_y * skew, 0.0, scale_y * np.sqrt(1 - skew**2)]
    matrix[:3, 2] = [0.0, -1.0, 0.0]
    return matrix_text(matrix)


# ---------------------------------------------------------------------------------------------
# Bad sequence files: read_sequence raises FileFormatError naming the file and the field / frame,
# and 'usdeform reconstruct' exits with 2 and one line.


def mha(**changes: str | None) -> Callable[[Path, Path], Path]:
    return lambda base, tmp: edit_metaimage(base / "sweep.mha", tmp / "bad.mha", **changes)


def nrrd(data: bytes | None = None, source: str = "sweep.seq.nrrd", **changes: str | None) -> Callable:
    return lambda base, tmp: edit_nrrd(base / source, tmp / "bad.seq.nrrd", data, **changes)


def truncated(name: str, keep: float) -> Callable[[Path, Path], Path]:
    def make(base: Path, tmp: Path) -> Path:
        raw = (base / name).read_bytes()
        target = tmp / ("bad" + "".join(Path(name).suffixes))
        target.write_bytes(raw[: int(len(raw) * keep)])
        return target

    return make


def written(name: str, content: bytes) -> Callable[[Path, Path], Path]:
    def make(base: Path, tmp: Path) -> Path:
        (tmp / name).write_bytes(content)
        return tmp / name

    return make


def with_data_file(kind: str, data_file: str) -> Callable[[Path, Path], Path]:
    if kind == "mha":
        return mha(ElementDataFile=data_file)
    return nrrd(data=b"", data_file=data_file)


def gzip_bomb(declared_frames: int) -> Callable[[Path, Path], Path]:
    """A gzip stream of far more zeros than ``sizes`` declares (the issue's 14 MB file declaring 49 KB)."""
    payload = gzip.compress(bytes(40 * 1024 * 1024), compresslevel=9)
    return nrrd(data=payload, source="sweep.gz.seq.nrrd", sizes=f"{COLS} {ROWS} {declared_frames}")


def bzip2_bomb() -> Callable[[Path, Path], Path]:
    return nrrd(data=bz2.compress(bytes(20 * 1024 * 1024)), source="sweep.gz.seq.nrrd", encoding="bzip2")


def zlib_bomb() -> Callable[[Path, Path], Path]:
    payload = zlib.compress(bytes(20 * 1024 * 1024), 9)

    def make(base: Path, tmp: Path) -> Path:
        path = edit_metaimage(
            base / "sweep.mha", tmp / "bad.mha", CompressedData="True", CompressedDataSize=str(len(payload))
        )
        raw = path.read_bytes()
        path.write_bytes(raw[: raw.index(b"ElementDataFile = LOCAL\n") + 24] + payload)
        return path

    return make


def directory(base: Path, tmp: Path) -> Path:
    (tmp / "folder.mha").mkdir()
    return tmp / "folder.mha"


@dataclass(frozen=True)
class FileCase:
    make: Callable[[Path, Path], Path]
    needles: tuple[str, ...]


FRAME_3 = "Seq_Frame0003_ProbeToReferenceTransform"
SEQUENCE_CASES = {
    # Poses that are not rigid: the frames collapsed into a voxel column or smeared.
    "zero rotation": FileCase(mha(**{FRAME_3: pose(np.zeros((3, 3)))}), (FRAME_3, "orthonormal")),
    "rotation scaled by 1.5": FileCase(mha(**{FRAME_3: pose(1.5 * np.eye(3))}), (FRAME_3, "orthonormal")),
    "sheared rotation": FileCase(mha(**{FRAME_3: pose(SHEAR)}), (FRAME_3, "orthonormal")),
    "reflection": FileCase(mha(**{FRAME_3: pose(REFLECTION)}), (FRAME_3, "reflection")),
    "last row of a pose": FileCase(mha(**{FRAME_3: pose(np.eye(3), (0, 0, 1, 1))}), (FRAME_3, "last row")),
    "NaN in a pose": FileCase(mha(**{FRAME_3: pose(np.eye(3)).replace("1.0", "nan", 1)}), (FRAME_3, "non-finite")),
    "15 numbers in a pose": FileCase(mha(**{FRAME_3: "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0"}), (FRAME_3, "16 numbers")),
    "text in a pose": FileCase(mha(**{FRAME_3: "one " * 16}), (FRAME_3, "cannot parse")),
    "nrrd: missing pose of a frame": FileCase(nrrd(**{FRAME_3: None}), (FRAME_3, "missing")),
    "nrrd: rotation scaled by 1.5": FileCase(nrrd(**{FRAME_3: pose(1.5 * np.eye(3))}), (FRAME_3, "orthonormal")),
    # Calibrations: the all-zero ImageToProbeTransform (a 1 x 80 x 1 volume) and 1e6 mm/px.
    "zero calibration": FileCase(
        mha(Seq_Frame0000_ImageToProbeTransform=calibration(0.0, 0.0)), ("Seq_Frame0000_ImageToProbeTransform", "mm")
    ),
    "1e6 mm per pixel": FileCase(
        mha(Seq_Frame0000_ImageToProbeTransform=calibration(1e6, 1e6)), ("ImageToProbeTransform", "1e+06 mm")
    ),
    "1e-9 mm per pixel": FileCase(
        mha(Seq_Frame0000_ImageToProbeTransform=calibration(1e-9, 0.5)), ("ImageToProbeTransform", "1e-09 mm")
    ),
    "skewed pixel axes": FileCase(
        mha(Seq_Frame0000_ImageToProbeTransform=calibration(0.5, 0.5, skew=0.9)),
        ("ImageToProbeTransform", "perpendicular"),
    ),
    "calibration differs between frames": FileCase(
        mha(Seq_Frame0004_ImageToProbeTransform=calibration(0.5, 0.5)), ("Seq_Frame0004_ImageToProbeTransform",)
    ),
    # Timestamps, forces, displacements.
    "decreasing timestamp": FileCase(mha(Seq_Frame0004_Timestamp="0.01"), ("timestamps", "frame 4")),
    "NaN timestamp": FileCase(mha(Seq_Frame0002_Timestamp="nan"), ("Seq_Frame0002_Timestamp", "non-finite")),
    "missing timestamp": FileCase(mha(Seq_Frame0005_Timestamp=None), ("Seq_Frame0005_Timestamp", "frame 5")),
    "infinite force": FileCase(mha(Seq_Frame0001_ContactForce="inf"), ("Seq_Frame0001_ContactForce", "non-finite")),
    "force 1e999": FileCase(mha(Seq_Frame0001_ContactForce="1e999"), ("Seq_Frame0001_ContactForce",)),
    "text force": FileCase(mha(Seq_Frame0001_ContactForce="heavy"), ("Seq_Frame0001_ContactForce", "cannot parse")),
    "NaN displacement": FileCase(
        mha(Seq_Frame0006_ProbeDisplacement="nan"), ("Seq_Frame0006_ProbeDisplacement", "non-finite")
    ),
    "a frame beyond the data": FileCase(mha(Seq_Frame0099_Timestamp="1.0"), ("Seq_Frame0099_Timestamp", "frame 99")),
    # Sizes and layout.
    "DimSize 2^32 x 2^32": FileCase(mha(DimSize="4294967296 4294967296 1"), ("DimSize",)),
    "DimSize product over memory": FileCase(mha(DimSize="2000000000 2000000000 8"), ("DimSize", "memory")),
    "negative DimSize": FileCase(mha(DimSize=f"{COLS} -{ROWS} {N_FRAMES}"), ("DimSize", "negative")),
    "DimSize of 2 numbers": FileCase(mha(DimSize=f"{COLS} {ROWS}"), ("DimSize", "3 numbers")),
    "DimSize of 5000 digits": FileCase(mha(DimSize="9" * 5000 + " 1 1"), ("DimSize",)),
    "NDims 0": FileCase(mha(NDims="0"), ("NDims",)),
    "NDims 100": FileCase(mha(NDims="100"), ("NDims",)),
    "float frames": FileCase(mha(ElementType="MET_FLOAT"), ("ElementType",)),
    "unknown element type": FileCase(mha(ElementType="MET_COMPLEX"), ("ElementType",)),
    "three channels": FileCase(mha(ElementNumberOfChannels="3"), ("ElementNumberOfChannels",)),
    "text pixel data": FileCase(mha(BinaryData="False"), ("BinaryData",)),
    "HeaderSize": FileCase(mha(HeaderSize="12"), ("HeaderSize",)),
    "not an image": FileCase(mha(ObjectType="Mesh"), ("ObjectType",)),
    "kinds list first": FileCase(mha(Kinds="list domain domain"), ("kinds",)),
    "unknown orientation": FileCase(mha(UltrasoundImageOrientation="XY"), ("UltrasoundImageOrientation",)),
    "no pose field": FileCase(
        mha(**{f"Seq_Frame{i:04d}_ProbeToReferenceTransform": None for i in range(N_FRAMES)}), ("no probe pose",)
    ),
    "file list": FileCase(mha(ElementDataFile="LIST"), ("ElementDataFile",)),
    # Pixel data: short, corrupt, or far longer than declared.
    "truncated pixel data": FileCase(truncated("sweep.mha", 0.9), ("pixel data",)),
    "truncated header": FileCase(truncated("sweep.mha", 0.1), ("ElementDataFile",)),
    "corrupt zlib data": FileCase(mha(CompressedData="True"), ("pixel data", "zlib")),
    "zlib bomb": FileCase(zlib_bomb(), ("pixel data", "more than")),
    "CompressedDataSize beyond the file": FileCase(
        mha(CompressedData="True", CompressedDataSize="99999999"), ("CompressedDataSize",)
    ),
    "header not text": FileCase(written("binary.mha", bytes(range(256)) * 8), ("header line 1",)),
    "a field twice": FileCase(written("twice.mha", b"ObjectType = Image\nObjectType = Image\n"), ("twice",)),
    # Data files that never end or do not exist.
    "mha data file /dev/zero": FileCase(with_data_file("mha", "/dev/zero"), ("ElementDataFile", "regular file")),
    "mha data file missing": FileCase(with_data_file("mha", "missing.raw"), ("ElementDataFile", "does not exist")),
    "nrrd data file /dev/zero": FileCase(with_data_file("nrrd", "/dev/zero"), ("data file", "regular file")),
    "nrrd data file missing": FileCase(with_data_file("nrrd", "missing.raw"), ("data file", "does not exist")),
    "nrrd data file list": FileCase(with_data_file("nrrd", "LIST"), ("data file",)),
    "sequence is a folder": FileCase(directory, ("regular file",)),
    # NRRD headers and payloads.
    "nrrd gzip bomb": FileCase(gzip_bomb(N_FRAMES), ("pixel data", "more than")),
    "nrrd bzip2 bomb": FileCase(bzip2_bomb(), ("pixel data", "more than")),
    "nrrd float frames": FileCase(nrrd(type="float", endian=None), ("type", "uint8")),
    "nrrd float frames with endian": FileCase(nrrd(type="float", endian="little"), ("type", "uint8")),
    "nrrd sizes 2^32": FileCase(nrrd(sizes="4294967296 4294967296 1"), ("sizes",)),
    "nrrd sizes over memory": FileCase(nrrd(sizes="2000000000 2000000000 8"), ("sizes", "memory")),
    "nrrd dimension mismatch": FileCase(nrrd(dimension="4"), ("sizes",)),
    "nrrd unknown encoding": FileCase(nrrd(encoding="zstd"), ("encoding",)),
    "nrrd truncated raw data": FileCase(truncated("sweep.seq.nrrd", 0.8), ("pixel data",)),
    "nrrd truncated gzip": FileCase(truncated("sweep.gz.seq.nrrd", 0.8), ("pixel data",)),
    "nrrd corrupt gzip": FileCase(nrrd(data=b"\x1f\x8b" + bytes(200), source="sweep.gz.seq.nrrd"), ("pixel data",)),
    "nrrd byte skip -1 with gzip": FileCase(nrrd(source="sweep.gz.seq.nrrd", byte_skip="-1"), ("byte skip",)),
    "nrrd negative line skip": FileCase(nrrd(line_skip="-3"), ("line skip",)),
    "nrrd text sizes": FileCase(nrrd(sizes="a b c"), ("header",)),
    "nrrd kinds": FileCase(nrrd(kinds="list domain domain"), ("kinds",)),
    "nrrd no magic": FileCase(written("bad.seq.nrrd", b"NRRD0005\nthis is not a field\n\n"), ("header",)),
}


def empty_and_misnamed_cases() -> dict[str, FileCase]:
    """Files that are empty, or named NRRD without being NRRD (issue 43: a 0-byte .seq.nrrd was reported as
    MetaImage without an ElementDataFile field), for every suffix a sequence file may have."""
    cases = {}
    for suffix in (".mha", ".mhd", ".seq.nrrd", ".nrrd"):
        cases[f"empty {suffix}"] = FileCase(written("empty" + suffix, b""), ("empty (0 bytes)",))
        cases[f"one newline {suffix}"] = FileCase(written("blank" + suffix, b"\n"), ())
    for suffix in (".seq.nrrd", ".nrrd", ".SEQ.NRRD"):
        cases[f"MetaImage named {suffix}"] = FileCase(
            lambda base, tmp, suffix=suffix: Path(shutil.copy(base / "sweep.mha", tmp / ("sweep" + suffix))),
            ("not an NRRD file", "NRRD000x"),
        )
        cases[f"text named {suffix}"] = FileCase(written("text" + suffix, b"hello"), ("not an NRRD file", "hello"))
    return cases


SEQUENCE_CASES.update(empty_and_misnamed_cases())


def _assert_names(message: str, path: Path, needles: tuple[str, ...]) -> None:
    assert str(path) in message
    for needle in needles:
        assert needle in message, f"{needle!r} not in {message!r}"


@pytest.mark.parametrize("case", SEQUENCE_CASES.values(), ids=SEQUENCE_CASES.keys())
def test_bad_sequence_file(base: Path, tmp_path: Path, case: FileCase) -> None:
    path = case.make(base, tmp_path)
    with pytest.raises(FileFormatError) as raised:
        read_sequence(path)
    _assert_names(str(raised.value), path, case.needles)


@pytest.mark.parametrize("case", SEQUENCE_CASES.values(), ids=SEQUENCE_CASES.keys())
def test_bad_sequence_file_on_the_command_line(
    base: Path, tmp_path: Path, capsys: pytest.CaptureFixture, case: FileCase
) -> None:
    path = case.make(base, tmp_path)
    message = run_failing(capsys, tmp_path, ["reconstruct", str(path), "--output", str(tmp_path / "out" / "v.nrrd")])
    _assert_names(message, path, case.needles)


# ---------------------------------------------------------------------------------------------
# Bad volume, model and configuration files.


def volume_nrrd(**changes: str | None) -> Callable[[Path, Path], Path]:
    return lambda base, tmp: edit_nrrd(base / "volume.nrrd", tmp / "bad.nrrd", **changes)


def model_file(change: Callable[[dict], object] | None = None, text: str | None = None) -> Callable:
    def make(base: Path, tmp: Path) -> Path:
        path = tmp / "bad.json"
        if text is not None:
            path.write_text(text)
            return path
        document = json.loads((base / "model.json").read_text())
        assert change is not None
        change(document)
        path.write_text(json.dumps(document))
        return path

    return make


def config(matrix: str = GOOD_CALIBRATION, spacing: str = "0.5 0.5 0.5", extra: str = "") -> Callable:
    def make(base: Path, tmp: Path) -> Path:
        path = tmp / "bad.xml"
        path.write_text(CONFIG.format(matrix=matrix, spacing=spacing, extra=extra))
        return path

    return make


def nested(depth: int) -> str:
    return "[" * depth + "]" * depth


OTHER_FILE_CASES: dict[str, tuple[Callable[[Path], object], FileCase]] = {
    "volume 2-D": (read_volume, FileCase(volume_nrrd(dimension="2", sizes="6 5"), ("dimension",))),
    "volume NaN direction": (
        read_volume,
        FileCase(volume_nrrd(space_directions="(nan,0,0) (0,0.5,0) (0,0,0.5)"), ("space directions",)),
    ),
    "volume gzip bomb": (
        read_volume,
        FileCase(volume_nrrd(encoding="gzip", data=None), ("pixel data",)),
    ),
    "volume sizes over memory": (read_volume, FileCase(volume_nrrd(sizes="2000000 2000000 2000000"), ("sizes",))),
    "volume data file /dev/zero": (read_volume, FileCase(volume_nrrd(data_file="/dev/zero"), ("regular file",))),
    "volume MetaImage NDims 2": (
        read_volume,
        FileCase(lambda b, t: edit_metaimage(b / "volume.mha", t / "bad.mha", NDims="2", DimSize="6 20"), ("NDims",)),
    ),
    "model n_intervals 1e12": (
        load_model,
        FileCase(model_file(lambda d: d.update(n_intervals=10**12)), ("n_intervals", "1000000000000")),
    ),
    "model n_intervals 1e30": (
        load_model,
        FileCase(model_file(lambda d: d.update(n_intervals=10**30)), ("n_intervals",)),
    ),
    "model frame_shape 1e12": (
        load_model,
        FileCase(model_file(lambda d: d.update(frame_shape=[10**12, 32])), ("frame_shape[0]",)),
    ),
    "model B-spline of 1e9 functions": (
        load_model,
        FileCase(model_file(lambda d: d.update(basis={"name": "bspline", "n_y": 10**9, "n_x": 4})), ("basis.n_y",)),
    ),
    "model nested 100000 deep": (load_model, FileCase(model_file(text=nested(100_000)), ("not a model file",))),
    "model 5000-digit integer": (
        load_model,
        FileCase(
            model_file(text='{"format": "usdeform-deformation-model", "version": ' + "7" * 5000 + "}"), ("digits",)
        ),
    ),
    "model NaN coefficient": (
        load_model,
        FileCase(model_file(lambda d: d["coefficients"][0].__setitem__(3, float("nan"))), ("coefficients[0][3]",)),
    ),
    "model not JSON": (load_model, FileCase(model_file(text="{not json"), ("not JSON",))),
    "model empty": (load_model, FileCase(model_file(text=""), ("empty (0 bytes)",))),
    "model version 99": (load_model, FileCase(model_file(lambda d: d.update(version=99)), ("version",))),
    "model /dev/zero": (load_model, FileCase(lambda b, t: Path("/dev/zero"), ("regular file",))),
    "config OutputExtent 2^42": (
        read_plus_config,
        FileCase(
            config(extra='OutputOrigin="0 0 0" OutputExtent="0 4398046511103 0 4398046511103 0 4398046511103"'),
            ("OutputExtent",),
        ),
    ),
    "config OutputExtent reversed": (
        read_plus_config,
        FileCase(config(extra='OutputOrigin="0 0 0" OutputExtent="0 10 5 0 0 10"'), ("OutputExtent",)),
    ),
    "config zero calibration": (
        read_plus_config,
        FileCase(config(matrix="0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 1"), ("Image->Probe", "pixel size")),
    ),
    "config 1e6 mm per pixel": (
        read_plus_config,
        FileCase(config(matrix=calibration(1e6, 1e6)), ("Image->Probe", "1e+06 mm")),
    ),
    "config zero spacing": (read_plus_config, FileCase(config(spacing="0 0.5 0.5"), ("OutputSpacing",))),
    "config malformed XML": (read_plus_config, FileCase(written("bad.xml", b"<Plus><unclosed></Plus>"), ("XML",))),
    "config /dev/zero": (read_plus_config, FileCase(lambda b, t: Path("/dev/zero"), ("regular file",))),
}


def disagreeing_model_cases() -> dict[str, tuple[Callable[[Path], object], FileCase]]:
    """Model files whose fields each pass alone but not together (issue 43): pixel scales that are not
    those of the frame shape (on 32 x 32 frames: 31), and stiffness profiles that do not rise over the
    fitted force range (0-10 N): falling from the start, all zeros, peaking below 10 N, flat at the start."""

    def scale(key: str, value: float) -> Callable[[dict], object]:
        return lambda d: d["normalization"].update({key: value})

    def version_1(key: str, value: float) -> Callable[[dict], object]:
        return lambda d: (d.update(version=1), d.pop("frame_shape"), d["normalization"].update({key: value}))

    def profile(index: int, c1: float, c2: float, c3: float) -> Callable[[dict], object]:
        return lambda d: d["sampled_positions"][index].update(profile={"c1": c1, "c2": c2, "c3": c3})

    cases: dict[str, tuple[Callable[[Path], object], FileCase]] = {}
    for key in ("x_scale", "y_scale"):
        for value in (126.0, 1e-300, 30.0, 32.0, 0.5, 1e6):
            needles = (f"normalization.{key}", f"{value:g}", "frame_shape 32 x 32")
            cases[f"model {key} {value:g}"] = (load_model, FileCase(model_file(scale(key, value)), needles))
        for value in (126.4, 1e-300, 31.5):
            cases[f"model version 1 {key} {value:g}"] = (
                load_model,
                FileCase(model_file(version_1(key, value)), (f"normalization.{key}", "version 1")),
            )
    coefficients = {"falling": (0.05, -1.5, 0.0), "zero": (0.0, 0.0, 0.0), "peaks at 0.56 N": (-1.0, 1.5, 0.0),
                    "flat at the start": (0.5, 0.0, 0.0), "falls after a preload": (0.0, -1.0, 2.0)}  # fmt: skip
    for name, (c1, c2, c3) in coefficients.items():
        for index in (0, 1):
            needles = (f"sampled_positions[{index}].profile", "does not rise", "0-10 N")
            cases[f"model profile {index} {name}"] = (
                load_model,
                FileCase(model_file(profile(index, c1, c2, c3)), needles),
            )
    return cases


OTHER_FILE_CASES.update(disagreeing_model_cases())


@pytest.mark.parametrize(("reader", "case"), OTHER_FILE_CASES.values(), ids=OTHER_FILE_CASES.keys())
def test_bad_volume_model_or_config_file(
    base: Path, tmp_path: Path, reader: Callable[[Path], object], case: FileCase
) -> None:
    path = case.make(base, tmp_path)
    with pytest.raises(FileFormatError) as raised:
        reader(path)
    _assert_names(str(raised.value), path, case.needles)


def test_a_gzip_bomb_is_refused_within_its_declared_size(base: Path, tmp_path: Path) -> None:
    """The issue's case: 40 MB of zeros in a small gzip stream declaring one 32 x 32 frame. The
    reader stops after the declared size (+1 byte), so it neither fills memory nor takes long."""
    import resource
    import time

    path = gzip_bomb(1)(base, tmp_path)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    with pytest.raises(FileFormatError, match="more than"):
        read_sequence(path)
    assert time.perf_counter() - start < 1.0
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 20 * 1024  # kB: far below 40 MB


# ---------------------------------------------------------------------------------------------
# Bad arguments through the API.


def recording_with(**changes: object) -> Callable[[], object]:
    def make() -> object:
        good = good_recording()
        fields = {name: getattr(good, name) for name in ("frames", "timestamps", "probe_to_base", "pose_valid")}
        fields.update(image_to_probe=good.image_to_probe, force=good.force, probe_displacement=good.probe_displacement)
        for name, value in changes.items():
            fields[name] = value(np.array(fields[name])) if callable(value) else value
        return Recording(**fields)  # type: ignore[arg-type]

    return make


def set_frame(index: int, rotation: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    def change(poses: np.ndarray) -> np.ndarray:
        poses[index, :3, :3] = rotation
        return poses

    return change


def set_value(index: int, value: float) -> Callable[[np.ndarray], np.ndarray]:
    def change(values: np.ndarray) -> np.ndarray:
        values[index] = value
        return values

    return change


FRAMES = np.zeros((2, ROWS, COLS), np.uint8)
HOLEY = Volume(np.zeros((4, 4, 4), np.float32), VoxelGrid((4, 4, 4), np.eye(4)), np.zeros((4, 4, 4), np.float32))
GRID = VoxelGrid((4, 4, 4), np.eye(4))


def corrected(forces: object = 5.0, model: object = None, frames: np.ndarray = FRAMES, **options: object) -> Callable:
    return lambda: correct_frames(frames, forces, PROFILE, model or good_model(), **options)  # type: ignore[arg-type]


@dataclass(frozen=True)
class ApiCase:
    call: Callable[[], object]
    error: type[Exception]
    needles: tuple[str, ...]


API_CASES = {
    "zero rotation": ApiCase(recording_with(probe_to_base=set_frame(2, np.zeros((3, 3)))), InputError,
                             ("probe_to_base", "frame 2", "orthonormal")),
    "rotation scaled by 1.5": ApiCase(recording_with(probe_to_base=set_frame(5, 1.5 * np.eye(3))), InputError,
                                      ("probe_to_base", "frame 5", "orthonormal")),
    "reflection": ApiCase(recording_with(probe_to_base=set_frame(1, REFLECTION)), InputError,
                          ("probe_to_base", "frame 1", "reflection")),
    "sheared": ApiCase(recording_with(probe_to_base=set_frame(7, SHEAR)), InputError, ("probe_to_base", "frame 7")),
    "zero calibration": ApiCase(recording_with(image_to_probe=np.diag([0.0, 0.0, 0.0, 1.0])), InputError,
                                ("image_to_probe", "pixel size")),
    "1e6 mm per pixel": ApiCase(recording_with(image_to_probe=np.diag([1e6, 1e6, 1.0, 1.0])), InputError,
                                ("image_to_probe", "1e+06 mm")),
    "parallel pixel axes": ApiCase(
        recording_with(image_to_probe=np.array([[0.5, 0.5, 0, 0], [0, 0, 1, 0], [0, 0, 0, 0], [0, 0, 0, 1.0]])),
        InputError, ("image_to_probe", "perpendicular")),
    "decreasing timestamps": ApiCase(recording_with(timestamps=set_value(3, -1.0)), InputError,
                                     ("timestamps", "frame 3")),
    "infinite force": ApiCase(recording_with(force=set_value(4, np.inf)), InputError, ("force", "frame 4")),
    "NaN displacement": ApiCase(recording_with(probe_displacement=set_value(6, np.nan)), InputError,
                                ("probe_displacement", "frame 6")),
    "frames larger than the model's": ApiCase(corrected(frames=np.zeros((2, 128, 128), np.uint8)), InputError,
                                              ("frames", "128 x 128")),
    "force 1e6 N": ApiCase(corrected([5.0, 1e6]), InputError, ("forces", "frame 1", "1e+06 N", "0 to 10 N")),
    "force 1e308 N": ApiCase(corrected([1e308, 5.0]), InputError, ("forces", "frame 0", "1e+308 N")),
    "force -5 N": ApiCase(corrected([-5.0, 5.0]), InputError, ("forces", "frame 0", "-5 N")),
    "NaN force": ApiCase(corrected([5.0, np.nan]), InputError, ("forces", "frame 1", "non-finite")),
    "coefficients 1e300": ApiCase(corrected(model=good_model(1e300)), InputError, ("model", "coefficients")),
    "fused correction, force 1e6 N": ApiCase(
        lambda: Compounder(GRID).add_corrected_frames(FRAMES, np.eye(4)[np.newaxis].repeat(2, 0), 1e6, PROFILE,
                                                      good_model()),
        InputError, ("forces", "frame 0")),
    "threads -1": ApiCase(corrected(threads=-1), InputError, ("threads", "-1")),
    "threads 0": ApiCase(corrected(threads=0), InputError, ("threads", "got 0")),
    "threads 2**64": ApiCase(corrected(threads=2**64), InputError, ("threads",)),
    "threads 20000": ApiCase(corrected(threads=20000), InputError, ("threads", "20000")),
    "threads 1.5": ApiCase(corrected(threads=1.5), InputError, ("threads", "1.5")),
    "compounder threads -1": ApiCase(lambda: Compounder(GRID).add_frames(FRAMES[0], np.eye(4), threads=-1), InputError,
                                     ("threads",)),
    "max_bytes -1": ApiCase(lambda: Compounder(GRID, max_bytes=-1), InputError, ("max_bytes", "-1")),
    "max_bytes 2**200": ApiCase(lambda: Compounder(GRID, max_bytes=2**200), InputError, ("max_bytes",)),
    "grid 2**42 per axis": ApiCase(lambda: Compounder(VoxelGrid((2**42,) * 3, np.eye(4))), MemoryLimitError,
                                   ("bytes",)),
    "grid over the machine's memory": ApiCase(
        lambda: Compounder(VoxelGrid((4096, 4096, 4096), np.eye(4)), max_bytes=2**100), MemoryLimitError,
        ("machine",)),
    "core accumulator 2**42 per axis": ApiCase(
        lambda: _core.Accumulator((2**42,) * 3, np.eye(4), "nearest", "mean", 2**40), MemoryLimitError, ("bytes",)),
    "core accumulator 2**63 per axis": ApiCase(
        lambda: _core.Accumulator((2**63, 2**63, 4), np.eye(4), "nearest", "mean", 2**127), MemoryLimitError,
        ("bytes",)),
    "hole filling threads -1": ApiCase(lambda: fill_holes(HOLEY, (HoleFillingElement("stick"),), threads=-1),
                                       InputError, ("threads",)),
    "hole filling max_bytes -1": ApiCase(lambda: fill_holes(HOLEY, (HoleFillingElement("stick"),), max_bytes=-1),
                                         InputError, ("max_bytes",)),
    "spacing 1e-30": ApiCase(lambda: VoxelGrid.from_bounds(np.zeros(3), np.ones(3), 1e-30), InputError,
                             ("spacing_mm", "1e+30 voxels")),
    "spacing 1e-9": ApiCase(lambda: VoxelGrid.from_bounds(np.zeros(3), np.ones(3), 1e-9), InputError,
                            ("index_to_world", "mm^3")),
    "spacing 0": ApiCase(lambda: VoxelGrid.from_bounds(np.zeros(3), np.ones(3), 0.0), InputError, ("spacing_mm",)),
    "n_intervals 1e30": ApiCase(
        lambda: QuadraticDisplacementModel(np.zeros((2, 10)), good_model().normalization, 10**30), InputError,
        ("n_intervals",)),
    "n_intervals 0": ApiCase(
        lambda: QuadraticDisplacementModel(np.zeros((2, 10)), good_model().normalization, 0), InputError,
        ("n_intervals",)),
    "volume and weight at one path": ApiCase(
        lambda: write_volume("/tmp/x.nrrd", Volume(np.ones((2, 2, 2), np.float32), VoxelGrid((2, 2, 2), np.eye(4)),
                                                   np.ones((2, 2, 2), np.float32)), weight_path="/tmp/x.nrrd"),
        InputError, ("weight_path",)),
    "sequence suffix": ApiCase(lambda: write_sequence("/tmp/x.txt", good_recording()), InputError, ("path", ".txt")),
    "volume suffix": ApiCase(
        lambda: write_volume("/tmp/x.png", Volume(np.ones((2, 2, 2), np.float32), VoxelGrid((2, 2, 2), np.eye(4)))),
        InputError, ("path", ".png")),
}  # fmt: skip


@pytest.mark.parametrize("case", API_CASES.values(), ids=API_CASES.keys())
def test_bad_api_argument(case: ApiCase) -> None:
    with pytest.raises(case.error) as raised:
        case.call()
    assert isinstance(raised.value, UsdeformError)
    for needle in case.needles:
        assert needle in str(raised.value), f"{needle!r} not in {str(raised.value)!r}"


def test_clamp_force_warns_and_clamps() -> None:
    with pytest.warns(ForceClampWarning, match="frame 1: force 1e\\+06 N"):
        clamped = correct_frames(FRAMES, [5.0, 1e6], PROFILE, good_model(), clamp_force=True)
    np.testing.assert_array_equal(clamped, correct_frames(FRAMES, [5.0, MAX_FORCE_N], PROFILE, good_model()))


def test_the_grid_bound_uses_this_machines_memory() -> None:
    assert memory_bytes() > 2**20


# ---------------------------------------------------------------------------------------------
# Bad command lines: exit 2, one line naming the argument or file, nothing written.


def files_in(folder: Path) -> set[Path]:
    return {path for path in folder.rglob("*")} if folder.exists() else set()


def run_failing(capsys: pytest.CaptureFixture, tmp_path: Path, argv: list[str]) -> str:
    """Run the command line expecting exit 2; return its message; check that it wrote nothing."""
    (tmp_path / "out").mkdir(exist_ok=True)
    before = files_in(tmp_path)
    try:
        status = main(argv)
    except SystemExit as exit:  # argparse
        status = exit.code
    captured = capsys.readouterr()
    assert status == 2, captured.err
    assert "Traceback" not in captured.err
    lines = captured.err.strip().splitlines()
    assert lines[-1].startswith(("usdeform: error:", "usage:")) or "error:" in lines[-1]
    if lines[0].startswith("usdeform: error:"):
        assert len(lines) == 1, captured.err
    assert files_in(tmp_path) == before, "a failed run left files behind"
    return captured.err


def sweep_with(**changes: str | None) -> Callable[[Path, Path], Path]:
    return lambda base, tmp: edit_metaimage(base / "sweep.mha", tmp / "sweep.mha", **changes)


def forces(*values: float) -> dict[str, str]:
    return {f"Seq_Frame{i:04d}_ContactForce": str(v) for i, v in enumerate(values)}


def model_with(change: Callable[[dict], object]) -> Callable[[Path, Path], Path]:
    def make(base: Path, tmp: Path) -> Path:
        document = json.loads((base / "model.json").read_text())
        change(document)
        (tmp / "model.json").write_text(json.dumps(document))
        return tmp / "model.json"

    return make


def hard_link(source: Path, tmp: Path) -> Path:
    link = tmp / "link.mha"
    if not link.exists():
        os.link(source, link)
    return link


def same_file(base: Path, tmp: Path) -> Path:
    (tmp / "sweep.mha").write_bytes((base / "sweep.mha").read_bytes())
    return tmp / "sweep.mha"


@dataclass(frozen=True)
class CliCase:
    argv: Callable[[Path, Path], list[str]]
    needles: tuple[str, ...]


def reconstruct(*extra: str, sequence: str = "{base}/sweep.mha", output: str = "{out}/v.nrrd") -> Callable:
    return lambda base, tmp: [
        part.format(base=base, out=tmp / "out", tmp=tmp)
        for part in ["reconstruct", sequence, "--output", output, *extra]
    ]


def correct(*extra: str, sweep: Callable | None = None, model: Callable | None = None, output: str = "{out}/c.mha"):
    def argv(base: Path, tmp: Path) -> list[str]:
        sweep_path = sweep(base, tmp) if sweep else base / "sweep.mha"
        model_path = model(base, tmp) if model else base / "model.json"
        parts = ["correct", str(sweep_path), "--model", str(model_path), "--output", output, *extra]
        return [part.format(base=base, out=tmp / "out", tmp=tmp, sweep=sweep_path) for part in parts]

    return argv


CLI_CASES = {
    # Outputs that would replace an input or each other (the lost recordings).
    "reconstruct --output is the input": CliCase(reconstruct(output="{base}/sweep.mha"), ("--output", "SEQUENCE")),
    "reconstruct --coverage is --output": CliCase(
        reconstruct("--coverage", "{out}/v.nrrd"), ("--coverage", "--output")
    ),
    "reconstruct --output is --config": CliCase(
        reconstruct("--config", "{base}/config.xml", output="{base}/config.xml"), ("--output",)
    ),
    "reconstruct --output v.png": CliCase(reconstruct(output="{out}/v.png"), ("--output", "v.png", ".nrrd")),
    "reconstruct --coverage c.png": CliCase(reconstruct("--coverage", "{out}/c.png"), ("--coverage", "c.png")),
    "reconstruct --output is a hard link to the input": CliCase(
        lambda b, t: ["reconstruct", str(b / "sweep.mha"), "--output", str(hard_link(b / "sweep.mha", t))],
        ("--output", "SEQUENCE")),
    "reconstruct --output in a missing folder": CliCase(reconstruct(output="{out}/missing/v.nrrd"),
                                                        ("--output", "does not exist")),
    "reconstruct --max-gib inf": CliCase(reconstruct("--max-gib", "inf"), ("--max-gib",)),
    "reconstruct --max-gib 1e40": CliCase(reconstruct("--max-gib", "1e40"), ("--max-gib",)),
    "reconstruct --max-gib -1": CliCase(reconstruct("--max-gib", "-1"), ("--max-gib",)),
    "reconstruct --max-gib nan": CliCase(reconstruct("--max-gib", "nan"), ("--max-gib",)),
    "reconstruct --spacing 1e-30": CliCase(reconstruct("--spacing", "1e-30"), ("spacing_mm", "voxels")),
    "reconstruct --spacing 1e-9": CliCase(reconstruct("--spacing", "1e-9"), ("spacing_mm",)),
    "reconstruct --spacing inf": CliCase(reconstruct("--spacing", "inf"), ("--spacing",)),
    "reconstruct --spacing 0.0002 --max-gib 1000": CliCase(reconstruct("--spacing", "0.0002", "--max-gib", "1000"),
                                                           ("bytes",)),
    "reconstruct --spacing 0.02 (over the limit)": CliCase(reconstruct("--spacing", "0.02"), ("bytes", "limit")),
    "reconstruct a missing file": CliCase(reconstruct(sequence="{tmp}/missing.mha"), ("missing.mha",)),
    "reconstruct /dev/zero": CliCase(reconstruct(sequence="/dev/zero"), ("/dev/zero", "regular file")),
    "reconstruct a folder": CliCase(reconstruct(sequence="{tmp}"), ("regular file",)),
    "reconstruct --config /dev/zero": CliCase(reconstruct("--config", "/dev/zero"), ("/dev/zero",)),
    "reconstruct --fill-holes unknown": CliCase(reconstruct("--fill-holes", "MAGIC"), ("--fill-holes",)),
    # correct: outputs.
    "correct --output is the sweep": CliCase(correct(sweep=same_file, output="{sweep}"), ("--output", "SWEEP")),
    "correct --output is --model": CliCase(correct(output="{base}/model.json"), ("--output", ".mha")),
    "correct --volume is --output": CliCase(correct("--volume", "{out}/c.mha"), ("--volume", "--output")),
    "correct --coverage is --volume": CliCase(correct("--volume", "{out}/v.nrrd", "--coverage", "{out}/v.nrrd"),
                                              ("--coverage", "--volume")),
    "correct --volume v.png": CliCase(correct("--volume", "{out}/v.png"), ("--volume", "v.png")),
    "correct --coverage c.png": CliCase(correct("--volume", "{out}/v.nrrd", "--coverage", "{out}/c.png"),
                                        ("--coverage",)),
    "correct --output c.txt": CliCase(correct(output="{out}/c.txt"), ("--output", ".txt")),
    "correct --coverage without --volume": CliCase(correct("--coverage", "{out}/c.nrrd"), ("--coverage", "--volume")),
    # correct: forces outside the fitted range (the black frames at 1e6 N) and bad models.
    "correct ContactForce 1e6": CliCase(correct(sweep=sweep_with(**forces(5, 5, 1e6))),
                                        ("sweep.mha", "ContactForce", "frame 2", "1e+06 N")),
    "correct ContactForce 1e308": CliCase(correct(sweep=sweep_with(**forces(1e308))), ("ContactForce", "frame 0")),
    "correct ContactForce -5": CliCase(correct(sweep=sweep_with(**forces(5, -5))), ("ContactForce", "frame 1", "-5 N")),
    "correct model n_intervals 1e12": CliCase(correct(model=model_with(lambda d: d.update(n_intervals=10**12))),
                                              ("model.json", "n_intervals")),
    "correct model coefficients 1e300": CliCase(
        correct(model=model_with(lambda d: d.update(coefficients=[[1e300] * 10] * 2))), ("coefficients",)),
    "correct model of 64 x 64 frames": CliCase(
        correct(model=model_with(lambda d: d.update(frame_shape=[64, 64]))), ("64 x 64",)),
    "correct model nested 100000 deep": CliCase(
        correct(model=lambda b, t: model_file(text=nested(100_000))(b, t)), ("bad.json",)),
    "correct model without positions": CliCase(
        correct(model=model_with(lambda d: d.pop("sampled_positions"))), ("sampled_positions",)),
    "correct a non-rigid sweep": CliCase(correct(sweep=sweep_with(**{FRAME_3: pose(1.5 * np.eye(3))})),
                                         (FRAME_3, "orthonormal")),
    "correct --max-gib 1e40": CliCase(correct("--volume", "{out}/v.nrrd", "--max-gib", "1e40"), ("--max-gib",)),
    # fit, demo, import-bag.
    "fit --output is the palpation": CliCase(
        lambda b, t: ["fit", str(b / "sweep.mha"), "--output", str(b / "sweep.mha"), "--flexible-layer-mm", "30"],
        ("--output", ".json")),
    "fit --output in a missing folder": CliCase(
        lambda b, t: ["fit", str(b / "sweep.mha"), "--output", str(t / "no" / "m.json"), "--flexible-layer-mm", "30"],
        ("--output", "does not exist")),
    "demo --size -4": CliCase(lambda b, t: ["demo", "--output", str(t / "out"), "--size", "-4"], ("--size",)),
    "demo --size 5000": CliCase(lambda b, t: ["demo", "--output", str(t / "out"), "--size", "5000"], ("--size",)),
    "demo --frames 100000000": CliCase(lambda b, t: ["demo", "--output", str(t / "out"), "--frames", "100000000"],
                                       ("--frames",)),
    "demo --frames 0": CliCase(lambda b, t: ["demo", "--output", str(t / "out"), "--frames", "0"], ("--frames",)),
    "demo --frames x": CliCase(lambda b, t: ["demo", "--output", str(t / "out"), "--frames", "x"], ("--frames",)),
    "import-bag --output x.txt": CliCase(
        lambda b, t: ["import-bag", str(t), "--output", str(t / "out" / "x.txt"), "--image-topic", "/i",
                      "--force-topic", "/f", "--pose-topic", "/p", "--depth-mm", "40", "--width-mm", "37.5"],
        ("--output", ".txt")),
}  # fmt: skip


def disagreeing_model_cli_cases() -> dict[str, CliCase]:
    """``correct`` with each model file of :func:`disagreeing_model_cases`: exit 2 naming the model file and
    its field (not the sweep's force, as a falling profile did before issue 43)."""

    def copied(make: Callable[[Path, Path], Path]) -> Callable[[Path, Path], Path]:
        def copy(base: Path, tmp: Path) -> Path:
            path = make(base, tmp)
            return path.replace(tmp / "model.json")

        return copy

    return {
        f"correct {name}": CliCase(correct(model=copied(case.make)), ("model.json", *case.needles[:1]))
        for name, (_, case) in disagreeing_model_cases().items()
    }


CLI_CASES.update(disagreeing_model_cli_cases())


def symlink_loop_cli_cases() -> dict[str, CliCase]:
    """Each file argument of each command given as a loop of symbolic links (issue 43: a RuntimeError
    traceback "Symlink loop"): exit 2 naming the argument."""
    topics = [
        "--image-topic",
        "/i",
        "--force-topic",
        "/f",
        "--pose-topic",
        "/p",
        "--depth-mm",
        "40",
        "--width-mm",
        "30",
    ]
    commands = {
        "reconstruct": ["reconstruct", "{base}/sweep.mha", "--output", "{out}/v.nrrd", "--coverage", "{out}/w.nrrd",
                        "--config", "{base}/config.xml"],
        "correct": ["correct", "{base}/sweep.mha", "--model", "{base}/model.json", "--output", "{out}/c.mha",
                    "--volume", "{out}/v.nrrd"],
        "fit": ["fit", "{base}/sweep.mha", "--output", "{out}/m.json", "--flexible-layer-mm", "30"],
        "import-bag": ["import-bag", "{tmp}", "--output", "{out}/x.mha", *topics],
    }  # fmt: skip
    names = {"reconstruct": "SEQUENCE", "correct": "SWEEP", "fit": "PALPATION 1", "import-bag": "BAG"}

    def looped(argv: list[str], index: int) -> Callable[[Path, Path], list[str]]:
        def make(base: Path, tmp: Path) -> list[str]:
            first, second = tmp / ("loop" + Path(argv[index]).suffix), tmp / ("other" + Path(argv[index]).suffix)
            first.symlink_to(second.name)
            second.symlink_to(first.name)
            parts = [*argv[:index], str(first), *argv[index + 1 :]]
            return [part.format(base=base, out=tmp / "out", tmp=tmp) for part in parts]

        return make

    cases = {}
    for command, argv in commands.items():
        for index, part in enumerate(argv):
            if "{" in part and not part.startswith("/"):
                name = argv[index - 1] if argv[index - 1].startswith("--") else names[command]
                cases[f"{command} {name} a symlink loop"] = CliCase(
                    looped(argv, index), (name, "loop of symbolic links")
                )
    return cases


CLI_CASES.update(symlink_loop_cli_cases())


def numeric_option_cli_cases() -> dict[str, CliCase]:
    """Every numeric option of the commands of this issue with values outside its range, not a number or
    not finite (issue 43: ``batch --retries -1`` was accepted; a manifest's ``max_gib = inf`` failed late):
    argparse's exit 2 naming the option, checked by the parser the manifest uses too."""
    bag = ["import-bag", "{tmp}", "--output", "{out}/x.mha", "--image-topic", "/i", "--force-topic", "/f",
           "--pose-topic", "/p", "--calibration", "{base}/config.xml"]  # fmt: skip
    options = {
        "--spacing": ["reconstruct", "{base}/sweep.mha", "--output", "{out}/v.nrrd"],
        "--max-gib": ["reconstruct", "{base}/sweep.mha", "--output", "{out}/v.nrrd"],
        "--flexible-layer-mm": ["fit", "{base}/sweep.mha", "--output", "{out}/m.json"],
        "--smoothness": ["fit", "{base}/sweep.mha", "--output", "{out}/m.json", "--flexible-layer-mm", "30"],
        "--wall-weight": ["fit", "{base}/sweep.mha", "--output", "{out}/m.json", "--flexible-layer-mm", "30"],
        "--retries": ["batch", "{tmp}/m.toml", "--out", "{out}/batch"],
        "--workers": ["batch", "{tmp}/m.toml", "--out", "{out}/batch"],
        "--kernel-threads": ["batch", "{tmp}/m.toml", "--out", "{out}/batch"],
        "--tolerance": bag,
        "--depth-mm": bag,
        "--width-mm": bag,
    }
    cases = {}
    for option, argv in options.items():
        for value in ("-1", "nan", "inf", "1e300", "x", "") + (("0",) if option != "--wall-weight" else ()):
            if value == "0" and option == "--retries":
                continue  # no retries is a valid choice
            cases[f"{argv[0]} {option} {value!r}"] = CliCase(
                lambda base, tmp, argv=argv, option=option, value=value: [
                    part.format(base=base, out=tmp / "out", tmp=tmp) for part in [*argv, f"{option}={value}"]
                ],
                (option,),
            )
    return cases


CLI_CASES.update(numeric_option_cli_cases())


def demo_cli_cases() -> dict[str, CliCase]:
    """``demo`` refused before any work, or failing in its first step: exit 2 and no output folder left
    behind (issue 43: failed runs left an empty one), for nested new folders too."""

    def demo(*extra: str, output: str = "{out}/demo/run") -> Callable[[Path, Path], list[str]]:
        return lambda base, tmp: [p.format(out=tmp / "out", base=base) for p in ["demo", "--output", output, *extra]]

    cases = {
        f"demo --force {value}": CliCase(demo("--force", value), (needle,))
        for value, needle in (("1000", "force_n"), ("16", "force_n"), ("-1", "--force"), ("nan", "--force"),
                              ("inf", "--force"), ("x", "--force"))
    }  # fmt: skip
    cases.update({f"demo --seed {value}": CliCase(demo("--seed", value), ("--seed",)) for value in ("-1", "1.5", "x")})
    cases["demo --output is a file"] = CliCase(demo(output="{base}/model.json"), ("--output", "not a folder"))
    return cases


CLI_CASES.update(demo_cli_cases())


def duplicate_input_cli_cases() -> dict[str, CliCase]:
    """One file given as two inputs, under the same name or another (``./``, a symbolic or a hard link):
    exit 2 naming both arguments, before anything is read."""

    def same(kind: str) -> Callable[[Path, Path], str]:
        def make(base: Path, tmp: Path) -> str:
            if kind == "path":
                return str(base / "sweep.mha")
            if kind == "./":
                return f"{base}/./sweep.mha"
            link = tmp / f"{kind}.mha"
            if kind == "symlink":
                link.symlink_to(base / "sweep.mha")
            else:
                os.link(base / "sweep.mha", link)
            return str(link)

        return make

    def fit(second: Callable[[Path, Path], str]) -> Callable[[Path, Path], list[str]]:
        return lambda base, tmp: ["fit", str(base / "sweep.mha"), str(base / "sweep.seq.nrrd"), second(base, tmp),
                                  "--output", str(tmp / "out" / "m.json"), "--flexible-layer-mm", "30"]  # fmt: skip

    cases = {f"fit a palpation twice ({kind})": CliCase(fit(same(kind)), ("PALPATION 3", "PALPATION 1"))
             for kind in ("path", "./", "symlink", "hard link")}  # fmt: skip
    cases["fit a copy of a palpation"] = CliCase(
        lambda base, tmp: ["fit", str(base / "sweep.mha"), str(base / "sweep.seq.nrrd"), "--output",
                           str(tmp / "out" / "m.json"), "--flexible-layer-mm", "30"],
        ("PALPATION 2", "sweep.seq.nrrd", "the same frames as PALPATION 1"))  # fmt: skip
    cases["correct --model is the sweep"] = CliCase(
        lambda base, tmp: ["correct", str(base / "sweep.mha"), "--model", str(base / "sweep.mha"), "--output",
                           str(tmp / "out" / "c.mha")], ("--model", "SWEEP"))  # fmt: skip
    cases["reconstruct --config is the sequence"] = CliCase(
        reconstruct("--config", "{base}/sweep.mha"), ("--config", "SEQUENCE"))  # fmt: skip
    return cases


CLI_CASES.update(duplicate_input_cli_cases())
CLI_CASES["batch --out is a file"] = CliCase(
    lambda base, tmp: ["batch", str(tmp / "m.toml"), "--out", str(base / "model.json")], ("--out", "not a folder")
)


@pytest.mark.parametrize("case", CLI_CASES.values(), ids=CLI_CASES.keys())
def test_bad_command_line(base: Path, tmp_path: Path, capsys: pytest.CaptureFixture, case: CliCase) -> None:
    message = run_failing(capsys, tmp_path, case.argv(base, tmp_path))
    for needle in case.needles:
        assert needle in message, f"{needle!r} not in {message!r}"


def test_the_good_inputs_pass(base: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The catalogue's starting points are valid: each failure above comes from its one change."""
    out = tmp_path / "out"
    out.mkdir()
    assert main(["reconstruct", str(base / "sweep.mha"), "--output", str(out / "v.nrrd")]) == 0
    assert main(["reconstruct", str(base / "sweep.seq.nrrd"), "--output", str(out / "w.nrrd")]) == 0
    assert main(["reconstruct", str(base / "sweep.gz.seq.nrrd"), "--config", str(base / "config.xml"),
                 "--output", str(out / "x.mha")]) == 0  # fmt: skip
    status = main(
        ["correct", str(base / "sweep.mha"), "--model", str(base / "model.json"), "--output", str(out / "c.mha"),
         "--volume", str(out / "c.nrrd"), "--coverage", str(out / "cc.nrrd")]
    )  # fmt: skip
    assert status == 0, capsys.readouterr().err
    read_volume(base / "volume.nrrd", base / "weight.nrrd")
    read_volume(base / "volume.mha")
    assert load_model(base / "model.json").sampled is not None
    assert not [p for p in out.iterdir() if p.name.endswith(".part")]


def test_clamp_force_on_the_command_line(base: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    sweep = sweep_with(**forces(5, 1e6))(base, tmp_path)
    output = tmp_path / "c.mha"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the command line prints the warning itself
        status = main(["correct", str(sweep), "--model", str(base / "model.json"), "--output", str(output),
                       "--clamp-force"])  # fmt: skip
    err = capsys.readouterr().err
    assert status == 0, err
    assert err.startswith("usdeform: warning: ") and "frame 1: force 1e+06 N" in err and "clamped" in err
    assert output.exists()


def test_outputs_that_belong_together_are_replaced_together(base: Path, tmp_path: Path) -> None:
    """A failed run leaves the previous run's sequence, volume and coverage, all three from that run."""
    out = tmp_path / "out"
    out.mkdir()
    argv = ["correct", str(base / "sweep.mha"), "--model", str(base / "model.json"), "--output", str(out / "c.mha"),
            "--volume", str(out / "v.nrrd"), "--coverage", str(out / "w.nrrd")]  # fmt: skip
    assert main(argv) == 0
    before = {path: path.read_bytes() for path in out.iterdir()}
    # The second run fails after the sequence is written, while compounding (grid over the limit).
    assert main([*argv, "--spacing", "0.01", "--max-gib", "0.001"]) == 2
    assert {path: path.read_bytes() for path in out.iterdir()} == before


@pytest.mark.parametrize("existing", [False, True], ids=["new folder", "existing folder"])
def test_a_demo_failing_midway_removes_only_the_folder_it_made(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture, existing: bool
) -> None:
    from usdeform.demo import pipeline

    def fail_after_writing(output: Path, config: object) -> None:
        Path(output).mkdir(parents=True, exist_ok=True)  # as run_demo does
        (Path(output) / "palpation-1.seq.nrrd").write_bytes(b"partial")
        raise InputError("the simulated failure")

    monkeypatch.setattr(pipeline, "run_demo", fail_after_writing)
    output = tmp_path / "parent" / "demo"
    if existing:
        output.mkdir(parents=True)
        (output / "notes.txt").write_text("kept")
    assert main(["demo", "--output", str(output)]) == 2
    assert capsys.readouterr().err.strip() == "usdeform: error: the simulated failure"
    if existing:  # what was there stays; what the run wrote stays too (the folder is not the run's to remove)
        assert (output / "notes.txt").read_text() == "kept"
    else:
        assert not (tmp_path / "parent").exists()


def test_catalogue_size() -> None:
    total = 2 * len(SEQUENCE_CASES) + len(OTHER_FILE_CASES) + len(API_CASES) + len(CLI_CASES)
    assert total >= 100, total


def test_no_process_wide_state_leaks() -> None:
    """main() restores the SIGTERM handler it installs."""
    before = signal.getsignal(signal.SIGTERM)
    main(["reconstruct", "/nonexistent.mha", "--output", "/tmp/never.nrrd"])
    assert signal.getsignal(signal.SIGTERM) == before


# ---------------------------------------------------------------------------------------------
# Signals during writes: a subprocess is stopped while it writes its n-th file.

PAUSING_CLI = """
import os, sys, time
target, folder, count, fsync = int(sys.argv[1]), os.path.realpath(sys.argv[2]), 0, os.fsync
def pausing_fsync(descriptor):
    global count
    # only the outputs count: a file written elsewhere first (a cache filled on first use) must not be taken for one
    is_output = os.path.dirname(os.path.realpath(f"/proc/self/fd/{descriptor}")) == folder
    count += is_output
    if is_output and count == target:
        print("PAUSED", flush=True)
        # short sleeps: a signal that lands between the print and a long sleep's start would wait out the sleep
        # (Python runs its handler between bytecodes); the loop's next check runs it
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            time.sleep(0.05)
    fsync(descriptor)
os.fsync = pausing_fsync  # atomic_output flushes every file with os.fsync before renaming it
from usdeform.cli import main
sys.exit(main(sys.argv[3:]))
"""


def _correct_argv(base: Path, out: Path, spacing: str) -> list[str]:
    return ["correct", str(base / "sweep.mha"), "--model", str(base / "model.json"), "--output", str(out / "c.mha"),
            "--volume", str(out / "v.nrrd"), "--coverage", str(out / "w.nrrd"), "--spacing", spacing]  # fmt: skip


def _stop_while_writing(argv: list[str], file_number: int, signal_number: int) -> tuple[int, str]:
    """Run the command line ``argv`` until it flushes its ``file_number``-th output (in the folder of its
    --output) to disk, send it ``signal_number`` there, and return its exit status and error output. The
    signal is sent on that event, which the run reports, not after a delay."""
    folder = Path(argv[argv.index("--output") + 1]).parent
    process = subprocess.Popen(
        [sys.executable, "-c", PAUSING_CLI, str(file_number), str(folder), *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert process.stdout is not None
    assert process.stdout.readline().strip() == "PAUSED"
    process.send_signal(signal_number)
    _, err = process.communicate(timeout=60)
    return process.returncode, err


@pytest.mark.parametrize("file_number", [1, 2, 3], ids=["sequence", "volume", "coverage"])
@pytest.mark.parametrize("signal_name", ["SIGTERM", "SIGINT"])
def test_a_signal_while_writing_leaves_the_previous_outputs_and_no_temporary_file(
    base: Path, tmp_path: Path, file_number: int, signal_name: str
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    assert main(_correct_argv(base, out, "0.5")) == 0
    before = {path.name: path.read_bytes() for path in out.iterdir()}
    status, err = _stop_while_writing(_correct_argv(base, out, "0.4"), file_number, getattr(signal, signal_name))
    if signal_name == "SIGTERM":
        assert (status, err.strip()) == (143, "usdeform: terminated")
    else:
        assert (status, err.strip()) == (130, "usdeform: interrupted")
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before  # no .part file, nothing replaced


# Ctrl-C while a command imports its modules (issue 43: a raw KeyboardInterrupt traceback in the first
# second or two). The interrupt is raised by the import itself, not sent after a delay: the test does
# not depend on the machine's load.

INTERRUPTING_CLI = """
import importlib.abc, os, signal, sys
target = sys.argv[1]
class Interrupt(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target_=None):
        if name == target:
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)  # Python raises KeyboardInterrupt at its next instruction
        return None
sys.meta_path.insert(0, Interrupt())
from usdeform.cli import main
sys.exit(main(sys.argv[2:]))
"""


def interrupted_import_cases() -> dict[str, tuple[str, list[str]]]:
    """(module whose import is interrupted, command line) for each command and a module it imports lazily."""
    bag = ["--output", "x.mha", "--image-topic", "/i", "--force-topic", "/f", "--pose-topic", "/p"]
    commands = {
        "reconstruct": ["reconstruct", "x.mha", "--output", "v.nrrd"],
        "fit": ["fit", "x.mha", "--output", "m.json", "--flexible-layer-mm", "30"],
        "correct": ["correct", "x.mha", "--model", "m.json", "--output", "c.mha"],
        "batch": ["batch", "m.toml", "--out", "out"],
        "diagnose": ["diagnose", "x.mha", "--out", "out"],
        "import-bag": ["import-bag", "x.bag", *bag],
        "demo": ["demo", "--quick"],
        "simulate": ["simulate", "palpation", "--output", "out"],
    }
    modules = {
        "reconstruct": ["usdeform.io", "usdeform.correction"],
        "fit": ["usdeform.fitting"],
        "correct": ["usdeform.correction"],
        "batch": ["usdeform.batch"],
        "diagnose": ["usdeform.gap"],
        "import-bag": ["usdeform.io.ros_bag"],
        "demo": ["usdeform.demo"],
        "simulate": ["usdeform.sim"],
    }
    return {f"{name} importing {module}": (module, commands[name]) for name in commands for module in modules[name]}


INTERRUPTED_IMPORTS = interrupted_import_cases()


@pytest.mark.parametrize(("module", "argv"), INTERRUPTED_IMPORTS.values(), ids=INTERRUPTED_IMPORTS.keys())
def test_ctrl_c_while_a_command_imports_its_modules(tmp_path: Path, module: str, argv: list[str]) -> None:
    process = subprocess.run(
        [sys.executable, "-c", INTERRUPTING_CLI, module, *argv], cwd=tmp_path, capture_output=True, text=True
    )
    assert (process.returncode, process.stderr.strip()) == (130, "usdeform: interrupted"), process.stderr[-2000:]
    assert not list(tmp_path.iterdir())


def test_the_command_line_module_imports_little() -> None:
    """``usdeform --help`` and importing usdeform.cli load none of the commands' dependencies (so it is fast
    and the window before main()'s handlers is the package's own import)."""
    heavy = ["usdeform.gap", "usdeform.batch", "usdeform.sim", "usdeform.demo", "usdeform.fitting", "usdeform.io",
             "matplotlib", "dask", "cv2", "tqdm", "nrrd", "scipy.stats"]  # fmt: skip
    script = (
        "import sys, contextlib, io\nfrom usdeform.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n    main(['--help'])\n"
        f"print([name for name in {heavy!r} if name in sys.modules])"
    )
    loaded = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]"


def test_after_kill_9_the_next_run_removes_the_temporary_files(base: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    status, _ = _stop_while_writing(_correct_argv(base, out, "0.5"), 2, signal.SIGKILL)
    assert status == -signal.SIGKILL
    assert [path for path in out.iterdir() if path.name.endswith(".part")]  # SIGKILL cannot be handled
    assert not [path for path in out.iterdir() if not path.name.startswith(".")]  # but nothing was committed
    assert main(_correct_argv(base, out, "0.5")) == 0
    assert sorted(path.name for path in out.iterdir()) == ["c.mha", "c.valid.mha", "v.nrrd", "w.nrrd"]


def test_only_the_temporary_files_of_dead_writers_of_that_output_are_removed(tmp_path: Path) -> None:
    from usdeform._files import atomic_output

    dead = tmp_path / ".v.nrrd.999999999.abcd1234.part"  # beyond pid_max: no such process
    other_output = tmp_path / ".v.nrrd.5.999999999.abcd1234.part"  # a temporary file of "v.nrrd.5"
    alive = tmp_path / f".v.nrrd.{os.getppid()}.abcd1234.part"  # a running writer's
    for path in (dead, other_output, alive):
        path.write_bytes(b"partial")
    with atomic_output(tmp_path / "v.nrrd") as handle:
        handle.write(b"complete")
    assert sorted(path.name for path in tmp_path.iterdir()) == sorted([other_output.name, alive.name, "v.nrrd"])


def live_network_cli_cases() -> dict[str, CliCase]:
    """``replay`` and ``live``'s rates refused as rates (issue 59: ``--rate -1`` said "seconds"; ``replay --rate
    1e-300`` overflowed in ``time.sleep``): exit 2 naming the option and the unit."""
    replay = ["replay", "{base}/sweep.seq.nrrd", "--to", "127.0.0.1:9"]
    live = ["live", "--model", "{base}/model.json", "--listen", "127.0.0.1:0"]
    cases = {}
    for argv, option in ((replay, "--rate"), (live, "--volume-rate"), (live, "--frame-rate")):
        for value in ("-1", "nan", "0", "1e-300", "inf"):
            cases[f"{argv[0]} {option} {value}"] = CliCase(
                lambda base, tmp, argv=argv, option=option, value=value: [
                    part.format(base=base) for part in [*argv, f"{option}={value}"]
                ],
                (option, "a rate in Hz"),
            )
    return cases


LIVE_NETWORK_CASES = live_network_cli_cases()


@pytest.mark.parametrize("case", LIVE_NETWORK_CASES.values(), ids=LIVE_NETWORK_CASES.keys())
def test_live_and_replay_rates(base: Path, tmp_path: Path, capsys: pytest.CaptureFixture, case: CliCase) -> None:
    error = run_failing(capsys, tmp_path, case.argv(base, tmp_path)).strip().splitlines()[-1]
    assert all(needle in error for needle in case.needles) and "seconds" not in error, error


def test_replay_serve_on_a_port_in_use_names_the_option_and_address(base: Path, tmp_path: Path, capsys) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        address = f"127.0.0.1:{taken.getsockname()[1]}"
        message = run_failing(capsys, tmp_path, ["replay", str(base / "sweep.seq.nrrd"), "--serve", address])
    assert f"--serve {address}: cannot listen there" in message, message


def test_replay_serve_without_a_client_names_serve(base: Path) -> None:
    pytest.importorskip("pyigtl")
    from usdeform.live import replay

    with pytest.raises(UsdeformError, match=r"--serve 127\.0\.0\.1:\d+: no client within 0\.2 s"):
        replay(base / "sweep.seq.nrrd", "127.0.0.1:0", listen=True, timeout_s=0.2)


def _diagnosis_file(tmp_path: Path, **changes: object) -> Path:
    """A diagnosis.json that names a 0.05 s image delay, with ``changes`` applied to its top level."""
    effect = {"effect": "image_latency", "parameters": {"delay_s": 0.05}, "uncertainty": {"delay_s": 0.002}}
    document = {"verdict": "explained", "named": ["image_latency"], "effects": [{**effect, "significant": True}]}
    path = tmp_path / "diagnosis.json"
    path.write_text(json.dumps({**document, **changes}))
    return path


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"verdict": "maybe"}, "verdict: expected one of"),
        ({"named": ["probe_tilt"]}, r"named\[0\]: 'probe_tilt' has no entry in 'effects'"),
        ({"effects": [{"effect": "image_latency", "parameters": {"delay_s": 5.0}}]},
         r"effects\[0\]\.parameters\.delay_s: 5\.0 is outside the library's range -0\.3\.\.0\.3"),
        ({"effects": [{"effect": "image_latency", "parameters": {"delay_s": "soon"}}]},
         r"effects\[0\]\.parameters\.delay_s: input should be a valid number"),
        ({"effects": [{"effect": "teleport", "parameters": {}}]}, r"effects\[0\]\.effect: 'teleport' is no effect"),
        ({"effects": [{"effect": "image_latency", "parameters": {"delay_s": 0.05}, "uncertainty": {"delay_s": -1}}]},
         r"effects\[0\]\.uncertainty\.delay_s: expected a non-negative number"),
        ({"effects": "none"}, "effects: input should be a valid list"),
    ],
)  # fmt: skip
def test_a_bad_diagnosis_json_is_refused_by_file_and_field(tmp_path: Path, changes: dict, message: str) -> None:
    """fit/correct --compensate and live --image-delay read diagnosis.json through one checked reader."""
    from usdeform.compensation import read_compensation
    from usdeform.live.pairing import image_delay_from_diagnosis

    path = _diagnosis_file(tmp_path, **changes)
    for read in (read_compensation, image_delay_from_diagnosis):
        with pytest.raises(InputError, match=rf"{re.escape(str(path))}: {message}"):
            read(path)


def test_diagnose_refuses_a_symlink_loop_by_name(tmp_path: Path, capsys) -> None:
    first, second = tmp_path / "loop.seq.nrrd", tmp_path / "other.seq.nrrd"
    first.symlink_to(second.name)
    second.symlink_to(first.name)
    message = run_failing(capsys, tmp_path, ["diagnose", str(first), "--out", str(tmp_path / "out" / "d")])
    assert f"{first} is a loop of symbolic links" in message, message


@pytest.mark.parametrize(
    "argv",
    [
        ["gap-benchmark", "--cases", "1000000000000"],
        ["compensation-benchmark", "--cases", "1000000000000"],
        ["compensation-benchmark", "--cases", "1", "--frame-size", "100000"],
    ],
)
def test_benchmark_sizes_are_bounded_before_any_work(tmp_path: Path, capsys, argv: list[str]) -> None:
    message = run_failing(capsys, tmp_path, [*argv, "--out", str(tmp_path / "out" / "bench")])
    assert "expected an integer from" in message and ("--cases" in message or "--frame-size" in message), message


# ---------------------------------------------------------------------------------------------
# simulate's numbers, effect parameters, memory and outputs; Ctrl-C from the first import; outputs named.


def simulate_number_cli_cases() -> dict[str, CliCase]:
    """Every numeric option of ``simulate`` and every effect parameter outside its physical bounds, not finite or
    not a number (issue 59: ``--force 1e308`` and ``--hold 1e308`` overflowed, ``--mesh-mm 1e-300`` raised
    ValueError, ``--rows 1000000`` asked for terabytes, ``latency:image_delay_s=1e308`` wrote a palpation without
    contact): exit 2 naming the option or the parameter, no folder left."""
    from usdeform.sim.command import EFFECT_PARAMETERS

    simulate = ["simulate", "palpation", "--output", "{out}/sim/run", "--preset", "coarse", "--rows", "32", "--cols",
                "32", "--frames", "4"]  # fmt: skip
    cases = {}
    for option in ("--at", "--force", "--length", "--frames", "--hold", "--rows", "--cols", "--mesh-mm", "--seed"):
        for value in ("-1", "nan", "inf", "1e308", "1e-300", "1000000", "x", ""):
            if (option, value) in (("--at", "1e-300"), ("--hold", "1e-300"), ("--seed", "1000000")):
                continue  # a valid position, hold and seed
            cases[f"simulate {option} {value!r}"] = CliCase(
                lambda base, tmp, option=option, value=value: [
                    *[part.format(out=tmp / "out") for part in simulate],
                    f"{option}={value}",
                ],
                (option,),
            )
    for effect, parameters in EFFECT_PARAMETERS.items():
        for parameter in parameters:
            for value in ("1e308", "-1e308", "nan", "x"):
                text = f"{effect}:{parameter}={value}"
                if effect == "viscoelasticity":
                    text += ",tau_s=1" if parameter == "g" else ",g=0.2"
                elif effect == "layer":
                    text += ",shear_modulus_kpa=5" if parameter != "shear_modulus_kpa" else ",thickness_mm=3"
                    if parameter in ("yeoh_c2", "yeoh_c3"):
                        text += ",thickness_mm=3"
                cases[f"simulate --effect {text}"] = CliCase(
                    lambda base, tmp, text=text: [
                        *[part.format(out=tmp / "out") for part in simulate],
                        "--effect",
                        text,
                    ],
                    (f"effect {text!r}: {parameter}",),
                )
    cases["simulate frames x rows x cols beyond memory"] = CliCase(
        lambda base, tmp: [*[part.format(out=tmp / "out") for part in simulate[:6]], "--rows", "4096", "--cols",
                           "4096", "--frames", "100000"],
        ("--frames", "--rows", "bytes"),
    )  # fmt: skip
    cases["simulate --force above the phantom's highest"] = CliCase(
        lambda base, tmp: [*[part.format(out=tmp / "out") for part in simulate], "--force", "200"],
        ("--force", "200 N", "highest force"),
    )
    cases["simulate --at beyond the phantom"] = CliCase(
        lambda base, tmp: [*[part.format(out=tmp / "out") for part in simulate], "--at", "90"], ("--at", "90 mm")
    )
    cases["simulate sweep --at + --length beyond the phantom"] = CliCase(
        lambda base, tmp: ["simulate", "sweep", "--output", str(tmp / "out" / "s"), "--at", "70", "--length", "20"],
        ("--length", "70 mm"),
    )
    return cases


CLI_CASES.update(simulate_number_cli_cases())  # run by test_bad_command_line


def test_a_failing_simulate_leaves_no_folder_it_made_and_keeps_what_was_there(tmp_path: Path, capsys) -> None:
    """The run fails in the force loop (a sensor reading 40 N low makes the robot press beyond the phantom's solved
    range), after its folder was made: the new folders go; in an existing folder, the files there stay as they were."""
    argv = ["simulate", "palpation", "--preset", "coarse", "--rows", "32", "--cols", "32", "--frames", "4",
            "--effect", "force-sensor:bias_n=-40"]  # fmt: skip
    run_failing(capsys, tmp_path, [*argv, "--output", str(tmp_path / "out" / "new" / "run")])
    existing = tmp_path / "out" / "kept"
    existing.mkdir()
    (existing / "palpation_40mm_500N.seq.nrrd").write_bytes(b"an earlier recording")
    message = run_failing(capsys, tmp_path, [*argv, "--output", str(existing)])
    assert "lower the force" in message, message


CONSOLE_SCRIPT = """
import sys
print("started", flush=True)  # the interpreter's own start (site, .pth files) is over
from {module} import {function}
sys.exit({function}())
"""


@pytest.mark.parametrize("delay_s", [0.05, 0.1, 0.2, 0.3])
def test_ctrl_c_at_any_moment_after_the_console_script_starts(tmp_path: Path, delay_s: float) -> None:
    """The console script of pyproject.toml, interrupted 0.05-0.3 s after its first line (issue 59: a traceback from
    the NumPy import, which ran before main()'s handler): exit 130, one line, no folder left."""
    import time

    import tomllib

    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    module, function = pyproject["project"]["scripts"]["usdeform"].split(":")
    argv = ["simulate", "palpation", "--output", str(tmp_path / "out"), "--preset", "coarse", "--rows", "32",
            "--cols", "32", "--frames", "4"]  # fmt: skip
    process = subprocess.Popen(
        [sys.executable, "-c", CONSOLE_SCRIPT.format(module=module, function=function), *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert process.stdout is not None and process.stdout.readline() == "started\n"
    time.sleep(delay_s)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130 and err.rstrip().endswith("usdeform: interrupted"), err[-2000:]
    assert "Traceback" not in err and not (tmp_path / "out").exists()


def test_write_errors_name_the_output_not_its_temporary_file(tmp_path: Path) -> None:
    """ "[Errno 27] File too large" from a write named no file, and a failed rename or creation named the
    temporary ``.part`` file (issue 59): each names the output."""
    import errno

    from usdeform._files import atomic_output, outputs_together

    target = tmp_path / "v.nrrd"
    with pytest.raises(OSError, match=re.escape(f"File too large: '{target}'")):
        with atomic_output(target):
            raise OSError(errno.EFBIG, "File too large")  # what a write beyond RLIMIT_FSIZE raises
    with pytest.raises(OSError) as raised:
        with atomic_output(tmp_path / "missing" / "v.nrrd"):
            pass
    assert str(raised.value).endswith(f"'{tmp_path / 'missing' / 'v.nrrd'}'") and ".part" not in str(raised.value)
    (tmp_path / "folder.json").mkdir()
    (tmp_path / "first.json").write_text("old")
    with pytest.raises(IsADirectoryError, match=r"folder\.json"), outputs_together():
        for name in ("first.json", "folder.json"):
            with atomic_output(tmp_path / name) as handle:
                handle.write(b"new")
    assert (tmp_path / "first.json").read_text() == "old"  # written together or not at all
    assert sorted(path.name for path in tmp_path.iterdir()) == ["first.json", "folder.json"]


@pytest.mark.parametrize("report", ["{out}/m.json", "{out}/rep", "{out}"], ids=["FR03", "FR04", "beside"])
def test_fit_refuses_a_report_folder_that_cannot_take_the_report_before_the_fit(
    base: Path, tmp_path: Path, capsys, report: str
) -> None:
    """FR03 (the report folder is the --output file) and FR04 (report.html is a folder): refused before the fit,
    nothing written (the model was written and the report failed after the fit)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "rep" / "report.html").mkdir(parents=True)
    (out / "report.json").mkdir()
    folder = report.format(out=out)
    argv = ["fit", str(base / "sweep.mha"), "--output", str(out / "m.json"), "--flexible-layer-mm", "30"]
    message = run_failing(capsys, tmp_path, [*argv, "--report", folder])
    assert "--report" in message and not (out / "m.json").exists(), message


@pytest.mark.parametrize("existing", [False, True], ids=["new folder", "existing folder"])
def test_a_compensation_benchmark_failing_in_its_first_case_leaves_nothing_it_made(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys, existing: bool
) -> None:
    """Issue 59: a failure in the first case left ``cb/case_000`` and ``cases.jsonl``."""
    from usdeform.compensation_benchmark import command

    def fail_in_the_case(case: object, settings: object, directory: Path) -> dict:
        directory.mkdir(parents=True)  # as run_case does
        (directory / "palpation.seq.nrrd").write_bytes(b"partial")
        raise InputError("the simulated failure")

    monkeypatch.setattr(command, "run_case", fail_in_the_case)
    out = tmp_path / "out" / "cb"
    if existing:
        out.mkdir(parents=True)
        (out / "notes.txt").write_text("kept")
    assert main(["compensation-benchmark", "--cases", "1", "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip().endswith("usdeform: error: the simulated failure")
    if existing:
        assert sorted(path.name for path in out.iterdir()) == ["notes.txt"]
    else:
        assert not (tmp_path / "out").exists()


def benchmark_number_cli_cases() -> dict[str, CliCase]:
    """Every numeric option of ``diagnose``, ``gap-benchmark`` and ``compensation-benchmark`` outside its range, not
    finite or not a number (issue 59: ``--cases 1000000000000`` ran out of memory after 120 s, ``--frame-size 100000``
    asked for 559 GiB): argparse's exit 2 naming the option, before any work."""
    commands = {
        "diagnose": (["diagnose", "{base}/sweep.seq.nrrd", "--out", "{out}/d"], ("--seed",)),
        "gap-benchmark": (["gap-benchmark", "--out", "{out}/g"], ("--cases", "--seed")),
        "compensation-benchmark": (
            ["compensation-benchmark", "--out", "{out}/c"],
            ("--cases", "--seed", "--frame-size", "--palpation-frames", "--sweep-frames", "--workers"),
        ),
    }
    cases = {}
    for command, (argv, options) in commands.items():
        for option in options:
            for value in ("-1", "nan", "inf", "1e300", "1000000000000000000000", "x", ""):
                cases[f"{command} {option} {value!r}"] = CliCase(
                    lambda base, tmp, argv=argv, option=option, value=value: [
                        *[part.format(base=base, out=tmp / "out") for part in argv],
                        f"{option}={value}",
                    ],
                    (option, "expected an integer from"),
                )
    return cases


CLI_CASES.update(benchmark_number_cli_cases())  # run by test_bad_command_line


def output_is_a_folder_cli_cases() -> dict[str, CliCase]:
    """Each output file of each command given as an existing folder (issue 59: "[Errno 21] Is a directory" after
    the work, naming the temporary ``.part`` file): exit 2 before the work, naming the option."""
    commands = {
        "reconstruct": ["reconstruct", "{base}/sweep.mha", "--output", "{out}/v.nrrd", "--coverage", "{out}/w.nrrd"],
        "correct": ["correct", "{base}/sweep.mha", "--model", "{base}/model.json", "--output", "{out}/c.mha",
                    "--volume", "{out}/v.nrrd", "--coverage", "{out}/w.nrrd"],
        "fit": ["fit", "{base}/sweep.mha", "--output", "{out}/m.json", "--flexible-layer-mm", "30"],
    }  # fmt: skip

    def folder_at(argv: list[str], index: int) -> Callable[[Path, Path], list[str]]:
        def make(base: Path, tmp: Path) -> list[str]:
            parts = [part.format(base=base, out=tmp / "out") for part in argv]
            Path(parts[index]).mkdir(parents=True)
            return parts

        return make

    return {
        f"{argv[0]} {argv[index - 1]} is a folder": CliCase(folder_at(argv, index), (argv[index - 1], "is a folder"))
        for argv in commands.values()
        for index, part in enumerate(argv)
        if part.startswith("{out}")
    }


CLI_CASES.update(output_is_a_folder_cli_cases())  # run by test_bad_command_line
