"""Import a recording from a ROS1 or ROS2 bag: B-mode images, contact force and probe poses.

The paper's system records on ROS. This module reads the three streams of a bag with the ``rosbags``
library (pure Python, no ROS installation; the optional extra ``usdeform[ros]``) and matches them to
the image timestamps:

- images: ``sensor_msgs/Image`` (mono8, mono16, 8UC1, 16UC1, rgb8, bgr8, rgba8, bgra8) or
  ``sensor_msgs/CompressedImage`` (any format OpenCV decodes), converted to 8-bit grey;
- force: ``geometry_msgs/WrenchStamped``; the contact force is the component of ``wrench.force``
  along ``force_axis``, a unit axis of the wrench's own frame (the sensor is taken to be mounted
  along the probe axis), with the sign chosen so that pressing into tissue reads positive;
- poses: ``geometry_msgs/PoseStamped`` or ``geometry_msgs/TransformStamped`` (the probe in the robot
  base), or ``tf2_msgs/TFMessage`` with ``pose_child_frame`` naming the probe frame (a direct
  parent -> probe transform; TF chains are not composed). Positions are in metres in ROS and are
  converted to millimetres.

Each stream is interpolated to the image time stamp (force linearly, position linearly, rotation by
spherical linear interpolation). A frame is kept only when every stream has a sample at most
``tolerance_s`` before and at most ``tolerance_s`` after it; the other frames are dropped and counted
per stream. Time stamps come from message headers (the bag's receive time when a header stamp is
zero); a stream whose messages all carry one stamp is refused (they cannot be placed in time), and of
messages that repeat an earlier stamp only the first is used, with a warning. ``ProbeDisplacement`` is
the probe's motion along its own axis (probe +z, into the tissue) since the first kept frame, mm, as
in a palpation that starts at first contact.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..errors import FileFormatError, InputError, UsdeformError
from ..options import NUMBERS
from ..recording import Recording

__all__ = ["AXES", "BagImport", "read_bag"]

ForceAxis = Literal["x", "y", "z", "-x", "-y", "-z"]
#: The wrench axes a ContactForce can be read from, as unit vectors of the wrench's frame.
AXES: dict[str, tuple[float, float, float]] = {
    "x": (1.0, 0.0, 0.0),
    "y": (0.0, 1.0, 0.0),
    "z": (0.0, 0.0, 1.0),
    "-x": (-1.0, 0.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "-z": (0.0, 0.0, -1.0),
}
_IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
_FORCE_TYPES = ("geometry_msgs/msg/WrenchStamped",)
_POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped", "tf2_msgs/msg/TFMessage")
_GREY_FROM_COLOUR = {
    "rgb8": cv2.COLOR_RGB2GRAY,
    "bgr8": cv2.COLOR_BGR2GRAY,
    "rgba8": cv2.COLOR_RGBA2GRAY,
    "bgra8": cv2.COLOR_BGRA2GRAY,
}
_CHANNELS = {"mono8": 1, "8UC1": 1, "mono16": 1, "16UC1": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}


@dataclass(frozen=True)
class BagImport:
    """The recording made from a bag and what was left out.

    Attributes
    ----------
    recording : Recording
        The kept frames with ContactForce (N), ProbeDisplacement (mm) and probe poses (mm).
    n_images : int
        Image messages on the image topic.
    dropped : dict of str to int
        Frames dropped per reason: ``"force"`` / ``"pose"`` (no sample within the tolerance on both
        sides of the image time).
    warnings : list of str
        Things the user should check (e.g. a force that reads mostly negative).
    """

    recording: Recording
    n_images: int
    dropped: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def _stamp_s(message: Any, receive_ns: int) -> float:
    """The header stamp of ``message`` in seconds, or the bag's receive time when the stamp is zero."""
    stamp = message.header.stamp
    seconds = int(stamp.sec) + int(stamp.nanosec) * 1e-9
    return seconds if seconds > 0 else receive_ns * 1e-9


