"""Recordings against a reference the tissue does not hold: a reflector fixed in the world, and a known weight.

A uniform sound-speed error scales displayed depth by assumed / true speed. The tissue's own image cannot show it,
since the simulator's mechanics scale with it, but a reflector that does not move with the tissue (the phantom's base
plate, the table under it, a wire plane held by the phantom's box) moves in the image by the probe's displacement
times assumed / true speed (:func:`simulate_reference_target`).

A force sensor's offset, drift and gain error scale or shift every force of a palpation alike, which the tissue's
stiffness can take up. A calibrated weight loaded on the probe off the tissue cannot: the reading against the known
load shows them (:func:`simulate_known_weight`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..errors import InputError
from ..recording import Recording
from .effects import Effect, Effects
from .imaging import ImagingSettings, ProbeState, probe_to_surface
from .phantoms import Phantom
from .recordings import DEFAULT_SURFACE_TO_BASE, simulate_palpation
from .robot import Clocks

__all__ = [
    "KNOWN_WEIGHT_LIFT_MM",
    "REFERENCE_DEPTH_KEY",
    "force_ramp_n_per_s",
    "simulate_known_weight",
    "simulate_reference_target",
]

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


#: How far above the unloaded surface the probe hangs while a known weight loads it, mm.
KNOWN_WEIGHT_LIFT_MM = 20.0
_UNLOADED_S, _PUT_ON_S, _DEFAULT_HOLD_S = 1.0, 0.3, 3.0


def simulate_known_weight(
    entry: Any, phantom: Phantom, effects: Effects | list[Effect] | None, settings: Any, seed: int
) -> tuple[Recording, np.ndarray]:
    """A known-weight recording as a record_next entry of kind ``known_weight`` asks: the probe in its holder,
    :data:`KNOWN_WEIGHT_LIFT_MM` above the phantom at ``entry.position_mm``, pointing down; 1 s unloaded, a weight of
    ``entry.known_weight_n`` (N) put on over 0.3 s, held ``entry.hold_s`` (3 s when 0), taken off over 0.3 s, 1 s
    unloaded. The sensor reads the load through the effects' sensor error (offset, drift, uncompensated probe weight,
    gain error and lag) with the force loop's sensor noise, on the force clock (1 kHz); each frame takes the reading
    of its force stamp (the effects' force delay). The frames are blank: the probe images air. ``settings``: a
    follow-up's recording settings (``rows``, ``cols``, ``settings``, ``controller``, ``frames_per_s``).

    Returns the recording and the load truly applied at each frame's time stamp (n,), N: the ``KnownLoad`` field a
    known-weight sequence file carries per frame.
    """
    weight = entry.known_weight_n
    if weight is None or not weight > 0:
        raise InputError(f"{entry.name}: known_weight needs known_weight_n, the calibrated load in N, above 0")
    chosen = Effects.of(effects)
    sensor, clocks = chosen.force_sensor, Clocks()
    hold = float(entry.hold_s) or _DEFAULT_HOLD_S
    duration = 2 * _UNLOADED_S + 2 * _PUT_ON_S + hold
    force_times = np.arange(int(duration * clocks.force_rate_hz) + 1) / clocks.force_rate_hz
    on = np.clip((force_times - _UNLOADED_S) / _PUT_ON_S, 0, 1)
    off = np.clip((force_times - _UNLOADED_S - _PUT_ON_S - hold) / _PUT_ON_S, 0, 1)
    load = float(weight) * (on - off)
    rng = np.random.default_rng(seed)
    lag = sensor.lag_fraction(1.0 / clocks.force_rate_hz)
    reading = np.empty_like(load)
    lagged = sensor.measured(load[0], 0.0, 0.0)
    for tick, (true_force, time) in enumerate(zip(load, force_times, strict=True)):
        lagged += lag * (sensor.measured(true_force, time, 0.0) - lagged)
        reading[tick] = lagged
    reading += settings.controller.sensor_noise_n * rng.standard_normal(len(reading))
    n_frames = int(np.clip(round(duration * settings.frames_per_s), _MIN_FRAMES, _MAX_FRAMES))
    frame_times = np.linspace(0.0, duration, n_frames)
    scanner = settings.settings or ImagingSettings(rows=settings.rows, cols=settings.cols)
    position = float(np.clip(entry.position_mm, 0.0, phantom.length_mm))
    lifted = DEFAULT_SURFACE_TO_BASE @ probe_to_surface(ProbeState(position, -KNOWN_WEIGHT_LIFT_MM, 0.0))
    recording = Recording(
        frames=np.zeros((n_frames, scanner.rows, scanner.cols), np.uint8),
        timestamps=frame_times,
        probe_to_base=np.tile(lifted, (n_frames, 1, 1)),
        pose_valid=np.ones(n_frames, dtype=bool),
        image_to_probe=scanner.image_to_probe,
        force=np.interp(frame_times - chosen.latency.force_delay_s, force_times, reading),
        probe_displacement=np.full(n_frames, -KNOWN_WEIGHT_LIFT_MM),
    )
    return recording, np.interp(frame_times, force_times, load)
