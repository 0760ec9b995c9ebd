"""The simulator: finite-element mechanics of a tissue section pressed by the probe, B-mode image
formation with tissue-attached speckle, force-controlled palpations and sweeps recorded on realistic
clocks with per-frame ground truth, and a library of switchable physical effects.

Typical use::

    from usdeform.sim import stiff_phantom, simulate_palpation, Effects, ImageLatency
    recording, truth = simulate_palpation(stiff_phantom(), s_mm=20.0, max_force_n=20.0, seed=1)
    delayed, _ = simulate_palpation(stiff_phantom(), 20.0, 20.0, seed=1, effects=[ImageLatency(0.08)])
"""

from __future__ import annotations

from .effects import (
    ConvexProbeFace,
    Effects,
    ForceSensorError,
    ImageLatency,
    LayeredTissue,
    LumenPressure,
    OutOfPlaneMotion,
    ProbeTilt,
    SlidingContact,
    SoundSpeedMismatch,
    Viscoelasticity,
)
from .imaging import ImagingSettings, ProbeState, TissueAcoustics
from .mechanics import Layer, MechanicsSolution, SectionSpec, Vessel, solution_is_cached, solve_section
from .phantoms import (
    Phantom,
    artery_vein_phantom,
    branching_phantom,
    coarse_phantom,
    compliant_vessel_phantom,
    soft_phantom,
    stiff_phantom,
)
from .recordings import GroundTruth, simulate_palpation, simulate_sweep, truth_image_to_base
from .reference_recordings import simulate_known_weight, simulate_reference_target
from .robot import Clocks, ForceController, SweepPath

__all__ = [
    "Clocks",
    "ConvexProbeFace",
    "Effects",
    "ForceController",
    "ForceSensorError",
    "GroundTruth",
    "ImageLatency",
    "ImagingSettings",
    "Layer",
    "LayeredTissue",
    "LumenPressure",
    "MechanicsSolution",
    "OutOfPlaneMotion",
    "Phantom",
    "ProbeState",
    "ProbeTilt",
    "SectionSpec",
    "SlidingContact",
    "SoundSpeedMismatch",
    "SweepPath",
    "TissueAcoustics",
    "Vessel",
    "Viscoelasticity",
    "artery_vein_phantom",
    "branching_phantom",
    "coarse_phantom",
    "compliant_vessel_phantom",
    "simulate_known_weight",
    "simulate_palpation",
    "simulate_reference_target",
    "simulate_sweep",
    "soft_phantom",
    "solution_is_cached",
    "solve_section",
    "stiff_phantom",
    "truth_image_to_base",
]
