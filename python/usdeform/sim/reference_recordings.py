"""A palpation over a reflector fixed in the world, the recording that shows the tissue's speed of sound.

A uniform sound-speed error scales displayed depth by assumed / true speed. The tissue's own image cannot show it,
since the simulator's mechanics scale with it, but a reflector that does not move with the tissue (the phantom's base
plate, the table under it, a wire plane held by the phantom's box) moves in the image by the probe's displacement
times assumed / true speed.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..recording import Recording
from .effects import Effect, Effects
from .imaging import ImagingSettings
from .phantoms import Phantom
from .recordings import simulate_palpation

__all__ = ["REFERENCE_DEPTH_KEY", "force_ramp_n_per_s", "simulate_reference_target"]

#: The sequence-file header key giving the reflector's depth below the unloaded surface, mm.
REFERENCE_DEPTH_KEY = "ReferenceTargetDepth"
_DISPLAY_MARGIN = 1.12  # the image reaches this far beyond the reflector: displayed deeper under a slow tissue
_DISPLAY_SPARE_MM = 4.0
_MIN_FRAMES, _MAX_FRAMES = 20, 240


def force_ramp_n_per_s(phantom: Phantom, position_mm: float, max_force_n: float, speed_mm_s: float) -> float:
    """The force ramp (N/s) that reaches the phantom's indentation at ``max_force_n`` in the time ``speed_mm_s`` (the
    probe's speed along its axis, mm/s) takes to travel it."""
    indentation = float(np.interp(max_force_n, phantom.solution_at(position_mm).force_n, phantom.probe_displacement_mm))
    return max_force_n * speed_mm_s / max(indentation, 1e-6)


def simulate_reference_target(
    entry: Any, phantom: Phantom, effects: Effects | list[Effect] | None, settings: Any, seed: int
) -> Recording:
    """A palpation of ``phantom`` with ``effects`` as a record_next entry of kind ``reference_target`` asks
    (``position_mm``, ``max_force_n``, ``ramp_speed_mm_s``, ``hold_s``, ``tilt_deg`` are not used: a level probe),
    over a flat reflector fixed in the world ``entry.reference_depth_mm`` below the unloaded surface (None: the
    phantom's base, where the tissue is bonded to it). The image reaches beyond the reflector (rows and columns of
    ``settings``, a follow-up's recording settings: ``rows``, ``cols``, ``settings``, ``acoustics``, ``controller``,
    ``frames_per_s``). The header key ``ReferenceTargetDepth`` gives the reflector's depth (the asked one, or the
    base's), as an operator who placed the wire or measured the phantom knows it."""
    position = float(np.clip(entry.position_mm, 0.0, phantom.length_mm))
    force = float(min(entry.max_force_n, phantom.max_force_n))
    base_mm = float(phantom.section_at(position).depth_mm)
    depth = base_mm if entry.reference_depth_mm is None else float(entry.reference_depth_mm)
    scanner = settings.settings or ImagingSettings(rows=settings.rows, cols=settings.cols)
    scanner = dataclasses.replace(scanner, depth_mm=max(scanner.depth_mm, depth * _DISPLAY_MARGIN + _DISPLAY_SPARE_MM))
    acoustics = dataclasses.replace(settings.acoustics, reference_depth_mm=depth)
    rate = force_ramp_n_per_s(phantom, position, force, float(entry.ramp_speed_mm_s))
    duration = 2 * force / rate + float(entry.hold_s)
    n_frames = int(np.clip(round(duration * settings.frames_per_s), _MIN_FRAMES, _MAX_FRAMES))
    recording, _ = simulate_palpation(
        phantom,
        position,
        force,
        n_frames=n_frames,
        ramp="up-hold-down" if entry.hold_s > 0 else "up-down",
        hold_s=float(entry.hold_s),
        seed=seed,
        effects=effects,
        rows=scanner.rows,
        cols=scanner.cols,
        ramp_rate_n_per_s=rate,
        settings=scanner,
        acoustics=acoustics,
        controller=settings.controller,
    )
    metadata = {**recording.metadata, REFERENCE_DEPTH_KEY: f"{depth:.3f}"}
    return dataclasses.replace(recording, metadata=metadata)
