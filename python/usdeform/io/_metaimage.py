"""A small MetaImage (.mha/.mhd) codec that keeps every header field, in order.

Why not a library: ITK/SimpleITK's MetaImageIO keeps the PLUS per-frame fields
(``Seq_Frame0000_...``) only as a metadata dictionary of a large compiled dependency (~100 MB) that
gives no control over the header layout, and the small pure-Python readers on PyPI (e.g.
metaimageio) reshape ``TransformMatrix`` to 3x3 (breaking NDims 2 or 4 files), keep only the last of
repeated fields and report truncated or corrupt data as bare numpy/zlib errors. The format
is simple (text ``Name = value`` lines up to ``ElementDataFile``, then raw or zlib-compressed
pixels), so this module reads and writes it directly, following PLUS's vtkPlusMetaImageSequenceIO:
``ObjectType`` first, ``ElementDataFile`` last, zlib (not gzip) compression with
``CompressedDataSize``, little-endian data, and for .mhd a ``<stem>.raw``/``<stem>.zraw`` data file.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._files import atomic_output, outputs_together
from ..errors import FileFormatError, InputError
from ..options import DEFAULT_COMPRESSION_LEVEL
from ..validation import checked_byte_count, regular_file
from ._common import deflate, parse_numbers

__all__ = ["CODEC_FIELDS", "MetaImage", "read_metaimage", "write_metaimage"]

_ELEMENT_TYPES = {
    "MET_CHAR": np.int8,
    "MET_UCHAR": np.uint8,
    "MET_SHORT": np.int16,
    "MET_USHORT": np.uint16,
    "MET_INT": np.int32,
    "MET_UINT": np.uint32,
    "MET_LONG": np.int32,
    "MET_ULONG": np.uint32,
    "MET_LONG_LONG": np.int64,
    "MET_ULONG_LONG": np.uint64,
    "MET_FLOAT": np.float32,
    "MET_DOUBLE": np.float64,
}
_WRITE_ELEMENT_TYPES = {
    np.dtype(np.int8): "MET_CHAR",
    np.dtype(np.uint8): "MET_UCHAR",
    np.dtype(np.int16): "MET_SHORT",
    np.dtype(np.uint16): "MET_USHORT",
    np.dtype(np.int32): "MET_INT",
    np.dtype(np.uint32): "MET_UINT",
    np.dtype(np.int64): "MET_LONG_LONG",
    np.dtype(np.uint64): "MET_ULONG_LONG",
    np.dtype(np.float32): "MET_FLOAT",
    np.dtype(np.float64): "MET_DOUBLE",
}

_MAX_DIMENSIONS = 16  # ITK's limit is lower still; more only serves to blow up header parsing

#: Header fields this codec interprets on reading and writes itself.
CODEC_FIELDS = frozenset(
    {
        "ObjectType",
        "NDims",
        "DimSize",
        "ElementType",
        "ElementNumberOfChannels",
        "BinaryData",
        "BinaryDataByteOrderMSB",
        "ElementByteOrderMSB",
        "CompressedData",
        "CompressedDataSize",
        "HeaderSize",
        "ElementDataFile",
    }
)


@dataclass(frozen=True, eq=False)
class MetaImage:
    """A MetaImage file's header ``fields`` (name -> value text, in file order) and its ``pixels``.

    ``pixels`` is indexed in C order, the reverse of ``DimSize``: (z, y, x) for a volume,
    (frame, row, col) for a PLUS sequence.
    """

    fields: dict[str, str]
    pixels: np.ndarray


def _is_true(text: str) -> bool:
    return text.strip().lower() == "true"


def _read_header(path: Path, raw: bytes) -> tuple[dict[str, str], int]:
    """Parse header lines up to and including ElementDataFile; return the fields and the data offset."""
    fields: dict[str, str] = {}
    position = 0
    line_number = 0
    while "ElementDataFile" not in fields:
        end = raw.find(b"\n", position)
        if end < 0:
            raise FileFormatError(
                f"{path}: header: no ElementDataFile field before the end of the file (truncated or not MetaImage)"
            )
        line_number += 1
        try:
            line = raw[position:end].decode("utf-8").strip()
        except UnicodeDecodeError:
            raise FileFormatError(f"{path}: header line {line_number} is not text (not a MetaImage header)") from None
        position = end + 1
        if not line:
            continue
        name, separator, value = line.partition("=")
        name, value = name.strip(), value.strip()
        if not separator or not name:
            raise FileFormatError(f"{path}: header line {line_number}: expected 'Name = value', got {line[:80]!r}")
        if name in fields:
            raise FileFormatError(f"{path}: header field {name} appears twice")
        fields[name] = value
    if fields.get("ObjectType") != "Image":
        raise FileFormatError(f"{path}: ObjectType: expected 'Image', got {fields.get('ObjectType')!r}")
    return fields, position


def _required(path: Path, fields: dict[str, str], name: str) -> str:
    if name not in fields:
        raise FileFormatError(f"{path}: header field {name} is missing")
    return fields[name]


def _decompress(path: Path, payload: memoryview, expected: int, declared_size: int | None) -> bytes:
    if declared_size is not None:
        if len(payload) < declared_size:
            raise FileFormatError(
                f"{path}: pixel data: CompressedDataSize is {declared_size} bytes, {len(payload)} follow the header"
            )
        payload = payload[:declared_size]
    decompressor = zlib.decompressobj()
    try:
        data = decompressor.decompress(payload, expected)
        if not decompressor.eof and decompressor.decompress(decompressor.unconsumed_tail, 1):
            raise FileFormatError(f"{path}: pixel data: decompresses to more than the {expected} bytes DimSize needs")
    except zlib.error as exc:
        raise FileFormatError(f"{path}: pixel data: corrupt zlib stream ({exc})") from None
    if not decompressor.eof or len(data) != expected:
        raise FileFormatError(
            f"{path}: pixel data: truncated compressed stream, {len(data)} of the {expected} bytes DimSize needs"
        )
    return data


def read_metaimage(path: str | Path, uint8_only: bool = False) -> MetaImage:
    """Read a .mha (pixels after the header) or .mhd (pixels in ElementDataFile) MetaImage file.

    Raises FileFormatError naming the file and the field for a malformed header, an unsupported
    layout (text data, several channels, file lists), data shorter than DimSize says or corrupt
    zlib data (and, with ``uint8_only``, for another element type than MET_UCHAR, before reading the
    data). ``pixels`` has the file's element type in native byte order and may be read-only.
    """
    path = regular_file(Path(path), "file")
    raw = path.read_bytes()
    fields, data_offset = _read_header(path, raw)

    ndims = int(parse_numbers(path, "NDims", _required(path, fields, "NDims"), 1, integer=True)[0])
    if ndims < 1:
        raise FileFormatError(f"{path}: NDims: expected a positive number of dimensions, got {ndims}")
    if ndims > _MAX_DIMENSIONS:
        raise FileFormatError(f"{path}: NDims: at most {_MAX_DIMENSIONS} dimensions are supported, got {ndims}")
    dim_size = parse_numbers(path, "DimSize", _required(path, fields, "DimSize"), ndims, integer=True)
    element_type = _required(path, fields, "ElementType")
    if element_type not in _ELEMENT_TYPES:
        raise FileFormatError(f"{path}: ElementType: unsupported element type {element_type!r}")
    if uint8_only and element_type != "MET_UCHAR":
        raise FileFormatError(f"{path}: ElementType: frames must be MET_UCHAR, got {element_type}")
    channels = fields.get("ElementNumberOfChannels", "1")
    if channels.strip() != "1":
        raise FileFormatError(
            f"{path}: ElementNumberOfChannels: only single-channel images are supported, got {channels!r}"
        )
    if not _is_true(fields.get("BinaryData", "True")):
        raise FileFormatError(f"{path}: BinaryData: only binary pixel data is supported")
    if fields.get("HeaderSize", "0").strip() != "0":
        raise FileFormatError(f"{path}: HeaderSize: skipping a data-file header is not supported")
    big_endian = _is_true(fields.get("BinaryDataByteOrderMSB", "False")) or _is_true(
        fields.get("ElementByteOrderMSB", "False")
    )
    dtype = np.dtype(_ELEMENT_TYPES[element_type]).newbyteorder(">" if big_endian else "<")

    data_file = fields["ElementDataFile"]
    if data_file == "LOCAL":
        payload = memoryview(raw)[data_offset:]
    elif data_file.upper() == "LIST" or "%" in data_file:
        raise FileFormatError(f"{path}: ElementDataFile: file lists ({data_file!r}) are not supported")
    else:
        data_path = regular_file(path.parent / data_file, f"{path}: ElementDataFile")
        payload = memoryview(data_path.read_bytes())

    expected = checked_byte_count(dim_size.tolist(), dtype.itemsize, f"{path}: DimSize")
    if _is_true(fields.get("CompressedData", "False")):
        declared = fields.get("CompressedDataSize")
        declared_size = (
            None if declared is None else int(parse_numbers(path, "CompressedDataSize", declared, 1, integer=True)[0])
        )
        data: bytes | memoryview = _decompress(path, payload, expected, declared_size)
    else:
        if len(payload) < expected:
            raise FileFormatError(
                f"{path}: pixel data: DimSize {fields['DimSize']} needs {expected} bytes, {len(payload)} are present"
            )
        data = payload[:expected]
    pixels = np.frombuffer(data, dtype=dtype).reshape(tuple(int(n) for n in dim_size[::-1]))
    if big_endian and dtype.itemsize > 1:
        pixels = pixels.astype(dtype.newbyteorder("="))
    return MetaImage(fields=fields, pixels=pixels)


def _check_field(name: str, value: str) -> None:
    if name in CODEC_FIELDS:
        raise InputError(f"header field {name} is written by the MetaImage codec itself")
    if not name or "=" in name or any(c in name + value for c in "\r\n"):
        raise InputError(f"header field {name!r} = {value!r} is not a one-line 'Name = value' pair")


def write_metaimage(
    path: str | Path,
    pixels: np.ndarray,
    fields: Iterable[tuple[str, str]],
    compress: bool,
    compression_level: int = DEFAULT_COMPRESSION_LEVEL,
) -> None:
    """Write ``pixels`` (C order; DimSize is the reversed shape) with extra header ``fields``, zlib-compressed at
    ``compression_level`` (1 fastest to 9 smallest, :func:`~usdeform.io._common.deflate`) when ``compress``.

    ``fields`` come after the codec's own fields (ObjectType, NDims, BinaryData, byte order,
    compression, DimSize, ElementType) and before ``ElementDataFile``, which is last. A .mhd path
    stores the pixels in ``<stem>.raw`` (``.zraw`` compressed) beside it; any other suffix stores them
    after the header (``ElementDataFile = LOCAL``). The files are written atomically, together.
    """
    path = Path(path)
    pixels = np.asarray(pixels)
    if pixels.dtype.newbyteorder("=") not in _WRITE_ELEMENT_TYPES:
        raise InputError(f"pixels: unsupported dtype {pixels.dtype}")
    element_type = _WRITE_ELEMENT_TYPES[pixels.dtype.newbyteorder("=")]
    data = np.ascontiguousarray(pixels, dtype=pixels.dtype.newbyteorder("<")).tobytes()
    if compress:
        data = deflate(data, compression_level, "zlib")

    lines = [
        ("ObjectType", "Image"),
        ("NDims", str(pixels.ndim)),
        ("BinaryData", "True"),
        ("BinaryDataByteOrderMSB", "False"),
        ("CompressedData", "True" if compress else "False"),
    ]
    if compress:
        lines.append(("CompressedDataSize", str(len(data))))
    lines += [("DimSize", " ".join(str(n) for n in pixels.shape[::-1])), ("ElementType", element_type)]
    for name, value in fields:
        _check_field(name, value)
        lines.append((name, value))

    detached = path.suffix.lower() == ".mhd"
    if detached:
        data_path = path.with_suffix(".zraw" if compress else ".raw")
        lines.append(("ElementDataFile", data_path.name))
    else:
        lines.append(("ElementDataFile", "LOCAL"))
    header = "".join(f"{name} = {value}\n" for name, value in lines).encode("utf-8")
    with outputs_together():
        if detached:
            with atomic_output(data_path) as handle:
                handle.write(data)
        with atomic_output(path) as handle:
            handle.write(header)
            if not detached:
                handle.write(data)
