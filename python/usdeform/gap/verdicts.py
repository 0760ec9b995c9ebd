"""The verdict of a diagnosis from its ranked candidates (:func:`decide`), and whether a candidate's fit lies at
an edge of the library (:func:`parameters_at_edge`); the attribution (:mod:`usdeform.gap.attribution`) ranks
the candidates."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import norm

from .linear_fits import MAX_DRIFT_N_PER_S
from .models import EDGE_FRACTION, EFFECT_BY_ID, LINEAR_PARAMETERS

__all__ = [
    "ALPHA",
    "KNOWN_DRIFT_TOLERANCE_N_PER_S",
    "KNOWN_DRIFT_Z",
    "LEAD_REASONS",
    "MIN_SHRINK_EXPLAINED",
    "MIN_SIGNATURE_SHRINK",
    "VERDICTS",
    "CandidateResult",
    "clean_member_of_edge_pair",
    "decide",
    "is_clean",
    "lead_candidate",
    "needs_signature_left",
    "parameter_names",
    "parameters_at_edge",
    "robust_error",
    "ruled_out_by_known_weight",
    "significantly_smaller",
]

ALPHA = 0.05
MIN_SHRINK_EXPLAINED = 0.5
#: The share of the held-out gap over its own signature groups that a candidate taking less than
#: ``MIN_SHRINK_EXPLAINED`` of the whole gap must take to be named (:func:`_explains_its_signature`). On this
#: project's benchmark (seed 2031, 30 cases) the effects it identified took 0.96-1.00 of their signature's gap
#: (latencies, force-sensor error, viscoelasticity, lumen pressure, probe tilt) or 0.65-0.91 (out-of-plane motion,
#: a layer, sliding); the best candidates of its nulls and out-of-library cases took at most 0.68.
MIN_SIGNATURE_SHRINK = 0.9
VERDICTS = (
    "no_significant_gap",
    "explained",
    "explained_in_part",
    "ambiguous",
    "at_edge_of_library",
    "unexplained",
)


@dataclass
class CandidateResult:
    """A library effect (or pair) fitted on the fitting split and evaluated on the held-out split."""

    effect: str
    parameters: dict[str, float]
    uncertainty: dict[str, float]
    gap_before: float
    gap_after: float
    shrink: float
    shrink_interval: tuple[float, float]
    significant: bool
    score: float
    n_parameters: int
    at_bound: list[str] = field(default_factory=list)  # parameters fitted at an edge of the library (in a fold)
    # per member effect: the held-out shrink of the gap over its signature groups (SIGNATURES)
    signature_shrink: dict[str, float] = field(default_factory=dict)
    signature_absent: list[str] = field(default_factory=list)  # members whose signature did not drop significantly
    # measure groups of its own signature that still differ significantly with it added, in measures it moves
    # (set for the candidates that take most of the gap)
    signature_left: list[str] = field(default_factory=list)
    # a pair: the member its significance was tested against (the one with the smaller held-out gap alone), ""
    tested_member: str = ""
    # parameters the recordings could not identify, held at their neutral value (reported in ``parameters``), each
    # with the recording (a record_next kind) that would identify it
    unidentified: dict[str, str] = field(default_factory=dict)


def parameter_names(effect_ids: tuple[str, ...]) -> list[tuple[str, str]]:
    """(effect, parameter name) of every nonlinear parameter of ``effect_ids``, in order."""
    return [(effect, name) for effect in effect_ids for name in EFFECT_BY_ID[effect].parameters]


def robust_error(rows: np.ndarray) -> float:
    """Interquartile range / 1.349 of the finite bootstrap rows (inf with fewer than three)."""
    ok = np.isfinite(rows)
    return float(np.subtract(*np.percentile(rows[ok], [75, 25]))) / 1.349 if ok.sum() > 2 else np.inf


def significantly_smaller(
    reference: tuple[float, np.ndarray], gap: tuple[float, np.ndarray], z: float, penalty: float = 0.0
) -> bool:
    """Whether ``gap`` (point, bootstrap rows) plus ``penalty`` is significantly smaller than ``reference`` (the same
    resamples): the log of their ratio exceeds ``z`` robust bootstrap errors of the rows' log ratios.

    A gap is a mean of squared z-scores, a scale statistic whose bootstrap spread grows with its size. On its own
    scale a gap concentrated in a few measures (a force offset, seen in the frames at first contact) spreads so
    wide that not even removing all of it passes (the z-score of a complete explanation is at most the gap over its
    spread: 2.5 where it spreads by 40 %, below the 2.7 that thirteen candidates ask); its logarithm compares
    shares, with a spread that does not grow with the gap."""
    reference_gap, reference_rows = reference
    gap_value, gap_rows = gap
    if reference_gap <= 0:
        return False
    if gap_value + penalty <= 0:
        return True
    with np.errstate(divide="ignore", invalid="ignore"):
        log_ratio_rows = np.log(reference_rows) - np.log(gap_rows + penalty)
    return bool(np.log(reference_gap / (gap_value + penalty)) > z * robust_error(log_ratio_rows))


def parameters_at_edge(
    effect_ids: tuple[str, ...], thetas: Sequence[np.ndarray], drifts_n_per_s: Sequence[float] = ()
) -> list[str]:
    """Names of the parameters that some fold fitted at an edge of the library (:class:`EffectModel` ``edges``,
    within ``EDGE_FRACTION`` of the range or beyond), and ``drift_n_per_s`` when a fold's sensor drift sits at
    its bound (+-``MAX_DRIFT_N_PER_S``). A fit there is the library's best, not the data's: the effect may be
    larger than modelled or in another form."""
    names = []
    for index, (effect, name) in enumerate(parameter_names(effect_ids)):
        model = EFFECT_BY_ID[effect]
        low, high = model.edge_of(name)
        bound_low, bound_high = model.bounds[model.parameters.index(name)]
        values = np.array([theta[index] for theta in thetas], dtype=float)
        if name in model.log_scale:
            values, low, high = np.log(values), np.log(low), np.log(high)
            bound_low, bound_high = np.log(bound_low), np.log(bound_high)
        tolerance = EDGE_FRACTION * (bound_high - bound_low)
        if np.any(values <= low + tolerance) or np.any(values >= high - tolerance):
            names.append(name)
    if any(abs(drift) >= MAX_DRIFT_N_PER_S * (1 - 2 * EDGE_FRACTION) for drift in drifts_n_per_s):
        names.append("drift_n_per_s")
    return names


def is_clean(candidate: CandidateResult) -> bool:
    """A significant candidate that takes most of the gap with no parameter at an edge of the library and no
    measure group of its own signature left significant: a clean explanation."""
    return (
        candidate.significant
        and candidate.shrink >= MIN_SHRINK_EXPLAINED
        and not candidate.at_bound
        and not candidate.signature_left
    )


def _signature_taken(candidate: CandidateResult) -> bool:
    """Whether every member of ``candidate`` shrinks the held-out gap over its signature groups by at least
    ``MIN_SIGNATURE_SHRINK``."""
    return bool(candidate.signature_shrink) and min(candidate.signature_shrink.values()) >= MIN_SIGNATURE_SHRINK


def needs_signature_left(candidate: CandidateResult) -> bool:
    """Whether :func:`decide` and :func:`lead_candidate` read ``candidate.signature_left`` (the attribution sets it
    for these and the best): a significant candidate that takes most of the gap or nearly all of its signature's."""
    return candidate.significant and (candidate.shrink >= MIN_SHRINK_EXPLAINED or _signature_taken(candidate))


