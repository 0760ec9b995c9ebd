"""Named gap measures between a recording and a simulation of it, with bootstrap uncertainties.

Every measure is the mean, over its samples, of a residual (recorded minus simulated):

* ``force_residual_n``: contact force, per phase (loading, holding, unloading) and force tercile;
* ``displacement_axial_px`` / ``displacement_lateral_px``: optical-flow displacement of the tracked
  points from the reference frame, per depth band (4), lateral band (3) and force tercile (3): the
  residual map;
* ``image_motion_px``: mean axial image motion per phase;
* ``image_delay_s``: the delay of the image motion against the simulation, which follows the robot's lambda:
  the least-squares tau in r = -tau v (r the displacement residual, v the simulated image velocity) taken on the
  differences of each unloading frame and the loading frame of the same lambda, over every tracked point. A
  delay makes the image lag on loading and lead on unloading; the difference cancels whatever rate-independent
  (elastic) misfit the two frames share, and weighting by v makes the fast-moving points count most;
* ``speckle_correlation``: motion-compensated speckle correlation of each frame with the previous one and
  with the earlier frames 1, 2 and 4 mm of lambda away, per phase;
* ``speckle_correlation_roughness``: how much each frame's correlation jumps against its neighbours in time,
  the mean of |d| with d = c_i - (c_{i-1} + c_{i+1}) / 2 (same partner separation), per separation. Strain,
  noise and a steady elevation drift change the correlation smoothly from frame to frame; a random elevation
  offset of every frame (probe micro-slip, vibration) makes each pair's correlation a fresh draw;
* ``vessel_area_ratio``: lumen area relative to the reference frame, per force tercile;
* ``force_near_contact_n``: contact force of the frames near contact (lambda below 20 % of its largest
  value, or the 8 lowest-lambda frames of the phase when fewer), loading and unloading apart. An ideal
  sensor reads zero at zero indentation, and the elastic curve (a non-negative cubic through the origin)
  cannot take up an offset there, so a sensor bias, a missing weight compensation or drift shows here
  undiluted by the stiffer frames;
* ``contact_slip_px``: outward lateral displacement (away from the probe axis) of the shallowest row
  of tracked points minus that of the points two grid rows deeper, per force tercile. Tissue stuck to
  the probe face does not move laterally under it, tissue sliding on gel spreads outwards; the
  difference to the rows beneath cancels the lateral bulging that the material law changes;
* ``displacement_scale_axial`` / ``displacement_scale_lateral``: the relative scale of the recorded
  to the simulated displacement field, sum(residual * simulated) / sum(simulated^2) over every tracked
  point (the least-squares slope minus one), per force tercile. One number pooled over the whole image:
  a uniform axial scale with the lateral one unchanged is what a wrong speed of sound does (depths
  displayed scaled); a scale of both that grows with force is a lambda that overstates the
  indentation (a compliant holder). Depth-dependent misfits (layers) show in it too, weighted by the
  squared displacement; the residual map tells them apart.

Uncertainty: the bootstrap over time blocks of about 0.3 s (whole blocks keep the serial
correlation of force noise and tracking errors), combined with a stated model-discrepancy floor
(``floor``) for differences every simulator has from any recording and that are no effect:
0.05 N + 0.5 % of the largest force (sensor non-linearity and noise; the material law is absorbed by the
elastic cubic); 0.2 px + 2 % of
the simulated displacement (Lucas-Kanade bias of 0.1-0.2 px, mesh convergence 1-2 %, geometry
snapping); 5 ms in the image delay (timestamps), combined with the delay that a 0.1 px difference between a
loading and an unloading frame of the same lambda would mimic at the simulated velocities (their tracking, and a
field that creeps a little on its own, which the library's force-only viscoelasticity leaves out); 0.01 in
correlation and in its roughness (about the mean |d| of independent 0.01 errors); 0.02 in area ratio. A measure
differs significantly when
|value| exceeds z_crit times its uncertainty, z_crit the two-sided 5 % Bonferroni level over all measures.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from .observations import CORRELATION_SEPARATIONS_MM, PHASES, Observation

__all__ = [
    "GROUPS",
    "FeatureLayout",
    "Prediction",
    "residual_sums",
]

GROUPS = (
    "force",
    "displacement",
    "image_motion",
    "timing",
    "speckle_correlation",
    "speckle_roughness",
    "vessel",
    "contact_force",
    "contact_slip",
    "displacement_scale",
    "reference_motion",
)
_DEPTH_BANDS = 4
_LATERAL_BANDS = 3
_FORCE_BINS = 3
_NEAR_CONTACT_FRACTION = 0.2  # frames with lambda below this fraction of its largest value are "near contact"
_NEAR_CONTACT_MIN_FRAMES = 8  # ... or at least this many lowest-lambda frames per phase (frames of both splits)
_SLIP_ROWS_BELOW = 2  # grid rows between the shallowest row and the reference row of the slip measure
_SCALE_FLOOR = 0.02  # displacement-scale floor: mesh convergence and material law under imposed lambda
_DELAY_TIMESTAMP_FLOOR_S = 0.005  # frame and pose timestamps, each good to a few milliseconds
_DELAY_TRACKING_FLOOR_PX = 0.1  # difference between a loading and an unloading frame of the same lambda
_ROUGHNESS_FLOOR = 0.01  # mean |d| of independent 0.01 correlation errors: sqrt(1.5 * 2 / pi) * 0.01
#: the reflector's image motion per mm of probe displacement: a probe axis within 5 degrees of the reflector's normal
#: (1 - cos 5 deg = 0.4 %) and the robot's displacement good to 0.1 %; 0.005 is 8 m/s of sound speed
_REFERENCE_FLOOR = 0.005


@dataclass
class Prediction:
    """The simulated side of the measures for one observation (n frames, N points)."""

    force_n: np.ndarray  # (n,)
    displacement_px: np.ndarray  # (n, N, 2)
    correlation: np.ndarray  # (lags, n)
    vessel_area_ratio: np.ndarray | None  # (n,)
    correlation_roughness: np.ndarray | None = None  # (lags, n) expected |d| (see correlation_roughness); None: 0
    # the displacement side of residual sums already computed (see residual_sums): (observation, layout,
    # displacement, sums, counts), newest last; models.predict shares one list among the predictions of a geometry
    displacement_sums: list = field(default_factory=list, repr=False, compare=False)
    # (n,) how far up the image a reflector fixed in the world moves, mm (the probe displacement of the tissue each
    # frame shows times assumed / true sound speed); None without a reference target
    reference_motion_mm: np.ndarray | None = None


@dataclass
class FeatureLayout:
    """Which feature every sample of an observation belongs to, and each feature's description and floor."""

    names: list[str]
    groups: np.ndarray  # (F,) index into GROUPS
    regions: list[str]
    force_ranges: list[tuple[float, float] | None]
    phases: list[str]
    floors: np.ndarray  # (F,)
    force_feature: np.ndarray  # (n,)
    loading_match: np.ndarray  # (n,) for unloading frames: the loading frame of nearest lambda; -1 elsewhere
    hold_start: np.ndarray  # first frames of the hold (the relaxation baseline)
    force_pair_offset: int
    point_bin: np.ndarray  # (N,) depth x lateral bin of each point
    force_bin: np.ndarray  # (n,)
    displacement_offset: int
    motion_offset: int
    correlation_offset: int
    roughness_offset: int
    vessel_offset: int | None
    contact_force_offset: int
    slip_offset: int
    scale_offset: int
    slip_rows: np.ndarray  # (N,) outward sign on the shallowest tracked row, minus it on the reference row, 0 else
    reference_offset: int | None = None  # the reference target's image-motion measure, when the recording has one

    @property
    def size(self) -> int:
        return len(self.names)


