"""A tracked ultrasound recording: B-mode frames, probe poses, calibration, force and displacement.

Conventions (see DESIGN.md): millimetres, newtons, seconds; transforms are 4x4 float64 named
``<from>_to_<to>`` acting on homogeneous column vectors; a pixel at (col, row) has image coordinates
``[col, row, 0, 1]`` and ``image_to_probe`` carries the pixel-to-mm scale, as in PLUS.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ._arrays import readonly as _readonly
from .errors import InputError
from .validation import check_calibration, check_finite_per_frame, check_rigid_transforms, check_timestamps

__all__ = ["Recording", "image_to_probe_from_geometry"]


def image_to_probe_from_geometry(
    rows: int, cols: int, depth_mm: float = 40.0, width_mm: float = 37.5, offset_mm: float = 0.0
) -> np.ndarray:
    """The paper's eq. 2 calibration: pixel (col, row) -> probe frame, mm. Returns (4, 4) float64.

    ``width_mm`` is the length L_p of the transducer array (spanning the ``cols`` pixels of a row),
    ``depth_mm`` the imaging depth D_I (spanning the ``rows`` pixels of a column) and ``offset_mm``
    the distance epsilon from the probe origin (centre of the probe face) to the image's top row.
    The image x axis (columns) maps to probe x, the image y axis (depth) to probe z, and the image
    normal to probe -y.
    """
    if int(rows) < 1 or int(cols) < 1:
        raise InputError(f"rows, cols: expected positive pixel counts, got {rows}, {cols}")
    for name, value in (("depth_mm", depth_mm), ("width_mm", width_mm)):
        if not (np.isfinite(value) and value > 0):
            raise InputError(f"{name}: expected a positive finite length in mm, got {value}")
    if not np.isfinite(offset_mm):
        raise InputError(f"offset_mm: expected a finite length in mm, got {offset_mm}")
    return np.array(
        [
            [width_mm / cols, 0.0, 0.0, -width_mm / 2.0],
            [0.0, 0.0, -1.0, 0.0],
            [0.0, depth_mm / rows, 0.0, offset_mm],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def _float_array(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    try:
        array = np.ascontiguousarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: cannot convert to a float64 array ({exc})") from None
    if array.shape != shape:
        raise InputError(f"{name}: expected shape {shape}, got {array.shape}")
    return array


@dataclass(frozen=True, eq=False)
class Recording:
    """A tracked B-mode recording of ``n`` frames, validated on construction.

    Parameters
    ----------
    frames : ndarray
        (n, rows, cols) uint8 B-mode images, C-contiguous; pixel (col, row) is ``frames[i, row, col]``.
    timestamps : ndarray
        (n,) float64 acquisition times, s, non-decreasing.
    probe_to_base : ndarray
        (n, 4, 4) float64 probe pose in the robot base (PLUS "Reference") frame, mm.
    pose_valid : ndarray
        (n,) bool, False where the pose is unusable (PLUS transform status not OK); the poses of
        such frames are not checked and must not be used.
    image_to_probe : ndarray
        (4, 4) float64 calibration, image pixel coordinates -> probe mm (paper eq. 2).
    force : ndarray, optional
        (n,) float64 contact force along the probe axis, N, compression positive; None if not recorded.
    probe_displacement : ndarray, optional
        (n,) float64 probe-tip displacement lambda_z along the probe axis, mm; None if not recorded.
    metadata : dict of str to str
        Other (non per-frame) header fields, name -> value, kept through read and write.
    pixel_valid : ndarray, optional
        (n, rows, cols) bool, False at pixels that hold no image data (a corrected frame's pixels
        sampled from outside the original frame); compounding leaves them out. Sequence files store it
        in a companion file (:func:`usdeform.io.pixel_valid_path`). None: every pixel is valid.

    Notes
    -----

    The arrays are stored as read-only views; build a new Recording to change them. Recordings
    compare by identity.
    """

    frames: np.ndarray
    timestamps: np.ndarray
    probe_to_base: np.ndarray
    pose_valid: np.ndarray
    image_to_probe: np.ndarray
    force: np.ndarray | None = None
    probe_displacement: np.ndarray | None = None
    metadata: dict[str, str] = field(default_factory=dict)
    pixel_valid: np.ndarray | None = None

    def __post_init__(self) -> None:
        frames = np.asarray(self.frames)
        if frames.dtype != np.uint8:
            raise InputError(f"frames: expected dtype uint8, got {frames.dtype}")
        if frames.ndim != 3 or min(frames.shape) < 1:
            raise InputError(f"frames: expected a non-empty (n, rows, cols) array, got shape {frames.shape}")
        frames = np.ascontiguousarray(frames)
        n = frames.shape[0]

        timestamps = _float_array("timestamps", self.timestamps, (n,))
        check_timestamps(timestamps)

        pose_valid = np.asarray(self.pose_valid)
        if pose_valid.dtype != np.bool_:
            raise InputError(f"pose_valid: expected dtype bool, got {pose_valid.dtype}")
        if pose_valid.shape != (n,):
            raise InputError(f"pose_valid: expected shape {(n,)}, got {pose_valid.shape}")
        pose_valid = np.ascontiguousarray(pose_valid)

        probe_to_base = _float_array("probe_to_base", self.probe_to_base, (n, 4, 4))
        check_rigid_transforms(probe_to_base, "probe_to_base", valid=pose_valid)
        image_to_probe = _float_array("image_to_probe", self.image_to_probe, (4, 4))
        check_calibration(image_to_probe, "image_to_probe")

        optional: dict[str, np.ndarray | None] = {}
        for name in ("force", "probe_displacement"):
            value = getattr(self, name)
            if value is not None:
                value = _float_array(name, value, (n,))
                check_finite_per_frame(value, name)
                value = _readonly(value)
            optional[name] = value

        pixel_valid = self.pixel_valid
        if pixel_valid is not None:
            pixel_valid = np.asarray(pixel_valid)
            if pixel_valid.dtype != np.bool_ or pixel_valid.shape != frames.shape:
                raise InputError(
                    f"pixel_valid: expected a bool array of shape {frames.shape}, "
                    f"got {pixel_valid.dtype} {pixel_valid.shape}"
                )
            pixel_valid = _readonly(np.ascontiguousarray(pixel_valid))

        if not isinstance(self.metadata, dict):
            raise InputError(f"metadata: expected a dict of str -> str, got {type(self.metadata).__name__}")
        for key, value in self.metadata.items():
            if not isinstance(key, str) or not isinstance(value, str):
                raise InputError(f"metadata: keys and values must be str, got {key!r}: {value!r}")
            if not key.strip() or any(c in key for c in "=:\r\n") or key != key.strip():
                raise InputError(
                    f"metadata: key {key!r} must be non-empty, without surrounding spaces, '=', ':' or line breaks"
                )
            if "\n" in value or "\r" in value or value != value.strip():
                raise InputError(f"metadata[{key!r}]: value must be one line without surrounding spaces")

        object.__setattr__(self, "frames", _readonly(frames))
        object.__setattr__(self, "timestamps", _readonly(timestamps))
        object.__setattr__(self, "probe_to_base", _readonly(probe_to_base))
        object.__setattr__(self, "pose_valid", _readonly(pose_valid))
        object.__setattr__(self, "image_to_probe", _readonly(image_to_probe))
        object.__setattr__(self, "force", optional["force"])
        object.__setattr__(self, "probe_displacement", optional["probe_displacement"])
        object.__setattr__(self, "metadata", dict(self.metadata))
        object.__setattr__(self, "pixel_valid", pixel_valid)

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        """Frame size as (rows, cols), pixels."""
        return int(self.frames.shape[1]), int(self.frames.shape[2])

    @property
    def image_to_base(self) -> np.ndarray:
        """(n, 4, 4) float64 ``probe_to_base @ image_to_probe``: pixel (col, row, 0, 1) -> base mm."""
        return self.probe_to_base @ self.image_to_probe

    def posed_indices(self, name: str = "recording") -> np.ndarray:
        """The indices of the frames with a valid probe pose; InputError naming ``name`` when none has one."""
        posed = np.flatnonzero(self.pose_valid)
        if posed.size == 0:
            raise InputError(f"{name}: no frame has a valid probe pose")
        return posed

    def select(self, indices: np.ndarray | Sequence[int] | slice) -> Recording:
        """A new Recording of the frames picked by ``indices`` (int array, bool mask or slice), in that order."""
        try:
            picked = np.arange(len(self))[indices]
        except IndexError as exc:
            raise InputError(f"indices: {exc}") from None
        if picked.ndim != 1:
            raise InputError(f"indices: must select a 1-D set of frames, got shape {picked.shape}")
        if picked.size == 0:
            raise InputError("indices: selects no frame")
        return Recording(
            frames=self.frames[picked],
            timestamps=self.timestamps[picked],
            probe_to_base=self.probe_to_base[picked],
            pose_valid=self.pose_valid[picked],
            image_to_probe=self.image_to_probe,
            force=None if self.force is None else self.force[picked],
            probe_displacement=None if self.probe_displacement is None else self.probe_displacement[picked],
            metadata=self.metadata,
            pixel_valid=None if self.pixel_valid is None else self.pixel_valid[picked],
        )
