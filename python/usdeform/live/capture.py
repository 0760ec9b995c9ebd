"""Recordings started and stopped by Plus Remote, as PLUS Server's VirtualCapture device makes them.

``StartRecording`` begins a recording of the frames the live service takes in, ``SuspendRecording`` and
``ResumeRecording`` pause it, ``StopRecording`` writes it to a PLUS sequence file
(:func:`usdeform.io.write_sequence`). Files named by a command are written in the service's output
directory, as PLUS writes them in its output directory; a name with a directory part is refused.
"""

from __future__ import annotations

import time
from pathlib import Path

from ..errors import InputError

__all__ = ["Capture", "output_file"]

#: Suffixes of the files a command may name: sequence files and volumes.
_SUFFIXES = (".mha", ".mhd", ".nrrd")


def output_file(directory: Path, name: str, option: str) -> Path:
    """The file ``name`` (a file name, no directory part) in ``directory``; InputError naming ``option``
    if it has a directory part or an unknown suffix."""
    if not name or Path(name).name != name or name in (".", ".."):
        raise InputError(f"{option} {name!r}: a file name without a directory is expected")
    if not name.lower().endswith(_SUFFIXES):
        raise InputError(f"{option} {name!r}: must end in .mha, .mhd or .nrrd (.seq.nrrd)")
    return directory / name


def default_recording_name() -> str:
    """PLUS's default name of a recording, with the local time: ``Recording_YYYYMMDD_HHMMSS.seq.nrrd``."""
    return time.strftime("Recording_%Y%m%d_%H%M%S.seq.nrrd")


class Capture:
    """A recording to ``path``: the spans ``[start, stop)`` of stored frames captured so far, and whether
    it is capturing (else suspended). ``first_frame``: frames stored when it started."""

    def __init__(self, path: Path, first_frame: int) -> None:
        self.path = path
        self.capturing = True
        self._spans: list[tuple[int, int]] = []
        self._start = first_frame

    def suspend(self, frames_stored: int) -> None:
        self._spans.append((self._start, frames_stored))
        self.capturing = False

    def resume(self, frames_stored: int) -> None:
        self._start, self.capturing = frames_stored, True

    def spans(self, frames_stored: int) -> list[tuple[int, int]]:
        """The spans captured when ``frames_stored`` frames are stored."""
        return self._spans + ([(self._start, frames_stored)] if self.capturing else [])

    def frames(self, frames_stored: int) -> int:
        """Frames captured when ``frames_stored`` frames are stored."""
        return sum(stop - start for start, stop in self.spans(frames_stored))
