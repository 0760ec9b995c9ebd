"""What the gap measures read from a recorded palpation: phases, tracks, speckle correlation, vessel, intensity.

Everything here comes from the recording alone (frames, ContactForce, ProbeDisplacement,
timestamps, ImageToProbeTransform): no phantom description and no labels.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import FitError, InputError
from ..metrics import pixel_size_mm, segment_vessel
from ..optical_flow import track_palpation
from ..recording import Recording
from .reference_target import REFERENCE_DEPTH_KEY, ReferenceTrack, track_reference

__all__ = ["CORRELATION_SEPARATIONS_MM", "MIN_FRAMES", "PHASES", "ROW_PROFILE_STRIPS", "Observation", "observe"]

PHASES = ("loading", "holding", "unloading")
MIN_FRAMES = 12
# Pairs of frames whose speckle correlation is measured: 0 = each frame with the previous one (noise, jitter);
# otherwise each frame with the earlier frame whose lambda differs by this much (mm, within a quarter of it):
# out-of-plane motion that grows with lambda decorrelates such pairs far more than strain does.
CORRELATION_SEPARATIONS_MM = (0.0, 1.0, 2.0, 4.0)
_SEPARATION_TOLERANCE = 0.25
_BLOCK_S = 0.3  # length of the time blocks the split and the bootstrap resample, s
_INTENSITY_BANDS = 8
_ABOVE_REFLECTOR_MM = 2.0  # tracked points and intensity bands stop this far above a reflector in the world, mm
_CORRELATION_SCALE_PX = 1.0  # finest Gaussian scale (sigma, pixels) at which frames are correlated
_STRUCTURE_SCALE_MM = 1.5  # Gaussian scale (sigma, mm) of the structure removed before correlating
# Finest pixel (mm) at which frames are correlated: finer frames are area-averaged down to it first. The flow,
# the warp and the 1-pixel fine scale work in pixels, and at a pixel much finer than half the speckle's axial
# size (0.2-0.5 mm resolution of linear probes) they leave a misregistration that decorrelates with motion
# and looks like out-of-plane motion (a null at 0.08 mm pixels was attributed to it).
_CORRELATION_PIXEL_MM = 0.12
ROW_PROFILE_STRIPS = 8  # lateral strips of the row profiles; wider than the lateral speckle size


@dataclass(frozen=True)
class Observation:
    """The measurable content of one palpation recording (n frames, N tracked points).

    time_s, force_n, probe_displacement_mm: (n,) per frame. phase: (n,) index into PHASES.
    block: (n,) time-block index (blocks of about 0.3 s; the unit of the split and the bootstrap).
    image_to_probe: (4, 4) pixel -> probe mm. points_px: (N, 2) tracked points in the reference frame.
    displacement_px: (n, N, 2) tracked displacement from the reference frame (the lowest-lambda frame in contact,
    lambda >= 0), NaN where lost and in frames out of contact.
    reference_index: the reference frame. correlation: (len(CORRELATION_SEPARATIONS_MM), n) motion-compensated
    speckle correlation of frame i with frame correlation_partner[row, i] (NaN and -1 where it has none).
    vessel_area_mm2: (n,) segmented lumen area, NaN where no lumen was found.
    vessel_center_probe_mm: (2,) lumen centre (x, z) in the probe frame in the reference frame, or None.
    vessel_radius_mm: equivalent radius of the reference lumen, mm, or None.
    intensity_depth_mm: (bands,) centre depth of each intensity band; intensity: (n, bands) mean grey
    level per band outside the lumen. reference_frame, peak_frame: (rows, cols) the reference frame and the
    highest-force loading frame (index peak_index), for the correction outcome.
    row_profile_strips: (n, ROW_PROFILE_STRIPS, rows) mean grey level of every image row outside the lumen,
    in each of ROW_PROFILE_STRIPS equal lateral strips of the image apart (for the near-field band coherence).
    reference: the reflector fixed in the world of a reference-target recording and its image motion, or None.
    reference_note: why a reference-target recording's reflector was not found ("" when it was, or none was asked).
    """

    name: str
    time_s: np.ndarray
    force_n: np.ndarray
    probe_displacement_mm: np.ndarray
    phase: np.ndarray
    block: np.ndarray
    image_to_probe: np.ndarray
    frame_shape: tuple[int, int]
    points_px: np.ndarray
    displacement_px: np.ndarray
    reference_index: int
    correlation: np.ndarray
    correlation_partner: np.ndarray
    vessel_area_mm2: np.ndarray
    vessel_center_probe_mm: np.ndarray | None
    vessel_radius_mm: float | None
    intensity_depth_mm: np.ndarray
    intensity: np.ndarray
    reference_frame: np.ndarray | None = None
    peak_frame: np.ndarray | None = None
    peak_index: int = -1
    row_profile_strips: np.ndarray | None = None
    reference: ReferenceTrack | None = None
    reference_note: str = ""

    @property
    def n_frames(self) -> int:
        return len(self.time_s)

    @property
    def pixel_size_mm(self) -> tuple[float, float]:
        """(lateral, axial) size of a pixel, mm."""
        return pixel_size_mm(self.image_to_probe)

    def row_depth_mm(self, rows: np.ndarray | float) -> np.ndarray:
        """Depth below the probe face, mm, of pixel rows (fractional rows too)."""
        return self.image_to_probe[2, 1] * np.asarray(rows, dtype=float) + self.image_to_probe[2, 3]


def _phases(force: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Loading before the plateau around the deepest press, holding on it, unloading after it.

    The plateau is the contiguous run of frames around the peak within 5 % of the range of either
    the force (force-controlled holds) or lambda (position-controlled holds) from its maximum.
    """
    peak = int(np.argmax(lam))
    near = (lam >= lam.max() - 0.05 * np.ptp(lam)) | (force >= force.max() - 0.05 * np.ptp(force))
    start = peak
    while start > 0 and near[start - 1]:
        start -= 1
    end = peak
    while end < len(lam) - 1 and near[end + 1]:
        end += 1
    phase = np.ones(len(lam), dtype=np.int64)
    phase[:start] = 0
    phase[end + 1 :] = 2
    return phase


