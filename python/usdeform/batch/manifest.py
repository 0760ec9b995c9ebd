"""Batch manifests: the subjects of a cohort, their recordings and options, read from TOML or CSV.

The format is documented in :mod:`usdeform.batch`. :func:`read_manifest` validates the whole file
before anything runs and raises :class:`~usdeform.errors.FileFormatError` naming the file, the line
(CSV) or the field (TOML) and what was expected. Recording paths are not opened here: on a cluster
they are read by the workers, which may see a file system the client does not. The diagnosis a
subject's ``compensate`` option names is the exception: it is read and checked here
(:func:`usdeform.compensation.read_compensation`; a missing or refused one would fail every task of
the subject), and read again by the workers, so it must be at the same path for both.
"""

from __future__ import annotations

import csv
import dataclasses
import errno
import os
import re
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import FileFormatError, InputError
from ..fitting import parse_basis
from ..options import NUMBERS
from ..pipeline import CHOICES, FIT_FIELDS, SWEEP_FIELDS, PipelineSettings

__all__ = ["Manifest", "Options", "Subject", "read_manifest", "recording_name"]

_SUBJECT_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
_RECORDING_SUFFIXES = (".igs.mha", ".igs.nrrd", ".seq.mha", ".seq.nrrd", ".mha", ".mhd", ".nrrd")
_TRUE, _FALSE = ("true", "yes", "1"), ("false", "no", "0", "")
_BOOLEANS = ("volume", "coverage", "report", "clamp_force", "force_compensation")
#: The options always in a fit's record and in a sweep's (compared on a rerun); their other options are in it
#: only when not at their defaults, so that a record without them holds for a subject that leaves them so.
_ALWAYS_RECORDED_FIT = FIT_FIELDS[: FIT_FIELDS.index("wall_weight")]
_ALWAYS_RECORDED_SWEEP = ("volume", "spacing_mm", "interpolation", "compounding", "max_gib")


@dataclass(frozen=True)
class Options(PipelineSettings):
    """The options of one subject: every setting of the pipeline (:class:`usdeform.pipeline.PipelineSettings`:
    the fit's as ``usdeform fit``, the correction's and volume's as ``usdeform correct``, the diagnosis to
    compensate), which outputs to write (``report``: the fit's report, as ``--report``; ``volume``: each
    sweep's volume; ``coverage``: its coverage volume, as ``--coverage``, needs ``volume``) and the
    diagnosis' seed. ``compensate`` is an absolute path."""

    report: bool = False
    volume: bool = True
    coverage: bool = False
    diagnosis_seed: int = 0

    def fit_options(self) -> dict[str, Any]:
        """The options a fit depends on (what a rerun compares to decide whether a model is still valid)."""
        return self._recorded(_ALWAYS_RECORDED_FIT, (*FIT_FIELDS, "report"))

    def reconstruction_options(self) -> dict[str, Any]:
        """The options a sweep's correction and compounding depend on."""
        return self._recorded(_ALWAYS_RECORDED_SWEEP, (*SWEEP_FIELDS, "coverage"))

    def _recorded(self, always: tuple[str, ...], names: tuple[str, ...]) -> dict[str, Any]:
        """The options ``always``, those of ``names`` not at their defaults, and the compensation's."""
        recorded = {name: getattr(self, name) for name in always}
        for name in names:
            if name not in always and getattr(self, name) != getattr(_DEFAULTS, name):
                recorded[name] = getattr(self, name)
        return {**recorded, **self._compensation_options()}

    def _compensation_options(self) -> dict[str, Any]:
        """``compensate`` and ``force_compensation`` where a diagnosis is compensated, else nothing."""
        if self.compensate is None:
            return {}
        return {"compensate": str(self.compensate), "force_compensation": self.force_compensation}


_DEFAULTS = Options()

_OPTION_NAMES = tuple(field.name for field in dataclasses.fields(Options))


@dataclass(frozen=True)
class Subject:
    """One subject: palpations to fit (absolute paths), sweeps to correct and reconstruct with that
    fit, the recordings to diagnose (empty: no diagnosis) and the options."""

    id: str
    palpations: tuple[Path, ...]
    sweeps: tuple[Path, ...]
    diagnosis: tuple[Path, ...]
    options: Options


@dataclass(frozen=True)
class Manifest:
    """A validated manifest: its file (None when built in Python) and its subjects."""

    subjects: tuple[Subject, ...]
    path: Path | None = None


def recording_name(path: Path) -> str:
    """The file name of a recording without its sequence-file suffix (``sweep-1.seq.nrrd`` -> ``sweep-1``)."""
    name = path.name
    for suffix in _RECORDING_SUFFIXES:
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return name


def _check_known(where: str, given: Iterable[str], known: tuple[str, ...], what: str) -> None:
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise FileFormatError(f"{where}: unknown {what} {', '.join(unknown)}; known: {', '.join(known)}")


