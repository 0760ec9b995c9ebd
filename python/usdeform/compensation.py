"""Undo the recording-level effects a gap diagnosis names (``usdeform fit/correct --compensate diagnosis.json``,
a batch manifest's ``compensate``).

:func:`read_compensation` reads a ``diagnosis.json`` (``usdeform diagnose``) and returns the
:class:`Compensation` of the effects it attributes the gap to; :meth:`Compensation.apply` undoes them
on a recording before the method sees it, with the diagnosis's fitted parameters. The command line
and the batch read their options with :func:`compensation_option` and compensate a sweep with
:func:`apply_compensation`:

- ``image_latency`` (delay_s, s): frame ``i`` was acquired at ``timestamp - delay``; its force, probe
  displacement and pose are re-paired to that time (linear interpolation, rotations by slerp between
  the recorded frames); frames acquired outside the recorded span are dropped.
- ``force_latency`` (delay_s, s): the force stamped ``t`` was the force at ``t - delay``; each frame
  takes the force stamped ``delay`` after its acquisition time (frames past the recorded span are dropped).
- ``force_sensor_error`` (offset_n, N; drift_n_per_s, N/s): measured = true + offset + drift * t, with
  t the time since the recording's first frame (the offset is the bias less the uncompensated probe
  weight): both are subtracted.
- ``viscoelasticity`` (g; tau_s, s): the force follows one-term Prony quasi-linear viscoelasticity,
  ``F(t) = int ((1 - g) + g exp(-(t - s) / tau)) dF_e(s)``, tissue loaded at once to the first
  frame's force (as the diagnosis models it). Each frame's force is replaced by the elastic force
  ``F_e`` that the force history up to it implies (the exact inverse of that recursion, linear
  between frames): the stiffness and the displacement model are then fitted on the elastic force, and
  a sweep frame's deformation is taken from its force history, not its instantaneous force.
- ``sound_speed_mismatch`` (error_m_s, m/s): true depth = displayed depth * (1540 + error) / 1540:
  the depth axis of ``image_to_probe`` is rescaled by that factor.

The effects are undone in this order: delays, sensor error, viscoelasticity, sound speed.

The diagnosis supports a compensation when its verdict is "explained" or "explained_in_part" (the
named effect takes most of the gap, or nearly all of the gap over its own signature, and a residual
beyond the library remains, as it does on any real recording) and the named effect is significant;
anything else ("ambiguous", "unexplained", "at_edge_of_library", "no_significant_gap") is refused
unless forced (the named effects, or the best-fitting one when none is named, are then applied).
Effects of the tissue itself (layered tissue, sliding contact, lumen pressure) change no recording
and are refused with what to do instead, as are the effects this module does not undo (probe tilt,
out-of-plane motion); in a named pair with a recording-level effect (``force_sensor_error+layered_tissue``)
the recording-level member is undone and the other listed as not undone, with the same advice.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ._arrays import interpolate_in_time
from .errors import InputError
from .recording import Recording

__all__ = [
    "Compensation",
    "add_compensation_options",
    "apply_compensation",
    "compensation_from_diagnosis",
    "compensation_option",
    "forced_compensation",
    "read_compensation",
]

#: Verdicts under which a diagnosis supports compensating the effect it names.
SUPPORTING_VERDICTS = ("explained", "explained_in_part")

#: The scanner's assumed speed of sound, m/s (as the diagnosis's sound-speed model).
ASSUMED_SOUND_SPEED_M_S = 1540.0

#: Least cost of an effect to a correction that counts (below it, segmentation noise): Dice, and
#: percentage points of area error.
MIN_DICE_COST = 0.01
MIN_AREA_COST_PCT = 2.0

#: The effects :meth:`Compensation.apply` undoes, with the diagnosis's parameters each needs.
COMPENSATED = {
    "image_latency": ("delay_s",),
    "force_latency": ("delay_s",),
    "force_sensor_error": ("offset_n", "drift_n_per_s"),
    "viscoelasticity": ("g", "tau_s"),
    "sound_speed_mismatch": ("error_m_s",),
}

#: Effects no compensation of a recording undoes, and what a user can do instead.
NOT_COMPENSATED = {
    "layered_tissue": "an effect of the tissue itself, which changes no recording: fit a finer basis "
    "(--basis bspline:12x12) so that the model follows the layer, and palpate at more positions",
    "sliding_contact": "an effect of the tissue itself, which changes no recording: palpate at more positions, "
    "with the same coupling gel as the sweep, so that the model carries the slip",
    "lumen_pressure": "an effect of the tissue itself, which changes no recording: palpate at more positions "
    "along the vessel, so that the model carries the lumen's collapse",
    "probe_tilt": "not compensated here: hold the probe normal to the skin (a tilted probe and a surface inclined "
    "under a level probe look the same in a palpation: the pose tells which)",
    "out_of_plane_motion": "not compensated here: hold the probe's elevation steady while palpating",
}


@dataclass(frozen=True)
class Compensation:
    """The recording-level effects to undo, with their fitted parameters and uncertainties.

    Attributes
    ----------
    source : str
        The diagnosis file.
    verdict : str
        Its verdict.
    effects : dict
        Effect ID -> parameter name -> value (units as in the name), for the IDs of :data:`COMPENSATED`.
    uncertainty : dict
        Effect ID -> parameter name -> standard uncertainty, where the diagnosis gives one.
    forced : bool
        True when the diagnosis does not support the compensation and it was forced.
    not_undone : dict
        Effect ID -> why no compensation of a recording undoes it and what to do instead, for the members of a
        named pair (e.g. ``force_sensor_error+layered_tissue``) that are left as they are.
    """

    source: str
    verdict: str
    effects: dict[str, dict[str, float]]
    uncertainty: dict[str, dict[str, float]]
    forced: bool
    not_undone: dict[str, str] = dataclasses.field(default_factory=dict)

    def _parameter(self, effect: str, name: str) -> float:
        return self.effects.get(effect, {}).get(name, 0.0)

    def apply(self, recording: Recording, name: str = "recording") -> tuple[Recording, str]:
        """``recording`` with the effects undone, and one line saying what changed (frames dropped too).

        Needs per-frame ContactForce for the force effects and ProbeDisplacement where it is recorded;
        ``name`` (e.g. its file) is named in errors and in the line."""
        changed, notes = recording, []
        image_delay = self._parameter("image_latency", "delay_s")
        force_delay = self._parameter("force_latency", "delay_s")
        if image_delay or force_delay:
            changed, dropped = _repaired(changed, image_delay, force_delay, name)
            notes.append(
                f"frames re-paired with the force and pose of their acquisition time (image delay "
                f"{image_delay * 1000:.3g} ms, force delay {force_delay * 1000:.3g} ms; {dropped} frame(s) outside "
                "the recorded span dropped)"
            )
        offset = self._parameter("force_sensor_error", "offset_n")
        drift = self._parameter("force_sensor_error", "drift_n_per_s")
        if "force_sensor_error" in self.effects:
            if changed.force is None:
                raise InputError(f"{name}: compensating the force sensor needs per-frame ContactForce")
            elapsed = changed.timestamps - recording.timestamps[0]
            changed = dataclasses.replace(changed, force=changed.force - offset - drift * elapsed)
            notes.append(f"force-sensor offset {offset:.3g} N and drift {drift:.3g} N/s subtracted")
        if "viscoelasticity" in self.effects:
            g, tau = self._parameter("viscoelasticity", "g"), self._parameter("viscoelasticity", "tau_s")
            if changed.force is None:
                raise InputError(f"{name}: compensating viscoelasticity needs per-frame ContactForce")
            if not (0 <= g < 1 and tau > 0):
                raise InputError(f"{self.source}: viscoelasticity: expected 0 <= g < 1 and tau_s > 0, got {g}, {tau}")
            changed = dataclasses.replace(changed, force=_elastic_force(changed.force, changed.timestamps, g, tau))
            notes.append(
                f"force replaced by the elastic force its history implies (relaxation g {g:.3g}, tau {tau:.3g} s)"
            )
        error = self._parameter("sound_speed_mismatch", "error_m_s")
        if error:
            scale = (ASSUMED_SOUND_SPEED_M_S + error) / ASSUMED_SOUND_SPEED_M_S
            image_to_probe = changed.image_to_probe.copy()
            image_to_probe[:3, 1] *= scale
            changed = dataclasses.replace(changed, image_to_probe=image_to_probe)
            notes.append(f"depth axis rescaled by {scale:.5f} (sound speed {error:+.3g} m/s)")
        notes.extend(f"{effect} not undone ({why})" for effect, why in self.not_undone.items())
        qualifier = " (forced: the diagnosis does not support it)" if self.forced else ""
        if not self.forced and self.verdict == "explained_in_part":
            qualifier = " (the diagnosis explains the gap only in part: a residual it cannot name remains)"
        return changed, f"{name}: compensated{qualifier}: " + "; ".join(notes)

    def to_json(self) -> dict[str, Any]:
        """The compensation for a model file's provenance."""
        return {
            "diagnosis": self.source,
            "verdict": self.verdict,
            "effects": self.effects,
            "uncertainty": self.uncertainty,
            "forced": self.forced,
            "not_undone": self.not_undone,
        }


