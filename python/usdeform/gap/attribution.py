"""Attribution: add each library effect (and the best pairs) to the calibrated simulator, fit it on one
split, measure the gap again on the other, rank, and decide.

Split: alternate time blocks of about 0.3 s (even blocks and odd blocks); every recording contributes to
both, so holding, loading and unloading are in each. Cross-fitting: every candidate is fitted on each split
and measured on the other, and its held-out gap (and each bootstrap row of it) is the mean of the two folds.
So every frame confirms, not half of them: a signature carried by a few frames (one measure at z of 2-3 per
split) is tested on both splits' evidence, never on the one it was fitted to. The measure table and the
figures are those of the first fold (fitted on the even blocks, measured on the odd ones).

Gap G: the mean over measure groups of the mean squared z-score of the group's measures
(:func:`usdeform.gap.measures.gap_statistic`); about 1 or less when the simulation explains the data.

Criterion: effects are ranked by ``G_heldout + 2 k / F`` (k fitted parameters, F measures: Akaike's 2 per parameter
in the units of one squared z-score per measure). An effect (or pair) is *significant* when a gap is seen and its
held-out gap with the penalty is significantly smaller: ``log(G0 / (G1 + 2 k / F))`` exceeds ``z(1 - alpha / m)``
times the block-bootstrap standard error of that log ratio, taken robustly as the interquartile range / 1.349
(alpha = 0.05, m candidates tested: Bonferroni; a one-sided normal test: the empirical alpha / m quantile of 200
resamples would be their worst draw, and for a signature in a few frames, such as the force near contact, a few
resamples miss or double those frames; on the log scale, because a gap's spread grows with its size,
:func:`usdeform.gap.verdicts.significantly_smaller`); a pair must also beat its
better member that way (with its extra parameters), and the better member must leave a significant gap (a measure or
a group, as for the verdict), and its second effect must remove at least half of the gap the better member leaves
(the standard of "explained" applied to the increment, so that an effect flexible enough to soak up nuisance is not
added for a sliver). A candidate is significant only where its own signature is present too (:data:`SIGNATURES`):
the held-out gap over its signature groups is significantly smaller with it at ``z(1 - alpha)`` (for a pair, with
each member's). Verdicts (:func:`usdeform.gap.verdicts.decide`): with a significant best-ranked
candidate that removes at least half of the held-out gap (shrink >= 0.5: most of the gap, not a sliver of it),
the verdict is about the best unless it is no clean explanation and a clean candidate's held-out gap is not
significantly larger, or it is a pair at an edge only through one member while its other member alone is a clean
explanation (:func:`usdeform.gap.verdicts.lead_candidate`); then it is about that one, and
``at_edge_of_library`` when a parameter of it was fitted at an edge of the library (``CandidateResult.at_bound``:
the data ask for more than the library's form of the effect gives, a fit that is no clean explanation), else
``ambiguous`` when the next such candidate not nested in it nor at an edge has a held-out gap not significantly
larger, or the best does not take half of the gap it leaves (the two named), else ``explained_in_part`` when a
measure or a group still differs significantly with it added, else ``explained``; with a significant best that
shrinks less, ``explained_in_part`` when it takes at least ``MIN_SIGNATURE_SHRINK`` (0.9) of the gap over its own
signature groups, none absent or left and no parameter at an edge (the rest of the gap lies in measures its physics
does not move), ``ambiguous`` when a rival that does too is as good; ``unexplained`` when some candidate is
significant but shrinks less otherwise, or a measure differs beyond z_crit (Bonferroni over measures), or a group of
measures jointly (chi-square, Bonferroni over groups);
``no_significant_gap`` otherwise. A gap is seen where a measure differs beyond z_crit or a group jointly, or,
where none does, through a clean candidate (significant, shrink >= 0.5, no parameter at an edge, no signature
group left): a directed test of the effect's own form, with more power than the tests of each measure against a
gap spread thinly over many (a lumen pressure of a few kPa, fitted to within 3 %, that no single measure shows).
The tests of the gap take each measure's z-scores on both splits together
(:func:`gap_tests`): the frames that carry a signature can fall mostly in one, such as the few frames at first
contact where a sensor offset shows undiluted by the elastic fit; on the fitting split the ideal simulation's linear
parameters were fitted, so the evidence it adds is conservative. These are the only thresholds: alpha and the
half of "most of the gap" are conventions, and ``MIN_SIGNATURE_SHRINK`` ("nearly all" of a signature) a round value
that this project's own benchmark separates with a margin (see its comment), not fitted to any generator's cases.
"""

