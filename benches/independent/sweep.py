"""Sweeps of the independent generator: one drawn case (phantom, scanner, hidden effect of ``cases.py``) recorded as
two palpations and a force-controlled sweep along the elevation direction, with and without the effect from the
same seeds, and the lumen's ground truth for every sweep frame (benches/compensation_independent.py is its command).

Why: ``usdeform fit`` learns the deformation from palpations and ``usdeform correct`` undoes it on a sweep; a
recording effect withheld from the method (an image or force delay, a force-sensor offset, creep, a wrong speed of
sound) then costs the corrected sweep some accuracy, and ``--compensate diagnosis.json`` is meant to give it back.
To measure that on data usdeform did not make, everything here is the independent generator's: its Q4 Demiray FEM
(``mechanics``), its texture and RF B-mode model (``imaging``) and its timeline and effects (``cases``: the
palpations and the sweep are made by the same ``cases.record_palpation`` that writes the gap benchmark's
palpations, so an effect is applied to all three recordings exactly as there).

The case (``draw``): ``cases._draw_case`` draws the phantom, scanner, palpation protocol and the hidden effect's
parameters from one stream; the protocol draws come before the effect's, so the same stream gives the same case
with the effect (``effect=True``) and without it (``effect=False``: kind ``null``, nothing hidden, the same phantom,
scanner, timelines, speckle, noise and poses; the streams are children of the case's seed made without
``SeedSequence.spawn``'s state, see ``children``). Only kinds that leave the phantom alone are offered (``KINDS``): the
timing, force-sensor, creep and sound-speed effects; a kind that changes the tissue has no "same case without it".

Palpations: two load-hold-unload palpations of ``cases.Protocol`` (contact 0.2-0.5 N, up to 8-20 N, hold 1.5-3 s,
20-30 fps, force noise 0.02-0.06 N, position ripple 0.01-0.05 mm: the ranges of ``cases``), the first at the drawn
ramp rate (3-6 N/s), the second at another (the drawn rate times 0.6-0.75 or 1.35-1.6, kept in 2-8 N/s) and hold
(1.5-3 s), at 10 % and 90 % of the sweep's length along elevation, with their own noise and frame streams.

Sweep (``SweepProtocol``): the probe approaches from contact at the palpation ramp rate to a target force of 40-60 %
of the palpations' peak (a sweep is made at a moderate force that keeps the vessel open), settles 1 s and then
translates along elevation at 5-10 mm/s for 3-6 s (15-60 mm: the length of a carotid or forearm vein scan) while the
force loop holds the target. The contact force the loop achieves is the target plus its tracking error: a slow
oscillation of 0.5-1 N amplitude at 0.2-0.5 Hz (the loop chasing the tissue's and the robot's slow disturbances
along the path) and 0.1-0.3 N rms of ripple at 2-5 Hz (the sum of six sinusoids of random frequency and phase in
that band, an admittance loop's ringing and the arm's vibration), faded in over the settle. These ranges are
of the order robotic force-controlled ultrasound reports (errors of a few tenths of a newton to
about one newton around a 5-15 N set point). The probe's travel is the inverse of the FEM force curve of the elastic
force (``cases._trajectory``: under creep the loop holds the total force and the indentation creeps), plus the
robot's position ripple; sensor noise and the effect as in the palpations. The phantom is uniform along elevation,
so every sweep frame images the same FEM cross-section; the speckle changes along the path through an elevation
beam (``ElevationTexture``): independent scatterer layers every sigma / 2 sharing the tissue's structure, weighted
by a Gaussian beam of FWHM 1-2 mm (a linear array near its elevation focus, as ``out_of_plane_drift`` draws it),
so frames 0.2-0.5 mm apart decorrelate partly and frames millimetres apart fully. The sweep's frames are written
as sweep.seq.nrrd with ContactForce, ProbeDisplacement (the pose stream's travel since contact) and poses like the
palpations (the same surface-to-base transform; the probe moving along the surface's y, the image normal).

Truth (``zero_force_mask``, ``imaged_mask``): per sweep frame, in its pixel grid (pixel (col, row) at probe x = -W/2 +
col W / cols, z = row D / rows, as the renderer samples it): the zero-force lumen, the undeformed vessel as imaged at
first contact in TRUE millimetres (the rows read as true depth: under a sound-speed mismatch the displayed depth is
true depth x 1540 / c, so the uncompensated image shows the vessel elsewhere than this truth); and the deformed lumen
actually imaged (the FEM's reference position of each pixel at the frame's imaged indentation, through the displayed
depth axis), which checks the segmentation. The phantom is uniform, so the zero-force truth is the same in every
frame; the imaged one follows the force.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from usdeform.io import write_sequence

from .cases import Protocol, Sweep, _draw_case, record_palpation
from .imaging import ASSUMED_SPEED_M_PER_S, Renderer, Scanner, Texture
from .mechanics import Face, Phantom, Solution, solve_phantom

KINDS = (
    "null",
    "image_latency",
    "force_sensor_error",
    "viscoelasticity",
    "sound_speed_mismatch",
    "force_latency",
    "force_sensor_lag",
    "pose_latency",
    "force_sensor_drift",
    "image_clock_drift",
)
"""Kinds a sweep case can hide: those that leave the phantom as drawn (its counterpart without the effect exists)."""


class SweepProtocol:
    """A force-controlled sweep: ramp from contact to the target force, settle, then the recorded sweep; the
    achieved force (N) is the target plus the force loop's tracking error. Duck-types ``cases.Protocol`` for
    ``cases._trajectory`` and ``cases.record_palpation`` (``duration_s``, ``target``, ``ripple_mm``,
    ``force_noise_n``)."""

    def __init__(self, palpation: Protocol, rng: np.random.Generator, quick: bool):
        self.contact_n = palpation.contact_n
        self.ramp_n_per_s = palpation.ramp_n_per_s
        self.target_n = float(rng.uniform(0.4, 0.6)) * palpation.max_force_n
        self.settle_s = 1.0
        self.sweep_s = float(rng.uniform(3.0, 6.0)) if not quick else float(rng.uniform(3.0, 3.5))
        self.speed_mm_per_s = float(rng.uniform(5.0, 10.0))
        self.oscillation_n = float(rng.uniform(0.5, 1.0))
        self.oscillation_hz = float(rng.uniform(0.2, 0.5))
        self.oscillation_phase = float(rng.uniform(0, 2 * np.pi))
        self.ripple_n_rms = float(rng.uniform(0.1, 0.3))
        self.ripple_hz = rng.uniform(2.0, 5.0, 6)
        self.ripple_phase = rng.uniform(0, 2 * np.pi, 6)
        self.ripple_mm = palpation.ripple_mm
        self.force_noise_n = palpation.force_noise_n
        self.frame_rate_hz = palpation.frame_rate_hz
        self.reach_s = (self.target_n - self.contact_n) / self.ramp_n_per_s
        self.start_s = self.reach_s + self.settle_s

    @property
    def duration_s(self) -> float:
        return self.start_s + self.sweep_s

    def error(self, t: np.ndarray) -> np.ndarray:
        """The force loop's tracking error (N), faded in over the settle after the target is reached."""
        slow = self.oscillation_n * np.sin(2 * np.pi * self.oscillation_hz * t + self.oscillation_phase)
        ripple = np.sin(2 * np.pi * np.multiply.outer(t, self.ripple_hz) + self.ripple_phase).sum(axis=-1)
        ripple *= self.ripple_n_rms / np.sqrt(len(self.ripple_hz) / 2)
        fade = np.clip((t - self.reach_s) / self.settle_s, 0.0, 1.0)
        return (slow + ripple) * fade * fade * (3 - 2 * fade)

    def target(self, t: np.ndarray) -> np.ndarray:
        """Achieved contact force (N): contact before 0, the ramp, then the target plus the tracking error."""
        ramp = np.clip(self.contact_n + self.ramp_n_per_s * t, self.contact_n, self.target_n)
        return np.clip(ramp + self.error(t), self.contact_n, None)

    def frame_times(self, rng: np.random.Generator) -> np.ndarray:
        period = 1 / self.frame_rate_hz
        ticks = self.start_s + np.arange(rng.uniform(0, period), self.sweep_s, period)
        return np.sort(ticks + rng.uniform(-5e-4, 5e-4, len(ticks)))

    def describe(self) -> dict[str, float]:
        return {
            "target_n": self.target_n,
            "sweep_s": self.sweep_s,
            "speed_mm_per_s": self.speed_mm_per_s,
            "length_mm": self.speed_mm_per_s * self.sweep_s,
            "oscillation_n": self.oscillation_n,
            "oscillation_hz": self.oscillation_hz,
            "ripple_n_rms": self.ripple_n_rms,
            "start_s": self.start_s,
        }


