"""PLUS sequence files (MetaImage .mha/.mhd, NRRD .seq.nrrd/.nrrd) to and from a Recording.

The layout follows PLUS's vtkPlusMetaImageSequenceIO / vtkPlusNrrdSequenceIO, which 3D Slicer's
Sequences module also reads: the frames are one 3-D image (DimSize/sizes ``cols rows n``, kinds
``domain domain list``, ultrasound image orientation ``MF`` = columns along the marked side, rows
going away from the transducer) and each frame has ``Seq_FrameNNNN_<name>`` header fields:
``ProbeToReferenceTransform`` (16 numbers, row-major, mm; Reference = robot base) with its
``...Status`` (OK/INVALID), ``ImageToProbeTransform`` (carries the mm-per-pixel scale),
``Timestamp`` (s), ``ContactForce`` (N, compression positive) and ``ProbeDisplacement`` (mm).
MetaImage headers hold them as ``Name = value`` lines, NRRD headers as ``Name:=value`` key/values.

Pixels without data (a corrected frame's pixels sampled from outside the original frame, a Recording's
``pixel_valid`` False) go to a companion sequence file beside the frames' file, named in its
``PixelValidFile`` header field (:func:`pixel_valid_path`): the same frames, poses and timestamps, with
pixel value 1 where the frame holds data and 0 where it holds none. 3D Slicer opens it as one more
sequence (a label map over the frames); :func:`read_sequence` reads it back into ``pixel_valid``.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from .._files import outputs_together
from ..errors import FileFormatError, InputError
from ..recording import Recording
from ..validation import check_calibration, check_rigid_transforms
from ._common import format_numbers, is_nrrd_file, parse_numbers, read_nrrd, write_nrrd
from ._metaimage import CODEC_FIELDS, read_metaimage, write_metaimage
from .plus_config import PlusConfig, read_plus_config

__all__ = [
    "PIXEL_VALID_FIELD",
    "SEQUENCE_SUFFIXES",
    "pixel_valid_path",
    "read_frame_series",
    "read_sequence",
    "write_sequence",
]

#: Header field naming the companion file of a sequence's pixel validity mask (a file name beside it).
PIXEL_VALID_FIELD = "PixelValidFile"

_FRAME_FIELD = re.compile(r"Seq_Frame(\d+)_(.+)")
_ORIENTATION_FIELDS = ("UltrasoundImageOrientation", "ultrasound image orientation")
_IMAGE_TYPE_FIELDS = ("UltrasoundImageType", "ultrasound image type")
_IMAGE_STATUS_FIELDS = ("ImageStatus", "Status")  # PLUS writes ImageStatus in MetaImage, Status in NRRD

# MetaImage geometry fields: frames carry their geometry in ImageToProbeTransform instead.
_METAIMAGE_LAYOUT_FIELDS = CODEC_FIELDS | {
    "Kinds",
    "ElementSpacing",
    "ElementSize",
    "Offset",
    "Position",
    "Origin",
    "TransformMatrix",
    "Rotation",
    "Orientation",
    "CenterOfRotation",
    "AnatomicalOrientation",
}
# Standard NRRD fields (teem's NRRD0005 specification, with their historical spellings).
_NRRD_LAYOUT_FIELDS = frozenset(
    {
        "type", "dimension", "space", "space dimension", "sizes", "space directions", "kinds", "endian",
        "encoding", "space origin", "measurement frame", "content", "thicknesses", "axis mins", "axismins",
        "axis maxs", "axismaxs", "centers", "centerings", "labels", "units", "spacings", "min", "max",
        "old min", "oldmin", "old max", "oldmax", "data file", "datafile", "line skip", "lineskip",
        "byte skip", "byteskip", "sample units", "sampleunits", "space units", "block size", "blocksize",
        "number",
    }
)  # fmt: skip
_RESERVED_METADATA = (
    _METAIMAGE_LAYOUT_FIELDS
    | _NRRD_LAYOUT_FIELDS
    | set(_ORIENTATION_FIELDS)
    | set(_IMAGE_TYPE_FIELDS)
    | {PIXEL_VALID_FIELD}
)
_DOUBLE_SUFFIXES = (".seq.nrrd", ".igs.nrrd", ".seq.mha", ".igs.mha")


def pixel_valid_path(path: str | Path) -> Path:
    """The companion file of ``path``'s pixel validity mask: ``.valid`` before its suffix
    (``corrected.seq.nrrd`` -> ``corrected.valid.seq.nrrd``, ``corrected.mha`` -> ``corrected.valid.mha``).

    Examples
    --------
    >>> pixel_valid_path("out/corrected.seq.nrrd").as_posix()
    'out/corrected.valid.seq.nrrd'
    """
    path = Path(path)
    suffix = next((s for s in _DOUBLE_SUFFIXES if path.name.lower().endswith(s)), path.suffix)
    return path.with_name(
        path.name[: len(path.name) - len(suffix)] + ".valid" + path.name[len(path.name) - len(suffix) :]
    )


def _read_metaimage_layout(path: Path) -> tuple[dict[str, str], np.ndarray, list[str]]:
    image = read_metaimage(path, uint8_only=True)
    kinds = image.fields["Kinds"].split() if "Kinds" in image.fields else None
    return image.fields, image.pixels, _default_kinds(image.pixels.ndim) if kinds is None else kinds


def _read_nrrd_layout(path: Path) -> tuple[dict[str, str], np.ndarray, list[str]]:
    header, pixels = read_nrrd(path, uint8_only=True)
    kinds = header.get("kinds")
    fields = {key: value for key, value in header.items() if isinstance(value, str)}
    return fields, pixels, _default_kinds(pixels.ndim) if kinds is None else [str(kind) for kind in kinds]


def _default_kinds(ndim: int) -> list[str]:
    """PLUS's rule without a Kinds field: the last axis lists the frames."""
    return ["domain"] * (ndim - 1) + ["list"] if ndim >= 3 else ["domain"] * ndim