def _explains_its_signature(candidate: CandidateResult) -> bool:
    """A significant candidate whose own signature is present (none absent) and nearly all taken: every member
    shrinks the held-out gap over its signature groups by at least ``MIN_SIGNATURE_SHRINK``, with no parameter at
    an edge of the library and no signature group left. It is at work even when it takes less than
    ``MIN_SHRINK_EXPLAINED`` of the whole gap: the rest lies in measures its physics does not move (a force
    sensor's offset, fitted to 3 %, under a displacement gap at depth that no library effect explains)."""
    return (
        candidate.significant
        and not candidate.at_bound
        and not candidate.signature_left
        and not candidate.signature_absent
        and _signature_taken(candidate)
    )


def _as_good(candidate: CandidateResult, best: CandidateResult, boots: dict[str, np.ndarray]) -> bool:
    """Whether ``best``'s held-out gap is not significantly smaller than ``candidate``'s at ``z(1 - alpha)``
    (:func:`significantly_smaller`; ``boots``: each candidate's bootstrap rows)."""
    return not significantly_smaller(
        (candidate.gap_after, boots[candidate.effect]), (best.gap_after, boots[best.effect]), float(norm.isf(ALPHA))
    )


def _decisively_better(best: CandidateResult, rival: CandidateResult) -> bool:
    """Whether ``best`` takes at least ``MIN_SHRINK_EXPLAINED`` of the held-out gap that ``rival`` leaves (the standard
    of "explained" applied to what one takes beyond the other, as a pair's second effect must): two clean candidates
    whose residuals differ by less are told apart only by what the bootstrap does not see, the ways the simulator and
    the robot differ beyond the library (a lumen pressing on the probe from first contact leaves 9 % less of a force
    offset's gap than the offset itself, on a generator with another material law)."""
    return best.gap_after <= (1 - MIN_SHRINK_EXPLAINED) * rival.gap_after