def _number(where: str, name: str, value: Any) -> float:
    """A numeric option, checked as the command line checks it (:data:`usdeform.options.NUMBERS`)."""
    return NUMBERS[name].check(value, f"{where}: {name}", error=FileFormatError)


def _choice(where: str, name: str, value: Any, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise FileFormatError(f"{where}: {name}: expected one of {', '.join(choices)}, got {value!r}")
    return str(value)


def _basis(where: str, value: Any) -> str:
    if not isinstance(value, str):
        raise FileFormatError(f"{where}: basis: expected a string such as 'quadratic' or 'bspline:8x6', got {value!r}")
    try:
        parse_basis(value)
    except InputError as error:
        raise FileFormatError(f"{where}: {error}") from None
    return value


def _options(where: str, values: Mapping[str, Any], base: Options, folder: Path) -> Options:
    """``base`` with the entries of ``values`` (already typed: TOML values, or CSV cells converted);
    ``compensate`` relative to ``folder`` (the manifest's)."""
    _check_known(where, values, _OPTION_NAMES, "option(s)")
    checked: dict[str, Any] = {}
    for name, value in values.items():
        if name in NUMBERS:
            checked[name] = _number(where, name, value)
        elif name == "basis":
            checked[name] = _basis(where, value)
        elif name in CHOICES:
            checked[name] = _choice(where, name, value, CHOICES[name])
        elif name == "compensate":
            if not isinstance(value, str) or not value.strip():
                raise FileFormatError(f"{where}: compensate: expected the path of a diagnosis.json, got {value!r}")
            checked[name] = _absolute(where, name, folder / value.strip())
        else:  # _BOOLEANS
            if not isinstance(value, bool):
                raise FileFormatError(f"{where}: {name}: expected true or false, got {value!r}")
            checked[name] = value
    return dataclasses.replace(base, **checked)


def _paths(where: str, name: str, value: Any, folder: Path) -> tuple[Path, ...]:
    if not isinstance(value, list) or not all(isinstance(item, str) and item.strip() for item in value):
        raise FileFormatError(f"{where}: {name}: expected a list of file paths (strings), got {value!r}")
    return tuple(_absolute(where, name, folder / item.strip()) for item in value)


def _absolute(where: str, name: str, path: Path) -> Path:
    """``path`` resolved, or FileFormatError naming the field for a loop of symbolic links."""
    try:
        resolved = path.resolve()
        os.stat(path)
    except RuntimeError as error:  # "Symlink loop" (pathlib before Python 3.13)
        raise FileFormatError(f"{where}: {name}: {path} is a loop of symbolic links") from error
    except OSError as error:  # not opened here (a cluster's workers may see another file system), but a loop is one
        if error.errno == errno.ELOOP:
            raise FileFormatError(f"{where}: {name}: {path} is a loop of symbolic links") from error
    return resolved


def _subject(
    where: str,
    subject_id: Any,
    palpations: tuple[Path, ...],
    sweeps: tuple[Path, ...],
    diagnosis: tuple[Path, ...],
    options: Options,
) -> Subject:
    if not isinstance(subject_id, str) or not _SUBJECT_ID.fullmatch(subject_id):
        raise FileFormatError(
            f"{where}: id: expected a name of letters, digits, '.', '_' and '-' (it names the output folder), "
            f"got {subject_id!r}"
        )
    if not palpations:
        raise FileFormatError(f"{where}: palpations: expected at least one palpation to fit the model to")
    if options.flexible_layer_mm is None:
        raise FileFormatError(f"{where}: flexible_layer_mm: required (in the subject's options or the defaults)")
    if options.coverage and not options.volume:
        raise FileFormatError(f"{where}: coverage: needs volume = true")
    try:  # before any work: a missing or refused diagnosis would fail each of the subject's tasks
        options.compensation()
    except InputError as error:
        raise FileFormatError(f"{where}: {error}") from None
    for name, paths in (("palpations", palpations), ("sweeps", sweeps), ("diagnosis", diagnosis)):
        repeated_paths = sorted({str(path) for path in paths if paths.count(path) > 1})
        if repeated_paths:
            raise FileFormatError(f"{where}: {name}: {repeated_paths[0]} is listed twice")
    names = [recording_name(path) for path in sweeps]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise FileFormatError(f"{where}: sweeps: two sweeps named {repeated[0]!r} would write the same outputs")
    return Subject(subject_id, palpations, sweeps, diagnosis, options)


def _read_toml(path: Path, text: str) -> tuple[Subject, ...]:
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # Python 3.10
        try:
            import tomli as tomllib
        except ImportError:
            raise ImportError(
                "reading TOML manifests on Python 3.10 needs tomli: pip install 'usdeform[cluster]'"
            ) from None
    try:
        document = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise FileFormatError(f"{path}: not valid TOML: {error}") from None
    _check_known(str(path), document, ("options", "subjects"), "top-level key(s)")
    defaults = document.get("options", {})
    if not isinstance(defaults, dict):
        raise FileFormatError(f"{path}: options: expected a table")
    base = _options(f"{path}: options", defaults, Options(), path.parent)
    items = document.get("subjects")
    if not isinstance(items, list) or not items:
        raise FileFormatError(f"{path}: subjects: expected one or more [[subjects]] tables")
    subjects = []
    for index, item in enumerate(items):
        where = f"{path}: subjects[{index}]"
        if not isinstance(item, dict):
            raise FileFormatError(f"{where}: expected a table")
        if isinstance(item.get("id"), str):
            where += f" (id {item['id']!r})"
        _check_known(where, item, ("id", "palpations", "sweeps", "diagnosis", "options"), "key(s)")
        overrides = item.get("options", {})
        if not isinstance(overrides, dict):
            raise FileFormatError(f"{where}: options: expected a table")
        palpations = _paths(where, "palpations", item.get("palpations"), path.parent)
        sweeps = _paths(where, "sweeps", item.get("sweeps", []), path.parent)
        diagnosis_value = item.get("diagnosis", False)
        if isinstance(diagnosis_value, bool):
            diagnosis = palpations if diagnosis_value else ()
        else:
            diagnosis = _paths(where, "diagnosis (true, false or a list of paths)", diagnosis_value, path.parent)
        options = _options(f"{where}: options", overrides, base, path.parent)
        subjects.append(_subject(where, item.get("id"), palpations, sweeps, diagnosis, options))
    return tuple(subjects)


def _cell_value(where: str, name: str, cell: str) -> Any:
    """A CSV cell of option column ``name`` as the type TOML would give it."""
    if name in _BOOLEANS:
        if cell.lower() not in _TRUE + _FALSE:
            raise FileFormatError(f"{where}: {name}: expected true or false, got {cell!r}")
        return cell.lower() in _TRUE
    number = NUMBERS.get(name)
    if number is not None:
        return number.parse_text(cell, f"{where}: {name}", error=FileFormatError)
    return cell


def _split_paths(where: str, name: str, cell: str, folder: Path) -> tuple[Path, ...]:
    return tuple(_absolute(where, name, folder / item.strip()) for item in cell.split(";") if item.strip())


def _read_csv(path: Path, text: str) -> tuple[Subject, ...]:
    reader = csv.DictReader(text.splitlines())
    columns = [name.strip() for name in reader.fieldnames or []]
    if "subject" not in columns or "palpations" not in columns:
        raise FileFormatError(f"{path}: line 1: the header must name the columns subject and palpations, got {columns}")
    _check_known(
        f"{path}: line 1", columns, ("subject", "palpations", "sweeps", "diagnosis", *_OPTION_NAMES), "column(s)"
    )
    reader.fieldnames = columns
    subjects = []
    for row in reader:
        where = f"{path}: line {reader.line_num}"
        if None in row:
            raise FileFormatError(f"{where}: more cells than the {len(columns)} columns of the header")
        cells = {name: (value or "").strip() for name, value in row.items()}
        if not any(cells.values()):
            continue  # a blank line
        palpations = _split_paths(where, "palpations", cells["palpations"], path.parent)
        diagnosis_cell = cells.get("diagnosis", "")
        if diagnosis_cell.lower() in _TRUE + _FALSE:
            diagnosis = palpations if diagnosis_cell.lower() in _TRUE else ()
        else:
            diagnosis = _split_paths(where, "diagnosis", diagnosis_cell, path.parent)
        values = {
            name: _cell_value(where, name, cell) for name, cell in cells.items() if name in _OPTION_NAMES and cell
        }
        options = _options(where, values, Options(), path.parent)
        sweeps = _split_paths(where, "sweeps", cells.get("sweeps", ""), path.parent)
        subjects.append(_subject(where, cells["subject"], palpations, sweeps, diagnosis, options))
    if not subjects:
        raise FileFormatError(f"{path}: no subject rows below the header")
    return tuple(subjects)


def read_manifest(path: str | Path) -> Manifest:
    """Read and validate a batch manifest (``.toml`` or ``.csv``; see :mod:`usdeform.batch`).

    Relative recording paths are taken relative to the manifest's folder. Raises FileFormatError
    naming the line or field at fault, InputError for an unknown file type, OSError if unreadable.
    """
    path = _absolute("manifest", "MANIFEST", Path(path))
    readers = {".toml": _read_toml, ".csv": _read_csv}
    reader = readers.get(path.suffix.lower())
    if reader is None:
        raise InputError(f"manifest: {path} must end in .toml or .csv")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as error:
        raise FileFormatError(f"{path}: not UTF-8 text ({error})") from None
    subjects = reader(path, text)
    seen: set[str] = set()
    for subject in subjects:
        if subject.id in seen:
            raise FileFormatError(f"{path}: subject {subject.id!r} is listed twice")
        seen.add(subject.id)
    return Manifest(subjects, path)
