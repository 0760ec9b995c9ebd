"""Record a follow-up protocol (record_next.json) on the simulator, as a robot would: ``usdeform simulate follow-up
DIR/record_next.json --preset NAME --output DIR2 --effect ...``.

Each palpation kind (palpation, hold, ramp_speed, position, tilt) is a force-controlled palpation
(:func:`usdeform.sim.simulate_palpation`) of the same phantom with the same effects, at the entry's position, highest
force, loading speed (converted to the force ramp that reaches the phantom's indentation at that force in the same
time), hold and probe tilt (added to any tilt the effects hold). ``reference_target`` (a palpation over a
reflector fixed in the world) and ``known_weight`` (a calibrated load on the probe off the tissue, with its per-frame
``KnownLoad``) are recorded by the simulator's functions for them (:data:`SIMULATORS`).
"""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._files import new_output_folders, outputs_together
from ..errors import InputError
from ..io import write_sequence
from ..recording import Recording
from ..sim import (
    Effects,
    ForceController,
    ImagingSettings,
    Phantom,
    ProbeTilt,
    TissueAcoustics,
    simulate_palpation,
)
from ..sim.reference_recordings import force_ramp_n_per_s, simulate_known_weight, simulate_reference_target
from .follow_up import FollowUpRecording
from .sensor_calibration import KNOWN_LOAD_FIELD

__all__ = [
    "SIMULATORS",
    "FollowUpSettings",
    "RecordedFollowUp",
    "record_follow_up",
    "run_follow_up_command",
    "simulate_follow_up",
]

MIN_FRAMES, MAX_FRAMES = 20, 240  # frames of one follow-up recording


@dataclass(frozen=True)
class FollowUpSettings:
    """How the simulator records: frames per second of recording (spread evenly, at least :data:`MIN_FRAMES`, at most
    :data:`MAX_FRAMES`), frame size (pixels), scanner and tissue acoustics, the force loop, and the seed."""

    frames_per_s: float = 10.0
    rows: int = 256
    cols: int = 256
    settings: ImagingSettings | None = None
    acoustics: TissueAcoustics = field(default_factory=TissueAcoustics)
    controller: ForceController = field(default_factory=ForceController)
    seed: int = 0


@dataclass(frozen=True)
class RecordedFollowUp:
    """One entry of the protocol and its recording (None with ``note`` saying why it was not recorded), and the
    further numbers per frame its sequence file carries (``KnownLoad`` of a known weight, N)."""

    entry: FollowUpRecording
    recording: Recording | None
    note: str = ""
    frame_series: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        if self.recording is None:
            return 0.0
        return float(self.recording.timestamps[-1] - self.recording.timestamps[0])


def _tilted(effects: Effects, tilt_deg: float) -> Effects:
    """``effects`` with the probe tilted by ``tilt_deg`` more (its pose records it)."""
    if not tilt_deg:
        return effects
    tilt = effects.tilt
    return dataclasses.replace(
        effects, tilt=ProbeTilt(tilt.tilt_deg + tilt_deg, tilt.surface_inclination_deg, tilt.travel_along_axis)
    )


def _palpation(
    entry: FollowUpRecording, phantom: Phantom, effects: Effects, settings: FollowUpSettings, seed: int
) -> tuple[Recording | None, str]:
    position = float(np.clip(entry.position_mm, 0.0, phantom.length_mm))
    force = min(entry.max_force_n, phantom.max_force_n)
    note = ""
    if position != entry.position_mm or force != entry.max_force_n:
        note = f"recorded at {position:g} mm and {force:g} N, the phantom's limits"
    rate = force_ramp_n_per_s(phantom, position, force, entry.ramp_speed_mm_s)
    duration = 2 * force / rate + entry.hold_s
    n_frames = int(np.clip(round(duration * settings.frames_per_s), MIN_FRAMES, MAX_FRAMES))
    recording, _ = simulate_palpation(
        phantom,
        position,
        force,
        n_frames=n_frames,
        ramp="up-hold-down" if entry.hold_s > 0 else "up-down",
        hold_s=entry.hold_s,
        seed=seed,
        effects=_tilted(effects, entry.tilt_deg),
        rows=settings.rows,
        cols=settings.cols,
        ramp_rate_n_per_s=rate,
        settings=settings.settings,
        acoustics=settings.acoustics,
        controller=settings.controller,
    )
    return recording, note


