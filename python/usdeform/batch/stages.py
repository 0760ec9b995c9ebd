"""The batch runner's units of pipeline work: fit one subject's palpations, correct one sweep.

Each runs the step of :mod:`usdeform.pipeline` that ``usdeform fit`` or ``usdeform correct`` runs, with the
subject's options (:class:`~usdeform.batch.Options`, a :class:`~usdeform.pipeline.PipelineSettings`), and
returns its details for the results manifest. No batch logic (skipping, retries, records) belongs here.
Every output is written atomically, so an interrupted call never leaves a half-written output.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..pipeline import correct_sweep, fit_model
from .manifest import Options

__all__ = ["fit_position", "reconstruct_sweep"]


def fit_position(
    palpation_paths: Sequence[Path], options: Options, model_path: Path, report_dir: Path | None = None
) -> dict[str, Any]:
    """Fit a deformation model to the palpations (PLUS sequence files) and write it to ``model_path``,
    with ``report_dir``, the fit's report (``report.html``, ``report.json``) there, as ``usdeform fit``.

    Returns the details for the results manifest (:meth:`usdeform.pipeline.FittedModel.details`).
    """
    return fit_model(palpation_paths, options, model_path, report_dir=report_dir).details()


def reconstruct_sweep(
    sweep_path: Path,
    model_path: Path,
    options: Options,
    corrected_path: Path,
    volume_path: Path | None,
    coverage_path: Path | None = None,
) -> dict[str, Any]:
    """Correct a sweep (PLUS sequence file with ContactForce) to zero force with a model file, write
    the corrected sequence to ``corrected_path`` and, with ``volume_path``, compound it into a volume
    (and its coverage to ``coverage_path``), as ``usdeform correct``.

    Returns the details for the results manifest (:meth:`usdeform.pipeline.CorrectedSweep.details`).
    """
    return correct_sweep(sweep_path, model_path, options, corrected_path, volume_path, coverage_path).details()
