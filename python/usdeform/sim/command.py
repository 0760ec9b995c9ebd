"""``usdeform simulate``: simulated palpations and sweeps as PLUS sequence files, with their ground truth beside them.

Each recording ``NAME.seq.nrrd`` gets ``NAME.truth.npz`` (:func:`write_ground_truth`): the arrays of
:class:`usdeform.sim.GroundTruth` (zero-force frames, lumen masks, true displacement field, true force,
probe displacement, sweep position and acquisition time per frame; mm, N, s, pixels), which
:func:`read_ground_truth` loads back. Effects are given on the command line as
``NAME[:PARAMETER=VALUE,...]`` (:func:`parse_effects`).
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import shutil
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Literal

import numpy as np
from tqdm import tqdm

from .._files import atomic_output, new_output_folders, outputs_together
from ..errors import FileFormatError, InputError, MemoryLimitError
from ..io import write_sequence
from ..options import NUMBERS, Number
from ..validation import checked_byte_count
from . import (
    ConvexProbeFace,
    Effects,
    ForceSensorError,
    GroundTruth,
    ImageLatency,
    Layer,
    LayeredTissue,
    LumenPressure,
    OutOfPlaneMotion,
    Phantom,
    ProbeTilt,
    SlidingContact,
    SoundSpeedMismatch,
    Viscoelasticity,
    coarse_phantom,
    compliant_vessel_phantom,
    simulate_palpation,
    simulate_sweep,
    soft_phantom,
    stiff_phantom,
)

__all__ = [
    "EFFECT_PARAMETERS",
    "PHANTOMS",
    "add_simulate_command",
    "parse_effects",
    "read_ground_truth",
    "simulate_to_files",
    "write_ground_truth",
]

#: The phantom presets by name.
PHANTOMS: dict[str, Callable[[], Phantom]] = {
    "stiff": stiff_phantom,
    "soft": soft_phantom,
    "compliant-vessel": compliant_vessel_phantom,
    "coarse": coarse_phantom,
}

#: Each effect's command-line name and parameters (those of its class in :mod:`usdeform.sim.effects`;
#: ``viscoelasticity`` takes one Prony term ``g`` (fraction), ``tau_s`` (s) per option, ``layer`` one
#: layer per option, from the surface down).
EFFECT_PARAMETERS: dict[str, tuple[str, ...]] = {
    "latency": ("image_delay_s", "force_delay_s", "pose_delay_s"),
    "force-sensor": ("bias_n", "drift_n_per_s", "uncompensated_weight_n", "lag_s", "gain_error"),
    "viscoelasticity": ("g", "tau_s"),
    "sound-speed": ("sound_speed_error_m_s",),
    "tilt": ("tilt_deg", "surface_inclination_deg", "travel_along_axis"),
    "convex-face": ("radius_mm",),
    "out-of-plane": ("shift_mm_per_mm", "jitter_mm", "drift_mm_per_s"),
    "layer": ("thickness_mm", "shear_modulus_kpa", "yeoh_c2", "yeoh_c3"),
    "sliding": (),
    "lumen-pressure": ("pressure_kpa",),
}
#: Each effect parameter's physical bounds: wider than the realistic ranges of :mod:`usdeform.sim.effects`'s
#: docstrings, narrower than what no recording could show (a delay longer than a palpation, a sound speed near 0).
EFFECT_BOUNDS: dict[str, Number] = {
    number.name: number
    for number in (
        Number("image_delay_s", -1.0, 1.0),
        Number("force_delay_s", -1.0, 1.0),
        Number("pose_delay_s", -1.0, 1.0),
        Number("bias_n", -50.0, 50.0),
        Number("drift_n_per_s", -1.0, 1.0),
        Number("uncompensated_weight_n", -50.0, 50.0),
        Number("lag_s", 0.0, 1.0),
        Number("gain_error", -0.5, 0.5),
        Number("g", 0.0, 1.0, above=True),
        Number("tau_s", 0.01, 1000.0),
        Number("sound_speed_error_m_s", -150.0, 150.0),
        Number("tilt_deg", -30.0, 30.0),
        Number("surface_inclination_deg", -30.0, 30.0),
        Number("travel_along_axis", 0.0, 1.0),
        Number("radius_mm", 5.0, 10_000.0),
        Number("shift_mm_per_mm", -1.0, 1.0),
        Number("jitter_mm", 0.0, 2.0),
        Number("drift_mm_per_s", -2.0, 2.0),
        Number("thickness_mm", 0.1, 100.0),
        Number("shear_modulus_kpa", 0.1, 1000.0),
        Number("yeoh_c2", -10.0, 10.0),
        Number("yeoh_c3", 0.0, 10.0),
        Number("pressure_kpa", 0.0, 30.0),
    )
}
#: The command line's own numbers: positions and lengths within any phantom, frames and pixels within what a
#: scanner records (the memory a recording needs is checked too), a hold of at most 10 minutes (the force loop runs
#: at 1 kHz), a mesh no finer than a quarter of the presets' 2 mm (16 times their elements).
_SIMULATE_NUMBERS: dict[str, Number] = {
    number.name: number
    for number in (
        Number("at_mm", 0.0, 1000.0),
        Number("force_n", 0.5, 1000.0),  # below 0.5 N no probe holds steady contact
        Number("length_mm", 1.0, 1000.0),
        Number("frames", 2, 100_000, integer=True),
        Number("hold_s", 0.0, 600.0),
        Number("rows", 8, 4096, integer=True),
        Number("cols", 8, 4096, integer=True),
        Number("mesh_mm", 0.5, 10.0),
    )
}
_REQUIRED = {"viscoelasticity": ("g", "tau_s"), "layer": ("thickness_mm", "shear_modulus_kpa")}
_SIMPLE_EFFECTS: dict[str, Callable[..., object]] = {
    "latency": ImageLatency,
    "force-sensor": ForceSensorError,
    "sound-speed": SoundSpeedMismatch,
    "tilt": ProbeTilt,
    "convex-face": ConvexProbeFace,
    "out-of-plane": OutOfPlaneMotion,
    "lumen-pressure": LumenPressure,
}

_TRUTH_FIELDS = tuple(f.name for f in dataclasses.fields(GroundTruth))


def _effect_parameters(text: str) -> tuple[str, dict[str, float]]:
    name, _, listed = text.partition(":")
    if name not in EFFECT_PARAMETERS:
        raise InputError(f"effect {text!r}: unknown effect {name!r}; expected one of {', '.join(EFFECT_PARAMETERS)}")
    parameters: dict[str, float] = {}
    for item in filter(None, listed.split(",")):
        key, equals, value = item.partition("=")
        if not equals or key not in EFFECT_PARAMETERS[name]:
            raise InputError(
                f"effect {text!r}: {item!r} is not PARAMETER=VALUE with a parameter of {name} "
                f"({', '.join(EFFECT_PARAMETERS[name]) or 'none'})"
            )
        if key in parameters:
            raise InputError(f"effect {text!r}: {key} given twice")
        try:
            number = float(value)
        except ValueError:
            raise InputError(f"effect {text!r}: {key}: expected a number, got {value!r}") from None
        parameters[key] = EFFECT_BOUNDS[key].check(number, f"effect {text!r}: {key}")
    missing = [key for key in _REQUIRED.get(name, ()) if key not in parameters]
    if missing:
        raise InputError(f"effect {text!r}: {name} needs {', '.join(missing)}")
    if name not in ("sliding", *_REQUIRED) and not parameters:
        raise InputError(f"effect {text!r}: give at least one of {', '.join(EFFECT_PARAMETERS[name])}")
    return name, parameters


def parse_effects(texts: Iterable[str]) -> Effects:
    """Effects from ``NAME[:PARAMETER=VALUE,...]`` texts (:data:`EFFECT_PARAMETERS`).

    Repeated ``viscoelasticity`` options add Prony terms, repeated ``layer`` options add layers from
    the surface down; any other effect may be given once.

    Examples
    --------
    >>> effects = parse_effects(["viscoelasticity:g=0.3,tau_s=1.5", "latency:image_delay_s=0.05", "sliding"])
    >>> effects.viscoelasticity.prony, effects.latency.image_delay_s, effects.sliding.enabled
    (((0.3, 1.5),), 0.05, True)
    """
    prony: list[tuple[float, float]] = []
    layers: list[Layer] = []
    chosen: list[object] = []
    seen: set[str] = set()
    for text in texts:
        name, parameters = _effect_parameters(text)
        if name == "viscoelasticity":
            prony.append((parameters["g"], parameters["tau_s"]))
        elif name == "layer":
            layers.append(Layer(**parameters))
        elif name in seen:
            raise InputError(f"effect {text!r}: {name} given twice")
        else:
            seen.add(name)
            chosen.append(SlidingContact(True) if name == "sliding" else _SIMPLE_EFFECTS[name](**parameters))
    if prony:
        chosen.append(Viscoelasticity(tuple(prony)))
    if layers:
        chosen.append(LayeredTissue(tuple(layers)))
    return Effects.of(chosen)  # type: ignore[arg-type]  # the effect classes above


def write_ground_truth(path: str | Path, truth: GroundTruth) -> None:
    """Write a recording's ground truth as a compressed NumPy archive (one array per field), atomically."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **{name: getattr(truth, name) for name in _TRUTH_FIELDS})
    with atomic_output(Path(path)) as handle:
        handle.write(buffer.getvalue())


