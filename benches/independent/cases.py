"""Cases of the independent generator: the palpation timeline, the nuisance draws, the hidden effects and the
recording written as a PLUS sequence file (see benches/gap_independent.py for the kinds and their ranges)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import lfilter

from usdeform.io import write_sequence
from usdeform.recording import Recording

from .imaging import ASSUMED_SPEED_M_PER_S, Renderer, Scanner, Texture
from .mechanics import Face, Phantom, Solution, solve_phantom

LIBRARY_KINDS = (
    "image_latency",
    "force_sensor_error",
    "viscoelasticity",
    "force_latency",
    "force_sensor_lag",
    "pose_latency",
    "force_sensor_drift",
    "surface_inclination",
    "probe_tilt",
    "out_of_plane_drift",
    "sound_speed_mismatch",
    "soft_layer",
    "frictionless_contact",
    "lumen_pressure",
    "image_clock_drift",
)
"""Hidden kinds that one of the diagnosis's library effects models (directly or by a physical equivalence)."""
OUT_OF_LIBRARY_KINDS = ("convex_probe_face", "gain_drift", "acoustic_shadow", "stiff_inclusion", "breathing_motion")
"""Hidden kinds no library effect models: naming any effect for them is a false attribution."""
KINDS = ("null", *LIBRARY_KINDS, *OUT_OF_LIBRARY_KINDS)
CYCLE = (
    "null",
    "image_latency",
    "force_latency",
    "force_sensor_error",
    "null",
    "viscoelasticity",
    "probe_tilt",
    "convex_probe_face",
    "null",
    "force_sensor_lag",
    "pose_latency",
    "gain_drift",
    "null",
    "force_sensor_drift",
    "surface_inclination",
    "sound_speed_mismatch",
    "null",
    "out_of_plane_drift",
    "convex_probe_face",
    "gain_drift",
    "null",
    "pose_latency",
    "viscoelasticity",
    "acoustic_shadow",
)


def kinds_to_cycle(parser, text: str | None, default: tuple[str, ...], known: tuple[str, ...]) -> tuple[str, ...]:
    """The kinds a ``--kinds`` option names (comma-separated; None: ``default``), or ``parser.error`` naming the
    unknown ones."""
    cycle = default if text is None else tuple(kind.strip() for kind in text.split(",") if kind.strip())
    unknown = sorted(set(cycle) - set(known))
    if unknown or not cycle:
        parser.error(f"unknown kinds {', '.join(unknown)}; choose from {', '.join(known)}")
    return cycle


"""Case i's kind is CYCLE[i % 24]: every kind of version 2 in 24 cases, a quarter nulls; cases 0, 1, 3, 4 and 5 have
the kinds of generator version 1's cycle and the same recordings. The kinds added since (``soft_layer``,
``frictionless_contact``, ``lumen_pressure``, ``image_clock_drift``, ``stiff_inclusion``, ``breathing_motion``) are
not in it (kept so a seed's cycle keeps its recordings): run them with ``--kinds``."""


@dataclass(frozen=True)
class Protocol:
    """Force-controlled palpation: contact force, peak (N), ramp rate (N/s), hold (s); noise (N, mm); rate (fps)."""

    contact_n: float
    max_force_n: float
    ramp_n_per_s: float
    hold_s: float
    force_noise_n: float
    ripple_mm: float
    frame_rate_hz: float
    max_frames: int

    @property
    def duration_s(self) -> float:
        return 2 * (self.max_force_n - self.contact_n) / self.ramp_n_per_s + self.hold_s

    def target(self, t: np.ndarray) -> np.ndarray:
        """Target force (N) at times ``t`` (s): contact before 0 and after the palpation."""
        up = self.contact_n + self.ramp_n_per_s * t
        down = self.contact_n + self.ramp_n_per_s * (self.duration_s - t)
        return np.clip(np.minimum(np.minimum(up, down), self.max_force_n), self.contact_n, None)


