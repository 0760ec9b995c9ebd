"""Shared helpers of the file readers and writers: atomic output, NRRD access and header numbers."""

from __future__ import annotations

import contextlib
import os
import tempfile
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import nrrd
import numpy as np

from ..errors import FileFormatError

__all__ = ["atomic_output", "format_numbers", "is_nrrd_file", "parse_numbers", "read_nrrd", "write_nrrd"]


def _process_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_process_umask()


@contextlib.contextmanager
def atomic_output(path: Path) -> Iterator[BinaryIO]:
    """Yield a binary file that replaces ``path`` only once the ``with`` block succeeds.

    The data go to a temporary file in the same directory, which is flushed to disk and then
    renamed over ``path`` (``os.replace``, atomic on POSIX and Windows); on any error the temporary
    file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    descriptor, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(descriptor, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(temporary, _FILE_MODE)
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
        raise


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
    """True when the file starts with the NRRD magic (``NRRD000x``), else it is read as MetaImage."""
    with Path(path).open("rb") as handle:
        return handle.read(4) == b"NRRD"


def read_nrrd(path: Path) -> tuple[dict, np.ndarray]:
    """Header and C-order data of a NRRD file (pynrrd); FileFormatError names the file and the part at fault."""
    with Path(path).open("rb") as handle:
        try:
            header = nrrd.read_header(handle)
        except (nrrd.NRRDError, ValueError, UnicodeDecodeError) as exc:
            raise FileFormatError(f"{path}: header: {exc}") from None
        try:
            data = nrrd.read_data(header, handle, str(path), index_order="C")
        except (nrrd.NRRDError, ValueError, OSError, EOFError, zlib.error) as exc:
            raise FileFormatError(f"{path}: pixel data: {exc}") from None
    return dict(header), data


def write_nrrd(path: Path, data: np.ndarray, header: dict, compress: bool) -> None:
    """Write C-order ``data`` with ``header`` atomically; gzip encoding when ``compress``."""
    header = {**header, "encoding": "gzip" if compress else "raw"}
    with atomic_output(path) as handle:
        nrrd.write(handle, np.asarray(data), header, index_order="C", compression_level=6)