def _frames_from_pixels(path: Path, pixels: np.ndarray, kinds: list[str]) -> np.ndarray:
    """Reshape C-order pixels whose file axes have ``kinds`` to (n, rows, cols)."""
    if len(kinds) != pixels.ndim:
        raise FileFormatError(f"{path}: kinds: {len(kinds)} entries for {pixels.ndim} image dimensions")
    sizes = pixels.shape[::-1]  # file axis order: columns first
    list_axes = [axis for axis, kind in enumerate(kinds) if kind.lower() in ("list", "time")]
    spatial_axes = [axis for axis, kind in enumerate(kinds) if kind.lower() in ("domain", "space")]
    if len(list_axes) + len(spatial_axes) != len(kinds) or list_axes not in ([], [len(kinds) - 1]):
        raise FileFormatError(f"{path}: kinds: expected 'domain domain [domain] list', got {' '.join(kinds)!r}")
    if len(spatial_axes) < 2 or any(sizes[axis] != 1 for axis in spatial_axes[2:]):
        raise FileFormatError(f"{path}: sizes {list(sizes)}: only 2-D frames are supported")
    cols, rows = sizes[0], sizes[1]
    count = sizes[list_axes[0]] if list_axes else 1
    if cols * rows * count == 0:
        raise FileFormatError(f"{path}: sizes {list(sizes)}: the file holds no image data")
    return pixels.reshape(count, rows, cols)


def _to_marked_far(path: Path, fields: dict[str, str], frames: np.ndarray) -> np.ndarray:
    """Flip frames stored in UF, MN or UN orientation to MF (PLUS's B-mode orientation in memory)."""
    name = next((name for name in _ORIENTATION_FIELDS if name in fields), None)
    if name is None:
        return frames
    code = fields[name].strip().upper()
    if len(code) == 3 and code[2] in "AD":  # third letter: direction of the (absent) z axis
        code = code[:2]
    if code not in ("MF", "MN", "UF", "UN"):
        raise FileFormatError(f"{path}: {name}: unsupported orientation {fields[name]!r}, expected MF, MN, UF or UN")
    if code[0] == "U":
        frames = frames[:, :, ::-1]
    if code[1] == "N":
        frames = frames[:, ::-1, :]
    return frames


