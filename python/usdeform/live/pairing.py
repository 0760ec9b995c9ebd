"""Pairing the streams of a live scan by timestamp: each image with its probe pose, force and
probe displacement.

Sources, as PLUS Server and robot nodes send them (:class:`StreamSettings`):

- the image: IMAGE messages of one device name (PLUS: ``Image_Reference``, the image stream's name
  and the frame its embedded transform points to);
- the probe pose: TRANSFORM ``ProbeToReference`` (Reference = the robot base), or ``ProbeToTracker``
  with ``ReferenceToTracker`` (the pose is then ``inv(ReferenceToTracker) @ ProbeToTracker``);
  OpenIGTLink v3 senders mark a lost pose by the header metadata ``TransformStatus`` (not ``OK``),
  and PLUS by default does not send it at all;
- the calibration: TRANSFORM ``ImageToProbe`` (PLUS sends it when listed among the server's
  transform names), unless a PLUS configuration gives it;
- the contact force and the probe displacement: scalars, each from one :class:`ScalarSource`: a
  STRING message of that device name holding the number (how PLUS Server sends a tracked frame's
  custom fields listed as ``<String Name="ContactForce"/>``), an IMAGE message's metadata key (PLUS
  with OpenIGTLink v3 attaches every custom frame field to the IMAGE message), or one translation
  component of a TRANSFORM (a robot node sending a wrench or a displacement as a transform).

Each sample keeps its sender's timestamp. An image stamped ``t`` shows the tissue at
``t - image_delay_s`` (the delay a diagnosis measured); every other stream is matched there: the
sample nearest that time within ``tolerance_s``. A stream is decided once a sample at or after
``t + tolerance_s`` has arrived (no later sample could be nearer), on an exact match, or after
``wait_s`` of waiting; an image left without a match in some stream is skipped and counted by that
stream's name, never given an interpolated or a stale value.
"""

from __future__ import annotations

import bisect
import collections
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import FileFormatError, InputError

__all__ = ["MAX_IMAGE_DELAY_S", "PairedFrame", "Pairer", "ScalarSource", "StreamSettings", "image_delay_from_diagnosis"]

ScalarKind = Literal["STRING", "META", "TRANSFORM"]
#: Longest image delay taken, s (a delay of seconds is a broken clock, not a latency to undo).
MAX_IMAGE_DELAY_S = 10.0
_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class ScalarSource:
    """Where a scalar stream comes from: ``STRING:NAME`` (a STRING message named NAME holding the
    number), ``META:KEY`` (the metadata value KEY of each IMAGE message) or ``TRANSFORM:NAME:AXIS``
    (translation component x, y or z of a TRANSFORM named NAME).

    Examples
    --------
    >>> ScalarSource.parse("TRANSFORM:ForceToProbe:z")
    ScalarSource(kind='TRANSFORM', name='ForceToProbe', axis='z')
    >>> str(ScalarSource.parse("STRING:ContactForce"))
    'STRING:ContactForce'
    """

    kind: ScalarKind
    name: str
    axis: str | None = None

    @classmethod
    def parse(cls, text: str) -> ScalarSource:
        parts = text.split(":")
        kind = parts[0].upper()
        if kind in ("STRING", "META") and len(parts) == 2 and parts[1]:
            return cls("STRING" if kind == "STRING" else "META", parts[1])
        if kind == "TRANSFORM" and len(parts) == 3 and parts[1] and parts[2].lower() in _AXES:
            return cls("TRANSFORM", parts[1], parts[2].lower())
        raise InputError(
            f"scalar source {text!r}: expected STRING:NAME, META:KEY or TRANSFORM:NAME:x|y|z "
            "(e.g. STRING:ContactForce, as PLUS Server sends a frame's custom fields)"
        )

    def __str__(self) -> str:
        return ":".join(part for part in (self.kind, self.name, self.axis) if part)


