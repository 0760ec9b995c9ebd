"""Honest verdicts from constructed candidate results (no FEM): fits at the library's edge, ambiguity, a residual
that stays; the benchmark's scoring of them and its confusion matrix."""

import json
from pathlib import Path

import numpy as np
import pytest

from usdeform.gap.attribution import (
    SIGNATURES,
    CandidateResult,
    _signature_shrink,
    decide,
    parameters_at_edge,
    signature_left,
)
from usdeform.gap.benchmark_scoring import BenchmarkCase, markdown_summary, score_case, summarise
from usdeform.gap.diagnosis import Diagnosis, _summary
from usdeform.gap.folds import HeldOut
from usdeform.gap.measures import GROUPS
from usdeform.gap.models import EFFECTS
from usdeform.gap.report import write_report
from usdeform.gap.verdicts import lead_candidate

ROWS = np.random.default_rng(0).standard_normal(200)


def candidate(effect, gap_after, *, significant=True, at_bound=(), parameters=None, n_parameters=1):
    return CandidateResult(
        effect=effect,
        parameters=parameters or {},
        uncertainty={},
        gap_before=10.0,
        gap_after=gap_after,
        shrink=1 - gap_after / 10.0,
        shrink_interval=(0.0, 1.0),
        significant=significant,
        score=gap_after + 0.1 * n_parameters,
        n_parameters=n_parameters,
        at_bound=list(at_bound),
    )


def boots(*items, spread=0.5, shared=1.0):
    """Bootstrap rows: a shared part (the resample) plus each candidate's own noise of ``spread``."""
    rng = np.random.default_rng(1)
    return {c.effect: c.gap_after + shared * ROWS + spread * rng.standard_normal(200) for c in items}


def test_a_clean_fit_is_explained():
    best, other = candidate("image_latency", 1.0), candidate("viscoelasticity", 6.0)
    assert decide([best, other], boots(best, other), gap_seen=True, residual_significant=False) == (
        "explained",
        ["image_latency"],
    )


def test_a_fit_at_the_edge_of_the_library_is_never_a_clean_explanation():
    best = candidate("probe_tilt", 1.0, at_bound=["tilt_deg"])
    assert decide([best], boots(best), gap_seen=True, residual_significant=False) == (
        "at_edge_of_library",
        ["probe_tilt"],
    )


def test_two_candidates_whose_gaps_do_not_differ_significantly_are_ambiguous():
    best, rival = candidate("layered_tissue", 1.0, n_parameters=2), candidate("probe_tilt", 1.3)
    verdict, named = decide([best, rival], boots(best, rival), gap_seen=True, residual_significant=False)
    assert verdict == "ambiguous" and named == ["layered_tissue", "probe_tilt"]
    # a rival fitted at an edge of the library is no clean alternative
    edge = candidate("force_latency", 1.3, at_bound=["delay_s"])
    assert decide([best, edge], boots(best, edge), gap_seen=True, residual_significant=False)[0] == "explained"
    # tight bootstrap rows (the resample moves both alike) tell them apart when the best takes at least half of
    # what the rival leaves; a residual 23 % smaller is told apart by nothing the bootstrap sees
    tight = boots(best, rival, spread=0.01)
    assert decide([best, rival], tight, gap_seen=True, residual_significant=False)[0] == "ambiguous"
    distant = candidate("probe_tilt", 2.0)
    tight = boots(best, distant, spread=0.01)
    assert decide([best, distant], tight, gap_seen=True, residual_significant=False)[0] == "explained"
    assert decide([best, distant], boots(best, distant), gap_seen=True, residual_significant=False)[0] == "ambiguous"


def test_a_pair_and_its_member_are_not_ambiguous_nor_is_an_insignificant_rival():
    best, member = candidate("image_latency+viscoelasticity", 1.0, n_parameters=3), candidate("image_latency", 1.1)
    weak = candidate("probe_tilt", 1.05, significant=False)
    rows = boots(best, member, weak)
    assert decide([best, member, weak], rows, gap_seen=True, residual_significant=False)[0] == "explained"


