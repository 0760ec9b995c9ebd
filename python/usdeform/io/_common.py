"""Shared helpers of the file readers and writers: NRRD access, header numbers and the deflate stream of
compressed pixel data."""

from __future__ import annotations

import bz2
import contextlib
import io
import os
import zlib
from collections.abc import Iterable
from pathlib import Path
from typing import BinaryIO

import nrrd
import numpy as np
from isal import isal_zlib

from .._files import atomic_output
from ..errors import FileFormatError
from ..options import DEFAULT_COMPRESSION_LEVEL
from ..validation import checked_byte_count, regular_file

__all__ = [
    "deflate",
    "format_numbers",
    "is_nrrd_file",
    "parse_numbers",
    "read_nrrd",
    "write_nrrd",
]


def parse_numbers(source: object, field: str, text: str, count: int | None = None, integer: bool = False) -> np.ndarray:
    """Parse whitespace-separated finite numbers of header ``field`` of file ``source``.

    Raises FileFormatError naming the file and the field when a value is missing, extra,
    unparsable or not finite. Returns float64 (or int64 when ``integer``) values.
    """
    parts = text.split()
    if count is not None and len(parts) != count:
        raise FileFormatError(f"{source}: {field}: expected {count} numbers, got {len(parts)} in {text!r}")
    try:
        values = np.array(
            [int(part) if integer else float(part) for part in parts], dtype=np.int64 if integer else np.float64
        )
    except (ValueError, OverflowError):
        kind = "integers" if integer else "numbers"
        raise FileFormatError(f"{source}: {field}: cannot parse {text!r} as {kind}") from None
    if not integer and not np.all(np.isfinite(values)):
        raise FileFormatError(f"{source}: {field}: non-finite number in {text!r}")
    return values


def _format_number(value: float) -> str:
    text = repr(float(value))  # shortest text that reads back to the same float64
    return text[:-2] if text.endswith(".0") else text


def format_numbers(values: Iterable[float]) -> str:
    """Space-separated numbers that parse back to exactly the same float64 values."""
    return " ".join(_format_number(value) for value in values)


def is_nrrd_file(path: Path) -> bool:
    """True when the file starts with the NRRD magic (``NRRD000x``), else it is read as MetaImage.
    FileFormatError unless ``path`` is a regular file (a pipe would block, a device never end), for an
    empty file, and for a file named ``.nrrd`` without the magic (a MetaImage message would mislead)."""
    with regular_file(Path(path), "file").open("rb") as handle:
        magic = handle.read(8)
    if not magic:
        raise FileFormatError(f"{path}: the file is empty (0 bytes)")
    if magic.startswith(b"NRRD"):
        return True
    if Path(path).name.lower().endswith(".nrrd"):
        raise FileFormatError(f"{path}: not an NRRD file: it starts with {magic!r}, not the magic 'NRRD000x'")
    return False


# The NRRD element types (teem's names and their synonyms) as NumPy kinds; pynrrd's table is private.
_NRRD_TYPES = {
    **dict.fromkeys(("signed char", "int8", "int8_t"), "i1"),
    **dict.fromkeys(("uchar", "unsigned char", "uint8", "uint8_t"), "u1"),
    **dict.fromkeys(("short", "short int", "signed short", "signed short int", "int16", "int16_t"), "i2"),
    **dict.fromkeys(("ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"), "u2"),
    **dict.fromkeys(("int", "signed int", "int32", "int32_t"), "i4"),
    **dict.fromkeys(("uint", "unsigned int", "uint32", "uint32_t"), "u4"),
    **dict.fromkeys(
        ("longlong", "long long", "long long int", "signed long long", "signed long long int", "int64", "int64_t"),
        "i8",
    ),
    **dict.fromkeys(("ulonglong", "unsigned long long", "unsigned long long int", "uint64", "uint64_t"), "u8"),
    "float": "f4",
    "double": "f8",
}
_COMPRESSED = {"gzip": "gzip", "gz": "gzip", "bzip2": "bzip2", "bz2": "bzip2"}
_TEXT = ("ascii", "text", "txt")
_CHUNK_BYTES = 1 << 20


