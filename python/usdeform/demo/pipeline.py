"""The demo's pipeline: simulate, measure, fit, sweep, correct, compound and score against the truth.

Every stage is the package's own (:mod:`usdeform.sim`, :func:`usdeform.fitting.measure_positions`,
:func:`usdeform.regression.fit_regression`, :func:`usdeform.correction.correct_recording`,
:class:`usdeform.volume.Compounder`, :mod:`usdeform.metrics`); this module only chains them the
way a user with a robot would, keeps the simulator's ground truth beside them, and times each stage.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from collections.abc import Callable, Iterable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from .._files import atomic_output
from ..compensation import apply_compensation, compensation_option
from ..correction import SampledProfiles, correct_recording, sweep_profiles
from ..correction._frames import correct_like
from ..errors import InputError, UsdeformError
from ..fitting import FIT_METHODS, SampledPosition, fit_measured, measure_positions
from ..gap import diagnose
from ..gap.report import write_text
from ..io import fit_provenance, save_model, write_sequence, write_volume
from ..metrics import area_mm2, centroid_distance_mm, dice, pixel_size_mm
from ..recording import Recording
from ..regression import DeformationModel, RegressionFit
from ..sim import (
    GroundTruth,
    Phantom,
    simulate_palpation,
    simulate_sweep,
    truth_image_to_base,
)
from ..sim.mechanics import cache_dir
from ..sim.recordings import DEFAULT_SURFACE_TO_BASE
from ..volume import Compounder, Volume, VoxelGrid, grid_for_frames
from .config import PRESETS, DemoConfig, DemoResult, EffectOutcome, FrameMetrics, VolumeMetrics

__all__ = ["run_demo"]


@contextlib.contextmanager
def _timed(timings: dict[str, float], stage: str) -> Iterator[None]:
    start = time.perf_counter()
    yield
    timings[stage] = timings.get(stage, 0.0) + time.perf_counter() - start


def _bar(iterable, description: str, *, show: bool = True):
    """A tqdm bar on stderr for one stage."""
    return tqdm(iterable, desc=description, unit="step", leave=False, disable=not show)


def _knots_used(phantom: Phantom, lower_mm: float, upper_mm: float) -> np.ndarray:
    """The geometry knots whose solves the positions in [lower_mm, upper_mm] blend."""
    knots = phantom.knot_positions_mm
    first = knots[knots <= lower_mm].max()
    last = knots[knots >= upper_mm].min()
    return knots[(knots >= first) & (knots <= last)]


#: FEM solutions of the default demo (soft preset, 3 mm mesh), shipped with the package so that a fresh
#: install skips its solves (about a minute on 2 cores); :func:`run_demo` copies them into the normal
#: solution cache (:func:`usdeform.sim.mechanics.cache_dir`), named by their cache key, which hashes every
#: parameter and the solver version: a changed phantom or solver misses them and solves as usual.
SHIPPED_SOLUTIONS = Path(__file__).parent / "solutions"


def solution_keys(phantom: Phantom, lower_mm: float, upper_mm: float) -> list[str]:
    """Cache keys of the knot solves the positions in [lower_mm, upper_mm] of ``phantom`` use."""
    lam = phantom.probe_displacement_mm
    return [
        phantom.unscaled_section_at(float(knot)).cache_key(lam) for knot in _knots_used(phantom, lower_mm, upper_mm)
    ]


def _seed_solution_cache(keys: list[str]) -> None:
    """Copy the shipped solutions among ``keys`` that the solution cache lacks into it (atomically)."""
    for key in keys:
        shipped, cached = SHIPPED_SOLUTIONS / f"{key}.npz", cache_dir() / f"{key}.npz"
        if shipped.exists() and not cached.exists():
            cached.parent.mkdir(parents=True, exist_ok=True)
            with atomic_output(cached) as handle:
                handle.write(shipped.read_bytes())


def _frame_metrics(sweep: Recording, truth: GroundTruth, corrected_masks: dict[str, np.ndarray]) -> FrameMetrics:
    """Dice, area error and centroid error of the deformed and of each corrected lumen, frame by frame."""
    pixel = pixel_size_mm(sweep.image_to_probe)
    references = truth.zero_force_vessel_mask
    truth_area = np.array([area_mm2(mask, pixel) for mask in references])
    scores: dict[str, dict[str, np.ndarray]] = {"dice": {}, "area": {}, "centroid": {}}
    for name, masks in {"deformed": truth.vessel_mask, **corrected_masks}.items():
        for values in scores.values():
            values[name] = np.full(len(sweep), np.nan)
        for index, (mask, reference) in enumerate(zip(masks, references, strict=True)):
            if not reference.any():  # the vessel left the frame: nothing to score
                continue
            scores["dice"][name][index] = dice(mask, reference)
            scores["area"][name][index] = area_mm2(mask, pixel) - truth_area[index]
            if mask.any():
                scores["centroid"][name][index] = centroid_distance_mm(mask, reference, pixel)
    assert sweep.force is not None  # a simulated sweep records its force
    return FrameMetrics(
        truth.sweep_position_mm, sweep.force, truth_area, scores["dice"], scores["area"], scores["centroid"]
    )


def _vessel_metrics(vessels: dict[str, Volume]) -> VolumeMetrics:
    """Lumen volume and centre-line depth of the compounded vessel masks (0-255; lumen >= 128)."""
    grid = next(iter(vessels.values())).grid
    weights = {name: _weight(volume) for name, volume in vessels.items()}
    lumens = {name: (volume.image >= 127.5) & (weights[name] > 0) for name, volume in vessels.items()}
    covered = np.all([weight > 0 for weight in weights.values()], axis=0)
    shared_slices = covered.any(axis=(0, 2))  # sweep slices (grid y) every volume covers
    voxel_mm3 = float(np.prod(grid.spacing))
    # Depth below the unloaded surface is -z in the surface frame, whose axes the simulator aligns with the base's.
    base_to_surface = np.linalg.inv(DEFAULT_SURFACE_TO_BASE)
    z_index = np.arange(grid.shape[0], dtype=float)
    slice_y = grid.index_to_world[1, 1] * np.arange(grid.shape[1]) + grid.index_to_world[1, 3]
    depth: dict[str, np.ndarray] = {}
    for name, lumen in lumens.items():
        counts = lumen.sum(axis=(0, 2)).astype(float)
        z_sums = (lumen.sum(axis=2) * z_index[:, None]).sum(axis=0)
        mean_z_index = np.where(counts > 0, z_sums / np.maximum(counts, 1), np.nan)
        world_z = grid.index_to_world[2, 2] * mean_z_index + grid.index_to_world[2, 3]
        depth[name] = np.where(shared_slices, -(base_to_surface[2, 2] * world_z + base_to_surface[2, 3]), np.nan)
    volumes = {name: float(lumen[:, shared_slices].sum()) * voxel_mm3 for name, lumen in lumens.items()}
    errors = {name: float(np.nanmean(np.abs(depth[name] - depth["truth"]))) for name in lumens}
    return VolumeMetrics(volumes, slice_y, depth, errors)


def _weight(volume: Volume) -> np.ndarray:
    if volume.weight is None:  # a Compounder's volume always has its coverage
        raise InputError("volume: no coverage weight")
    return volume.weight


def _compound(grid: VoxelGrid, frames: np.ndarray, image_to_base: np.ndarray) -> Volume:
    compounder = Compounder(grid, "linear", "mean")
    compounder.add_frames(frames, image_to_base)
    return compounder.volume()


def _corrected_like_the_sweep(
    images: np.ndarray, sweep: Recording, profiles: np.ndarray, model: DeformationModel
) -> np.ndarray:
    """``images`` (one per sweep frame, e.g. the true lumen masks) warped as the sweep's frames are
    corrected: a vessel-anchored model is placed on the lumens it finds in the sweep's frames."""
    assert sweep.force is not None  # a simulated sweep records its force
    return correct_like(images, sweep.frames, sweep.force, profiles, model)


