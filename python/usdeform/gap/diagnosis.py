"""``diagnose``: where the sim-to-real gap lies, which library effect explains it, how far it shrinks."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter1d
from tqdm import tqdm

from .._arrays import finite_or_none
from ..errors import InputError
from ..io import PlusConfig
from ..recording import Recording
from .attribution import FITS, SIGNATURES, Attribution, MeasureResult, attribute
from .calibration import calibrate, library_solves
from .correction_outcome import compensation_outcome, correction_measures
from .detectability import ProtocolAdvice
from .follow_up import FollowUpRecording, first_protocol, plan_follow_up, recording_position_mm
from .inputs import as_recordings
from .models import surveyed_depth_mm, without_points_near_base
from .observations import Observation, observe
from .processes import run_all, worker_pool
from .reference_target import reference_sentence, reference_targets
from .sensor_calibration import known_sensor, known_weight_calibration, sensor_finding
from .statistics import critical_z
from .verdicts import MIN_SHRINK_EXPLAINED, CandidateResult

__all__ = ["Diagnosis", "check_seed", "diagnose"]

_INTENSITY_FLOOR = 2.0  # grey levels: speckle-model and beam-profile differences every simulator has


@dataclass
class Diagnosis:
    """The diagnosis of one set of palpation recordings (see ``to_json`` for the file contract).

    verdict: one of :data:`usdeform.gap.attribution.VERDICTS` (see :func:`usdeform.gap.attribution.decide`);
    named: the effects the verdict names (two when ambiguous, none without an attribution). effects: every
    candidate, best first, each with the parameters it fitted at an edge of the library (``at_bound``).
    measures: every held-out measure of the ideal simulation (recorded minus simulated) with its
    uncertainty, significance (both splits together) and value after adding the best candidate (None for image
    statistics, which no library effect changes), and its value on the fitting split. calibration: the
    fitted free parameters of the ideal simulator. gap_shown_by_candidate: no measure or group differed on its own
    and the gap was seen through a clean candidate's held-out test (:func:`usdeform.gap.attribution.attribute`).
    undetectable: library effects that would leave no significant
    gap in these recordings even at the top of their realistic range (:mod:`usdeform.gap.detectability`).
    record_next: for each of those, and for the two effects of an ambiguous verdict, what to record next (the
    repeats that would reveal it, the protocol that shows its signature). compensation: what the named effect
    costs the correction and what compensating it gives back (:func:`usdeform.gap.correction_outcome.
    compensation_outcome`).
    """

    verdict: str
    summary: str
    effects: list[CandidateResult]
    measures: list[MeasureResult]
    calibration: list[dict[str, object]]
    gap_before: float
    critical_z: float
    undetectable: list[str] = field(default_factory=list)
    named: list[str] = field(default_factory=list)
    record_next: list[ProtocolAdvice] = field(default_factory=list)
    compensation: dict[str, Any] = field(default_factory=dict)
    gap_shown_by_candidate: bool = False
    recordings: list[str] = field(default_factory=list)  # the files read (absolute), for ``diagnose --follow-up``
    follow_up: list[FollowUpRecording] = field(default_factory=list)  # record_next.json (gap.follow_up)
    # library sections left out ({"recording", "section", "error", "effect"}) and solved another way
    # ({"recording", "section", "how"}): see :class:`usdeform.gap.attribution.Attribution`
    unsolved_sections: list[dict[str, str]] = field(default_factory=list)
    resolved_sections: list[dict[str, str]] = field(default_factory=list)
    # the force sensor fitted on each known-weight recording (SensorCalibration.to_json)
    sensor_calibration: list[dict[str, Any]] = field(default_factory=list)
    # per recording with a reflector fixed in the world asked for: what it shows (gap.reference_target)
    reference_targets: list[dict[str, Any]] = field(default_factory=list)
    observations: list[Observation] = field(default_factory=list, repr=False)
    attribution: Attribution | None = field(default=None, repr=False)

    def to_json(self) -> dict[str, object]:
        """The diagnosis.json contract."""
        return {
            "verdict": self.verdict,
            "named": self.named,
            "summary": self.summary,
            "effects": [
                {
                    "effect": effect.effect,
                    "parameters": effect.parameters,
                    "uncertainty": effect.uncertainty,
                    "gap_before": effect.gap_before,
                    "gap_after": effect.gap_after,
                    "shrink": effect.shrink,
                    "significant": effect.significant,
                    "at_bound": effect.at_bound,
                    "signature_shrink": effect.signature_shrink,
                    "signature_absent": effect.signature_absent,
                    "signature_left": effect.signature_left,
                    "unidentified": effect.unidentified,
                }
                for effect in self.effects
            ],
            "measures": [
                {
                    "name": measure.name,
                    "region": measure.region,
                    "force_range_n": list(measure.force_range_n) if measure.force_range_n is not None else None,
                    "phase": measure.phase,
                    "value": finite_or_none(measure.value),
                    "uncertainty": finite_or_none(measure.uncertainty),
                    "significant": measure.significant,
                    "recording": measure.recording,
                    "value_after": finite_or_none(measure.value_after),
                    "value_fitting_split": finite_or_none(measure.value_fitting_split),
                    "uncertainty_fitting_split": finite_or_none(measure.uncertainty_fitting_split),
                }
                for measure in self.measures
            ],
            "calibration": self.calibration,
            "gap_before": self.gap_before,
            "critical_z": self.critical_z,
            "undetectable": self.undetectable,
            "record_next": [dataclasses.asdict(advice) for advice in self.record_next],
            "compensation": self.compensation,
            "gap_shown_by_candidate": self.gap_shown_by_candidate,
            "recordings": self.recordings,
            "unsolved_sections": self.unsolved_sections,
            "resolved_sections": self.resolved_sections,
            "sensor_calibration": self.sensor_calibration,
            "reference_targets": self.reference_targets,
        }


def _block_bootstrap(observation: Observation, rng: np.random.Generator, statistic, n: int = 200) -> np.ndarray:
    """``statistic(frame_weights)`` over ``n`` resamples of whole time blocks with replacement, stacked."""
    blocks = np.unique(observation.block)
    results = []
    for _ in range(n):
        counts = np.bincount(rng.choice(blocks, len(blocks)), minlength=observation.block.max() + 1)
        results.append(statistic(counts[observation.block].astype(float)))
    return np.array(results)


def _intensity_measures(observation: Observation, rng: np.random.Generator, z_crit: float) -> list[MeasureResult]:
    """Mean intensity against depth minus the calibrated gain + attenuation line, per depth band."""
    depth = observation.intensity_depth_mm
    profile_rows = observation.intensity
    usable = np.isfinite(profile_rows).all(axis=0)
    if usable.sum() < 3:
        return []

    def residual(weights: np.ndarray) -> np.ndarray:
        profile = weights @ np.nan_to_num(profile_rows[:, usable]) / weights.sum()
        slope, intercept = np.polyfit(depth[usable], profile, 1)
        return profile - (slope * depth[usable] + intercept)

    point = residual(np.ones(observation.n_frames))
    boot = _block_bootstrap(observation, rng, residual)
    sigma = np.sqrt(np.std(boot, axis=0) ** 2 + _INTENSITY_FLOOR**2)
    band = np.ptp(depth) / max(len(depth) - 1, 1) / 2
    return [
        MeasureResult(
            name="mean_intensity_vs_depth",
            recording=observation.name,
            group="image_intensity",
            region=f"depth {d - band:.0f}-{d + band:.0f} mm",
            force_range_n=None,
            phase="all",
            value=float(v),
            uncertainty=float(s),
            significant=bool(abs(v) > z_crit * s),
        )
        for d, v, s in zip(depth[usable], point, sigma, strict=True)
    ]


_NEAR_FIELD_MM = (0.5, 10.0)  # depth range of the near field below the probe face, mm
_BAND_HIGH_PASS_MM = 1.0  # Gaussian sigma of the smooth depth trend (gain, TGC, attenuation, focus) removed, mm


def _high_pass(profile: np.ndarray, sigma_px: float) -> np.ndarray:
    """Profile minus its Gaussian smoothing (the depth trend), NaNs filled by interpolation first."""
    rows = np.arange(profile.shape[-1])
    filled = np.zeros(profile.shape)
    for index, values in enumerate(profile):
        ok = np.isfinite(values)
        if ok.any():
            filled[index] = np.interp(rows, rows[ok], values[ok])
    return filled - gaussian_filter1d(filled, sigma_px, axis=-1, mode="nearest")


def _correlation_length_px(values: np.ndarray) -> float:
    """Integral correlation length (pixels) of a zero-mean profile: 1 + 2 sum of its autocorrelation up to
    the first non-positive lag."""
    values = values - values.mean()
    variance = float(values @ values)
    if variance <= 0:
        return 1.0
    length = 1.0
    for lag in range(1, len(values) // 2):
        rho = float(values[lag:] @ values[:-lag]) / variance
        if rho <= 0:
            break
        length += 2 * rho
    return length


def _near_field_band_measure(observation: Observation, rng: np.random.Generator, z_crit: float) -> list[MeasureResult]:
    """Coherence of horizontal bands under the probe (reverberation, or any echo pattern across the image).

    The frame-averaged mean grey level of each near-field row (0.5-10 mm, above the vessel), high-passed
    to remove the depth trend, is correlated between every pair of the image's lateral strips, and the
    pairwise correlations are averaged. Speckle in different strips is independent, so for a simulator or
    a recording without banding each pairwise r is about normal with variance 1 / K, K the number of
    independent rows (the near-field depth over the profile's correlation length, measured below the near
    field), and the P pairwise r are uncorrelated: the mean has variance 1 / (K P). Bands that span the
    width make every r positive. Uncertainty: that chance spread combined with the block bootstrap.
    """
    strips = observation.row_profile_strips
    if strips is None:
        return []
    axial_mm = observation.image_to_probe[2, 1]
    depth = observation.row_depth_mm(np.arange(strips.shape[2]))
    bottom = _NEAR_FIELD_MM[1]
    if observation.vessel_center_probe_mm is not None and observation.vessel_radius_mm is not None:
        bottom = min(bottom, float(observation.vessel_center_probe_mm[1]) - observation.vessel_radius_mm - 2.0)
    near = (depth >= _NEAR_FIELD_MM[0]) & (depth <= bottom)
    deep = depth > max(bottom, _NEAR_FIELD_MM[1]) + 2.0
    if near.sum() * axial_mm < 3.0 or deep.sum() < 20:
        return []
    sigma_px = _BAND_HIGH_PASS_MM / axial_mm
    pairs = np.triu_indices(strips.shape[1], k=1)

    finite = np.isfinite(strips)
    values = np.where(finite, strips, 0.0)

    def mean_profile(weights: np.ndarray) -> np.ndarray:
        """(strips, rows) weighted frame mean, high-passed."""
        total = np.einsum("n,nsr->sr", weights, values)
        count = np.einsum("n,nsr->sr", weights, finite.astype(float))
        return _high_pass(np.where(count > 0, total / np.maximum(count, 1e-12), np.nan), sigma_px)

    def coherence(weights: np.ndarray) -> float:
        profile = mean_profile(weights)[:, near]
        profile = profile - profile.mean(axis=1, keepdims=True)
        profile /= np.maximum(np.linalg.norm(profile, axis=1, keepdims=True), 1e-12)
        return float(np.mean((profile @ profile.T)[pairs]))

    value = coherence(np.ones(observation.n_frames))
    boot = _block_bootstrap(observation, rng, coherence)
    overall = mean_profile(np.ones(observation.n_frames))
    length_px = np.mean([_correlation_length_px(overall[strip, deep]) for strip in range(strips.shape[1])])
    independent_rows = near.sum() / length_px
    sigma = float(np.sqrt(1.0 / (max(independent_rows, 1.0) * len(pairs[0])) + np.var(boot)))
    return [
        MeasureResult(
            name="near_field_band_coherence",
            recording=observation.name,
            group="image_intensity",
            region=f"depth {_NEAR_FIELD_MM[0]:g}-{bottom:.1f} mm, coherence across lateral strips",
            force_range_n=None,
            phase="all",
            value=value,
            uncertainty=sigma,
            significant=bool(abs(value) > z_crit * sigma),
        )
    ]


def _where(measures: list[MeasureResult]) -> str:
    significant = [m for m in measures if m.significant]
    if not significant:  # seen through a clean candidate's held-out test (Attribution.gap_shown_by_candidate)
        return (
            "many measures, none of which differs beyond its uncertainty on its own: it shows in the held-out test of "
            "the effect below, fitted on one half of the recording and taking most of the gap on the other"
        )
    worst = sorted(significant, key=lambda m: -abs(m.value) / m.uncertainty)[:3]
    parts = []
    for measure in worst:
        force = f", {measure.force_range_n[0]:.1f}-{measure.force_range_n[1]:.1f} N" if measure.force_range_n else ""
        parts.append(f"{measure.name} ({measure.region}{force}, {measure.phase})")
    groups = sorted({m.group for m in significant})
    if len(significant) == 1:
        return f"1 measure of {groups[0]}: {parts[0]}"
    return f"{len(significant)} measures of {', '.join(groups)}, most of all {'; '.join(parts)}"


def _parameter_text(effect: CandidateResult) -> str:
    """``name = value +/- error`` of every fitted parameter, those at an edge of the library marked."""
    return ", ".join(
        f"{name} = {value:.3g} +/- {effect.uncertainty.get(name, float('nan')):.2g}"
        + (" (at the edge of the library)" if name in effect.at_bound else "")
        for name, value in effect.parameters.items()
    )


def _summary(
    verdict: str,
    measures: list[MeasureResult],
    effects: list[CandidateResult],
    named: list[str],
    lead_reason: str,
) -> str:
    where = _where(measures)
    best = effects[0]
    if verdict == "no_significant_gap":
        text = "No significant gap: the calibrated ideal simulator explains the recordings within their uncertainty."
        if best.shrink <= 0:
            return text
        return (
            f"{text} The candidate that fits best, {best.effect}, would shrink the held-out gap by "
            f"{100 * best.shrink:.0f} %, but what it shrinks is within the uncertainty: a lead to test with a harder "
            "press or a longer hold, not an attribution."
        )
    parameters = _parameter_text(best)
    held_out = (
        f"shrinks it by {100 * best.shrink:.0f} % held out (gap {best.gap_before:.3g} -> {best.gap_after:.3g}; "
        "fitted on each half of the recording, measured on the other)"
    )
    if verdict == "explained":
        return (
            f"The gap lies in {where}. It is best explained by {best.effect} ({parameters}), which {held_out}."
            f"{_passed_over(effects, lead_reason)}"
        )
    if verdict == "explained_in_part" and best.shrink < MIN_SHRINK_EXPLAINED:
        own = "; ".join(
            f"{100 * shrink:.0f} % of it in {', '.join(SIGNATURES[member])}"
            for member, shrink in best.signature_shrink.items()
        )
        return (
            f"The gap lies in {where}. It is explained only in part by {best.effect} ({parameters}), which takes "
            f"{own} (the measures where its physics shows) but {100 * best.shrink:.0f} % of the whole gap held out "
            f"(gap {best.gap_before:.3g} -> {best.gap_after:.3g}): the rest lies in measures it does not move, and "
            "no effect of the library explains that."
        )
    if verdict == "explained_in_part":
        return (
            f"The gap lies in {where}. It is explained only in part by {best.effect} ({parameters}), which "
            f"{held_out}, but what remains still differs significantly: another effect, or this one in another "
            f"form, is at work too.{_passed_over(effects, lead_reason)}"
        )
    if verdict == "ambiguous":
        rival = next(effect for effect in effects if effect.effect == named[1])
        return (
            f"The gap lies in {where}. It is ambiguous between {best.effect} ({parameters}; shrink "
            f"{100 * best.shrink:.0f} %) and {rival.effect} ({_parameter_text(rival)}; shrink "
            f"{100 * rival.shrink:.0f} %): their held-out gaps do not differ significantly, or the better takes "
            "less than half of what the other leaves (a difference the ways a robot differs from the simulator "
            f"can make), so these recordings cannot tell them apart.{_passed_over(effects, lead_reason)}"
        )
    if verdict == "at_edge_of_library":
        return (
            f"The gap lies in {where}. The best candidate, {best.effect} ({parameters}), {held_out}, but "
            f"{_why_not_clean(best)}: the data ask for more than the library's form of that effect gives (a larger "
            "effect, the same physics in another form, or an effect outside the library), so this is no clean "
            "explanation."
        )
    return (
        f"The gap lies in {where}. No effect of the library explains it: the best candidate, {best.effect}, "
        f"shrinks it by {100 * best.shrink:.0f} % held out"
        f"{' (significant, but less than half)' if best.significant else ' (not significantly)'}; "
        "the gap is unexplained."
    )


def _why_not_clean(effect: CandidateResult) -> str:
    """Why ``effect`` is no clean explanation: fitted at an edge of the library, and/or the measure groups of its
    own signature left significant."""
    reasons = [f"it was fitted at the edge of the library ({', '.join(effect.at_bound)})"] if effect.at_bound else []
    if effect.signature_left:
        left = ", ".join(effect.signature_left)
        reasons.append(f"what its own physics shows in still differs significantly ({left})")
    return " and ".join(reasons)


def _passed_over(effects: list[CandidateResult], lead_reason: str) -> str:
    """Sentences on the candidates ranked above the named one that were no clean explanation, from why the verdict
    is about it (``lead_reason``, :func:`usdeform.gap.verdicts.lead_candidate`), or "" when there were none:
    ``"as_good"``, their held-out gap is not significantly smaller; ``"clean_member"``, the pair that gave way to it
    (``effects[1]``) takes more of the gap only at the library's edge."""
    named = effects[0]
    passed = [effect for effect in effects[1:] if effect.significant and effect.score < named.score]
    if lead_reason == "best" or not passed:
        return ""
    pair = effects[1] if lead_reason == "clean_member" else None
    others = [effect for effect in passed if effect is not pair]
    text = ""
    if others:
        reasons = [f"{item.effect} (shrink {100 * item.shrink:.0f} %: {_why_not_clean(item)})" for item in others]
        text += f" Ranked above it but not named, as no clean explanation: {'; '.join(reasons)}."
        if lead_reason == "as_good":
            text += " Its held-out gap is not significantly smaller."
    if pair is not None:
        text += (
            f" {pair.effect} takes more of the gap (shrink {100 * pair.shrink:.0f} %), but {_why_not_clean(pair)}: "
            f"what remains beyond {named.effect} asks for more than the library's form of the other effect gives."
        )
    return text


