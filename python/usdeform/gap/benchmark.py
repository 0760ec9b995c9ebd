"""The gap benchmark: "real" palpations with a withheld effect, diagnosed from their PLUS files alone.

Each case is one force-controlled palpation (load, hold, unload) simulated on a phantom the
diagnosis never sees, written as a PLUS sequence file and diagnosed from that file alone. Kinds:

* ``single``: one library effect of random type, magnitude drawn uniformly from the upper part of
  its realistic range (``EFFECT_RANGES``; the ranges of the effects' docstrings, with the weakest
  third left out, since a vanishing effect is indistinguishable from none);
* ``null``: no effect; ``pair``: two library effects;
* ``out_of_library``: an effect only this generator knows (``OOL_KINDS``): force-sensor
  saturation of the logged force channel, a static reverberation pattern under the probe, a
  compliant probe holder (the recorded lambda overstates the indentation by F / k_holder) and a convex probe face
  (an arc of radius 40-80 mm: the library's faces are flat).

A ``probe_tilt`` case draws its form: a probe tilted over the surface or a surface inclined under a level probe,
pressed along the surface normal or along the probe's axis.

Nuisance (every case): the phantom comes from a pool of four (mesh 2 or 3 mm, three Yeoh variants,
Poisson's ratios 0.45-0.495, tissue 50-85 mm deep, lumen 0.01-0.1 times as stiff as the tissue, probe faces
37.5-48 mm wide, moduli 12-41 kPa, various vessels; cached solves) at a random sweep position (vessel and
stiffness vary along s); scanner and tissue acoustics vary per case (image width up to the probe face's,
axial / lateral / elevation PSF, noise, gain, TGC, attenuation, scatterer density, wall echo, imaging depth,
and the scatterers' sub-resolution micro-motion, up to ``MAX_SCATTERER_JITTER_MM``, which decorrelates the speckle
with compression in a way no library effect models);
force-sensor noise, robot ripple, ramp rate, hold time, force and frame count vary too. The diagnosis
uses its own neo-Hookean 2.5 mm library (:mod:`usdeform.gap.calibration`), so material law and mesh always
differ and compressibility, tissue depth, strain stiffening, lumen stiffness and probe face width must be calibrated.

Generation and diagnosis seeds are independent streams of ``seed``.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .._files import check_output_folder
from ..errors import InputError, UsdeformError
from ..io import write_sequence
from ..recording import Recording
from ..sim import (
    ConvexProbeFace,
    Effects,
    ForceController,
    ForceSensorError,
    ImageLatency,
    ImagingSettings,
    Layer,
    LayeredTissue,
    LumenPressure,
    OutOfPlaneMotion,
    Phantom,
    ProbeTilt,
    SectionSpec,
    SlidingContact,
    SoundSpeedMismatch,
    TissueAcoustics,
    Viscoelasticity,
    simulate_palpation,
)
from .benchmark_follow_up import loop_markdown, loop_summary, record_case_follow_up, round_one_row
from .benchmark_scoring import (
    ATTRIBUTING,
    BenchmarkCase,
    CaseKind,
    confusion,
    markdown_summary,
    score_case,
    summarise,
)
from .diagnosis import check_seed, diagnose
from .follow_up import FollowUpRecording
from .models import EFFECTS
from .report import write_text

__all__ = [
    "ATTRIBUTING",
    "EFFECT_RANGES",
    "OOL_KINDS",
    "BenchmarkCase",
    "confusion",
    "draw_effect",
    "finished_rows",
    "generate_case",
    "run_benchmark",
]

MAX_CASES = 10_000  # a benchmark's cases: each takes minutes
OOL_KINDS = ("force_saturation", "reverberation", "holder_compliance", "convex_probe_face")
_MECHANICAL_OOL = {"convex_probe_face"}  # simulated with the case, not applied to its recording
EFFECT_RANGES = {
    "image_latency": (0.04, 0.15),  # s
    "force_sensor_error": (0.3, 1.0),  # N bias (sign random), plus drift within +-0.1 N/s and weight 0-2 N
    "viscoelasticity": (0.1, 0.45),  # g, tau 0.3-3 s
    "sound_speed_mismatch": (30.0, 90.0),  # |m/s|, range -90..+60
    "probe_tilt": (3.0, 10.0),  # |deg| of the probe's tilt or the surface's inclination
    "out_of_plane_motion": (0.1, 0.3),  # mm/mm, jitter 0-0.3 mm
    "layered_tissue": (3.0, 12.0),  # fat thickness mm, modulus ratio 0.15-0.5
    "sliding_contact": (1.0, 1.0),
    "lumen_pressure": (0.05, 0.25),  # pressure / modulus
    "force_latency": (0.04, 0.15),  # s: the force stream stamped late against pose and images
}
IMAGE_WIDTHS_MM = (37.5, 40.0, 42.5, 45.0)  # linear arrays; a case draws one no wider than its probe face
MAX_SCATTERER_JITTER_MM = 0.02  # rms per axis; 0.02 mm brings simulated speckle to the real sweep's decorrelation
# between frames (usdeform.sim.imaging.TissueAcoustics), so a palpation's micro-motion stays below it
_ROUND: tuple[tuple[CaseKind, str | None], ...] = (
    *(("single", model.effect) for model in EFFECTS),
    ("null", None),
    ("out_of_library", "force_saturation"),
    ("out_of_library", "reverberation"),
    ("null", None),
    ("out_of_library", "holder_compliance"),
    ("out_of_library", "convex_probe_face"),
    ("pair", None),
)


@dataclass(frozen=True)
class CaseSetup:
    """What a case's recordings share: the phantom, the position pressed (mm), the hidden effects, scanner, tissue
    acoustics and force loop, the frame rate (frames per s of recording) and an effect only the generator knows,
    applied to each recording after it is simulated (kind and parameters), if any."""

    phantom: Phantom
    position_mm: float
    effects: Effects
    settings: ImagingSettings
    acoustics: TissueAcoustics
    controller: ForceController
    frames_per_s: float
    out_of_library: tuple[str, dict[str, float]] | None = None

    def apply(self, recording: Recording) -> Recording:
        """``recording`` with the generator's own effect, if the case has one."""
        if self.out_of_library is None:
            return recording
        kind, parameters = self.out_of_library
        return _out_of_library(kind, recording, parameters)