def _motion_compensated_correlation(
    first: np.ndarray, second: np.ndarray, structure_px: tuple[float, float] = (8.0, 8.0)
) -> float:
    """Speckle correlation of ``first`` with ``second`` warped back by their dense (Farneback) flow.

    Compensating the in-plane motion leaves the decorrelation by strain, noise and out-of-plane motion.
    Both frames are band-passed first, between Gaussian scales of ``_CORRELATION_SCALE_PX`` and
    ``structure_px`` (lateral, axial sigma, pixels):

    * the fine scale: the flow is smooth over its window and the warp interpolates, which leaves
      sub-pixel misregistration and interpolation smoothing that decorrelate the finest scale of a
      moving frame but not of a still one (a step of about 0.02 between still and moving simulated
      frames at full resolution, none at a 1-pixel scale);
    * the coarse scale removes what does not decorrelate: the depth profile of gain and attenuation,
      the vessel and other structure, which otherwise dominate the coefficient (0.99 between frames
      4 mm of indentation apart) and hide the speckle's own decorrelation.
    """
    flow = cv2.calcOpticalFlowFarneback(first, second, None, 0.5, 3, 21, 3, 5, 1.1, 0)  # type: ignore[call-overload, unused-ignore]
    rows, cols = first.shape
    flow += _pixel_grid(rows, cols)  # in place: the sampling positions of the warp
    reference, moving = (_speckle_band(frame, structure_px) for frame in (first, second))
    warped = cv2.remap(moving, flow, None, cv2.INTER_LINEAR)  # type: ignore[call-overload, unused-ignore]
    margin_r, margin_c = rows // 10, cols // 10
    a = reference[margin_r:-margin_r, margin_c:-margin_c].ravel()
    b = warped[margin_r:-margin_r, margin_c:-margin_c].ravel()
    a -= a.mean()
    b -= b.mean()
    denominator = np.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / denominator if denominator > 0 else np.nan


def _speckle_band(frame: np.ndarray, structure_px: tuple[float, float]) -> np.ndarray:
    """The frame band-passed between the fine correlation scale and ``structure_px``, float32."""
    values = frame.astype(np.float32)
    fine = cv2.GaussianBlur(values, (0, 0), _CORRELATION_SCALE_PX)
    return fine - cv2.GaussianBlur(values, (0, 0), sigmaX=structure_px[0], sigmaY=structure_px[1])


