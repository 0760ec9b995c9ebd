"""A reflector fixed in the world found in rendered frames, the ratio of its image motion to the probe's displacement
(assumed / true speed of sound), and the measure that carries it into the diagnosis."""

from types import SimpleNamespace

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.gap import measures
from usdeform.gap.measures import GROUPS
from usdeform.gap.reference_target import reference_sentence, reference_targets, sound_speed_m_s, track_reference
from usdeform.sim.imaging import (
    GriddedSolution,
    ImagingSettings,
    ProbeState,
    ScattererField,
    TissueAcoustics,
    render_frame,
    unit_complex_noise,
)
from usdeform.sim.mechanics import SectionSpec

SECTION = SectionSpec(vessel_center_x_mm=2.0, vessel_depth_mm=18.0, vessel_radius_mm=5.0)
SETTINGS = ImagingSettings(rows=160, cols=96, depth_mm=40.0)
LAMBDAS = np.concatenate([np.linspace(0.0, 8.0, 12), np.linspace(8.0, 0.0, 12)[1:]])


class _Compression:
    """Uniform axial compression of the section over its depth: u_z = lambda (1 - z / H)."""

    def __init__(self, section):
        self.section = section
        self.probe_displacement_mm = np.linspace(0.0, 10.0, 6)

    def displacement(self, points_mm, probe_displacement_mm):
        z = points_mm[:, 1]
        return np.column_stack([np.zeros(len(z)), probe_displacement_mm * (1 - z / self.section.depth_mm)])


def _frames(speed_m_s: float, reference_depth_mm: float | None) -> np.ndarray:
    acoustics = TissueAcoustics(sound_speed_m_s=speed_m_s, reference_depth_mm=reference_depth_mm)
    field = ScattererField(3, SETTINGS, acoustics)
    gridded = GriddedSolution(_Compression(SECTION), SECTION, SETTINGS)
    frames = []
    for index, lam in enumerate(LAMBDAS):
        noise = unit_complex_noise(np.random.default_rng(index), SETTINGS)
        probe = ProbeState(0.0, float(lam))
        frames.append(render_frame(field, SECTION, gridded.at(float(lam)), probe, SETTINGS, acoustics, noise))
    return np.stack(frames)


@pytest.mark.parametrize("speed", [1460.0, 1607.0])
def test_the_reflector_motion_gives_the_speed_of_sound_with_or_without_its_depth(speed):
    frames = _frames(speed, 30.0)
    for depth in (None, 30.0):
        track = track_reference(frames, LAMBDAS, SETTINGS.image_to_probe, "reference", depth)
        assert track.ratio == pytest.approx(1540.0 / speed, abs=0.004)
        assert abs(sound_speed_m_s(track.ratio) - speed) < 8.0
        assert track.ratio_error < 0.004
        assert track.world_depth_mm == pytest.approx(30.0 * 1540.0 / speed, abs=0.3)
        assert np.isfinite(track.depth_mm).all()


def test_frames_without_a_reflector_are_refused_naming_the_recording():
    with pytest.raises(InputError, match="plain: frames: no reflector fixed in the world"):
        track_reference(_frames(1540.0, None), LAMBDAS, SETTINGS.image_to_probe, "plain")


def test_the_reference_measure_is_the_recorded_minus_the_simulated_image_motion_per_mm():
    frames = _frames(1607.0, 30.0)
    track = track_reference(frames, LAMBDAS, SETTINGS.image_to_probe, "reference", 30.0)
    n = len(LAMBDAS)
    observation = SimpleNamespace(reference=track, probe_displacement_mm=LAMBDAS, n_frames=n)
    sums, counts = np.zeros((n, 1)), np.zeros((n, 1))
    for simulated_ratio in (1.0, 1540.0 / 1607.0):
        sums[:], counts[:] = 0.0, 0.0
        measures._reference_sums(observation, simulated_ratio * LAMBDAS, sums[:, 0], counts[:, 0])
        value = sums.sum() / counts.sum()
        assert value == pytest.approx(track.ratio - simulated_ratio, abs=1e-9)
    assert "reference_motion" in GROUPS


