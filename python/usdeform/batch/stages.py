"""The seam between the batch runner and the pipeline: fit one position's palpations, reconstruct one sweep.

Both functions run the library stages that ``usdeform fit`` and ``usdeform correct`` run
(:func:`usdeform.fitting.fit_palpations`,
:func:`usdeform.reconstruction.correct_recording` and :func:`~usdeform.reconstruction.compound_recording`)
and add only what the batch needs: reading from paths and the details for the results manifest. With
the ``compensate`` option both undo the diagnosed effects first, as ``--compensate`` does
(:mod:`usdeform.compensation`), and record them in the details' ``compensation``. No batch logic
(skipping, retries, records) belongs here.

Both functions read their inputs from paths and write every output atomically (the io writers write
a temporary file and rename it), so an interrupted call never leaves a half-written output.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..compensation import apply_compensation
from ..errors import InputError
from ..fit_report import assess_fit, write_fit_report
from ..fitting import fit_palpations
from ..io import load_model, read_sequence, save_model, write_sequence, write_volume
from ..io._common import outputs_together
from ..reconstruction import STIFFNESS_SOURCE_FIELD, compound_recording, correct_recording
from .manifest import Options

__all__ = ["fit_position", "reconstruct_sweep"]


def fit_position(
    palpation_paths: Sequence[Path], options: Options, model_path: Path, report_dir: Path | None = None
) -> dict[str, Any]:
    """Fit a deformation model to the palpations (PLUS sequence files) and write it to ``model_path``,
    with ``report_dir``, the fit's report (``report.html``, ``report.json``) there.

    As ``usdeform fit`` (``--report``, ``--compensate``). Returns the details for the results manifest:
    per-palpation stiffness (N/m, mean and SD), each palpation's phases (which frames were fitted), the fit's
    loss, the report's warnings (with or without the report) and, with the ``compensate`` option, the
    compensation (the model's ``provenance.compensation``: the diagnosis, its effects and parameters,
    whether forced, and one note per palpation saying what changed).
    """
    if options.flexible_layer_mm is None:
        raise InputError("flexible_layer_mm: required to fit a model")
    recordings = [read_sequence(path) for path in palpation_paths]
    fitted = fit_palpations(
        recordings,
        options.flexible_layer_mm,
        method=options.fit_method(),
        names=[str(path) for path in palpation_paths],
        solver=options.solver,
        smoothness=options.smoothness,
        compensation=options.compensation(),
    )
    report = assess_fit(fitted, names=[str(path) for path in palpation_paths])
    provenance = {**fitted.provenance, "method": options.method, "palpations": [str(path) for path in palpation_paths]}
    with outputs_together():
        save_model(model_path, fitted.fit.fitted, fitted.sampled, provenance)
        if report_dir is not None:
            write_fit_report(report, report_dir)
    return {
        "stiffness_n_per_m": [list(position.stiffness.stiffness_mean_sd_n_per_m) for position in fitted.measured],
        "palpation_phases": [phases.to_json() for phases in fitted.phases],
        "loss": fitted.fit.loss,
        "warnings": list(report.warnings),
        **({"compensation": fitted.provenance["compensation"]} if "compensation" in fitted.provenance else {}),
    }


def reconstruct_sweep(
    sweep_path: Path, model_path: Path, options: Options, corrected_path: Path, volume_path: Path | None
) -> dict[str, Any]:
    """Correct a sweep (PLUS sequence file with ContactForce) to zero force with a model file, write
    the corrected sequence to ``corrected_path`` and, with ``volume_path``, compound it into a volume.

    As ``usdeform correct`` (``--compensate``) with its default stiffness source (``"auto"``; the manifest
    has no option for it). Returns the details for the results manifest (frames, force range in N, the
    stiffness source used, volume shape and, with the ``compensate`` option, the compensation: the
    diagnosis, its effects and parameters, whether forced, and a note saying what changed).
    """
    model_file = load_model(model_path)
    if model_file.sampled is None:
        raise InputError(
            f"{model_path}: sampled_positions: correcting a sweep needs the palpations' 3-D positions "
            "in the base frame, as 'usdeform fit' records them"
        )
    recording, compensation = apply_compensation(options.compensation(), read_sequence(sweep_path), str(sweep_path))
    corrected = correct_recording(recording, model_file.model, model_file.sampled, name=str(sweep_path))
    write_sequence(corrected_path, corrected)
    assert recording.force is not None  # checked by correct_recording
    details: dict[str, Any] = {
        "frames": len(recording),
        "force_range_n": [float(recording.force.min()), float(recording.force.max())],
        "stiffness_source": corrected.metadata[STIFFNESS_SOURCE_FIELD],
        **({"compensation": compensation} if compensation is not None else {}),
    }
    if volume_path is not None:
        volume, _ = compound_recording(
            corrected,
            spacing_mm=options.spacing_mm,
            interpolation=options.interpolation,
            compounding=options.compounding,
            max_bytes=int(options.max_gib * 1024**3),
            name=str(sweep_path),
        )
        write_volume(volume_path, volume, compression_level=options.compression_level)
        details["volume_shape"] = list(volume.grid.shape)
    return details
