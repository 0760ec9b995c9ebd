"""Running the paper's 3D experiments: palpations and fits per phantom, sweeps corrected with every model."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ...correction import SampledProfiles, correct_recording, sweep_profiles
from ...fitting import measure_positions
from ...options import StiffnessSource
from ...recording import Recording
from ...regression import DisplacementModel, fit_regression
from ...sim import (
    Phantom,
    simulate_palpation,
    simulate_sweep,
)
from ..paper_2d import Method
from .config import PRESETS, SOURCES, VIEWED, Paper3dConfig, PhantomSweeps, SweepCase, Views, variant_names, variants
from .measures import (
    lambda_miss_mm,
    measure_variants,
    variant_walls,
)
from .table import plot_bars, plot_views, write_results

__all__ = ["run_paper_3d"]


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


def _run_sweep(
    sweeps: PhantomSweeps,
    fitted: _Fitted,
    force_n: float,
    config: Paper3dConfig,
    methods: tuple[Method, ...],
    seed: int,
) -> tuple[SweepCase, Views]:
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
    case = SweepCase(
        sweeps.label,
        force_n,
        n_frames,
        (float(recording.force.min()), float(recording.force.max())),
        (float(recording.probe_displacement.min()), float(recording.probe_displacement.max())),
        indices.tolist(),
    )
    corrected: dict[str, Recording] = {}
    profiles = {s: sweep_profiles(recording, fitted.sampled, stiffness_source=s) for s in SOURCES}
    case.stiffness = {source: lambda_miss_mm(recording, profiles[source]) for source in SOURCES}
    variants: dict[str, tuple[DisplacementModel, np.ndarray]] = {}
    for method in methods:
        sources: tuple[StiffnessSource, ...] = SOURCES if method.coupling == "stiffness" else ("interpolated",)
        for source in sources:
            name = method.name if source == "interpolated" else f"{method.name}/sweep"
            model = fitted.models[method.name]
            corrected[name] = correct_recording(recording, model, fitted.sampled, stiffness_source=source)
            variants[name] = (model, profiles[source])
    case.frames, case.volume, views = measure_variants(recording, truth, corrected, indices, config.voxel_mm)
    case.walls = variant_walls(recording, truth, indices, variants)
    return case, views


def run_paper_3d(output_dir: str | Path, config: Paper3dConfig | None = None) -> list[SweepCase]:
    """Run the sweeps of ``config`` (None: :class:`Paper3dConfig`'s defaults); write ``results.md``,
    ``results.json``, ``fig9_views.png`` and ``fig10_bars.png`` to ``output_dir``; return the cases."""
    config = Paper3dConfig() if config is None else config
    output = Path(output_dir)
    output.mkdir(parents=True, exist_ok=True)
    methods = variants(config)
    names = ["deformed", *variant_names(methods)]
    cases: list[SweepCase] = []
    views: dict[str, Views] = {}
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
                write_results(cases, config, methods, names, output)  # a cut-off run keeps what it measured
                if sweeps.stiffness_amplitude is None and force == max(sweeps.forces_n):  # Fig. 9 shows these
                    views[f"{sweeps.label}, {force:g} N"] = Views(
                        sweep_views.grid,
                        {name: sweep_views.images[name] for name in VIEWED},
                        {name: sweep_views.lumens[name] for name in VIEWED},
                    )
                progress.update()
    plotted = [p for p in config.phantoms if p.stiffness_amplitude is None]  # the paper's phantoms
    if plotted:
        plot_views(views, output / "fig9_views.png")
        plot_bars(cases, plotted, output / "fig10_bars.png")
    return cases