def test_a_significant_residual_is_explained_in_part_and_a_small_shrink_unexplained():
    best = candidate("viscoelasticity", 2.0)
    assert decide([best], boots(best), gap_seen=True, residual_significant=True) == (
        "explained_in_part",
        ["viscoelasticity"],
    )
    small = candidate("viscoelasticity", 7.0)
    assert decide([small], boots(small), gap_seen=True, residual_significant=True) == ("unexplained", [])
    none = candidate("viscoelasticity", 9.0, significant=False)
    assert decide([none], boots(none), gap_seen=True, residual_significant=True) == ("unexplained", [])
    assert decide([none], boots(none), gap_seen=False, residual_significant=False) == ("no_significant_gap", [])


def test_an_effect_that_takes_its_own_signature_but_less_than_half_of_the_gap_is_explained_in_part():
    """A force-sensor offset fitted well takes all of the contact-force gap, but the whole gap is mostly displacement
    at depth that no effect moves: it is named, in part; not when its signature is taken less than
    MIN_SIGNATURE_SHRINK, absent, left, at an edge, or the candidate is not significant; as good a rival that takes
    its own signature too makes it ambiguous."""
    from usdeform.gap.verdicts import MIN_SIGNATURE_SHRINK, needs_signature_left

    def offset(gap_after=5.4, share=0.99, **changes):
        result = candidate("force_sensor_error", gap_after, parameters={"offset_n": -0.756})
        result.signature_shrink = {"force_sensor_error": share}
        for name, value in changes.items():
            setattr(result, name, value)
        return result

    weak = candidate("sliding_contact", 9.4)
    best = offset()
    assert needs_signature_left(best) and not needs_signature_left(weak)
    assert decide([best, weak], boots(best, weak), gap_seen=True, residual_significant=True) == (
        "explained_in_part",
        ["force_sensor_error"],
    )
    summary = _summary("explained_in_part", [], [best, weak], ["force_sensor_error"], "best")
    assert "explained only in part by force_sensor_error (offset_n = -0.756" in summary
    assert "99 % of it in force, contact_force" in summary and "but 46 % of the whole gap held out" in summary
    assert "no effect of the library explains that" in summary
    refused = [
        offset(share=MIN_SIGNATURE_SHRINK - 0.01),
        offset(signature_absent=["force_sensor_error"]),
        offset(signature_left=["contact_force"]),
        offset(at_bound=["drift_n_per_s"]),
        offset(significant=False),
    ]
    for result in refused:
        assert decide([result, weak], boots(result, weak), gap_seen=True, residual_significant=True) == (
            "unexplained",
            [],
        )
    lag = candidate("force_latency", 5.5)
    lag.signature_shrink = {"force_latency": 0.97}
    assert decide([best, lag], boots(best, lag), gap_seen=True, residual_significant=True) == (
        "ambiguous",
        ["force_sensor_error", "force_latency"],
    )
    lag.signature_shrink = {"force_latency": 0.6}
    assert decide([best, lag], boots(best, lag), gap_seen=True, residual_significant=True)[0] == "explained_in_part"


def test_a_residual_left_in_the_effects_own_signature_is_no_clean_explanation():
    """A soft layer that takes up part of a curved probe face's field leaves the displacement (its own signature)
    significant: at the edge of the library, not a layer explained in part; a force delay that leaves a residual in
    the lumen's area only (not its signature) is explained in part."""
    layer = candidate("layered_tissue", 3.0)
    layer.signature_left = ["displacement"]
    assert decide([layer], boots(layer), gap_seen=True, residual_significant=True) == (
        "at_edge_of_library",
        ["layered_tissue"],
    )
    delay = candidate("force_latency", 2.0)
    assert decide([delay], boots(delay), gap_seen=True, residual_significant=True) == (
        "explained_in_part",
        ["force_latency"],
    )