def read_ground_truth(path: str | Path) -> GroundTruth:
    """The :class:`~usdeform.sim.GroundTruth` that :func:`write_ground_truth` wrote (a file written before
    ``probe_tilt_deg``, ``face_height_mm`` or ``surface_bend`` was recorded holds untilted frames of a flat face
    on a flat surface: zeros and identities)."""
    try:
        with np.load(Path(path), allow_pickle=False) as archive:
            fields = {name: archive[name] for name in _TRUTH_FIELDS if name in archive.files}
            for added in ("probe_tilt_deg", "face_height_mm"):
                if added not in fields and "force_n" in fields:
                    fields[added] = np.zeros(len(fields["force_n"]))
            if "surface_bend" not in fields and "force_n" in fields:  # written before curved surfaces: flat
                fields["surface_bend"] = np.tile(np.eye(4), (len(fields["force_n"]), 1, 1))
            missing = [name for name in _TRUTH_FIELDS if name not in fields]
            if missing:
                raise FileFormatError(f"{path}: not a ground-truth file: missing {', '.join(missing)}")
            return GroundTruth(**fields)
    except (ValueError, OSError) as error:
        if isinstance(error, FileNotFoundError):
            raise
        raise FileFormatError(f"{path}: not a ground-truth file ({error})") from None


