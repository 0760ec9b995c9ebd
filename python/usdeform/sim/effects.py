"""Switchable physical effects for the simulator, each with its parameters and a realistic range.

Every effect is a frozen dataclass whose default (all parameters zero / off) changes nothing: a
recording made with a zero-parameter effect is bit-identical to one made without it. Collect the
effects of a recording in :class:`Effects` (or pass a list of effect objects to the ``simulate_*``
functions). A recording never records which effects were on.

The ranges in the docstrings are the orders of magnitude reported for clinical tissue, gel
phantoms and robotic ultrasound set-ups; pick values inside them to mimic a real system.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any, TypeAlias

import numpy as np

from ..errors import InputError
from .imaging import ProbeState, TissueAcoustics, probe_to_surface
from .mechanics import Layer

__all__ = [
    "ConvexProbeFace",
    "Effect",
    "Effects",
    "ForceSensorError",
    "ImageLatency",
    "LayeredTissue",
    "LumenPressure",
    "OutOfPlaneMotion",
    "ProbeTilt",
    "SlidingContact",
    "SoundSpeedMismatch",
    "Viscoelasticity",
]


def _check_finite(owner: object, *names: str, non_negative: bool = False) -> None:
    for name in names:
        value = getattr(owner, name)
        if not np.isfinite(value) or (non_negative and value < 0):
            kind = "finite non-negative" if non_negative else "finite"
            raise InputError(f"{type(owner).__name__}.{name}: expected a {kind} number, got {value!r}")


@dataclass(frozen=True)
class ImageLatency:
    """Per-stream delays: each stream's samples are time-stamped later than they were acquired.

    A frame stamped t shows the tissue at t - image_delay_s; a force sample stamped t is the sensor's
    reading at t - force_delay_s; a pose stamped t is the robot's at t - pose_delay_s (each against the
    robot's true clock, which the force controller runs on: the delays are in the logging, not the loop).
    Image range 0-0.15 s: video paths (frame grabber or USB, scanner software) lag trackers and force
    sensors by tens to over a hundred milliseconds, which is why PLUS calibrates it (Lasso et al., "PLUS:
    open-source toolkit for ultrasound-guided intervention systems", IEEE TBME 61(10), 2014). Force and
    pose 0-0.15 s: a force stream that reaches the recorder through another process, a network bridge
    (ROS topics, an F/T sensor's UDP stream) or a DAQ buffer is stamped on arrival, 1-150 ms late, and
    robot state messages lag their controllers by 1-50 ms (Kaspar et al., "ROS-based robot state and
    data logging latencies", and the "Temporal calibration" chapter of PLUS). A force delay makes a
    loading-unloading loop in force against displacement with no creep at constant indentation.
    Negative values: stamped too early.
    """

    image_delay_s: float = 0.0
    force_delay_s: float = 0.0
    pose_delay_s: float = 0.0

    def __post_init__(self) -> None:
        _check_finite(self, "image_delay_s", "force_delay_s", "pose_delay_s")


@dataclass(frozen=True)
class ForceSensorError:
    """Force/torque sensor error: constant bias, linear drift, uncompensated probe weight, gain error and a
    first-order lag.

    measured = (1 + gain_error) * true + bias_n + drift_n_per_s * t
               - uncompensated_weight_n * cos(probe axis to vertical),
    (compression positive; the probe's weight pulls it away from the sensor when it points down), passed
    through a first-order low-pass of time constant ``lag_s`` (the sensor's or its filter's; 0: none).
    The force controller acts on the measured force, so the tissue sees the error too.
    Ranges: residual bias after taring 0-1 N and thermal drift 0-0.1 N/s (strain-gauge F/T
    sensors drift with temperature after power-up, most in the first tens of minutes; ATI's F/T
    transducer manual advises re-biasing before each task); probe plus holder weigh 0.2-0.6 kg,
    i.e. 2-6 N if gravity compensation is missing or miscalibrated; lag 0-0.2 s (the low-pass
    filters of F/T amplifiers and of robots' external-force estimates run at 1-100 Hz); gain error, the
    reading off by a fixed fraction of the force (an error that grows with load), within +-0.02 for a
    calibrated strain-gauge sensor (1-2 % of full scale) and up to +-0.2 for a force estimated from a
    robot's joint torques.
    """

    bias_n: float = 0.0
    drift_n_per_s: float = 0.0
    uncompensated_weight_n: float = 0.0
    lag_s: float = 0.0
    gain_error: float = 0.0

    def __post_init__(self) -> None:
        _check_finite(self, "bias_n", "drift_n_per_s", "uncompensated_weight_n", "gain_error")
        _check_finite(self, "lag_s", non_negative=True)
        if self.gain_error <= -1:
            raise InputError(f"ForceSensorError.gain_error: expected a value above -1, got {self.gain_error!r}")

    def lag_fraction(self, time_step_s: float) -> float:
        """The fraction of the gap to the new reading the lagged output closes in one step (1: no lag)."""
        return 1.0 if self.lag_s == 0 else float(1 - np.exp(-time_step_s / self.lag_s))

    def measured(self, true_force_n: float, time_s: float, probe_tilt_deg: float) -> float:
        """Sensor reading, N, of the true axial force at ``time_s`` (s since the recording started)."""
        weight = self.uncompensated_weight_n * np.cos(np.radians(probe_tilt_deg))
        return (1 + self.gain_error) * true_force_n + self.bias_n + self.drift_n_per_s * time_s - weight


@dataclass(frozen=True)
class Viscoelasticity:
    """Quasi-linear viscoelasticity (Fung) of the tissue with a Prony-series relaxation function.

    The contact force is ``F(t) = int G(t - tau) dF_e(lambda(tau))``, with ``F_e`` the elastic
    (finite-element) force and ``G(t) = 1 - sum g_i (1 - exp(-t / tau_i))``: loading and unloading
    give different forces at the same lambda and the force relaxes at constant lambda to
    ``(1 - sum g_i) F_e``. ``prony`` holds pairs (g_i, tau_i in s), 0 < sum g_i < 1; empty = elastic.
    Ranges: soft tissues relax 20-50 % and gelatin / PVA phantoms 5-20 %, with time constants
    from ~0.1 s to ~100 s (Fung, *Biomechanics: Mechanical Properties of Living Tissues*, 2nd ed.
    1993, ch. 7; Abramowitch & Woo, J. Biomech. Eng. 126, 2004). The deformation field at a given
    lambda stays the elastic one (QLV separates time and strain).
    """

    prony: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        terms = tuple((float(g), float(tau)) for g, tau in self.prony)
        object.__setattr__(self, "prony", terms)
        for index, (g, tau) in enumerate(terms):
            if not (np.isfinite(g) and g > 0 and np.isfinite(tau) and tau > 0):
                raise InputError(f"Viscoelasticity.prony[{index}]: expected (g > 0, tau_s > 0), got {(g, tau)}")
        if sum(g for g, _ in terms) >= 1:
            raise InputError(f"Viscoelasticity.prony: the g_i must sum to less than 1, got {sum(g for g, _ in terms)}")


class _RelaxationIntegrator:
    """Recursive QLV force for a Prony series, exact for an elastic force linear within each time step."""

    def __init__(self, viscoelasticity: Viscoelasticity, time_step_s: float):
        g = np.array([term[0] for term in viscoelasticity.prony])
        tau = np.array([term[1] for term in viscoelasticity.prony])
        self._g = g
        self._g_infinity = 1.0 - g.sum()
        self._decay = np.exp(-time_step_s / tau)
        self._ramp = tau / time_step_s * (1.0 - self._decay)
        self._history = np.zeros(len(g))
        self._elastic_force = 0.0

    def step(self, elastic_force_n: float) -> float:
        """Advance one time step to the elastic force ``elastic_force_n``; returns the viscoelastic force, N."""
        if self._g.size == 0:
            return elastic_force_n
        self._history = self._decay * self._history + self._ramp * (elastic_force_n - self._elastic_force)
        self._elastic_force = elastic_force_n
        return float(self._g_infinity * elastic_force_n + self._g @ self._history)

    def start_loaded(self, elastic_force_n: float) -> None:
        """Set the state of tissue just loaded (instantly) to ``elastic_force_n``."""
        self._history = np.full(self._g.size, elastic_force_n)
        self._elastic_force = elastic_force_n


@dataclass(frozen=True)
class SoundSpeedMismatch:
    """The tissue's speed of sound differs from the 1540 m/s the scanner assumes by ``sound_speed_error_m_s``.

    Depths are displayed scaled by assumed / true speed (axial scaling of the image). Range
    -90 to +100 m/s: fat ~1450-1480, muscle ~1580-1600, tendon-rich tissue and cartilage up to ~1640, gelatin
    phantoms 1500-1560 m/s (Duck, *Physical Properties of Tissue*, 1990). A reflector fixed in the world
    (``TissueAcoustics.reference_depth_mm``) shows it in a palpation.
    """

    sound_speed_error_m_s: float = 0.0

    def __post_init__(self) -> None:
        _check_finite(self, "sound_speed_error_m_s")

    def acoustics(self, acoustics: TissueAcoustics) -> TissueAcoustics:
        """The tissue acoustics with the true speed of sound."""
        if self.sound_speed_error_m_s == 0:
            return acoustics
        return replace(acoustics, sound_speed_m_s=acoustics.sound_speed_m_s + self.sound_speed_error_m_s)


@dataclass(frozen=True)
class ProbeTilt:
    """The probe face and the tissue surface inclined to each other within the image plane, degrees.

    ``tilt_deg``: the probe tilted about its elevation axis over a level surface (the pose records it);
    ``surface_inclination_deg``: the surface inclined under a level probe (the pose does not record it: the
    surface frame is rotated in the base frame instead, :meth:`surface_rotation`). A palpation sees only their
    sum, :attr:`relative_deg`: the image plane rotated about the centre of the probe face by it, and the face
    meeting the surface progressively from its lower edge (a section with ``face_tilt_deg = -relative_deg``,
    :class:`~usdeform.sim.mechanics.SectionSpec`; lambda counts from first contact, when the face centre is
    ``probe_width / 2 * |tan(relative)|`` above the surface). The robot presses at ``travel_along_axis *
    relative`` to the surface normal (0: along the normal; 1: along the probe's axis, as a robot pressing along its
    tool axis, or a level probe pressed vertically into an inclined surface), so a sticking face drags the tissue
    sideways (``SectionSpec.face_travel_deg``) and the probe moves sideways with it. The sensor measures the axial
    component ``cos(relative)`` of the contact force. Range 0-10 degrees: residual
    misalignment of robotic probes without (or with) normal-positioning control (Jiang et al., "Automatic normal
    positioning of robotic ultrasound probe based only on confidence map optimization and force measurement",
    IEEE RA-L 5(2), 2020); a limb or neck surface slopes by as much under a probe held level.
    """

    tilt_deg: float = 0.0
    surface_inclination_deg: float = 0.0
    travel_along_axis: float = 0.0

    def __post_init__(self) -> None:
        _check_finite(self, "tilt_deg", "surface_inclination_deg", "travel_along_axis")
        if not 0 <= self.travel_along_axis <= 1:
            raise InputError(f"ProbeTilt.travel_along_axis: expected 0-1, got {self.travel_along_axis}")
        for name in ("tilt_deg", "surface_inclination_deg", "relative_deg"):
            if abs(getattr(self, name)) > 30:
                raise InputError(f"ProbeTilt.{name}: expected at most 30 degrees, got {getattr(self, name)}")

    @property
    def relative_deg(self) -> float:
        """The face's tilt to the surface in the image plane, degrees (sign as ``tilt_deg``)."""
        return self.tilt_deg + self.surface_inclination_deg

    @property
    def travel_slope(self) -> float:
        """The probe's lateral travel (mm, along the surface x axis) per mm of indentation."""
        return float(np.tan(np.radians(self.travel_along_axis * self.relative_deg)))

    def surface_rotation(self) -> np.ndarray:
        """(4, 4) rotation of the surface frame (about its elevation axis through its origin) that inclines the
        surface by ``surface_inclination_deg`` in the base frame, so that a probe tilted by ``relative_deg`` to the
        surface has the pose of one tilted by ``tilt_deg`` (the identity without an inclination)."""
        untilted_probe = np.diag([1.0, -1.0, -1.0])  # the probe frame's axes in the surface frame
        rotation = np.eye(4)
        tilted_back = probe_to_surface(ProbeState(0.0, 0.0, -self.surface_inclination_deg))[:3, :3]
        rotation[:3, :3] = tilted_back @ untilted_probe.T
        return rotation


@dataclass(frozen=True)
class ConvexProbeFace:
    """A probe face that is a circular arc of radius ``radius_mm`` in the image plane instead of flat (inf).

    The face meets the surface progressively from its lowest point (a section with ``face_radius_mm``,
    :class:`~usdeform.sim.mechanics.SectionSpec`). Range: 40-80 mm for the footprint of curved linear and
    small convex probes; a flat linear array with a rounded housing acts as a large radius.
    """

    radius_mm: float = float("inf")

    def __post_init__(self) -> None:
        if not (self.radius_mm > 0):
            raise InputError(
                f"ConvexProbeFace.radius_mm: expected a positive radius in mm or inf, got {self.radius_mm}"
            )


@dataclass(frozen=True)
class OutOfPlaneMotion:
    """The imaged tissue moves along the elevation axis: speckle decorrelates between frames.

    Shift of the tissue relative to the image plane, mm: ``shift_mm_per_mm * lambda`` (out-of-plane
    bulging under the probe, which plane strain leaves out) plus ``drift_mm_per_s * t`` (the probe or the
    tissue creeping along the elevation axis: a holder's slow slip, breathing, a patient settling) plus
    independent Gaussian jitter of ``jitter_mm`` rms per frame (probe micro-slip and vibration). Ranges:
    0-0.3 mm/mm, 0-0.3 mm/s (a millimetre or more over a palpation) and 0-0.5 mm, against an elevation slice
    1-2 mm thick, over which speckle fully decorrelates (Prager et al., "Sensorless freehand 3-D ultrasound
    using regression of the echo intensity", Ultrasound Med. Biol. 29(3), 2003).
    """

    shift_mm_per_mm: float = 0.0
    jitter_mm: float = 0.0
    drift_mm_per_s: float = 0.0

    def __post_init__(self) -> None:
        _check_finite(self, "shift_mm_per_mm", "drift_mm_per_s")
        _check_finite(self, "jitter_mm", non_negative=True)

    def shift_mm(self, probe_displacement_mm: float, unit_normal: float, time_s: float = 0.0) -> float:
        """Elevation shift, mm, at indentation lambda and ``time_s`` (s since the recording started) for the
        frame's standard-normal draw ``unit_normal``."""
        return (
            self.shift_mm_per_mm * probe_displacement_mm + self.drift_mm_per_s * time_s + self.jitter_mm * unit_normal
        )


@dataclass(frozen=True)
class LayeredTissue:
    """Skin / fat / muscle layers from the surface down (each a :class:`~usdeform.sim.mechanics.Layer`).

    Typical values: skin 1-3 mm, shear modulus 30-150 kPa; subcutaneous fat 3-20 mm, 0.5-7 kPa;
    muscle 10-30 kPa (shear = Young / 3; Samani et al., Phys. Med. Biol. 52, 2007; Krouskop et al.,
    Ultrason. Imaging 20, 1998). Empty = homogeneous.
    """

    layers: tuple[Layer, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "layers", tuple(self.layers))


@dataclass(frozen=True)
class SlidingContact:
    """Frictionless sliding of the tissue under the probe face instead of sticking.

    Coupling gel lubricates the contact (friction coefficients well below 0.1 with gel), so reality
    is nearer sliding than the sticking the paper's boundary model implies. Off = stick.
    """

    enabled: bool = False


@dataclass(frozen=True)
class LumenPressure:
    """Pressure inside the vessel lumen, kPa, resisting its collapse.

    Range: veins 0.5-2 kPa (4-15 mmHg, supine), arteries 10-16 kPa (80-120 mmHg); water-filled
    phantom vessels a few kPa of hydrostatic head.
    """

    pressure_kpa: float = 0.0

    def __post_init__(self) -> None:
        _check_finite(self, "pressure_kpa", non_negative=True)


Effect: TypeAlias = (
    ImageLatency
    | ForceSensorError
    | Viscoelasticity
    | SoundSpeedMismatch
    | ProbeTilt
    | ConvexProbeFace
    | OutOfPlaneMotion
    | LayeredTissue
    | SlidingContact
    | LumenPressure
)

_FIELD_OF_TYPE = {
    ImageLatency: "latency",
    ForceSensorError: "force_sensor",
    Viscoelasticity: "viscoelasticity",
    SoundSpeedMismatch: "sound_speed",
    ProbeTilt: "tilt",
    ConvexProbeFace: "face",
    OutOfPlaneMotion: "out_of_plane",
    LayeredTissue: "layers",
    SlidingContact: "sliding",
    LumenPressure: "lumen_pressure",
}


@dataclass(frozen=True)
class Effects:
    """The set of effects of one recording; every field defaults to the effect switched off."""

    latency: ImageLatency = ImageLatency()
    force_sensor: ForceSensorError = ForceSensorError()
    viscoelasticity: Viscoelasticity = Viscoelasticity()
    sound_speed: SoundSpeedMismatch = SoundSpeedMismatch()
    tilt: ProbeTilt = ProbeTilt()
    face: ConvexProbeFace = ConvexProbeFace()
    out_of_plane: OutOfPlaneMotion = OutOfPlaneMotion()
    layers: LayeredTissue = LayeredTissue()
    sliding: SlidingContact = SlidingContact()
    lumen_pressure: LumenPressure = LumenPressure()

    def __post_init__(self) -> None:
        for name, kind in ((field, kind) for kind, field in _FIELD_OF_TYPE.items()):
            if not isinstance(getattr(self, name), kind):
                raise InputError(
                    f"Effects.{name}: expected a {kind.__name__}, got {type(getattr(self, name)).__name__}"
                )

    @classmethod
    def of(cls, effects: Effects | Iterable[Effect] | None) -> Effects:
        """Effects from an Effects, a list of effect objects (at most one of each kind) or None (none)."""
        if effects is None:
            return cls()
        if isinstance(effects, Effects):
            return effects
        chosen: dict[str, Any] = {}  # field name -> effect of that field's type
        for effect in effects:
            name = _FIELD_OF_TYPE.get(type(effect))
            if name is None:
                raise InputError(
                    f"effects: expected effect objects from usdeform.sim.effects, got {type(effect).__name__}"
                )
            if name in chosen:
                raise InputError(f"effects: {type(effect).__name__} given twice")
            chosen[name] = effect
        return cls(**chosen)

    def section_changes(self) -> dict[str, object]:
        """SectionSpec fields changed by the mechanical effects (layers, sliding contact, lumen
        pressure, the face's tilt to the surface and its curvature), for
        :meth:`usdeform.sim.phantoms.Phantom.with_section_changes`; empty when all are off."""
        changes: dict[str, object] = {}
        if self.layers.layers:
            changes["layers"] = self.layers.layers
        if self.sliding.enabled:
            changes["contact"] = "slide"
        if self.lumen_pressure.pressure_kpa != 0:
            changes["lumen_pressure_kpa"] = self.lumen_pressure.pressure_kpa
        if self.tilt.relative_deg != 0:
            changes["face_tilt_deg"] = -self.tilt.relative_deg  # the image's tilt is the face's, sign reversed
        if self.tilt.travel_slope:
            changes["face_travel_deg"] = self.tilt.travel_along_axis * self.tilt.relative_deg
        if np.isfinite(self.face.radius_mm):
            changes["face_radius_mm"] = self.face.radius_mm
        return changes

    def relaxation(self, time_step_s: float) -> _RelaxationIntegrator:
        """A fresh QLV force integrator for this recording's time step (identity when elastic)."""
        return _RelaxationIntegrator(self.viscoelasticity, time_step_s)