def run_demo(output_dir: str | Path, config: DemoConfig | None = None, *, progress: bool = True) -> DemoResult:
    """Run the pipeline and write its files (recordings, model, volumes) into ``output_dir``.

    Parameters
    ----------
    output_dir : str or Path
        Folder for the files (created).
    config : DemoConfig, optional
        What to simulate and how to correct (default: ``DemoConfig()``).
    progress : bool
        Show a tqdm bar per stage on stderr.

    Returns
    -------
    DemoResult
        Everything the report shows; ``files`` lists what was written. The report itself is
        :func:`usdeform.demo.report.write_report`. With ``config.effects``, ``effect_outcome`` holds the
        blind diagnosis of the palpations and the sweep corrected with the compensation it supports
        (``diagnosis.json``, ``compensated.nrrd`` and ``vessel_compensated.nrrd`` written too).
    """
    config = DemoConfig() if config is None else config
    output = Path(output_dir)
    output.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    phantom = config.phantom()
    effects = config.simulated_effects()
    force = float(config.force_n if config.force_n is not None else PRESETS[config.preset][1])
    if force >= phantom.max_force_n:
        raise InputError(
            f"force_n: the sweep force {force:g} N must stay below the palpations' highest force "
            f"({phantom.max_force_n:g} N for the {config.preset} phantom), which the model is fitted up to"
        )
    positions = config.palpation_positions_mm
    start, end = positions[0], positions[-1]
    seeds = [int(s) for s in np.random.SeedSequence(config.seed).generate_state(len(positions) + 1)]
    size = config.frame_size

    def bar(iterable, description: str):
        return _bar(iterable, description, show=progress)

    with _timed(timings, "FEM solves"):
        _seed_solution_cache(solution_keys(phantom, start, end))
        for knot in bar(_knots_used(phantom, start, end), "FEM solves (cached after the first run)"):
            phantom.solution_at(float(knot))
    palpations = []
    with _timed(timings, "simulate palpations"):
        for position, seed in zip(bar(positions, "simulate palpations"), seeds, strict=False):
            palpations.append(
                simulate_palpation(
                    phantom,
                    position,
                    phantom.max_force_n,
                    config.palpation_frames,
                    seed=seed,
                    effects=effects,
                    rows=size,
                    cols=size,
                )
            )
    with _timed(timings, "stiffness and optical flow"):
        measured, sampled = _measure(
            bar([recording for recording, _ in palpations], "stiffness fits and optical flow"),
            phantom.base_section.depth_mm,
        )
    fits: dict[str, RegressionFit] = {}
    with _timed(timings, "regression"):
        for name in bar(FIT_METHODS, "regression"):
            fits[name] = fit_measured(measured, FIT_METHODS[name])
    with _timed(timings, "simulate sweep"):
        description = f"simulate a {config.sweep_frames}-frame sweep at {force:g} N"
        with tqdm(total=1, desc=description, unit="sweep", leave=False, disable=not progress) as one_step:
            sweep, truth = simulate_sweep(
                phantom,
                start,
                end - start,
                force,
                config.sweep_frames,
                seed=seeds[-1],
                effects=effects,
                rows=size,
                cols=size,
            )
            one_step.update()
    with _timed(timings, "correction"):
        corrected = correct_recording(sweep, fits[config.method].fitted, sampled)
        profiles = sweep_profiles(sweep, sampled)
        lumen = truth.vessel_mask.astype(np.uint8) * 255
        corrected_masks = {
            name: _corrected_like_the_sweep(lumen, sweep, profiles, fits[name].fitted) >= 128
            for name in bar(FIT_METHODS, "correction")
        }
    frame_metrics = _frame_metrics(sweep, truth, corrected_masks)

    truth_poses = truth_image_to_base(truth, sweep)
    sources = {
        "deformed": (sweep.frames, truth.vessel_mask, sweep.image_to_base),
        "corrected": (corrected.frames, corrected_masks[config.method], corrected.image_to_base),
        "truth": (truth.zero_force_frames, truth.zero_force_vessel_mask, truth_poses),
    }
    grid = grid_for_frames(np.concatenate([poses for _, _, poses in sources.values()]), sweep.shape, config.spacing_mm)
    volumes, vessels = {}, {}
    with _timed(timings, "compounding"):
        for name in bar(sources, "compounding"):
            frames, masks, poses = sources[name]
            volumes[name] = _compound(grid, frames, poses)
            vessels[name] = _compound(grid, masks.astype(np.uint8) * 255, poses)
    volume_metrics = _vessel_metrics(vessels)

    result = DemoResult(
        config,
        phantom,
        force,
        palpations,
        measured,
        sampled,
        fits,
        sweep,
        truth,
        corrected,
        corrected_masks,
        frame_metrics,
        volumes,
        vessels,
        volume_metrics,
        timings,
    )
    with _timed(timings, "writing files"):
        _write_files(result, output, progress)
    if config.effects:
        result.effect_outcome = _diagnose_and_compensate(result, output, progress)
    return result


