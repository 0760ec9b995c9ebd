"""The paper's 3D experiments (Section IV-B, Figs. 9 and 10) on the simulated phantoms.

For each phantom the pipeline is run as on a real system: palpations at ``n_palpations`` positions
equally spaced along the path (the ends included) give the stiffness profiles and the regression's
observations (:func:`usdeform.sampling.measure_positions`); force-controlled sweeps along the path
at each force are corrected with every model (:func:`usdeform.reconstruction.correct_recording`,
stiffness interpolated between the palpations or taken from the sweep's own force and probe
displacement) and compounded. The ground truth is the simulator's zero-force frames compounded at
the zero-force probe poses (the probe touching the unloaded surface, from the simulator's own
geometry, not from the package's).

Measured:

- per frame, on ``random_frames`` frames drawn per sweep: the vessel segmented
  (:func:`usdeform.metrics.segment_vessel`) in the deformed and the corrected frame against the one
  in the zero-force frame: centroid distance (mm), area difference (mm^2), Dice (paper Fig. 10);
- per volume: the lumen segmented slice by slice across the sweep (:func:`segment_volume_lumen`)
  against the truth lumen (the simulator's zero-force lumen masks compounded): lumen volume (mm^3),
  centre-line depth error (mm, :func:`centre_line_depth_mm`), 3-D Dice, and the lumen's extent in the
  coronal view at the true centre-line depth relative to the truth's (Fig. 9);
- per sweep frame: how far the interpolated stiffness misses the recorded displacement at the
  recorded force (the error the ``"sweep"`` stiffness source removes);
- why a corrected lumen is too small or large, by region (:func:`wall_errors_mm`): the model's
  displacement against the simulator's true field just outside the lumen's top, bottom, left and
  right walls, and in the tissue away from the vessel.

Volumes use the simulator's layout: the sweep runs along the base y axis and the probe axis along
base -z, so a volume slice at fixed y is an axial view and one at fixed z a coronal view.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from ..compounding import compound_frames, grid_for_frames
from ..errors import InputError
from ..hole_filling import PLUS_MIN_KNOWN_WEIGHT, HoleFillingElement
from ..io._common import atomic_output
from ..metrics import area_mm2, centroid_distance_mm, dice, pixel_size_mm, segment_vessel
from ..options import StiffnessSource
from ..propagation import SampledProfiles
from ..reconstruction import correct_recording, finish_volume, sweep_profiles
from ..recording import Recording
from ..regression import DisplacementModel, fit_regression
from ..sampling import measure_positions
from ..sim import (
    Effects,
    ForceSensorError,
    GroundTruth,
    ImageLatency,
    OutOfPlaneMotion,
    Phantom,
    Viscoelasticity,
    simulate_palpation,
    simulate_sweep,
    soft_phantom,
    stiff_phantom,
    truth_image_to_base,
)
from ..stiffness import StiffnessProfile
from ..volume import Volume, VoxelGrid
from .paper_2d import Method, Paper2dConfig, methods_for

__all__ = [
    "NUISANCES",
    "QUICK",
    "Paper3dConfig",
    "SweepCase",
    "centre_line_depth_mm",
    "compound_filled",
    "lumen_from_masks",
    "run_paper_3d",
    "segment_volume_lumen",
    "wall_errors_mm",
]

PRESETS: dict[str, Callable[[], Phantom]] = {"stiff": stiff_phantom, "soft": soft_phantom}


@dataclass(frozen=True)
class PhantomSweeps:
    """Sweeps over one phantom: the ``preset`` (``"stiff"``, ``"soft"``), its stiffness variation along
    s (None: the preset's), the path (start and length, mm), the number of palpations along it, their
    highest force (N), the sweep forces (N) and the simulator's nuisance ``effects`` on palpations and
    sweeps (None: an ideal system)."""

    label: str
    preset: str
    start_mm: float
    length_mm: float
    n_palpations: int
    palpation_force_n: float
    forces_n: tuple[float, ...]
    stiffness_amplitude: float | None = None
    effects: Effects | None = None


#: A real system's nuisances, each mid-range of :mod:`usdeform.sim.effects`: 30 ms image latency, a
#: 0.3 N force bias drifting 0.005 N/s, 10 % viscoelastic relaxation (1 s), out-of-plane tissue motion
#: (0.05 mm per mm of indentation plus 0.15 mm rms jitter: speckle decorrelation between frames).
NUISANCES = Effects(
    latency=ImageLatency(0.03),
    force_sensor=ForceSensorError(bias_n=0.3, drift_n_per_s=0.005),
    viscoelasticity=Viscoelasticity(((0.1, 1.0),)),
    out_of_plane=OutOfPlaneMotion(shift_mm_per_mm=0.05, jitter_mm=0.15),
)


@dataclass(frozen=True)
class Paper3dConfig:
    """What the experiments simulate. ``frame_spacing_mm``: sweep distance between frames;
    ``voxel_mm``: voxel size; ``mesh_size_mm`` overrides the presets' mesh (quick runs)."""

    rows: int = 256
    cols: int = 256
    palpation_frames: int = 40
    frame_spacing_mm: float = 0.5
    voxel_mm: float = 0.4
    random_frames: int = 10
    phantoms: tuple[PhantomSweeps, ...] = (
        PhantomSweeps("stiff", "stiff", 20.0, 40.0, 4, 30.0, (5.0, 10.0, 15.0, 20.0, 25.0)),
        PhantomSweeps("soft", "soft", 10.0, 60.0, 3, 16.0, (2.0, 4.0, 6.0, 8.0)),
        # The paper's stiff phantom barely varies along 40 mm (+/-4 %); tissue under a real sweep
        # varies more: the same phantom with +/-30 % along s, at 15 N, compares the stiffness sources
        # (palpated to 20 N: at its softest, 30 N would press beyond the solved 11 mm).
        PhantomSweeps("stiff, +/-30 % along s", "stiff", 20.0, 40.0, 4, 20.0, (15.0,), stiffness_amplitude=0.3),
        PhantomSweeps(
            "stiff, +/-30 % along s, nuisances",
            "stiff",
            20.0,
            40.0,
            4,
            20.0,
            (15.0,),
            stiffness_amplitude=0.3,
            effects=NUISANCES,
        ),
    )
    bspline_functions: tuple[int, int] = (8, 8)
    seed: int = 0
    mesh_size_mm: float | None = None


#: A small configuration for smoke tests: coarse mesh, small frames, short paths, few forces.
QUICK = Paper3dConfig(
    rows=96,
    cols=96,
    palpation_frames=20,
    frame_spacing_mm=1.0,
    voxel_mm=0.5,
    random_frames=3,
    phantoms=(
        PhantomSweeps("stiff", "stiff", 20.0, 12.0, 2, 30.0, (25.0,)),
        PhantomSweeps("soft", "soft", 20.0, 12.0, 2, 16.0, (8.0,)),
    ),
    mesh_size_mm=4.0,
)

#: Hole filling of the volumes: STICK, as PLUS's configurations use, over at most 4 voxels (the gaps
#: between frames, not the space beyond the sweep).
HOLE_FILLING = (HoleFillingElement("stick", stick_length_limit=4),)

#: The volumes Fig. 9 shows side by side.
VIEWED = ("truth", "deformed", "paper", "spline-lambda")

#: Stiffness sources compared (see :func:`usdeform.reconstruction.sweep_profiles`).
SOURCES: tuple[StiffnessSource, ...] = ("interpolated", "sweep")


def _variants(config: Paper3dConfig) -> tuple[Method, ...]:
    """The paper's comparison and its variants (methods fitted to tracked displacements only)."""
    return tuple(
        m
        for m in methods_for(Paper2dConfig(bspline_functions=config.bspline_functions))
        if not m.truth and m.name != "spline-force"
    )


def _variant_names(methods: tuple[Method, ...]) -> list[str]:
    """Every corrected variant: each method with interpolated stiffness, ``method/sweep`` with the sweep's."""
    return [m.name for m in methods] + [f"{m.name}/sweep" for m in methods if m.coupling == "stiffness"]


@dataclass
class SweepCase:
    """One sweep's results. ``frames``: per-frame metrics of the random frames, each a dict of variant
    name (``deformed``, a method, ``method/sweep``) to a list over the frames; ``volume``: per variant,
    the volume metrics; ``stiffness``: how far each source's profile misses the recorded lambda (mm);
    ``walls``: per variant, :func:`wall_errors_mm` averaged over the random frames."""

    phantom: str
    target_force_n: float
    n_frames: int
    force_range_n: tuple[float, float]
    probe_displacement_range_mm: tuple[float, float]
    frame_indices: list[int]
    frames: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    volume: dict[str, dict[str, float]] = field(default_factory=dict)
    stiffness: dict[str, dict[str, float]] = field(default_factory=dict)
    walls: dict[str, dict[str, float]] = field(default_factory=dict)


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


def _volume_metrics(lumen: np.ndarray, truth_lumen: np.ndarray, grid: VoxelGrid) -> dict[str, float]:
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


def _frame_metrics(
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


def _walls(
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


def _lambda_miss_mm(recording: Recording, profiles: np.ndarray) -> dict[str, float]:
    """How far each frame's profile puts the recorded force from the recorded probe displacement, mm."""
    assert recording.force is not None and recording.probe_displacement is not None
    lambdas = np.array([StiffnessProfile(*p).lambda_at(f) for p, f in zip(profiles, recording.force, strict=True)])
    miss = np.abs(lambdas - recording.probe_displacement)
    return {"mean_mm": float(np.nanmean(miss)), "max_mm": float(np.nanmax(miss))}


@dataclass
class _Fitted:
    phantom: Phantom
    sampled: SampledProfiles
    models: dict[str, DisplacementModel]


def _phantom(sweeps: PhantomSweeps, config: Paper3dConfig) -> Phantom:
    phantom = PRESETS[sweeps.preset]()
    if sweeps.stiffness_amplitude is not None:
        phantom = dataclasses.replace(phantom, stiffness_amplitude=sweeps.stiffness_amplitude)
    return phantom if config.mesh_size_mm is None else phantom.with_section_changes(mesh_size_mm=config.mesh_size_mm)


def _fit(sweeps: PhantomSweeps, config: Paper3dConfig, methods: tuple[Method, ...], seed: int) -> _Fitted:
    """Palpate the phantom along the path and fit every method."""
    phantom = _phantom(sweeps, config)
    positions = np.linspace(sweeps.start_mm, sweeps.start_mm + sweeps.length_mm, sweeps.n_palpations)
    palpations = [
        simulate_palpation(
            phantom,
            float(position),
            sweeps.palpation_force_n,
            n_frames=config.palpation_frames,
            seed=seed + number,
            effects=sweeps.effects,
            rows=config.rows,
            cols=config.cols,
        )[0]
        for number, position in enumerate(positions)
    ]
    measured, sampled = measure_positions(palpations, phantom.base_section.depth_mm)
    observations = [m.observations for m in measured]
    models = {
        m.name: fit_regression(observations, coupling=m.coupling, integration=m.integration, basis=m.basis).model
        for m in methods
    }
    return _Fitted(phantom, sampled, models)


@dataclass
class _Views:
    """What the figures show of one sweep: the lumen volumes and images of truth, deformed and each variant."""

    grid: VoxelGrid
    images: dict[str, np.ndarray]
    lumens: dict[str, np.ndarray]


def _run_sweep(
    sweeps: PhantomSweeps,
    fitted: _Fitted,
    force_n: float,
    config: Paper3dConfig,
    methods: tuple[Method, ...],
    seed: int,
) -> tuple[SweepCase, _Views]:
    n_frames = round(sweeps.length_mm / config.frame_spacing_mm) + 1
    recording, truth = simulate_sweep(
        fitted.phantom,
        sweeps.start_mm,
        sweeps.length_mm,
        force_n,
        n_frames=n_frames,
        seed=seed,
        effects=sweeps.effects,
        rows=config.rows,
        cols=config.cols,
    )
    assert recording.force is not None and recording.probe_displacement is not None
    rng = np.random.default_rng(seed)
    indices = np.sort(rng.choice(n_frames, size=min(config.random_frames, n_frames), replace=False))
    truth_poses = truth_image_to_base(truth, recording)
    grid = grid_for_frames(
        np.concatenate([truth_poses, recording.image_to_base]), recording.shape, config.voxel_mm, margin_mm=1.0
    )
    truth_lumen = lumen_from_masks(truth.zero_force_vessel_mask, truth_poses, grid, fill_holes=True)
    truth_volume, _ = compound_filled(truth.zero_force_frames, truth_poses, grid)
    case = SweepCase(
        sweeps.label,
        force_n,
        n_frames,
        (float(recording.force.min()), float(recording.force.max())),
        (float(recording.probe_displacement.min()), float(recording.probe_displacement.max())),
        indices.tolist(),
    )
    frames = {"deformed": recording.frames}
    poses = {"deformed": recording.image_to_base}
    masks: dict[str, np.ndarray] = {}  # the corrected frames' pixels that hold data
    profiles = {s: sweep_profiles(recording, fitted.sampled, stiffness_source=s) for s in SOURCES}
    case.stiffness = {source: _lambda_miss_mm(recording, profiles[source]) for source in SOURCES}
    variants: dict[str, tuple[DisplacementModel, np.ndarray]] = {}
    for method in methods:
        sources: tuple[StiffnessSource, ...] = SOURCES if method.coupling == "stiffness" else ("interpolated",)
        for source in sources:
            name = method.name if source == "interpolated" else f"{method.name}/sweep"
            model = fitted.models[method.name]
            corrected = correct_recording(recording, model, fitted.sampled, stiffness_source=source)
            assert corrected.pixel_valid is not None  # correct_recording marks the pixels holding data
            masks[name] = corrected.pixel_valid
            frames[name], poses[name] = corrected.frames, corrected.image_to_base
            variants[name] = (model, profiles[source])
    case.frames = _frame_metrics(frames, truth, indices, pixel_size_mm(recording.image_to_probe))
    case.walls = _walls(recording, truth, indices, variants)
    views = _Views(grid, {"truth": truth_volume.image}, {"truth": truth_lumen})
    for name in frames:
        volume, covered = compound_filled(frames[name], poses[name], grid, valid=masks.get(name))
        lumen = segment_volume_lumen(volume, truth_lumen, covered)
        case.volume[name] = _volume_metrics(lumen, truth_lumen, grid)
        views.images[name], views.lumens[name] = volume.image, lumen
    case.volume["truth"] = _volume_metrics(truth_lumen, truth_lumen, grid)
    return case, views


def run_paper_3d(output_dir: str | Path, config: Paper3dConfig = Paper3dConfig()) -> list[SweepCase]:
    """Run the sweeps of ``config``; write ``results.md``, ``results.json``, ``fig9_views.png`` and
    ``fig10_bars.png`` to ``output_dir``; return the cases."""
    output = Path(output_dir)
    output.mkdir(parents=True, exist_ok=True)
    methods = _variants(config)
    names = ["deformed", *_variant_names(methods)]
    cases: list[SweepCase] = []
    views: dict[str, _Views] = {}
    total = sum(len(p.forces_n) + 1 for p in config.phantoms)
    with tqdm(total=total, desc="paper-3d", unit="step") as progress:
        for number, sweeps in enumerate(config.phantoms):
            seed = config.seed + 1000 * number
            progress.set_postfix_str(f"{sweeps.label}: palpations and fits")
            fitted = _fit(sweeps, config, methods, seed)
            progress.update()
            for force_number, force in enumerate(sweeps.forces_n):
                progress.set_postfix_str(f"{sweeps.label}: sweep at {force:g} N")
                case, sweep_views = _run_sweep(sweeps, fitted, force, config, methods, seed + 100 + force_number)
                cases.append(case)
                _write_results(cases, config, methods, names, output)  # a cut-off run keeps what it measured
                if sweeps.stiffness_amplitude is None and force == max(sweeps.forces_n):  # Fig. 9 shows these
                    views[f"{sweeps.label}, {force:g} N"] = _Views(
                        sweep_views.grid,
                        {name: sweep_views.images[name] for name in VIEWED},
                        {name: sweep_views.lumens[name] for name in VIEWED},
                    )
                progress.update()
    plotted = [p for p in config.phantoms if p.stiffness_amplitude is None]  # the paper's phantoms
    if plotted:
        _plot_views(views, output / "fig9_views.png")
        _plot_bars(cases, plotted, output / "fig10_bars.png")
    return cases


def _nanmax(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(max(finite)) if finite else float("nan")


def _nanmean_abs(values: list[float]) -> float:
    finite = [abs(v) for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def _write_results(
    cases: list[SweepCase], config: Paper3dConfig, methods: tuple[Method, ...], names: list[str], output: Path
) -> None:
    lines = [
        "# The paper's 3D experiments on the simulated phantoms",
        "",
        f"Frames {config.rows} x {config.cols}, {config.palpation_frames}-frame palpations, sweep frames every "
        f"{config.frame_spacing_mm:g} mm, voxels {config.voxel_mm:g} mm, {config.random_frames} random frames per "
        "sweep. Truth: the simulator's zero-force frames and lumen masks at the zero-force probe poses. "
        "Volumes: nearest-neighbour mean compounding (corrected pixels sampled from outside their frame left "
        "out), gaps between frames filled (STICK, sticks up to 4 voxels). "
        "Variants (`/sweep`: stiffness from the sweep's own force and probe displacement instead of the "
        "inverse-distance interpolation between palpations):",
        "",
        "- `deformed`: no correction, at the recorded poses",
    ]
    lines += [f"- `{m.name}`: {m.description}" for m in methods]
    lines += [
        "",
        "## Per frame (Fig. 10): max centroid distance (mm) / mean |area difference| (mm^2) / mean Dice",
        "",
        "| phantom | force (N) | " + " | ".join(names) + " |",
        "|---" * (len(names) + 2) + "|",
    ]
    for c in cases:
        cells = [
            f"{_nanmax(c.frames[n]['centroid_mm']):.2f} / {_nanmean_abs(c.frames[n]['area_diff_mm2']):.1f} / "
            f"{np.mean(c.frames[n]['dice']) if c.frames[n]['dice'] else float('nan'):.3f}"
            for n in names
        ]
        lines.append(f"| {c.phantom} | {c.target_force_n:g} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Area reduction and spread across forces",
        "",
        "Area difference cut: 1 - mean |area diff| corrected / deformed over the phantom's frames; "
        "SD of the mean corrected area across forces (mm^2).",
        "",
        "| phantom | " + " | ".join(f"{n} cut / SD" for n in names[1:]) + " | deformed SD |",
        "|---" * (len(names) + 1) + "|",
    ]
    for phantom in dict.fromkeys(c.phantom for c in cases):
        rows = [c for c in cases if c.phantom == phantom]

        def spread(name: str, rows: list[SweepCase] = rows) -> float:
            means = [np.nanmean(c.frames[name]["area_mm2"]) for c in rows if c.frames[name]["area_mm2"]]
            return float(np.std(means)) if len(means) > 1 else float("nan")

        deformed = np.mean([_nanmean_abs(c.frames["deformed"]["area_diff_mm2"]) for c in rows])
        cells = []
        for name in names[1:]:
            corrected = np.mean([_nanmean_abs(c.frames[name]["area_diff_mm2"]) for c in rows])
            cells.append(f"{100 * (1 - corrected / deformed):.0f} % / {spread(name):.1f}")
        lines.append(f"| {phantom} | " + " | ".join(cells) + f" | {spread('deformed'):.1f} |")
    lines += [
        "",
        "## Volume (Fig. 9): lumen volume error (%) / centre-line depth error mean, max (mm) / 3-D Dice / "
        "coronal extent (fraction of the truth's)",
        "",
        "| phantom | force (N) | truth volume (mm^3) | " + " | ".join(names) + " |",
        "|---" * (len(names) + 3) + "|",
    ]
    for c in cases:
        cells = [
            f"{v['volume_error_pct']:+.0f} / {v['depth_error_mean_mm']:+.2f}, {v['depth_error_max_mm']:.2f} / "
            f"{v['dice']:.3f} / {v['coronal_extent_ratio']:.2f}"
            for v in (c.volume[n] for n in names)
        ]
        lines.append(
            f"| {c.phantom} | {c.target_force_n:g} | {c.volume['truth']['volume_mm3']:.0f} | "
            + " | ".join(cells)
            + " |"
        )
    lines += [
        "",
        "## Stiffness: |lambda at the recorded force - recorded lambda| over the sweep (mm), mean / max",
        "",
        "| phantom | force (N) | force range (N) | lambda range (mm) | interpolated | sweep |",
        "|---|---|---|---|---|---|",
    ]
    for c in cases:
        lines.append(
            f"| {c.phantom} | {c.target_force_n:g} | {c.force_range_n[0]:.1f}-{c.force_range_n[1]:.1f} | "
            f"{c.probe_displacement_range_mm[0]:.2f}-{c.probe_displacement_range_mm[1]:.2f} | "
            + " | ".join(f"{c.stiffness[s]['mean_mm']:.2f} / {c.stiffness[s]['max_mm']:.2f}" for s in SOURCES)
            + " |"
        )
    lines += [
        "",
        "## Why a lumen ends too small or large, by region (mean over the random frames, mm)",
        "",
        "Signed error of the displacement (model minus true) just outside each wall; a corrected wall "
        "lands at its true place minus that error, so the corrected lumen height is off by top - bottom "
        "and its width by left - right. `elsewhere`: mean error magnitude in the tissue more than two "
        "lumen radii from the vessel. `deformed`: no correction (the error is minus the true field).",
        "",
        "| phantom | force (N) | variant | top | bottom | left | right | height error | width error | elsewhere |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in cases:
        for name in names:
            if name in c.walls:
                w = c.walls[name]
                lines.append(
                    f"| {c.phantom} | {c.target_force_n:g} | {name} | {w['top']:+.2f} | {w['bottom']:+.2f} | "
                    f"{w['left']:+.2f} | {w['right']:+.2f} | {w['height_error_mm']:+.2f} | "
                    f"{w['width_error_mm']:+.2f} | {w['elsewhere_mm']:.2f} |"
                )
    with atomic_output(output / "results.md") as handle:
        handle.write(("\n".join(lines) + "\n").encode())
    payload = {"config": asdict(config), "variants": names, "cases": [asdict(c) for c in cases]}
    with atomic_output(output / "results.json") as handle:
        handle.write(json.dumps(payload, indent=1, default=float).encode())


def _plot_views(views: dict[str, _Views], path: Path) -> None:
    """Fig. 9: axial (middle y slice) and coronal (true centre-line depth) views of truth, deformed and
    two corrections, per phantom at its highest force, lumen contours overlaid; as in the paper, a
    dashed line marks where the other view cuts (blue: the coronal plane, red: the axial one)."""
    figure = Figure(figsize=(3.0 * len(VIEWED), 2.8 * 2 * len(views)))
    axes = figure.subplots(2 * len(views), len(VIEWED), squeeze=False)
    for number, (title, view) in enumerate(views.items()):
        truth_depth = centre_line_depth_mm(view.lumens["truth"], view.grid)
        slices = np.flatnonzero(np.isfinite(truth_depth))
        y = int(slices[len(slices) // 2])
        origin, step = view.grid.index_to_world[2, 3], view.grid.index_to_world[2, 2]
        z = int(np.clip(np.rint((np.nanmean(truth_depth) - origin) / step), 0, view.grid.shape[0] - 1))
        for column, name in enumerate(VIEWED):
            for row, (image, lumen, kind, cut, colour) in enumerate(
                (
                    # axial rows flipped so that the probe is on top: the coronal plane is at row nz-1-z
                    (
                        view.images[name][::-1, y, :],
                        view.lumens[name][::-1, y, :],
                        "axial",
                        view.grid.shape[0] - 1 - z,
                        "C0",
                    ),
                    (view.images[name][z, :, :], view.lumens[name][z, :, :], "coronal", y, "C3"),
                )
            ):
                axis = axes[2 * number + row, column]
                axis.imshow(image, cmap="gray", vmin=0, vmax=255)
                if lumen.any():
                    axis.contour(lumen.astype(float), levels=[0.5], colors=["lime"], linewidths=0.8)
                axis.axhline(cut, color=colour, linestyle="--", linewidth=0.8)
                axis.set_title(f"{title}: {name}, {kind}", fontsize=7)
                axis.axis("off")
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def _plot_bars(cases: list[SweepCase], phantoms: list[PhantomSweeps], path: Path) -> None:
    """Fig. 10: per phantom and force, (left) the centroid distance of the deformed and corrected frames
    to the zero-force frame's, mean over the random frames with the maximum marked, and (right) the
    vessel cross-section area of the zero-force (truth), deformed and corrected frames, mean and SD."""
    shown = ("deformed", "paper", "spline-lambda")
    figure = Figure(figsize=(11, 3.4 * len(phantoms)))
    axes = figure.subplots(len(phantoms), 2, squeeze=False)
    for row, sweeps in enumerate(phantoms):
        rows = [c for c in cases if c.phantom == sweeps.label]
        forces = np.arange(len(rows))
        labels = [f"{c.target_force_n:g} N" for c in rows]
        centroid, area = axes[row]
        width = 0.8 / len(shown)
        for number, name in enumerate(shown):
            at = forces + (number - (len(shown) - 1) / 2) * width
            distances = [np.asarray(c.frames[name]["centroid_mm"], dtype=float) for c in rows]
            centroid.bar(at, [np.nanmean(d) for d in distances], width, label=f"{name} (mean)", color=f"C{number + 1}")
            centroid.plot(at, [np.nanmax(d) for d in distances], "v", color="k", markersize=4)
        centroid.plot([], [], "v", color="k", markersize=4, label="maximum")
        centroid.set_xticks(forces, labels)
        centroid.set(title=f"{sweeps.label} phantom: vessel centroid distance", ylabel="distance to truth (mm)")
        centroid.legend(fontsize=7)
        width = 0.8 / (len(shown) + 1)
        for number, name in enumerate(("truth", *shown)):
            at = forces + (number - len(shown) / 2) * width
            areas = [_areas(c, name) for c in rows]
            area.bar(
                at,
                [np.nanmean(a) for a in areas],
                width,
                yerr=[np.nanstd(a) for a in areas],
                capsize=2,
                label=name,
                color=f"C{number}",
            )
        area.set_xticks(forces, labels)
        area.set(title=f"{sweeps.label} phantom: vessel cross-section area", ylabel="area (mm$^2$)")
        area.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def _areas(case: SweepCase, name: str) -> np.ndarray:
    """Vessel areas (mm^2) over the random frames of ``name`` (a variant or ``"truth"``, the zero-force
    frames' area: any variant's area minus its difference to the truth)."""
    if name != "truth":
        return np.asarray(case.frames[name]["area_mm2"], dtype=float)
    deformed = case.frames["deformed"]
    return np.asarray(deformed["area_mm2"], dtype=float) - np.asarray(deformed["area_diff_mm2"], dtype=float)
