"""Sim-to-real gap diagnosis: where the gap between recordings and the simulator lies, which effect of
the simulator's library explains it, and how far it shrinks once that effect is added.

Typical use::

    from usdeform.gap import diagnose, write_report
    diagnosis = diagnose(["palpation1.seq.nrrd", "palpation2.seq.nrrd"])
    write_report(diagnosis, "diagnosis_dir")

or ``usdeform diagnose RECORDING_OR_FOLDER... --out DIR`` (and ``--follow-up DIR`` for a second round).

Output contract (``DIR/diagnosis.json``; the same content as :class:`Diagnosis`)::

    {"verdict": "no_significant_gap" | "explained" | "explained_in_part" | "ambiguous" | "at_edge_of_library"
                | "unexplained",
     "named": [ID, ...],
     "summary": "<one paragraph>",
     "effects": [{"effect": ID, "parameters": {...}, "uncertainty": {...}, "gap_before": x,
                  "gap_after": y, "shrink": fraction, "significant": bool, "at_bound": [name, ...],
                  "signature_shrink": {ID: fraction}, "signature_absent": [ID, ...], "signature_left": [group, ...],
                  "unidentified": {name: KIND}},
                 ... best first],
     "measures": [{"name", "region", "force_range_n", "phase", "value", "uncertainty",
                   "significant", "recording", "value_after", "value_fitting_split",
                   "uncertainty_fitting_split"}, ...],
     "calibration": [{"recording", "shear_modulus_kpa", "section_poisson_ratio", "section_depth_mm",
                      "section_lumen_stiffness_ratio", "section_probe_width_mm", "vessel_center_x_mm", ...},
                     ...],
     "gap_before": G0, "critical_z": z, "gap_shown_by_candidate": bool,
     "undetectable": [ID, ...],
     "record_next": [{"effect": ID, "reason": "undetectable" | "ambiguous with ID" | "ambiguous with tissue
                      stiffness (...)", "repeats": k | null,
                      "protocol": "<the recording that shows its signature>"}, ...],
     "compensation": {"effects": {ID: {...}}, "supported": bool, "refusal": "<why --compensate refuses>",
                      "recordings": [{"recording", "dice_uncompensated", "dice_compensated",
                                      "area_error_pct_uncompensated", "area_error_pct_compensated",
                                      "error": "<why a score is missing>" (only then)}, ...],
                      "summary": "<one line>"},
     "recordings": ["<absolute path of each file read>", ...],
     "unsolved_sections": [{"recording", "section", "error", "effect"}, ...],
     "resolved_sections": [{"recording", "section", "how"}, ...],
     "sensor_calibration": [{"recording", "gain_error", "gain_error_uncertainty", "offset_n",
                             "offset_uncertainty_n", "drift_n_per_s", "drift_uncertainty_n_per_s", "frames"}, ...],
     "reference_targets": [{"recording", "found", "sound_speed_m_s", "sound_speed_uncertainty_m_s",
                            "reflector_depth_mm"} or {"recording", "found": false, "note"}, ...]}

ID is one of image_latency, force_sensor_error, viscoelasticity, sound_speed_mismatch, probe_tilt,
out_of_plane_motion, layered_tissue, sliding_contact, lumen_pressure, force_latency, or a pair ``a+b``. The verdict
(:func:`usdeform.gap.attribution.decide`) names in ``named`` the effect it attributes the gap to: one for
"explained" (it removes at least half of the held-out gap and leaves no significant measure or group),
"explained_in_part" (it removes at least half, but a significant residual remains outside its own signature; or it
removes less than half but at least ``MIN_SIGNATURE_SHRINK`` of the gap over its own signature, cleanly: the rest lies
where its physics does not show) and
"at_edge_of_library" (a parameter of it was fitted at an edge of the library, listed in its ``at_bound``, or its own
signature is left in part, ``signature_left``: no clean explanation); two for
"ambiguous" (their held-out gaps do not differ significantly, or the better one does not take half of the gap the
other leaves); none otherwise. An effect is significant only
where its own signature is present: ``signature_shrink`` is the held-out shrink of the gap over the measure groups
where its physics shows (:data:`usdeform.gap.attribution.SIGNATURES`), per member of a pair, and
``signature_absent`` the members whose signature did not drop significantly; ``signature_left`` (of the best
candidate) the groups of its own signature that still differ significantly with it added in measures it acts on
(moves by a standard error, away from zero or by half their gap), which makes the verdict "at_edge_of_library" (an
effect at work leaves no residual where its own physics shows). ``gap_shown_by_candidate``: no measure or group
differed on its own, and the gap was seen through a clean candidate's held-out test (significant, at least half of
the gap, nothing at an edge or left: a test of the effect's own form, which sees a gap spread thinly over many
measures). Values
are recorded minus simulated on the held-out split (``value_fitting_split``: on the fitting split; a
measure's significance takes both splits together); ``force_range_n`` is null for measures over
all forces. ``undetectable`` lists, in library order, the effects that would leave no significant gap in
these recordings even at the top of their realistic range (a noise-free power check of the verdict's tests,
:mod:`usdeform.gap.detectability`): a "no_significant_gap" verdict says nothing about them. ``record_next``
says, for each of them, for the effects of an ambiguous verdict and for the force sensor's gain error (which
no palpation tells from a stiffer tissue), what to record next: ``repeats``, how many
palpations like these would reveal it at the top of its realistic range (the power check's expected z-scores grow as
the square root of their number; null: more than 16, another protocol is needed), and ``protocol``, the recording
that shows its own signature (a longer hold, a second ramp speed, another position or tilt), in numbers taken from
these recordings. ``compensation`` says what the named effect costs the correction and what compensating it
(``usdeform fit/correct --compensate DIR/diagnosis.json``) gives back: each recording's highest-force frame
corrected to its lowest-force frame with the method fitted as recorded and with the effect undone at its fitted
size (:func:`usdeform.gap.correction_outcome.compensation_outcome`); ``supported`` False means ``--compensate``
refuses it (``refusal``) and the numbers are what ``--force-compensation`` would give.
``unidentified`` maps a parameter the recordings could not identify (held at its neutral value, as written in
``parameters``) to the record_next kind that would identify it. ``unsolved_sections`` lists the library sections
that could not be solved and were left out, with the effect left unfitted with them; ``resolved_sections`` those
solved with finer load steps or only to the recorded indentation (:class:`usdeform.gap.attribution.Attribution`).
``sensor_calibration`` holds the force sensor fitted on each known-weight recording given (per-frame ``KnownLoad``,
:mod:`usdeform.gap.sensor_calibration`); such recordings are no palpations, and the force_sensor_error candidate is
still fitted on the palpations alone. A reflector fixed in the world is tracked in a recording whose header has
``ReferenceTargetDepth`` (mm), or in every palpation with ``diagnose --reference-depth-mm``; ``reference_targets``
gives the speed of sound each such reflector shows, or why it was not found (the recording is then a plain palpation).
``recordings`` lists the files read, which ``usdeform diagnose NEW... --follow-up DIR`` reads again with the new
ones. ``DIR/record_next.json`` (:mod:`usdeform.gap.follow_up`) turns ``record_next`` into recordings a robot makes
next, each with its kind (palpation, hold, ramp_speed, position, tilt, reference_target, known_weight), its
parameters in mm, N, mm/s, s and degrees, and the effect IDs it reveals. An unidentified parameter of the named
effect (or the best candidate) asks for the kind it names under any verdict; the rest is planned only when the
verdict is "no_significant_gap", "ambiguous", "at_edge_of_library" or "unexplained". ``usdeform simulate follow-up
DIR/record_next.json`` records it on the simulator (:mod:`usdeform.gap.follow_up_sim`); ``fit``/``correct
--compensate`` and ``live --image-delay`` read diagnosis.json through
:func:`usdeform.gap.diagnosis_file.read_diagnosis`. ``DIR/report.html`` (summary first, effects, calibration, the
measures before and after) opens without a server, with ``force_curves.png`` and ``residual_map.png`` beside it.
Method, criterion and thresholds: :mod:`usdeform.gap.attribution` and :mod:`usdeform.gap.measures`;
what makes calibration fast: :mod:`usdeform.gap.calibration`.
"""

from __future__ import annotations

from .attribution import MeasureResult
from .diagnosis import Diagnosis, diagnose
from .report import write_report
from .verdicts import CandidateResult

__all__ = ["CandidateResult", "Diagnosis", "MeasureResult", "diagnose", "write_report"]