def _pool() -> list[tuple[Phantom, float]]:
    """Nuisance phantoms (with the largest force each is pressed to), their solves cached after first use."""
    specs = [
        (
            SectionSpec(
                vessel_depth_mm=20,
                vessel_radius_mm=7.5,
                shear_modulus_kpa=40.8,
                yeoh_c2=-0.17,
                yeoh_c3=0.02,
                poisson_ratio=0.49,
                depth_mm=70.0,
                lumen_stiffness_ratio=0.02,
                mesh_size_mm=2.0,
            ),  # the paper's probe: face and image 37.5 mm wide
            20.0,
            2.0,
            1.0,
        ),
        (
            SectionSpec(
                vessel_depth_mm=16,
                vessel_radius_mm=5.0,
                shear_modulus_kpa=20.0,
                probe_width_mm=42.0,
                width_mm=126.0,
                mesh_size_mm=3.0,
            ),
            12.0,
            -2.0,
            1.5,
        ),
        (
            SectionSpec(
                vessel_center_x_mm=-3,
                vessel_depth_mm=14,
                vessel_radius_mm=4.5,
                shear_modulus_kpa=12.0,
                yeoh_c2=1.0,
                yeoh_c3=1.5,
                poisson_ratio=0.47,
                depth_mm=50.0,
                lumen_stiffness_ratio=0.1,
                probe_width_mm=40.0,
                mesh_size_mm=2.0,
            ),
            8.0,
            3.0,
            -1.0,
        ),
        (
            SectionSpec(
                vessel_center_x_mm=4,
                vessel_depth_mm=22,
                vessel_radius_mm=6.5,
                shear_modulus_kpa=30.0,
                yeoh_c2=0.5,
                yeoh_c3=0.5,
                poisson_ratio=0.495,
                depth_mm=85.0,
                lumen_stiffness_ratio=0.01,
                probe_width_mm=48.0,
                width_mm=150.0,
                mesh_size_mm=3.0,
            ),
            16.0,
            -3.0,
            2.0,
        ),
    ]
    return [
        (
            Phantom(
                f"pool{index}",
                spec,
                length_mm=40.0,
                stiffness_amplitude=0.1,
                vessel_shift_x_mm=shift_x,
                vessel_shift_depth_mm=shift_depth,
                max_force_n=force,
                max_probe_displacement_mm=10.0,
                n_probe_steps=16,
                geometry_knots=2,
            ),
            force,
        )
        for index, (spec, force, shift_x, shift_depth) in enumerate(specs)
    ]


