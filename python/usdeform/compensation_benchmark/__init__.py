"""``usdeform compensation-benchmark``: what a recording-level effect costs the corrected volume, and how much
``--compensate`` gives back.

Each case simulates two load-hold-unload palpations (at two positions along the phantom) and a force-controlled sweep
between them (its force wandering about the target as a robot's does) with its ground truth
(:class:`BenchmarkSettings`), with a withheld effect drawn as the gap benchmark draws it
(:func:`usdeform.gap.benchmark.draw_effect`: image latency, force-sensor bias, drift and weight, viscoelasticity or
sound-speed mismatch), or none (null cases). The model is fitted and the sweep corrected as
``usdeform fit`` and ``usdeform correct`` do (:func:`~usdeform.fitting.fit_palpations`,
:func:`~usdeform.correction.correct_recording`), under four conditions:

* ``a`` the effect, no compensation;
* ``b`` compensated with the diagnosis's own fitted effect: :func:`usdeform.gap.diagnose` runs blind on the two
  palpations, its ``diagnosis.json`` is read with :func:`~usdeform.compensation.compensation_option` and applied
  with :func:`~usdeform.compensation.apply_compensation`, as ``--compensate`` does; a refused compensation is
  reported and scores as ``a``;
* ``c`` compensated with the true parameters (a :class:`~usdeform.compensation.Compensation` of the drawn effect);
* ``d`` the same case without the effect (same seeds);
* ``e`` compensated with the diagnosis's own fitted effect whatever its verdict, as ``--force-compensation`` does
  (:func:`~usdeform.compensation.forced_compensation`: both effects of an ambiguous verdict, the best-fitting one
  where none is named; ``b`` where ``b`` was applied; ``a`` where even forcing applies nothing, an effect of the
  tissue): what the diagnosis's fitted sizes give back, apart from its gate.

The sweep's true lumen masks are warped as its frames are corrected
(:func:`~usdeform.correction._frames.correct_like`) and scored against the zero-force lumen, frame by frame where the
lumen is in view: Dice (pixels), area error (% of the true area) and centre-line depth error (mm, the lumen
centroid's depth). Areas and depths of the truth use the true pixel size (``cases._true_pixel_mm``); those of a
corrected sweep its own ``image_to_probe``, so an uncompensated sound-speed mismatch shows in mm. Frames a latency
compensation drops are left out of its scores.

Scoring (:func:`~usdeform.compensation_benchmark.scoring.case_scores`, ``scoring.summarise``): a metric's goodness is
Dice, minus the area error, minus the depth error; the cost of the effect is goodness(d) - goodness(a) and the
recovered share (goodness(b) - goodness(a)) / cost (``c``: the same with the true parameters; ``e``: forced). A case
is costly when the effect costs at least :data:`MIN_DICE_COST` Dice or :data:`MIN_AREA_COST_PCT` % area; the share of
a metric is the median over the costly cases whose cost in that metric reaches its own threshold
(:data:`SHARE_THRESHOLDS`). Null cases must come out bit for bit unchanged when compensated (corrected frames,
validity and poses).

Follow-up (the loop of :mod:`usdeform.gap.follow_up`): where the diagnosis of the two palpations asks for more
recordings (its record_next.json), the simulator records them with the same phantom and effect
(:mod:`usdeform.gap.follow_up_sim`) and the diagnosis of all of them (round 1) is the one ``b`` and ``e`` compensate
with; each case reports both rounds' verdicts and what was added. Modules: ``cases`` (simulation and conditions),
``scoring`` (shares and tables), ``command`` (the run and its command line).
"""

from .cases import CONDITIONS, EFFECT_TYPES, BenchmarkSettings, true_compensation
from .command import add_compensation_benchmark_command, run_compensation_benchmark
from .scoring import case_scores, markdown_report, summarise

__all__ = [
    "CONDITIONS",
    "EFFECT_TYPES",
    "BenchmarkSettings",
    "add_compensation_benchmark_command",
    "case_scores",
    "markdown_report",
    "run_compensation_benchmark",
    "summarise",
    "true_compensation",
]
