"""The follow-up protocol: ``record_next.json``, the recordings a robot makes next so that a second diagnosis can
decide what the first could not.

:func:`plan_follow_up` turns a diagnosis's advice (:mod:`usdeform.gap.detectability`) into concrete recordings with
their parameters in physical units, taken from the recordings given (their position, highest force, loading speed
and hold). Which recording reveals which effect:

| effect | recording |
|---|---|
| sound_speed_mismatch | reference_target: a reflector fixed in the world moves by the probe's displacement x c0 / c |
| force_sensor_error | known_weight: a calibrated load read by the sensor off the tissue (bias and gain) |
| viscoelasticity, out_of_plane_motion | hold: relaxation and drift show while the indentation stays |
| image_latency | ramp_speed: a delay's residual grows with the loading speed |
| force_latency | ramp_speed and hold: it grows with speed and vanishes in a hold |
| probe_tilt | tilt: a known tilt of the probe changes the shear a tilt adds, an inclined surface does not follow it |
| layered_tissue, sliding_contact, lumen_pressure | position: another section along the tissue |

A parameter of the named effect that the recordings could not identify (held at its neutral value) asks for the
recording it names, whatever the verdict. The rest is planned only for :data:`FOLLOW_UP_VERDICTS`: the effects the
recordings could not reveal, the two of an ambiguous verdict, the best candidate (a lead within the noise, one
fitted at an edge of the library, or the best of an unexplained gap) and, where no gap was seen, the sensor's gain. An
unexplained gap also asks for the speed of sound's and the force sensor's own recordings when no palpation can show
them. One recording of
each kind serves every effect it reveals. An effect that needs more palpations of the kind given (its power check's
repeats, at most :data:`MAX_PLANNED_REPEATS` times the recordings given) counts every palpation planned, except the
speed of sound and the force sensor (:data:`OWN_RECORDING_ONLY`), which get their own recording.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._files import atomic_output
from ..errors import InputError
from ..recording import Recording
from .detectability import GAIN_REASON, LARGEST_REALISTIC, ProtocolAdvice, recording_figures
from .observations import Observation
from .verdicts import CandidateResult

__all__ = [
    "FOLLOW_UP_VERDICTS",
    "FORMAT",
    "KINDS",
    "FirstProtocol",
    "FollowUpRecording",
    "first_protocol",
    "first_recordings",
    "plan_follow_up",
    "read_json_file",
    "read_record_next",
    "record_next_json",
    "recording_position_mm",
    "write_record_next",
]

FORMAT = "usdeform.record_next"
VERSION = 1
#: The recording kinds of the contract, in the order a plan lists them.
KINDS = ("palpation", "hold", "ramp_speed", "position", "tilt", "reference_target", "known_weight")
#: The kinds a robot records as a palpation of the tissue (all but known_weight).
PALPATION_KINDS = KINDS[:-1]
#: Verdicts whose follow-up can decide what the recordings given could not.
FOLLOW_UP_VERDICTS = ("no_significant_gap", "ambiguous", "at_edge_of_library", "unexplained")
#: The recording that shows each effect's own signature.
EFFECT_KIND = {
    "image_latency": "ramp_speed",
    "force_sensor_error": "known_weight",
    "viscoelasticity": "hold",
    "sound_speed_mismatch": "reference_target",
    "probe_tilt": "tilt",
    "out_of_plane_motion": "hold",
    "layered_tissue": "position",
    "sliding_contact": "position",
    "lumen_pressure": "position",
    "force_latency": "ramp_speed",
}
#: Effects a palpation shows at most through its noise: always their own recording, never repeats.
OWN_RECORDING_ONLY = {"sound_speed_mismatch", "force_sensor_error"}
_ALSO_HOLD = {"force_latency"}  # effects told apart by a hold as well as by their own kind
MAX_PLANNED_REPEATS = 3  # more palpations than this many times those given: the effect's own recording instead
SPEED_FACTOR = 3.0  # a ramp_speed recording loads this many times as fast as those given
TILT_DEG = 5.0  # a tilt recording's probe tilt about the elevation axis
POSITION_STEP_MM = 10.0  # a position recording's distance from the first recording's position
_REASONS = {
    "palpation": "More palpations like the first: the effect is small against the noise of those given.",
    "hold": "Hold the top force: creep lets the force fall while the indentation stays; a delay does not.",
    "ramp_speed": "Load faster: a delay's residual grows with speed, tissue creep does not.",
    "position": "Press another section: a layer, sliding or lumen pressure changes with the tissue under the probe.",
    "tilt": "Tilt the probe: a tilted probe follows its pose, an inclined surface stays where it is.",
    "reference_target": "Press over a reflector fixed in the world: it moves by the probe's travel times c0 / c.",
    "known_weight": "Load the probe off the tissue with a known weight: the reading shows the sensor's bias and gain.",
}


@dataclass(frozen=True)
class FollowUpRecording:
    """One entry of record_next.json (the contract in :mod:`usdeform.gap`): what to record, in mm, N, s and
    degrees, and the effect IDs it reveals."""

    name: str
    kind: str
    position_mm: float
    max_force_n: float
    ramp_speed_mm_s: float
    hold_s: float
    tilt_deg: float
    reference_depth_mm: float | None
    known_weight_n: float | None
    reveals: list[str]
    reason: str

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class FirstProtocol:
    """What the recordings given did: the first one's position along the tissue (mm), their highest force (N),
    fastest loading speed (mm/s), longest hold at the top (s) and how many there were."""

    position_mm: float
    max_force_n: float
    ramp_speed_mm_s: float
    hold_s: float
    count: int


def recording_position_mm(recording: Recording) -> float:
    """The probe's position along the tissue (mm): its first valid pose's base y in the simulator's phantom frame
    (:data:`usdeform.sim.recordings.DEFAULT_SURFACE_TO_BASE`, where ``simulate --at`` puts it)."""
    from ..sim.recordings import DEFAULT_SURFACE_TO_BASE

    poses = recording.probe_to_base[recording.pose_valid]
    if not len(poses):
        return float("nan")
    origin = np.linalg.solve(DEFAULT_SURFACE_TO_BASE, poses[0][:, 3])
    return float(origin[1])


def first_protocol(observations: Sequence[Observation], positions_mm: Sequence[float]) -> FirstProtocol:
    """The :class:`FirstProtocol` of the observed palpations at ``positions_mm``."""
    holds, speeds, _ = zip(*(recording_figures(observation) for observation in observations), strict=True)
    known = [p for p in positions_mm if np.isfinite(p)]
    return FirstProtocol(
        position_mm=round(known[0], 1) if known else 0.0,
        max_force_n=round(max(float(np.nanmax(o.force_n)) for o in observations), 1),
        ramp_speed_mm_s=round(max(speeds), 2),
        hold_s=round(max(holds), 1),
        count=len(observations),
    )


def _wanted(verdict: str, effects: Sequence[CandidateResult], advice: Sequence[ProtocolAdvice]) -> tuple[dict, int]:
    """Effect IDs to reveal per recording kind, and how many palpations like those given the effects need: for
    "no_significant_gap" the effects the recordings could not reveal, the best candidate (a lead within the noise) and
    the sensor's gain; for "ambiguous" the two effects named; for "at_edge_of_library" the best candidate; for
    "unexplained" the best candidate and the effects no palpation can show (:data:`OWN_RECORDING_ONLY`), which may
    hide in the gap left."""
    wanted: dict[str, list[str]] = {}
    repeats = 1

    def want(effect: str) -> None:
        for kind in [EFFECT_KIND[effect]] + (["hold"] if effect in _ALSO_HOLD else []):
            if effect not in wanted.setdefault(kind, []):
                wanted[kind].append(effect)

    for item in advice:
        if item.reason == GAIN_REASON or item.effect not in EFFECT_KIND:
            continue
        if verdict == "ambiguous" and item.reason.startswith("ambiguous with"):
            want(item.effect)
        elif verdict == "unexplained" and item.reason == "undetectable" and item.effect in OWN_RECORDING_ONLY:
            want(item.effect)
        elif verdict == "no_significant_gap" and item.reason == "undetectable":
            needed = item.repeats if item.repeats is not None else MAX_PLANNED_REPEATS + 1
            if needed <= MAX_PLANNED_REPEATS and item.effect not in OWN_RECORDING_ONLY:
                repeats = max(repeats, needed)
                wanted.setdefault("palpation", []).append(item.effect)
            else:
                want(item.effect)
    if effects and verdict in ("no_significant_gap", "at_edge_of_library", "unexplained"):
        for member in effects[0].effect.split("+"):
            want(member)
    if verdict == "no_significant_gap":  # a gain error scales every force as a stiffer tissue would
        want("force_sensor_error")
    return wanted, repeats


def _other_position(position_mm: float) -> float:
    """A position :data:`POSITION_STEP_MM` away, towards the smaller number when above twice the step."""
    step = -POSITION_STEP_MM if position_mm > 2 * POSITION_STEP_MM else POSITION_STEP_MM
    return round(position_mm + step, 1)


def _entry(index: int, kind: str, reveals: list[str], first: FirstProtocol) -> FollowUpRecording:
    tau_s = LARGEST_REALISTIC["viscoelasticity"]["tau_s"]
    hold = first.hold_s
    if kind == "hold":
        hold = round(max(3 * tau_s, 2 * first.hold_s, 5.0), 1)
    return FollowUpRecording(
        name=f"follow_up_{index:02d}_{kind}",
        kind=kind,
        position_mm=_other_position(first.position_mm) if kind == "position" else first.position_mm,
        max_force_n=first.max_force_n,
        ramp_speed_mm_s=round(first.ramp_speed_mm_s * (SPEED_FACTOR if kind == "ramp_speed" else 1.0), 2),
        hold_s=hold,
        tilt_deg=TILT_DEG if kind == "tilt" else 0.0,
        reference_depth_mm=None,
        known_weight_n=float(round(first.max_force_n)) if kind == "known_weight" else None,
        reveals=sorted(reveals),
        reason=_REASONS[kind],
    )


def plan_follow_up(
    verdict: str,
    effects: Sequence[CandidateResult],
    advice: Sequence[ProtocolAdvice],
    first: FirstProtocol,
    named: Sequence[str] = (),
) -> list[FollowUpRecording]:
    """The recordings to make next; see the module docstring for what each reveals and why it is asked for. A
    parameter the recordings could not identify (``CandidateResult.unidentified``) of a named effect (``named``, else
    the best candidate) asks for the recording kind it names, whatever the verdict; the rest of the plan is empty
    unless the verdict is one of :data:`FOLLOW_UP_VERDICTS`."""
    unidentified: dict[str, list[str]] = {}
    for effect in [effect for effect in effects if effect.effect in named] or list(effects[:1]):
        for kind in effect.unidentified.values():
            unidentified.setdefault(kind, []).append(effect.effect)
    if verdict not in FOLLOW_UP_VERDICTS:
        entries = [(kind, unidentified[kind]) for kind in KINDS if kind in unidentified]
        return [_entry(index, kind, list(dict.fromkeys(r)), first) for index, (kind, r) in enumerate(entries, 1)]
    wanted, repeats = _wanted(verdict, effects, advice)
    for kind, members in unidentified.items():
        wanted.setdefault(kind, []).extend(members)
    small = wanted.pop("palpation", [])
    planned = [kind for kind in KINDS if kind in wanted]
    palpations = sum(kind in PALPATION_KINDS for kind in planned)
    extra = max((repeats - 1) * first.count - palpations, 0)
    entries = [(kind, wanted[kind]) for kind in planned]
    if small:  # the planned palpations count as repeats; plain ones make up the rest
        entries = [(kind, reveals + small if kind in PALPATION_KINDS else reveals) for kind, reveals in entries]
        entries = [("palpation", small)] * extra + entries
    return [
        _entry(index, kind, list(dict.fromkeys(reveals)), first) for index, (kind, reveals) in enumerate(entries, 1)
    ]


def record_next_json(recordings: Sequence[FollowUpRecording]) -> dict[str, Any]:
    """The record_next.json document of ``recordings``."""
    return {
        "format": FORMAT,
        "version": VERSION,
        "diagnosis": "diagnosis.json",
        "recordings": [recording.to_json() for recording in recordings],
    }


_NUMBERS = {  # field -> (low, high): the bounds a robot or the simulator can record
    "position_mm": (-1000.0, 1000.0),
    "max_force_n": (0.0, 200.0),
    "ramp_speed_mm_s": (0.0, 100.0),
    "hold_s": (0.0, 600.0),
    "tilt_deg": (-45.0, 45.0),
    "reference_depth_mm": (0.0, 500.0),
    "known_weight_n": (0.0, 200.0),
}
_OPTIONAL = ("reference_depth_mm", "known_weight_n")


def _number(source: str, where: str, field: str, value: object) -> float | None:
    if value is None and field in _OPTIONAL:
        return None
    low, high = _NUMBERS[field]
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise InputError(f"{source}: {where}: {field}: expected a number, got {value!r}")
    if not low <= value <= high or (field in ("max_force_n", "ramp_speed_mm_s") and value == 0):
        raise InputError(f"{source}: {where}: {field}: {value!r} is outside {low:g}..{high:g}")
    return float(value)


def read_json_file(path: Path, name: str) -> Any:
    """The JSON document at ``path``; InputError naming ``name`` and the file when it cannot be read or parsed."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as error:
        raise InputError(f"{name}: {path} is not a readable JSON file ({error})") from None


