"""What the live service sends, and where 3D Slicer places it.

Slicer's OpenIGTLinkIF takes an IMAGE's matrix as its image-to-RAS and a TRANSFORM as a RAS-to-RAS
transform, and never reads the IMAGE's coordinate flag (OpenIGTLinkIO's ``IGTLToVTKTransform``,
SlicerOpenIGTLink's ``vtkMRMLIGTLConnectorNode``). PLUS Server sends its Reference coordinates as they
are, flagged RAS. Two placements follow (:data:`PLACEMENTS`):

- ``plus`` (the default): matrices in the Reference (robot base) frame as they are, as PLUS Server
  sends them: the corrected stream overlays PLUS's raw stream in Slicer;
- ``files``: matrices turned from LPS to RAS (``diag(-1, -1, 1)`` on the left), as Slicer turns the
  saved volume files (their space is left-posterior-superior): the stream coincides with them.

Either way the IMAGE's flag says RAS: what Slicer takes the matrix to mean.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np

from ..errors import InputError
from ..recording import Recording
from .pairing import PairedFrame
from .transport import pyigtl_module

__all__ = [
    "LPS_TO_RAS",
    "PLACEMENTS",
    "OutputSettings",
    "Placement",
    "frame_messages",
    "image_message",
    "transform_message",
]

Placement = Literal["plus", "files"]
PLACEMENTS: tuple[str, ...] = get_args(Placement)
#: LPS to RAS (and back): x and y negated.
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


@dataclass(frozen=True)
class OutputSettings:
    """What the service sends, and how often.

    ``volume_rate_hz``: volumes sent per second at most (a volume goes out only when it holds frames the
    last one did not). ``frame_rate_hz``: corrected frames sent per second at most; None: every frame,
    as soon as it is corrected. ``placement``: see the module's notes. ``relay``: also send each paired
    frame as received (the raw image and its probe pose), beside the corrected one.
    """

    volume_rate_hz: float = 2.0
    frame_rate_hz: float | None = None
    placement: Placement = "plus"
    relay: bool = True
    volume_name: str = "CorrectedVolume"
    frame_name: str = "CorrectedImage"
    pose_name: str = "CorrectedProbe"
    raw_name: str = "Image_Reference"
    raw_pose_name: str = "ProbeToReference"
    status_name: str = "usdeformStatus"

    def __post_init__(self) -> None:
        for name in ("volume_rate_hz", "frame_rate_hz"):
            value = getattr(self, name)
            if value is None and name == "frame_rate_hz":
                continue
            if not (isinstance(value, (int, float)) and math.isfinite(value) and 1e-3 <= value <= 1e3):
                raise InputError(f"{name}: expected a rate from 0.001 to 1000 Hz, got {value}")
        for name in ("volume_name", "frame_name", "pose_name", "raw_name", "raw_pose_name", "status_name"):
            if not 0 < len(getattr(self, name).encode()) <= 20:
                raise InputError(f"{name}: an OpenIGTLink device name has 1 to 20 bytes, got {getattr(self, name)!r}")
        if self.placement not in PLACEMENTS:
            raise InputError(f"placement: expected one of {', '.join(PLACEMENTS)}, got {self.placement!r}")

    def world(self, matrix: np.ndarray) -> np.ndarray:
        """``matrix`` (to the Reference frame, mm) as sent: as it is, or turned to RAS (``files``)."""
        matrix = np.asarray(matrix, dtype=np.float64)
        return LPS_TO_RAS @ matrix if self.placement == "files" else matrix


def image_message(image: np.ndarray, index_to_world: np.ndarray, name: str, timestamp: float, **metadata: str) -> Any:
    """An IMAGE message (OpenIGTLink v3 header) of ``image`` ((k, j, i), or (rows, cols) for a frame)
    whose matrix is ``index_to_world`` (mm), flagged RAS."""
    pyigtl = pyigtl_module()
    pixels = image[np.newaxis] if image.ndim == 2 else image
    message = pyigtl.ImageMessage(
        pixels, ijk_to_world_matrix=index_to_world, world_coordinate_system="ras", timestamp=timestamp, device_name=name
    )
    message.header_version = 2
    message.metadata = metadata
    return message


def transform_message(matrix: np.ndarray, name: str, timestamp: float) -> Any:
    """A TRANSFORM message (OpenIGTLink v3 header, ``TransformStatus`` OK, as PLUS Server sends one)."""
    message = pyigtl_module().TransformMessage(matrix, timestamp=timestamp, device_name=name)
    message.header_version = 2
    message.metadata = {"TransformStatus": "OK"}
    return message


def frame_messages(
    outputs: OutputSettings, frames: Sequence[PairedFrame], corrected: Recording, image_to_probe: np.ndarray
) -> list[Any]:
    """The messages of a batch of ``frames`` and the same ``corrected``, per frame: as received (``relay``: the
    raw image and its probe pose) and corrected (the frame at its zero-force pose and that pose);
    ``frame_rate_hz``: the latest frame of the batch only. ``image_to_probe``: the calibration (4, 4), mm."""
    messages = []
    chosen = range(len(frames)) if outputs.frame_rate_hz is None else range(len(frames) - 1, len(frames))
    for i in chosen:
        frame, t = frames[i], frames[i].timestamp
        if outputs.relay:
            messages.append(transform_message(outputs.world(frame.probe_to_base), outputs.raw_pose_name, t))
            image_to_base = outputs.world(frame.probe_to_base @ image_to_probe)
            messages.append(image_message(frame.pixels, image_to_base, outputs.raw_name, t))
        image_to_base = corrected.image_to_base[i]
        probe_to_base = outputs.world(image_to_base @ np.linalg.inv(image_to_probe))
        messages.append(transform_message(probe_to_base, outputs.pose_name, t))
        frame_pixels = np.asarray(corrected.frames[i])
        messages.append(image_message(frame_pixels, outputs.world(image_to_base), outputs.frame_name, t))
    return messages
