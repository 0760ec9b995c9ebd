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

import collections
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import FileFormatError, InputError

__all__ = ["PairedFrame", "Pairer", "ScalarSource", "StreamSettings", "image_delay_from_diagnosis"]

ScalarKind = Literal["STRING", "META", "TRANSFORM"]
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
        for name in ("image_delay_s", "tolerance_s", "wait_s"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0 or (name == "wait_s" and value > 60):
                raise InputError(f"{name}: expected a finite non-negative number of seconds, got {value}")

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
    """Timestamped samples of one stream, oldest first (senders stamp in order; a late one is inserted)."""

    def __init__(self, max_samples: int = 4096) -> None:
        self.samples: collections.deque[tuple[float, Any]] = collections.deque(maxlen=max_samples)

    def add(self, timestamp: float, value: Any) -> None:
        if self.samples and timestamp < self.samples[-1][0]:
            ordered = sorted([*self.samples, (timestamp, value)], key=lambda sample: sample[0])
            self.samples.clear()
            self.samples.extend(ordered)
        else:
            self.samples.append((timestamp, value))

    def decided(self, at: float, tolerance: float) -> bool:
        return bool(self.samples) and (self.samples[-1][0] >= at + tolerance or self.match(at, 0.0) is not None)

    def match(self, at: float, tolerance: float) -> Any | None:
        best: tuple[float, Any] | None = None
        for timestamp, value in reversed(self.samples):
            gap = abs(timestamp - at)
            if gap <= tolerance and (best is None or gap < best[0]):
                best = (gap, value)
            if timestamp < at - tolerance:
                break
        return None if best is None else best[1]

    def forget_before(self, at: float) -> None:
        while len(self.samples) > 1 and self.samples[1][0] < at:
            self.samples.popleft()


def _number(text: str) -> float | None:
    try:
        value = float(text.strip().split()[0])
    except (ValueError, IndexError):
        return None
    return value if math.isfinite(value) else None


class Pairer:
    """Collects the messages of a live scan and hands out paired frames in arrival order.

    Feed it with :meth:`add` (a pyigtl message and when it was read); :meth:`ready` yields the images
    decided so far, paired (:class:`PairedFrame`) or skipped (counted in :attr:`skipped` by the
    stream that had no match, with a log line from the caller).
    """

    def __init__(self, settings: StreamSettings, *, max_pending: int = 10_000) -> None:
        self.settings = settings
        self.series = {key: _Series() for key in settings.streams}
        self.pending: collections.deque[_Image] = collections.deque()
        self.max_pending = max_pending
        self.calibration: np.ndarray | None = None
        self.skipped: collections.Counter[str] = collections.Counter()
        self.images_read = 0
        self.ignored: collections.Counter[str] = collections.Counter()
        self._last_timestamp = -math.inf

    def add(self, message: Any, received: float) -> str | None:
        """Take one message; returns a note for the log when it was ignored for a reason the user
        should hear about (once per kind), else None."""
        kind, name, timestamp = message.message_type, message.device_name, float(message.timestamp)
        settings = self.settings
        if kind == "IMAGE" and name == settings.image_name:
            return self._add_image(message, received)
        if kind == "TRANSFORM":
            matrix = np.asarray(message.matrix, dtype=np.float64)
            valid = str(getattr(message, "metadata", {}).get("TransformStatus", "OK")).upper() == "OK"
            if name == settings.calibration_name and self.calibration is None and valid:
                self.calibration = matrix
            if f"pose:{name}" in self.series and valid and np.all(np.isfinite(matrix)):
                self.series[f"pose:{name}"].add(timestamp, matrix)
        for key, source in (("force", settings.force), ("displacement", settings.displacement)):
            if source is None or source.kind == "META":
                continue
            if kind == source.kind and name == source.name:
                value = (
                    _number(message.string)
                    if kind == "STRING"
                    else float(np.asarray(message.matrix, dtype=np.float64)[_AXES[source.axis or "z"], 3])
                )
                if value is None or not math.isfinite(value):
                    text = str(getattr(message, "string", ""))[:40]
                    return self._ignore(f"{kind} {name!r} without a number", f" (e.g. {text!r})")
                self.series[key].add(timestamp, value)
        if kind == "IMAGE" and name != settings.image_name:
            return self._ignore(f"IMAGE {name!r}", f" (the images read are {settings.image_name!r}: --image-name)")
        return None

    def _ignore(self, what: str, detail: str = "") -> str | None:
        """Count a message ignored as ``what`` (one count per kind of message, whatever it held); the
        note, with ``detail``, for the first of each."""
        self.ignored[what] += 1
        return f"ignoring {what}{detail}" if self.ignored[what] == 1 else None

    def _add_image(self, message: Any, received: float) -> str | None:
        self.images_read += 1
        index = self.images_read - 1
        pixels = np.asarray(message.image)
        if pixels.ndim == 3 and pixels.shape[0] == 1:
            pixels = pixels[0]
        timestamp = float(message.timestamp)
        reason = None
        if pixels.ndim != 2 or pixels.dtype != np.uint8:
            reason = "format"
        elif timestamp <= self._last_timestamp:
            reason = "order"
        elif len(self.pending) >= self.max_pending:
            reason = "backlog"
        if reason is not None:
            self.skipped[reason] += 1
            return (
                f"skipped image {index} (t = {timestamp:.6f} s): "
                + {
                    "format": f"not a single-component uint8 frame ({pixels.dtype}, shape {pixels.shape})",
                    "order": f"stamped at or before the previous image ({self._last_timestamp:.6f} s)",
                    "backlog": f"{self.max_pending} images already wait for their pose or force",
                }[reason]
            )
        self._last_timestamp = timestamp
        metadata = {str(k): str(v) for k, v in getattr(message, "metadata", {}).items()}
        self.pending.append(_Image(index, timestamp, np.ascontiguousarray(pixels), received, metadata))
        return None

    def _scalar(self, key: str, source: ScalarSource | None, image: _Image, at: float) -> tuple[bool, Any]:
        if source is not None and source.kind == "META":
            return True, _number(image.metadata.get(source.name, ""))
        series = self.series[key]
        return series.decided(at, self.settings.tolerance_s), series.match(at, self.settings.tolerance_s)

    def ready(self, now: float, *, flush: bool = False) -> Iterator[PairedFrame | tuple[int, float, str]]:
        """Decided images, oldest first: a :class:`PairedFrame`, or ``(index, timestamp, stream)`` for
        an image skipped for lack of a match in ``stream`` ("calibration" without one). ``flush``:
        decide every pending image with the samples at hand (the scan ended)."""
        settings = self.settings
        while self.pending:
            image = self.pending[0]
            at = image.timestamp - settings.image_delay_s
            waited_out = flush or now - image.received >= settings.wait_s
            decisions: dict[str, tuple[bool, Any]] = {}
            for key in self.series:
                if key.startswith("pose:"):
                    series = self.series[key]
                    decisions[key] = (series.decided(at, settings.tolerance_s), series.match(at, settings.tolerance_s))
            decisions["force"] = self._scalar("force", settings.force, image, at)
            if settings.displacement is not None:
                decisions["displacement"] = self._scalar("displacement", settings.displacement, image, at)
            if not waited_out and not all(decided for decided, _ in decisions.values()):
                return
            self.pending.popleft()
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
            for series in self.series.values():
                series.forget_before(at - 2.0 * settings.tolerance_s - 1.0)

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
    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> _ = (folder / "diagnosis.json").write_text(json.dumps({"verdict": "explained", "named": ["image_latency"],
    ...     "effects": [{"effect": "image_latency", "parameters": {"delay_s": 0.052}}]}))
    >>> image_delay_from_diagnosis(folder)
    (0.052, 'image delay 0.052 s: image_latency named by the diagnosis (explained)')
    """
    file = Path(path) / "diagnosis.json" if Path(path).is_dir() else Path(path)
    try:
        document = json.loads(file.read_text())
        verdict, named = str(document["verdict"]), list(document.get("named", []))
        effects = {entry["effect"]: entry for entry in document["effects"]}
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise FileFormatError(f"{file}: not a diagnosis.json of usdeform diagnose ({error})") from None
    if "image_latency" not in named:
        return 0.0, f"image delay 0 s: the diagnosis ({verdict}) does not name image_latency"
    try:
        delay = float(effects["image_latency"]["parameters"]["delay_s"])
    except (KeyError, TypeError, ValueError):
        raise FileFormatError(f"{file}: effects: image_latency has no parameters.delay_s") from None
    if not math.isfinite(delay) or delay < 0:
        raise InputError(f"{file}: image_latency delay_s {delay}: the live pairing takes a delay of 0 s or more")
    return delay, f"image delay {delay:g} s: image_latency named by the diagnosis ({verdict})"