def draw_effect(effect: str, rng: np.random.Generator, base_modulus_kpa: float, duration_s: float):
    """A library effect of random magnitude, its parameters and its scalar magnitude (as the diagnosis reports it)."""
    low, high = EFFECT_RANGES[effect]
    value = float(rng.uniform(low, high))
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if effect == "image_latency":
        return ImageLatency(value), {"delay_s": value}, value
    if effect == "force_latency":
        return ImageLatency(force_delay_s=value), {"delay_s": value}, value
    if effect == "force_sensor_error":
        drift = float(rng.uniform(-0.1, 0.1))  # ForceSensorError's thermal range
        weight = float(rng.uniform(0.0, 2.0)) if rng.random() < 0.5 else 0.0
        offset = sign * value - weight
        times = np.linspace(0, duration_s, 200)
        magnitude = float(np.sqrt(np.mean((offset + drift * times) ** 2)))
        return (
            ForceSensorError(sign * value, drift, weight),
            {"bias_n": sign * value, "drift_n_per_s": drift, "uncompensated_weight_n": weight},
            magnitude,
        )
    if effect == "viscoelasticity":
        tau = float(np.exp(rng.uniform(np.log(0.3), np.log(3.0))))
        return Viscoelasticity(((value, tau),)), {"g": value, "tau_s": tau}, value
    if effect == "sound_speed_mismatch":
        error = -value if sign < 0 else min(value, 60.0)
        return SoundSpeedMismatch(error), {"error_m_s": error}, abs(error)
    if effect == "probe_tilt":  # a probe tilted over the surface or a surface inclined under it; pressed along the
        # surface normal or along the probe's axis
        inclined = bool(rng.random() < 0.5)
        travel = float(rng.random() < 0.5)
        tilt = ProbeTilt(0.0 if inclined else sign * value, sign * value if inclined else 0.0, travel)
        form = {"surface_inclination_deg" if inclined else "tilt_deg": sign * value, "travel_along_axis": travel}
        return tilt, form, value
    if effect == "out_of_plane_motion":
        jitter = float(rng.uniform(0.0, 0.3))
        return OutOfPlaneMotion(value, jitter), {"shift_mm_per_mm": value, "jitter_mm": jitter}, value
    if effect == "layered_tissue":
        ratio = float(rng.uniform(0.15, 0.5))
        layer = Layer(thickness_mm=value, shear_modulus_kpa=ratio * base_modulus_kpa)
        return LayeredTissue((layer,)), {"thickness_mm": value, "modulus_ratio": ratio}, value
    if effect == "sliding_contact":
        return SlidingContact(True), {"enabled": 1.0}, 1.0  # frictionless: a slip fraction of 1
    if effect == "lumen_pressure":
        pressure = value * base_modulus_kpa
        return LumenPressure(pressure), {"pressure_kpa": pressure}, pressure
    raise InputError(f"unknown effect {effect!r}")


def draw_out_of_library(kind: str, rng: np.random.Generator) -> dict[str, float]:
    """The parameters of an effect only the generator knows (applied to each recording by :func:`_out_of_library`)."""
    if kind == "force_saturation":
        return {"saturation_fraction": float(rng.uniform(0.7, 0.85))}
    if kind == "reverberation":
        return {
            "spacing_mm": float(rng.uniform(1.5, 3.0)),
            "amplitude": float(rng.uniform(30.0, 60.0)),
            "decay_mm": float(rng.uniform(4.0, 8.0)),
            "lateral_cycles": float(rng.uniform(0.5, 2)),
        }
    if kind == "holder_compliance":
        return {"holder_stiffness_n_per_mm": float(rng.uniform(4.0, 10.0))}
    raise InputError(f"unknown out-of-library kind {kind!r}")


