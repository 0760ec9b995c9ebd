"""An on-disk cache of the calibration's FEM library entries, shared by diagnoses, processes and runs.

A library entry (:func:`usdeform.gap.library_entries.library_entry`: a section solved and gridded, or why it could
not be solved) depends only on the section, the library's steps, the grid and the code that solves and grids it. The
cache stores each entry under a key that hashes all of them:

| part of the key | what it covers |
| --- | --- |
| ``SectionSpec.cache_key(steps)`` | the section's parameters (mesh, materials, contact, effects), steps, solver |
| the grid | ``grid_x`` and ``grid_z`` (mm), as float64 bytes |
| the code | the sources of the mechanics and the library entry, the compiled kernels, scikit-fem's version |

Entries live in ``$USDEFORM_CACHE_DIR/library``, else ``$XDG_CACHE_HOME/usdeform/library``, else
``~/.cache/usdeform/library``. ``USDEFORM_LIBRARY_CACHE=off`` switches the cache off (entries are then computed
every time and nothing is written). The folder holds at most ``$USDEFORM_CACHE_MAX_MB`` (4096 MB by default): after
each write the least recently used entries go first (:func:`usdeform._files.prune_cache`). Each entry is written to
a temporary file and renamed over its target, so concurrent processes never read half an entry; the last writer
wins, with the same contents. An entry that cannot be read, or whose stored key differs, is ignored and written
again.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from .. import _core
from .._files import atomic_output, mark_used, prune_cache
from ..sim import SectionSpec, solution_is_cached
from ..sim import mechanics as _mechanics
from . import library_entries as _library_entries
from .library_entries import LibraryEntry, library_entry

__all__ = ["CACHE_SWITCH", "cached_library_entry", "entry_is_cached", "library_cache_dir"]

#: The environment variable that switches the cache off ("off", "0", "no" or "false").
CACHE_SWITCH = "USDEFORM_LIBRARY_CACHE"
_OFF = {"off", "0", "no", "false"}


def library_cache_dir() -> Path | None:
    """The directory of cached library entries (see the module docstring); None where the cache is switched off."""
    if os.environ.get(CACHE_SWITCH, "").strip().lower() in _OFF:
        return None
    root = os.environ.get("USDEFORM_CACHE_DIR")
    if not root:
        root = str(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "usdeform")
    return Path(root) / "library"


@functools.cache
def _code_version() -> str:
    """Hex digest of the code an entry depends on: the mechanics and library-entry sources, the compiled kernels
    and scikit-fem's version (computed once per process)."""
    digest = hashlib.sha256(importlib.metadata.version("scikit-fem").encode())
    sources = sorted(Path(_mechanics.__file__).parent.glob("*.py"))
    for path in [*sources, Path(_library_entries.__file__), Path(_core.__file__)]:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def entry_key(variant: SectionSpec, steps: np.ndarray, grid_x: np.ndarray, grid_z: np.ndarray) -> str:
    """Hex digest of every input of ``variant``'s library entry (see the module docstring)."""
    payload = {
        "section": variant.cache_key(steps),
        "grid_x": hashlib.sha256(np.ascontiguousarray(grid_x, dtype=np.float64).tobytes()).hexdigest(),
        "grid_z": hashlib.sha256(np.ascontiguousarray(grid_z, dtype=np.float64).tobytes()).hexdigest(),
        "code": _code_version(),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:40]


def _entry_path(variant: SectionSpec, steps: np.ndarray, grid_x: np.ndarray, grid_z: np.ndarray) -> Path | None:
    directory = library_cache_dir()
    return None if directory is None else directory / f"{entry_key(variant, steps, grid_x, grid_z)}.npz"


def entry_is_cached(variant: SectionSpec, steps: np.ndarray, grid_x: np.ndarray, grid_z: np.ndarray) -> bool:
    """Whether :func:`cached_library_entry` would read this entry from disk (with the cache switched off: whether
    the section's solution is cached, :func:`usdeform.sim.solution_is_cached`) rather than solve it."""
    path = _entry_path(variant, steps, grid_x, grid_z)
    return solution_is_cached(variant, steps) if path is None else path.exists()


def _read(path: Path) -> LibraryEntry | str | None:
    """The entry stored at ``path``; None where it is missing, unreadable or stored under another key."""
    try:
        with np.load(path, allow_pickle=False) as stored:
            if str(stored["key"]) != path.stem:
                return None
            if "error" in stored.files:
                return str(stored["error"])
            return LibraryEntry(stored["field"], stored["lumen_area_mm2"], stored["force_n"], str(stored["resolved"]))
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error):
        return None


def _write(path: Path, entry: LibraryEntry | str) -> None:
    """Store ``entry`` at ``path`` atomically (a failure to write leaves the cache as it was), then keep the folder
    within its size limit."""
    arrays = (
        {"error": np.array(entry)}
        if isinstance(entry, str)
        else {
            "field": entry.field,
            "lumen_area_mm2": entry.lumen_area_mm2,
            "force_n": entry.force_n,
            "resolved": np.array(entry.resolved),
        }
    )
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path) as handle:
            np.savez(handle, key=np.array(path.stem), **arrays)  # type: ignore[arg-type]  # numpy's stub
    except OSError:
        return  # a cache that cannot be written (read-only, full disk) only costs the next run the solve
    prune_cache(path.parent, keep=path)


def cached_library_entry(
    variant: SectionSpec, steps: np.ndarray, grid_x: np.ndarray, grid_z: np.ndarray
) -> LibraryEntry | str:
    """:func:`usdeform.gap.library_entries.library_entry`, read from the cache where stored, else computed and
    stored."""
    path = _entry_path(variant, steps, grid_x, grid_z)
    if path is not None:
        stored = _read(path)
        if stored is not None:
            mark_used(path)
            return stored
    entry = library_entry(variant, steps, grid_x, grid_z)
    if path is not None:
        _write(path, entry)
    return entry
