"""The exception hierarchy of usdeform.

Every error the package raises on purpose derives from :class:`UsdeformError`. Errors caused by the
caller's input also derive from :class:`ValueError`, so ``except ValueError`` keeps working. The
compiled core (``usdeform._core``) raises these same classes.
"""

from __future__ import annotations

__all__ = [
    "FileFormatError",
    "FitError",
    "InputError",
    "InternalError",
    "MemoryLimitError",
    "UsdeformError",
]


class UsdeformError(Exception):
    """Base class of every error raised by usdeform."""


class InputError(UsdeformError, ValueError):
    """An argument has the wrong shape, dtype, length or value (the message names it)."""


class FileFormatError(InputError):
    """A file is malformed or truncated (the message names the file, field or frame)."""


class MemoryLimitError(InputError):
    """An output would need more memory than the caller allowed; raise the limit to proceed."""


class FitError(UsdeformError, ValueError):
    """A model cannot be fitted to the given data (too few samples, degenerate or unphysical fit)."""


class InternalError(UsdeformError, RuntimeError):
    """A bug inside usdeform (for example a panic in the compiled core); please report it."""