def _reverberation(frames: np.ndarray, pixel_mm: float, parameters: dict[str, float]) -> np.ndarray:
    """Static multiple echoes between the probe face and a near-field reflector, added under the probe."""
    depth = np.arange(frames.shape[1]) * pixel_mm
    echoes = parameters["spacing_mm"] * np.arange(1, 8)[None, :]
    bands = np.exp(-0.5 * ((depth[:, None] - echoes) / 0.25) ** 2).sum(axis=1)
    pattern = parameters["amplitude"] * bands * np.exp(-depth / parameters["decay_mm"])
    lateral = 1.0 + 0.2 * np.sin(np.linspace(0, 2 * np.pi * parameters["lateral_cycles"], frames.shape[2]))
    added = pattern[:, None] * lateral[None, :]
    return np.clip(frames.astype(np.float64) + added[None], 0, 255).astype(np.uint8)


def _out_of_library(kind: str, recording: Recording, parameters: dict[str, float]) -> Recording:
    """Apply an effect only the generator knows to a recording (a saturation's limit is set, as ``saturation_n``,
    by the first recording's highest force and kept for the others)."""
    force = np.array(recording.force)
    lam = np.array(recording.probe_displacement)
    frames = recording.frames
    poses = np.array(recording.probe_to_base)
    if kind == "force_saturation":
        parameters.setdefault("saturation_n", float(parameters["saturation_fraction"] * force.max()))
        force = np.minimum(force, parameters["saturation_n"])
    elif kind == "reverberation":
        frames = _reverberation(frames, float(np.linalg.norm(recording.image_to_probe[:3, 1])), parameters)
    elif kind == "holder_compliance":
        extra = np.clip(force, 0, None) / parameters["holder_stiffness_n_per_mm"]
        lam = lam + extra
        poses[:, 2, 3] -= extra
    else:
        raise InputError(f"unknown out-of-library kind {kind!r}")
    return dataclasses.replace(recording, frames=frames, force=force, probe_displacement=lam, probe_to_base=poses)