def _truth_path(sequence_path: Path) -> Path:
    name = sequence_path.name
    for suffix in (".seq.nrrd", ".seq.mha", ".mha", ".nrrd"):
        if name.endswith(suffix):
            return sequence_path.with_name(name[: -len(suffix)] + ".truth.npz")
    return sequence_path.with_name(name + ".truth.npz")


def simulate_to_files(
    output_dir: str | Path,
    protocol: Literal["palpation", "sweep"],
    *,
    phantom: Phantom,
    positions_mm: Sequence[float] = (),
    forces_n: Sequence[float] = (),
    length_mm: float = 40.0,
    n_frames: int | None = None,
    ramp: Literal["up", "up-down", "up-hold-down"] = "up",
    hold_s: float = 0.0,
    effects: Effects | None = None,
    rows: int = 256,
    cols: int = 256,
    seed: int = 0,
    progress: bool = True,
) -> list[Path]:
    """Simulate recordings and write each as ``DIR/NAME.seq.nrrd`` with ``DIR/NAME.truth.npz`` beside it.

    Parameters
    ----------
    output_dir : str or Path
        Folder (created).
    protocol : {"palpation", "sweep"}
        ``palpation``: one recording per position in ``positions_mm`` and force in ``forces_n`` (the
        highest force of the ramp, N), named ``palpation_<s>mm_<F>N``. ``sweep``: one constant-force
        sweep per start position and force, over ``length_mm`` along the phantom, ``sweep_<s>mm_<F>N``.
    phantom : Phantom
        The phantom.
    positions_mm, forces_n : sequence of float
        Positions along the phantom (mm) and forces (N); every combination is recorded.
    length_mm : float
        Sweep length, mm.
    n_frames : int, optional
        Frames per recording (default: 50 per palpation, 400 per sweep).
    ramp, hold_s
        The palpation's force ramp (see :func:`usdeform.sim.simulate_palpation`).
    effects : Effects, optional
        Physical effects (:func:`parse_effects`).
    rows, cols : int
        Frame size, pixels.
    seed : int
        Seed; recording ``i`` uses the ``i``-th draw of ``numpy.random.SeedSequence(seed)``.
    progress : bool
        Show a tqdm bar on stderr.

    Returns
    -------
    list of Path
        The sequence files written (each with its ``.truth.npz``).
    """
    if protocol not in ("palpation", "sweep"):
        raise InputError(f"protocol: expected 'palpation' or 'sweep', got {protocol!r}")
    if not positions_mm or not forces_n:
        raise InputError("positions_mm, forces_n: give at least one position and one force")
    if int(seed) != seed or seed < 0:
        raise InputError(f"seed: expected a non-negative integer, got {seed!r}")
    if n_frames is not None and (int(n_frames) != n_frames or n_frames < 2):
        raise InputError(f"n_frames (--frames): expected an integer >= 2, got {n_frames!r}")
    frames = (50 if protocol == "palpation" else 400) if n_frames is None else int(n_frames)
    # the frames, zero-force frames, two lumen masks (1 byte each) and the float32 displacement pair of each pixel
    checked_byte_count(
        (frames, rows, cols), 12, "frames x rows x cols (--frames, --rows, --cols)", error=MemoryLimitError
    )
    for force in forces_n:
        if force > phantom.max_force_n:
            raise InputError(
                f"forces_n (--force): {force:g} N is above the {phantom.name} phantom's highest force, "
                f"{phantom.max_force_n:g} N (its mechanics are solved up to that force)"
            )
    for position in positions_mm:
        ends = (position, position + length_mm) if protocol == "sweep" else (position,)
        if not all(0.0 <= end <= phantom.length_mm for end in ends):
            raise InputError(
                f"positions_mm (--at): {position:g} mm{' + length_mm (--length)' if protocol == 'sweep' else ''} "
                f"is outside the phantom [0, {phantom.length_mm:g}] mm"
            )
    output = Path(output_dir)
    created = new_output_folders(output, "output_dir (--output)")
    jobs = [(float(s), float(f)) for s in positions_mm for f in forces_n]
    seeds = [int(s) for s in np.random.SeedSequence(int(seed)).generate_state(len(jobs))]
    try:
        output.mkdir(parents=True, exist_ok=True)
        with outputs_together():  # every recording replaces its files, or none does
            return _simulate_jobs(output, protocol, phantom, jobs, seeds, frames, length_mm, ramp, hold_s, effects,
                                  rows, cols, progress)  # fmt: skip
    except BaseException:  # errors, Ctrl-C, SIGTERM: a failed run leaves no folder it made
        if created:
            shutil.rmtree(created[-1], ignore_errors=True)
        raise