def correlation_partners(lam: np.ndarray) -> np.ndarray:
    """(len(CORRELATION_SEPARATIONS_MM), n) index of the earlier frame each frame is correlated with, -1 for none.

    Separation 0: the previous frame. Otherwise the earlier frame whose |lambda difference| is nearest
    the separation, if within ``_SEPARATION_TOLERANCE`` of it.
    """
    n = len(lam)
    partners = np.full((len(CORRELATION_SEPARATIONS_MM), n), -1, dtype=np.int64)
    for row, separation in enumerate(CORRELATION_SEPARATIONS_MM):
        if separation == 0:
            partners[row, 1:] = np.arange(n - 1)
            continue
        for index in range(1, n):
            miss = np.abs(np.abs(lam[index] - lam[:index]) - separation)
            nearest = int(np.argmin(miss))
            if miss[nearest] <= _SEPARATION_TOLERANCE * separation:
                partners[row, index] = nearest
    return partners


@functools.lru_cache(maxsize=4)
def _pixel_grid(rows: int, cols: int) -> np.ndarray:
    """(rows, cols, 2) float32 (column, row) of every pixel, read-only."""
    grid = np.stack(np.meshgrid(np.arange(cols, dtype=np.float32), np.arange(rows, dtype=np.float32)), axis=2)
    grid.flags.writeable = False
    return grid


def _probe_point(image_to_probe: np.ndarray, col_row: np.ndarray) -> np.ndarray:
    """Pixel coordinates (m, 2) -> probe-frame (x, z) in mm (m, 2)."""
    homogeneous = np.column_stack([col_row, np.zeros(len(col_row)), np.ones(len(col_row))])
    return (homogeneous @ image_to_probe.T)[:, [0, 2]]