def _undetectable_sentence(verdict: str, undetectable: list[str]) -> str:
    """What the verdict cannot speak for: the effects these recordings could not reveal (none when explained)."""
    if verdict == "explained" or not undetectable:
        return ""
    return (
        f" These recordings could not reveal {', '.join(undetectable)} even at the top of their realistic range, "
        "so the verdict says nothing about them."
    )


def _correction_sentence(measures: list[MeasureResult], attribution: Attribution) -> str:
    """The correction's Dice fitted on the recording, on the ideal simulator and with the best candidate."""
    own = [m for m in measures if m.name == "correction_dice_recording_fit"]
    gaps = [m for m in measures if m.name == "correction_dice"]
    if not own or not gaps or not attribution.candidates:
        return ""
    recording = float(np.mean([m.value for m in own]))
    before = recording - float(np.mean([m.value for m in gaps]))
    after = recording - float(np.mean([m.value_after for m in gaps if m.value_after is not None]))
    return (
        f" The correction (Dice of the highest-force frame corrected to the lowest-force frame) scores {recording:.3f} "
        f"fitted on the recording, {before:.3f} fitted on the ideal simulator and {after:.3f} with "
        f"{attribution.candidates[0].effect} added."
    )


def _unidentified_sentence(effects: list[CandidateResult], named: list[str]) -> str:
    """The parameters of the named effects (or, without one, of the best candidate) the recordings could not identify,
    each held at its neutral value, with the recording that would identify it ("" when none)."""
    shown = [effect for effect in effects if effect.effect in named] or effects[:1]
    parts = [
        f"{name} of {effect.effect} (a {kind} recording would identify it)"
        for effect in shown
        for name, kind in effect.unidentified.items()
    ]
    if not parts:
        return ""
    return f" Not identified by these recordings, so held at its neutral value: {'; '.join(parts)}."


