"""The live scan's frames: kept on disk as they arrive, corrected and compounded into a volume that
grows with the scan.

Every paired frame is appended to a :class:`FrameStore` (pixels and fields in files; nothing per frame
in memory), which later becomes the recording written to a PLUS sequence file. A batch of
frames is corrected once, by :func:`usdeform.reconstruction.correct_recording`, the function
``usdeform correct`` runs; the corrected frames are appended to files of the same store (pixels, their
validity mask as bits, their poses; nothing per frame in memory) and compounded by
:class:`usdeform.compounding.Compounder` (the kernels give the same voxels for any batching and thread
count). The volume sent during the scan is built from the compounder on another thread, for the box
of the grid the frames reach only (:meth:`LiveVolume.sent_volume`); a lock orders it with the
compounding, while the correction of the next frames goes on.

The grid: a recording's volume encloses all its frames, which a live scan knows only at its end. The
live volume's grid encloses the frames so far plus a margin; a frame outside it grows the grid (the
corrected frames so far, mapped back from the store, are inserted into the larger grid). At the end,
:meth:`LiveVolume.final_volume` compounds the stored corrected frames on the grid ``usdeform correct
--volume`` uses for the recording, with the same hole filling and voxel type: the same volume, voxel
for voxel (the correction of a frame is deterministic, and a vessel-anchored model's lumen search
batch after batch is the one pass ``usdeform correct`` makes).
"""

from __future__ import annotations

import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..correction import SampledProfiles, correct_recording
from ..errors import InputError
from ..io import write_sequence
from ..options import Compounding, Interpolation, StiffnessSource
from ..recording import Recording
from ..regression import DeformationModel, LumenTrack
from ..volume import (
    DEFAULT_MAX_BYTES,
    DEFAULT_SPACING_MM,
    Compounder,
    HoleFillingElement,
    Volume,
    VoxelGrid,
    VoxelType,
    corner_points,
    finish_volume,
)
from .pairing import PairedFrame

__all__ = ["FrameStore", "LiveVolume"]

#: Stored corrected frames inserted at once when a grid is filled: a multiple of the compounding's
#: 16-frame batch, small so that the frames' correction waits little for the threads meanwhile
#: (unpacking 32 validity masks holds the interpreter lock for about 1 ms of 256 x 256 frames).
_CHUNK = 32
#: Float64 fields of a stored frame: timestamp, ``probe_to_base`` (16, row-major), force, displacement.
_N_FIELDS = 19


class _AppendedArrays:
    """Arrays of one record shape and dtype appended to a file and mapped back from it (the caller
    holds the lock that orders writing and reading)."""

    def __init__(self, path: Path, dtype: type, shape: tuple[int, ...]) -> None:
        self.path, self.dtype, self.shape = path, np.dtype(dtype), shape
        self.record_bytes = self.dtype.itemsize * int(np.prod(shape))
        self._file = path.open("wb")

    def append(self, records: np.ndarray) -> None:
        self._file.write(np.ascontiguousarray(records, dtype=self.dtype).data)

    def flush(self) -> None:
        self._file.flush()

    def map(self, start: int, stop: int) -> np.ndarray:
        """Records ``start:stop``, mapped read-only from the file (which the caller has flushed)."""
        if stop <= start:
            return np.empty((0, *self.shape), dtype=self.dtype)
        offset = start * self.record_bytes
        return np.memmap(self.path, dtype=self.dtype, mode="r", offset=offset, shape=(stop - start, *self.shape))

    def close(self) -> None:
        self._file.close()


