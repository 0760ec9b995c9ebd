"""The phases of a recorded palpation: approach, loading, hold and unloading, and its loading ramp from contact.

The method (paper eqs. 4-10) assumes a loading curve: force rising with probe displacement from
contact. A robot's palpation records more: an approach (the probe moves down to the surface, the
force at the sensor's noise), the loading ramp, maybe a hold at the top (the force held while
viscoelastic tissue creeps, or the position held while it relaxes) and the unloading.
:func:`detect_phases` finds them from the per-frame force and probe displacement alone:

- **No contact**: the force's range (highest - lowest) is within ``max(8 sigma, 0.1 N)``, ``sigma``
  the noise (as below) of the whole recording's force: an InputError, as is a force that peaks before frame 4
  (no loading ramp: the stiffness fit needs 5 frames).
- **Noise and baseline**: the pre-contact candidates are the leading frames up to the first one whose
  force exceeds the lowest force by 10 % of the force range. The baseline ``F0`` is their median
  force; the noise ``sigma`` is 1.4826 x the median absolute deviation of their force's second
  differences / sqrt(6) (a ramp's second differences are zero, so loading frames among the
  candidates do not inflate it). The contact threshold is ``max(5 sigma, 0.1 N)``.
- **Contact**: the last frame before the force's top whose force is within the threshold of the
  baseline; after it the force stays out of the noise. The frames before it are the **approach**
  when the probe travelled more than 0.5 mm along its axis during them with the force within the
  threshold of the baseline throughout; the probe displacement is then re-zeroed at the contact
  frame. Otherwise the palpation starts in contact: contact is the first frame and the displacement
  keeps its recorded zero (a frame or two at the noise level in contact are part of the ramp).
- **Top**: the frames from the first one whose force comes within ``band`` of the highest force
  (``band`` = 5 % of the force range from the baseline, at least the contact threshold) to the last
  one that is within ``band`` of it or within 5 % of the displacement range of the deepest
  displacement (a position-controlled hold relaxes the force, not the displacement).
- **Hold**: the top is a hold when it has at least 3 frames and its force rises by less than half
  the loading ramp's rate (N per frame, least squares); the **loading** ramp then ends at the first
  top frame. Otherwise the top is the end of the ramp: loading runs to its last frame.
- **Unloading**: every frame after the top.

The method is fitted on the loading ramp from contact (:meth:`PalpationPhases.loading_recording`). A
palpation that is a loading ramp from contact keeps every frame and its displacement, so it is fitted
exactly as recorded.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError
from ..recording import Recording

__all__ = ["PalpationPhases", "detect_phases"]

_CANDIDATE_FRACTION = 0.10  # pre-contact candidates: force below the lowest + this share of the force range
_NOISE_SIGMAS = 5.0  # contact threshold in noise standard deviations ...
_NO_CONTACT_SIGMAS = 8.0  # a force range within this many (or the minimum threshold): no contact
_MIN_THRESHOLD_N = 0.1  # ... and at least this, N
_MIN_APPROACH_MM = 0.5  # the probe travels more than this at the noise level: an approach, mm
_TOP_FRACTION = 0.05  # the top: within this share of the force (or displacement) range of its highest value
_MIN_HOLD_FRAMES = 3
_MIN_LOADING_FRAMES = 5  # the stiffness fit's cubic needs 5 samples (usdeform.fitting.fit_stiffness)
_MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class PalpationPhases:
    """Where one palpation's phases are, as half-open frame ranges ``(start, stop)`` (empty: start == stop).

    Attributes
    ----------
    name : str
        The recording (e.g. its file), for messages.
    n_frames : int
        Frames of the recording.
    approach, loading, hold, unloading : tuple of int
        The phases' frame ranges, in this order, together covering every frame.
    baseline_force_n, noise_n, contact_threshold_n : float
        The pre-contact force, its noise (standard deviation) and the contact threshold above the baseline, N.
    displacement_zero_mm : float
        The recorded probe displacement at contact, subtracted from the loading ramp's (0 when the
        palpation starts in contact), mm.
    """

    name: str
    n_frames: int
    approach: tuple[int, int]
    loading: tuple[int, int]
    hold: tuple[int, int]
    unloading: tuple[int, int]
    baseline_force_n: float
    noise_n: float
    contact_threshold_n: float
    displacement_zero_mm: float

    @property
    def contact_frame(self) -> int:
        """The first frame of the loading ramp (index in the recording)."""
        return self.loading[0]

    @property
    def is_loading_ramp(self) -> bool:
        """True when every frame is on the loading ramp from contact (fitted as recorded)."""
        return self.loading == (0, self.n_frames)

    def loading_recording(self, recording: Recording) -> Recording:
        """The loading ramp's frames with the probe displacement counted from contact; ``recording``
        itself when it is a loading ramp from contact."""
        if self.is_loading_ramp:
            return recording
        if len(recording) != self.n_frames or recording.probe_displacement is None:
            raise InputError(f"{self.name}: not the recording whose phases these are ({self.n_frames} frames)")
        ramp = recording.select(slice(*self.loading))
        assert ramp.probe_displacement is not None  # checked above
        return dataclasses.replace(ramp, probe_displacement=ramp.probe_displacement - self.displacement_zero_mm)

    def summary(self) -> str:
        """One line: which frames are which phase and which are fitted."""
        phases = ", ".join(
            f"{label} {_frames(span)}"
            for label, span in (
                ("approach", self.approach),
                ("loading", self.loading),
                ("hold", self.hold),
                ("unloading", self.unloading),
            )
            if span[1] > span[0]
        )
        zero = f"; probe displacement re-zeroed there ({self.displacement_zero_mm:.3g} mm recorded)"
        contact = (
            f"the force leaves the baseline {self.baseline_force_n:.3g} N by more than "
            f"{self.contact_threshold_n:.3g} N after it{zero}"
            if self.approach[1] > self.approach[0]
            else "the palpation starts in contact"
        )
        return (
            f"{phases} of {self.n_frames}; fitted on the loading ramp (frames {_frames(self.loading)}) from "
            f"contact at frame {self.contact_frame} ({contact})"
        )

    def to_json(self) -> dict[str, Any]:
        """The phases for a model file's provenance or a report: frame ranges ``[start, stop)``, N, mm."""
        return {
            "name": self.name,
            "n_frames": self.n_frames,
            "contact_frame": self.contact_frame,
            "fitted_frames": list(self.loading),
            **{label: list(getattr(self, label)) for label in ("approach", "loading", "hold", "unloading")},
            "baseline_force_n": self.baseline_force_n,
            "noise_n": self.noise_n,
            "contact_threshold_n": self.contact_threshold_n,
            "displacement_zero_mm": self.displacement_zero_mm,
        }