def _simulate_jobs(
    output: Path,
    protocol: Literal["palpation", "sweep"],
    phantom: Phantom,
    jobs: list[tuple[float, float]],
    seeds: list[int],
    n_frames: int,
    length_mm: float,
    ramp: Literal["up", "up-down", "up-hold-down"],
    hold_s: float,
    effects: Effects | None,
    rows: int,
    cols: int,
    progress: bool,
) -> list[Path]:
    written = []
    for (position, force), recording_seed in zip(
        tqdm(jobs, desc=f"simulate {protocol}s", unit="recording", disable=not progress), seeds, strict=True
    ):
        if protocol == "palpation":
            recording, truth = simulate_palpation(
                phantom,
                position,
                force,
                n_frames,
                ramp,
                recording_seed,
                effects,
                rows,
                cols,
                hold_s=hold_s,
            )
        else:
            recording, truth = simulate_sweep(
                phantom,
                position,
                length_mm,
                force,
                n_frames,
                recording_seed,
                effects,
                rows,
                cols,
            )
        path = output / f"{protocol}_{position:g}mm_{force:g}N.seq.nrrd"
        write_sequence(path, recording)
        write_ground_truth(_truth_path(path), truth)
        written.append(path)
    return written


def _run(args: argparse.Namespace) -> None:
    phantom = PHANTOMS[args.preset]()
    if args.mesh_mm is not None:
        phantom = phantom.with_section_changes(mesh_size_mm=args.mesh_mm)
    if args.protocol == "follow-up" or args.record_next is not None:
        from ..gap.follow_up_sim import run_follow_up_command

        return run_follow_up_command(args, phantom, parse_effects(args.effect))
    forces = args.force or [phantom.max_force_n if args.protocol == "palpation" else phantom.max_force_n / 2]
    written = simulate_to_files(
        args.output,
        args.protocol,
        phantom=phantom,
        positions_mm=args.at,
        forces_n=forces,
        length_mm=args.length,
        n_frames=args.frames,
        ramp=args.ramp,
        hold_s=args.hold,
        effects=parse_effects(args.effect),
        rows=args.rows,
        cols=args.cols,
        seed=args.seed,
    )
    for path in written:
        print(f"wrote {path} and {_truth_path(path).name}")