from __future__ import annotations

import itertools
import math
from concurrent.futures import Executor
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import norm

from .calibration import CalibratedSection
from .detectability import ProtocolAdvice, effect_repeats, protocol_advice
from .folds import (
    LINEAR_IDENTIFIED_BY,
    LINEAR_NEUTRAL,
    Fold,
    HeldOut,
    as_effects,
    fit_all,
    fit_folds,
    fit_in_fold,
    linear_parameters,
    parameter_uncertainty,
    unidentified_linear,
)
from .measures import GROUPS, Prediction
from .models import EFFECTS, LINEAR_PARAMETERS
from .observations import Observation
from .sensor_calibration import KnownSensor
from .statistics import combined_z, critical_z, gap_tests
from .verdicts import (
    ALPHA,
    MIN_SHRINK_EXPLAINED,
    VERDICTS,
    CandidateResult,
    decide,
    is_clean,
    lead_candidate,
    needs_signature_left,
    parameter_names,
    parameters_at_edge,
    ruled_out_by_known_weight,
    significantly_smaller,
)

__all__ = [
    "FITS",
    "VERDICTS",
    "Attribution",
    "CandidateResult",
    "MeasureResult",
    "attribute",
    "decide",
    "parameters_at_edge",
]

_PAIRS_FROM_TOP = 3
#: The fits of an attribution: each library effect's (its folds in turn), and each pair's in each of the two folds.
FITS = len(EFFECTS) + 2 * math.comb(_PAIRS_FROM_TOP, 2)
#: A candidate acts on a measure that it moves by at least one standard error (combined over the splits), away from
#: zero or by at least ``_ACTED_SHARE`` of the measure's gap without it; a residual it leaves in its own signature
#: counts against it only in measures it acts on. A static misfit of the section that a delay leaves as it was, or
#: only nudges towards zero (an image delay moving a lateral displacement misfit of 5 z by 1 z, where another FEM
#: engine's section differs from the library's), is no sign that the delay is modelled wrongly.
_MOVED_Z = 1.0
_ACTED_SHARE = 0.5
#: ... and only in a group of which it leaves more than this share of the gap (the root of the summed squared z after
#: over that before, over the group's measures it acts on): a candidate that took at least three quarters of its
#: signature's gap has the form the data show, and what stays of a large gap is the precision of the library's
#: reduced model (fields interpolated between solved variants), not another form.
_LEFT_SHARE = 0.25
#: The measure groups (:data:`usdeform.gap.measures.GROUPS`) where each library effect's own physics shows: its
#: signature. A candidate is named only where the held-out gap over these groups drops significantly with it, not
#: because it lowers the overall gap (a soft layer flexible enough to take up a vessel-area or correlation misfit
#: that is no layer). A delay of the images shows in the image motion against the robot (the timing measure: a
#: residual in proportion to the rate of loading); of the force, and a sensor's bias, drift or relaxation, in the
#: force; a depth scale, a tilt, a layer (strain concentrated in a depth band) and sliding in the displacement field,
#: its scale and the slip at the surface (a wrong speed of sound also in a world-fixed reflector's image motion);
#: out-of-plane motion in the speckle correlation; lumen pressure in the
#: lumen's area and the push on the probe at contact.
SIGNATURES: dict[str, tuple[str, ...]] = {
    "image_latency": ("timing", "image_motion", "displacement"),
    "force_sensor_error": ("force", "contact_force"),
    "viscoelasticity": ("force",),
    "sound_speed_mismatch": ("displacement", "displacement_scale", "image_motion", "reference_motion"),
    "probe_tilt": ("displacement", "displacement_scale"),
    "out_of_plane_motion": ("speckle_correlation", "speckle_roughness"),
    "layered_tissue": ("displacement", "displacement_scale"),
    "sliding_contact": ("contact_slip", "displacement"),
    "lumen_pressure": ("vessel", "contact_force", "displacement"),
    "force_latency": ("force", "contact_force"),
}


@dataclass
class MeasureResult:
    """One measure: value (recorded minus simulated) and uncertainty on the held-out split, before and after the best
    candidate; the same on the fitting split before (where the ideal simulation's linear parameters were fitted, so
    a difference there is a conservative one). Significance takes both splits together (:func:`gap_tests`)."""

    name: str
    recording: str
    group: str
    region: str
    force_range_n: tuple[float, float] | None
    phase: str
    value: float
    uncertainty: float
    significant: bool
    value_after: float | None = None
    value_fitting_split: float | None = None
    uncertainty_fitting_split: float | None = None