def _reference_target(
    entry: FollowUpRecording, phantom: Phantom, effects: Effects, settings: FollowUpSettings, seed: int
) -> tuple[Recording, dict[str, np.ndarray]]:
    return simulate_reference_target(entry, phantom, effects, settings, seed), {}


def _known_weight(
    entry: FollowUpRecording, phantom: Phantom, effects: Effects, settings: FollowUpSettings, seed: int
) -> tuple[Recording, dict[str, np.ndarray]]:
    recording, load = simulate_known_weight(entry, phantom, effects, settings, seed)
    return recording, {KNOWN_LOAD_FIELD: load}


#: The simulator's functions for the kinds that are no force-controlled palpation of the tissue: each takes (entry,
#: phantom, effects, settings, seed) and returns the recording and its further numbers per frame.
SIMULATORS: dict[str, Callable[..., tuple[Recording, dict[str, np.ndarray]]]] = {
    "reference_target": _reference_target,
    "known_weight": _known_weight,
}


def simulate_follow_up(
    entries: Sequence[FollowUpRecording],
    phantom: Phantom,
    effects: Effects | None = None,
    settings: FollowUpSettings = FollowUpSettings(),
) -> list[RecordedFollowUp]:
    """Record each entry on ``phantom`` with ``effects`` (the same hidden effects as the first recordings); entry
    ``i`` uses the ``i``-th draw of ``numpy.random.SeedSequence(settings.seed)``."""
    chosen = Effects.of(effects)
    seeds = [int(s) for s in np.random.SeedSequence(int(settings.seed)).generate_state(max(len(entries), 1))]
    recorded = []
    for entry, seed in zip(entries, seeds, strict=False):
        if entry.kind in SIMULATORS:
            recording, series = SIMULATORS[entry.kind](entry, phantom, chosen, settings, seed)
            recorded.append(RecordedFollowUp(entry, recording, frame_series=series))
        else:
            recorded.append(RecordedFollowUp(entry, *_palpation(entry, phantom, chosen, settings, seed)))
    return recorded


def record_follow_up(
    entries: Sequence[FollowUpRecording],
    output: str | Path,
    phantom: Phantom,
    effects: Effects | None = None,
    settings: FollowUpSettings = FollowUpSettings(),
) -> list[tuple[RecordedFollowUp, Path | None]]:
    """:func:`simulate_follow_up`, each recording written as ``OUTPUT/<name>.seq.nrrd``; the path is None for an
    entry not recorded. The files replace their targets together, or none does; a failed run leaves no folder it
    made."""
    output = Path(output)
    created = new_output_folders(output, "--output")
    written = []
    try:
        with outputs_together():
            for item in simulate_follow_up(entries, phantom, effects, settings):
                path = None
                if item.recording is not None:
                    output.mkdir(parents=True, exist_ok=True)
                    path = output / f"{item.entry.name}.seq.nrrd"
                    write_sequence(path, item.recording, frame_series=item.frame_series)
                written.append((item, path))
    except BaseException:  # errors, Ctrl-C, SIGTERM
        if created:
            shutil.rmtree(created[-1], ignore_errors=True)
        raise
    return written


def run_follow_up_command(args: Any, phantom: Phantom, effects: Effects) -> None:
    """``usdeform simulate follow-up RECORD_NEXT --output DIR``: the entries recorded into DIR, each named as listed."""
    from .follow_up import read_record_next

    if args.protocol != "follow-up" or args.record_next is None:
        raise InputError("simulate follow-up: give the protocol 'follow-up' and the record_next.json to record")
    if int(args.seed) != args.seed or args.seed < 0:
        raise InputError(f"--seed: expected a non-negative integer, got {args.seed!r}")
    entries = read_record_next(args.record_next)
    settings = FollowUpSettings(rows=args.rows, cols=args.cols, seed=args.seed)
    for item, path in record_follow_up(entries, args.output, phantom, effects, settings):
        done = f"wrote {path}" + (f" ({item.note})" if item.note else "") if path else item.note
        print(f"{item.entry.name}: {done}")
