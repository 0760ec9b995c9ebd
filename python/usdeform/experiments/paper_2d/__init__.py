"""The paper's 2D experiments (Section IV-A: TABLES I and II, Figs. 4 and 6-8) on the simulated phantoms.

1. Same position: the model is fitted on two palpations of the stiff phantom and corrects a third
   at 5-25 N (paper: Dice 0.69 -> 0.92 at 25 N).
2. Other positions of the stiff phantom, more than 20 mm away, with only their stiffness
   (paper: corrected Dice 0.96 on average).
3. The unseen soft phantom at 2-8 N with the stiff phantom's model, against the force-based
   baseline (Sun et al. 2010) fitted at the same place (paper: 0.66 -> 0.89 by stiffness, 0.74 by force).
4. TABLE II: every position and force, for both methods.

Every experiment runs the methods of :func:`methods_for` side by side: the paper's quadratic model,
the force-based baseline, the cubic B-spline spatial basis with the same force and stiffness coupling,
each optionally integrated over probe displacement instead of force, and "oracles" (a
model fitted to the simulator's true displacement field: no optical-flow error).

Dice compares the vessel segmented (:func:`usdeform.metrics.segment_vessel`) in the deformed or
corrected frame with the vessel segmented in the simulator's zero-force frame at the same probe
position. The diagnosis compares each fitted displacement with the true one by region, which
separates what a model cannot represent from what the tracking gets wrong.

The modules: :mod:`~usdeform.experiments.paper_2d.config` (configuration, methods, result records),
:mod:`~usdeform.experiments.paper_2d.evaluation` (one palpation simulated, corrected and compared),
:mod:`~usdeform.experiments.paper_2d.running` (the experiments in order) and
:mod:`~usdeform.experiments.paper_2d.report` (tables and figures).
"""

from __future__ import annotations

from .config import QUICK, Method, Paper2dConfig, methods_for
from .evaluation import Palpated, evaluate, palpate
from .running import run_paper_2d

__all__ = ["QUICK", "Method", "Palpated", "Paper2dConfig", "evaluate", "methods_for", "palpate", "run_paper_2d"]