def _breathing(t: np.ndarray, hidden: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Breathing: the tissue block's axial displacement (mm, positive away from the probe) and the force loop's
    answer to it, the displacement through a first-order low-pass of the loop's bandwidth (steady state), mm."""
    omega, phase = 2 * np.pi * hidden["frequency_hz"], hidden["phase_rad"]
    ratio = hidden["frequency_hz"] / hidden["loop_bandwidth_hz"]
    base = hidden["amplitude_mm"] * np.sin(omega * t + phase)
    follow = hidden["amplitude_mm"] / np.hypot(1.0, ratio) * np.sin(omega * t + phase - np.arctan(ratio))
    return base, follow


def _trajectory(
    solution: Solution, protocol: Protocol, hidden: dict[str, float], kind: str, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Force control on a 1 kHz clock from -1 s: times (s), the probe's travel lambda (mm), true contact force (N)
    and the indentation into the tissue (mm; lambda, but under breathing lambda minus the tissue's motion, negative
    while the probe is lifted off)."""
    dt = 1e-3
    t = np.arange(-1.0, protocol.duration_s + 0.5, dt)
    target = protocol.target(t)
    if kind == "viscoelasticity":
        g, tau = hidden["g"], hidden["tau_s"]
        decay = np.exp(-dt / tau)
        elastic = np.empty_like(t)
        q = 0.0
        elastic[0] = target[0]
        for i in range(1, len(t)):  # F_target = F_e + q, q' = -q / tau + g F_e'
            q = (q * decay + g * (target[i] - elastic[i - 1])) / (1 + g)
            elastic[i] = target[i] - q
        commanded = solution.lambda_at(elastic)
    else:
        commanded = solution.lambda_at(target)
    ripple = gaussian_filter1d(rng.standard_normal(len(t)), 1 / (2 * np.pi * 3.0 * dt))
    ripple *= protocol.ripple_mm / max(float(ripple.std()), 1e-12)
    lam = np.clip(commanded + ripple, 0.0, solution.lambdas[-1])
    indentation = lam
    if kind == "breathing_motion":  # the robot follows the tissue in part; the force follows the indentation
        base, follow = _breathing(t, hidden)
        lam = commanded + ripple + follow
        indentation = np.minimum(lam - base, solution.lambdas[-1])  # < 0: lifted off, over a film of gel (F = 0)
    elastic_true = solution.force_at(indentation)
    force = elastic_true.copy()
    if kind == "viscoelasticity":
        g, tau = hidden["g"], hidden["tau_s"]
        decay = np.exp(-dt / tau)
        q = 0.0
        for i in range(1, len(t)):
            q = q * decay + g * (elastic_true[i] - elastic_true[i - 1])
            force[i] += q
    return t, lam, force, indentation


def _frame_times(protocol: Protocol, rng: np.random.Generator) -> np.ndarray:
    """Frame timestamps (s) over the palpation: the scanner's clock, at most ``max_frames`` kept, 1 ms jitter."""
    period = 1 / protocol.frame_rate_hz
    ticks = np.arange(rng.uniform(0, period), protocol.duration_s, period)
    if len(ticks) > protocol.max_frames:
        ticks = ticks[np.rint(np.linspace(0, len(ticks) - 1, protocol.max_frames)).astype(int)]
    return np.sort(ticks + rng.uniform(-5e-4, 5e-4, len(ticks)))


def _probe_to_base(origin: np.ndarray, tilt_rad: float, surface_to_base: np.ndarray) -> np.ndarray:
    """(n, 4, 4) probe poses: probe z into the tissue (surface z up), tilted ``tilt_rad`` in the image plane (about
    its y axis; positive: its right edge deeper), origin at ``origin`` (n, 2) (lateral, depth below the surface, mm)."""
    poses = np.tile(np.eye(4), (len(origin), 1, 1))
    poses[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    if tilt_rad:
        c, s = np.cos(tilt_rad), np.sin(tilt_rad)
        poses[:, :3, :3] = [[c, 0.0, -s], [0.0, -1.0, 0.0], [-s, 0.0, -c]]
    poses[:, 0, 3] = origin[:, 0]
    poses[:, 2, 3] = -origin[:, 1]
    return surface_to_base[None] @ poses


def _draw_case(kind: str, rng: np.random.Generator, quick: bool) -> tuple[Phantom, Scanner, Protocol, dict]:
    """Random nuisance (phantom, scanner, protocol) and the hidden effect's parameters."""
    probe_width = float(rng.choice([37.5, 40.0, 42.0, 45.0, 48.0]))
    max_force = float(rng.uniform(8.0, 20.0))
    phantom = Phantom(
        width_mm=float(rng.uniform(100, 150)),
        depth_mm=float(rng.uniform(60, 80)),
        probe_width_mm=probe_width,
        vessel_x_mm=float(rng.uniform(-4, 4)),
        vessel_depth_mm=float(rng.uniform(14, 24)),
        vessel_radius_mm=float(rng.uniform(4, 7)),
        shear_modulus_kpa=float(rng.uniform(10, 40)),
        poisson_ratio=float(rng.uniform(0.45, 0.49)),
        stiffening_b=float(rng.uniform(0.3, 3.0)),
        lumen_ratio=float(np.exp(rng.uniform(np.log(0.005), np.log(0.05)))),
        elevation_mm=float(rng.uniform(20, 30)),  # plane-strain force per mm -> N (3-D spread)
        element_mm=1.6 if quick else float(rng.uniform(1.0, 1.3)),
        force_cap_n=round(1.15 * max_force + 1.0, 1),
    )
    widths = [w for w in (37.5, 40.0, 42.5, 45.0) if w <= probe_width]
    scanner = Scanner(
        rows=256,
        cols=int(rng.choice([192, 224, 256])),
        depth_mm=float(rng.choice([40.0, 42.5, 45.0])),
        width_mm=float(rng.choice(widths)),
        frequency_mhz=float(rng.uniform(5.0, 7.5)),
        pulse_cycles=float(rng.uniform(1.2, 2.0)),
        lateral_fwhm_mm=float(rng.uniform(0.4, 0.8)),
        attenuation_db_cm_mhz=float(rng.uniform(0.3, 0.7)),
        tgc_db_per_cm=float(rng.uniform(3.0, 8.0)),
        noise_db=float(rng.uniform(-45, -30)),
        gain_db=float(rng.uniform(-26, -16)),
        dynamic_range_db=float(rng.uniform(50, 60)),
        wall_db=float(rng.uniform(6, 12)),
        jitter_mm=float(rng.uniform(0.01, 0.02)),
        density_variation=float(rng.uniform(0.1, 0.3)),
        fibres=int(rng.integers(0, 3)),
        fine_rows=4 if quick else 8,
    )
    protocol = Protocol(
        contact_n=float(rng.uniform(0.2, 0.5)),
        max_force_n=max_force,
        ramp_n_per_s=float(rng.uniform(3, 6)),
        hold_s=float(rng.uniform(1.5, 3.0)),
        force_noise_n=float(rng.uniform(0.02, 0.06)),
        ripple_mm=float(rng.uniform(0.01, 0.05)),
        frame_rate_hz=float(rng.uniform(20, 30)),
        max_frames=40 if quick else int(rng.integers(80, 121)),
    )
    hidden: dict[str, float] = {}
    if kind == "image_latency":
        hidden = {"delay_s": float(rng.uniform(0.05, 0.15))}
    elif kind == "force_sensor_error":
        hidden = {
            "bias_n": float(rng.uniform(0.3, 1.0) * rng.choice([-1.0, 1.0])),
            "drift_n_per_s": float(rng.uniform(0.0, 0.02) * rng.choice([-1.0, 1.0])),
        }
    elif kind == "viscoelasticity":
        g = float(rng.uniform(0.15, 0.45))
        hidden = {
            "g": g,
            "tau_s": float(np.exp(rng.uniform(np.log(0.5), np.log(3.0)))),
            "g_prony_equivalent": g / (1 + g),
        }
    elif kind == "force_latency":
        hidden = {"force_delay_s": float(rng.uniform(0.05, 0.25))}
    elif kind == "force_sensor_lag":
        hidden = {"lag_tau_s": float(rng.uniform(0.05, 0.3))}
    elif kind == "pose_latency":
        hidden = {"pose_delay_s": float(rng.uniform(0.05, 0.2))}
    elif kind == "force_sensor_drift":
        hidden = {
            "bias_n": float(rng.uniform(0.1, 0.5) * rng.choice([-1.0, 1.0])),
            "drift_n_per_s": float(rng.uniform(0.02, 0.1) * rng.choice([-1.0, 1.0])),
            "gain_error": float(rng.uniform(0.03, 0.1) * rng.choice([-1.0, 1.0])),
        }
    elif kind == "surface_inclination":  # a level probe travelling along its axis, i.e. at the angle to the normal
        angle = float(rng.uniform(4, 12) * rng.choice([-1.0, 1.0]))
        hidden = {"inclination_deg": angle}
        phantom = replace(phantom, face_tilt_deg=angle, travel_deg=-angle)
    elif kind == "probe_tilt":  # a tilted probe travelling along the surface normal
        angle = float(rng.uniform(4, 12) * rng.choice([-1.0, 1.0]))
        hidden = {"tilt_deg": angle}
        phantom = replace(phantom, face_tilt_deg=angle)
    elif kind == "out_of_plane_drift":
        hidden = {
            "drift_mm": float(rng.uniform(0.2, 1.5) * rng.choice([-1.0, 1.0])),
            "time_fraction": float(rng.uniform(0.0, 1.0)),
            "beam_fwhm_mm": float(rng.uniform(1.0, 2.0)),
        }
    elif kind == "sound_speed_mismatch":  # 1450-1520 or 1560-1600 m/s, uniform over the 110 m/s
        offset = float(rng.uniform(0.0, 110.0))
        hidden = {"sound_speed_m_per_s": 1450.0 + offset if offset < 70.0 else 1490.0 + offset}
    elif kind == "convex_probe_face":
        hidden = {"face_radius_mm": float(rng.uniform(40.0, 80.0))}
        phantom = replace(phantom, face_radius_mm=hidden["face_radius_mm"])
    elif kind == "gain_drift":
        hidden = {"gain_drift_db": float(rng.uniform(4.0, 10.0) * rng.choice([-1.0, 1.0]))}
    elif kind == "acoustic_shadow":  # beside the vessel, clear of it and its wall
        hidden = {
            "x_mm": phantom.vessel_x_mm + float(rng.uniform(10.0, 13.0) * rng.choice([-1.0, 1.0])),
            "depth_mm": float(rng.uniform(5.0, 12.0)),
            "radius_mm": float(rng.uniform(0.8, 2.0)),
            "echo_db": float(rng.uniform(12.0, 20.0)),
            "loss_db": float(rng.uniform(10.0, 25.0)),
        }
    elif kind == "soft_layer":  # subcutaneous fat over stiffer tissue (elementwise modulus in the FEM)
        hidden = {
            "layer_thickness_mm": float(rng.uniform(3.0, 12.0)),
            "layer_modulus_ratio": float(rng.uniform(0.15, 0.5)),
        }
        phantom = replace(
            phantom, layer_depth_mm=hidden["layer_thickness_mm"], layer_ratio=hidden["layer_modulus_ratio"]
        )
    elif kind == "frictionless_contact":  # a switch: the face constrains the normal displacement only
        hidden = {"friction_coefficient": 0.0}
        phantom = replace(phantom, frictionless=True)
    elif kind == "lumen_pressure":  # a follower fluid pressure in the lumen, applied before contact
        ratio = float(rng.uniform(0.08, 0.3))
        hidden = {"pressure_ratio": ratio, "pressure_kpa": ratio * phantom.shear_modulus_kpa}
        phantom = replace(phantom, lumen_pressure_kpa=hidden["pressure_kpa"])
    elif kind == "image_clock_drift":  # the frames' delay grows linearly over the recording
        start = float(rng.uniform(0.0, 0.03))
        hidden = {"delay_start_s": start, "delay_end_s": start + float(rng.uniform(0.08, 0.25))}
    elif kind == "stiff_inclusion":  # beside or below the vessel (wall to edge 5-15 mm), inside the image at rest
        for _ in range(10000):  # always feasible: beside the vessel, away from the image's nearer edge
            radius = float(rng.uniform(2.5, 6.0))
            gap = float(rng.uniform(5.0, 15.0))
            angle = float(rng.uniform(-90.0, 90.0))  # from straight below the vessel, positive to the right
            distance = phantom.vessel_radius_mm + gap + radius
            x = phantom.vessel_x_mm + distance * float(np.sin(np.radians(angle)))
            z = phantom.vessel_depth_mm + distance * float(np.cos(np.radians(angle)))
            if abs(x) + radius <= scanner.width_mm / 2 - 1.0 and z + radius <= scanner.depth_mm - 1.0:
                break
        else:
            raise RuntimeError("no stiff inclusion fits the image")
        hidden = {
            "x_mm": x,
            "depth_mm": z,
            "radius_mm": radius,
            "gap_mm": gap,
            "modulus_ratio": float(rng.uniform(4.0, 10.0)),
            "echo_db": 0.0 if rng.random() < 0.5 else float(rng.uniform(1.0, 3.0)),
        }
        phantom = replace(
            phantom,
            inclusion_x_mm=x,
            inclusion_depth_mm=z,
            inclusion_radius_mm=radius,
            inclusion_ratio=hidden["modulus_ratio"],
        )
    elif kind == "breathing_motion":  # the tissue's axial motion, the force loop's bandwidth (a nuisance)
        hidden = {
            "amplitude_mm": float(rng.uniform(0.3, 1.2)),
            "frequency_hz": float(rng.uniform(0.2, 1 / 3)),
            "phase_rad": float(rng.uniform(0.0, 2 * np.pi)),
            "loop_bandwidth_hz": float(rng.uniform(0.5, 2.0)),
        }
    return phantom, scanner, protocol, hidden


def case_texture(kind: str, hidden: dict[str, float], phantom: Phantom, scanner: Scanner, texture_seed: int) -> Texture:
    """The case's texture: elevation slices under ``out_of_plane_drift``, the calcification of ``acoustic_shadow``,
    the inclusion's echo of ``stiff_inclusion``, all drawn from ``texture_seed``."""
    elevation = None
    if kind == "out_of_plane_drift":  # beam sigma and the span of its positions
        drift = hidden["drift_mm"]
        elevation = (hidden["beam_fwhm_mm"] / 2.3548, min(0.0, drift), max(0.0, drift))
    shadow = None
    if kind == "acoustic_shadow":
        shadow = tuple(hidden[k] for k in ("x_mm", "depth_mm", "radius_mm", "echo_db", "loss_db"))
    inclusion = None
    if kind == "stiff_inclusion":
        inclusion = tuple(hidden[k] for k in ("x_mm", "depth_mm", "radius_mm", "echo_db"))
    return Texture(phantom, scanner, np.random.default_rng(texture_seed), elevation, shadow, inclusion)  # type: ignore[arg-type]


def generate_case(
    kind: str, rng: np.random.Generator, directory: Path, cache: Path, quick: bool = False, png: bool = False
) -> dict[str, object]:
    """Simulate one palpation into ``directory / palpation.seq.nrrd``; returns what was hidden and drawn (the
    ``case`` that ``follow_up.record_follow_up`` records more of: kind, hidden parameters, phantom, scanner, protocol,
    texture seed, surface-to-base pose and FEM cache)."""
    phantom, scanner, protocol, hidden = _draw_case(kind, rng, quick)
    solution = solve_phantom(phantom, cache)
    reached = float(solution.forces[-1])
    if protocol.max_force_n > 0.85 * reached:  # soft phantom: press less than the FEM reached
        protocol = Protocol(**{**asdict(protocol), "max_force_n": 0.85 * reached})
    if kind == "breathing_motion":  # the peak indentation plus the breathing's residual stays within the FEM
        ratio = hidden["frequency_hz"] / hidden["loop_bandwidth_hz"]
        residual = hidden["amplitude_mm"] * ratio / np.hypot(1.0, ratio)
        limit = float(solution.force_at(solution.lambdas[-1] - residual - 3 * protocol.ripple_mm))
        if protocol.max_force_n > limit:
            protocol = Protocol(**{**asdict(protocol), "max_force_n": limit})
    face = Face.of(phantom, solution.lift_mm)  # lifted: first contact on a surface bulged by lumen pressure
    texture_seed = int(rng.integers(2**63))
    texture = case_texture(kind, hidden, phantom, scanner, texture_seed)
    speed = hidden.get("sound_speed_m_per_s", ASSUMED_SPEED_M_PER_S)
    renderer = Renderer(solution, texture, scanner, face, speed / ASSUMED_SPEED_M_PER_S)
    recording, timeline = record_palpation(kind, hidden, solution, protocol, renderer, face, scanner, rng)
    frames, frame_lambda, times = recording.frames, timeline["frame_lambda"], recording.timestamps
    directory.mkdir(parents=True, exist_ok=True)
    write_sequence(directory / "palpation.seq.nrrd", recording)
    if png:
        for index in np.linspace(0, len(frames) - 1, 5).astype(int):
            cv2.imwrite(str(directory / f"frame_{index:03d}.png"), frames[index])
    return {
        "kind": kind,
        "hidden_parameters": hidden,
        "phantom": asdict(phantom),
        "scanner": asdict(scanner),
        "protocol": asdict(protocol),
        "texture_seed": texture_seed,
        "surface_to_base": np.asarray(timeline["surface_to_base"]).tolist(),
        "fem_cache": str(cache),
        "fem_max_force_n": reached,
        "fem_max_lambda_mm": float(solution.lambdas[-1]),
        "peak_lambda_mm": float(frame_lambda.max()),
        "n_frames": len(times),
    }


@dataclass
class Sweep:
    """A translation of the probe along the elevation direction (the image normal) during a recording: the probe
    moves ``speed_mm_per_s`` from ``start_s`` on, starting ``offset_mm`` along elevation; ``texture_offset_mm``:
    where the texture's elevation slices sit (the beam position is offset + travel - texture offset)."""

    speed_mm_per_s: float = 0.0
    start_s: float = 0.0
    offset_mm: float = 0.0
    texture_offset_mm: float = 0.0

    def position(self, times: np.ndarray) -> np.ndarray:
        return self.offset_mm + self.speed_mm_per_s * np.clip(times - self.start_s, 0.0, None)


def sensed_force(
    kind: str,
    hidden: dict[str, float],
    t: np.ndarray,
    force: np.ndarray,
    times: np.ndarray,
    noise_n: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """The force sensor's reading (N) at the frame ``times`` (s) of the true load ``force`` (N) on the 1 kHz clock
    ``t`` (s): the hidden kind's sensor effect (lag, gain, bias, drift, delay) and Gaussian noise of ``noise_n``."""
    sensed = force
    if kind == "force_sensor_lag":  # first-order low-pass, exact on the 1 kHz clock, settled at the start
        decay = np.exp(-(t[1] - t[0]) / hidden["lag_tau_s"])
        sensed = lfilter([1 - decay], [1, -decay], force, zi=[decay * force[0]])[0]
    elif kind == "force_sensor_drift":  # gain error on the load, bias, drift with time from the recording's start
        sensed = (1 + hidden["gain_error"]) * force + hidden["bias_n"] + hidden["drift_n_per_s"] * t
    frame_force = np.interp(times - hidden.get("force_delay_s", 0.0), t, sensed)
    frame_force = frame_force + rng.normal(0.0, noise_n, len(times))
    if kind == "force_sensor_error":
        frame_force = frame_force + hidden["bias_n"] + hidden["drift_n_per_s"] * times
    return frame_force


def record_palpation(
    kind: str,
    hidden: dict[str, float],
    solution: Solution,
    protocol: Protocol,
    renderer: Renderer,
    face: Face,
    scanner: Scanner,
    rng: np.random.Generator,
    times: np.ndarray | None = None,
    surface_to_base: np.ndarray | None = None,
    sweep: Sweep | None = None,
) -> tuple[Recording, dict[str, np.ndarray]]:
    """The timeline of one force-controlled recording with the hidden effect applied (``generate_case``'s, shared
    with the sweeps of ``sweep.py``): the trajectory on the 1 kHz clock from ``protocol`` (anything with
    ``duration_s``, ``target(t)``, ``ripple_mm``, ``force_noise_n``), frame times (``_frame_times`` unless given),
    logged force and displacement, the frames rendered and the poses (``surface_to_base`` drawn unless given;
    ``sweep``: the probe translated along elevation, the beam moving through the texture's elevation slices).
    Returns the recording and the timeline's arrays (``t``, ``force`` true, ``frame_lambda`` logged,
    ``imaged_lambda`` the tissue's state each frame shows, ``elevations``)."""
    t, lam, force, indentation = _trajectory(
        solution, protocol, hidden, kind, np.random.default_rng(rng.integers(2**63))
    )
    if times is None:
        times = _frame_times(protocol, rng)
    frame_lambda = np.interp(times - hidden.get("pose_delay_s", 0.0), t, lam)  # the robot's pose stream
    frame_force = sensed_force(kind, hidden, t, force, times, protocol.force_noise_n, rng)
    delay = hidden.get("delay_s", 0.0)
    if kind == "image_clock_drift":  # linear in the frame's time, from the first frame to the last
        progress = (times - times[0]) / (times[-1] - times[0])
        delay = hidden["delay_start_s"] + (hidden["delay_end_s"] - hidden["delay_start_s"]) * progress
    imaged_lambda = np.interp(times - delay, t, indentation)  # the tissue's state (lambda but under breathing)
    gains = hidden.get("gain_drift_db", 0.0) * times / protocol.duration_s
    elevations = np.zeros(len(times))
    if kind == "out_of_plane_drift":  # part with time, part with the indentation
        share = hidden["time_fraction"]
        progress = share * times / protocol.duration_s + (1 - share) * imaged_lambda / imaged_lambda.max()
        elevations = hidden["drift_mm"] * progress
    if sweep is not None:  # the beam at the probe's elevation when the frame's tissue state was imaged
        elevations = elevations + sweep.position(times - delay) - sweep.texture_offset_mm
    frame_rng = np.random.default_rng(rng.integers(2**63))
    frames = np.stack(
        [
            renderer.render(float(v), frame_rng, float(g), float(e))
            for v, g, e in zip(imaged_lambda, gains, elevations, strict=True)
        ]
    )
    if surface_to_base is None:
        yaw = np.radians(rng.uniform(-30, 30))
        surface_to_base = np.array(
            [
                [np.cos(yaw), -np.sin(yaw), 0.0, float(rng.uniform(400, 600))],
                [np.sin(yaw), np.cos(yaw), 0.0, float(rng.uniform(-100, 100))],
                [0.0, 0.0, 1.0, float(rng.uniform(50, 150))],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
    origin = face.centre(frame_lambda)  # tissue frame; the world (surface) frame is level under an inclined tissue
    world = np.radians(hidden.get("inclination_deg", 0.0))
    if world:
        origin = origin @ np.array([[np.cos(world), -np.sin(world)], [np.sin(world), np.cos(world)]])
    if sweep is None:
        probe_to_base = _probe_to_base(origin, face.tilt_rad - world, surface_to_base)
    else:  # along the surface frame's y (the image normal is the probe's -y, i.e. the surface's y)
        local = _probe_to_base(origin, face.tilt_rad - world, np.eye(4))
        local[:, 1, 3] = sweep.position(times - hidden.get("pose_delay_s", 0.0))
        probe_to_base = surface_to_base[None] @ local
    recording = Recording(
        frames=frames,
        timestamps=times,
        probe_to_base=probe_to_base,
        pose_valid=np.ones(len(times), dtype=bool),
        image_to_probe=scanner.image_to_probe(),
        force=frame_force,
        probe_displacement=frame_lambda,
    )
    timeline = {
        "t": t,
        "force": force,
        "lambda": lam,
        "frame_lambda": frame_lambda,
        "frame_force_true": np.interp(times, t, force),
        "imaged_lambda": imaged_lambda,
        "elevations": elevations,
        "surface_to_base": surface_to_base,
    }
    return recording, timeline