def clean_member_of_edge_pair(candidate: CandidateResult, pair: CandidateResult) -> bool:
    """Whether ``candidate`` is the clean (:func:`is_clean`) member of ``pair`` that the pair's significance was
    tested against (``tested_member``: the pair took significantly more of the gap than it, and it left a
    significant residual) and the pair is no clean explanation only because a parameter of its other member was
    fitted at an edge of the library (none of ``candidate``'s own parameters at an edge, no signature group of the
    pair left): the member accounts for most of the gap on its own, and what the pair takes beyond it the library
    gives only at its edge."""
    if candidate.effect != pair.tested_member or pair.signature_left or not pair.at_bound:
        return False
    own = {*EFFECT_BY_ID[candidate.effect].parameters, *LINEAR_PARAMETERS.get(candidate.effect, ())}
    return is_clean(candidate) and not own & set(pair.at_bound)


SENSOR_EFFECT = "force_sensor_error"


#: A candidate's sensor drift contradicts the known weights' beyond this many combined standard errors...
KNOWN_DRIFT_Z = 3.0
#: ... and this difference, N/s (a drift that small changes a palpation's force by under 0.1 N in 10 s).
KNOWN_DRIFT_TOLERANCE_N_PER_S = 0.01


def ruled_out_by_known_weight(
    candidates: Sequence[CandidateResult],
    sensor: str | None,
    known_drift_n_per_s: tuple[float, float] | None = None,
) -> set[str]:
    """The candidates what known weights show of the force sensor contradicts (``sensor``: "error", "clean" or None,
    :func:`usdeform.gap.sensor_calibration.sensor_finding`). A sensor shown free of error rules out every candidate
    with a sensor error. A sensor shown in error rules out every candidate without one, when a candidate with one is
    significant: the palpations then show the error the known weight measured, and another effect may join it only
    as a pair. A weight measured apart from the tissue says nothing of any other effect. ``known_drift_n_per_s``:
    the drift the known weights identify (value, standard error; N/s); a candidate whose fitted drift differs from
    it by more than :data:`KNOWN_DRIFT_Z` combined standard errors and :data:`KNOWN_DRIFT_TOLERANCE_N_PER_S` is ruled
    out too, whatever the finding (a weight too short to show the sensor clean still shows a drift it does not have).
    """
    with_sensor = {c.effect for c in candidates if SENSOR_EFFECT in c.effect.split("+")}
    if sensor == "clean":
        return with_sensor
    if sensor == "error" and any(c.significant and c.effect in with_sensor for c in candidates):
        return {c.effect for c in candidates} - with_sensor
    contradicted = set()
    if known_drift_n_per_s is not None:
        known, known_error = known_drift_n_per_s
        for c in candidates:
            fitted, error = c.parameters.get("drift_n_per_s"), c.uncertainty.get("drift_n_per_s")
            if c.effect not in with_sensor or fitted is None or error is None or "drift_n_per_s" in c.unidentified:
                continue
            difference = abs(fitted - known)
            if difference > max(KNOWN_DRIFT_TOLERANCE_N_PER_S, KNOWN_DRIFT_Z * float(np.hypot(error, known_error))):
                contradicted.add(c.effect)
    return contradicted


LEAD_REASONS = ("best", "as_good", "clean_member")