def _terciles(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    edges = np.quantile(values, np.linspace(0, 1, _FORCE_BINS + 1))
    return np.clip(np.searchsorted(edges, values, side="right") - 1, 0, _FORCE_BINS - 1), edges


def build_layout(observation: Observation, ideal: Prediction) -> FeatureLayout:
    """The features of one observation; floors scale with the ideal simulation's displacement."""
    force_bin, edges = _terciles(observation.force_n)
    force_range = [(float(edges[q]), float(edges[q + 1])) for q in range(_FORCE_BINS)]
    names, groups, regions, ranges, phases, floors = [], [], [], [], [], []
    max_force = float(np.max(np.abs(observation.force_n)))

    def add(name, group, region, force_range_n, phase, floor):
        names.append(name)
        groups.append(GROUPS.index(group))
        regions.append(region)
        ranges.append(force_range_n)
        phases.append(phase)
        floors.append(floor)

    for phase in PHASES:
        for q in range(_FORCE_BINS):
            add("force_residual_n", "force", "probe", force_range[q], phase, 0.05 + 0.005 * max_force)
    force_feature = observation.phase * _FORCE_BINS + force_bin
    force_pair_offset = len(names)
    add("force_hysteresis_n", "force", "probe", None, "unloading", 0.05)
    add("force_relaxation_n", "force", "probe", None, "holding", 0.05)
    lam = observation.probe_displacement_mm
    loading = np.flatnonzero(observation.phase == 0)
    loading_match = np.full(observation.n_frames, -1)
    if len(loading):
        for index in np.flatnonzero(observation.phase == 2):
            loading_match[index] = loading[np.argmin(np.abs(lam[loading] - lam[index]))]
    hold_start = np.flatnonzero(observation.phase == 1)[:3]

    rows, cols = observation.frame_shape
    points = observation.points_px
    depth_band = np.clip((points[:, 1] / rows * _DEPTH_BANDS).astype(int), 0, _DEPTH_BANDS - 1)
    lateral_band = np.clip((points[:, 0] / cols * _LATERAL_BANDS).astype(int), 0, _LATERAL_BANDS - 1)
    point_bin = depth_band * _LATERAL_BANDS + lateral_band
    displacement_offset = len(names)
    depth_mm = observation.image_to_probe[2, 1] * rows
    width_mm = abs(observation.image_to_probe[0, 0]) * cols
    mean_ideal = _binned_mean_abs(ideal.displacement_px, point_bin, force_bin)
    for b in range(_DEPTH_BANDS * _LATERAL_BANDS):
        d, lat = divmod(b, _LATERAL_BANDS)
        region = (
            f"depth {d * depth_mm / _DEPTH_BANDS:.0f}-{(d + 1) * depth_mm / _DEPTH_BANDS:.0f} mm, "
            f"lateral {(lat / _LATERAL_BANDS - 0.5) * width_mm:.0f} to "
            f"{((lat + 1) / _LATERAL_BANDS - 0.5) * width_mm:.0f} mm"
        )
        for q in range(_FORCE_BINS):
            for c, component in enumerate(("lateral", "axial")):
                add(
                    f"displacement_{component}_px",
                    "displacement",
                    region,
                    force_range[q],
                    "all",
                    0.2 + 0.02 * mean_ideal[b, q, c],
                )
    motion_offset = len(names)
    motion_scale = np.nanmean(np.abs(ideal.displacement_px[..., 1]))
    for phase in PHASES:
        add("image_motion_px", "image_motion", "whole image", None, phase, 0.2 + 0.02 * float(motion_scale))
    add("image_delay_s", "timing", "whole image", None, "unloading", _delay_floor_s(observation, loading_match, ideal))
    correlation_offset = len(names)
    for separation in CORRELATION_SEPARATIONS_MM:
        name = f"speckle_correlation_{separation:g}mm" if separation else "speckle_correlation_previous_frame"
        for phase in PHASES:
            add(name, "speckle_correlation", "whole image", None, phase, 0.01)
    roughness_offset = len(names)
    for separation in CORRELATION_SEPARATIONS_MM:
        name = "speckle_correlation_roughness" + (f"_{separation:g}mm" if separation else "_previous_frame")
        add(name, "speckle_roughness", "whole image", None, "all", _ROUGHNESS_FLOOR)
    vessel_offset = None
    if ideal.vessel_area_ratio is not None and np.isfinite(observation.vessel_area_mm2).sum() >= 3:
        vessel_offset = len(names)
        for q in range(_FORCE_BINS):
            add("vessel_area_ratio", "vessel", "vessel lumen", force_range[q], "all", 0.02)
    contact_force_offset = len(names)
    for phase in ("loading", "unloading"):
        add("force_near_contact_n", "contact_force", "probe", None, phase, 0.05 + 0.005 * max_force)
    slip_offset = len(names)
    slip_rows = _slip_rows(observation)
    ideal_valid = np.isfinite(ideal.displacement_px).all(axis=2)
    ideal_slip = np.abs(contact_slip(np.nan_to_num(ideal.displacement_px[..., 0]), ideal_valid, slip_rows)[0])
    for q in range(_FORCE_BINS):
        in_bin = force_bin == q
        scale = float(np.mean(ideal_slip[in_bin])) if in_bin.any() else 0.0
        add("contact_slip_px", "contact_slip", "shallowest tracked rows", force_range[q], "all", 0.1 + 0.05 * scale)
    scale_offset = len(names)
    for q in range(_FORCE_BINS):
        in_bin = (force_bin == q) & (np.arange(observation.n_frames) != observation.reference_index)
        for c, component in enumerate(("lateral", "axial")):
            simulated = ideal.displacement_px[in_bin, :, c]
            rms = float(np.sqrt(np.nanmean(simulated**2))) if np.isfinite(simulated).any() else 0.0
            # 2 % (mesh, material law) plus the 0.2 px tracking bias relative to the bin's displacement
            floor = _SCALE_FLOOR + 0.2 / max(rms, 0.2)
            add(
                f"displacement_scale_{component}",
                "displacement_scale",
                "all tracked points",
                force_range[q],
                "all",
                floor,
            )
    reference_offset = None
    if observation.reference is not None:
        reference_offset = len(names)
        region = f"reflector fixed in the world, {observation.reference.world_depth_mm:.1f} mm deep as displayed"
        add("reference_motion_ratio", "reference_motion", region, None, "all", _REFERENCE_FLOOR)
    return FeatureLayout(
        names=names,
        groups=np.array(groups),
        regions=regions,
        force_ranges=ranges,
        phases=phases,
        floors=np.array(floors),
        force_feature=force_feature,
        loading_match=loading_match,
        hold_start=hold_start,
        force_pair_offset=force_pair_offset,
        point_bin=point_bin,
        force_bin=force_bin,
        displacement_offset=displacement_offset,
        motion_offset=motion_offset,
        correlation_offset=correlation_offset,
        roughness_offset=roughness_offset,
        vessel_offset=vessel_offset,
        contact_force_offset=contact_force_offset,
        slip_offset=slip_offset,
        scale_offset=scale_offset,
        slip_rows=slip_rows,
        reference_offset=reference_offset,
    )


def _slip_rows(observation: Observation) -> np.ndarray:
    """(N,) outward sign (+1 right of the probe axis, -1 left) of the points on the shallowest tracked row,
    minus that sign on the row ``_SLIP_ROWS_BELOW`` grid rows deeper, 0 elsewhere (all 0 without such rows)."""
    points = observation.points_px
    signs = np.zeros(len(points))
    row_of_point = _grid_rows(points[:, 1])
    if row_of_point.max(initial=-1) < _SLIP_ROWS_BELOW:
        return signs
    to_probe = observation.image_to_probe
    outward = np.sign(to_probe[0, 0] * points[:, 0] + to_probe[0, 3])
    for row, factor in ((0, 1.0), (_SLIP_ROWS_BELOW, -1.0)):
        on_row = (row_of_point == row) & (outward != 0)
        if not on_row.any():
            return np.zeros(len(points))
        signs[on_row] = factor * outward[on_row]
    return signs


def _grid_rows(rows_px: np.ndarray) -> np.ndarray:
    """(N,) index of the tracking-grid row of each point, shallowest 0: a new row starts where the sorted
    depths jump by more than 2 px (grid rows are several pixels apart; a row is no longer exactly level
    once the tracks are referenced to another frame than the tracker's)."""
    order = np.argsort(rows_px)
    labels = np.empty(len(rows_px), dtype=np.int64)
    labels[order] = np.cumsum(np.concatenate([[0], np.diff(rows_px[order]) > 2.0]))
    return labels


def _slip(lateral_px: np.ndarray, valid: np.ndarray, slip_rows: np.ndarray, top: bool) -> tuple[np.ndarray, np.ndarray]:
    """(n,) mean outward lateral displacement of one slip row per frame, and whether the row has a track."""
    on_row = slip_rows > 0 if top else slip_rows < 0
    row_valid = valid[:, on_row]
    signed = np.where(row_valid, lateral_px[:, on_row] * slip_rows[on_row], 0.0)
    kept = row_valid.sum(axis=1)
    return signed.sum(axis=1) / np.maximum(kept, 1), kept > 0


def contact_slip(lateral_px: np.ndarray, valid: np.ndarray, slip_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n,) outward slip of the shallowest row relative to the reference row (px), and where it is defined."""
    if not slip_rows.any():
        return np.zeros(len(lateral_px)), np.zeros(len(lateral_px), dtype=bool)
    top, top_ok = _slip(lateral_px, valid, slip_rows, top=True)
    below, below_ok = _slip(lateral_px, valid, slip_rows, top=False)
    # the reference row's signs carry the minus already: top - below = top + (signed reference row)
    return top + below, top_ok & below_ok


def correlation_roughness(correlation: np.ndarray) -> np.ndarray:
    """(..., n) |d| with d_i = c_i - (c_{i-1} + c_{i+1}) / 2 along the last axis (frames); NaN where a neighbour
    or the frame has no correlation. A trend linear in time cancels; independent draws per frame do not. The
    absolute value, not the square: a few large jumps do not dominate the bootstrap."""
    result = np.full(correlation.shape, np.nan)
    result[..., 1:-1] = np.abs(correlation[..., 1:-1] - 0.5 * (correlation[..., :-2] + correlation[..., 2:]))
    return result


def _matched_velocity_difference(
    observation: Observation, loading_match: np.ndarray, displacement_px: np.ndarray
) -> np.ndarray:
    """(unloading frames, N, 2) image velocity (px/s) of each unloading frame's matched loading frame minus its
    own, from ``displacement_px`` (n, N, 2) by central differences in time."""
    unloading = np.flatnonzero(loading_match >= 0)
    with np.errstate(invalid="ignore", divide="ignore"):  # repeated timestamps give non-finite velocities: skipped
        velocity = np.gradient(displacement_px, observation.time_s, axis=0)
    return velocity[loading_match[unloading]] - velocity[unloading]


def _delay_floor_s(observation: Observation, loading_match: np.ndarray, ideal: Prediction) -> float:
    """Floor of ``image_delay_s``: the timestamps' precision, and the delay that a loading-unloading tracking bias
    of ``_DELAY_TRACKING_FLOOR_PX`` mimics at the simulated velocity differences (rms over points and frames)."""
    difference = _matched_velocity_difference(observation, loading_match, ideal.displacement_px)
    squared = np.sum(difference**2, axis=-1)
    squared = squared[np.isfinite(squared)]
    if not squared.size or not squared.mean() > 0:
        return _DELAY_TIMESTAMP_FLOOR_S
    return float(np.hypot(_DELAY_TIMESTAMP_FLOOR_S, _DELAY_TRACKING_FLOOR_PX / np.sqrt(squared.mean())))


def _binned_mean_abs(displacement: np.ndarray, point_bin: np.ndarray, force_bin: np.ndarray) -> np.ndarray:
    """(bins, force bins, 2) mean |displacement| per spatial and force bin."""
    result = np.zeros((_DEPTH_BANDS * _LATERAL_BANDS, _FORCE_BINS, 2))
    for b in range(result.shape[0]):
        for q in range(_FORCE_BINS):
            values = np.abs(displacement[force_bin == q][:, point_bin == b])
            if values.size and np.isfinite(values).any():
                result[b, q] = np.nanmean(values.reshape(-1, 2), axis=0)
    return result


def _finite_pair(values: np.ndarray) -> np.ndarray:
    """(...) whether both components of ``values`` (..., 2) are finite."""
    return np.isfinite(values[..., 0]) & np.isfinite(values[..., 1])


def _bin_sums(values: np.ndarray, point_bin: np.ndarray) -> np.ndarray:
    """(..., bins) sums of ``values`` (..., N) over the points of each spatial bin (``point_bin`` (N,)).

    Each bin is a slice of the points sorted by bin (stable, so in their own order) summed along the last axis:
    the same sum, to the last bit, as ``values[..., point_bin == b].sum(axis=-1)``.
    """
    order = np.argsort(point_bin, kind="stable")
    edges = np.searchsorted(point_bin[order], np.arange(_DEPTH_BANDS * _LATERAL_BANDS + 1))
    grouped = values[..., order]
    return np.stack([grouped[..., start:stop].sum(axis=-1) for start, stop in itertools.pairwise(edges)], axis=-1)


_DISPLACEMENT_SUMS_ENTRIES = 4  # per geometry; a diagnosis measures one against a single observation and layout


def _displacement_sums(
    observation: Observation, layout: FeatureLayout, prediction: Prediction
) -> tuple[np.ndarray, np.ndarray]:
    """(n, F) residual sums and sample counts of the features of the tracked displacement (the residual map, image
    motion and delay, contact slip and displacement scale), 0 in the other features.

    Those of a read-only simulated displacement are remembered in ``prediction.displacement_sums`` (returned as
    copies), which models.predict shares among the predictions of one geometry: a fit of an effect that leaves the
    displacement as it was predicts the same array at every evaluation.
    """
    displacement_px = prediction.displacement_px
    remembered = prediction.displacement_sums
    for entry in remembered:
        if entry[0] is observation and entry[1] is layout and entry[2] is displacement_px:
            return entry[3].copy(), entry[4].copy()
    n = observation.n_frames
    sums = np.zeros((n, layout.size))
    counts = np.zeros((n, layout.size))
    frames = np.arange(n)
    unloading = np.flatnonzero(layout.loading_match >= 0)
    matched = layout.loading_match[unloading]
    residual = observation.displacement_px - displacement_px  # (n, N, 2)
    valid = _finite_pair(residual)
    valid[observation.reference_index] = False
    tracked = np.where(valid[..., None], residual, 0.0)  # (n, N, 2), 0 where a point has no residual
    # (3, n, bins): lateral and axial residual sums and point counts per frame and spatial bin
    binned = _bin_sums(np.concatenate([np.moveaxis(tracked, 2, 0), valid[None]]), layout.point_bin)
    bins = np.arange(binned.shape[2])
    column = layout.displacement_offset + 2 * (bins * _FORCE_BINS + layout.force_bin[:, None])  # (n, bins), lateral
    for c in (0, 1):
        sums[frames[:, None], column + c] = binned[c]
        counts[frames[:, None], column + c] = binned[2]
    kept = valid.sum(axis=1)
    motion = np.where(kept > 0, tracked[..., 1].sum(axis=1) / np.maximum(kept, 1), 0.0)
    sums[frames, layout.motion_offset + observation.phase] = motion
    counts[frames, layout.motion_offset + observation.phase] = (kept > 0).astype(float)
    velocity_difference = _matched_velocity_difference(observation, layout.loading_match, displacement_px)
    paired = valid[matched] & valid[unloading] & _finite_pair(velocity_difference)
    velocity_difference = np.where(paired[..., None], velocity_difference, 0.0)
    residual_difference = np.where(paired[..., None], residual[matched] - residual[unloading], 0.0)
    delay_column = layout.motion_offset + len(PHASES)
    sums[unloading, delay_column] = -(residual_difference * velocity_difference).sum(axis=(1, 2))
    counts[unloading, delay_column] = (velocity_difference**2).sum(axis=(1, 2))

    slip, slip_ok = contact_slip(residual[..., 0], valid, layout.slip_rows)
    slip_column = layout.slip_offset + layout.force_bin
    sums[frames[slip_ok], slip_column[slip_ok]] = slip[slip_ok]
    counts[frames[slip_ok], slip_column[slip_ok]] = 1.0

    simulated = np.where(valid[..., None], displacement_px, 0.0)  # finite wherever valid
    energy = np.einsum("ijc,ijc->ic", simulated, simulated)  # (n, 2)
    frame, component = np.nonzero(energy > 0)
    scale_column = layout.scale_offset + 2 * layout.force_bin[frame] + component
    sums[frame, scale_column] = np.einsum("ijc,ijc->ic", tracked, simulated)[frame, component]
    counts[frame, scale_column] = energy[frame, component]
    # remembered only for a read-only array that owns its data: the predictions' arrays, which no caller writes to
    if not displacement_px.flags.writeable and displacement_px.base is None:
        if len(remembered) >= _DISPLACEMENT_SUMS_ENTRIES:
            remembered.pop(0)
        remembered.append((observation, layout, displacement_px, sums.copy(), counts.copy()))
    return sums, counts


def _reference_sums(observation: Observation, motion_mm: np.ndarray, sums: np.ndarray, counts: np.ndarray) -> None:
    """Fill one measure's per-frame ``sums`` and ``counts`` (n,) so that their weighted ratio is the least-squares
    slope, against the probe displacement, of the recorded reflector's image motion minus ``motion_mm`` (the
    simulated): recorded minus simulated image motion per mm of probe displacement."""
    track = observation.reference
    assert track is not None
    ok = np.isfinite(track.depth_mm)
    lam = observation.probe_displacement_mm
    residual = -track.depth_mm - motion_mm
    centred_lam = lam - lam[ok].mean()
    sums[ok] = (residual[ok] - residual[ok].mean()) * centred_lam[ok]
    counts[ok] = centred_lam[ok] ** 2


def residual_sums(
    observation: Observation,
    layout: FeatureLayout,
    prediction: Prediction,
    observed_roughness: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame residual sums and sample counts of every feature, each (n, F).

    A feature's value over a set of frames with weights w is ``(w @ sums) / (w @ counts)``.
    ``observed_roughness``: (lags, n) the recorded side of the correlation roughness when the observation is a
    simulation's expectation (whose correlation is smooth); by default that of ``observation.correlation``.
    """
    sums, counts = _displacement_sums(observation, layout, prediction)
    frames = np.arange(observation.n_frames)
    force_residual = observation.force_n - prediction.force_n
    sums[frames, layout.force_feature] = force_residual
    counts[frames, layout.force_feature] = 1.0
    # Differences at matched lambda (loading minus unloading) and within the hold cancel whatever
    # elastic, rate-independent model error there is; they keep hysteresis, delay and relaxation.
    unloading = np.flatnonzero(layout.loading_match >= 0)
    matched = layout.loading_match[unloading]
    sums[unloading, layout.force_pair_offset] = force_residual[matched] - force_residual[unloading]
    counts[unloading, layout.force_pair_offset] = 1.0
    if len(layout.hold_start):
        holding = np.flatnonzero(observation.phase == 1)
        sums[holding, layout.force_pair_offset + 1] = force_residual[holding] - force_residual[layout.hold_start].mean()
        counts[holding, layout.force_pair_offset + 1] = 1.0

    lam = observation.probe_displacement_mm
    near = lam <= _NEAR_CONTACT_FRACTION * np.max(lam)
    for index, phase in ((0, 0), (1, 2)):
        chosen = near & (observation.phase == phase)
        if chosen.sum() < _NEAR_CONTACT_MIN_FRAMES:  # a fast ramp: the phase's lowest-lambda frames instead
            in_phase = np.flatnonzero(observation.phase == phase)
            chosen[in_phase[np.argsort(lam[in_phase])[:_NEAR_CONTACT_MIN_FRAMES]]] = True
        sums[chosen, layout.contact_force_offset + index] = force_residual[chosen]
        counts[chosen, layout.contact_force_offset + index] = 1.0

    difference = observation.correlation - prediction.correlation  # (lags, n)
    lag, frame = np.nonzero(np.isfinite(difference))
    correlation_column = layout.correlation_offset + lag * len(PHASES) + observation.phase[frame]
    sums[frame, correlation_column] = difference[lag, frame]
    counts[frame, correlation_column] = 1.0

    roughness = correlation_roughness(observation.correlation) if observed_roughness is None else observed_roughness
    if prediction.correlation_roughness is not None:
        roughness = roughness - prediction.correlation_roughness
    lag, frame = np.nonzero(np.isfinite(roughness))
    sums[frame, layout.roughness_offset + lag] = roughness[lag, frame]
    counts[frame, layout.roughness_offset + lag] = 1.0

    if layout.reference_offset is not None and prediction.reference_motion_mm is not None:
        _reference_sums(
            observation,
            prediction.reference_motion_mm,
            sums[:, layout.reference_offset],
            counts[:, layout.reference_offset],
        )
    if layout.vessel_offset is not None and prediction.vessel_area_ratio is not None:
        reference_area = observation.vessel_area_mm2[observation.reference_index]
        difference = observation.vessel_area_mm2 / reference_area - prediction.vessel_area_ratio
        ok = np.isfinite(difference)
        column = layout.vessel_offset + layout.force_bin
        sums[frames[ok], column[ok]] = difference[ok]
        counts[frames[ok], column[ok]] = 1.0
    return sums, counts