def _grey_image(message: Any, topic: str, index: int) -> np.ndarray:
    """An 8-bit grey (rows, cols) image from a sensor_msgs Image or CompressedImage message."""
    where = f"{topic} message {index}"
    if message.__msgtype__.endswith("CompressedImage"):
        image = cv2.imdecode(np.frombuffer(bytes(message.data), np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise FileFormatError(f"{where}: cannot decode the compressed image (format {message.format!r})")
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        if image.dtype == np.uint16:
            return np.right_shift(image, 8).astype(np.uint8)
        if image.dtype != np.uint8:
            raise FileFormatError(f"{where}: compressed image of {image.dtype}; expected 8- or 16-bit pixels")
        return image
    encoding = str(message.encoding)
    channels = _CHANNELS.get(encoding)
    if channels is None:
        raise FileFormatError(
            f"{where}: image encoding {encoding!r} is not supported; expected one of {sorted(_CHANNELS)}"
        )
    rows, cols, step = int(message.height), int(message.width), int(message.step)
    sixteen = encoding in ("mono16", "16UC1")
    row_bytes = cols * channels * (2 if sixteen else 1)
    data = np.asarray(message.data, dtype=np.uint8)
    if rows < 1 or cols < 1 or step < row_bytes or data.size < rows * step:
        raise FileFormatError(
            f"{where}: image of {rows} x {cols} {encoding} with step {step} needs {rows * step} bytes, got {data.size}"
        )
    pixels = data[: rows * step].reshape(rows, step)[:, :row_bytes]
    if sixteen:
        words = pixels.copy().view(">u2" if message.is_bigendian else "<u2")
        return (words >> 8).astype(np.uint8)
    if channels == 1:
        return np.ascontiguousarray(pixels)
    return cv2.cvtColor(np.ascontiguousarray(pixels).reshape(rows, cols, channels), _GREY_FROM_COLOUR[encoding])


def _pose_samples(message: Any, receive_ns: int, child_frame: str | None) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """(time s, position m, quaternion xyzw) samples of the probe pose carried by ``message``."""
    kind = message.__msgtype__
    if kind.endswith("PoseStamped"):
        position, orientation = message.pose.position, message.pose.orientation
        stamped = [(message, position, orientation)]
    elif kind.endswith("TransformStamped"):
        stamped = [(message, message.transform.translation, message.transform.rotation)]
    else:  # TFMessage: keep the transforms whose child frame is the probe
        stamped = [
            (transform, transform.transform.translation, transform.transform.rotation)
            for transform in message.transforms
            if child_frame is None or transform.child_frame_id == child_frame
        ]
    return [
        (
            _stamp_s(carrier, receive_ns),
            np.array([position.x, position.y, position.z], dtype=np.float64),
            np.array([orientation.x, orientation.y, orientation.z, orientation.w], dtype=np.float64),
        )
        for carrier, position, orientation in stamped
    ]


def _connection(reader: Any, topic: str, allowed: Sequence[str], role: str) -> Any:
    """The bag connection of ``topic``, checked to carry one of the ``allowed`` message types."""
    connections = [c for c in reader.connections if c.topic == topic]
    if not connections:
        topics = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
        raise InputError(f"{role} topic {topic!r} is not in the bag; it has: {', '.join(topics) or 'no topics'}")
    msgtype = connections[0].msgtype
    if msgtype not in allowed:
        raise InputError(f"{role} topic {topic!r} carries {msgtype}; expected one of {', '.join(allowed)}")
    return connections


def _bracketed(sample_times: np.ndarray, times: np.ndarray, tolerance_s: float) -> np.ndarray:
    """True where a sample lies at most ``tolerance_s`` before and at most ``tolerance_s`` after each time."""
    if sample_times.size == 0:
        return np.zeros(times.shape, dtype=bool)
    after = np.searchsorted(sample_times, times, side="left")
    before = np.searchsorted(sample_times, times, side="right") - 1
    has_before = before >= 0
    has_after = after < sample_times.size
    gap_before = np.where(has_before, times - sample_times[np.clip(before, 0, None)], np.inf)
    gap_after = np.where(has_after, sample_times[np.clip(after, None, sample_times.size - 1)] - times, np.inf)
    return (gap_before <= tolerance_s) & (gap_after <= tolerance_s)


def _sorted_unique(times: np.ndarray) -> np.ndarray:
    """Indices that sort ``times`` and keep the first of equal times (interpolation needs increasing times)."""
    order = np.argsort(times, kind="stable")
    keep = np.ones(order.size, dtype=bool)
    keep[1:] = np.diff(times[order]) > 0
    return order[keep]


def _repeated_stamps(times: np.ndarray, topic: str, role: str) -> str | None:
    """InputError when every message of a stream carries one header stamp (the stamps cannot place the
    samples in time: the issue's 12 frames at t = 0 with one force); else a warning when some repeat an
    earlier stamp (only the first of them is used), or None."""
    if times.size > 1 and np.all(times == times[0]):
        raise InputError(
            f"{role} topic {topic!r}: all {times.size} messages carry the same header stamp {times[0]:.9f} s, "
            "so they cannot be placed in time; the publisher does not stamp its messages"
        )
    repeated = times.size - np.unique(times).size
    if repeated:
        return f"{role} topic {topic!r}: {repeated} of {times.size} messages repeat an earlier header stamp (kept one)"
    return None


def read_bag(
    path: str | Path,
    *,
    image_topic: str,
    force_topic: str,
    pose_topic: str,
    image_to_probe: np.ndarray | Callable[[int, int], np.ndarray],
    pose_child_frame: str | None = None,
    force_axis: ForceAxis = "z",
    tolerance_s: float = 0.05,
    pose_unit_mm: float = 1000.0,
) -> BagImport:
    """Read a ROS1 (``.bag``) or ROS2 (folder) bag into a :class:`Recording`.

    Parameters
    ----------
    path : str or Path
        A ROS1 ``.bag`` file or a ROS2 bag folder (sqlite3 or mcap storage).
    image_topic, force_topic, pose_topic : str
        Topics of the B-mode images, the force/torque sensor and the probe pose.
    image_to_probe : ndarray or callable
        (4, 4) calibration, image pixel -> probe mm, or a function of the frame size (rows, cols) that
        returns it (e.g. :func:`usdeform.recording.image_to_probe_from_geometry` with the probe's geometry).
    pose_child_frame : str, optional
        For TF topics: the child frame id of the probe (required when the TF topic carries other frames).
    force_axis : {"x", "y", "z", "-x", "-y", "-z"}
        Axis of the wrench frame along which the contact force is read (compression positive).
    tolerance_s : float
        Largest gap, s, between an image and the nearest force/pose sample on each side of it.
    pose_unit_mm : float
        Millimetres per pose unit (1000 for ROS's metres).

    Returns
    -------
    BagImport
        The recording, the number of image messages and the frames dropped per stream.
    """
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore
    except ImportError as error:
        raise InputError("reading ROS bags needs the rosbags library: pip install 'usdeform[ros]'") from error
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such bag file or folder")
    NUMBERS["tolerance_s"].check(tolerance_s)
    if force_axis not in AXES:
        raise InputError(f"force_axis: expected one of {sorted(AXES)}, got {force_axis!r}")
    axis = np.array(AXES[force_axis])

    images: list[np.ndarray] = []
    image_times: list[float] = []
    force_times: list[float] = []
    forces: list[float] = []
    pose_samples: list[tuple[float, np.ndarray, np.ndarray]] = []
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            image_connections = _connection(reader, image_topic, _IMAGE_TYPES, "image")
            force_connections = _connection(reader, force_topic, _FORCE_TYPES, "force")
            pose_connections = _connection(reader, pose_topic, _POSE_TYPES, "pose")
            for connection, receive_ns, raw in reader.messages(
                connections=[*image_connections, *force_connections, *pose_connections]
            ):
                message: Any = reader.deserialize(raw, connection.msgtype)
                if connection.topic == image_topic:
                    images.append(_grey_image(message, image_topic, len(images)))
                    image_times.append(_stamp_s(message, receive_ns))
                elif connection.topic == force_topic:
                    vector = message.wrench.force
                    forces.append(float(np.dot(axis, [vector.x, vector.y, vector.z])))
                    force_times.append(_stamp_s(message, receive_ns))
                else:
                    pose_samples.extend(_pose_samples(message, receive_ns, pose_child_frame))
    except UsdeformError:
        raise
    except (AnyReaderError, OSError) as error:
        raise FileFormatError(f"{path}: cannot read the bag: {error}") from error
    except Exception as error:  # rosbags parses a corrupt bag into any error (UnicodeDecodeError, struct.error, ...)
        raise FileFormatError(f"{path}: cannot read the bag: {type(error).__name__}: {error}"[:300]) from error

    if not images:
        raise InputError(f"image topic {image_topic!r}: no messages in {path}")
    shapes = {image.shape for image in images}
    if len(shapes) > 1:
        first = images[0].shape
        index = next(i for i, image in enumerate(images) if image.shape != first)
        raise InputError(f"{image_topic} message {index}: image of {images[index].shape}, earlier ones {first}")

    warnings = [
        warning
        for warning in (
            _repeated_stamps(np.array(image_times), image_topic, "image"),
            _repeated_stamps(np.array(force_times), force_topic, "force"),
            _repeated_stamps(np.array([t for t, _, _ in pose_samples]), pose_topic, "pose"),
        )
        if warning
    ]
    times = np.array(image_times)
    order = _sorted_unique(times)  # frames of a repeated stamp: the first
    times = times[order]
    force_t = np.array(force_times)
    force_order = _sorted_unique(force_t)
    force_t, force_values = force_t[force_order], np.array(forces)[force_order]
    pose_t = np.array([t for t, _, _ in pose_samples])
    pose_order = _sorted_unique(pose_t)
    pose_t = pose_t[pose_order]
    if not np.all(np.isfinite(force_values)):
        raise InputError(f"force topic {force_topic!r}: non-finite force values")

    with_force = _bracketed(force_t, times, tolerance_s)
    with_pose = _bracketed(pose_t, times, tolerance_s)
    keep = with_force & with_pose
    dropped = {"force": int(np.count_nonzero(~with_force)), "pose": int(np.count_nonzero(with_force & ~with_pose))}
    if not keep.any():
        raise InputError(
            f"{path}: no image has force and pose samples within {tolerance_s} s on both sides "
            f"(images {times[0]:.3f}-{times[-1]:.3f} s; force samples {force_t.size}, pose samples {pose_t.size})"
        )
    kept_times = times[keep]

    positions = np.array([p for _, p, _ in pose_samples])[pose_order] * pose_unit_mm
    quaternions = np.array([q for _, _, q in pose_samples])[pose_order]
    norms = np.linalg.norm(quaternions, axis=1)
    if not (np.all(np.isfinite(positions)) and np.all(np.isfinite(norms)) and np.all(norms > 1e-6)):
        raise InputError(f"pose topic {pose_topic!r}: non-finite position or zero-length orientation quaternion")
    rotations = Rotation.from_quat(quaternions / norms[:, None])
    if pose_t.size == 1:
        probe_rotation = Rotation.concatenate([rotations] * kept_times.size)
    else:
        probe_rotation = Slerp(pose_t, rotations)(kept_times)
    probe_to_base = np.tile(np.eye(4), (kept_times.size, 1, 1))
    probe_to_base[:, :3, :3] = probe_rotation.as_matrix()
    probe_to_base[:, :3, 3] = np.stack([np.interp(kept_times, pose_t, positions[:, k]) for k in range(3)], axis=1)

    force = np.interp(kept_times, force_t, force_values)
    probe_axis = probe_to_base[0, :3, 2]
    probe_displacement = (probe_to_base[:, :3, 3] - probe_to_base[0, :3, 3]) @ probe_axis
    if np.median(force) < 0 and np.ptp(force) > 0.1:
        warnings.append(
            f"ContactForce reads mostly negative (median {np.median(force):.2f} N): the wrench axis may point "
            f"the other way; try force_axis={'-' + force_axis if len(force_axis) == 1 else force_axis[1:]!r}"
        )
    frames = np.stack([images[i] for i in order[keep]])
    recording = Recording(
        frames=frames,
        timestamps=kept_times - kept_times[0],
        probe_to_base=probe_to_base,
        pose_valid=np.ones(kept_times.size, dtype=bool),
        image_to_probe=np.asarray(
            image_to_probe(*frames.shape[1:]) if callable(image_to_probe) else image_to_probe, dtype=np.float64
        ),
        force=force,
        probe_displacement=probe_displacement,
        metadata={"Source": f"ROS bag {path.name}", "BagStartTime": f"{kept_times[0]:.9f}"},
    )
    return BagImport(recording=recording, n_images=len(images), dropped=dropped, warnings=warnings)