def test_a_residual_counts_against_an_effect_only_in_its_own_signature_and_where_it_acts():
    """Lateral displacement at depth that a delay leaves as the ideal simulator had it, or only nudges (a static
    misfit of the section, by less than half), is no sign of a wrong delay; a displacement residual the layer acted on
    (moved by half of it or more) and did not close is one, as is one it moved away from zero; a residual outside
    the signature never is; nor is one the candidate shrank to under a quarter of its gap."""
    groups = np.array([GROUPS.index("displacement"), GROUPS.index("displacement"), GROUPS.index("vessel")])
    significant = np.array([True, False, True])
    before = np.array([-4.9, 0.5, 5.0])
    assert signature_left("image_latency", groups, significant, before, np.array([-4.1, 0.4, 1.0])) == []
    assert signature_left("image_latency", groups, significant, before, np.array([-3.6, 0.4, 1.0])) == []
    assert signature_left("layered_tissue", groups, significant, before, np.array([-2.2, 0.4, 5.0])) == ["displacement"]
    assert signature_left("layered_tissue", groups, significant, before, np.array([-6.4, 0.4, 5.0])) == ["displacement"]
    assert signature_left("force_latency", groups, significant, before, np.array([-1.0, 0.4, 1.0])) == []
    # a large gap the candidate took nearly all of: what stays is the reduced model's precision, not another form
    large = np.array([-60.0, 0.5, 5.0])
    assert signature_left("probe_tilt", groups, significant, large, np.array([-5.0, 0.4, 5.0])) == []
    assert signature_left("probe_tilt", groups, significant, large, np.array([-20.0, 0.4, 5.0])) == ["displacement"]


def test_a_clean_candidate_as_good_held_out_leads_over_one_that_leaves_its_own_signature():
    """A delayed pose stream: image delay with relaxation ranks first but leaves force and displacement (its own
    signature) significant; image and force delayed alike fit as well held out and leave nothing of theirs: the
    verdict is about the clean one, and the summary says the one passed over is not significantly better held
    out. Significantly worse, or itself at an edge, it does not lead."""
    unclean = candidate("image_latency+viscoelasticity", 1.0, n_parameters=3)
    unclean.signature_left = ["force", "displacement"]
    unclean.score = 1.0  # ranked first
    clean = candidate("image_latency+force_latency", 1.05)
    rows = boots(unclean, clean)
    assert lead_candidate([unclean, clean], rows) == (1, "as_good")
    assert decide([clean, unclean], rows, gap_seen=True, residual_significant=False) == (
        "explained",
        ["image_latency+force_latency"],
    )
    summary = _summary("explained", [], [clean, unclean], ["image_latency+force_latency"], "as_good")
    assert "Ranked above it but not named, as no clean explanation: image_latency+viscoelasticity" in summary
    assert summary.endswith("Its held-out gap is not significantly smaller.")
    assert lead_candidate([unclean, clean], boots(unclean, clean, spread=0.01)) == (0, "best")
    edge = candidate("image_latency+force_latency", 1.05, at_bound=["delay_s"])
    assert lead_candidate([unclean, edge], boots(unclean, edge)) == (0, "best")
    assert lead_candidate([clean, unclean], boots(clean, unclean)) == (0, "best")  # a clean best leads
    small = candidate("image_latency", 6.0)  # shrinks less than half: never a clean explanation
    assert lead_candidate([unclean, small], boots(unclean, small, shared=30.0)) == (0, "best")


def _pair(effect, gap_after, tested_member, at_bound, n_parameters=4):
    pair = candidate(effect, gap_after, at_bound=at_bound, n_parameters=n_parameters)
    pair.tested_member = tested_member
    return pair


