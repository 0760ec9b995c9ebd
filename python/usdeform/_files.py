"""Atomic outputs: files that replace their targets only when complete, written alone or together, and the
checks of output paths and folders before any work."""

from __future__ import annotations

import contextlib
import contextvars
import errno
import glob
import os
import re
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import BinaryIO

from .errors import InputError

__all__ = [
    "CACHE_LIMIT_VARIABLE",
    "atomic_output",
    "cache_limit_bytes",
    "check_output_folder",
    "check_output_paths",
    "mark_used",
    "new_output_folders",
    "outputs_together",
    "prune_cache",
]

#: The environment variable that caps each on-disk cache folder (FEM solutions, FEM library entries), in MB.
CACHE_LIMIT_VARIABLE = "USDEFORM_CACHE_MAX_MB"
_DEFAULT_CACHE_LIMIT_MB = 4096.0


def cache_limit_bytes() -> int:
    """The most bytes a cache folder may hold: ``$USDEFORM_CACHE_MAX_MB`` (default 4096 MB), else InputError naming
    the variable where it is no positive number."""
    text = os.environ.get(CACHE_LIMIT_VARIABLE, "").strip()
    try:
        megabytes = float(text) if text else _DEFAULT_CACHE_LIMIT_MB
    except ValueError:
        megabytes = float("nan")
    if not megabytes > 0 or megabytes == float("inf"):
        raise InputError(f"{CACHE_LIMIT_VARIABLE}: expected a positive number of MB, got {text!r}")
    return int(megabytes * 1024 * 1024)


def mark_used(path: Path) -> None:
    """Set a cache file's modification time to now: :func:`prune_cache` removes the least recently used first."""
    with contextlib.suppress(OSError):
        os.utime(path)


def prune_cache(directory: Path, keep: Path) -> None:
    """Remove the least recently used ``*.npz`` files of ``directory`` (oldest modification time first, see
    :func:`mark_used`) until it holds at most :func:`cache_limit_bytes`; never ``keep``, the entry just written.
    Files another process removes first are skipped."""
    limit = cache_limit_bytes()
    entries = []
    for path in directory.glob("*.npz"):
        with contextlib.suppress(OSError):
            status = path.stat()
            entries.append((status.st_mtime, status.st_size, path))
    total = sum(size for _, size, _ in entries)
    for _, size, path in sorted(entries):
        if total <= limit:
            break
        if path == keep:
            continue
        with contextlib.suppress(OSError):
            path.unlink()
        total -= size


def _process_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_process_umask()


# The files written inside an ``outputs_together`` block: (temporary, target) pairs not yet renamed.
_PENDING: contextvars.ContextVar[list[tuple[Path, Path]] | None] = contextvars.ContextVar("_PENDING", default=None)
_PART = ".part"


@contextlib.contextmanager
def outputs_together() -> Iterator[None]:
    """Files written with :func:`atomic_output` inside the block replace their targets together when it
    succeeds (one rename each, in order, after all were written); on any error, including Ctrl-C or
    SIGTERM, none of them is replaced and their temporary files are removed. Blocks nest (an inner
    block joins the outer one)."""
    if _PENDING.get() is not None:
        yield
        return
    pending: list[tuple[Path, Path]] = []
    token = _PENDING.set(pending)
    try:
        yield
    except BaseException:
        _remove(temporary for temporary, _ in pending)
        raise
    finally:
        _PENDING.reset(token)
    folders = [path for _, path in pending if path.is_dir()]
    if folders:  # os.replace would fail on it after the files before it were replaced
        _remove(temporary for temporary, _ in pending)
        raise IsADirectoryError(errno.EISDIR, "is a folder, not a file; nothing was written", str(folders[0]))
    for index, (temporary, path) in enumerate(pending):
        try:
            os.replace(temporary, path)
        except OSError as error:
            _remove(temporary for temporary, _ in pending[index:])
            raise _naming_output(error, path) from None
        except BaseException:
            _remove(temporary for temporary, _ in pending[index:])
            raise


def _naming_output(error: OSError, path: Path) -> OSError:
    """``error`` naming the output ``path`` where it names one of its temporary files or no file ("[Errno 27] File
    too large" from a write); an error naming another file is returned as it is."""
    named = error.filename
    if named is not None and not (Path(named).name.startswith(f".{path.name}.") and str(named).endswith(_PART)):
        return error
    if error.errno is None:  # raised without an error number (a message alone): keep the message
        return type(error)(f"{path}: {error}")
    return type(error)(error.errno, error.strerror, str(path))


def _remove(paths: Iterable[Path]) -> None:
    for path in paths:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)


def _process_exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process
        return True
    return True


