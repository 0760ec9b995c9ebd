"""The live service: OpenIGTLink in, corrected frames and a growing corrected volume out.

The connections and their threads are those of :class:`~usdeform.live.connections.Connections`. The calling
thread pairs and corrects the frames, queues them for the viewers ahead of any volume waiting, then
compounds them. Right after a batch of frames, the packing thread builds the volume sent (the box of
the grid the frames reach, :meth:`~usdeform.live.engine.LiveVolume.sent_volume`) and packs it, in the
gap before the next frame. Everything a connection sends is read as input; the outputs go
to every connection accepted on the listening address that sends no image (placed as
:mod:`~usdeform.live.outputs` says):

- ``Image_Reference`` (IMAGE) and ``ProbeToReference`` (TRANSFORM): each paired frame as received,
  when it is corrected (``relay``);
- ``CorrectedImage`` (IMAGE, uint8) and ``CorrectedProbe`` (TRANSFORM): the frame corrected
  to zero force at its zero-force pose, as soon as it is corrected;
- ``CorrectedVolume``: IMAGE, the volume so far (float32, or uint8 with ``voxel_type``), metadata
  ``FramesInserted``, stamped with the timestamp of the last frame in it;
- ``usdeformStatus``: STRING, counts of images read, corrected and skipped, with each volume.

A connection that drops, a message that cannot be read and a viewer that goes away are logged (logger
``usdeform.live``) and the service goes on.
"""

from __future__ import annotations

import itertools
import logging
import math
import queue
import sys
import threading
import time
import warnings
from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..correction import SampledProfiles, StiffnessSourceChoice
from ..errors import InputError, UsdeformError
from ..io import load_model, write_volume
from ..options import Compounding, Interpolation
from ..regression import DeformationModel, DisplacementModel, VesselAnchoredModel
from ..validation import ForceClampWarning, forces_in_range
from ..volume import DEFAULT_SPACING_MM, HoleFillingElement, Volume, VoxelType, voxel_values
from .capture import Capture
from .connections import Connections, Peer, socket_address
from .engine import FrameStore, LiveVolume
from .outputs import OutputSettings, frame_messages, image_message
from .pairing import PairedFrame, Pairer, StreamSettings
from .plus_commands import PlusCommand, answer, parse_command, volume_reply
from .transport import pack_message, pyigtl_module

__all__ = ["LiveResult", "LiveServer", "OutputSettings", "serve"]

log = logging.getLogger("usdeform.live")

#: How long a thread holds the interpreter lock while another waits for it, s, during a live session
#: (Python's default is 5 ms: a frame would wait that long at each of its handovers between threads).
SWITCH_INTERVAL_S = 0.001

#: Why an image was skipped, for the reasons that are not a stream without a match.
_SKIP_REASONS = {
    "shape": "its shape is not the model's",
    "force range": "its force is outside the model's fitted range",
    "suspended": "the reconstruction is suspended (Plus Remote)",
    "earlier": "stamped before the scan's last frame (the recording is one scan on one clock)",
}


class _VolumeOutput:
    """A volume to send as ``name``: built from ``live`` on the packing thread when its turn comes, or
    ``volume`` holding ``frames`` frames as given."""

    def __init__(
        self, name: str, live: LiveVolume | None = None, volume: Volume | None = None, frames: int = 0
    ) -> None:
        self.name, self.live, self.volume, self.frames = name, live, volume, frames


@dataclass
class LiveResult:
    """What a live session did.

    ``latency_s``: per corrected frame, from its IMAGE message read whole to its corrected frame queued
    for the viewers and its voxels in the compounder (in the next volume sent), s; a
    float64 array, 8 bytes a frame (0.9 MB an hour at 30 frames/s). With the frames' timestamps, the
    only memory a session keeps per frame.
    ``frames_sent``: corrected frames handed to the viewers.
    ``skipped``: images without a usable match, by stream (``pose:NAME``, ``force``, ``displacement``,
    ``calibration``) or reason (``shape``, ``force range``, ``format``, ``order``).
    """

    images_read: int = 0
    frames_corrected: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    malformed: int = 0
    volumes_sent: int = 0
    frames_sent: int = 0
    regrown: int = 0
    latency_s: array[float] = field(default_factory=lambda: array("d"))
    volume: Volume | None = None
    recording: Path | None = None
    volume_path: Path | None = None
    seconds: float = 0.0