def _elastic_force(force_n: np.ndarray, times_s: np.ndarray, g: float, tau_s: float) -> np.ndarray:
    """The elastic force (N) whose one-term Prony QLV force (module docstring) is ``force_n`` at ``times_s``."""
    elastic = np.empty_like(force_n)
    elastic[0] = history = force_n[0]
    for index in range(1, len(force_n)):
        step = max(times_s[index] - times_s[index - 1], 1e-9)
        decay = np.exp(-step / tau_s)
        ramp = tau_s / step * (1 - decay)
        elastic[index] = (force_n[index] - g * decay * history + g * ramp * elastic[index - 1]) / (1 - g + g * ramp)
        history = decay * history + ramp * (elastic[index] - elastic[index - 1])
    return elastic


def _repaired(recording: Recording, image_delay_s: float, force_delay_s: float, name: str) -> tuple[Recording, int]:
    """Frames re-paired with force, displacement and pose at their acquisition time (see the module
    docstring), and how many frames fell outside the recorded span."""
    times = recording.timestamps
    if np.any(np.diff(times) <= 0) or not recording.pose_valid.all():
        raise InputError(
            f"{name}: re-pairing frames in time needs strictly increasing timestamps and a valid pose on every frame"
        )
    acquired = times - image_delay_s
    force_stamped = acquired + force_delay_s  # the stamp of the force sample taken at the acquisition time
    kept = np.flatnonzero(
        (acquired >= times[0]) & (acquired <= times[-1]) & (force_stamped >= times[0]) & (force_stamped <= times[-1])
    )
    if kept.size < 2:
        raise InputError(f"{name}: fewer than 2 frames remain once re-paired with their acquisition time")
    at = acquired[kept]
    probe_to_base = np.tile(np.eye(4), (kept.size, 1, 1))
    probe_to_base[:, :3, :3] = Slerp(times, Rotation.from_matrix(recording.probe_to_base[:, :3, :3]))(at).as_matrix()
    probe_to_base[:, :3, 3] = interpolate_in_time(at, times, recording.probe_to_base[:, :3, 3])
    picked = recording.select(kept)
    return (
        dataclasses.replace(
            picked,
            probe_to_base=probe_to_base,
            force=None if recording.force is None else np.interp(force_stamped[kept], times, recording.force),
            probe_displacement=None
            if recording.probe_displacement is None
            else np.interp(at, times, recording.probe_displacement),
        ),
        len(recording) - kept.size,
    )