class _FrameFields:
    """The ``Seq_FrameNNNN_<name>`` fields of a file, grouped by frame, with checked accessors."""

    def __init__(self, path: Path, fields: dict[str, str], count: int) -> None:
        self.path = path
        self.by_frame: list[dict[str, str]] = [{} for _ in range(count)]
        for key, value in fields.items():
            match = _FRAME_FIELD.fullmatch(key)
            if match is None:
                continue
            index = int(match.group(1))
            if index >= count:
                raise FileFormatError(f"{path}: {key}: frame {index} is beyond the {count} frames of the image data")
            self.by_frame[index][match.group(2)] = value

    def __len__(self) -> int:
        return len(self.by_frame)

    def anywhere(self, name: str) -> bool:
        return any(name in frame for frame in self.by_frame)

    def text(self, index: int, name: str) -> str:
        try:
            return self.by_frame[index][name]
        except KeyError:
            raise FileFormatError(f"{self.path}: frame {index}: field Seq_Frame{index:04d}_{name} is missing") from None

    def number(self, index: int, name: str) -> float:
        return float(parse_numbers(self.path, f"Seq_Frame{index:04d}_{name}", self.text(index, name), 1)[0])

    def matrix(self, index: int, name: str) -> np.ndarray:
        return parse_numbers(self.path, f"Seq_Frame{index:04d}_{name}", self.text(index, name), 16).reshape(4, 4)

    def rigid(self, index: int, name: str) -> np.ndarray:
        """A rigid transform (orthonormal rotation, last row [0, 0, 0, 1])."""
        matrix = self.matrix(index, name)
        check_rigid_transforms(matrix, f"{self.path}: Seq_Frame{index:04d}_{name}", error=FileFormatError)
        return matrix

    def ok(self, index: int, name: str) -> bool:
        """A PLUS status field (``...Status``): True for OK or when absent."""
        return self.by_frame[index].get(name, "OK").strip().upper() == "OK"

    def series(self, name: str) -> np.ndarray | None:
        """One number per frame, or None when no frame has the field."""
        if not self.anywhere(name):
            return None
        return np.array([self.number(index, name) for index in range(len(self))])


def _poses(frame_fields: _FrameFields) -> tuple[np.ndarray, np.ndarray]:
    """probe_to_base (n, 4, 4) and pose_valid (n,) from ProbeToReference or ProbeToTracker and ReferenceToTracker."""
    count = len(frame_fields)
    probe_to_base = np.empty((count, 4, 4))
    pose_valid = np.empty(count, dtype=bool)
    if frame_fields.anywhere("ProbeToReferenceTransform"):
        for i in range(count):
            pose_valid[i] = frame_fields.ok(i, "ProbeToReferenceTransformStatus")
            read = frame_fields.rigid if pose_valid[i] else frame_fields.matrix
            probe_to_base[i] = read(i, "ProbeToReferenceTransform")
    elif frame_fields.anywhere("ProbeToTrackerTransform"):
        for i in range(count):
            pose_valid[i] = frame_fields.ok(i, "ProbeToTrackerTransformStatus") and frame_fields.ok(
                i, "ReferenceToTrackerTransformStatus"
            )
            read = frame_fields.rigid if pose_valid[i] else frame_fields.matrix
            probe_to_tracker = read(i, "ProbeToTrackerTransform")
            reference_to_tracker = read(i, "ReferenceToTrackerTransform")
            try:
                probe_to_base[i] = np.linalg.solve(reference_to_tracker, probe_to_tracker)
            except np.linalg.LinAlgError:
                if pose_valid[i]:
                    raise FileFormatError(
                        f"{frame_fields.path}: Seq_Frame{i:04d}_ReferenceToTrackerTransform is singular"
                    ) from None
                probe_to_base[i] = np.eye(4)
            probe_to_base[i, 3] = [0.0, 0.0, 0.0, 1.0]  # exact for rigid inputs, removes round-off
    else:
        raise FileFormatError(
            f"{frame_fields.path}: no probe pose: expected Seq_FrameNNNN_ProbeToReferenceTransform, or "
            "Seq_FrameNNNN_ProbeToTrackerTransform with Seq_FrameNNNN_ReferenceToTrackerTransform"
        )
    for i in range(count):
        pose_valid[i] &= all(frame_fields.ok(i, name) for name in _IMAGE_STATUS_FIELDS)
    return probe_to_base, pose_valid