def read_record_next(path: str | Path) -> list[FollowUpRecording]:
    """The recordings a record_next.json asks for, each field checked (InputError naming the file and field)."""
    source = str(path)
    document = read_json_file(Path(path), "record_next.json")
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise InputError(f"{source}: not a record_next.json: 'format' is not {FORMAT!r}")
    if document.get("version") != VERSION:
        raise InputError(f"{source}: version: expected {VERSION}, got {document.get('version')!r}")
    items = document.get("recordings")
    if not isinstance(items, list):
        raise InputError(f"{source}: recordings: expected a list")
    recordings = []
    for index, item in enumerate(items):
        where = f"recordings[{index}]"
        if not isinstance(item, dict):
            raise InputError(f"{source}: {where}: expected an object")
        if item.get("kind") not in KINDS:
            raise InputError(f"{source}: {where}: kind: expected one of {', '.join(KINDS)}, got {item.get('kind')!r}")
        name, reveals, reason = item.get("name"), item.get("reveals", []), item.get("reason", "")
        if not isinstance(name, str) or not name or Path(name).name != name:
            raise InputError(f"{source}: {where}: name: expected a file stem without folders, got {name!r}")
        if not isinstance(reveals, list) or not all(isinstance(effect, str) for effect in reveals):
            raise InputError(f"{source}: {where}: reveals: expected a list of effect IDs")
        numbers = {field: _number(source, where, field, item.get(field)) for field in _NUMBERS}
        recordings.append(
            FollowUpRecording(name=name, kind=item["kind"], reveals=reveals, reason=str(reason), **numbers)  # type: ignore[arg-type]
        )
    if len({recording.name for recording in recordings}) != len(recordings):
        raise InputError(f"{source}: recordings: two entries share a name")
    return recordings


def first_recordings(folder: str | Path) -> list[Path]:
    """The recordings a first diagnosis read (``diagnose --follow-up DIR``: DIR/diagnosis.json's ``recordings``),
    each checked to exist (InputError naming the file and field)."""
    source = Path(folder) / "diagnosis.json"
    if not Path(folder).is_dir():
        raise InputError(f"--follow-up: {folder} is not a folder of 'usdeform diagnose'")
    document = read_json_file(source, "--follow-up")
    paths = document.get("recordings") if isinstance(document, dict) else None
    if not isinstance(paths, list) or not paths or not all(isinstance(path, str) for path in paths):
        raise InputError(f"{source}: recordings: expected the list of files the diagnosis read")
    missing = [path for path in paths if not Path(path).is_file()]
    if missing:
        raise InputError(f"{source}: recordings: {missing[0]} no longer exists")
    return [Path(path) for path in paths]


def write_record_next(path: Path, recordings: Sequence[FollowUpRecording]) -> None:
    """Write record_next.json atomically."""
    with atomic_output(path) as handle:
        handle.write(json.dumps(record_next_json(recordings), indent=1).encode("utf-8"))
