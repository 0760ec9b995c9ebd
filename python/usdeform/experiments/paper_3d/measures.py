"""What the paper-3d experiments measure: per-frame vessel metrics, lumen volumes, centre lines and wall errors."""

from __future__ import annotations

import numpy as np

from ...errors import InputError
from ...metrics import area_mm2, centroid_distance_mm, dice, pixel_size_mm, segment_vessel
from ...recording import Recording
from ...regression import DisplacementModel, StiffnessProfile
from ...sim import GroundTruth, truth_image_to_base
from ...volume import PLUS_MIN_KNOWN_WEIGHT, Volume, VoxelGrid, compound_frames, finish_volume, grid_for_frames
from .config import HOLE_FILLING, Views

__all__ = [
    "centre_line_depth_mm",
    "compound_filled",
    "frame_metrics",
    "lambda_miss_mm",
    "lumen_from_masks",
    "measure_variants",
    "segment_volume_lumen",
    "variant_walls",
    "volume_metrics",
    "wall_errors_mm",
]


def compound_filled(
    frames: np.ndarray, image_to_base: np.ndarray, grid: VoxelGrid, *, valid: np.ndarray | None = None
) -> tuple[Volume, np.ndarray]:
    """Frames compounded (nearest, mean) on ``grid``, pixels whose ``valid`` flag is False left out
    (the corrected frames' pixels sampled from outside the frame), and the gaps between them filled as
    PLUS's configurations do (:data:`HOLE_FILLING`); returns the volume and where it holds a value,
    ``(z, y, x)`` bool (covered, or filled with a non-zero value)."""
    volume = compound_frames(frames, image_to_base, grid, valid=valid)
    assert volume.weight is not None  # a Compounder's volume has its weight
    filled = finish_volume(volume, hole_filling=HOLE_FILLING)
    return filled, (volume.weight >= PLUS_MIN_KNOWN_WEIGHT) | (filled.image != 0)


def lumen_from_masks(
    masks: np.ndarray, image_to_base: np.ndarray, grid: VoxelGrid, *, fill_holes: bool = False
) -> np.ndarray:
    """``(z, y, x)`` bool lumen: per-frame lumen masks compounded (mean) on ``grid`` (the gaps between
    frames filled with ``fill_holes``, as :func:`compound_filled`), where at least half of the pixels
    landing in a voxel are lumen."""
    if fill_holes:
        return compound_filled(masks.astype(np.float32), image_to_base, grid)[0].image >= 0.5
    volume = compound_frames(masks.astype(np.float32), image_to_base, grid)
    assert volume.weight is not None  # a Compounder's volume has its weight
    return (volume.image >= 0.5) & (volume.weight > 0)


def segment_volume_lumen(volume: Volume, seed_lumen: np.ndarray, covered: np.ndarray | None = None) -> np.ndarray:
    """The vessel lumen of a compounded volume, ``(z, y, x)`` bool, segmented slice by slice across the
    sweep (each y slice an axial view) with :func:`~usdeform.metrics.segment_vessel`.

    Parameters
    ----------
    volume : Volume
        The compounded volume; uncovered voxels take the median of the slice.
    seed_lumen : ndarray
        ``(z, y, x)`` bool: where the lumen is expected; its centroid in each slice seeds the
        segmentation, and slices where it is empty are skipped.
    covered : ndarray, optional
        ``(z, y, x)`` bool: the voxels holding a value (default: coverage weight above 0).

    Returns
    -------
    ndarray
        ``(z, y, x)`` bool; empty in slices where no lumen was found.
    """
    if covered is None:
        if volume.weight is None:
            raise InputError("volume: needs its coverage weight, or covered, to tell uncovered voxels")
        covered = volume.weight > 0
    lumen = np.zeros(volume.grid.shape, dtype=bool)
    for y in range(volume.grid.shape[1]):
        in_slice = covered[:, y, :]
        expected = seed_lumen[:, y, :]
        if not expected.any() or in_slice.sum() < 100:
            continue
        values = volume.image[:, y, :]
        axial = np.where(in_slice, values, np.median(values[in_slice])).astype(np.float32)
        z, x = np.argwhere(expected).mean(axis=0)
        try:
            lumen[:, y, :] = segment_vessel(axial, seed_px=(float(x), float(z))).mask
        except InputError:
            continue  # no lumen in this slice: counts as missed
    return lumen