def test_a_pair_at_the_edge_only_through_its_other_member_gives_way_to_its_clean_member():
    """An image delay that leaves speckle decorrelation: image delay with out-of-plane motion takes significantly more
    of the gap than the delay alone (the member it was tested against), but only with the shift at its bound. The
    verdict is about the delay, explained in part, not the library's edge; not when the delay itself is at an
    edge, shrinks less than half, is not the member the pair was tested against, or the pair leaves a signature
    group, nor for a member whose own parameter is at the edge (the other member's name for it does not count)."""
    pair = _pair("image_latency+out_of_plane_motion", 0.8, "image_latency", ["shift_mm_per_mm"])
    delay = candidate("image_latency", 1.9)
    shift = candidate("out_of_plane_motion", 9.7, at_bound=["shift_mm_per_mm"], n_parameters=3)
    rows = boots(pair, delay, shift, spread=0.01)
    assert lead_candidate([pair, delay, shift], rows) == (1, "clean_member")
    assert decide([delay, pair, shift], rows, gap_seen=True, residual_significant=True) == (
        "explained_in_part",
        ["image_latency"],
    )
    summary = _summary("explained_in_part", [], [delay, pair, shift], ["image_latency"], "clean_member")
    assert "explained only in part by image_latency" in summary
    assert "image_latency+out_of_plane_motion takes more of the gap (shrink 92 %), but it was fitted at the edge" in (
        summary
    )
    assert "not significantly smaller" not in summary
    assert lead_candidate([pair, candidate("image_latency", 1.9, at_bound=["delay_s"])], rows) == (0, "best")
    assert lead_candidate([pair, candidate("image_latency", 6.0)], rows) == (0, "best")
    # the weaker member alone (the pair was tested against the other): no residual beyond it was tested
    tilt_pair = _pair("probe_tilt+layered_tissue", 0.8, "layered_tissue", ["modulus_ratio"])
    tilt = candidate("probe_tilt", 2.5, n_parameters=2)
    layer = candidate("layered_tissue", 2.0, at_bound=["modulus_ratio"], n_parameters=2)
    assert lead_candidate([tilt_pair, layer, tilt], boots(tilt_pair, layer, tilt, spread=0.01)) == (0, "best")
    signature = _pair("image_latency+out_of_plane_motion", 0.8, "image_latency", ["shift_mm_per_mm"])
    signature.signature_left = ["correlation"]
    assert lead_candidate([signature, delay], rows) == (0, "best")
    own_edge = _pair("image_latency+force_latency", 0.8, "image_latency", ["delay_s"], n_parameters=2)
    assert lead_candidate([own_edge, delay], boots(own_edge, delay, spread=0.01)) == (0, "best")
    bias = candidate("force_sensor_error", 1.9)
    drifting = _pair("force_sensor_error+probe_tilt", 0.8, "force_sensor_error", ["drift_n_per_s"], n_parameters=2)
    assert lead_candidate([drifting, bias], boots(drifting, bias, spread=0.01)) == (0, "best")


@pytest.mark.parametrize(
    ("effects", "thetas", "drifts", "expected"),
    [
        (("probe_tilt",), [[15.0, 0.5], [14.0, 0.5]], [], ["tilt_deg"]),  # one fold at the 15 degree bound
        (("probe_tilt",), [[9.0, 0.0], [10.0, 1.0]], [], []),  # along the normal or the axis: forms, not edges
        (("viscoelasticity",), [[0.3, 0.052], [0.3, 0.06]], [], ["tau_s"]),  # tau measured in log units
        (("viscoelasticity",), [[0.01, 2.7], [0.02, 2.0]], [], []),  # g near 0 is relaxation vanishing, no edge
        (("layered_tissue",), [[7.8, 0.19], [7.8, 0.2]], [], ["modulus_ratio"]),  # softer than any solved layer
        (("sliding_contact",), [[1.0], [1.0]], [], []),  # frictionless is a physical limit
        (("force_sensor_error",), [[], []], [0.15, 0.03], ["drift_n_per_s"]),  # at the bound
        (("force_sensor_error",), [[], []], [0.1, -0.08], []),  # the top of the thermal range is inside
        (("force_sensor_error",), [[], []], [-0.02, 0.01], []),
        (("image_latency", "probe_tilt"), [[0.1, -15.0, 0.2], [0.1, -14.9, 0.2]], [], ["tilt_deg"]),
    ],
)
def test_parameters_at_the_edge_of_the_library(effects, thetas, drifts, expected):
    assert parameters_at_edge(effects, [np.array(theta) for theta in thetas], drifts) == expected


