"""``usdeform demo``: the paper's pipeline end to end on the simulator, shown in a self-contained report.

Palpations at a few positions along a path over a phantom whose stiffness varies along it, the
stiffness fits, optical flow, regression, a constant-force sweep, the correction of every frame,
compounding of the deformed, corrected and zero-force (ground truth) volumes, and the metrics
against the truth; :func:`run_demo` returns them and writes ``report.html`` with the volumes, the
model file and the recordings. With simulated effects (``--effect``) the palpations are also diagnosed blind
and the sweep corrected with the compensation the diagnosis supports (:class:`EffectOutcome`).
"""

from __future__ import annotations

from .config import PRESETS, DemoConfig, DemoResult, EffectOutcome, FrameMetrics, VolumeMetrics
from .pipeline import run_demo

__all__ = ["PRESETS", "DemoConfig", "DemoResult", "EffectOutcome", "FrameMetrics", "VolumeMetrics", "run_demo"]