def _measure(
    recordings: Iterable[Recording], flexible_layer_mm: float
) -> tuple[list[SampledPosition], SampledProfiles]:
    """Each palpation measured on its own (one sampling position each), and the positions' stiffness profiles."""
    measured: list[SampledPosition] = []
    positions = []
    for number, recording in enumerate(recordings):
        (one,), at = measure_positions([recording], flexible_layer_mm, names=[f"palpation {number}"])
        measured.append(one)
        positions.append(at.positions_mm[0])
    return measured, SampledProfiles(np.array(positions), tuple(m.stiffness.profile for m in measured))


def _truth_frames(truth: GroundTruth, kept: np.ndarray) -> GroundTruth:
    """The ground truth of the frames ``kept`` (indices)."""
    return GroundTruth(**{name: getattr(truth, name)[kept] for name in GroundTruth.__dataclass_fields__})


def _diagnose_and_compensate(result: DemoResult, output: Path, progress: bool) -> EffectOutcome:
    """Diagnose the palpations blind (``output/diagnosis.json``) and, where the diagnosis supports a compensation
    (read as ``--compensate`` reads it), refit and correct the sweep with it as the demo did without, compound the
    compensated sweep (``output/compensated.nrrd``, ``output/vessel_compensated.nrrd``) and score it.

    The compensated palpations are measured and fitted by the demo's own stages, not
    :func:`usdeform.fitting.fit_palpations` (which fits the loading ramps only), so that the compensation is
    the only difference between the two corrections."""
    config, timings, files = result.config, result.timings_s, result.files
    recordings = [recording for recording, _ in result.palpations]
    with _timed(timings, "diagnosis"):
        try:
            diagnosis: dict[str, Any] | None = diagnose(recordings, seed=config.seed, progress=progress).to_json()
        except UsdeformError as error:  # a diagnosis that fails is an outcome to report, not the demo's failure
            return EffectOutcome(None, f"the diagnosis failed: {error}")
        path = output / "diagnosis.json"
        write_text(path, json.dumps(diagnosis, indent=1))
        files["the diagnosis of the palpations (usdeform diagnose's diagnosis.json)"] = path
        try:
            compensation = compensation_option(path, False)
        except InputError as error:
            return EffectOutcome(diagnosis, str(error))
    assert compensation is not None  # a path was given
    with _timed(timings, "compensated fit and correction"):
        try:
            measured, sampled = _measure(
                (
                    apply_compensation(compensation, recording, f"palpation {n}")[0]
                    for n, recording in enumerate(recordings)
                ),
                result.phantom.base_section.depth_mm,
            )
            model = fit_measured(measured, FIT_METHODS[config.method]).fitted
            sweep, record = apply_compensation(compensation, result.sweep, "sweep")
            kept = np.searchsorted(result.sweep.timestamps, sweep.timestamps)  # the frames a re-pairing kept
            corrected = correct_recording(sweep, model, sampled)
            lumen = result.sweep_truth.vessel_mask[kept].astype(np.uint8) * 255
            masks = _corrected_like_the_sweep(lumen, sweep, sweep_profiles(sweep, sampled), model) >= 128
            frame_metrics = _frame_metrics(
                result.sweep.select(kept),
                _truth_frames(result.sweep_truth, kept),
                {"corrected": result.corrected_masks[config.method][kept], "compensated": masks},
            )
            grid = result.volumes["truth"].grid
            volume = _compound(grid, corrected.frames, corrected.image_to_base)
            vessel = _compound(grid, masks.astype(np.uint8) * 255, corrected.image_to_base)
            vessels = result.vessel_volumes
            volume_metrics = _vessel_metrics(
                {"corrected": vessels["corrected"], "compensated": vessel, "truth": vessels["truth"]}
            )
            for label, name, written in (
                ("volume of the sweep compensated with the diagnosis and corrected", "compensated", volume),
                ("the vessel lumen in the compensated volume (threshold at 128)", "vessel_compensated", vessel),
            ):
                write_volume(output / f"{name}.nrrd", written)
                files[label] = output / f"{name}.nrrd"
        except UsdeformError as error:  # e.g. a compensated force outside the fitted range: reported
            return EffectOutcome(diagnosis, f"the fit or correction compensated with {path} failed: {error}")
    return EffectOutcome(diagnosis, "", record, kept, frame_metrics, volume_metrics)