@dataclass(frozen=True)
class StreamSettings:
    """What the live service reads, and how it pairs it (see the module's notes).

    Parameters
    ----------
    image_name : str
        Device name of the IMAGE messages to correct.
    pose : tuple of str
        ``("ProbeToReference",)``, or ``(probe_to_tracker, reference_to_tracker)`` names.
    calibration_name : str
        TRANSFORM carrying the image-to-probe calibration (unused when a calibration is given).
    force, displacement : ScalarSource, optional
        The contact force (N) and the probe displacement (mm); displacement None: not read (the
        stiffness then comes from the sampled positions alone).
    image_delay_s : float
        The images' delay behind pose and force, s (a frame stamped t shows the tissue at t - delay).
    tolerance_s : float
        Largest time between an image and a sample matched to it, s.
    wait_s : float
        Longest wait for a stream to decide an image's match, s.
    """

    image_name: str = "Image_Reference"
    pose: tuple[str, ...] = ("ProbeToReference",)
    calibration_name: str = "ImageToProbe"
    force: ScalarSource = ScalarSource("STRING", "ContactForce")
    displacement: ScalarSource | None = ScalarSource("STRING", "ProbeDisplacement")
    image_delay_s: float = 0.0
    tolerance_s: float = 0.002
    wait_s: float = 0.25

    def __post_init__(self) -> None:
        if len(self.pose) not in (1, 2) or not all(self.pose):
            raise InputError(f"pose: expected ProbeToReference or ProbeToTracker,ReferenceToTracker, got {self.pose}")
        for name, longest in (("image_delay_s", MAX_IMAGE_DELAY_S), ("tolerance_s", 60.0), ("wait_s", 60.0)):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= longest):
                raise InputError(f"{name}: expected a number of seconds from 0 to {longest:g}, got {value}")

    @property
    def streams(self) -> dict[str, str]:
        """Stream key -> what it is, for counts and logs: each pose transform, force, displacement."""
        names = {f"pose:{name}": f"TRANSFORM {name}" for name in self.pose}
        names["force"] = str(self.force)
        if self.displacement is not None:
            names["displacement"] = str(self.displacement)
        return names


@dataclass(frozen=True)
class PairedFrame:
    """One image with the samples matched to it: pose (4, 4) in the reference (base) frame, mm."""

    index: int  #: arrival order of the image among the images read
    timestamp: float  #: the image's own timestamp, s
    pixels: np.ndarray  #: (rows, cols) uint8
    probe_to_base: np.ndarray
    force: float
    displacement: float | None
    received: float  #: time.perf_counter() when the image message was read whole


@dataclass
class _Image:
    index: int
    timestamp: float
    pixels: np.ndarray
    received: float
    metadata: dict[str, str]


class _Series:
    """Timestamped samples of one stream from one connection, oldest first (a sender stamps in order; a
    late one is inserted); ``last_received``: ``time.perf_counter()`` of the latest sample, s."""

    def __init__(self, max_samples: int = 4096) -> None:
        self.samples: collections.deque[tuple[float, Any]] = collections.deque(maxlen=max_samples)
        self.last_received = -math.inf

    def add(self, timestamp: float, value: Any, received: float) -> None:
        self.last_received = max(self.last_received, received)
        if self.samples and timestamp < self.samples[-1][0]:
            if len(self.samples) == self.samples.maxlen:
                self.samples.popleft()
            bisect.insort(self.samples, (timestamp, value), key=lambda sample: sample[0])
        else:
            self.samples.append((timestamp, value))

    def decided(self, at: float, tolerance: float) -> bool:
        return bool(self.samples) and (self.samples[-1][0] >= at + tolerance or self.match(at, 0.0) is not None)

    def match(self, at: float, tolerance: float) -> tuple[float, Any] | None:
        """The (gap, value) of the sample nearest ``at`` within ``tolerance``, s; None without one."""
        best: tuple[float, Any] | None = None
        for timestamp, value in reversed(self.samples):
            gap = abs(timestamp - at)
            if gap <= tolerance and (best is None or gap < best[0]):
                best = (gap, value)
            if timestamp < at - tolerance:
                break
        return best

    def forget_before(self, at: float) -> None:
        while len(self.samples) > 1 and self.samples[1][0] < at:
            self.samples.popleft()


