"""Fuzzing of every file reader: random bytes, truncations, byte flips and mutated header fields.

Whatever the file holds, a reader returns or raises a :class:`~usdeform.errors.UsdeformError`;
nothing else escapes (no numpy, zlib, JSON, XML, recursion or memory error, no abort, no hang).
The CI run tries a few hundred files in all; ``pytest -m long`` tries thousands.
"""

from __future__ import annotations

import functools
import json
import re
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from test_bad_inputs import CONFIG, GOOD_CALIBRATION, SAMPLED, good_model, good_recording
from usdeform.errors import UsdeformError
from usdeform.io import (
    load_model,
    read_plus_config,
    read_sequence,
    read_volume,
    save_model,
    write_sequence,
    write_volume,
)
from usdeform.volume import Volume, VoxelGrid

CI_EXAMPLES = 40  # per test: 7 tests (and 60 ROS bags), a few hundred files in CI
LONG_EXAMPLES = 3000  # per test under -m long: about twenty thousand files


def _good_files(folder: Path) -> dict[str, Path]:
    recording = good_recording().select(slice(0, 3))
    files = {
        "sequence.mha": folder / "sequence.mha",
        "sequence.z.mha": folder / "sequence.z.mha",
        "sequence.seq.nrrd": folder / "sequence.seq.nrrd",
        "sequence.gz.seq.nrrd": folder / "sequence.gz.seq.nrrd",
        "volume.nrrd": folder / "volume.nrrd",
        "volume.mha": folder / "volume.mha",
        "model.json": folder / "model.json",
        "config.xml": folder / "config.xml",
    }
    write_sequence(files["sequence.mha"], recording, compress=False)
    write_sequence(files["sequence.z.mha"], recording, compress=True)
    write_sequence(files["sequence.seq.nrrd"], recording, compress=False)
    write_sequence(files["sequence.gz.seq.nrrd"], recording, compress=True)
    grid = VoxelGrid((3, 4, 5), np.diag([0.5, 0.5, 0.5, 1.0]))
    volume = Volume(np.arange(60, dtype=np.float32).reshape(grid.shape), grid)
    write_volume(files["volume.nrrd"], volume, compress=True)
    write_volume(files["volume.mha"], volume, compress=False)
    save_model(files["model.json"], good_model(), SAMPLED)
    files["config.xml"].write_text(
        CONFIG.format(matrix=GOOD_CALIBRATION, spacing="0.5 0.5 0.5", extra='OutputOrigin="0 0 0" FillHoles="OFF"')
    )
    return files


READERS: dict[str, Callable[[Path], object]] = {
    "sequence.mha": read_sequence,
    "sequence.z.mha": read_sequence,
    "sequence.seq.nrrd": read_sequence,
    "sequence.gz.seq.nrrd": read_sequence,
    "volume.nrrd": read_volume,
    "volume.mha": read_volume,
    "model.json": load_model,
    "config.xml": read_plus_config,
}


@functools.cache
def good_files() -> dict[str, bytes]:
    """The content of one good file per reader (each reads without error)."""
    with tempfile.TemporaryDirectory() as folder:
        files = _good_files(Path(folder))
        for name, path in files.items():
            READERS[name](path)
        return {name: path.read_bytes() for name, path in files.items()}


def _read(folder: Path, name: str, content: bytes) -> None:
    path = folder / f"fuzz.{name}"
    path.write_bytes(content)
    try:
        READERS[name](path)
    except UsdeformError:
        pass


def _header_end(content: bytes) -> int:
    """Where a file's text header ends (the whole file for JSON and XML)."""
    for marker in (b"ElementDataFile = LOCAL\n", b"\n\n"):
        if marker in content:
            return content.index(marker) + len(marker)
    return len(content)


# Values that have broken readers: huge, negative, non-finite, empty, many digits, odd text.
NASTY_VALUES = st.one_of(
    st.sampled_from(
        [
            "", "0", "-1", "-0", "1e308", "1e999", "-1e999", "nan", "inf", "4294967296", "9223372036854775808",
            "9" * 5000, "1.5", "0x10", "True", "LOCAL", "/dev/zero", "LIST", "%d", "gzip", "raw", "bzip2",
            "0 0 0", "1 2", "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1", "0 " * 16, "MET_FLOAT", "float", "double",
            "uint8", "[" * 1000, "{}", "\x00", "\u00e9", "domain list", "list domain domain", "../" * 8,
        ]
    ),
    st.text(max_size=40),
    st.integers(-(2**70), 2**70).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
)  # fmt: skip

NAMES = st.sampled_from(list(READERS))


def _mutate_header(content: bytes, line_index: int, value: str) -> bytes:
    """Replace the value of one header line (``Name = value``, ``name: value``, ``key:=value``, a JSON
    or XML attribute value) with ``value``."""
    end = _header_end(content)
    lines = content[:end].split(b"\n")
    index = line_index % len(lines)
    line = lines[index].decode("utf-8", "replace")
    match = re.match(r'(\s*[^=:"]*(?:=|:=|:)\s*"?)', line)
    prefix = match.group(1) if match else ""
    lines[index] = (prefix + value + ('"' if prefix.endswith('"') else "")).encode("utf-8", "surrogatepass")
    return b"\n".join(lines) + content[end:]