def observe(
    recording: Recording,
    name: str = "recording",
    reference_depth_mm: float | None = None,
    find_reference: bool = False,
) -> Observation:
    """Extract the observation of one palpation recording (the slow part: tracking and correlation).

    A reflector fixed in the world (:mod:`usdeform.gap.reference_target`) is tracked when its depth below the
    unloaded surface is known (the header key ``ReferenceTargetDepth``, else ``reference_depth_mm``, as
    ``diagnose --reference-depth-mm`` gives it), or searched for when ``find_reference`` says the recording has one.
    A recording whose own header key names a reflector that is not found is used as a plain palpation, with the reason
    in ``reference_note``; one asked for by the option or ``find_reference`` is an input error. The tracked points and
    the intensity bands stop 2 mm above a reflector found: it and the shadow below it are no tissue.

    Raises InputError, naming ``name`` and the field, when the recording has no ContactForce or
    ProbeDisplacement, too few frames, a force that never rises, an image calibration that is not a scaled in-plane
    mapping, a ReferenceTargetDepth that is no positive number, or a reflector the option asks for that is not found.
    """
    in_header = REFERENCE_DEPTH_KEY in recording.metadata
    if in_header:
        text = recording.metadata[REFERENCE_DEPTH_KEY]
        try:
            reference_depth_mm = float(text)
        except ValueError:
            reference_depth_mm = float("nan")
        if not (np.isfinite(reference_depth_mm) and reference_depth_mm > 0):
            raise InputError(f"{name}: {REFERENCE_DEPTH_KEY}: expected a positive depth in mm, got {text!r}")
    if recording.force is None:
        raise InputError(f"{name}: no ContactForce field: the gap diagnosis needs the contact force of every frame")
    if recording.probe_displacement is None:
        raise InputError(f"{name}: no ProbeDisplacement field: the gap diagnosis needs lambda_z of every frame")
    n = recording.frames.shape[0]
    if n < MIN_FRAMES:
        raise InputError(f"{name}: frames: {n} frames, a palpation needs at least {MIN_FRAMES}")
    image_to_probe = np.asarray(recording.image_to_probe, dtype=np.float64)
    lateral, axial = image_to_probe[:3, 0], image_to_probe[:3, 1]
    if abs(lateral @ axial) > 1e-6 * np.linalg.norm(lateral) * np.linalg.norm(axial) or abs(lateral[1]) + abs(
        axial[1]
    ) > 1e-6 * (np.linalg.norm(lateral) + np.linalg.norm(axial)):
        raise InputError(
            f"{name}: ImageToProbeTransform: expected image columns and rows along probe x and z "
            "(an in-plane scaled calibration), got an inconsistent calibration"
        )
    force = np.asarray(recording.force, dtype=np.float64)
    lam = np.asarray(recording.probe_displacement, dtype=np.float64)
    if np.ptp(lam) <= 0.2:
        raise InputError(
            f"{name}: ProbeDisplacement: lambda varies by {np.ptp(lam):.3g} mm; a palpation needs > 0.2 mm"
        )
    if np.ptp(force) <= 0.5:
        raise InputError(f"{name}: ContactForce: the force varies by {np.ptp(force):.3g} N; a palpation needs > 0.5 N")
    time = np.asarray(recording.timestamps, dtype=np.float64)
    time = time - time[0]
    frames = recording.frames
    reference, reference_note = None, ""
    if reference_depth_mm is not None or find_reference:  # before the slow part: a missing reflector is an input error
        try:
            reference = track_reference(frames, lam, image_to_probe, name, reference_depth_mm)
        except InputError as exc:
            if not in_header:
                raise
            reference_note = f"{exc}; used as a plain palpation"

    try:
        tracks = track_palpation(frames, lam)
    except FitError as exc:
        raise InputError(f"{name}: frames: optical flow failed ({exc})") from None
    displacement = np.full((n, len(tracks.points_px), 2), np.nan)
    displacement[tracks.reference_index] = 0.0
    displacement[tracks.frame_indices] = tracks.displacements_px
    points, displacement, reference_index = _in_contact(np.asarray(tracks.points_px), displacement, lam, name)
    if reference is not None:  # points on the reflector or in its shadow move with the world, not the tissue
        reflector_mm = reference.world_depth_mm - reference.ratio * lam[reference_index]
        tissue = _probe_point(image_to_probe, points)[:, 1] < reflector_mm - _ABOVE_REFLECTOR_MM
        points, displacement = points[tissue], displacement[:, tissue]

    partners = correlation_partners(lam)
    lateral_mm, axial_mm = float(np.linalg.norm(lateral)), float(np.linalg.norm(axial))
    correlated_shape = (
        max(1, round(frames.shape[2] * min(1.0, lateral_mm / _CORRELATION_PIXEL_MM))),
        max(1, round(frames.shape[1] * min(1.0, axial_mm / _CORRELATION_PIXEL_MM))),
    )  # (cols, rows), as cv2.resize takes it

    correlated = frames
    if correlated_shape != (frames.shape[2], frames.shape[1]):  # each frame once: it is correlated several times
        correlated = np.stack([cv2.resize(frame, correlated_shape, interpolation=cv2.INTER_AREA) for frame in frames])
    structure_px = (
        _STRUCTURE_SCALE_MM / lateral_mm * correlated_shape[0] / frames.shape[2],
        _STRUCTURE_SCALE_MM / axial_mm * correlated_shape[1] / frames.shape[1],
    )
    correlation = np.full(partners.shape, np.nan)
    for row, index in zip(*np.nonzero(partners >= 0), strict=True):
        correlation[row, index] = _motion_compensated_correlation(
            correlated[partners[row, index]], correlated[index], structure_px
        )

    areas, center, radius = _vessel(frames, image_to_probe, reference_index)
    depth_mm, intensity, strips = _intensity_bands(frames, image_to_probe)
    if reference is not None:  # a band that reaches the reflector (2 mm above it) or its shadow is no tissue
        reflector_mm = np.where(np.isfinite(reference.depth_mm), reference.depth_mm, np.nanmin(reference.depth_mm))
        band_bottom_mm = depth_mm + 0.5 * np.ptp(depth_mm) / max(len(depth_mm) - 1, 1)
        intensity[band_bottom_mm[None, :] > reflector_mm[:, None] - _ABOVE_REFLECTOR_MM] = np.nan
    phase = _phases(force, lam)
    loading = np.flatnonzero(phase == 0)
    peak = int(loading[np.argmax(force[loading])]) if len(loading) else int(np.argmax(force))
    duration = max(time[-1], 1e-9)
    block = np.minimum((time / _BLOCK_S).astype(np.int64), int(duration / _BLOCK_S))
    return Observation(
        name=name,
        time_s=time,
        force_n=force,
        probe_displacement_mm=lam,
        phase=phase,
        block=np.unique(block, return_inverse=True)[1],
        image_to_probe=image_to_probe,
        frame_shape=(frames.shape[1], frames.shape[2]),
        points_px=points,
        displacement_px=displacement,
        reference_index=reference_index,
        correlation=correlation,
        correlation_partner=partners,
        vessel_area_mm2=areas,
        vessel_center_probe_mm=center,
        vessel_radius_mm=radius,
        intensity_depth_mm=depth_mm,
        intensity=intensity,
        reference_frame=np.array(frames[reference_index]),
        peak_frame=np.array(frames[peak]),
        peak_index=peak,
        row_profile_strips=strips,
        reference=reference,
        reference_note=reference_note,
    )