def _number(text: str) -> float | None:
    try:
        value = float(text.strip().split()[0])
    except (ValueError, IndexError):
        return None
    return value if math.isfinite(value) else None


def _counted(counts: collections.Counter[str], key: str) -> bool:
    """Count one more ``key``; whether it is the first or a hundredth (the ones worth a log line)."""
    counts[key] += 1
    return counts[key] == 1 or counts[key] % 100 == 0


class Pairer:
    """Collects the messages of a live scan and hands out paired frames, each connection's in arrival order.

    Feed it with :meth:`add` (a pyigtl message, when it was read and the connection it came on);
    :meth:`ready` yields the images decided so far, paired (:class:`PairedFrame`) or skipped (counted
    in :attr:`skipped` by the stream that had no match, with a log line from the caller).

    Each connection is a source of its own: its images keep their order among themselves only (a
    stray sender, or a second replay of a recording, does not make the others' images late), wait in
    a queue of their own, and are paired with the samples of their own connection for every stream it
    sends. A stream the image's connection does not send (a robot node's force beside PLUS's images) is
    taken from the other connections sending it; those silent for ``wait_s`` are not waited for.
    """

    def __init__(self, settings: StreamSettings, *, max_pending: int = 10_000) -> None:
        self.settings = settings
        self.series: dict[str, dict[str, _Series]] = {key: {} for key in settings.streams}
        self.queues: dict[str, collections.deque[_Image]] = {}
        self.max_pending = max_pending
        self.calibration: np.ndarray | None = None
        self.skipped: collections.Counter[str] = collections.Counter()
        self.images_read = 0
        self.ignored: collections.Counter[str] = collections.Counter()
        self._last_timestamp: dict[str, float] = {}

    @property
    def pending(self) -> int:
        """Images waiting for a match, over all connections."""
        return sum(len(queue) for queue in self.queues.values())

    def _sample(self, key: str, source: str, timestamp: float, value: Any, received: float) -> None:
        self.series[key].setdefault(source, _Series()).add(timestamp, value, received)

    def add(self, message: Any, received: float, source: str = "") -> str | None:
        """Take one message read on connection ``source``; returns a note for the log when it was ignored
        for a reason the user should hear about (the first and every hundredth of each kind), else None."""
        kind, name, timestamp = message.message_type, message.device_name, float(message.timestamp)
        settings = self.settings
        if kind == "IMAGE" and name == settings.image_name:
            return self._add_image(message, received, source)
        if kind == "TRANSFORM":
            matrix = np.asarray(message.matrix, dtype=np.float64)
            valid = str(getattr(message, "metadata", {}).get("TransformStatus", "OK")).upper() == "OK"
            if name == settings.calibration_name and self.calibration is None and valid:
                self.calibration = matrix
            if f"pose:{name}" in self.series and valid and np.all(np.isfinite(matrix)):
                self._sample(f"pose:{name}", source, timestamp, matrix, received)
        for key, scalar in (("force", settings.force), ("displacement", settings.displacement)):
            if scalar is None or scalar.kind == "META":
                continue
            if kind == scalar.kind and name == scalar.name:
                value = (
                    _number(message.string)
                    if kind == "STRING"
                    else float(np.asarray(message.matrix, dtype=np.float64)[_AXES[scalar.axis or "z"], 3])
                )
                if value is None or not math.isfinite(value):
                    text = str(getattr(message, "string", ""))[:40]
                    return self._ignore(f"{kind} {name!r} without a number", f" (e.g. {text!r})")
                self._sample(key, source, timestamp, value, received)
        if kind == "IMAGE" and name != settings.image_name:
            return self._ignore(f"IMAGE {name!r}", f" (the images read are {settings.image_name!r}: --image-name)")
        return None

    def _ignore(self, what: str, detail: str = "") -> str | None:
        """Count a message ignored as ``what`` (one count per kind of message, whatever it held); the
        note, with ``detail``, for the first of each."""
        self.ignored[what] += 1
        return f"ignoring {what}{detail}" if self.ignored[what] == 1 else None

    def _add_image(self, message: Any, received: float, source: str) -> str | None:
        self.images_read += 1
        index = self.images_read - 1
        pixels = np.asarray(message.image)
        if pixels.ndim == 3 and pixels.shape[0] == 1:
            pixels = pixels[0]
        timestamp = float(message.timestamp)
        last = self._last_timestamp.get(source, -math.inf)
        queue = self.queues.setdefault(source, collections.deque())
        reason = None
        if pixels.ndim != 2 or pixels.dtype != np.uint8:
            reason = "format"
        elif timestamp <= last:
            reason = "order"
        elif len(queue) >= self.max_pending:
            reason = "backlog"
        if reason is not None:
            if not _counted(self.skipped, reason):
                return None
            return (
                f"skipped image {index} (t = {timestamp:.6f} s): "
                + {
                    "format": f"not a single-component uint8 frame ({pixels.dtype}, shape {pixels.shape})",
                    "order": f"stamped at or before this connection's previous image ({last:.6f} s)",
                    "backlog": f"{self.max_pending} images of this connection already wait for their pose or force",
                }[reason]
                + f" ({self.skipped[reason]} skipped for this so far)"
            )
        self._last_timestamp[source] = timestamp
        metadata = {str(k): str(v) for k, v in getattr(message, "metadata", {}).items()}
        queue.append(_Image(index, timestamp, np.ascontiguousarray(pixels), received, metadata))
        return None

    def _decide(self, key: str, source: str, at: float, now: float) -> tuple[bool, Any]:
        """Whether stream ``key`` is decided for an image of ``source`` showing time ``at``, and its match."""
        tolerance, by_source = self.settings.tolerance_s, self.series[key]
        own = by_source.get(source)
        candidates = [own] if own is not None else list(by_source.values())
        if not candidates:
            return False, None
        matches = [match for series in candidates if (match := series.match(at, tolerance)) is not None]
        best = min(matches, key=lambda match: match[0]) if matches else None
        if own is not None:
            return own.decided(at, tolerance), None if best is None else best[1]
        live = [series for series in candidates if now - series.last_received < self.settings.wait_s]
        decided = (best is not None and best[0] == 0.0) or all(series.decided(at, tolerance) for series in live)
        return decided, None if best is None else best[1]

    def _scalar(self, key: str, scalar: ScalarSource | None, image: _Image, source: str, at: float, now: float) -> Any:
        if scalar is not None and scalar.kind == "META":
            return True, _number(image.metadata.get(scalar.name, ""))
        return self._decide(key, source, at, now)

    def ready(self, now: float, *, flush: bool = False) -> Iterator[PairedFrame | tuple[int, float, str]]:
        """Decided images, each connection's oldest first: a :class:`PairedFrame`, or ``(index,
        timestamp, stream)`` for an image skipped for lack of a match in ``stream`` ("calibration"
        without one). ``flush``: decide every pending image with the samples at hand (the scan ended)."""
        for source in list(self.queues):
            yield from self._ready(source, now, flush)

    def _ready(self, source: str, now: float, flush: bool) -> Iterator[PairedFrame | tuple[int, float, str]]:
        settings, queue = self.settings, self.queues[source]
        while queue:
            image = queue[0]
            at = image.timestamp - settings.image_delay_s
            waited_out = flush or now - image.received >= settings.wait_s
            decisions: dict[str, tuple[bool, Any]] = {}
            for key in self.series:
                if key.startswith("pose:"):
                    decisions[key] = self._decide(key, source, at, now)
            decisions["force"] = self._scalar("force", settings.force, image, source, at, now)
            if settings.displacement is not None:
                decisions["displacement"] = self._scalar("displacement", settings.displacement, image, source, at, now)
            if not waited_out and not all(decided for decided, _ in decisions.values()):
                return
            queue.popleft()
            missing = next((key for key, (_, value) in decisions.items() if value is None), None)
            if missing is None and self.calibration is None:
                missing = "calibration"
            if missing is not None:
                self.skipped[missing] += 1
                yield image.index, image.timestamp, missing
                continue
            poses = [decisions[f"pose:{name}"][1] for name in settings.pose]
            probe_to_base = poses[0] if len(poses) == 1 else np.linalg.solve(poses[1], poses[0])
            displacement = decisions["displacement"][1] if settings.displacement is not None else None
            yield PairedFrame(
                image.index,
                image.timestamp,
                image.pixels,
                probe_to_base,
                float(decisions["force"][1]),
                None if displacement is None else float(displacement),
                image.received,
            )
            own = [by_source[source] for by_source in self.series.values() if source in by_source]
            for series in own:
                series.forget_before(at - 2.0 * settings.tolerance_s - 1.0)

    def close_source(self, source: str, now: float) -> Iterator[PairedFrame | tuple[int, float, str]]:
        """Connection ``source`` closed: its pending images decided with the samples at hand, then its
        samples and order forgotten (a later connection of that name starts afresh)."""
        if source in self.queues:
            yield from self._ready(source, now, True)
            del self.queues[source]
        for by_source in self.series.values():
            by_source.pop(source, None)
        self._last_timestamp.pop(source, None)

    def with_calibration(self, image_to_probe: np.ndarray) -> Pairer:
        """Use this calibration (e.g. from a PLUS configuration) instead of waiting for the TRANSFORM."""
        self.calibration = np.asarray(image_to_probe, dtype=np.float64)
        return self