def _diagnosis(verdict, named, effects):
    return Diagnosis(
        verdict=verdict,
        summary="constructed",
        effects=effects,
        measures=[],
        calibration=[],
        gap_before=10.0,
        critical_z=3.0,
        named=named,
    )


def test_the_edge_and_the_names_reach_diagnosis_json_and_report_html(tmp_path):
    tilt = candidate("probe_tilt", 1.0, at_bound=["tilt_deg"], parameters={"tilt_deg": 15.0})
    write_report(_diagnosis("at_edge_of_library", ["probe_tilt"], [tilt]), tmp_path)
    data = json.loads((tmp_path / "diagnosis.json").read_text())
    assert data["verdict"] == "at_edge_of_library" and data["named"] == ["probe_tilt"]
    assert data["effects"][0]["at_bound"] == ["tilt_deg"]
    page = (tmp_path / "report.html").read_text()
    assert "at edge of library (probe_tilt)" in page and "tilt_deg = 15 +/- nan (at the edge of the library)" in page


def _case(index, kind, hidden):
    return BenchmarkCase(index, kind, hidden, {}, {name: float("nan") for name in hidden}, Path("x"), 0.0, 10.0)


def _row(case, verdict, named, top):
    effects = [{"effect": top, "parameters": {}, "shrink": 0.9}] if top else []
    row = score_case(case, {"verdict": verdict, "named": named, "effects": effects, "undetectable": []}, 10.0)
    return row | {"total_s": 1.0, "diagnosis_s": 1.0}


def test_the_benchmark_counts_an_ambiguous_verdict_listing_the_hidden_effect_and_publishes_a_confusion_matrix():
    rows = [
        _row(_case(0, "single", ["viscoelasticity"]), "ambiguous", ["force_sensor_error", "viscoelasticity"], "x"),
        _row(_case(1, "single", ["probe_tilt"]), "at_edge_of_library", ["probe_tilt"], "probe_tilt"),
        _row(_case(2, "single", ["image_latency"]), "explained_in_part", ["image_latency"], "image_latency"),
        _row(_case(3, "null", []), "explained_in_part", ["layered_tissue"], "layered_tissue"),
        _row(_case(4, "out_of_library", ["holder_compliance"]), "at_edge_of_library", ["probe_tilt"], "probe_tilt"),
        _row(_case(5, "single", ["probe_tilt"]), "at_edge_of_library", ["probe_tilt"], "probe_tilt"),
    ]
    assert [row.get("identified") for row in rows[:3]] == [True, False, True]
    assert rows[3]["false_attribution"] and rows[4]["flagged_unexplained"]
    summary = summarise(rows)
    assert summary["top1_identification"] == (2 / 4, 4)
    assert summary["single_named_at_edge"] == (2 / 4, 4)
    assert {"hidden": "probe_tilt", "named": "probe_tilt", "verdict": "at_edge_of_library", "cases": 2} in summary[
        "confusion"
    ]
    markdown = markdown_summary(summary, "test")
    assert "| viscoelasticity | force_sensor_error or viscoelasticity | ambiguous | 1 |" in markdown
    assert "| none | layered_tissue | explained_in_part | 1 |" in markdown


def test_repeats_needed_grow_as_the_expected_z_scores_shrink():
    from usdeform.gap.detectability import MAX_REPEATS, repeats_needed

    groups = np.zeros(40, dtype=int)
    strong = np.full(40, 6.0)
    assert repeats_needed(strong, strong, groups) == 1
    assert repeats_needed(np.zeros(40), np.zeros(40), groups) is None
    counts = [repeats_needed(np.full(40, z), np.full(40, z), groups) for z in (0.6, 0.4, 0.3)]
    assert all(count is not None for count in counts)
    assert 1 < counts[0] < counts[1] < counts[2] <= MAX_REPEATS


