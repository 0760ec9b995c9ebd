"""B-mode image formation for the simulator: tissue-attached speckle, vessel, attenuation, log compression.

- :mod:`~usdeform.sim.imaging.settings`: the scanner (:class:`ImagingSettings`) and the tissue's
  acoustics (:class:`TissueAcoustics`);
- :mod:`~usdeform.sim.imaging.geometry`: the surface, probe and image frames, where the probe is
  (:class:`ProbeState`) and where tissue points appear in its image;
- :mod:`~usdeform.sim.imaging.scatterers`: the point scatterers of the reference tissue, seeded per
  slab from the seed, and their random jitter;
- :mod:`~usdeform.sim.imaging.fields`: a section's finite-element displacement sampled on a grid;
- :mod:`~usdeform.sim.imaging.echo`: the complex echo of the deformed scatterers and the B-mode frame;
- :mod:`~usdeform.sim.imaging.truth`: the lumen mask and the true displacement of every pixel.
"""

from __future__ import annotations

from .echo import b_mode, echo_signal, render_frame, unit_complex_noise
from .fields import GriddedDisplacement, GriddedSolution, interpolation_bracket
from .geometry import ProbeState, probe_to_surface, section_to_surface, surface_to_image
from .scatterers import ScattererField, scatterer_jitter_mm
from .settings import ImagingSettings, TissueAcoustics
from .truth import true_displacement_px, vessel_mask

__all__ = [
    "GriddedDisplacement",
    "GriddedSolution",
    "ImagingSettings",
    "ProbeState",
    "ScattererField",
    "TissueAcoustics",
    "b_mode",
    "echo_signal",
    "interpolation_bracket",
    "probe_to_surface",
    "render_frame",
    "scatterer_jitter_mm",
    "section_to_surface",
    "surface_to_image",
    "true_displacement_px",
    "unit_complex_noise",
    "vessel_mask",
]