def _in_contact(
    points_px: np.ndarray, displacement_px: np.ndarray, lam: np.ndarray, name: str
) -> tuple[np.ndarray, np.ndarray, int]:
    """Tracks re-referenced to the lowest-lambda frame in contact (lambda >= 0), frames out of contact dropped.

    With lambda < 0 the probe is lifted off the tissue: such a frame says nothing about the deformation,
    and whether it shows the tissue shifted, unchanged or not at all depends on the coupling, not on
    the tissue. So the displacements are taken from the first frame in contact, and frames out of
    contact get NaN. Returns the points in the new reference frame (points lost there are dropped),
    the displacement (n, N', 2) and the new reference index.
    """
    in_contact = lam >= 0
    if not in_contact.any():
        raise InputError(f"{name}: ProbeDisplacement: every frame has lambda < 0; the probe never touches the tissue")
    reference = int(np.flatnonzero(in_contact)[np.argmin(lam[in_contact])])
    at_reference = displacement_px[reference]
    kept = np.isfinite(at_reference).all(axis=1)
    moved = displacement_px[:, kept] - at_reference[None, kept]
    moved[~in_contact] = np.nan
    return points_px[kept] + at_reference[kept], moved, reference


def _vessel(
    frames: np.ndarray, image_to_probe: np.ndarray, reference_index: int
) -> tuple[np.ndarray, np.ndarray | None, float | None]:
    """Lumen area per frame (NaN where none is found) and the reference lumen's centre and radius."""
    pixel_area = float(np.linalg.norm(image_to_probe[:3, 0]) * np.linalg.norm(image_to_probe[:3, 1]))
    areas = np.full(len(frames), np.nan)
    try:
        reference = segment_vessel(frames[reference_index])
    except (InputError, FitError):
        return areas, None, None
    seed = reference.ellipse_center_px
    for index, frame in enumerate(frames):
        try:
            segmentation = segment_vessel(frame, seed_px=seed)
        except (InputError, FitError):
            continue
        areas[index] = np.count_nonzero(segmentation.mask) * pixel_area
    rows, cols = np.nonzero(reference.mask)
    center = _probe_point(image_to_probe, np.array([[cols.mean(), rows.mean()]]))[0]
    radius = float(np.sqrt(np.count_nonzero(reference.mask) * pixel_area / np.pi))
    return areas, center, radius


def _intensity_bands(frames: np.ndarray, image_to_probe: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean grey level per depth band of every frame, leaving out dark (lumen) pixels of the band: band
    centre depths (bands,) mm, values (n, bands); and every row's mean in each lateral strip (n, strips, rows)."""
    rows = frames.shape[1]
    edges = np.linspace(0, rows, _INTENSITY_BANDS + 1).astype(int)
    centres_px = 0.5 * (edges[:-1] + edges[1:])
    depth_mm = _probe_point(image_to_probe, np.column_stack([np.zeros(len(centres_px)), centres_px]))[:, 1]
    smoothed = np.stack([cv2.GaussianBlur(frame, (0, 0), 3.0) for frame in frames]).astype(np.float64)
    tissue = smoothed > 0.5 * np.median(smoothed)
    values = np.full((len(frames), _INTENSITY_BANDS), np.nan)
    for band, (top, bottom) in enumerate(itertools.pairwise(edges)):
        mask = tissue[:, top:bottom]
        total = np.where(mask, frames[:, top:bottom], 0).sum(axis=(1, 2))
        count = mask.sum(axis=(1, 2))
        values[:, band] = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    strip_edges = np.linspace(0, frames.shape[2], ROW_PROFILE_STRIPS + 1).astype(int)
    strips = np.full((len(frames), ROW_PROFILE_STRIPS, rows), np.nan)
    for strip, (left, right) in enumerate(itertools.pairwise(strip_edges)):
        mask = tissue[:, :, left:right]
        total = np.where(mask, frames[:, :, left:right], 0).sum(axis=2)
        count = mask.sum(axis=2)
        strips[:, strip] = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return depth_mm, values, strips