def _image_to_probe(frame_fields: _FrameFields, config: PlusConfig | None) -> np.ndarray:
    if config is not None:
        return config.image_to_probe
    name = "ImageToProbeTransform"
    if not frame_fields.anywhere(name):
        raise FileFormatError(
            f"{frame_fields.path}: no Seq_FrameNNNN_{name} field; pass the PLUS configuration holding the "
            "Image -> Probe calibration as config= (--config on the command line)"
        )
    first_text = frame_fields.text(0, name)
    image_to_probe = frame_fields.matrix(0, name)
    check_calibration(image_to_probe, f"{frame_fields.path}: Seq_Frame0000_{name}", error=FileFormatError)
    for i in range(1, len(frame_fields)):
        if frame_fields.text(i, name) != first_text and not np.allclose(
            frame_fields.matrix(i, name), image_to_probe, rtol=1e-9, atol=1e-12
        ):
            raise FileFormatError(
                f"{frame_fields.path}: Seq_Frame{i:04d}_{name} differs from frame 0's; a Recording has one calibration"
            )
    return image_to_probe


def read_sequence(path: str | Path, config: PlusConfig | str | Path | None = None) -> Recording:
    """Read a PLUS sequence file (.mha/.mhd MetaImage or .seq.nrrd/.nrrd NRRD) into a Recording.

    Poses come from ``ProbeToReferenceTransform`` or, in PLUS tracker recordings, from
    ``probe_to_base = inv(ReferenceToTracker) @ ProbeToTracker``; a frame's pose is valid when its
    transform status fields (and its ImageStatus, if present) are OK or absent. ``image_to_probe``
    comes from ``config`` (a PlusConfig or the path of a PLUS XML configuration, whose Image -> Probe
    CoordinateDefinition is used) when given, else from the frames' ``ImageToProbeTransform``. Force
    and displacement are None when the file has no ContactForce / ProbeDisplacement fields. Header
    fields that are neither layout nor per-frame fields go to ``metadata``; other per-frame fields
    are dropped. Frames stored in UF/MN/UN orientation are flipped to MF. A ``PixelValidFile`` field
    reads its companion file into ``pixel_valid`` (see the module's docstring).

    Raises FileFormatError, naming the file and the field or frame, for a malformed or truncated file.
    """
    path = Path(path)
    if isinstance(config, (str, Path)):
        config = read_plus_config(config)
    if is_nrrd_file(path):
        fields, pixels, kinds = _read_nrrd_layout(path)
    else:
        fields, pixels, kinds = _read_metaimage_layout(path)
    frames = _to_marked_far(path, fields, _frames_from_pixels(path, pixels, kinds))
    frame_fields = _FrameFields(path, fields, frames.shape[0])
    probe_to_base, pose_valid = _poses(frame_fields)
    metadata = {
        key: value
        for key, value in fields.items()
        if key not in _RESERVED_METADATA and _FRAME_FIELD.fullmatch(key) is None
    }
    pixel_valid = _read_pixel_valid(path, fields, frames.shape)
    try:
        return Recording(
            frames=frames,
            timestamps=np.array([frame_fields.number(i, "Timestamp") for i in range(len(frame_fields))]),
            probe_to_base=probe_to_base,
            pose_valid=pose_valid,
            image_to_probe=_image_to_probe(frame_fields, config),
            force=frame_fields.series("ContactForce"),
            probe_displacement=frame_fields.series("ProbeDisplacement"),
            metadata=metadata,
            pixel_valid=pixel_valid,
        )
    except FileFormatError:
        raise
    except InputError as exc:
        raise FileFormatError(f"{path}: {exc}") from None