def lead_candidate(ordered: Sequence[CandidateResult], boots: dict[str, np.ndarray]) -> tuple[int, str]:
    """Index in ``ordered`` (best first) of the candidate the verdict is about, and why (:data:`LEAD_REASONS`).

    The best, unless it takes most of the gap but is no clean explanation (a parameter at an edge of the library, or
    its own signature left significant) while a clean candidate (:func:`is_clean`) has a held-out gap not
    significantly larger (:func:`_as_good`). Then the first such: two candidates the held-out data rank alike are
    told apart by whether each accounts for its own physics, not by the last digits of the gap (a delay of the pose
    stream fits about as well as an image delay with relaxation, but leaves no force loop unexplained where
    relaxation would show one): ``"as_good"``. Failing that, a pair that is no clean explanation only through its
    other member's edge (:func:`clean_member_of_edge_pair`) gives way to the clean member it was tested against:
    ``"clean_member"``; the gap is then that member's in part (the pair's test found a significant residual beyond
    it, so :func:`decide` says ``explained_in_part`` unless a clean rival makes it ``ambiguous``), not the library's
    edge (an image delay that leaves speckle decorrelation the library's out-of-plane motion takes only at its
    bound). Otherwise the best: ``"best"``.
    ``signature_left`` must be set for every candidate :func:`needs_signature_left` picks.
    """
    if not ordered:
        return 0, "best"
    best = ordered[0]
    if not best.significant or best.shrink < MIN_SHRINK_EXPLAINED or is_clean(best):
        return 0, "best"
    for index, candidate in enumerate(ordered[1:], start=1):
        if is_clean(candidate) and _as_good(candidate, best, boots):
            return index, "as_good"
    for index, candidate in enumerate(ordered[1:], start=1):
        if clean_member_of_edge_pair(candidate, best):
            return index, "clean_member"
    return 0, "best"


def decide(
    ordered: list[CandidateResult],
    boots: dict[str, np.ndarray],
    *,
    gap_seen: bool,
    residual_significant: bool,
) -> tuple[str, list[str]]:
    """The verdict and the effects it names, from the candidates best first (significant first, then by score,
    the :func:`lead_candidate` moved first).

    ``boots``: each candidate's held-out gap bootstrap rows (the folds' rows averaged); ``gap_seen``: the ideal
    simulation leaves a significant measure or group, or a clean candidate shows the gap in its held-out test
    (:func:`usdeform.gap.attribution.attribute`); ``residual_significant``: the best candidate leaves a significant
    measure or group.
    With a significant best candidate that shrinks the gap by at least ``MIN_SHRINK_EXPLAINED``, in this order:

    * ``at_edge_of_library``: a parameter of it was fitted at an edge of the library (``at_bound``), or a measure
      group of its own signature still differs significantly with it added (``signature_left``): the data ask
      for more than the library's form of the effect gives (an effect that is at work leaves no residual where
      its own physics shows; one that only resembles what is at work does), so the fit is no clean explanation;
    * ``ambiguous``: the next significant candidate that is not nested in it (a pair and its member are told apart
      by the pair's own test), not fitted at an edge of the library and with no signature group left (no clean
      rival: a force stream 0.2 s early imitates relaxation's loop) and shrinks as much has a held-out gap that is
      not significantly larger at ``z(1 - alpha)`` (:func:`significantly_smaller`), or the best does not take at
      least half of the gap it leaves (:func:`_decisively_better`). The parameter penalty, which ranks them, is
      left out here: one parameter fewer is no evidence from the data. Both are named;
    * ``explained_in_part``: the residual with it added still shows a significant measure or group;
    * ``explained`` otherwise.

    A significant best that shrinks less is ``explained_in_part`` when it takes nearly all of its own signature's
    gap (:func:`_explains_its_signature`; ``ambiguous`` with a rival that does too and is as good), else
    ``unexplained``, as is a gap no candidate takes; else ``no_significant_gap``.
    """
    best = ordered[0] if ordered and ordered[0].significant else None
    if best is None:
        return ("unexplained" if gap_seen else "no_significant_gap"), []
    by_signature = best.shrink < MIN_SHRINK_EXPLAINED
    if by_signature and not _explains_its_signature(best):
        return "unexplained", []
    if not by_signature and not is_clean(best):
        return "at_edge_of_library", [best.effect]
    members = set(best.effect.split("+"))
    rivals = [
        candidate
        for candidate in ordered[1:]
        if (_explains_its_signature(candidate) if by_signature else is_clean(candidate))
        and not (set(candidate.effect.split("+")) <= members or members <= set(candidate.effect.split("+")))
    ]
    if rivals and (_as_good(rivals[0], best, boots) or not _decisively_better(best, rivals[0])):
        return "ambiguous", [best.effect, rivals[0].effect]
    if residual_significant or by_signature:
        return "explained_in_part", [best.effect]
    return "explained", [best.effect]