class ElevationTexture:
    """A texture whose speckle changes along elevation: the base texture's structure (density, wall, lumen, fibres;
    its bright points taken out) times independent scatterer layers (amplitudes, sparse bright points) every
    sigma / 2 along elevation, made when the beam first reaches them (each from its own seed), summed by a Gaussian
    elevation beam (``Texture.weights``' rule: squared weights sum to 1). Duck-types ``imaging.Texture`` for
    ``imaging.Renderer``."""

    def __init__(self, texture: Texture, texture_seed: int, beam_fwhm_mm: float, layer_seed: int):
        self.x0, self.z0 = texture.x0, texture.z0
        self.opacity, self.loss_db_per_mm = texture.opacity, texture.loss_db_per_mm
        self.values = texture.values
        nz, nx = texture.values.shape
        replay = np.random.default_rng(texture_seed)  # Texture's first draws: amplitudes, density, bright points
        amplitude = replay.standard_normal((nz, nx)).astype(np.float32)
        replay.standard_normal((nz // 40 + 2, nx // 20 + 2))
        bright = replay.random((nz, nx)) < 4e-4
        safe = np.abs(amplitude) > 1e-3
        strength = np.where(safe, texture.values / np.where(safe, amplitude, 1.0), 0.0)
        for _ in range(3):  # the few near-zero amplitudes: the strength of a neighbour
            strength = np.where(safe, strength, np.roll(strength, 1, axis=1))
            safe = safe | np.roll(safe, 1, axis=1)
        self.plain = (strength / np.where(bright, 4.0, 1.0)).astype(np.float32)
        self.sigma_mm = beam_fwhm_mm / 2.3548
        self.spacing = self.sigma_mm / 2
        self.layer_seed = layer_seed
        self.layers: dict[int, np.ndarray] = {}

    def _layer(self, k: int) -> np.ndarray:
        if k not in self.layers:
            rng = np.random.default_rng([self.layer_seed, k + 100000])
            points = np.where(rng.random(self.plain.shape) < 4e-4, 4.0, 1.0).astype(np.float32)
            self.layers[k] = (rng.standard_normal(self.plain.shape).astype(np.float32) * self.plain * points).astype(
                np.float32
            )
        return self.layers[k]

    def weights(self, elevation_mm: float) -> list[tuple[float, np.ndarray]]:
        low = int(np.floor((elevation_mm - 3 * self.sigma_mm) / self.spacing))
        high = int(np.ceil((elevation_mm + 3 * self.sigma_mm) / self.spacing))
        ks = np.arange(low, high + 1)
        raw = np.exp(-0.5 * ((ks * self.spacing - elevation_mm) / self.sigma_mm) ** 2)
        raw /= np.sqrt(np.sum(raw**2))
        for k in [k for k in self.layers if k < low - 2 or k > high + 2]:  # forget the layers left behind
            del self.layers[k]
        return [(float(w), self._layer(int(k))) for w, k in zip(raw, ks, strict=True) if w > 1e-3]


def pixel_grid(shape: tuple[int, int], image_to_probe: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Probe-frame (x lateral, z depth) mm of every pixel centre, (rows, cols) each, from the calibration."""
    rows, cols = shape
    col, row = np.meshgrid(np.arange(cols), np.arange(rows))
    pixels = np.stack([col.ravel(), row.ravel(), np.zeros(col.size), np.ones(col.size)])
    probe = image_to_probe @ pixels
    return probe[0].reshape(rows, cols), probe[2].reshape(rows, cols)


def zero_force_mask(phantom: Phantom, face: Face, shape: tuple[int, int], image_to_probe: np.ndarray) -> np.ndarray:
    """The undeformed lumen as imaged at first contact, the pixel grid read in true mm (bool, rows x cols). At
    first contact the tissue is undeformed (no kind here pre-loads it), so a pixel's tissue point is the face's
    pose applied to its probe-frame position."""
    x, z = pixel_grid(shape, image_to_probe)
    centre = face.centre(0.0)
    e_x, e_z = face.axes()
    tx = centre[0] + x * e_x[0] + z * e_z[0]
    tz = centre[1] + x * e_x[1] + z * e_z[1]
    return np.hypot(tx - phantom.vessel_x_mm, tz - phantom.vessel_depth_mm) < phantom.vessel_radius_mm


def imaged_mask(renderer: Renderer, phantom: Phantom, lam: float, shape: tuple[int, int]) -> np.ndarray:
    """The deformed lumen the frame shows at indentation ``lam`` (bool, rows x cols): each pixel centre placed
    through the displayed depth axis (the renderer's axial scale) and mapped to its reference position by the
    renderer's own fixed point."""
    s = renderer.scanner
    probe = copy.copy(renderer)
    probe.xc = -s.width_mm / 2 + np.arange(shape[1]) * s.width_mm / s.cols
    probe.zc = np.arange(shape[0]) * s.depth_mm / s.rows
    x_ref, z_ref = probe.reference_positions(lam)
    return np.hypot(x_ref - phantom.vessel_x_mm, z_ref - phantom.vessel_depth_mm) < phantom.vessel_radius_mm


def children(seed: np.random.SeedSequence, n: int) -> list[np.random.SeedSequence]:
    """``seed.spawn(n)`` without its state: the same children at every call (``spawn`` counts the children it has
    given, so a second call gives others, and the case without the effect would not be the same case)."""
    return [
        np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, i), pool_size=seed.pool_size) for i in range(n)
    ]


@dataclass
class Drawn:
    kind: str
    phantom: Phantom
    scanner: Scanner
    protocol: Protocol
    protocol_2: Protocol
    hidden: dict[str, float]
    beam_fwhm_mm: float


def draw(kind: str, seed: np.random.SeedSequence, quick: bool) -> Drawn:
    """The case's phantom, scanner, palpation protocols, elevation beam and hidden effect (``cases._draw_case``'s
    stream, then the second palpation's and the beam's draws from their own child stream)."""
    if kind not in KINDS:
        raise ValueError(f"sweep kinds: {', '.join(KINDS)}; got {kind}")
    streams = children(seed, 2)
    phantom, scanner, protocol, hidden = _draw_case(kind, np.random.default_rng(streams[0]), quick)
    rng = np.random.default_rng(streams[1])
    factor = float(rng.uniform(0.6, 0.75)) if rng.random() < 0.5 else float(rng.uniform(1.35, 1.6))
    protocol_2 = replace(
        protocol,
        ramp_n_per_s=float(np.clip(protocol.ramp_n_per_s * factor, 2.0, 8.0)),
        hold_s=float(rng.uniform(1.5, 3.0)),
    )
    return Drawn(kind, phantom, scanner, protocol, protocol_2, hidden, float(rng.uniform(1.0, 2.0)))


def generate_sweep_case(
    drawn: Drawn, seed: np.random.SeedSequence, directory: Path, cache: Path, effect: bool, quick: bool
) -> dict[str, object]:
    """Writes palpation_1.seq.nrrd, palpation_2.seq.nrrd, sweep.seq.nrrd and truth.npz (``zero_force`` (rows, cols),
    ``imaged`` (frames, rows, cols), ``imaged_lambda``, ``true_force``) into ``directory``; ``effect`` False: the
    same case without the hidden effect (kind null). Returns what was drawn and recorded."""
    kind = drawn.kind if effect else "null"
    hidden = drawn.hidden if effect else {}
    phantom, scanner = drawn.phantom, drawn.scanner
    solution: Solution = solve_phantom(phantom, cache)
    reached = float(solution.forces[-1])
    protocols = [drawn.protocol, drawn.protocol_2]
    protocols = [
        p if p.max_force_n <= 0.85 * reached else Protocol(**{**asdict(p), "max_force_n": 0.85 * reached})
        for p in protocols
    ]
    face = Face.of(phantom, solution.lift_mm)
    texture_seed, layer_seed, sweep_seed, pose_seed, *palpation_seeds = (
        int(s.generate_state(1)[0]) for s in children(seed, 6)
    )
    texture = ElevationTexture(
        Texture(phantom, scanner, np.random.default_rng(texture_seed)), texture_seed, drawn.beam_fwhm_mm, layer_seed
    )
    speed = hidden.get("sound_speed_m_per_s", ASSUMED_SPEED_M_PER_S)
    renderer = Renderer(solution, texture, scanner, face, speed / ASSUMED_SPEED_M_PER_S)  # type: ignore[arg-type]
    yaw = np.radians(np.random.default_rng(pose_seed).uniform(-30, 30))
    origin = np.random.default_rng([pose_seed, 1]).uniform([400, -100, 50], [600, 100, 150])
    surface_to_base = np.array(
        [
            [np.cos(yaw), -np.sin(yaw), 0.0, origin[0]],
            [np.sin(yaw), np.cos(yaw), 0.0, origin[1]],
            [0.0, 0.0, 1.0, origin[2]],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    sweep_protocol = SweepProtocol(
        replace(protocols[0], max_force_n=min(p.max_force_n for p in protocols)),
        np.random.default_rng(sweep_seed),
        quick,
    )
    length = sweep_protocol.speed_mm_per_s * sweep_protocol.sweep_s
    directory.mkdir(parents=True, exist_ok=True)
    info: dict[str, object] = {"palpations": []}
    for index, (protocol, palpation_seed) in enumerate(zip(protocols, palpation_seeds, strict=True)):
        position = (0.1 if index == 0 else 0.9) * length
        recording, timeline = record_palpation(
            kind,
            hidden,
            solution,
            protocol,
            renderer,
            face,
            scanner,
            np.random.default_rng(palpation_seed),
            surface_to_base=surface_to_base,
            sweep=Sweep(0.0, 0.0, position),
        )
        write_sequence(directory / f"palpation_{index + 1}.seq.nrrd", recording)
        info["palpations"].append(  # type: ignore[union-attr]
            {
                "protocol": asdict(protocol),
                "elevation_mm": position,
                "n_frames": len(recording.timestamps),
                "peak_lambda_mm": float(timeline["frame_lambda"].max()),
            }
        )
    sweep_rng = np.random.default_rng([sweep_seed, 1])
    times = sweep_protocol.frame_times(sweep_rng)
    recording, timeline = record_palpation(
        kind,
        hidden,
        solution,
        sweep_protocol,  # type: ignore[arg-type]
        renderer,
        face,
        scanner,
        sweep_rng,
        times=times,
        surface_to_base=surface_to_base,
        sweep=Sweep(sweep_protocol.speed_mm_per_s, sweep_protocol.start_s, 0.0),
    )
    write_sequence(directory / "sweep.seq.nrrd", recording)
    shape = recording.frames.shape[1:]
    zero = zero_force_mask(phantom, face, shape, scanner.image_to_probe())
    imaged = np.stack([imaged_mask(renderer, phantom, float(v), shape) for v in timeline["imaged_lambda"]])
    np.savez_compressed(
        directory / "truth.npz",
        zero_force=zero,
        imaged=imaged,
        imaged_lambda=timeline["imaged_lambda"],
        true_force=timeline["frame_force_true"],
        logged_force=np.asarray(recording.force),
        logged_lambda=np.asarray(recording.probe_displacement),
        image_to_probe=scanner.image_to_probe(),
    )
    info.update(
        {
            "kind": kind,
            "hidden_parameters": hidden,
            "phantom": asdict(phantom),
            "scanner": asdict(scanner),
            "sweep": sweep_protocol.describe(),
            "beam_fwhm_mm": drawn.beam_fwhm_mm,
            "fem_max_force_n": reached,
            "sweep_frames": len(times),
            "sweep_force_range_n": [float(np.min(recording.force)), float(np.max(recording.force))],
            "sweep_lambda_range_mm": [float(timeline["frame_lambda"].min()), float(timeline["frame_lambda"].max())],
            "palpation_peak_force_n": min(p.max_force_n for p in protocols),
            "zero_force_area_px": int(zero.sum()),
            "tissue_depth_mm": phantom.depth_mm,
        }
    )
    return info