def _read_pixel_valid(path: Path, fields: dict[str, str], shape: tuple[int, ...]) -> np.ndarray | None:
    """The pixel validity mask of the companion file that ``fields`` name (None: no such field)."""
    name = fields.get(PIXEL_VALID_FIELD)
    if name is None:
        return None
    companion = path.parent / name.strip()
    if Path(name.strip()).name != name.strip() or not companion.is_file():
        raise FileFormatError(
            f"{path}: {PIXEL_VALID_FIELD}: {name!r} is no file beside it (the pixel validity mask; "
            f"keep the two files together)"
        )
    if is_nrrd_file(companion):
        mask_fields, pixels, kinds = _read_nrrd_layout(companion)
    else:
        mask_fields, pixels, kinds = _read_metaimage_layout(companion)
    mask = _to_marked_far(companion, mask_fields, _frames_from_pixels(companion, pixels, kinds))
    if mask.shape != shape:
        raise FileFormatError(
            f"{companion}: {mask.shape[0]} frames of {mask.shape[1]} x {mask.shape[2]} pixels, but {path} "
            f"has {shape[0]} of {shape[1]} x {shape[2]}"
        )
    return np.ascontiguousarray(mask != 0)


def read_frame_series(path: str | Path, name: str) -> np.ndarray | None:
    """One number per frame of the per-frame field ``Seq_FrameNNNN_<name>`` of a sequence file (such as
    ``KnownLoad``, the load truly applied to the force sensor in a known-weight recording, N), or None when no frame
    has it. Raises FileFormatError, naming the file and the frame, where a frame lacks it or it is no number."""
    path = Path(path)
    fields, pixels, kinds = _read_nrrd_layout(path) if is_nrrd_file(path) else _read_metaimage_layout(path)
    return _FrameFields(path, fields, _frames_from_pixels(path, pixels, kinds).shape[0]).series(name)


_WRITTEN_FRAME_FIELDS = frozenset(
    {"ProbeToReferenceTransform", "ProbeToReferenceTransformStatus", "ImageToProbeTransform"}
    | {"ImageToProbeTransformStatus", "Timestamp", "ContactForce", "ProbeDisplacement", *_IMAGE_STATUS_FIELDS}
)


def _frame_fields(
    recording: Recording, image_status_name: str, series: Mapping[str, np.ndarray] | None = None
) -> list[tuple[str, str]]:
    image_to_probe = format_numbers(recording.image_to_probe.ravel())
    fields = []
    for i in range(len(recording)):
        prefix = f"Seq_Frame{i:04d}_"
        # An invalid pose may hold NaN (a tracking dropout); PLUS writes identity for such a pose.
        probe_to_base = recording.probe_to_base[i]
        if not recording.pose_valid[i] and not np.all(np.isfinite(probe_to_base)):
            probe_to_base = np.eye(4)
        fields += [
            (prefix + "ProbeToReferenceTransform", format_numbers(probe_to_base.ravel())),
            (prefix + "ProbeToReferenceTransformStatus", "OK" if recording.pose_valid[i] else "INVALID"),
            (prefix + "ImageToProbeTransform", image_to_probe),
            (prefix + "ImageToProbeTransformStatus", "OK"),
            (prefix + "Timestamp", format_numbers([recording.timestamps[i]])),
        ]
        if recording.force is not None:
            fields.append((prefix + "ContactForce", format_numbers([recording.force[i]])))
        if recording.probe_displacement is not None:
            fields.append((prefix + "ProbeDisplacement", format_numbers([recording.probe_displacement[i]])))
        fields += [(prefix + name, format_numbers([values[i]])) for name, values in (series or {}).items()]
        fields.append((prefix + image_status_name, "OK"))
    return fields


def _checked_series(series: Mapping[str, object] | None, count: int) -> dict[str, np.ndarray]:
    """``series`` as (count,) float64 arrays; InputError naming the series that is no such array or whose name is
    no plain field name or one the writer writes itself."""
    checked = {}
    for name, values in (series or {}).items():
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z][A-Za-z0-9]*", name):
            raise InputError(f"frame_series: {name!r} is no field name (letters and digits, a letter first)")
        if name in _WRITTEN_FRAME_FIELDS:
            raise InputError(f"frame_series: {name!r} is a per-frame field the recording itself writes")
        try:
            array = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"frame_series: {name}: expected numbers") from None
        if array.shape != (count,) or not np.all(np.isfinite(array)):
            raise InputError(
                f"frame_series: {name}: expected {count} finite numbers, one a frame, got shape {array.shape}"
            )
        checked[name] = array
    return checked