class FrameStore:
    """The paired frames of a live scan, appended to files: pixels (uint8) and fields (float64: the
    timestamp, s, ``probe_to_base`` row-major, mm, the force, N, and the probe displacement, mm); and the
    same frames corrected (:meth:`append_corrected`): pixels, validity mask (one bit a pixel) and
    ``image_to_base`` poses (float64, mm). Nothing per frame is kept in memory: a session's memory
    does not grow with its length (the files do: about 2.1 bytes a pixel and 280 bytes a frame).

    The files are written by the thread that processes the frames and read back (:meth:`recording`,
    :meth:`corrected`) from the thread that grows the grid: one lock orders them, each read flushes
    the files first.

    Parameters
    ----------
    directory : Path, optional
        Where the store's temporary directory, holding its files, goes (None: the system's); the
        directory is removed by :meth:`close`.
    frame_shape : tuple of int
        ``(rows, cols)``.
    image_to_probe : ndarray
        The calibration, (4, 4) mm.
    with_displacement : bool
        The frames carry a probe displacement.
    """

    def __init__(
        self,
        frame_shape: tuple[int, int],
        image_to_probe: np.ndarray,
        *,
        with_displacement: bool,
        directory: Path | None = None,
    ) -> None:
        self._temporary = tempfile.TemporaryDirectory(prefix="usdeform-live-", dir=directory)
        self.frame_shape = frame_shape
        self.image_to_probe = np.asarray(image_to_probe, dtype=np.float64)
        self.with_displacement = with_displacement
        self._lock = threading.Lock()  # the files are read back from the thread that grows the grid
        folder = Path(self._temporary.name)
        rows, cols = frame_shape
        self._pixels = _AppendedArrays(folder / "frames.u8", np.uint8, (rows, cols))
        self._fields = _AppendedArrays(folder / "fields.f8", np.float64, (_N_FIELDS,))
        self._corrected = _AppendedArrays(folder / "corrected.u8", np.uint8, (rows, cols))
        self._valid = _AppendedArrays(folder / "valid.bits", np.uint8, (-(-rows * cols // 8),))
        self._image_to_base = _AppendedArrays(folder / "image_to_base.f8", np.float64, (4, 4))
        self.n_frames = 0  # paired frames stored
        self.n_corrected = 0  # corrected frames stored

    def __len__(self) -> int:
        return self.n_frames

    def append(self, frames: Sequence[PairedFrame]) -> Recording:
        """Keep ``frames``; returns them as a recording (the fields exactly as they will be written)."""
        fields = np.empty((len(frames), _N_FIELDS), dtype=np.float64)
        fields[:, 0] = [frame.timestamp for frame in frames]
        fields[:, 1:17] = np.reshape([frame.probe_to_base for frame in frames], (len(frames), 16))
        fields[:, 17] = [frame.force for frame in frames]
        fields[:, 18] = [frame.displacement or 0.0 for frame in frames]
        batch = self._recording(np.stack([frame.pixels for frame in frames]), fields)
        with self._lock:
            self._pixels.append(batch.frames)
            self._fields.append(fields)
            self.n_frames += len(frames)
        return batch

    def _recording(self, pixels: np.ndarray, fields: np.ndarray, metadata: dict[str, str] | None = None) -> Recording:
        """A recording of ``pixels`` (n, rows, cols) and their ``fields`` (n, 19), as :meth:`append` lays them."""
        return Recording(
            frames=pixels,
            timestamps=fields[:, 0].copy(),
            probe_to_base=fields[:, 1:17].reshape(-1, 4, 4).copy(),
            pose_valid=np.ones(len(fields), dtype=bool),
            image_to_probe=self.image_to_probe,
            force=fields[:, 17].copy(),
            probe_displacement=fields[:, 18].copy() if self.with_displacement else None,
            metadata=metadata or {},
        )

    def recording(self, start: int = 0, stop: int | None = None, metadata: dict[str, str] | None = None) -> Recording:
        """Frames ``start:stop`` as a recording; the pixels are mapped from the file, not loaded."""
        with self._lock:
            stop = self.n_frames if stop is None else stop
            self._pixels.flush()
            self._fields.flush()
        return self._recording(self._pixels.map(start, stop), self._fields.map(start, stop), metadata)

    def append_corrected(self, corrected: Recording) -> None:
        """Keep ``corrected``, the next frames as :func:`~usdeform.reconstruction.correct_recording`
        returns them (uint8 pixels of :attr:`frame_shape`): pixels, ``pixel_valid`` (all valid
        without one, which compounds the same) and ``image_to_base``."""
        frames = np.asarray(corrected.frames)
        n = len(frames)
        if corrected.pixel_valid is None:
            valid = np.ones((n, frames.shape[1] * frames.shape[2]), dtype=bool)
        else:
            valid = np.asarray(corrected.pixel_valid).reshape(n, -1)
        packed, image_to_base = np.packbits(valid, axis=1), corrected.image_to_base
        with self._lock:
            self._corrected.append(frames)
            self._valid.append(packed)
            self._image_to_base.append(image_to_base)
            self.n_corrected += n

    def corrected(self, start: int = 0, stop: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Corrected frames ``start:stop``: their pixels (uint8, ``(n, rows, cols)``, mapped from the
        file, not loaded), validity mask (bool, the same shape) and ``image_to_base`` poses
        (``(n, 4, 4)`` float64, mm), as :meth:`append_corrected` kept them."""
        with self._lock:
            stop = self.n_corrected if stop is None else stop
            for appended in (self._corrected, self._valid, self._image_to_base):
                appended.flush()
        rows, cols = self.frame_shape
        packed = self._valid.map(start, stop)
        valid = np.unpackbits(packed, axis=1, count=rows * cols).view(np.bool_).reshape(-1, rows, cols)
        return self._corrected.map(start, stop), valid, np.array(self._image_to_base.map(start, stop))

    def write(self, path: Path, metadata: dict[str, str], spans: Sequence[tuple[int, int]] | None = None) -> int:
        """Write the frames so far (or those of the ``[start, stop)`` ``spans``) to a PLUS sequence file
        (``usdeform correct`` redoes the scan from it); returns the frames written. Frames of several
        spans are read into memory; one span or all are written from the files."""
        if spans is None:
            spans = [(0, self.n_frames)]
        spans = [(start, stop) for start, stop in spans if stop > start]
        if not spans:
            raise InputError(f"{path}: no frame was recorded")
        if len(spans) == 1:
            recording = self.recording(*spans[0], metadata=metadata)
        else:
            recording = self.recording(metadata=metadata).select(np.concatenate([np.arange(*span) for span in spans]))
        write_sequence(path, recording)
        return len(recording)

    def close(self) -> None:
        for appended in (self._pixels, self._fields, self._corrected, self._valid, self._image_to_base):
            appended.close()
        self._temporary.cleanup()


class LiveVolume:
    """Frames corrected to zero force and compounded into a grid that grows with the scan.

    Parameters
    ----------
    store : FrameStore
        The frames kept so far; :meth:`add` keeps each batch corrected in it too, and a grown grid and
        :meth:`final_volume` are compounded from those stored corrected frames.
    model : DisplacementModel or VesselAnchoredModel
        The fitted model (a vessel-anchored one follows the lumen from batch to batch as one call over
        the whole scan would: :class:`~usdeform.regression.LumenTrack`).
    sampled : SampledProfiles
        The palpated positions and their stiffness, as the model file holds them.
    stiffness_source : {"interpolated", "sweep"}
        As for :func:`~usdeform.reconstruction.correct_recording`.
    clamp_force : bool
        Clamp forces outside the model's range (else such frames must not reach :meth:`add`).
    spacing_mm, interpolation, compounding, max_bytes
        The volume's, as for ``usdeform correct --volume``.
    margin_mm : float
        Room left around the frames when the grid grows, mm.
    grid : VoxelGrid, optional
        A fixed grid (Plus Remote's OutputOrigin, OutputExtent and OutputSpacing): it never grows, the
        parts of frames outside it are left out, and the final volume is on it. None: the grid grows
        with the frames.
    """

    def __init__(
        self,
        store: FrameStore,
        model: DeformationModel,
        sampled: SampledProfiles,
        *,
        stiffness_source: StiffnessSource,
        clamp_force: bool = False,
        spacing_mm: float = DEFAULT_SPACING_MM,
        interpolation: Interpolation = "nearest",
        compounding: Compounding = "mean",
        max_bytes: int = DEFAULT_MAX_BYTES,
        margin_mm: float = 10.0,
        grid: VoxelGrid | None = None,
    ) -> None:
        self.store, self.model, self.sampled = store, model, sampled
        self.stiffness_source: StiffnessSource = stiffness_source
        self.clamp_force = clamp_force
        self.spacing_mm, self.interpolation, self.compounding = spacing_mm, interpolation, compounding
        self.max_bytes, self.margin_mm, self.grid = max_bytes, margin_mm, grid
        self.compounder: Compounder | None = None
        self.lumen_track = LumenTrack()  # the scan's lumen search so far (vessel-anchored models)
        self.lower = np.full(3, np.inf)
        self.upper = np.full(3, -np.inf)
        self.regrown = 0
        self._growing: _Growth | None = None
        self._frames_inserted = 0
        # Orders the compounder's use: frames are added on the processing thread, the volumes sent
        # are built on the sending thread (:meth:`sent_volume`).
        self._lock = threading.Lock()

    def correct(self, batch: Recording, lumen_track: LumenTrack) -> Recording:
        """``batch`` corrected as ``usdeform correct`` corrects a recording, the next part of the scan
        whose lumen search so far is ``lumen_track`` (updated)."""
        return correct_recording(
            batch,
            self.model,
            self.sampled,
            stiffness_source=self.stiffness_source,
            clamp_force=self.clamp_force,
            name="live scan",
            lumen_track=lumen_track,
        )

    def add(self, batch: Recording) -> Recording:
        """Correct ``batch`` (frames already in the store, last), keep it corrected in the store and
        compound it (:meth:`correct_next` then :meth:`compound`); returns it corrected."""
        corrected = self.correct_next(batch)
        self.compound(corrected)
        return corrected

    def correct_next(self, batch: Recording) -> Recording:
        """Correct ``batch`` (frames already in the store, last) and keep it corrected in the store;
        returns it corrected, to be handed to :meth:`compound` next. Runs while a volume may be built
        (:meth:`sent_volume`)."""
        self.poll()
        corrected = self.correct(batch, self.lumen_track)
        self.store.append_corrected(corrected)
        return corrected

    def compound(self, corrected: Recording) -> None:
        """Compound ``corrected``, the batch :meth:`correct_next` returned last (waits for a volume being
        built by :meth:`sent_volume`).

        A batch reaching past the grid starts a larger grid in a thread, filled with the stored
        corrected frames so far (this batch among them); until it is ready (:meth:`poll`), frames go on
        into the present grid, clipped to it, and the new one gets them from the store."""
        image_to_base = corrected.image_to_base
        corners = corner_points(image_to_base, (0, corrected.shape[1] - 1), (0, corrected.shape[0] - 1))
        with self._lock:
            self.lower = np.minimum(self.lower, corners.min(axis=0))
            self.upper = np.maximum(self.upper, corners.max(axis=0))
            if self.compounder is None:
                self.compounder = self._compounder(self.grid or self._grown_grid())
            elif self.grid is None and self._growing is None and not self._covers(self.compounder.grid):
                self._growing = _Growth(self, self._grown_grid(), self.store.n_corrected)
            self.compounder.add_frames(corrected.frames, image_to_base, valid=corrected.pixel_valid)
            self._frames_inserted = self.compounder.frames_inserted

    def poll(self, *, wait: bool = False) -> None:
        """Move to the grown grid once it holds the frames so far (``wait``: wait for it)."""
        growing = self._growing
        if growing is None or not (wait or growing.done.is_set()):
            return
        self._growing = None
        compounder = growing.result()
        # Those added meanwhile (frames are added on this thread only, so none come in between).
        self._insert(compounder, growing.n_frames, self.store.n_corrected)
        with self._lock:
            self.compounder, self.regrown = compounder, self.regrown + 1
            self._frames_inserted = compounder.frames_inserted
        if not self._covers(compounder.grid):
            self._growing = _Growth(self, self._grown_grid(), self.store.n_corrected)

    def _grown_grid(self) -> VoxelGrid:
        """A grid around the frames so far with room to grow: ``margin_mm`` on every side, and as much
        again as the frames already span on a side they grew past (the grid doubles along a sweep, so
        refilling it costs at most about twice the frames of the scan in all)."""
        extent = self.upper - self.lower
        lower, upper = self.lower - self.margin_mm, self.upper + self.margin_mm
        if self.compounder is not None:
            old = self.compounder.grid
            first = old.origin - 0.5 * old.spacing
            last = old.origin + (np.array(old.shape[::-1]) - 0.5) * old.spacing
            lower = np.where(self.lower < first, lower - extent, np.minimum(lower, first))
            upper = np.where(self.upper > last, upper + extent, np.maximum(upper, last))
        return VoxelGrid.from_bounds(lower, upper, self.spacing_mm)

    def _covers(self, grid: VoxelGrid) -> bool:
        first = grid.origin - 0.5 * grid.spacing
        last = grid.origin + (np.array(grid.shape[::-1]) - 0.5) * grid.spacing
        return bool(np.all(self.lower >= first) and np.all(self.upper <= last))

    def _compounder(self, grid: VoxelGrid) -> Compounder:
        return Compounder(grid, self.interpolation, self.compounding, max_bytes=self.max_bytes)

    def _insert(self, compounder: Compounder, start: int, stop: int) -> None:
        """Insert the store's corrected frames ``start:stop`` into ``compounder``, ``_CHUNK`` at a time."""
        for first in range(start, stop, _CHUNK):
            frames, valid, image_to_base = self.store.corrected(first, min(first + _CHUNK, stop))
            compounder.add_frames(frames, image_to_base, valid=valid)

    def _refill(self, grid: VoxelGrid, n_frames: int) -> Compounder:
        """A compounder on ``grid`` holding the store's first ``n_frames`` corrected frames."""
        compounder = self._compounder(grid)
        self._insert(compounder, 0, n_frames)
        return compounder

    def volume(self) -> Volume | None:
        """The volume so far on the part of the grid the frames reach (None before the first frame)."""
        sent = self.sent_volume()
        return None if sent is None else sent[0]

    def sent_volume(self) -> tuple[Volume, int] | None:
        """The volume so far on the part of the grid the frames reach, and the frames it holds (None
        before the first frame, or while the frames are outside a fixed grid). Only that box of the grid
        is computed (float32 image and weight), while frames wait to be compounded (not to be
        corrected); safe to call from any thread."""
        with self._lock:
            compounder = self.compounder
            if compounder is None:
                return None
            grid = compounder.grid
            first = np.floor((self.lower - grid.origin) / grid.spacing).astype(int)
            last = np.ceil((self.upper - grid.origin) / grid.spacing).astype(int)
            first, last = np.maximum(first, 0), np.minimum(last, np.array(grid.shape[::-1]) - 1)
            if np.any(first > last):  # the frames are outside a fixed grid
                return None
            lo = (int(first[2]), int(first[1]), int(first[0]))
            hi = (int(last[2]) + 1, int(last[1]) + 1, int(last[0]) + 1)
            volume = compounder.volume_region(lo, hi)
            frames = compounder.frames_inserted
        return volume, frames

    @property
    def frames_inserted(self) -> int:
        """Frames in the compounder so far (read without waiting for a volume being built)."""
        return self._frames_inserted

    def final_volume(
        self, *, hole_filling: Sequence[HoleFillingElement] = (), voxel_type: VoxelType = "float32"
    ) -> Volume | None:
        """The volume ``usdeform correct --volume`` makes of the recorded frames: the stored corrected
        frames compounded on the grid enclosing them, then hole filling and the voxel type (None
        without frames)."""
        if not self.store.n_corrected:
            return None
        self.poll(wait=True)
        grid = self.grid or VoxelGrid.from_bounds(self.lower, self.upper, self.spacing_mm)
        compounder = self._refill(grid, self.store.n_corrected)
        return finish_volume(
            compounder.volume(), hole_filling=hole_filling, voxel_type=voxel_type, max_bytes=self.max_bytes
        )


class _Growth:
    """A larger grid being filled in a thread with a live volume's first ``n_frames`` stored corrected
    frames (those stored meanwhile are inserted by :meth:`LiveVolume.poll`)."""

    def __init__(self, volume: LiveVolume, grid: VoxelGrid, n_frames: int) -> None:
        self.n_frames = n_frames
        self.done = threading.Event()
        self._compounder: Compounder | None = None
        self._error: BaseException | None = None

        def fill() -> None:
            try:
                self._compounder = volume._refill(grid, n_frames)
            except BaseException as error:  # handed to the processing thread by result()
                self._error = error
            finally:
                self.done.set()

        threading.Thread(target=fill, name="usdeform-live-grow", daemon=True).start()

    def result(self) -> Compounder:
        self.done.wait()
        if self._error is not None:
            raise self._error
        assert self._compounder is not None
        return self._compounder