def _write_files(result: DemoResult, output: Path, progress: bool) -> None:
    """The recordings (PLUS sequence files), the model file and the volumes (NRRD)."""
    files = result.files
    jobs: list[tuple[str, Path, Callable[[Path], None]]] = []
    config = result.config
    for number, ((recording, _), position) in enumerate(
        zip(result.palpations, config.palpation_positions_mm, strict=True)
    ):
        label = f"palpation at {position:g} mm up to {result.phantom.max_force_n:g} N ({len(recording)} frames)"
        path = output / f"palpation_{number}.seq.nrrd"
        jobs.append((label, path, partial(write_sequence, recording=recording)))
    sweep_label = f"the sweep, {len(result.sweep)} frames at {result.sweep_force_n:g} N"
    jobs.append((sweep_label, output / "sweep.seq.nrrd", partial(write_sequence, recording=result.sweep)))
    corrected = result.corrected
    jobs.append(
        (
            "the sweep corrected to zero force",
            output / "corrected.seq.nrrd",
            partial(write_sequence, recording=corrected),
        )
    )
    fit = result.fits[result.config.method]
    provenance = {
        **fit_provenance(fit),
        "demo": {**dataclasses.asdict(result.config), "sweep_force_n": result.sweep_force_n},
        "flexible_layer_mm": result.phantom.base_section.depth_mm,
    }
    save = partial(save_model, model=fit.fitted, sampled_positions=result.sampled, provenance=provenance)
    jobs.append(
        (f"the fitted model ({config.method} settings, as usdeform fit writes it)", output / "model.json", save)
    )
    names = {"deformed": "the sweep as recorded", "corrected": "the corrected sweep", "truth": "the zero-force truth"}
    for name, volume in result.volumes.items():
        jobs.append((f"volume of {names[name]}", output / f"{name}.nrrd", partial(write_volume, volume=volume)))
    for name, volume in result.vessel_volumes.items():
        label = f"the vessel lumen in {names[name]} (0 outside to 255 inside: threshold at 128)"
        jobs.append((label, output / f"vessel_{name}.nrrd", partial(write_volume, volume=volume)))
    for label, path, write in _bar(jobs, "writing files", show=progress):
        write(path)
        files[label] = path