class LiveServer:
    """The live service; :func:`serve` runs one until it stops.

    Parameters
    ----------
    model : DisplacementModel or VesselAnchoredModel
        The fitted model (``usdeform fit``'s default, vessel-anchored, follows the lumen from frame to
        frame across the scan's batches as ``usdeform correct`` does over the recording).
    sampled : SampledProfiles
        The model file's palpated positions and stiffness profiles.
    listen : str or (host, port)
        Address to accept connections on (port 0: any free port, see :attr:`port`).
    connect : str or (host, port), optional
        A PLUS Server to read from (reconnected to when it drops).
    streams : StreamSettings
        What is read and how it is paired.
    calibration : ndarray, optional
        Image-to-probe calibration (4, 4), e.g. from a PLUS configuration; None: the TRANSFORM
        ``streams.calibration_name``.
    outputs : OutputSettings
        What is sent and how often.
    record : Path, optional
        PLUS sequence file to write the paired frames to at the end.
    volume_path : Path, optional
        Volume file to write the final volume to (the one ``usdeform correct --volume`` makes of the
        recording).
    stiffness_source : {"auto", "interpolated", "sweep"}
        As for ``usdeform correct`` (auto: sweep when the displacement is read).
    clamp_force : bool
        Clamp forces outside the model's range (``usdeform correct --clamp-force`` on the recording);
        else such frames are skipped.
    spacing_mm, interpolation, compounding, hole_filling, voxel_type, max_bytes
        The volume's options, as ``usdeform correct --volume`` takes them (hole filling: the final volume only;
        the voxel type: the volumes sent during the scan too, uint8 being a quarter of the bytes to send).
    max_seconds, idle_stop_s, max_images : optional
        Stop after this long, after this long without any message once one came, after this many images.
    work_dir : Path, optional
        Where the frames, received and corrected, are kept until the end (default: the system's
        temporary directory): about 2.1 bytes a pixel and 0.3 KiB a frame.
    output_dir : Path, optional
        Where the files Plus Remote's commands name are written (OutputFilename, OutputVolFilename);
        default: the working directory.
    """

    def __init__(
        self,
        model: DeformationModel,
        sampled: SampledProfiles,
        *,
        listen: str | tuple[str, int] = ("127.0.0.1", 18945),
        connect: str | tuple[str, int] | None = None,
        streams: StreamSettings | None = None,
        calibration: np.ndarray | None = None,
        outputs: OutputSettings | None = None,
        record: Path | None = None,
        volume_path: Path | None = None,
        stiffness_source: StiffnessSourceChoice = "auto",
        clamp_force: bool = False,
        spacing_mm: float | None = None,
        interpolation: Interpolation | None = None,
        compounding: Compounding | None = None,
        hole_filling: Sequence[HoleFillingElement] = (),
        voxel_type: VoxelType = "float32",
        max_bytes: int | None = None,
        max_seconds: float | None = None,
        idle_stop_s: float | None = None,
        max_images: int | None = None,
        work_dir: Path | None = None,
        output_dir: Path | None = None,
    ) -> None:
        if not isinstance(model, (DisplacementModel, VesselAnchoredModel)):
            raise InputError(f"model: expected a DisplacementModel or VesselAnchoredModel, got {type(model).__name__}")
        self.model, self.sampled = model, sampled
        self.listen_address = socket_address(listen, "--listen")
        self.connect_address = None if connect is None else socket_address(connect, "--connect")
        self.streams = streams or StreamSettings()
        self.outputs = outputs or OutputSettings()
        self.record, self.volume_path = record, volume_path
        self.pairer = Pairer(self.streams)
        if calibration is not None:
            self.pairer.with_calibration(calibration)
        self.stiffness_source = (
            ("sweep" if self.streams.displacement is not None else "interpolated")
            if stiffness_source == "auto"
            else stiffness_source
        )
        if self.stiffness_source == "sweep" and self.streams.displacement is None:
            raise InputError("stiffness_source='sweep' needs the probe displacement stream (displacement)")
        self.clamp_force = clamp_force
        self.volume_options: dict[str, Any] = {
            "spacing_mm": spacing_mm or DEFAULT_SPACING_MM,
            "interpolation": interpolation or "nearest",
            "compounding": compounding or "mean",
        }
        if max_bytes is not None:
            self.volume_options["max_bytes"] = max_bytes
        self.hole_filling, self.voxel_type = tuple(hole_filling), voxel_type
        self.max_seconds, self.idle_stop_s, self.max_images = max_seconds, idle_stop_s, max_images
        if output_dir is not None and not output_dir.is_dir():
            raise InputError(f"output_dir {output_dir}: not a directory")
        self.work_dir, self.output_dir = work_dir, output_dir or Path.cwd()
        self.result = LiveResult()
        self._stop = threading.Event()
        self._connections = Connections(self.listen_address, self.connect_address, self._stop, pack=self._pack)
        self._store: FrameStore | None = None
        self._volume: LiveVolume | None = None
        self._timestamps: array[float] = array("d")  # each stored frame's timestamp, s (8 bytes a frame)
        self._volume_queued = threading.Event()  # a volume waits to be built: no other is queued
        self._volume_frames = 0  # frames in the compounder when the last volume was queued
        self._last_frame_sent = -math.inf
        self._last_processed = -math.inf  # time.perf_counter() when the last batch was compounded
        self.volume_name = self.outputs.volume_name  # Plus Remote's OutputVolDeviceName may change it
        self.suspended = False  # Plus Remote's SuspendVolumeReconstruction: frames skipped until resumed
        self._stop_command: tuple[Peer, PlusCommand] | None = None  # a StopVolumeReconstruction to answer
        self.volume_file: Path | None = None  # Plus Remote's OutputVolFilename
        self.capture: Capture | None = None  # a recording Plus Remote started
        self._jobs: list[threading.Thread] = []  # commands' files being written
        self.port = 0

    def start(self) -> LiveServer:
        """Bind the listening address and start the connection threads; :attr:`port` is then set."""
        self._connections.start()
        self.port = self._connections.port
        return self

    def stop(self, command: tuple[Peer, PlusCommand] | None = None) -> None:
        """Ask :meth:`run` to finish (from any thread); ``command``: a StopVolumeReconstruction and the
        connection that sent it, answered after the final volume."""
        if command is not None:
            self._stop_command = command
        self._stop.set()

    @property
    def frames_stored(self) -> int:
        """Frames taken in so far (those a recording holds)."""
        return 0 if self._store is None else len(self._store)

    def write_capture(self, capture: Capture) -> int:
        """Write the frames of ``capture`` to its file; returns how many."""
        if self._store is None:
            raise InputError(f"{capture.path}: no frame was recorded")
        return self._store.write(capture.path, {}, capture.spans(len(self._store)))

    def in_background(self, peer: Peer, job: Callable[[], list[Any]]) -> None:
        """Run ``job`` (a command writing a file) in a thread, then send what it returns to ``peer``; the
        service waits for it before it ends."""
        thread = threading.Thread(
            target=lambda: self._connections.queue_outputs(job(), to=peer), name="usdeform-live-command", daemon=True
        )
        self._jobs.append(thread)
        thread.start()

    # -- outputs -----------------------------------------------------------------------------------

    def _pack(self, output: Any) -> list[bytes | memoryview]:
        """The buffers to send of a queued output, a :class:`_VolumeOutput` (built now if it is to be
        built from the live volume) or a pyigtl message; on the sending thread."""
        if not isinstance(output, _VolumeOutput):
            return pack_message(output)
        if output.live is not None and output.volume is None:
            self._volume_queued.clear()  # the next one may be queued while this one is built and sent
            built = output.live.sent_volume()
            if built is None:
                return []
            output.volume, output.frames = built
        assert output.volume is not None
        return pack_message(self._volume_message(output.volume, output.frames, output.name))

    def _volume_message(self, volume: Volume, frames: int, name: str) -> Any:
        """The volume holding the first ``frames`` frames, stamped with the last one's timestamp."""
        return image_message(
            voxel_values(volume.image, self.voxel_type),
            self.outputs.world(volume.index_to_world),
            name,
            self._timestamps[frames - 1] if frames else 0.0,
            FramesInserted=str(frames),
        )

    def _status_message(self) -> Any:
        result = self.result
        skipped = sum(self._skipped().values())
        text = (
            f"images {self.pairer.images_read} corrected {result.frames_corrected} skipped {skipped} "
            f"malformed {self._connections.malformed}"
        )
        return pyigtl_module().StringMessage(text, device_name=self.outputs.status_name)

    # -- processing --------------------------------------------------------------------------------

    def _skipped(self) -> dict[str, int]:
        """Images skipped so far, by stream or reason (those the pairer refused on arrival included)."""
        refused = {key: count for key, count in self.pairer.skipped.items() if key in ("format", "order", "backlog")}
        return {**self.result.skipped, **refused}

    def _skip(self, index: int, timestamp: float, reason: str) -> None:
        counts = self.result.skipped
        counts[reason] = counts.get(reason, 0) + 1
        if counts[reason] == 1 or counts[reason] % 100 == 0:
            why = _SKIP_REASONS.get(reason) or f"no {self.streams.streams.get(reason, reason)} matching it"
            log.warning(
                "skipped image %d (t = %.6f s): %s (%d skipped for this so far)", index, timestamp, why, counts[reason]
            )

    def _usable(self, frame: PairedFrame) -> bool:
        shape = self.model.frame_shape
        if frame.pixels.shape != shape:
            self._skip(frame.index, frame.timestamp, "shape")
            if self.result.skipped["shape"] == 1:
                log.warning("image shape %s, but the model was fitted on %s frames", frame.pixels.shape, shape)
            return False
        if not self.clamp_force:
            try:
                forces_in_range(np.array([frame.force]), self.model.normalization.force_scale)
            except InputError:
                self._skip(frame.index, frame.timestamp, "force range")
                return False
        return True

    def _process(self, frames: list[PairedFrame]) -> None:
        if not frames:
            return
        if self._store is None:
            assert self.pairer.calibration is not None
            self._store = FrameStore(
                frames[0].pixels.shape,
                self.pairer.calibration,
                with_displacement=self.streams.displacement is not None,
                directory=self.work_dir,
            )
            self._volume = LiveVolume(
                self._store,
                self.model,
                self.sampled,
                stiffness_source=self.stiffness_source,
                clamp_force=self.clamp_force,
                **self.volume_options,
            )
        assert self._volume is not None
        batch = self._store.append(frames)
        self._timestamps.extend(frame.timestamp for frame in frames)
        with warnings.catch_warnings():  # clamp_force: the recording keeps the forces as sent
            warnings.simplefilter("ignore", ForceClampWarning)
            corrected = self._volume.correct_next(batch)
        self.result.frames_corrected += len(frames)
        now = time.perf_counter()
        rate = self.outputs.frame_rate_hz
        if rate is None or now - self._last_frame_sent >= 1.0 / rate:  # before the compounding, ahead of volumes
            self._connections.send_outputs(
                frame_messages(self.outputs, frames, corrected, self._store.image_to_probe), ahead=True
            )
            period = 0.0 if rate is None else 1.0 / rate
            self._last_frame_sent = max(self._last_frame_sent + period, now - period / 2)
            self.result.frames_sent += len(frames) if rate is None else 1
        self._volume.compound(corrected)
        now = time.perf_counter()
        self.result.latency_s.extend(now - frame.received for frame in frames)
        self._last_processed = now

    def _outputs_due(self, now: float, last: dict[str, float], processed: bool) -> None:
        """Hand the packing thread the volume (built there) and the status when due: at most at the volume
        rate, only when frames were added since the last, never while another waits to be built; right
        after a batch of frames (``processed``), so that it is built and sent before the next frame comes,
        or once frames stopped for a volume period; never waits."""
        volume_state = self._volume
        if volume_state is None or volume_state.compounder is None or self._volume_queued.is_set():
            return
        period = 1.0 / self.outputs.volume_rate_hz
        frames = volume_state.frames_inserted
        if now - last["volume"] < period or frames <= self._volume_frames:
            return
        if not processed and now - self._last_processed < period:
            return
        self._volume_queued.set()
        if not self._connections.offer_outputs([_VolumeOutput(self.volume_name, volume_state), self._status_message()]):
            self._volume_queued.clear()  # the packing thread is behind: next time
            return
        self._volume_frames = frames
        last["volume"] = max(last["volume"] + period, now - period / 2)  # on average at the rate asked
        self.result.volumes_sent += 1

    def _command(self, peer: Peer, command: PlusCommand) -> None:
        """Carry out a PLUS volume-reconstruction command and answer it as PLUS Server does."""
        reply = answer(self, peer, command)
        if reply is not None:
            log.info("%s: %s", peer.name, reply.content if command.v3 else reply.string)
            self._connections.queue_outputs([reply], to=peer)  # after a volume it answers

    def snapshot(self) -> tuple[Volume, int] | None:
        """The volume so far and the frames it holds (:meth:`LiveVolume.sent_volume`)."""
        return None if self._volume is None else self._volume.sent_volume()

    def send_volume(self, peer: Peer, snapshot: tuple[Volume, int] | None = None) -> None:
        """The volume so far (or ``snapshot``), as :attr:`volume_name`, to ``peer`` alone."""
        volume, frames = snapshot or (None, 0)
        output = _VolumeOutput(self.volume_name, self._volume if volume is None else None, volume, frames)
        self._connections.queue_outputs([output], to=peer)

    def _should_stop(self, started: float, now: float) -> bool:
        if self._stop.is_set():
            return True
        if self.max_seconds is not None and now - started >= self.max_seconds:
            log.info("stopping: %.1f s elapsed (max_seconds)", now - started)
            return True
        if self.max_images is not None and self.pairer.images_read >= self.max_images and not self.pairer.pending:
            log.info("stopping: %d images read (max_images)", self.pairer.images_read)
            return True
        last_input = self._connections.last_input
        idle = now - last_input >= self.idle_stop_s if self.idle_stop_s is not None else False
        if idle and self._connections.inbox.empty() and not self.pairer.pending:
            log.info("stopping: no message for %.1f s", now - last_input)
            return True
        return False

    def run(self) -> LiveResult:
        """Serve until a stop condition (or :meth:`stop`), then finish: the final volume is sent and
        written, the recording written. Starts the server first if :meth:`start` was not called."""
        if not self._connections.started:
            self.start()
        started = time.perf_counter()
        last = {"volume": -math.inf, "log": started}
        switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        try:
            try:
                while not self._should_stop(started, time.perf_counter()):
                    self._step(last)
            except KeyboardInterrupt:  # Ctrl-C ends the scan; a second one abandons the files
                log.info("interrupted: sending the final volume and writing the files")
            self._finish(last)
        finally:
            sys.setswitchinterval(switch_interval)
            self._close()
        self.result.malformed = self._connections.malformed
        self.result.seconds = time.perf_counter() - started
        return self.result

    def _read_inbox(self, wait_s: float | None) -> list[str]:
        """Take the messages read so far (waiting up to ``wait_s`` for one; None: no wait) to the pairer and
        the commands; returns the connections that closed."""
        items = []
        if wait_s is not None:
            try:
                items.append(self._connections.inbox.get(timeout=wait_s))
            except queue.Empty:
                pass
        while True:
            try:
                items.append(self._connections.inbox.get_nowait())
            except queue.Empty:
                break
        closed = []
        for peer, message, received in items:
            if message is None:
                closed.append(peer.name)
                continue
            command = parse_command(message)
            if command is not None:
                self._command(peer, command)
                continue
            note = self.pairer.add(message, received, peer.name)
            if note:
                log.warning("%s: %s", peer.name, note)
        return closed

    def _step(self, last: dict[str, float]) -> None:
        closed = self._read_inbox(0.01)
        now = time.perf_counter()
        if self._volume is not None:
            self._volume.poll()  # a grown grid, once filled, takes over
        corrected = self.result.frames_corrected
        self._pair_and_process(now, closed=closed)
        self._outputs_due(time.perf_counter(), last, processed=self.result.frames_corrected > corrected)
        if now - last["log"] >= 10.0:
            last["log"] = now
            log.info(self._status_message().string)

    def _pair_and_process(self, now: float, flush: bool = False, closed: Sequence[str] = ()) -> None:
        frames: list[PairedFrame] = []
        decided = itertools.chain(
            self.pairer.ready(now, flush=flush), *(self.pairer.close_source(name, now) for name in closed)
        )
        for item in decided:
            if isinstance(item, PairedFrame) and self.suspended:
                self._skip(item.index, item.timestamp, "suspended")
            elif isinstance(item, PairedFrame):
                if self._usable(item):
                    frames.append(item)
            else:
                self._skip(*item)
        self.result.images_read = self.pairer.images_read
        frames.sort(key=lambda frame: frame.timestamp)  # several connections' frames, in the scan's time
        while frames and self._timestamps and frames[0].timestamp < self._timestamps[-1]:
            late = frames.pop(0)  # the recording is one scan on one clock
            self._skip(late.index, late.timestamp, "earlier")
        try:
            self._process(frames)
        except UsdeformError as error:  # a batch the correction refuses: counted, the service goes on
            log.warning("skipped %d frames the correction refused: %s", len(frames), error)
            self.result.skipped["refused"] = self.result.skipped.get("refused", 0) + len(frames)

    def _finish(self, last: dict[str, float]) -> None:
        closed = self._read_inbox(None)  # the messages read before the stop
        self._pair_and_process(time.perf_counter(), flush=True, closed=closed)
        result = self.result
        result.skipped = self._skipped()
        if self._volume is None or self._store is None:
            log.warning("no frame was corrected: nothing to write")
            return
        volume = self._volume.final_volume(hole_filling=self.hole_filling, voxel_type=self.voxel_type)
        result.volume, result.regrown = volume, self._volume.regrown
        if volume is not None:
            final = _VolumeOutput(self.volume_name, volume=volume, frames=len(self._store))
            self._connections.queue_outputs([final, self._status_message()])
            result.volumes_sent += 1
        if self._stop_command is not None and volume is not None:
            peer, command = self._stop_command
            reply = volume_reply(command, volume, self.volume_file, self.volume_name)
            self._connections.queue_outputs([reply], to=peer)
        if self.capture is not None:  # a recording Plus Remote started and did not stop
            try:
                log.info("wrote %s (%d frames recorded)", self.capture.path, self.write_capture(self.capture))
            except (OSError, UsdeformError) as error:
                log.warning("the recording Plus Remote started is not written: %s", error)
        for job in self._jobs:
            job.join()
        self._connections.end_outputs(timeout_s=30.0)
        metadata = {
            "UsdeformLiveImagesRead": str(self.pairer.images_read),
            "UsdeformLiveImagesSkipped": ", ".join(
                f"{k.replace(':', ' ')} {v}" for k, v in sorted(result.skipped.items())
            )
            or "none",
            "UsdeformLiveImageDelaySeconds": repr(self.streams.image_delay_s),
        }
        if self.record is not None:
            self._store.write(self.record, metadata)
            result.recording = self.record
            log.info("wrote %s (%d frames)", self.record, len(self._store))
        if self.volume_path is not None and volume is not None:
            write_volume(self.volume_path, volume)
            result.volume_path = self.volume_path
            log.info("wrote %s", self.volume_path)

    def _close(self) -> None:
        self._connections.close()
        if self._store is not None:
            self._store.close()


def serve(
    model: str | Path | DeformationModel,
    sampled: SampledProfiles | None = None,
    **options: Any,
) -> LiveResult:
    """Run a :class:`LiveServer` until it stops and return what it did.

    ``model``: a model file (``usdeform fit``), or the model with its ``sampled``
    profiles; ``options``: those of :class:`LiveServer`, e.g.
    ``serve("model.json", listen="127.0.0.1:18945", record=Path("scan.seq.nrrd"), idle_stop_s=5)``.
    """
    fitted: DeformationModel
    if isinstance(model, (str, Path)):
        model_file = load_model(model)
        fitted, sampled = model_file.model, model_file.sampled
    else:
        fitted = model
    if sampled is None:
        raise InputError("sampled: the palpated positions and their stiffness profiles are needed")
    return LiveServer(fitted, sampled, **options).start().run()
