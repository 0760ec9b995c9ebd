"""A lumen measured alike in the fit and in the correction: the vessel part's scale is a ratio of radii."""

from __future__ import annotations

import numpy as np
import pytest

from usdeform.correction import searched_lumen
from usdeform.fitting import fit_stiffness, measure_wall
from usdeform.metrics import segment_vessel
from usdeform.optical_flow import track_palpation
from usdeform.recording import Recording
from usdeform.reference.lumens import find_lumen, search_window
from usdeform.regression import VesselAnchor

CENTRE = (70.0, 50.0)  # x, y pixels
RADIUS_PX = 10.0


def _walled_lumen_frame(seed: int = 0) -> np.ndarray:
    """Speckle (level 110) over a darker deep half (level 40), an anechoic disc with a bright wall ring
    (3 px, level 230): the whole frame's median and the window's differ."""
    rng = np.random.default_rng(seed)
    rows, cols = 140, 160
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    level = np.where(y < 70, 110.0, 40.0)
    distance = np.hypot(x - CENTRE[0], y - CENTRE[1])
    level = np.where(distance < RADIUS_PX + 3.0, 230.0, level)
    level = np.where(distance < RADIUS_PX, 8.0, level)
    speckle = rng.rayleigh(scale=1.0, size=(rows, cols)) / np.sqrt(np.pi / 2)
    return np.clip(level * speckle, 0, 255).astype(np.uint8)


def test_the_searched_lumen_is_the_one_the_correction_search_finds_at_zero_force() -> None:
    frame = _walled_lumen_frame()
    whole = VesselAnchor.of_mask(segment_vessel(frame, CENTRE).mask)
    searched = searched_lumen(frame, whole)
    zero_field = lambda window: np.zeros((2, window[0].stop - window[0].start, window[1].stop - window[1].start))  # noqa: E731
    again = find_lumen(frame, zero_field, searched.centre_px, search_window(searched, frame.shape))
    assert again is not None
    assert again.radius_px == pytest.approx(searched.radius_px, abs=0.25)
    assert np.hypot(*np.subtract(again.centre_px, searched.centre_px)) < 0.25
    # the window's levels are not the whole frame's: the two radii differ on this frame
    assert abs(searched.radius_px - whole.radius_px) > 0.3


def test_the_fit_anchors_its_vessel_part_on_the_searched_lumen() -> None:
    n = 6
    frames = np.stack([_walled_lumen_frame(0)] * n)  # no deformation: only the lumen's measure matters
    force = np.linspace(0.2, 5.0, n)
    displacement = force / 2.0
    recording = Recording(
        frames=frames,
        timestamps=np.arange(n, dtype=np.float64),
        probe_to_base=np.repeat(np.eye(4)[np.newaxis], n, axis=0),
        pose_valid=np.ones(n, dtype=bool),
        image_to_probe=np.diag([0.25, 0.25, 1.0, 1.0]),
        force=force,
        probe_displacement=displacement,
    )
    tracked = track_palpation(frames, force)
    observations, _ = measure_wall(recording, tracked, fit_stiffness(force, displacement), seed_px=CENTRE)
    assert observations is not None and observations.vessel is not None
    whole = VesselAnchor.of_mask(segment_vessel(frames[0], CENTRE).mask)
    assert observations.vessel.radius_px == pytest.approx(searched_lumen(frames[0], whole).radius_px)