def _json_mutation(content: bytes, path: list[int], value: object) -> bytes:
    """Replace one value inside the model file's JSON document."""
    document = json.loads(content)
    node: object = document
    for step in path:
        if isinstance(node, dict) and node:
            key = sorted(node)[step % len(node)]
            if not isinstance(node[key], (dict, list)):
                node[key] = value
                break
            node = node[key]
        elif isinstance(node, list) and node:
            index = step % len(node)
            if not isinstance(node[index], (dict, list)):
                node[index] = value
                break
            node = node[index]
    return json.dumps(document).encode()


def fuzz(body: Callable[..., None], **strategies: st.SearchStrategy) -> tuple[Callable, Callable]:
    """A CI test and a ``long``-marked test of ``body`` with the given strategies."""
    common = {"deadline": None, "suppress_health_check": [HealthCheck.function_scoped_fixture, HealthCheck.too_slow]}
    ci = settings(max_examples=CI_EXAMPLES, **common)(given(**strategies)(body))  # type: ignore[arg-type]
    long = settings(max_examples=LONG_EXAMPLES, **common)(given(**strategies)(body))  # type: ignore[arg-type]
    return ci, pytest.mark.long(long)


def _random_bytes(tmp_path: Path, name: str, content: bytes) -> None:
    _read(tmp_path, name, content)


def _random_bytes_after_magic(tmp_path: Path, name: str, content: bytes) -> None:
    """Random bytes after a real file's first line (the readers' format detection passes)."""
    first_line = good_files()[name][: good_files()[name].index(b"\n") + 1]
    _read(tmp_path, name, first_line + content)


def _truncation(tmp_path: Path, name: str, fraction: float) -> None:
    _read(tmp_path, name, good_files()[name][: int(len(good_files()[name]) * fraction)])


def _byte_flips(tmp_path: Path, name: str, flips: list[tuple[float, int]]) -> None:
    content = bytearray(good_files()[name])
    for position, value in flips:
        content[int(position * (len(content) - 1))] = value
    _read(tmp_path, name, bytes(content))


def _header_value(tmp_path: Path, name: str, lines: list[int], values: list[str]) -> None:
    content = good_files()[name]
    for line, value in zip(lines, values, strict=False):
        content = _mutate_header(content, line, value)
    _read(tmp_path, name, content)


def _model_value(tmp_path: Path, path: list[int], value: object) -> None:
    _read(tmp_path, "model.json", _json_mutation(good_files()["model.json"], path, value))


def _appended(tmp_path: Path, name: str, extra: bytes) -> None:
    """Bytes appended to (or a header line inserted into) a good file."""
    content = good_files()[name]
    end = _header_end(content)
    _read(tmp_path, name, content[:end] + extra + content[end:] if extra.endswith(b"\n") else content + extra)


JSON_VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**80), 2**80), st.floats(), st.text(max_size=10),
    st.lists(st.integers(-5, 10**12), max_size=4),
)  # fmt: skip

test_random_bytes, test_random_bytes_long = fuzz(_random_bytes, name=NAMES, content=st.binary(max_size=2048))
test_random_bytes_after_magic, test_random_bytes_after_magic_long = fuzz(
    _random_bytes_after_magic, name=NAMES, content=st.binary(max_size=2048)
)
test_truncation, test_truncation_long = fuzz(_truncation, name=NAMES, fraction=st.floats(0.0, 1.0))
test_byte_flips, test_byte_flips_long = fuzz(
    _byte_flips, name=NAMES, flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)), min_size=1, max_size=8)
)
test_header_values, test_header_values_long = fuzz(
    _header_value,
    name=NAMES,
    lines=st.lists(st.integers(0, 10_000), min_size=1, max_size=3),
    values=st.lists(NASTY_VALUES, min_size=1, max_size=3),
)
test_model_values, test_model_values_long = fuzz(
    _model_value, path=st.lists(st.integers(0, 50), min_size=1, max_size=5), value=JSON_VALUES
)
test_appended, test_appended_long = fuzz(
    _appended,
    name=NAMES,
    extra=st.one_of(
        st.binary(max_size=256),
        st.builds(
            lambda k, v: f"{k} = {v}\n".encode(), st.sampled_from(["DimSize", "NDims", "data file"]), NASTY_VALUES
        ),
    ),
)


def test_a_ros_bag_with_flipped_bytes_raises_only_usdeform_errors(tmp_path: Path) -> None:
    """The ROS bag reader (rosbags underneath) on bags with bytes flipped: only UsdeformError escapes."""
    pytest.importorskip("rosbags")
    from test_ros_bag import write_bag
    from usdeform.io.ros_bag import read_bag
    from usdeform.recording import image_to_probe_from_geometry

    bag = write_bag(tmp_path / "good", ros1=True)
    good = bag.read_bytes()
    rng = np.random.default_rng(0)
    for _ in range(60):
        content = bytearray(good)
        for position in rng.integers(0, len(content), rng.integers(1, 6)):
            content[position] = rng.integers(0, 256)
        if rng.random() < 0.3:
            content = content[: rng.integers(0, len(content))]
        path = tmp_path / "fuzz.bag"
        path.write_bytes(bytes(content))
        try:
            read_bag(
                path,
                image_topic="/us/image",
                force_topic="/ft/wrench",
                pose_topic="/robot/probe_pose",
                image_to_probe=image_to_probe_from_geometry(24, 32),
            )
        except UsdeformError:
            pass