def _sensor_sentence(calibrations: list[dict[str, Any]], ruled_out: list[str]) -> str:
    """The force sensor's gain error and offset on each known weight given, and the significant candidates that rules
    out (``ruled_out``; "" when no known weight was given)."""
    parts = [
        f"gain error {c['gain_error']:.3g} +/- {c['gain_error_uncertainty']:.2g} and offset {c['offset_n']:.3g} +/- "
        f"{c['offset_uncertainty_n']:.2g} N ({Path(c['recording']).name})"
        for c in calibrations
    ]
    if not parts:
        return ""
    finding = sensor_finding(calibrations)
    listed = ", ".join(ruled_out)
    meaning = {
        ("error", True): f" That is a sensor error, which the palpations show too: explanations without it are ruled "
        f"out ({listed}).",
        ("error", False): " That is a sensor error, which the palpations do not show: it rules no explanation out.",
        ("clean", True): f" That is a sensor free of error: explanations with a sensor error are ruled out ({listed}).",
        ("clean", False): " That is a sensor free of error.",
    }.get((finding or "", bool(ruled_out)), "")
    return f" On a known weight the force sensor reads with {'; '.join(parts)}.{meaning}"


def check_seed(seed: object, option: str = "seed") -> int:
    """``seed`` as a non-negative integer (numpy's seeds are), else InputError naming ``option``."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise InputError(f"{option}: expected a non-negative integer, got {seed!r}")
    return int(seed)


def diagnose(
    recordings: Sequence[Recording | str | Path],
    *,
    config: PlusConfig | str | Path | None = None,
    seed: int = 0,
    progress: bool = True,
    workers: int | None = None,
    reference_depth_mm: float | None = None,
) -> Diagnosis:
    """Diagnose the sim-to-real gap of palpation recordings (Recordings, PLUS sequence files or folders of them).

    Sweeps among them (the probe travels across the surface) are listed in ``calibration`` and
    left out: every measure needs a palpation.

    Steps: observe each recording (tracking, speckle correlation, vessel, intensity); calibrate the
    ideal simulator to it (vessel geometry, modulus by modulus scaling, the tissue depth from a survey of three
    sections, the FEM variant library solved around that depth; its
    compressibility, tissue depth, strain stiffening, lumen stiffness and probe face width are fitted with every
    candidate, see :mod:`usdeform.gap.models`); leave out the tracked points next to the calibrated base
    (:func:`usdeform.gap.models.without_points_near_base`); measure the gap; fit each library effect and the best
    pairs on each split and rank them on the other (cross-fitted, see :mod:`usdeform.gap.attribution`).
    ``config``: a PLUS configuration (or its XML path) whose Image -> Probe calibration the sequence files are read
    with, for files that do not carry ``ImageToProbeTransform``. ``seed`` drives the bootstrap only.
    ``workers``: processes for the observations, the FEM library's solves and the attribution's fits (default: the
    available cores, see :func:`usdeform.gap.processes.available_workers`); the diagnosis is the same for any number.
    ``reference_depth_mm``: the depth of a reflector fixed in the world under every palpation, mm below the unloaded
    surface (a recording's header key ``ReferenceTargetDepth`` gives it for that recording alone). Known-weight
    recordings (per-frame ``KnownLoad``) calibrate the force sensor (``sensor_calibration``); they are no palpations.
    """
    seed = check_seed(seed)
    named, sweeps, known_weights = as_recordings(recordings, config)
    sensor = [known_weight_calibration(path, seed).to_json() for path in known_weights]

    with worker_pool(workers) as pool:
        with tqdm(total=len(named), desc="observe", disable=not progress) as bar:
            observations = run_all(
                pool, observe, [(recording, name, reference_depth_mm) for name, recording in named], bar
            )
        # depth first (see usdeform.gap.calibration): the survey of every recording, then each full library at
        # its surveyed depth, the solves of all the recordings together
        with tqdm(
            total=library_solves(observations, survey=True) + library_solves(observations),
            desc="calibrate (FEM library)",
            disable=not progress,
        ) as bar:
            surveys = calibrate(observations, survey=True, progress=bar, pool=pool)
            depths_mm = [surveyed_depth_mm(o, survey) for o, survey in zip(observations, surveys, strict=True)]
            bar.total += library_solves(observations, depths_mm) - library_solves(observations)
            sections = calibrate(observations, depths_mm=depths_mm, progress=bar, pool=pool)
        observations = [without_points_near_base(o, section) for o, section in zip(observations, sections, strict=True)]
        with tqdm(total=FITS, desc="attribute effects", disable=not progress) as bar:
            attribution = attribute(
                observations, sections, seed=seed, progress=bar, pool=pool, sensor=known_sensor(sensor)
            )
    rng = np.random.default_rng(seed + 1)
    intensity_count = sum(np.isfinite(o.intensity).all(axis=0).sum() + 1 for o in observations)
    z_crit = critical_z(len(attribution.measures) + int(intensity_count))
    measures = list(attribution.measures)
    for observation in observations:
        measures += _intensity_measures(observation, rng, z_crit)
        measures += _near_field_band_measure(observation, rng, z_crit)
    for observation, before, after in zip(
        observations, attribution.predictions_before, attribution.predictions_after, strict=True
    ):
        measures += correction_measures(observation, before, after, rng, z_crit)
    verdict = attribution.verdict
    if verdict == "no_significant_gap" and any(m.significant for m in measures):
        verdict = "unexplained"  # only image statistics differ, and no library effect changes them
    calibration: list[dict[str, object]] = [
        {
            "recording": observation.name,
            "shear_modulus_kpa": section.shear_modulus_kpa,
            **{f"section_{name}": value for name, value in parameters.items()},
            "vessel_center_x_mm": section.spec.vessel_center_x_mm if section.has_vessel else None,
            "vessel_depth_mm": section.spec.vessel_depth_mm if section.has_vessel else None,
            "vessel_radius_mm": section.spec.vessel_radius_mm if section.has_vessel else None,
            "mesh_size_mm": section.spec.mesh_size_mm,
        }
        for observation, section, parameters in zip(observations, sections, attribution.section_parameters, strict=True)
    ]
    calibration += [{"recording": name, "ignored": "a sweep: the measures need palpations"} for name in sweeps]
    references = reference_targets(observations)
    diagnosis = Diagnosis(
        verdict=verdict,
        summary=_summary(verdict, measures, attribution.candidates, attribution.named, attribution.lead_reason)
        + _undetectable_sentence(verdict, attribution.undetectable)
        + _correction_sentence(measures, attribution)
        + _unidentified_sentence(attribution.candidates, attribution.named)
        + _sensor_sentence(
            sensor, [c.effect for c in attribution.candidates if c.significant and c.effect in attribution.ruled_out]
        )
        + reference_sentence(references),
        effects=attribution.candidates,
        measures=measures,
        calibration=calibration,
        gap_before=attribution.gap_before,
        critical_z=z_crit,
        undetectable=attribution.undetectable,
        gap_shown_by_candidate=attribution.gap_shown_by_candidate,
        named=attribution.named,
        record_next=attribution.advice,
        observations=observations,
        attribution=attribution,
        unsolved_sections=attribution.unsolved_sections,
        resolved_sections=attribution.resolved_sections,
        sensor_calibration=sensor,
        reference_targets=references,
    )
    diagnosis.recordings = [str(Path(name).resolve()) for name, _ in named if Path(name).is_file()]
    positions = [recording_position_mm(recording) for _, recording in named]
    protocol = first_protocol(observations, positions)
    plan = plan_follow_up(verdict, attribution.candidates, attribution.advice, protocol, attribution.named)
    # a known weight given already calibrates the sensor: it is not asked for again
    diagnosis.follow_up = [entry for entry in plan if not (sensor and entry.kind == "known_weight")]
    diagnosis.compensation = compensation_outcome(
        observations, [recording for _, recording in named], diagnosis.to_json()
    )
    return diagnosis