@dataclass
class Attribution:
    """Everything the diagnosis decided, with the held-out measures before and after the best candidate, and the
    library effects these recordings could not reveal even at the top of their realistic range
    (:mod:`usdeform.gap.detectability`); section_parameters: the ideal section's calibrated free parameters
    (Poisson's ratio, tissue depth, Yeoh ratio, lumen stiffness ratio, probe face width) of each recording."""

    verdict: str
    candidates: list[CandidateResult]
    measures: list[MeasureResult]
    gap_before: float
    critical_z: float
    named: list[str] = field(default_factory=list)
    predictions_before: list[Prediction] = field(default_factory=list)
    predictions_after: list[Prediction] = field(default_factory=list)
    undetectable: list[str] = field(default_factory=list)
    section_parameters: list[dict[str, float]] = field(default_factory=list)
    advice: list[ProtocolAdvice] = field(default_factory=list)
    # why the verdict is about candidates[0] (verdicts.LEAD_REASONS); candidates[1] is then the best-ranked
    # candidate it was preferred to, unless "best"
    lead_reason: str = "best"
    # no measure or group differed on its own: the gap was seen through a clean candidate's held-out test
    gap_shown_by_candidate: bool = False
    # library sections that could not be solved and were left out, each with the effect taken out with it (not
    # fitted): {"recording", "section", "error", "effect"}; and those solved with finer load steps or only to the
    # recorded indentation: {"recording", "section", "how"}
    unsolved_sections: list[dict[str, str]] = field(default_factory=list)
    resolved_sections: list[dict[str, str]] = field(default_factory=list)
    # candidates a known weight contradicts (verdicts.ruled_out_by_known_weight): ranked last, not decided on
    ruled_out: list[str] = field(default_factory=list)


def _signature_shrink(before: HeldOut, after: HeldOut, effect: str) -> tuple[float, bool]:
    """Shrink of the held-out gap over ``effect``'s signature groups (:data:`SIGNATURES`), and whether the gap there
    is significantly smaller at ``z(1 - alpha)`` (:func:`significantly_smaller`; one-sided, the candidate's own test
    has already corrected for the number of candidates)."""
    groups = SIGNATURES[effect]
    gap_before, boot_before = before.gap(groups)
    gap_after, boot_after = after.gap(groups)
    shrink = 1 - gap_after / gap_before if gap_before > 0 else 0.0
    present = significantly_smaller((gap_before, boot_before), (gap_after, boot_after), float(norm.isf(ALPHA)))
    return float(shrink), present