def generate_case(
    index: int, kind: CaseKind, effect: str | None, rng: np.random.Generator, directory: Path
) -> tuple[BenchmarkCase, CaseSetup]:
    """Simulate one case into ``directory / palpation.seq.nrrd``; returns it with what a follow-up of it records
    with (the same phantom, position, hidden effects, scanner and force loop)."""
    start = time.perf_counter()
    phantom, force = _pool()[int(rng.integers(0, 4))]
    position = float(rng.uniform(0.0, phantom.length_mm))
    base_modulus = phantom.base_section.shear_modulus_kpa
    ramp_rate = float(rng.uniform(3.0, 6.0))
    hold = float(rng.uniform(1.5, 3.0))
    max_force = float(force * rng.uniform(0.8, 1.0))
    duration = 2 * max_force / ramp_rate + hold
    chosen: list[str] = []
    if kind == "single":
        chosen = [effect]  # type: ignore[list-item]
    elif kind == "pair":
        chosen = [str(e) for e in rng.choice([m.effect for m in EFFECTS], 2, replace=False)]
    effects, parameters, magnitudes = [], {}, {}
    for name in chosen:
        effect_object, effect_parameters, magnitude = draw_effect(name, rng, base_modulus, duration)
        effects.append(effect_object)
        parameters[name] = effect_parameters
        magnitudes[name] = magnitude
    if kind == "out_of_library" and effect in _MECHANICAL_OOL:  # a face that is an arc: the library's are flat
        radius = float(rng.uniform(40.0, 80.0))
        effects.append(ConvexProbeFace(radius))
        parameters[str(effect)] = {"radius_mm": radius}
    image_widths = [width for width in IMAGE_WIDTHS_MM if width <= phantom.base_section.probe_width_mm]
    settings = ImagingSettings(
        width_mm=float(rng.choice(image_widths)),
        depth_mm=float(rng.choice([40.0, 45.0])),
        axial_resolution_mm=float(rng.uniform(0.2, 0.35)),
        lateral_resolution_mm=float(rng.uniform(0.4, 0.7)),
        elevation_resolution_mm=float(rng.uniform(1.2, 2.0)),
        tgc_db_per_cm=float(rng.uniform(4.0, 8.0)),
        gain_db=float(rng.uniform(-24.0, -16.0)),
        noise_db=float(rng.uniform(-45.0, -30.0)),
    )
    micro_motion = rng.spawn(1)[0]  # its own stream: drawing it leaves every other draw of the case as it was
    acoustics = TissueAcoustics(
        attenuation_db_per_cm_mhz=float(rng.uniform(0.3, 0.7)),
        scatterer_density_per_mm3=float(rng.uniform(8.0, 30.0)),
        wall_echo_db=float(rng.uniform(6.0, 12.0)),
        scatterer_jitter_mm=float(micro_motion.uniform(0.0, MAX_SCATTERER_JITTER_MM)),
        jitter_correlation_mm=float(micro_motion.uniform(0.5, 2.0)),
    )
    controller = ForceController(
        sensor_noise_n=float(rng.uniform(0.02, 0.06)), position_ripple_mm=float(rng.uniform(0.01, 0.05))
    )
    n_frames = int(rng.integers(80, 111))
    setup = CaseSetup(
        phantom=phantom,
        position_mm=position,
        effects=Effects.of(effects),
        settings=settings,
        acoustics=acoustics,
        controller=controller,
        frames_per_s=n_frames / duration,
    )
    recording, _ = simulate_palpation(
        phantom,
        position,
        max_force,
        n_frames=n_frames,
        ramp="up-hold-down",
        hold_s=hold,
        seed=int(rng.integers(0, 2**31)),
        effects=effects,
        ramp_rate_n_per_s=ramp_rate,
        settings=settings,
        acoustics=acoustics,
        controller=controller,
    )
    hidden = list(chosen)
    if kind == "out_of_library":
        hidden = [str(effect)]
        if effect not in _MECHANICAL_OOL:
            parameters[str(effect)] = draw_out_of_library(str(effect), rng)
            setup = dataclasses.replace(setup, out_of_library=(str(effect), parameters[str(effect)]))
            recording = _out_of_library(str(effect), recording, parameters[str(effect)])
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "palpation.seq.nrrd"
    write_sequence(path, recording)
    duration_s = float(recording.timestamps[-1] - recording.timestamps[0])
    case = BenchmarkCase(index, kind, hidden, parameters, magnitudes, path, time.perf_counter() - start, duration_s)
    return case, setup


def finished_rows(log: Path, seed: int) -> list[dict]:
    """The rows of the cases ``log`` already holds, for ``--resume`` (of this benchmark and the compensation
    benchmark): a last line cut short by a killed run is dropped (its case runs again); rows of another seed are an
    error, since their cases differ."""
    rows = []
    lines = log.read_text().splitlines() if log.exists() else []
    for number, line in enumerate(lines, start=1):
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            if number == len(lines):
                break  # the line being written when the run was stopped
            raise InputError(f"{log}: line {number} is not a JSON case row; choose another --out") from None
        if row.get("seed") != seed:
            raise InputError(
                f"{log}: case {row.get('case')} was run with seed {row.get('seed')}, not {seed}; "
                "resume with that seed or choose another --out"
            )
        rows.append(row)
    return rows