def nrrd_dtype(path: Path, header: dict) -> np.dtype:
    """The element type of a NRRD header (``type``, and ``endian`` for multi-byte raw or compressed data)."""
    name = header.get("type")
    if name not in _NRRD_TYPES:
        raise FileFormatError(f"{path}: type: unsupported element type {name!r}")
    dtype = np.dtype(_NRRD_TYPES[name])
    if dtype.itemsize > 1 and str(header.get("encoding", "")).lower() not in _TEXT:
        endian = header.get("endian")
        if endian not in ("little", "big"):
            raise FileFormatError(f"{path}: endian: type {name!r} needs 'endian: little' or 'big', got {endian!r}")
        dtype = dtype.newbyteorder("<" if endian == "little" else ">")
    return dtype


def _nrrd_int(path: Path, header: dict, names: tuple[str, ...], minimum: int) -> int:
    value = next((header[name] for name in names if name in header), 0)
    if not isinstance(value, (int, np.integer)) or value < minimum:
        raise FileFormatError(f"{path}: {names[-1]}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


def _decompress(path: Path, handle: BinaryIO, method: str, needed: int) -> bytes:
    """Decompress at most ``needed`` bytes (the declared size) from ``handle``, reading it in chunks:
    a stream that would give more or less is an error, found without inflating all of it."""
    gzip = zlib.decompressobj(zlib.MAX_WBITS | 16) if method == "gzip" else None
    bzip2 = bz2.BZ2Decompressor() if method == "bzip2" else None
    parts: list[bytes] = []
    produced, pending = 0, b""
    try:
        while produced <= needed:
            if gzip is not None:
                if gzip.eof:
                    break
                pending = pending or handle.read(_CHUNK_BYTES)
                if not pending:
                    break
                part = gzip.decompress(pending, needed + 1 - produced)
                pending = gzip.unconsumed_tail
            else:
                assert bzip2 is not None
                if bzip2.eof:
                    break
                chunk = handle.read(_CHUNK_BYTES) if bzip2.needs_input else b""
                if bzip2.needs_input and not chunk:
                    break
                part = bzip2.decompress(chunk, needed + 1 - produced)
            parts.append(part)
            produced += len(part)
    except (zlib.error, OSError, EOFError) as exc:
        raise FileFormatError(f"{path}: pixel data: corrupt {method} stream ({exc})") from None
    if produced > needed:
        raise FileFormatError(f"{path}: pixel data: decompresses to more than the {needed} bytes sizes needs")
    if produced < needed:
        raise FileFormatError(
            f"{path}: pixel data: truncated {method} stream, {produced} of the {needed} bytes sizes needs"
        )
    return b"".join(parts)


def _read_nrrd_data(path: Path, header: dict, handle: BinaryIO) -> np.ndarray:
    """The data of a NRRD file whose header was read from ``handle``, read without ever taking more
    than the declared size (pynrrd reads a raw or compressed payload to its end, which never comes
    for ``/dev/zero`` and may be gigabytes for a small gzip bomb)."""
    for name in ("dimension", "sizes", "encoding"):
        if name not in header:
            raise FileFormatError(f"{path}: {name}: required field is missing")
    sizes = [int(n) for n in np.atleast_1d(header["sizes"])]
    if header["dimension"] != len(sizes):
        raise FileFormatError(f"{path}: sizes: {len(sizes)} sizes for dimension {header['dimension']}")
    dtype = nrrd_dtype(path, header)
    needed = checked_byte_count(sizes, dtype.itemsize, f"{path}: sizes")
    encoding = str(header["encoding"]).lower()
    line_skip = _nrrd_int(path, header, ("lineskip", "line skip"), 0)
    byte_skip = _nrrd_int(path, header, ("byteskip", "byte skip"), -1)
    data_file = header.get("datafile", header.get("data file"))
    with contextlib.ExitStack() as stack:
        if data_file is not None:
            if not isinstance(data_file, str) or data_file.upper().startswith("LIST") or " " in data_file.strip():
                raise FileFormatError(f"{path}: data file: file lists ({data_file!r}) are not supported")
            data_path = regular_file(path.parent / data_file, f"{path}: data file")
            handle = stack.enter_context(data_path.open("rb"))
        for _ in range(line_skip):
            handle.readline()
        if encoding in _COMPRESSED:
            if byte_skip < 0:
                raise FileFormatError(f"{path}: byte skip: -1 is only allowed with raw encoding")
            raw = _decompress(path, handle, _COMPRESSED[encoding], byte_skip + needed)[byte_skip:]
        elif encoding == "raw":
            if byte_skip == -1:
                handle.seek(-needed, os.SEEK_END)
            else:
                handle.seek(byte_skip, os.SEEK_CUR)
            raw = handle.read(needed)
            if len(raw) < needed:
                raise FileFormatError(f"{path}: pixel data: sizes {sizes} needs {needed} bytes, {len(raw)} are present")
        elif encoding in _TEXT:
            count = needed // dtype.itemsize
            try:
                values = np.array(handle.read().split()[:count], dtype=np.float64)
            except ValueError as exc:
                raise FileFormatError(f"{path}: pixel data: not numbers ({exc})") from None
            if values.size < count:
                raise FileFormatError(f"{path}: pixel data: sizes {sizes} needs {count} numbers, {values.size} found")
            return values.astype(dtype).reshape(sizes[::-1])
        else:
            raise FileFormatError(f"{path}: encoding: unsupported encoding {header['encoding']!r}")
    data = np.frombuffer(raw, dtype=dtype).reshape(sizes[::-1])
    return data.astype(dtype.newbyteorder("=")) if not dtype.isnative else data


def read_nrrd(path: Path, uint8_only: bool = False) -> tuple[dict, np.ndarray]:
    """Header (pynrrd) and C-order data of a NRRD file; FileFormatError names the file and the part at fault.

    The data are read without taking more than the declared size (see :func:`_read_nrrd_data`);
    detached data files must be regular files. ``uint8_only``: any other ``type`` is an error.
    """
    path = regular_file(Path(path), "file", error=FileFormatError)
    with path.open("rb") as handle:
        try:
            header = nrrd.read_header(handle)
        except Exception as exc:  # pynrrd's field parsers fail in many ways (IndexError on an empty vector, ...)
            raise FileFormatError(f"{path}: header: {type(exc).__name__}: {exc}"[:300]) from None
        if uint8_only and _NRRD_TYPES.get(header.get("type")) != "u1":
            raise FileFormatError(f"{path}: type: frames must be uint8, got {header.get('type')!r}")
        try:
            data = _read_nrrd_data(path, dict(header), handle)
        except OSError as exc:
            raise FileFormatError(f"{path}: pixel data: {exc}") from None
    return dict(header), data


_WINDOW_BITS = {"zlib": zlib.MAX_WBITS, "gzip": zlib.MAX_WBITS | 16}


def deflate(data: bytes | memoryview, level: int, container: str) -> bytes:
    """``data`` compressed at ``level`` (1 fastest to 9 smallest) in a ``container``: "zlib" (MetaImage's
    compressed pixels) or "gzip" (NRRD's gzip encoding).

    Level 1 is ISA-L's deflate (python-isal), levels 2-9 are zlib's. Every level is a standard deflate
    stream that zlib, ITK, 3D Slicer and PLUS inflate. ISA-L because it is the fast setting that batch
    runs write with: on the batch cohort's files (a 100-frame 128 x 128 uint8 sequence, an 80 x 60 x 75
    float32 volume) it took 3.4 ms where zlib's level 1 took 36 and 18 ms, for the size of zlib's levels
    1-3 (``benches/bench_volume_compression.py``).
    """
    if level == 1:
        return isal_zlib.compress(data, 1, wbits=_WINDOW_BITS[container])
    compressor = zlib.compressobj(level, zlib.DEFLATED, _WINDOW_BITS[container])
    return compressor.compress(data) + compressor.flush()


def write_nrrd(
    path: Path,
    data: np.ndarray,
    header: dict,
    compress: bool,
    compression_level: int = DEFAULT_COMPRESSION_LEVEL,
) -> None:
    """Write C-order ``data`` with ``header`` atomically: gzip encoding at ``compression_level`` (1 fastest
    to 9 smallest, :func:`deflate`) when ``compress``, raw otherwise. pynrrd formats the header."""
    data = np.ascontiguousarray(data)
    if not compress:
        with atomic_output(path) as handle:
            nrrd.write(handle, data, {**header, "encoding": "raw"}, index_order="C")
        return
    with io.BytesIO() as buffer:  # pynrrd's header for raw data, then the data compressed here
        nrrd.write(buffer, data, {**header, "encoding": "raw"}, index_order="C")
        written = buffer.getbuffer()
        header_bytes = bytes(written[: len(written) - data.nbytes])
        del written
    raw_line = b"\nencoding: raw\n"
    if header_bytes.count(raw_line) != 1:  # pynrrd writes each field once, on its own line
        raise RuntimeError(f"{path}: pynrrd's header does not have one 'encoding: raw' line")
    payload = deflate(data.data.cast("B"), compression_level, "gzip")
    with atomic_output(path) as handle:
        handle.write(header_bytes.replace(raw_line, b"\nencoding: gzip\n"))
        handle.write(payload)