def _number(source: str, field: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise InputError(f"{source}: {field}: expected a finite number, got {value!r}")
    return float(value)


def read_compensation(
    path: str | Path, *, force: bool = False, force_option: str = "--force-compensation"
) -> Compensation:
    """The compensation a ``diagnosis.json`` supports (see the module docstring).

    Parameters
    ----------
    path : str or Path
        The diagnosis (``usdeform diagnose --out DIR`` writes ``DIR/diagnosis.json``).
    force : bool
        Apply the named effects (or the best-fitting one when none is named) even where the diagnosis
        does not support them (verdict not in :data:`SUPPORTING_VERDICTS`, effect not significant).
    force_option : str
        The option that sets ``force``, named where a compensation is refused.

    Raises
    ------
    InputError
        The file is not a diagnosis, the compensation is not supported (and not forced), or the effect
        is one no compensation of a recording undoes.
    """
    source = str(path)
    from .gap.diagnosis_file import read_diagnosis  # the one reader of diagnosis.json (gap imports this module)

    document = read_diagnosis(path)
    return compensation_from_diagnosis(document, source, force=force, force_option=force_option)


def compensation_from_diagnosis(
    document: object, source: str, *, force: bool = False, force_option: str = "--force-compensation"
) -> Compensation:
    """The compensation a diagnosis (the ``diagnosis.json`` contract, :meth:`usdeform.gap.Diagnosis.to_json`)
    supports; ``source`` names it in errors, the rest as :func:`read_compensation`."""
    if not isinstance(document, dict) or not isinstance(document.get("effects"), list):
        raise InputError(f"{source}: not a diagnosis.json ('usdeform diagnose' writes one): no 'effects' list")
    verdict, named = str(document.get("verdict")), document.get("named") or []
    by_id = {str(effect.get("effect")): effect for effect in document["effects"] if isinstance(effect, dict)}
    chosen = [str(effect_id) for effect_id in named] or list(by_id)[:1]
    if not chosen:
        raise InputError(f"{source}: the diagnosis (verdict {verdict!r}) has no effect to compensate")
    insignificant = [effect_id for effect_id in chosen if not by_id.get(effect_id, {}).get("significant")]
    reasons = [
        *(
            [f"verdict {verdict!r}, not {' or '.join(map(repr, SUPPORTING_VERDICTS))}"]
            if verdict not in SUPPORTING_VERDICTS
            else []
        ),
        *(["it names no effect (the best-fitting one is " + chosen[0] + ")"] if not named else []),
        *([f"{' and '.join(insignificant)} not significant"] if insignificant else []),
    ]
    if reasons and not force:
        raise InputError(
            f"{source}: the diagnosis does not support compensating {' and '.join(chosen)} ({'; '.join(reasons)}); "
            f"{force_option} applies it anyway"
        )
    effects: dict[str, dict[str, float]] = {}
    uncertainty: dict[str, dict[str, float]] = {}
    not_undone: dict[str, str] = {}
    for effect_id in chosen:
        entry = by_id.get(effect_id)
        if entry is None:
            raise InputError(f"{source}: named effect {effect_id!r} has no entry in 'effects'")
        parameters, errors = entry.get("parameters") or {}, entry.get("uncertainty") or {}
        for member in effect_id.split("+"):
            if member in NOT_COMPENSATED:
                not_undone[member] = NOT_COMPENSATED[member]
                continue
            if member not in COMPENSATED:
                raise InputError(f"{source}: unknown effect {member!r}")
            effects[member] = {
                key: _number(source, f"{effect_id}.parameters.{key}", parameters.get(key))
                for key in COMPENSATED[member]
            }
            uncertainty[member] = {
                key: _number(source, f"{effect_id}.uncertainty.{key}", errors[key])
                for key in COMPENSATED[member]
                if errors.get(key) is not None
            }
    if not effects:
        raise InputError(f"{source}: " + "; ".join(f"{member}: {why}" for member, why in not_undone.items()))
    return Compensation(source, verdict, effects, uncertainty, bool(reasons), not_undone)


def forced_compensation(document: object, source: str) -> Compensation | None:
    """What ``--force-compensation`` applies from a diagnosis dict (:func:`compensation_from_diagnosis` forced: the
    named effects, or the best-fitting one when none is named), or None where it applies nothing (an effect no
    compensation of a recording undoes, or no effect at all)."""
    try:
        return compensation_from_diagnosis(document, source, force=True)
    except InputError:
        return None


def compensation_option(
    path: str | Path | None,
    force: bool,
    *,
    option: str = "--compensate",
    force_option: str = "--force-compensation",
) -> Compensation | None:
    """The compensation an option names, or None without a file: ``usdeform fit/correct --compensate
    FILE [--force-compensation]``, and a batch manifest's ``compensate`` and ``force_compensation``
    (``option`` and ``force_option`` name them in errors).

    Raises
    ------
    InputError
        ``force`` without a file, or the file refused by :func:`read_compensation`, with ``option``
        and the file named.
    """
    if path is None:
        if force:
            raise InputError(f"{force_option}: needs {option}")
        return None
    try:
        return read_compensation(path, force=force, force_option=force_option)
    except InputError as error:
        raise InputError(f"{option}: {error}") from None


def apply_compensation(
    compensation: Compensation | None, recording: Recording, name: str
) -> tuple[Recording, dict[str, Any] | None]:
    """``recording`` with ``compensation`` undone (:meth:`Compensation.apply`; ``name`` as there) and
    the record of it for a provenance or a batch's details: :meth:`Compensation.to_json` with ``notes``,
    the line saying what changed. Without a compensation, ``recording`` unchanged and None."""
    if compensation is None:
        return recording, None
    compensated, note = compensation.apply(recording, name)
    return compensated, {**compensation.to_json(), "notes": [note]}


def add_compensation_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--compensate`` and ``--force-compensation`` (the options of ``fit`` and ``correct``) to ``parser``."""
    parser.add_argument(
        "--compensate",
        type=Path,
        metavar="DIAGNOSIS",
        help="undo the recording effects a diagnosis.json ('usdeform diagnose') attributes the gap to, with its "
        "fitted parameters, before the method sees the recordings: image or force delay (frames re-paired in "
        "time), force-sensor offset and drift (subtracted), sound-speed mismatch (depth axis rescaled)",
    )
    parser.add_argument(
        "--force-compensation",
        action="store_true",
        help="compensate even where the diagnosis does not support it (verdict not 'explained' or "
        "'explained_in_part', effect not significant)",
    )
