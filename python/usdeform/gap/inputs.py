"""The recordings given to ``diagnose``: PLUS sequence files or folders of them, sorted into palpations, sweeps (left
out) and known-weight recordings (the force sensor's calibration, :mod:`usdeform.gap.sensor_calibration`)."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import PlusConfig, read_sequence
from ..recording import Recording
from .sensor_calibration import is_known_weight

__all__ = ["as_recordings"]

_SEQUENCE_SUFFIXES = (".mha", ".mhd", ".nrrd")


def _is_sweep(recording: Recording) -> bool:
    """Whether the probe travels across the surface (a sweep) rather than pressing in place (a palpation):
    its origin moves more than 5 mm, and more than twice lambda's range, perpendicular to its axis."""
    poses = recording.probe_to_base[recording.pose_valid]
    if len(poses) < 2:
        return False
    travel = poses[:, :3, 3] - poses[0, :3, 3]
    axis = poses[0, :3, 2]
    lateral = travel - np.outer(travel @ axis, axis)
    distance = float(np.max(np.linalg.norm(lateral, axis=1)))
    pressing = float(np.ptp(recording.probe_displacement)) if recording.probe_displacement is not None else 0.0
    return distance > 5.0 and distance > 2 * pressing


def _frames_digest(recording: Recording) -> str:
    """SHA-256 of a recording's frames (shape, dtype and bytes): the same palpation under two names has one."""
    frames = np.ascontiguousarray(recording.frames)
    digest = hashlib.sha256(f"{frames.shape}{frames.dtype}".encode())
    digest.update(frames.tobytes())
    return digest.hexdigest()


def as_recordings(
    recordings: Sequence[Recording | str | Path], config: PlusConfig | str | Path | None = None
) -> tuple[list[tuple[str, Recording]], list[str], list[Path]]:
    """Named palpation recordings (folders expanded to their sequence files, read with ``config``), the names of
    skipped sweeps, and the known-weight recordings (files with a per-frame ``KnownLoad``, not read as palpations).

    Refused (InputError naming the file or folder): a folder without sequence files, and a recording given twice,
    by the same path or with the same frames under another name (it would count its evidence twice)."""
    named: list[tuple[str, Recording]] = []
    sweeps: list[tuple[str, Recording]] = []
    known_weights: list[Path] = []
    seen_paths: dict[Path, str] = {}
    seen_frames: dict[str, str] = {}
    for index, item in enumerate(recordings):
        if isinstance(item, Recording):
            files: list[Path] = []
            candidates = [(f"recording {index}", item)]
        elif Path(item).is_dir():
            files = sorted(p for p in Path(item).iterdir() if p.name.lower().endswith(_SEQUENCE_SUFFIXES))
            if not files:
                raise InputError(f"{item}: no PLUS sequence files ({', '.join(_SEQUENCE_SUFFIXES)}) in this folder")
        else:
            files = [Path(item)]
        for path in files:
            _check_once(path, seen_paths)
        known_weights += [path for path in files if path.is_file() and is_known_weight(path)]
        if files:
            candidates = [(str(p), read_sequence(p, config)) for p in files if p not in known_weights]
        for name, recording in candidates:
            digest = _frames_digest(recording)
            if digest in seen_frames:
                raise InputError(
                    f"{name}: the same frames as {seen_frames[digest]} (one palpation given twice); give each once"
                )
            seen_frames[digest] = name
            (sweeps if _is_sweep(recording) else named).append((name, recording))
    if not named:
        raise InputError("recordings: expected at least one palpation recording (sweeps alone cannot be diagnosed)")
    return named, [name for name, _ in sweeps], known_weights


def _check_once(path: Path, seen: dict[Path, str]) -> None:
    """Refuse ``path`` when the same file (by its resolved path) was given before."""
    try:
        resolved = path.resolve()
    except RuntimeError as loop:  # pathlib's "Symlink loop" before Python 3.13
        raise InputError(f"{path} is a loop of symbolic links") from loop
    if resolved in seen:
        raise InputError(f"{path}: given twice (also as {seen[resolved]}); give each recording once")
    seen[resolved] = str(path)