def run_benchmark(
    n_cases: int,
    seed: int,
    out: str | Path,
    *,
    progress: bool = True,
    command: str = "",
    resume: bool = False,
    follow_up_round: bool = True,
) -> dict[str, object]:
    """Generate and diagnose ``n_cases`` cases; write DIR/cases.jsonl (one line per finished case),
    DIR/benchmark.json and DIR/benchmark.md. Returns the summary.

    ``resume``: keep the cases DIR/cases.jsonl already holds and run only the others (case i's generation and
    diagnosis seeds depend on ``seed`` and i alone, so a resumed run scores the cases an uninterrupted one
    would). Without it, a DIR that holds finished cases is an error rather than overwritten. ``follow_up_round``:
    record what each case's record_next.json asks for and diagnose all its recordings again
    (:mod:`usdeform.gap.benchmark_follow_up`)."""
    if isinstance(n_cases, bool) or int(n_cases) != n_cases or not 1 <= n_cases <= MAX_CASES:
        raise InputError(f"--cases: expected an integer from 1 to {MAX_CASES}, got {n_cases!r}")
    seed = check_seed(seed)
    out = check_output_folder(out, "--out")
    log = out / "cases.jsonl"
    finished = finished_rows(log, seed) if resume else []
    if not resume and log.exists() and log.read_text().strip():
        raise InputError(f"{log} already holds finished cases: pass --resume to continue, or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    # SeedSequence children are keyed by their index: case i draws the same streams whatever n_cases is
    generation_seed, diagnosis_seed = np.random.SeedSequence(int(seed)).spawn(2)
    generation_rngs = [np.random.default_rng(s) for s in generation_seed.spawn(n_cases)]
    diagnosis_seeds = [int(s.generate_state(1)[0]) for s in diagnosis_seed.spawn(n_cases)]
    write_text(log, "".join(json.dumps(row) + "\n" for row in finished))
    rows: list[dict] = [row for row in finished if row["case"] < n_cases]
    pending = sorted(set(range(n_cases)) - {row["case"] for row in rows})
    for index in tqdm(pending, desc="gap benchmark", disable=not progress, total=n_cases, initial=len(rows)):
        kind, effect = _ROUND[index % len(_ROUND)]
        start = time.perf_counter()
        case, setup = generate_case(index, kind, effect, generation_rngs[index], out / f"case_{index:03d}")
        diagnosis_start = time.perf_counter()
        result, follow_up = _diagnosed([case.path], diagnosis_seeds[index])
        row = score_case(case, result, case.duration_s)
        row["seed"] = int(seed)
        row["diagnosis_s"] = time.perf_counter() - diagnosis_start
        write_text(case.path.parent / "diagnosis.json", json.dumps(result, indent=1))
        if follow_up_round:
            round_start = time.perf_counter()
            paths: list[Path] = []
            row["follow_up"] = {}
            if follow_up:
                paths, row["follow_up"] = record_case_follow_up(
                    follow_up, setup, case.path.parent / "follow_up", diagnosis_seeds[index]
                )
            if paths:
                result, _ = _diagnosed([case.path, *paths], diagnosis_seeds[index])
                write_text(case.path.parent / "diagnosis_round1.json", json.dumps(result, indent=1))
            row["round1"] = round_one_row(case, result, case.duration_s)
            row["round1_s"] = time.perf_counter() - round_start
        row["total_s"] = time.perf_counter() - start
        rows.append(row)
        with log.open("a") as handle:
            handle.write(json.dumps(row) + "\n")
    rows.sort(key=lambda row: row["case"])
    summary = summarise(rows)
    markdown = markdown_summary(summary, command)
    if follow_up_round:
        summary["loop"] = loop_summary(rows)
        markdown += loop_markdown(summary["loop"])  # type: ignore[arg-type]
    write_text(out / "benchmark.json", json.dumps({"summary": summary, "cases": rows}, indent=1))
    write_text(out / "benchmark.md", markdown)
    return summary


def _diagnosed(paths: list[Path], seed: int) -> tuple[dict, list[FollowUpRecording]]:
    """The diagnosis.json of ``paths`` and its follow-up protocol; a failed diagnosis is an outcome to report (its
    verdict says the error), not a crash."""
    try:
        diagnosis = diagnose(paths, seed=seed, progress=False)
    except UsdeformError as exc:
        return {"verdict": f"error: {exc}", "effects": [], "measures": []}, []
    return diagnosis.to_json(), diagnosis.follow_up