def image_delay_from_diagnosis(path: str | Path) -> tuple[float, str]:
    """The image delay a diagnosis measured (``usdeform diagnose``'s ``diagnosis.json``, or its folder),
    s, and a note saying where it came from: the ``delay_s`` of ``image_latency`` when the verdict names
    that effect, else 0.

    Examples
    --------
    >>> import json, tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> _ = (folder / "diagnosis.json").write_text(json.dumps({"verdict": "explained", "named": ["image_latency"],
    ...     "effects": [{"effect": "image_latency", "parameters": {"delay_s": 0.052}}]}))
    >>> image_delay_from_diagnosis(folder)
    (0.052, 'image delay 0.052 s: image_latency named by the diagnosis (explained)')
    """
    from ..gap.diagnosis_file import diagnosis_path, read_diagnosis  # the one reader of diagnosis.json

    file = diagnosis_path(path)
    document = read_diagnosis(file)
    verdict, named = str(document["verdict"]), list(document.get("named", []))
    effects = {entry["effect"]: entry for entry in document["effects"]}
    if "image_latency" not in named:
        return 0.0, f"image delay 0 s: the diagnosis ({verdict}) does not name image_latency"
    try:
        delay = float(effects["image_latency"]["parameters"]["delay_s"])
    except (KeyError, TypeError, ValueError):
        raise FileFormatError(f"{file}: effects: image_latency has no parameters.delay_s") from None
    if not (math.isfinite(delay) and 0 <= delay <= MAX_IMAGE_DELAY_S):
        raise InputError(
            f"{file}: image_latency delay_s {delay}: the live pairing takes a delay from 0 to {MAX_IMAGE_DELAY_S:g} s"
        )
    return delay, f"image delay {delay:g} s: image_latency named by the diagnosis ({verdict})"