def centre_line_depth_mm(lumen: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """World z (mm) of the lumen's centroid in each y slice, ``(y,)``; NaN where the slice holds none."""
    counts = lumen.sum(axis=(0, 2))
    z_index = np.arange(lumen.shape[0], dtype=np.float64)
    mean_z = (lumen.sum(axis=2) * z_index[:, np.newaxis]).sum(axis=0) / np.maximum(counts, 1)
    origin, step = grid.index_to_world[2, 3], grid.index_to_world[2, 2]
    return np.where(counts > 0, origin + step * mean_z, np.nan)


def _coronal_extent_mm2(lumen: np.ndarray, truth_depth_mm: np.ndarray, grid: VoxelGrid) -> float:
    """Lumen area (mm^2) in the coronal surface through the true centre line (one z per y slice)."""
    origin, step = grid.index_to_world[2, 3], grid.index_to_world[2, 2]
    area = 0.0
    for y, depth in enumerate(truth_depth_mm):
        if np.isfinite(depth):
            z = int(np.clip(np.rint((depth - origin) / step), 0, lumen.shape[0] - 1))
            area += float(lumen[z, y, :].sum())
    return area * abs(grid.index_to_world[0, 0] * grid.index_to_world[1, 1])


def volume_metrics(lumen: np.ndarray, truth_lumen: np.ndarray, grid: VoxelGrid) -> dict[str, float]:
    truth_depth = centre_line_depth_mm(truth_lumen, grid)
    depth_error = centre_line_depth_mm(lumen, grid) - truth_depth
    compared = np.isfinite(truth_depth)
    voxel_mm3 = float(abs(np.linalg.det(grid.index_to_world[:3, :3])))
    found = np.isfinite(depth_error) & compared
    truth_extent = _coronal_extent_mm2(truth_lumen, truth_depth, grid)
    return {
        "volume_mm3": float(lumen.sum() * voxel_mm3),
        "volume_error_pct": float(100.0 * (lumen.sum() / max(truth_lumen.sum(), 1) - 1.0)),
        "dice": dice(lumen.reshape(lumen.shape[0], -1), truth_lumen.reshape(lumen.shape[0], -1)),  # 3-D
        "depth_error_mean_mm": float(np.mean(depth_error[found])) if found.any() else float("nan"),
        "depth_error_max_mm": float(np.max(np.abs(depth_error[found]))) if found.any() else float("nan"),
        "slices_found": float(found.sum() / max(compared.sum(), 1)),
        "coronal_extent_ratio": _coronal_extent_mm2(lumen, truth_depth, grid) / max(truth_extent, 1e-9),
    }


def _segment(frame: np.ndarray, seed_px: tuple[float, float] | None) -> np.ndarray:
    """The vessel mask, or an empty mask when no lumen is found (a failed correction)."""
    try:
        return segment_vessel(frame, seed_px=seed_px).mask
    except InputError:
        return np.zeros(frame.shape, dtype=bool)


def frame_metrics(
    frames: dict[str, np.ndarray], truth: GroundTruth, indices: np.ndarray, pixel_size: tuple[float, float]
) -> dict[str, dict[str, list[float]]]:
    """Centroid distance (mm), area difference (mm^2, frame minus zero force) and Dice of each variant's
    frames (``(n_frames, rows, cols)`` each) against the zero-force frame, at ``indices``."""
    result: dict[str, dict[str, list[float]]] = {
        name: {"centroid_mm": [], "area_diff_mm2": [], "area_mm2": [], "dice": []} for name in frames
    }
    for index in indices:
        reference = _segment(truth.zero_force_frames[index], None)
        if not reference.any():
            continue
        row, col = np.argwhere(reference).mean(axis=0)
        for name, stack in frames.items():
            mask = _segment(stack[index], (float(col), float(row)))
            row_of = result[name]
            row_of["dice"].append(dice(mask, reference) if mask.any() else 0.0)
            row_of["centroid_mm"].append(
                centroid_distance_mm(mask, reference, pixel_size) if mask.any() else float("nan")
            )
            row_of["area_mm2"].append(area_mm2(mask, pixel_size) if mask.any() else float("nan"))
            row_of["area_diff_mm2"].append(
                area_mm2(mask, pixel_size) - area_mm2(reference, pixel_size) if mask.any() else float("nan")
            )
    return result


def wall_errors_mm(
    displacement_px: np.ndarray, true_displacement_px: np.ndarray, lumen: np.ndarray, pixel_size: tuple[float, float]
) -> dict[str, float]:
    """Where a displacement field errs around a vessel, and what that does to the corrected lumen.

    With backward mapping a corrected wall lands at its true place minus the field's error there
    (to first order), so the corrected lumen's height is off by ``error(top) - error(bottom)`` (axial
    components) and its width by ``error(left) - error(right)`` (lateral components).

    Parameters
    ----------
    displacement_px : ndarray
        ``(2, rows, cols)`` model displacement (lateral, axial), pixels (zeros: no correction).
    true_displacement_px : ndarray
        ``(rows, cols, 2)`` the simulator's field (:class:`~usdeform.sim.GroundTruth`), NaN outside tissue.
    lumen : ndarray
        ``(rows, cols)`` bool zero-force lumen.
    pixel_size : tuple of float
        ``(lateral, axial)`` mm per pixel.

    Returns
    -------
    dict
        Mean signed errors (mm) just outside each wall (``top``, ``bottom``: axial; ``left``, ``right``:
        lateral), ``height_error_mm``, ``width_error_mm`` and ``elsewhere_mm``, the mean error magnitude
        in the tissue more than two lumen radii from the vessel.
    """
    true_field = np.moveaxis(true_displacement_px.astype(np.float64), -1, 0)
    error_mm = (displacement_px - true_field) * np.array(pixel_size)[:, np.newaxis, np.newaxis]
    rows, cols = lumen.shape
    walls: dict[str, list[float]] = {"top": [], "bottom": [], "left": [], "right": []}
    for col in np.flatnonzero(lumen.any(axis=0)):
        inside = np.flatnonzero(lumen[:, col])
        if inside[0] > 0:
            walls["top"].append(error_mm[1, inside[0] - 1, col])
        if inside[-1] < rows - 1:
            walls["bottom"].append(error_mm[1, inside[-1] + 1, col])
    for row in np.flatnonzero(lumen.any(axis=1)):
        inside = np.flatnonzero(lumen[row])
        if inside[0] > 0:
            walls["left"].append(error_mm[0, row, inside[0] - 1])
        if inside[-1] < cols - 1:
            walls["right"].append(error_mm[0, row, inside[-1] + 1])
    result = {name: float(np.nanmean(values)) if values else float("nan") for name, values in walls.items()}
    centre = np.argwhere(lumen).mean(axis=0)
    radius = np.sqrt(lumen.sum() / np.pi)
    row_index, col_index = np.mgrid[0:rows, 0:cols]
    far = (np.hypot(row_index - centre[0], col_index - centre[1]) > 2 * radius) & np.all(
        np.isfinite(true_field), axis=0
    )
    result["height_error_mm"] = result["top"] - result["bottom"]
    result["width_error_mm"] = result["left"] - result["right"]
    result["elsewhere_mm"] = float(np.linalg.norm(error_mm[:, far], axis=0).mean()) if far.any() else float("nan")
    return result


def variant_walls(
    recording: Recording,
    truth: GroundTruth,
    indices: np.ndarray,
    models: dict[str, tuple[DisplacementModel, np.ndarray]],
) -> dict[str, dict[str, float]]:
    """:func:`wall_errors_mm` of each variant (model and per-frame profiles) and of no correction,
    averaged over the frames at ``indices``."""
    assert recording.force is not None
    pixel_size = pixel_size_mm(recording.image_to_probe)
    per_frame: dict[str, list[dict[str, float]]] = {name: [] for name in ("deformed", *models)}
    for index in indices:
        lumen = truth.zero_force_vessel_mask[index]
        if not lumen.any():
            continue
        true_field = truth.displacement_px[index]
        per_frame["deformed"].append(wall_errors_mm(np.zeros((2, *lumen.shape)), true_field, lumen, pixel_size))
        for name, (model, profiles) in models.items():
            field_px = model.displacement(
                float(recording.force[index]), StiffnessProfile(*profiles[index]), lumen.shape
            )
            per_frame[name].append(wall_errors_mm(field_px, true_field, lumen, pixel_size))
    return {
        name: {key: float(np.nanmean([row[key] for row in rows])) for key in rows[0]}
        for name, rows in per_frame.items()
        if rows
    }


def lambda_miss_mm(recording: Recording, profiles: np.ndarray) -> dict[str, float]:
    """How far each frame's profile puts the recorded force from the recorded probe displacement, mm."""
    assert recording.force is not None and recording.probe_displacement is not None
    lambdas = np.array([StiffnessProfile(*p).lambda_at(f) for p, f in zip(profiles, recording.force, strict=True)])
    miss = np.abs(lambdas - recording.probe_displacement)
    return {"mean_mm": float(np.nanmean(miss)), "max_mm": float(np.nanmax(miss))}


def measure_variants(
    recording: Recording, truth: GroundTruth, corrected: dict[str, Recording], indices: np.ndarray, voxel_mm: float
) -> tuple[dict[str, dict[str, list[float]]], dict[str, dict[str, float]], Views]:
    """The deformed sweep and its corrections against the simulator's zero-force truth.

    Parameters
    ----------
    recording, truth : Recording, GroundTruth
        The simulated sweep and its truth.
    corrected : dict of str to Recording
        Each variant's corrected sweep (:func:`~usdeform.correction.correct_recording`).
    indices : ndarray
        The frames whose per-frame metrics are measured.
    voxel_mm : float
        Voxel size of the volumes, mm.

    Returns
    -------
    tuple
        :func:`frame_metrics` of ``deformed`` and every variant at ``indices``; :func:`volume_metrics` of
        each and of ``truth``; the volumes and lumens (:class:`Views`).
    """
    truth_poses = truth_image_to_base(truth, recording)
    grid = grid_for_frames(
        np.concatenate([truth_poses, recording.image_to_base]), recording.shape, voxel_mm, margin_mm=1.0
    )
    truth_lumen = lumen_from_masks(truth.zero_force_vessel_mask, truth_poses, grid, fill_holes=True)
    truth_volume, _ = compound_filled(truth.zero_force_frames, truth_poses, grid)
    frames = {"deformed": recording.frames} | {name: c.frames for name, c in corrected.items()}
    poses = {"deformed": recording.image_to_base} | {name: c.image_to_base for name, c in corrected.items()}
    masks = {name: c.pixel_valid for name, c in corrected.items()}  # the corrected pixels that hold data
    per_frame = frame_metrics(frames, truth, indices, pixel_size_mm(recording.image_to_probe))
    views = Views(grid, {"truth": truth_volume.image}, {"truth": truth_lumen})
    volumes: dict[str, dict[str, float]] = {}
    for name in frames:
        volume, covered = compound_filled(frames[name], poses[name], grid, valid=masks.get(name))
        lumen = segment_volume_lumen(volume, truth_lumen, covered)
        volumes[name] = volume_metrics(lumen, truth_lumen, grid)
        views.images[name], views.lumens[name] = volume.image, lumen
    volumes["truth"] = volume_metrics(truth_lumen, truth_lumen, grid)
    return per_frame, volumes, views