def _fake_case(hold_s, rate_mm_s=2.0, depth_mm=6.0):
    """A stand-in case with only the observation's time and indentation (load, hold, unload)."""
    from types import SimpleNamespace

    ramp_s = depth_mm / rate_mm_s
    time = np.linspace(0, 2 * ramp_s + hold_s, 400)
    lam = np.clip(np.minimum(time, 2 * ramp_s + hold_s - time) * rate_mm_s, 0, depth_mm)
    return SimpleNamespace(observation=SimpleNamespace(time_s=time, probe_displacement_mm=lam))


def test_what_to_record_next_takes_its_numbers_from_the_recordings():
    from usdeform.gap.detectability import GAIN_REASON, protocol_advice, protocol_text

    case = _fake_case(hold_s=1.5)  # within 3 % of the top indentation: 1.7 s
    assert "a hold of 5 s at the top force (these: 1.7 s)" in protocol_text("viscoelasticity", [case])
    assert "(6.0 mm/s; these: 2.0 mm/s)" in protocol_text("image_latency", [case])
    assert "to about 9 mm (these: 6.0 mm)" in protocol_text("layered_tissue", [case])
    repeats = {"image_latency": 1, "viscoelasticity": 4, "sound_speed_mismatch": None, "probe_tilt": 1}
    advice = protocol_advice([case], repeats, ambiguous=("force_sensor_error", "image_latency+viscoelasticity"))
    assert [(a.effect, a.reason, a.repeats) for a in advice] == [
        ("viscoelasticity", "undetectable", 4),
        ("sound_speed_mismatch", "undetectable", None),
        ("force_sensor_error", "ambiguous with image_latency+viscoelasticity", None),
        ("image_latency", "ambiguous with force_sensor_error", None),
        ("viscoelasticity", "ambiguous with force_sensor_error", None),
        ("force_sensor_error", GAIN_REASON, None),  # always: no palpation tells a gain error from stiffer tissue
    ]
    assert "known weight" in advice[-1].protocol


def test_what_to_record_next_reaches_diagnosis_json_and_report_html(tmp_path):
    from usdeform.gap.detectability import ProtocolAdvice

    diagnosis = _diagnosis("no_significant_gap", [], [candidate("viscoelasticity", 9.0, significant=False)])
    diagnosis.record_next = [
        ProtocolAdvice("viscoelasticity", "undetectable", 4, "a hold of 6 s"),
        ProtocolAdvice("sound_speed_mismatch", "undetectable", None, "a target of known depth"),
    ]
    write_report(diagnosis, tmp_path)
    data = json.loads((tmp_path / "diagnosis.json").read_text())
    assert data["record_next"][0] == {
        "effect": "viscoelasticity",
        "reason": "undetectable",
        "repeats": 4,
        "protocol": "a hold of 6 s",
    }
    page = (tmp_path / "report.html").read_text()
    assert "What to record next" in page and "<td>more than 16</td><td>a target of known depth</td>" in page


def _fold(groups):
    """A fold with only the measure layout the held-out gap needs (no recordings)."""
    from usdeform.gap.folds import Fold

    fold = Fold.__new__(Fold)
    fold.groups = np.array([GROUPS.index(group) for group in groups])
    fold.n_features = len(groups)
    return fold


def _held(fold, point, spread=0.3):
    rng = np.random.default_rng(2)
    point = np.asarray(point, dtype=float)
    return HeldOut([fold], [(point, point[None] + spread * rng.standard_normal((200, len(point))))])


