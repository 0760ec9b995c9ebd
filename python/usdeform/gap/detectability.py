"""Which library effects these recordings could reveal at all: a noise-free power check of the gap tests.

A "no significant gap" verdict says only that the recordings show no effect *that they can show*. Some
effects leave almost nothing a palpation measures: a wrong speed of sound scales displayed depths
uniformly, which neither strain nor a geometry calibrated on the same image can see; frictionless and
bonded contact of a flat probe coincide as the tissue nears incompressibility (Dundurs' second constant,
proportional to 1 - 2 nu, vanishes), so sliding moves the tracked tissue by hundredths of a millimetre. So
the diagnosis states, for each library effect, whether it would leave a significant gap in *these*
recordings (their frames, forces, tracked points and uncertainties) at the top of its realistic range.

Check: the calibrated simulator with the effect at ``LARGEST_REALISTIC`` (fitted, like every candidate, to
the recording's fitting split) stands in for the recording; the ideal simulator is fitted to it in turn, and
its expected residuals, divided by the recording's own uncertainties, go through the gap tests of the verdict
(:func:`usdeform.gap.measures.gap_tests`, both splits). No noise is added: an effect that passes would show
in about half of such recordings at that magnitude, one that fails in fewer. Image statistics (mean
intensity, near-field band) are left out: no library effect changes them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .cases import HeldOutCase
from .measures import correlation_roughness, residual_sums
from .models import EFFECTS, predict
from .observations import Observation
from .statistics import gap_tests

__all__ = [
    "GAIN_PROTOCOL",
    "GAIN_REASON",
    "LARGEST_REALISTIC",
    "MAX_REPEATS",
    "ProtocolAdvice",
    "effect_repeats",
    "protocol_advice",
    "protocol_text",
    "recording_figures",
    "repeats_needed",
    "undetectable_effects",
]

# The top of each effect's realistic range (the sources are in usdeform.sim.effects); the second parameter of
# a two-parameter effect sits mid-range.
LARGEST_REALISTIC: dict[str, dict[str, float]] = {
    "image_latency": {"delay_s": 0.15},  # video paths and frame buffers, 0-0.15 s
    "force_sensor_error": {"offset_n": 1.0},  # residual bias after taring, 0-1 N
    "viscoelasticity": {"g": 0.45, "tau_s": 1.0},  # soft tissue relaxes 20-50 %; tau mid-range of 0.1-100 s
    "sound_speed_mismatch": {"error_m_s": -90.0},  # fat (~1450 m/s) against the assumed 1540 m/s
    "probe_tilt": {"tilt_deg": 10.0, "travel_along_axis": 0.5},  # 0-10 degrees of misalignment, either travel
    # 0-0.3 mm/mm; jitter of 0-0.5 mm; drift 0-0.3 mm/s, left out here (the check of the steady shift)
    "out_of_plane_motion": {"shift_mm_per_mm": 0.3, "jitter_mm": 0.3, "drift_mm_per_s": 0.0},
    "layered_tissue": {"thickness_mm": 10.0, "modulus_ratio": 0.2},  # subcutaneous fat, 3-20 mm, far softer
    "sliding_contact": {"slip_fraction": 1.0},  # frictionless contact
    "lumen_pressure": {"pressure_ratio": 0.25},  # a quarter of the shear modulus: a few kPa (veins, phantoms)
    "force_latency": {"delay_s": 0.15},  # force streams stamped on arrival (bridges, DAQ buffers), 0-0.15 s
}


def _expected_recording(case: HeldOutCase, effect: str) -> tuple[Observation, np.ndarray]:
    """The observation replaced by the calibrated simulation with ``effect`` at its largest realistic magnitude,
    and the expected correlation roughness of that simulation."""
    observation = case.observation
    parameters = LARGEST_REALISTIC[effect]
    if effect == "force_sensor_error":  # its parameters enter the force fit linearly: add the offset directly
        simulated = case.ideal
        force = simulated.force_n + parameters["offset_n"]
    else:
        simulated, _ = predict(observation, case.section, {effect: parameters}, case.fit)
        force = simulated.force_n
    area = observation.vessel_area_mm2
    if simulated.vessel_area_ratio is not None:
        area = simulated.vessel_area_ratio * area[observation.reference_index]
    expected = dataclasses.replace(
        observation,
        force_n=force,
        displacement_px=np.where(np.isfinite(observation.displacement_px), simulated.displacement_px, np.nan),
        correlation=np.where(np.isfinite(observation.correlation), simulated.correlation, np.nan),
        vessel_area_mm2=np.where(np.isfinite(observation.vessel_area_mm2), area, np.nan),
    )
    roughness = correlation_roughness(expected.correlation)
    if simulated.correlation_roughness is not None:
        roughness = np.where(np.isfinite(roughness), simulated.correlation_roughness, np.nan)
    return expected, roughness


def _expected_z(cases: Sequence[HeldOutCase], effect: str) -> tuple[np.ndarray, np.ndarray]:
    """Held-out and fitting-split z-scores of the ideal simulator fitted to the expected recordings of ``cases``
    with ``effect`` at the top of its realistic range (no noise)."""
    held, fitting = [], []
    for case in cases:
        expected, roughness = _expected_recording(case, effect)
        ideal, _ = predict(expected, case.section, {}, case.fit)
        held_z, fitting_z = case.split_z(*residual_sums(expected, case.layout, ideal, observed_roughness=roughness))
        held.append(held_z)
        fitting.append(fitting_z)
    return np.concatenate(held), np.concatenate(fitting)


def effect_repeats(cases: Sequence[HeldOutCase], groups: np.ndarray) -> dict[str, int | None]:
    """For each library effect (library order), how many recordings like those of ``cases`` (each with its layout,
    splits and uncertainties) it takes to reveal it at the top of its realistic range (:func:`repeats_needed`):
    1 when these do."""
    return {model.effect: repeats_needed(*_expected_z(cases, model.effect), groups) for model in EFFECTS}


def undetectable_effects(cases: Sequence[HeldOutCase], groups: np.ndarray) -> list[str]:
    """IDs of the library effects that, at the top of their realistic range, would leave no significant gap
    in the recordings of ``cases``, in library order."""
    return [effect for effect, repeats in effect_repeats(cases, groups).items() if repeats != 1]


MAX_REPEATS = 16  # more palpations of the same kind than this is no protocol one would advise


def repeats_needed(held: np.ndarray, fitting: np.ndarray, groups: np.ndarray) -> int | None:
    """The fewest repeats (1 to ``MAX_REPEATS``) of these recordings after which expected z-scores ``held`` and
    ``fitting`` pass the gap tests: k palpations of the same kind average to z-scores sqrt(k) as large. None when
    even ``MAX_REPEATS`` would not: the effect needs another protocol, not more of this one."""
    for repeats in range(1, MAX_REPEATS + 1):
        scale = np.sqrt(repeats)
        if gap_tests((held * scale, fitting * scale), groups)[0]:
            return repeats
    return None


@dataclass(frozen=True)
class ProtocolAdvice:
    """What to record next for one effect these recordings could not reveal (``reason`` "undetectable") or
    could not tell from another (``reason`` "ambiguous with B", or "ambiguous with tissue stiffness" for a force
    sensor's gain error, which no palpation can tell from a stiffer tissue): ``repeats`` palpations like these would
    reveal it at the top of its realistic range (None: no number would), and ``protocol`` is the recording that shows
    its own signature."""

    effect: str
    reason: str
    repeats: int | None
    protocol: str


GAIN_REASON = "ambiguous with tissue stiffness (a gain error of the force sensor)"
GAIN_PROTOCOL = (
    "a known weight (a calibrated mass hung from, or a scale pressed by, the probe in its holder): a sensor that "
    "reads a fixed fraction too high or too low scales every force, which the fit takes up as stiffer or softer "
    "tissue. The correction is unaffected while the sweep is recorded with the same sensor; the stiffness and "
    "modulus reported are scaled by it"
)


def recording_figures(observation: Observation) -> tuple[float, float, float]:
    """A palpation's hold at the top indentation (s), loading rate (mm/s) and deepest indentation (mm)."""
    lam, time = observation.probe_displacement_mm, observation.time_s
    top = int(np.argmax(lam))
    near_top = lam >= lam[top] - max(0.03 * lam[top], 0.05)
    rate = float(lam[top] - lam[0]) / max(float(time[top] - time[0]), 1e-9)
    return float(np.ptp(time[near_top])), rate, float(lam[top])


def _protocol_figures(cases: Sequence[HeldOutCase]) -> tuple[float, float, float]:
    """The recordings' longest hold at the top indentation (s), fastest loading rate (mm/s) and deepest
    indentation (mm)."""
    holds, rates, depths = zip(*(recording_figures(case.observation) for case in cases), strict=True)
    return max(holds), max(rates), max(depths)


def protocol_text(effect: str, cases: Sequence[HeldOutCase]) -> str:
    """The recording that would show ``effect``'s own signature, in numbers taken from these recordings."""
    hold_s, rate_mm_s, depth_mm = _protocol_figures(cases)
    tau_s = LARGEST_REALISTIC["viscoelasticity"]["tau_s"]
    texts = {
        "image_latency": f"a second ramp about three times as fast ({3 * rate_mm_s:.1f} mm/s; these: "
        f"{rate_mm_s:.1f} mm/s): a delay leaves a residual in proportion to the loading rate",
        "force_sensor_error": "frames out of contact before and after the press (lift the probe off for 1 s) and a "
        "second palpation a few minutes later: a bias reads out of contact, a drift changes between the two",
        "viscoelasticity": f"a hold of {max(3 * tau_s, 2 * hold_s, 5.0):.0f} s at the top force (these: "
        f"{hold_s:.1f} s) and a second ramp speed: relaxation lets the force fall at a constant indentation",
        "sound_speed_mismatch": "a target of known depth (a wire, the base of a phantom) or the same target "
        "imaged at a second tilt of 10-15 degrees: a palpation's strain cannot show a uniform depth scale",
        "probe_tilt": "a second palpation at a known tilt of 5 degrees each way about the elevation axis: the "
        "lateral shear a tilt adds changes sign with it, and the contact's progress from the lower edge with it "
        "(a palpation sees only the angle between face and surface: the probe's pose during it tells a tilted "
        "probe from an inclined surface)",
        "out_of_plane_motion": f"a hold of {max(2 * hold_s, 5.0):.0f} s (the speckle decorrelates while the "
        "indentation stays) and a second ramp speed: a drift in time and one in proportion to the indentation part",
        "layered_tissue": f"a deeper press, to about {1.5 * depth_mm:.0f} mm (these: {depth_mm:.1f} mm): a soft layer "
        "takes the strain in its depth band, more so as it compresses",
        "sliding_contact": "a palpation at another position, with tissue tracked near the probe face's edges, where "
        "slip and bonding differ most",
        "lumen_pressure": "a palpation away from the vessel, and one pressed until the lumen closes: the lumen's "
        "push at contact is there only over the vessel",
        "force_latency": f"a second ramp about three times as fast ({3 * rate_mm_s:.1f} mm/s) and a hold of "
        f"{max(2 * hold_s, 5.0):.0f} s: a late force stream's residual grows with the loading rate and vanishes in "
        "the hold, where relaxation creeps",
    }
    return texts[effect]


def protocol_advice(
    cases: Sequence[HeldOutCase], repeats: dict[str, int | None], ambiguous: Sequence[str] = ()
) -> list[ProtocolAdvice]:
    """What to record next: for each effect these recordings could not reveal (``repeats`` other than 1, see
    :func:`effect_repeats`) the repeats that would and the protocol that shows its signature; for the two effects
    an ambiguous verdict names (``ambiguous``; pairs split into their effects), the protocols that tell them
    apart; and always the force sensor's gain error, which scales every force as a stiffer or softer tissue would
    (the elastic force fit takes it up), with the recording that measures it."""
    advice = [
        ProtocolAdvice(effect, "undetectable", count, protocol_text(effect, cases))
        for effect, count in repeats.items()
        if count != 1
    ]
    for index, named in enumerate(ambiguous):
        other = ambiguous[1 - index] if len(ambiguous) == 2 else ""
        for effect in named.split("+"):
            if effect in other.split("+") or effect not in LARGEST_REALISTIC:
                continue
            advice.append(ProtocolAdvice(effect, f"ambiguous with {other}", None, protocol_text(effect, cases)))
    advice.append(ProtocolAdvice("force_sensor_error", GAIN_REASON, None, GAIN_PROTOCOL))
    return advice