def _remove_stale_parts(path: Path) -> None:
    """Remove ``path``'s temporary files left by processes that no longer run (killed with SIGKILL,
    which no handler sees); their names carry the writer's process id."""
    prefix = f".{path.name}."
    for candidate in path.parent.glob(f"{glob.escape(prefix)}*{_PART}"):
        # PID.RANDOM.part exactly: ".v.nrrd.5.123.x.part" belongs to the target "v.nrrd.5", not "v.nrrd".
        match = re.fullmatch(r"(\d+)\.[^.]+\.part", candidate.name[len(prefix) :])
        if match and int(match.group(1)) != os.getpid() and not _process_exists(int(match.group(1))):
            _remove([candidate])


@contextlib.contextmanager
def atomic_output(path: Path) -> Iterator[BinaryIO]:
    """Yield a binary file that replaces ``path`` only once the ``with`` block succeeds.

    The data go to a temporary file ``.NAME.PID.XXXX.part`` in the same directory, which is flushed
    to disk and then renamed over ``path`` (``os.replace``, atomic on POSIX and Windows), or inside
    :func:`outputs_together` at the end of that block; on any error the temporary file is removed
    and ``path`` is left as it was. Temporary files of ``path`` left by killed processes are removed.
    """
    path = Path(path)
    _remove_stale_parts(path)
    try:
        descriptor, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.{os.getpid()}.", suffix=_PART)
    except OSError as error:
        raise _naming_output(error, path) from None
    temporary = Path(name)
    try:
        with os.fdopen(descriptor, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(temporary, _FILE_MODE)
        pending = _PENDING.get()
        if pending is None:
            os.replace(temporary, path)
        else:
            pending.append((temporary, path))
    except OSError as error:
        _remove([temporary])
        raise _naming_output(error, path) from None
    except BaseException:
        _remove([temporary])
        raise


def check_output_paths(
    outputs: Mapping[str, tuple[Path | None, tuple[str, ...]]], inputs: Mapping[str, Path | None]
) -> None:
    """Refuse, before anything is read or written, an input given twice (two palpations that are one file
    would be fitted as two), and an output with an unwritable suffix, in a folder that does not exist, that is
    a folder, equal to an input (it would be replaced) or to another output.

    ``outputs`` maps each output's name (e.g. ``--volume``) to its path (None: not asked for) and the
    suffixes it may have; ``inputs`` maps each input's name to its path. InputError names both.
    """
    seen: dict[object, str] = {}
    for name, path in inputs.items():
        if path is not None:
            identity = _identity(path, name)
            if identity in seen:
                raise InputError(f"{name}: {path} is also {seen[identity]}; give each input once")
            seen[identity] = name
    for name, (path, suffixes) in outputs.items():
        if path is None:
            continue
        if path.suffix.lower() not in suffixes:
            raise InputError(f"{name}: {path} must end in {', '.join(suffixes)}")
        if not path.parent.is_dir():
            raise InputError(f"{name}: folder {path.parent} does not exist")
        if path.is_dir():
            raise InputError(f"{name}: {path} is a folder, not a file")
        identity = _identity(path, name)
        if identity in seen:
            raise InputError(f"{name}: {path} is also {seen[identity]}; it would be overwritten")
        seen[identity] = name


def check_output_folder(folder: str | Path, option: str) -> Path:
    """Refuse, before any work, an output folder that is an existing file or cannot be written.

    The folder need not exist: its nearest existing ancestor must be a folder one can create files in (tried with
    a temporary file, which also catches read-only file systems and, unlike ``os.access``, holds for root).
    Raises InputError naming ``option`` and the path; returns the path.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{option}: {folder} is an existing file, not a folder (a folder is created if missing)")
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(f"{option}: {folder} cannot be created: {existing} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as error:
        raise InputError(f"{option}: {folder} cannot be written ({existing}: {error.strerror or error})") from None
    return folder


def new_output_folders(folder: Path, name: str) -> list[Path]:
    """The folders that writing into ``folder`` creates (``folder`` and its missing parents, outermost
    last), so that a failed run can remove them; InputError naming the option ``name``, before any
    work, when ``folder`` is a file or cannot be created (:func:`check_output_folder`)."""
    folder = check_output_folder(folder, name)
    return [path for path in (folder, *folder.parents) if not path.exists()]


def _identity(path: Path, name: str) -> object:
    """What makes two paths one file: device and inode when it exists (symbolic and hard links), else
    the resolved path; InputError naming ``name`` for a loop of symbolic links (pathlib raises
    RuntimeError for it, which no caller expects)."""
    try:
        status = os.stat(path)
    except OSError as error:
        try:
            if error.errno == errno.ELOOP:
                raise RuntimeError("Symlink loop")
            return path.resolve()
        except RuntimeError as loop:  # a loop; pathlib says "Symlink loop" before Python 3.13
            raise InputError(f"{name}: {path} is a loop of symbolic links") from loop
    return (status.st_dev, status.st_ino)