def test_an_effect_is_named_only_where_its_own_signature_drops():
    """A soft layer that lowers the gap only through the lumen's area (a misfit that is no layer) has no signature;
    one that lowers the displacement residual has; the signature groups cover the library."""
    fold = _fold(["displacement", "displacement", "vessel", "vessel"])
    before = _held(fold, [4.0, -4.0, 5.0, 5.0])
    area_only = _held(fold, [4.0, -4.0, 0.5, 0.3])
    field = _held(fold, [0.5, -0.2, 5.0, 5.0])
    assert _signature_shrink(before, area_only, "layered_tissue") == (pytest.approx(0.0, abs=1e-12), False)
    shrink, present = _signature_shrink(before, field, "layered_tissue")
    assert present and shrink > 0.9
    assert _signature_shrink(before, area_only, "lumen_pressure")[1]
    # an effect whose groups are not measured at all (no speckle correlation here) cannot show its signature
    assert _signature_shrink(before, field, "out_of_plane_motion") == (0.0, False)
    assert set(SIGNATURES) == {model.effect for model in EFFECTS}
    assert all(group in GROUPS for groups in SIGNATURES.values() for group in groups)


def test_a_known_weight_rules_out_a_sensor_drift_it_contradicts_even_when_too_short_to_show_the_sensor_clean():
    """A known weight read a drift of 0.005 +/- 0.004 N/s (too uncertain to call the sensor clean); a candidate that
    needs -0.121 +/- 0.002 N/s is ruled out, one that agrees, or cannot identify its drift, or has none, stays."""
    import dataclasses

    from usdeform.gap.verdicts import ruled_out_by_known_weight

    needs = dataclasses.replace(
        candidate("force_sensor_error", 1.0), parameters={"drift_n_per_s": -0.121}, uncertainty={"drift_n_per_s": 0.002}
    )
    agrees = dataclasses.replace(
        candidate("force_sensor_error+viscoelasticity", 1.1, n_parameters=3),
        parameters={"drift_n_per_s": 0.009},
        uncertainty={"drift_n_per_s": 0.003},
    )
    held = dataclasses.replace(
        needs, effect="force_sensor_error+lumen_pressure", unidentified={"drift_n_per_s": "hold"}
    )
    creep = candidate("viscoelasticity", 1.2)
    everything = [needs, agrees, held, creep]
    assert ruled_out_by_known_weight(everything, None, (0.005, 0.004)) == {"force_sensor_error"}
    assert ruled_out_by_known_weight(everything, None) == set()


def test_a_known_weight_rules_out_the_explanations_it_contradicts():
    from usdeform.gap.verdicts import ruled_out_by_known_weight

    sensor = candidate("force_sensor_error", 1.0)
    pair = candidate("force_sensor_error+viscoelasticity", 0.9, n_parameters=3)
    pressure, creep = candidate("lumen_pressure", 1.1), candidate("viscoelasticity", 5.0, significant=False)
    everything = [sensor, pair, pressure, creep]
    assert ruled_out_by_known_weight(everything, None) == set()
    # a sensor free of error: nothing with a sensor error stands
    assert ruled_out_by_known_weight(everything, "clean") == {
        "force_sensor_error",
        "force_sensor_error+viscoelasticity",
    }
    # a sensor error the palpations show too: what leaves it out does not stand
    assert ruled_out_by_known_weight(everything, "error") == {"lumen_pressure", "viscoelasticity"}
    # a sensor error the palpations do not show: the weight was measured apart from the tissue, it rules nothing out
    quiet = [candidate("force_sensor_error", 9.0, significant=False), pressure]
    assert ruled_out_by_known_weight(quiet, "error") == set()
    # the ambiguity it settles: a sensor offset against lumen pressure
    ordered = [sensor, pressure]
    assert decide(ordered, boots(*ordered), gap_seen=True, residual_significant=False)[0] == "ambiguous"
    kept = [c for c in ordered if c.effect not in ruled_out_by_known_weight(ordered, "error")]
    assert decide(kept, boots(*kept), gap_seen=True, residual_significant=False) == (
        "explained",
        ["force_sensor_error"],
    )
