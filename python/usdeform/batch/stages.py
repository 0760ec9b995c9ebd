"""The seam between the batch runner and the pipeline: fit one position's palpations, reconstruct one sweep.

THIS MODULE IS THE SINGLE SEAM of :mod:`usdeform.batch` to the pipeline. Its two functions mirror
what ``usdeform fit`` and ``usdeform correct`` do (python/usdeform/cli.py ``_fit`` and ``_correct``)
through the current public API, because that logic still lives in the command line. When the
library stages that take it over land (``usdeform.reconstruction``), the coordinator points these
two functions at them and nothing else in the batch package changes. Keep it small: no batch logic
(skipping, retries, records) belongs here.

Both functions read their inputs from paths and write every output atomically (the io writers write
a temporary file and rename it), so an interrupted call never leaves a half-written output.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..compounding import Compounder, grid_for_frames
from ..correction import correct_frames
from ..errors import FitError, InputError
from ..io import SampledProfiles, fit_provenance, load_model, read_sequence, save_model, write_sequence, write_volume
from ..regression import fit_regression
from ..sampling import measure_palpation
from .manifest import Options

__all__ = ["fit_position", "reconstruct_sweep"]


def fit_position(palpation_paths: Sequence[Path], options: Options, model_path: Path) -> dict[str, Any]:
    """Fit a deformation model to the palpations (PLUS sequence files) and write it to ``model_path``.

    As ``usdeform fit``: stiffness and optical flow per palpation, its position the mean probe
    position off the probe axis (base frame, mm), one regression over all of them. Returns the
    details for the results manifest: per-palpation stiffness (N/m, mean and SD) and the fit's loss.
    """
    from ..cli import _basis, _surface_positions  # not at the top: cli imports this package's command

    if options.flexible_layer_mm is None:
        raise InputError("flexible_layer_mm: required to fit a model")
    recordings = [read_sequence(path) for path in palpation_paths]
    shapes = {recording.shape for recording in recordings}
    if len(shapes) > 1:
        raise InputError(f"palpations: frames must have one size, got {sorted(shapes)} (rows, cols)")
    positions, sampled = [], []
    for path, recording in zip(palpation_paths, recordings, strict=True):
        if not recording.pose_valid.any():
            raise InputError(f"{path}: no frame has a valid probe pose")
        positions.append(_surface_positions(recording.probe_to_base[recording.pose_valid]).mean(axis=0))
        try:
            sampled.append(measure_palpation(recording, options.flexible_layer_mm))
        except (InputError, FitError) as error:
            raise type(error)(f"{path}: {error}") from None
    fit = fit_regression(
        [measured.observations for measured in sampled],
        recordings[0].shape,
        solver=options.solver,
        coupling=options.coupling,
        integration=options.integration,
        basis=_basis(options.basis),
        smoothness=options.smoothness,
    )
    profiles = SampledProfiles(np.array(positions), tuple(measured.stiffness.profile for measured in sampled))
    provenance = {
        **fit_provenance(fit),
        "flexible_layer_mm": options.flexible_layer_mm,
        "palpations": [str(path) for path in palpation_paths],
    }
    save_model(model_path, fit.model, profiles, provenance)
    return {
        "stiffness_n_per_m": [list(measured.stiffness.stiffness_mean_sd_n_per_m) for measured in sampled],
        "loss": fit.loss,
    }


def reconstruct_sweep(
    sweep_path: Path, model_path: Path, options: Options, corrected_path: Path, volume_path: Path | None
) -> dict[str, Any]:
    """Correct a sweep (PLUS sequence file with ContactForce) to zero force with a model file, write
    the corrected sequence to ``corrected_path`` and, with ``volume_path``, compound it into a volume.

    As ``usdeform correct``: per-frame stiffness by inverse-distance weights of the probe positions
    off the probe axis. Returns the details for the results manifest (frames, force range in N).
    """
    from ..cli import _surface_positions  # not at the top: cli imports this package's command

    model_file = load_model(model_path)
    if model_file.sampled is None or model_file.sampled.positions_mm.shape[1:] != (3,):
        raise InputError(
            f"{model_path}: sampled_positions: correcting a sweep needs the palpations' 3-D positions "
            "in the base frame, as 'usdeform fit' records them"
        )
    recording = read_sequence(sweep_path)
    if recording.force is None:
        raise InputError(f"{sweep_path}: correction needs each frame's ContactForce")
    normalization = model_file.model.normalization
    fitted_shape = (round(normalization.y_scale) + 1, round(normalization.x_scale) + 1)
    if tuple(recording.shape) != fitted_shape:
        raise InputError(
            f"{sweep_path}: frames of {recording.shape[0]} x {recording.shape[1]} pixels, but the model "
            f"was fitted on {fitted_shape[0]} x {fitted_shape[1]} frames"
        )
    valid = np.flatnonzero(recording.pose_valid)
    if valid.size == 0:
        raise InputError(f"{sweep_path}: no frame has a valid probe pose")
    surface = _surface_positions(recording.probe_to_base[valid])
    positions = np.stack(
        [np.interp(recording.timestamps, recording.timestamps[valid], axis) for axis in surface.T], axis=1
    )
    corrected = correct_frames(recording.frames, recording.force, model_file.sampled.along(positions), model_file.model)
    write_sequence(corrected_path, dataclasses.replace(recording, frames=corrected))
    details: dict[str, Any] = {
        "frames": len(recording),
        "force_range_n": [float(recording.force.min()), float(recording.force.max())],
    }
    if volume_path is not None:
        image_to_base = recording.image_to_base[valid]
        grid = grid_for_frames(image_to_base, recording.shape, options.spacing_mm)
        compounder = Compounder(
            grid, options.interpolation, options.compounding, max_bytes=int(options.max_gib * 1024**3)
        )
        compounder.add_frames(corrected[valid], image_to_base)
        write_volume(volume_path, compounder.volume())
        details["volume_shape"] = list(grid.shape)
    return details