def _write_metaimage_sequence(
    path: Path, recording: Recording, compress: bool, series: Mapping[str, np.ndarray] | None = None
) -> None:
    fields = [
        ("AnatomicalOrientation", "RAI"),
        ("CenterOfRotation", "0 0 0"),
        ("ElementSpacing", "1 1 1"),
        ("Offset", "0 0 0"),
        ("TransformMatrix", "1 0 0 0 1 0 0 0 1"),
        ("Kinds", "domain domain list"),
        ("UltrasoundImageOrientation", "MF"),
        ("UltrasoundImageType", "BRIGHTNESS"),
        *recording.metadata.items(),
        *_frame_fields(recording, "ImageStatus", series),
    ]
    write_metaimage(path, recording.frames, fields, compress)


def _write_nrrd_sequence(
    path: Path, recording: Recording, compress: bool, series: Mapping[str, np.ndarray] | None = None
) -> None:
    # As PLUS writes 2-D frame sequences: a 3-D NRRD in a 2-D space whose third axis lists the frames.
    header = {
        "type": "uint8",
        "dimension": 3,
        "space dimension": 2,
        "space directions": np.array([[1.0, 0.0], [0.0, 1.0], [np.nan, np.nan]]),
        "kinds": ["domain", "domain", "list"],
        "endian": "little",
        "space origin": np.array([0.0, 0.0]),
        "ultrasound image orientation": "MF",
        "ultrasound image type": "BRIGHTNESS",
        **recording.metadata,
        **dict(_frame_fields(recording, "Status", series)),
    }
    write_nrrd(path, recording.frames, header, compress)


_WRITERS: dict[str, Callable[..., None]] = {
    ".mha": _write_metaimage_sequence,
    ".mhd": _write_metaimage_sequence,
    ".nrrd": _write_nrrd_sequence,
}
#: The suffixes :func:`write_sequence` writes (``.seq.nrrd`` ends in ``.nrrd``).
SEQUENCE_SUFFIXES = tuple(_WRITERS)


def write_sequence(
    path: str | Path,
    recording: Recording,
    compress: bool = True,
    frame_series: Mapping[str, object] | None = None,
) -> None:
    """Write ``recording`` as a PLUS sequence file: .mha/.mhd (MetaImage) or .seq.nrrd/.nrrd (NRRD).

    PLUS and 3D Slicer (SlicerIGSIO extension) recognise these files by the names ``*.igs.mha``,
    ``*.igs.nrrd``, ``*.seq.mha``, ``*.seq.nrrd``, ``*.mha`` and ``*.mhd``; any of them may be used.

    A recording whose ``pixel_valid`` marks pixels without data also writes that mask to the companion
    file :func:`pixel_valid_path` names (see the module's docstring).

    ``frame_series``: further numbers, one a frame, written as ``Seq_FrameNNNN_<name>`` (such as ``KnownLoad``;
    :func:`read_frame_series` reads them back).

    ``compress`` selects zlib (MetaImage) or gzip (NRRD) pixel data. The recording is validated
    first, and the file is written to a temporary file beside ``path`` and then renamed over it, so
    an error never leaves a half-written file.
    """
    path = Path(path)
    writer = _WRITERS.get(path.suffix.lower())
    if writer is None:
        raise InputError(f"path: {path} must end in .mha, .mhd, .seq.nrrd or .nrrd")
    if not isinstance(recording, Recording):
        raise InputError(f"recording: expected a Recording, got {type(recording).__name__}")
    recording = dataclasses.replace(recording)  # runs the validation again
    for key in recording.metadata:
        if key in _RESERVED_METADATA or key.startswith("Seq_Frame"):
            raise InputError(f"metadata: key {key!r} is a layout or per-frame field of sequence files")
    series = _checked_series(frame_series, len(recording))
    if recording.pixel_valid is None or recording.pixel_valid.all():
        writer(path, recording, compress, series)
        return
    companion = pixel_valid_path(path)
    mask = dataclasses.replace(recording, frames=recording.pixel_valid.astype(np.uint8), pixel_valid=None)
    frames = dataclasses.replace(recording, metadata={**recording.metadata, PIXEL_VALID_FIELD: companion.name})
    with outputs_together():  # the frames and their mask replace the old ones together, or neither does
        writer(companion, mask, compress)
        writer(path, frames, compress, series)