def add_simulate_command(commands: argparse._SubParsersAction) -> None:
    """Add ``usdeform simulate`` to the command line's subparsers."""
    effects = "; ".join(f"{name}: {', '.join(keys) or 'no parameters'}" for name, keys in EFFECT_PARAMETERS.items())
    parser = commands.add_parser(
        "simulate",
        help="simulate palpations or sweeps: PLUS sequence files with the ground truth beside them",
        description="Simulate robotic palpations or constant-force sweeps on a finite-element phantom and write "
        "them as PLUS sequence files (DIR/NAME.seq.nrrd) with their ground truth (DIR/NAME.truth.npz: zero-force "
        "frames, lumen masks, true displacement field, true force, probe displacement, sweep position).",
    )
    parser.add_argument("protocol", choices=["palpation", "sweep", "follow-up"], help="what the robot does")
    parser.add_argument("record_next", nargs="?", help="follow-up: the record_next.json of 'usdeform diagnose'")
    parser.add_argument("--output", type=Path, required=True, metavar="DIR", help="output folder")
    parser.add_argument("--preset", choices=list(PHANTOMS), default="stiff", help="the phantom (default: stiff)")
    parser.add_argument(
        "--at",
        type=_SIMULATE_NUMBERS["at_mm"].argument(),
        nargs="+",
        default=[40.0],
        metavar="MM",
        help="palpation positions, or sweep starts, mm along the phantom (default: 40)",
    )
    parser.add_argument(
        "--force",
        type=_SIMULATE_NUMBERS["force_n"].argument(),
        nargs="+",
        metavar="N",
        help="palpation: highest force of the ramp; sweep: target force; N, one recording per force "
        "(default: the phantom's highest force for palpations, half of it for sweeps)",
    )
    parser.add_argument(
        "--length",
        type=_SIMULATE_NUMBERS["length_mm"].argument(),
        default=40.0,
        metavar="MM",
        help="sweep length, mm (default: 40)",
    )
    parser.add_argument(
        "--frames",
        type=_SIMULATE_NUMBERS["frames"].argument(),
        metavar="N",
        help="frames per recording (default: 50 / 400)",
    )
    parser.add_argument("--ramp", choices=["up", "up-down", "up-hold-down"], default="up", help="palpation ramp")
    parser.add_argument(
        "--hold",
        type=_SIMULATE_NUMBERS["hold_s"].argument(),
        default=0.0,
        metavar="S",
        help="hold at the top of up-hold-down, s",
    )
    parser.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME[:PARAMETER=VALUE,...]",
        help=f"a physical effect, repeatable, e.g. viscoelasticity:g=0.3,tau_s=1.5. Effects and parameters: {effects}",
    )
    parser.add_argument(
        "--rows", type=_SIMULATE_NUMBERS["rows"].argument(), default=256, help="frame rows, pixels (default: 256)"
    )
    parser.add_argument(
        "--cols", type=_SIMULATE_NUMBERS["cols"].argument(), default=256, help="frame columns, pixels (default: 256)"
    )
    parser.add_argument(
        "--mesh-mm",
        type=_SIMULATE_NUMBERS["mesh_mm"].argument(),
        metavar="MM",
        help="finite-element mesh size (default: the preset's)",
    )
    parser.add_argument("--seed", type=NUMBERS["seed"].argument(), default=0, help="seed (default: 0)")
    parser.set_defaults(run=_run)