def _evaluate(
    folds: list[Fold],
    effect_ids: tuple[str, ...],
    thetas: list[np.ndarray],
    before: HeldOut,
    n_tests: int,
    member: tuple[float, np.ndarray] | None = None,
    known: dict[str, tuple[float, float]] | None = None,
) -> tuple[CandidateResult, list[Prediction], np.ndarray]:
    """Cross-fitted held-out evaluation (``thetas``: the fit of each fold) against the ideal simulation's held-out
    values ``before``; ``member``: held-out gap and its bootstrap rows of a pair's better member, which the pair
    must beat too. Significant only with every member's signature present (:func:`_signature_shrink`). The
    predictions returned are the first fold's. ``known``: sensor parameters a known weight identified, (value,
    standard error): one the recordings cannot identify is held at it rather than at its neutral value."""
    known = known or {}
    effects = [as_effects(effect_ids, theta) for theta in thetas]
    linear = [linear_parameters(fold, fold_effects) for fold, fold_effects in zip(folds, effects, strict=True)]
    unidentified = unidentified_linear([fold_errors for _, fold_errors in linear])
    free_errors = [fold_errors for _, fold_errors in linear]
    held = {name: known.get(name, (LINEAR_NEUTRAL[name], math.nan)) for name in unidentified}
    if unidentified:  # held at the known weight's value or their neutral values, the rest fitted again
        for fold_effects in effects:
            fold_effects["force_sensor_error"].update({name: value for name, (value, _) in held.items()})
        linear = [linear_parameters(fold, fold_effects) for fold, fold_effects in zip(folds, effects, strict=True)]
    fold_predictions = [fold.predictions(fold_effects) for fold, fold_effects in zip(folds, effects, strict=True)]
    after = HeldOut.of(folds, fold_predictions)
    gap_before, boot_before = before.gap()
    gap_after, boot_after = after.gap()
    n_features = float(np.mean([fold.n_features for fold in folds]))
    n_parameters = len(thetas[0]) + sum(len(LINEAR_PARAMETERS.get(e, ())) for e in effect_ids) - len(unidentified)
    references = [(gap_before, boot_before, n_parameters)]
    if member is not None:
        references.append((member[0], member[1], n_parameters - 1))
    z_required = float(norm.isf(ALPHA / n_tests))
    passes = True
    for reference_gap, reference_boot, extra in references:
        penalty = 2 * max(extra, 1) / n_features
        passes = passes and significantly_smaller(
            (reference_gap, reference_boot), (gap_after, boot_after), z_required, penalty
        )
    signature = {effect: _signature_shrink(before, after, effect) for effect in effect_ids}
    with np.errstate(invalid="ignore", divide="ignore"):
        shrink_boot = np.where(boot_before > 0, 1 - boot_after / boot_before, np.nan)
    interval = tuple(float(q) for q in np.nanquantile(shrink_boot, [0.025, 0.975]))
    # The mean of the folds' fits, and its standard error from theirs (two independent halves of the data).
    names = [name for _, name in parameter_names(effect_ids)]
    parameters = dict(zip(names, map(float, np.mean(thetas, axis=0)), strict=True))
    fold_errors = [parameter_uncertainty(fold, effect_ids, theta) for fold, theta in zip(folds, thetas, strict=True)]
    errors = dict(zip(names, map(float, np.sqrt(np.sum(np.square(fold_errors), axis=0)) / len(folds)), strict=True))
    drifts = [values["drift_n_per_s"] for values, _ in linear if "drift_n_per_s" in values]
    for name in linear[0][0]:
        parameters[name] = float(np.mean([values[name] for values, _ in linear]))
        errors[name] = float(np.sqrt(np.sum([np.square(sigmas[name]) for _, sigmas in linear]))) / len(folds)
    for name, (value, error) in held.items():  # the known weight's, or neutral with the error of the free fit
        parameters[name] = value
        errors[name] = (
            error
            if name in known
            else float(np.sqrt(np.sum([np.square(sigmas[name]) for sigmas in free_errors]))) / len(folds)
        )
    if "lumen_pressure" in effect_ids:
        modulus = float(np.mean([case.section.shear_modulus_kpa for case in folds[0].cases]))
        parameters["pressure_kpa"] = parameters["pressure_ratio"] * modulus
        errors["pressure_kpa"] = errors["pressure_ratio"] * modulus
    shrink = 1 - gap_after / gap_before if gap_before > 0 else 0.0
    result = CandidateResult(
        effect="+".join(effect_ids),
        parameters=parameters,
        uncertainty=errors,
        gap_before=gap_before,
        gap_after=gap_after,
        shrink=float(shrink),
        shrink_interval=interval,  # type: ignore[arg-type]
        significant=passes and all(present for _, present in signature.values()),
        score=gap_after + 2 * n_parameters / n_features,
        n_parameters=int(n_parameters),
        at_bound=parameters_at_edge(effect_ids, thetas, drifts),
        signature_shrink={effect: shrink for effect, (shrink, _) in signature.items()},
        signature_absent=[effect for effect, (_, present) in signature.items() if not present],
        unidentified={name: LINEAR_IDENTIFIED_BY[name] for name in unidentified if name not in known},
    )
    return result, fold_predictions[0], boot_after


def signature_left(
    effect: str, groups: np.ndarray, significant_after: np.ndarray, z_before: np.ndarray, z_after: np.ndarray
) -> list[str]:
    """The measure groups of ``effect``'s own signature (:data:`SIGNATURES`; a pair: its members') where a measure
    that it acts on (moved by at least ``_MOVED_Z``, away from zero or by ``_ACTED_SHARE`` of its gap) still differs
    significantly with it added (``significant_after``), unless
    it took all but ``_LEFT_SHARE`` of the gap of the group's measures it moved (``z_before`` and ``z_after``: the
    combined z-scores without and with it; ``groups``: each measure's group index)."""
    before, after = np.nan_to_num(z_before), np.nan_to_num(z_after)
    change = np.abs(after - before)
    moved = (change >= _MOVED_Z) & ((change >= _ACTED_SHARE * np.abs(before)) | (np.abs(after) > np.abs(before)))
    own_groups = {group for member in effect.split("+") for group in SIGNATURES[member]}
    left = set()
    for index in np.unique(groups[significant_after & moved]):
        acted_on = moved & (groups == index)
        if np.sum(after[acted_on] ** 2) > _LEFT_SHARE**2 * np.sum(before[acted_on] ** 2):
            left.add(GROUPS[index])
    return [group for group in GROUPS if group in own_groups & left]


