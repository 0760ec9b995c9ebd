"""Sim-to-real gap diagnosis: where the gap between recordings and the simulator lies, which effect of
the simulator's library explains it, and how far it shrinks once that effect is added.

Typical use::

    from usdeform.gap import diagnose, write_report
    diagnosis = diagnose(["palpation1.seq.nrrd", "palpation2.seq.nrrd"])
    write_report(diagnosis, "diagnosis_dir")
"""

from __future__ import annotations

from .attribution import CandidateResult, MeasureResult
from .diagnosis import Diagnosis, diagnose

__all__ = ["CandidateResult", "Diagnosis", "MeasureResult", "diagnose"]
