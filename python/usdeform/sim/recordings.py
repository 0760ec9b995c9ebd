"""Simulated robotic recordings: force-controlled palpation and sweep, with per-frame ground truth.

A recording is simulated the way a real system produces one. A 1-DOF admittance force controller
moves the probe vertically (along its axis unless tilted) on the force sensor's clock (1 kHz), pressing on the phantom's
finite-element mechanics (through the effects' viscoelasticity and sensor errors) while small robot
position ripple disturbs it. The pose is sampled on its own, slower clock (250 Hz), the B-mode
frames at 50 fps on a third clock; as in a real pipeline, each frame gets the force and pose
interpolated to its timestamp. Each frame is rendered from the tissue state at its acquisition
time (its timestamp minus the image latency, if that effect is on); a delayed force or pose stream
(:class:`usdeform.sim.effects.ImageLatency`) gives each frame the value its stream stamped with the
frame's time, acquired that much earlier.

Ground truth per frame (:class:`GroundTruth`): the frame at zero force at the same probe position
(same speckle and noise realisation), the vessel lumen masks deformed and at zero force, the
true pixel displacement field from the zero-force frame to the deformed frame, and the true
contact force, lambda and sweep position at acquisition.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable, Hashable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ..errors import InputError
from ..recording import Recording
from ..validation import available_cores, threads_argument
from .effects import Effect, Effects
from .imaging import (
    GriddedDisplacement,
    GriddedSolution,
    ImagingSettings,
    ProbeState,
    ScattererField,
    TissueAcoustics,
    b_mode,
    echo_signal,
    probe_to_surface,
    true_displacement_px,
    unit_complex_noise,
    vessel_mask,
)
from .mechanics import MechanicsSolution, SectionSpec
from .phantoms import Phantom
from .robot import Clocks, ElasticForce, ForceController, SweepPath, Trajectory, run_force_loop

__all__ = [
    "DEFAULT_SURFACE_TO_BASE",
    "Clocks",
    "ForceController",
    "GroundTruth",
    "simulate_palpation",
    "simulate_sweep",
    "truth_image_to_base",
]

DEFAULT_SURFACE_TO_BASE = np.array(
    [[1.0, 0.0, 0.0, 550.0], [0.0, 1.0, 0.0, -40.0], [0.0, 0.0, 1.0, 120.0], [0.0, 0.0, 0.0, 1.0]]
)
"""Phantom surface frame in the robot base: a phantom on a table in front of the robot, axes aligned, mm."""

_MECHANICS_SPACING_MM = 0.5  # frames take the mechanics of the nearest multiple of this sweep position
_FRAMES_PER_BLOCK = 8  # frames per thread whose electronic noise is drawn ahead of rendering


class _SharedOnce:
    """Values made once per key by the first thread that asks (``make(key, *inputs)``, the inputs that thread passes
    to :meth:`get`), shared with the others, and dropped after the last of the uses ``keys`` lists (one per
    occurrence; each use calls :meth:`get` then :meth:`release`)."""

    def __init__(self, make: Callable[..., Any], keys: Iterable[Hashable]):
        self._make = make
        self._uses = Counter(keys)
        self._lock = threading.Lock()
        self._entries: dict[Hashable, list] = {}  # key -> [its lock, its value, or None until made]

    def get(self, key: Hashable, *inputs: Any) -> Any:
        with self._lock:
            entry = self._entries.setdefault(key, [threading.Lock(), None])
        with entry[0]:
            if entry[1] is None:
                entry[1] = self._make(key, *inputs)
            return entry[1]

    def release(self, key: Hashable) -> None:
        with self._lock:
            self._uses[key] -= 1
            if self._uses[key] == 0:
                del self._entries[key]


def _mechanics_position(s_mm: float, phantom: Phantom) -> float:
    """The sweep position whose mechanics (section and solution) a frame at ``s_mm`` uses.

    Sampling the phantom every 0.5 mm shares one solution among the frames of a sweep that lie
    near each other; over 0.5 mm the presets' stiffness changes < 0.5 % and the vessel < 0.03 mm.
    The probe pose and the speckle use the exact position.
    """
    return float(np.clip(np.round(s_mm / _MECHANICS_SPACING_MM) * _MECHANICS_SPACING_MM, 0.0, phantom.length_mm))


@dataclass(frozen=True)
class GroundTruth:
    """Per-frame truth of a simulated recording of n frames (rows x cols pixels).

    zero_force_frames: (n, rows, cols) uint8, the frame at zero force at the same probe position.
    vessel_mask: (n, rows, cols) bool lumen in the recorded (deformed) frame.
    zero_force_vessel_mask: (n, rows, cols) bool lumen in the zero-force frame.
    displacement_px: (n, rows, cols, 2) float32 (d_col, d_row): zero-force pixel (c, r) is at
        (c + d_col, r + d_row) in the recorded frame (backward mapping); NaN where no tissue.
    force_n: (n,) true contact force along the probe axis at acquisition, N.
    probe_displacement_mm: (n,) true lambda at acquisition, mm.
    sweep_position_mm: (n,) true sweep coordinate s at acquisition, mm.
    acquisition_time_s: (n,) when each frame was acquired (its timestamp minus the image latency), s.
    probe_tilt_deg: (n,) the probe's rotation about its elevation axis relative to the surface at acquisition,
        degrees.
    face_height_mm: (n,) the probe face centre's height above the undeformed surface at first contact, mm (0 for
        a flat face level with the surface; see :class:`~usdeform.sim.imaging.ProbeState`).
    surface_bend: (n, 4, 4) the flat surface frame mapped onto the curved one at each frame's position
        (:meth:`~usdeform.sim.robot.SweepPath.surface_bend`; identity on a flat surface).

    The zero-force frames and masks are imaged through the same scanner, pose and imaging effects
    (sound speed, tilt) as the recording: they differ from it only by the deformation (and by any
    out-of-plane motion, which the zero-force frames do not have).
    """

    zero_force_frames: np.ndarray
    vessel_mask: np.ndarray
    zero_force_vessel_mask: np.ndarray
    displacement_px: np.ndarray
    force_n: np.ndarray
    probe_displacement_mm: np.ndarray
    sweep_position_mm: np.ndarray
    acquisition_time_s: np.ndarray
    probe_tilt_deg: np.ndarray
    face_height_mm: np.ndarray
    surface_bend: np.ndarray


def truth_image_to_base(truth: GroundTruth, recording: Recording) -> np.ndarray:
    """``(n, 4, 4)`` image poses (mm) of the simulator's zero-force frames: the probe at each frame's
    true sweep position and tilt at first contact with the unloaded surface (:class:`ProbeState` with lambda 0), on
    the phantom at :data:`DEFAULT_SURFACE_TO_BASE` (not inclined; bent as the sweep's surface), with the
    recording's ``image_to_probe``."""
    probe_to_base = np.stack(
        [
            DEFAULT_SURFACE_TO_BASE
            @ bend
            @ probe_to_surface(ProbeState(float(s), 0.0, float(tilt), face_height_mm=float(h)))
            for s, tilt, h, bend in zip(
                truth.sweep_position_mm, truth.probe_tilt_deg, truth.face_height_mm, truth.surface_bend, strict=True
            )
        ]
    )
    return probe_to_base @ recording.image_to_probe


def _record(
    phantom: Phantom,
    trajectory: Trajectory,
    image_times_s: np.ndarray,
    effects: Effects,
    settings: ImagingSettings,
    acoustics: TissueAcoustics,
    clocks: Clocks,
    surface_to_base: np.ndarray,
    seeds: np.random.SeedSequence,
    tilt_deg: Callable[[float], float],
    threads: int | None,
    surface_bend: Callable[[float], np.ndarray] = lambda s_mm: np.eye(4),
) -> tuple[Recording, GroundTruth]:
    """Sample the streams on their clocks, render every frame and its ground truth; ``tilt_deg`` gives the
    probe's tilt (degrees) at a sweep position (mm), ``surface_bend`` the curved surface's frame there (see
    :meth:`SweepPath.surface_bend`). The frames are rendered in ``threads`` threads (None: one
    per core); each frame's electronic noise is drawn in frame order, so they are the same for any number."""
    acoustics = effects.sound_speed.acoustics(acoustics)
    scatterer_seed, noise_seed, elevation_seed = seeds.spawn(3)
    field = ScattererField(int(scatterer_seed.generate_state(1)[0]), settings, acoustics)
    noise_rng = np.random.default_rng(noise_seed)
    elevation_draws = np.random.default_rng(elevation_seed).standard_normal(len(image_times_s))
    face_height = float(phantom.section_at(float(trajectory.sweep_position_mm[0])).face_gap_mm(np.zeros(1))[0])
    if effects.tilt.surface_inclination_deg:  # the surface inclined in the base frame, the probe's pose not
        surface_to_base = surface_to_base @ effects.tilt.surface_rotation()

    # Pose stream (its own clock) and per-frame values interpolated to the image timestamps.
    pose_times = np.arange(0.0, trajectory.time_s[-1] + 1e-12, 1.0 / clocks.pose_rate_hz)
    pose_lambda = trajectory.at(pose_times - effects.latency.pose_delay_s, trajectory.probe_displacement_mm)
    pose_position = trajectory.at(pose_times - effects.latency.pose_delay_s, trajectory.sweep_position_mm)
    frame_lambda = np.interp(image_times_s, pose_times, pose_lambda)
    frame_position = np.interp(image_times_s, pose_times, pose_position)
    probe_to_base = np.stack(
        [
            surface_to_base
            @ surface_bend(s)
            @ probe_to_surface(
                ProbeState(s, lam, tilt_deg(s), face_height_mm=face_height, lateral_mm=lam * effects.tilt.travel_slope)
            )
            for s, lam in zip(frame_position, frame_lambda, strict=False)
        ]
    )
    frame_force = trajectory.at(image_times_s - effects.latency.force_delay_s, trajectory.measured_force_n)

    # Tissue state when each frame was acquired.
    acquisition_times = image_times_s - effects.latency.image_delay_s
    true_lambda = trajectory.at(acquisition_times, trajectory.probe_displacement_mm)
    true_position = trajectory.at(acquisition_times, trajectory.sweep_position_mm)
    true_force = trajectory.at(acquisition_times, trajectory.true_force_n)
    true_tilt = np.array([tilt_deg(s) for s in true_position])
    reach_tilt = float(true_tilt[np.argmax(np.abs(true_tilt))])  # the grids cover the most tilted frame

    n = len(image_times_s)
    shape = (n, settings.rows, settings.cols)
    frames, zero_force_frames = np.empty(shape, np.uint8), np.empty(shape, np.uint8)
    masks, zero_force_masks = np.empty(shape, bool), np.empty(shape, bool)
    displacements = np.empty((*shape, 2), np.float32)
    probes, mechanics_positions = [], []
    # mechanics position -> (section, solution), solved in frame order before any frame is rendered
    mechanics: dict[float, tuple[SectionSpec, MechanicsSolution]] = {}
    for index in range(n):
        position, lam = float(true_position[index]), max(float(true_lambda[index]), 0.0)
        shift = effects.out_of_plane.shift_mm(lam, float(elevation_draws[index]), float(acquisition_times[index]))
        probes.append(
            ProbeState(position, lam, float(true_tilt[index]), shift, face_height, lam * effects.tilt.travel_slope)
        )
        mechanics_position = _mechanics_position(position, phantom)
        mechanics_positions.append(mechanics_position)
        if mechanics_position not in mechanics:
            mechanics[mechanics_position] = (
                phantom.section_at(mechanics_position),
                phantom.solution_at(mechanics_position),
            )

    def gridded(mechanics_position: float) -> tuple[GriddedSolution, GriddedDisplacement]:
        """The section's field on the imaging grid, and its field at zero force."""
        fields = GriddedSolution(
            mechanics[mechanics_position][1], mechanics[mechanics_position][0], settings, reach_tilt
        )
        return fields, fields.at(0.0)

    # frames at the same sweep position with the same mechanics share their zero-force frame (a palpation: all)
    zero_force_keys = [(mechanics_positions[index], probes[index].sweep_position_mm) for index in range(n)]
    zero_force_probes: dict[tuple[float, float], ProbeState] = {}
    for key, probe in zip(zero_force_keys, probes, strict=True):
        if key not in zero_force_probes:
            zero_force_probes[key] = probe.at_zero_force()

    def at_zero_force(
        key: tuple[float, float], zero_force_displacement: GriddedDisplacement
    ) -> tuple[np.ndarray, np.ndarray]:
        """The lumen mask and noiseless echo at zero force of the frames of ``key`` (mechanics position, sweep
        position), whose section's field at zero force is ``zero_force_displacement``."""
        section, solution = mechanics[key[0]]
        probe = zero_force_probes[key]
        return vessel_mask(solution, probe, settings, acoustics), echo_signal(
            field, section, zero_force_displacement, probe, settings, acoustics
        )

    fields_by_position = _SharedOnce(gridded, mechanics_positions)
    zero_force_by_key = _SharedOnce(at_zero_force, zero_force_keys)

    def render(index: int, noise: np.ndarray) -> None:
        probe, mechanics_position = probes[index], mechanics_positions[index]
        section, solution = mechanics[mechanics_position]
        fields, zero_force_displacement = fields_by_position.get(mechanics_position)
        zero_force_mask, zero_force_echo = zero_force_by_key.get(zero_force_keys[index], zero_force_displacement)
        displacement = fields.at(probe.probe_displacement_mm)
        frames[index] = b_mode(echo_signal(field, section, displacement, probe, settings, acoustics), noise, settings)
        zero_force_frames[index] = b_mode(zero_force_echo, noise, settings)
        masks[index] = vessel_mask(solution, probe, settings, acoustics)
        zero_force_masks[index] = zero_force_mask
        displacements[index] = true_displacement_px(
            section, zero_force_displacement, displacement, probe, settings, acoustics
        )
        fields_by_position.release(mechanics_position)
        zero_force_by_key.release(zero_force_keys[index])

    workers = threads or available_cores()
    with ThreadPoolExecutor(workers) as pool:
        for first in range(0, n, _FRAMES_PER_BLOCK * workers):
            block = range(first, min(first + _FRAMES_PER_BLOCK * workers, n))
            noises = [unit_complex_noise(noise_rng, settings) for _ in block]  # drawn in frame order
            pending = [pool.submit(render, index, noise) for index, noise in zip(block, noises, strict=True)]
            try:
                for frame in pending:
                    frame.result()
            except BaseException:  # a frame failed, or an interrupt: drop the frames of the block not yet started
                for frame in pending:
                    frame.cancel()
                raise

    recording = Recording(
        frames=frames,
        timestamps=image_times_s,
        probe_to_base=probe_to_base,
        pose_valid=np.ones(n, dtype=bool),
        image_to_probe=settings.image_to_probe,
        force=frame_force,
        probe_displacement=frame_lambda,
    )
    truth = GroundTruth(
        zero_force_frames=zero_force_frames,
        vessel_mask=masks,
        zero_force_vessel_mask=zero_force_masks,
        displacement_px=displacements,
        force_n=true_force,
        probe_displacement_mm=true_lambda,
        sweep_position_mm=true_position,
        acquisition_time_s=acquisition_times,
        probe_tilt_deg=true_tilt,
        face_height_mm=np.full(n, face_height),
        surface_bend=np.stack([surface_bend(float(s)) for s in true_position]),
    )
    return recording, truth


def _prepare(
    phantom: Phantom,
    seed: int,
    effects: Effects | Iterable[Effect] | None,
    rows: int,
    cols: int,
    settings: ImagingSettings | None,
    surface_to_base: np.ndarray,
) -> tuple[Phantom, Effects, ImagingSettings, np.random.SeedSequence]:
    """Check the common arguments; apply the mechanical effects to the phantom; split the seed."""
    surface_to_base = np.asarray(surface_to_base, dtype=float)
    if (
        surface_to_base.shape != (4, 4)
        or not np.all(np.isfinite(surface_to_base))
        or not np.array_equal(surface_to_base[3], [0, 0, 0, 1])
    ):
        raise InputError("surface_to_base: expected a finite (4, 4) homogeneous transform with last row [0, 0, 0, 1]")
    if not isinstance(phantom, Phantom):
        raise InputError(f"phantom: expected a usdeform.sim.phantoms.Phantom, got {type(phantom).__name__}")
    if int(seed) != seed or seed < 0:
        raise InputError(f"seed: expected a non-negative integer, got {seed!r}")
    chosen = Effects.of(effects)
    changes = chosen.section_changes()
    if changes:
        phantom = phantom.with_section_changes(**changes)
    if settings is None:
        settings = ImagingSettings(rows=rows, cols=cols)
    elif (settings.rows, settings.cols) != (rows, cols):
        raise InputError(f"rows, cols ({rows}, {cols}) disagree with settings ({settings.rows}, {settings.cols})")
    return phantom, chosen, settings, np.random.SeedSequence(int(seed))


def _spread_image_times(duration_s: float, n_frames: int, clocks: Clocks) -> np.ndarray:
    """Timestamps of ``n_frames`` frames of the image stream spread evenly over [0, duration_s]."""
    available = int(np.floor((duration_s - clocks.image_offset_s) * clocks.image_rate_hz + 1e-9)) + 1
    if available < n_frames:
        raise InputError(
            f"n_frames: {n_frames} frames do not fit in {duration_s:.3g} s at {clocks.image_rate_hz} fps "
            f"({available} available)"
        )
    ticks = np.rint(np.linspace(0, available - 1, n_frames)).astype(int)
    return clocks.image_offset_s + ticks / clocks.image_rate_hz


def simulate_palpation(
    phantom: Phantom,
    s_mm: float,
    max_force_n: float,
    n_frames: int = 50,
    ramp: Literal["up", "up-down", "up-hold-down"] = "up",
    seed: int = 0,
    effects: Effects | Iterable[Effect] | None = None,
    rows: int = 256,
    cols: int = 256,
    *,
    ramp_rate_n_per_s: float = 5.0,
    hold_s: float = 0.0,
    settings: ImagingSettings | None = None,
    acoustics: TissueAcoustics = TissueAcoustics(),
    clocks: Clocks = Clocks(),
    controller: ForceController = ForceController(),
    surface_to_base: np.ndarray = DEFAULT_SURFACE_TO_BASE,
    threads: int | None = None,
    surface_bend: np.ndarray | None = None,
) -> tuple[Recording, GroundTruth]:
    """Robotic palpation at sweep position ``s_mm``: the target force ramps 0 -> ``max_force_n``
    (N) at ``ramp_rate_n_per_s`` (and back down for ``ramp="up-down"``; ``ramp="up-hold-down"``
    holds ``max_force_n`` for ``hold_s`` seconds before ramping down, as real palpations that show
    relaxation and sensor drift do) under force control.

    Returns the Recording (``n_frames`` frames spread evenly over the ramp, rows x cols pixels)
    and its :class:`GroundTruth`. Deterministic for a given ``seed``, the same for any number of ``threads``
    rendering the frames (None: one per core). ``surface_bend``: the curved surface's frame at ``s_mm``
    (:meth:`SweepPath.surface_bend` of the sweep this palpation serves; None: flat).
    """
    threads = threads_argument(threads)
    phantom, chosen, settings, seeds = _prepare(phantom, seed, effects, rows, cols, settings, surface_to_base)
    if ramp not in ("up", "up-down", "up-hold-down"):
        raise InputError(f"ramp: expected 'up', 'up-down' or 'up-hold-down', got {ramp!r}")
    if not (np.isfinite(hold_s) and hold_s >= 0) or (hold_s > 0 and ramp != "up-hold-down"):
        raise InputError(
            f"hold_s: expected a non-negative time in s, used only with ramp='up-hold-down', got {hold_s!r}"
        )
    if not (np.isfinite(max_force_n) and max_force_n > 0):
        raise InputError(f"max_force_n: expected a positive force in N, got {max_force_n!r}")
    if not (np.isfinite(ramp_rate_n_per_s) and ramp_rate_n_per_s > 0):
        raise InputError(f"ramp_rate_n_per_s: expected a positive rate in N/s, got {ramp_rate_n_per_s!r}")
    if int(n_frames) != n_frames or n_frames < 2:
        raise InputError(f"n_frames: expected an integer >= 2, got {n_frames!r}")
    position = float(s_mm)
    phantom.section_at(position)  # validates s_mm against the phantom
    rise_s = max_force_n / ramp_rate_n_per_s
    hold = hold_s if ramp == "up-hold-down" else 0.0
    ramp_s = rise_s if ramp == "up" else 2 * rise_s + hold

    def target(time: float) -> float:
        if time <= rise_s:
            return ramp_rate_n_per_s * time
        if time <= rise_s + hold:
            return max_force_n
        return max(ramp_rate_n_per_s * (2 * rise_s + hold - time), 0.0)

    control_seed, record_seed = seeds.spawn(2)

    def tilt(s_mm: float) -> float:
        return chosen.tilt.relative_deg

    trajectory = run_force_loop(
        target,
        lambda time: position,
        tilt,
        ramp_s + 2.0 / clocks.pose_rate_hz,  # every stream brackets the last frame
        0.0,
        ElasticForce(phantom, position, position),
        chosen,
        controller,
        clocks,
        np.random.default_rng(control_seed),
    )
    image_times = _spread_image_times(ramp_s, n_frames, clocks)
    bend = np.eye(4) if surface_bend is None else np.asarray(surface_bend, dtype=np.float64)
    if bend.shape != (4, 4) or not np.all(np.isfinite(bend)):
        raise InputError(f"surface_bend: expected a finite (4, 4) transform, got shape {bend.shape}")
    return _record(
        phantom,
        trajectory,
        image_times,
        chosen,
        settings,
        acoustics,
        clocks,
        surface_to_base,
        record_seed,
        tilt,
        threads,
        lambda s_mm: bend,
    )


def simulate_sweep(
    phantom: Phantom,
    start_s_mm: float,
    length_mm: float,
    target_force_n: float,
    n_frames: int = 400,
    seed: int = 0,
    effects: Effects | Iterable[Effect] | None = None,
    rows: int = 256,
    cols: int = 256,
    *,
    settings: ImagingSettings | None = None,
    acoustics: TissueAcoustics = TissueAcoustics(),
    clocks: Clocks = Clocks(),
    controller: ForceController = ForceController(),
    surface_to_base: np.ndarray = DEFAULT_SURFACE_TO_BASE,
    frame_step: int = 1,
    path: SweepPath = SweepPath(),
    threads: int | None = None,
) -> tuple[Recording, GroundTruth]:
    """Force-controlled sweep along base y from ``start_s_mm`` over ``length_mm`` (mm) at
    ``target_force_n`` (N), recording ``n_frames`` frames, every ``frame_step``-th of the 50 fps
    stream (1: consecutive frames; 3 at 0.5 mm apart: 8.3 mm/s, a robot's sweep speed).

    The probe starts pressed to the target force at the start position and moves at constant
    speed (length over the frames' duration), tilted along the way as ``path`` says (on top of a
    :class:`~usdeform.sim.effects.ProbeTilt`); the force controller tracks the target while the
    stiffness under the probe changes. Returns the Recording and its :class:`GroundTruth`, the same for any
    number of ``threads`` rendering the frames (None: one per core).
    """
    threads = threads_argument(threads)
    phantom, chosen, settings, seeds = _prepare(phantom, seed, effects, rows, cols, settings, surface_to_base)
    if not (np.isfinite(target_force_n) and target_force_n > 0):
        raise InputError(f"target_force_n: expected a positive force in N, got {target_force_n!r}")
    if not (np.isfinite(length_mm) and length_mm > 0):
        raise InputError(f"length_mm: expected a positive length in mm, got {length_mm!r}")
    if int(n_frames) != n_frames or n_frames < 2:
        raise InputError(f"n_frames: expected an integer >= 2, got {n_frames!r}")
    if int(frame_step) != frame_step or frame_step < 1:
        raise InputError(f"frame_step: expected an integer >= 1, got {frame_step!r}")
    start, end = float(start_s_mm), float(start_s_mm) + float(length_mm)
    phantom.section_at(start), phantom.section_at(end)  # validates the range against the phantom
    image_times = clocks.image_offset_s + np.arange(n_frames) * int(frame_step) / clocks.image_rate_hz
    speed = length_mm / (image_times[-1] - image_times[0])
    elastic_force = ElasticForce(phantom, start, end)

    def sweep_position(time: float) -> float:  # moves from the first frame to the last
        return float(np.clip(start + speed * (time - image_times[0]), start, end))

    def tilt(s_mm: float) -> float:
        return chosen.tilt.relative_deg + path.tilt_deg((s_mm - start) / length_mm)

    def bend(s_mm: float) -> np.ndarray:
        return path.surface_bend(s_mm, start + 0.5 * length_mm)

    control_seed, record_seed = seeds.spawn(2)
    trajectory = run_force_loop(
        lambda time: target_force_n,
        sweep_position,
        tilt,
        image_times[-1] + 2.0 / clocks.pose_rate_hz,  # every stream brackets the last frame
        elastic_force.probe_displacement_at(start, target_force_n),
        elastic_force,
        chosen,
        controller,
        clocks,
        np.random.default_rng(control_seed),
    )
    return _record(
        phantom,
        trajectory,
        image_times,
        chosen,
        settings,
        acoustics,
        clocks,
        surface_to_base,
        record_seed,
        tilt,
        threads,
        bend,
    )