def _recording(frames: np.ndarray, metadata: dict[str, str] | None = None):
    from usdeform.recording import Recording

    n = len(frames)
    return Recording(
        frames=frames,
        timestamps=np.arange(n) * 0.2,
        probe_to_base=np.tile(np.eye(4), (n, 1, 1)),
        pose_valid=np.ones(n, bool),
        image_to_probe=SETTINGS.image_to_probe,
        force=0.2 + 1.5 * LAMBDAS,
        probe_displacement=LAMBDAS,
        metadata=metadata or {},
    )


@pytest.mark.slow
def test_observe_tracks_the_reflector_by_its_key_or_option_or_searches_when_asked():
    from usdeform.gap.observations import observe

    frames = _frames(1607.0, 30.0)
    observed = observe(_recording(frames, {"ReferenceTargetDepth": "30"}), "palpation.seq.nrrd")
    by_key = observed.reference
    by_option = observe(_recording(frames), "palpation.seq.nrrd", reference_depth_mm=30.0).reference
    found = observe(_recording(frames), "palpation.seq.nrrd", find_reference=True).reference
    assert by_key is not None and by_key.depth_given and found is not None and not found.depth_given
    assert by_option is not None and by_option.ratio == pytest.approx(by_key.ratio, abs=1e-12)
    assert by_key.ratio == pytest.approx(found.ratio, abs=1e-9)
    # the file name says nothing: a reference_target name without the key or the option is a plain palpation
    assert observe(_recording(frames), "/data/follow_up_01_reference_target.seq.nrrd").reference is None
    with pytest.raises(InputError, match="ReferenceTargetDepth: expected a positive depth"):
        observe(_recording(frames, {"ReferenceTargetDepth": "deep"}), "palpation.seq.nrrd")
    # a recording's own key naming a reflector that is not there: a plain palpation, and the reason kept
    plain = _frames(1540.0, None)
    missed = observe(_recording(plain, {"ReferenceTargetDepth": "30"}), "follow_up_01_reference_target.seq.nrrd")
    assert missed.reference is None and "no reflector fixed in the world found" in missed.reference_note
    with pytest.raises(InputError, match=r"palpation\.seq\.nrrd: frames: no reflector"):
        observe(_recording(plain), "palpation.seq.nrrd", reference_depth_mm=30.0)
    # the intensity bands and the tracked points stop above the reflector: it and what lies below it are no tissue
    assert np.isnan(observed.intensity[:, -1]).all() and np.isfinite(missed.intensity[:, -1]).all()
    tracked_mm = observed.row_depth_mm(observed.points_px[:, 1])
    assert tracked_mm.max() < by_key.world_depth_mm - 2.0 < missed.row_depth_mm(missed.points_px[:, 1]).max()
    reported = reference_targets([observed, missed])
    assert reported[0]["found"] and reported[0]["sound_speed_m_s"] == pytest.approx(1607.0, abs=10.0)
    assert not reported[1]["found"] and "follow_up_01_reference_target" in reference_sentence(reported)


@pytest.mark.parametrize("error_m_s", [-70.0, 60.0])
def test_the_follow_up_simulators_reference_target_gives_back_its_sound_speed(gap_phantom, error_m_s):
    """The simulator's reference_target recording: the phantom's base under bright deep tissue, the black below it
    (the band is not brighter than the median row by half, as a contrast test on grey levels alone would ask)."""
    from usdeform.gap.follow_up import FollowUpRecording
    from usdeform.gap.follow_up_sim import FollowUpSettings
    from usdeform.sim import SoundSpeedMismatch
    from usdeform.sim.reference_recordings import simulate_reference_target

    entry = FollowUpRecording(
        "follow_up_01_reference_target", "reference_target", 20.0, 12.0, 2.0, 0.0, 0.0, None, None, [], ""
    )
    settings = FollowUpSettings(frames_per_s=12.0, rows=192, cols=64, seed=5)
    recording = simulate_reference_target(entry, gap_phantom, [SoundSpeedMismatch(error_m_s)], settings, 5)
    depth = float(recording.metadata["ReferenceTargetDepth"])
    track = track_reference(recording.frames, recording.probe_displacement, recording.image_to_probe, "ref", depth)
    speed = sound_speed_m_s(track.ratio)
    speed_error = 1540.0 / track.ratio**2 * track.ratio_error
    assert abs(speed - (1540.0 + error_m_s)) < 3 * speed_error + 5.0
    assert speed_error < 10.0