def attribute(
    observations: list[Observation],
    sections: list[CalibratedSection],
    *,
    seed: int = 0,
    progress=None,
    pool: Executor | None = None,
    sensor: KnownSensor | None = None,
) -> Attribution:
    """Fit every library effect and the best pairs; rank them; decide the verdict (see the module docstring).

    ``progress``: optional tqdm-like object, ``update(1)`` after each fit (:data:`FITS` in all). ``pool``: worker
    processes (:func:`usdeform.gap.processes.worker_pool`) for the fits (None: fitted here; the result is the same).
    ``sensor``: what known weights show of the force sensor (:func:`usdeform.gap.sensor_calibration.known_sensor`):
    the candidates its finding contradicts are ranked last and left out of the verdict
    (:func:`ruled_out_by_known_weight`); a drift it identifies is held where the palpations cannot identify one.
    """
    left_out = set().union(*(section.left_out_effects for section in sections))
    library = [model for model in EFFECTS if model.effect not in left_out]
    if progress is not None:
        progress.update(len(left_out))  # the fits left out
    folds = [Fold(observations, sections, seed, fitting_split) for fitting_split in (0, 1)]
    problem = folds[0]  # the fold whose held-out measures the table reports
    before = [case.ideal for case in problem.cases]
    ideals = HeldOut.of(folds, [[case.ideal for case in fold.cases] for fold in folds])
    gap_before, _ = ideals.gap()
    z_before = ideals.first_fold_z
    n_tests = len(library) + _PAIRS_FROM_TOP

    known = {"drift_n_per_s": sensor.drift_n_per_s} if sensor and sensor.drift_n_per_s else {}
    singles: dict[str, tuple[CandidateResult, list[np.ndarray], list[Prediction], np.ndarray]] = {}
    fits = fit_all(folds, fit_folds, [((model.effect,), None) for model in library], pool, progress)
    for model, thetas in zip(library, fits, strict=True):
        result, predictions, boot = _evaluate(folds, (model.effect,), thetas, ideals, n_tests, known=known)
        singles[model.effect] = (result, thetas, predictions, boot)
    ranked = sorted(singles, key=lambda effect: singles[effect][0].score)
    z_crit = critical_z(problem.n_features)

    def gap_remains(effect: str) -> bool:
        """Whether a measure or a group still differs significantly with the single effect ``effect`` added."""
        predictions = singles[effect][2]
        return gap_tests((problem.held_values(predictions)[0], problem.fit_values(predictions)), problem.groups)[0]

    candidates = {effect: singles[effect] for effect in ranked}
    pairs = [
        tuple(sorted(pair, key=[m.effect for m in EFFECTS].index))
        for pair in itertools.combinations(ranked[:_PAIRS_FROM_TOP], 2)
    ]
    # a pair's folds start from its members' fits in that fold: each fold fitted on its own
    jobs = [
        (index, order, np.concatenate([singles[effect][1][index] for effect in order]))
        for order in pairs
        for index in range(len(folds))
    ]
    fold_fits = fit_all(folds, fit_in_fold, jobs, pool, progress)
    fits = [fold_fits[start : start + len(folds)] for start in range(0, len(fold_fits), len(folds))]
    for order, thetas in zip(pairs, fits, strict=True):
        member = min(order, key=lambda effect: singles[effect][0].gap_after)
        result, predictions, boot = _evaluate(
            folds,
            order,
            thetas,
            ideals,
            n_tests,
            member=(singles[member][0].gap_after, singles[member][3]),
            known=known,
        )
        result.tested_member = member
        member_gap = singles[member][0].gap_after
        increment = 1 - result.gap_after / member_gap if member_gap > 0 else 0.0
        result.significant = result.significant and increment >= MIN_SHRINK_EXPLAINED and gap_remains(member)
        candidates[result.effect] = (result, thetas, predictions, boot)
    z_fit_before = problem.fit_values(before)
    ideal_gap, significant = gap_tests((z_before, z_fit_before), problem.groups)
    residuals: dict[str, bool] = {}
    z_combined_before = combined_z((z_before, z_fit_before))

    def read_residual(result: CandidateResult, predictions: list[Prediction]) -> None:
        """Whether a measure or group still differs with ``result`` added (``residuals``), and its signature_left."""
        if result.effect in residuals:
            return
        z_by_split = (problem.held_values(predictions)[0], problem.fit_values(predictions))
        residuals[result.effect], significant_after = gap_tests(z_by_split, problem.groups)
        result.signature_left = signature_left(
            result.effect, problem.groups, significant_after, z_combined_before, combined_z(z_by_split)
        )

    def ranked_candidates() -> list[tuple[CandidateResult, list[np.ndarray], list[Prediction], np.ndarray]]:
        """Significant candidates first (a pair is significant only when it beats its better member), then by
        score; the first and those :func:`needs_signature_left` picks have their residual read."""
        ranking = sorted(
            candidates.values(), key=lambda item: (item[0].effect in ruled_out, not item[0].significant, item[0].score)
        )
        for index, (result, _, predictions, _) in enumerate(ranking):
            if index == 0 or needs_signature_left(result):
                read_residual(result, predictions)
        return ranking

    ruled_out: set[str] = set()
    ordered = ranked_candidates()
    # A gap is seen where a measure or a group differs beyond its uncertainty, or where a clean candidate (no
    # parameter at an edge of the library, its signature present and none of it left) takes most of the gap
    # significantly on the held-out half: a directed test of the effect's own form, which sees a gap spread over
    # many measures below what each one's test can tell. Without either there is no gap to attribute, however
    # consistently a candidate soaks up residuals below the model-discrepancy floors.
    gap_shown_by_candidate = not ideal_gap and any(is_clean(item[0]) for item in ordered)
    if not ideal_gap and not gap_shown_by_candidate:
        for result, *_ in candidates.values():
            result.significant = False
        ordered = ranked_candidates()
    ruled_out.update(
        ruled_out_by_known_weight(
            [item[0] for item in ordered], sensor.finding if sensor else None, sensor.drift_n_per_s if sensor else None
        )
    )
    if ruled_out:
        ordered = ranked_candidates()
    considered = [item for item in ordered if item[0].effect not in ruled_out]  # ordered's first, as ranked
    lead, lead_reason = lead_candidate([item[0] for item in considered], {item[0].effect: item[3] for item in ordered})
    ordered.insert(0, ordered.pop(lead))
    considered = ordered[: len(considered)]
    chosen = ordered[0]
    z_after, _ = problem.held_values(chosen[2])
    residual_significant = residuals[chosen[0].effect]
    verdict, named = decide(
        [item[0] for item in considered],
        {item[0].effect: item[3] for item in ordered},
        gap_seen=ideal_gap or gap_shown_by_candidate,
        residual_significant=residual_significant,
    )
    # an effect left out of the library is neither undetectable nor advised on: the diagnosis says it was left out
    repeats = {e: count for e, count in effect_repeats(problem.cases, problem.groups).items() if e not in left_out}
    measures = []
    offset = 0
    for case in problem.cases:
        layout = case.layout
        for index in range(layout.size):
            column = offset + index
            sigma = float(case.sigma_held[index])
            measures.append(
                MeasureResult(
                    name=layout.names[index],
                    recording=case.observation.name,
                    group=GROUPS[layout.groups[index]],
                    region=layout.regions[index],
                    force_range_n=layout.force_ranges[index],
                    phase=layout.phases[index],
                    value=float(z_before[column] * sigma),
                    uncertainty=sigma,
                    significant=bool(significant[column]),
                    value_after=float(z_after[column] * sigma),
                    value_fitting_split=float(z_fit_before[column] * case.sigma_fit[index]),
                    uncertainty_fitting_split=float(case.sigma_fit[index]),
                )
            )
        offset += layout.size
    return Attribution(
        verdict=verdict,
        candidates=[item[0] for item in ordered],
        measures=measures,
        gap_before=gap_before,
        critical_z=z_crit,
        named=named,
        predictions_before=before,
        predictions_after=chosen[2],
        undetectable=[effect for effect, count in repeats.items() if count != 1],
        section_parameters=[case.section_parameters for case in problem.cases],
        advice=protocol_advice(problem.cases, repeats, named if verdict == "ambiguous" else ()),
        lead_reason=lead_reason,
        gap_shown_by_candidate=gap_shown_by_candidate,
        unsolved_sections=[entry.as_dict() for section in sections for entry in section.unsolved],
        resolved_sections=[
            {"recording": observation.name, "section": name, "how": how}
            for observation, section in zip(observations, sections, strict=True)
            for name, how in section.resolved
        ],
        ruled_out=sorted(ruled_out),
    )