def _frames(span: tuple[int, int]) -> str:
    """``start-last`` of a half-open frame range (``start`` alone for one frame)."""
    return str(span[0]) if span[1] - span[0] == 1 else f"{span[0]}-{span[1] - 1}"


def _noise_n(force: np.ndarray) -> float:
    """Robust standard deviation of white noise on a locally linear ``force`` (N) from its second
    differences; 0 for fewer than 5 samples."""
    if force.size < 5:
        return 0.0
    second = np.diff(force, 2)
    return float(_MAD_TO_SIGMA * np.median(np.abs(second - np.median(second))) / np.sqrt(6.0))


def _rate(force: np.ndarray) -> float:
    """Least-squares slope of ``force`` against frame index, N per frame."""
    return float(np.polyfit(np.arange(force.size, dtype=np.float64), force, 1)[0])


def detect_phases(recording: Recording, name: str = "palpation") -> PalpationPhases:
    """Approach, loading, hold and unloading of a palpation, by the rules of the module docstring.

    Parameters
    ----------
    recording : Recording
        The palpation, with per-frame ContactForce (N) and ProbeDisplacement (mm).
    name : str
        The recording (e.g. its file), named in errors and in the result.

    Returns
    -------
    PalpationPhases

    Raises
    ------
    InputError
        Force or displacement not recorded, no contact (the force never leaves the noise) or no
        loading ramp (fewer than 5 frames from contact to the top).
    """
    force, displacement = recording.force, recording.probe_displacement
    if force is None or displacement is None:
        missing = " and ".join(
            field for field, values in (("ContactForce", force), ("ProbeDisplacement", displacement)) if values is None
        )
        raise InputError(f"{name}: a palpation needs per-frame {missing}, which the recording does not have")
    n_frames = len(force)
    recording_threshold = max(_NO_CONTACT_SIGMAS * _noise_n(force), _MIN_THRESHOLD_N)
    if np.ptp(force) <= recording_threshold:
        raise InputError(
            f"{name}: no contact: the force never rises out of the sensor's noise (it spans {np.ptp(force):.3g} N, "
            f"{force.min():.3g}-{force.max():.3g} N; noise threshold {recording_threshold:.3g} N)"
        )
    peak = int(np.argmax(force))
    if peak + 1 < _MIN_LOADING_FRAMES:
        raise InputError(
            f"{name}: no loading ramp: the force is highest at frame {peak} ({force[peak]:.3g} N); the stiffness "
            f"fit needs at least {_MIN_LOADING_FRAMES} frames of rising force from contact"
        )
    lowest = float(force[: peak + 1].min())
    candidates = force[: int(np.argmax(force[: peak + 1] > lowest + _CANDIDATE_FRACTION * (force[peak] - lowest)))]
    baseline = float(np.median(candidates)) if candidates.size else float(force[0])
    noise = _noise_n(candidates)
    threshold = max(_NOISE_SIGMAS * noise, _MIN_THRESHOLD_N)
    at_noise = np.flatnonzero(force[:peak] <= baseline + threshold)
    contact, zero = 0, 0.0
    if at_noise.size:
        last_at_noise = int(at_noise[-1])
        before = slice(0, last_at_noise + 1)
        travel = float(displacement[last_at_noise] - displacement[before].min())
        if travel > _MIN_APPROACH_MM and np.all(np.abs(force[before] - baseline) <= threshold):
            contact, zero = last_at_noise, float(displacement[last_at_noise])

    band = max(_TOP_FRACTION * (force[peak] - baseline), threshold)
    after = displacement[contact:]
    in_top = (force[contact:] >= force[peak] - band) | (after >= after.max() - _TOP_FRACTION * np.ptp(after))
    top_start = contact + int(np.argmax(force[contact:] >= force[peak] - band))
    top_stop = contact + int(np.flatnonzero(in_top)[-1]) + 1
    top_frames = top_stop - top_start
    is_hold = (
        top_frames >= _MIN_HOLD_FRAMES
        and (
            top_start == contact  # at the top from contact on: no ramp at all
            or _rate(force[top_start:top_stop]) < 0.5 * _rate(force[contact : top_start + 1])
        )
    )
    loading_stop = top_start if is_hold else top_stop
    if loading_stop - contact < _MIN_LOADING_FRAMES:
        raise InputError(
            f"{name}: no loading ramp: {loading_stop - contact} frame(s) from contact (frame {contact}) to the top "
            f"of the force (frame {top_start}, {force[top_start]:.3g} N); the stiffness fit needs at least "
            f"{_MIN_LOADING_FRAMES} frames of rising force"
        )
    return PalpationPhases(
        name=name,
        n_frames=n_frames,
        approach=(0, contact),
        loading=(contact, loading_stop),
        hold=(loading_stop, top_stop),
        unloading=(top_stop, n_frames),
        baseline_force_n=baseline,
        noise_n=noise,
        contact_threshold_n=threshold,
        displacement_zero_mm=zero,
    )
