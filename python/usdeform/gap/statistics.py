"""Statistics of the gap measures (:mod:`usdeform.gap.measures`): the time-block splits, the block bootstrap, the
gap statistic G and the tests of whether measures differ (Bonferroni over measures, chi-square over groups)."""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2, norm

from .measures import GROUPS
from .observations import Observation

__all__ = [
    "bootstrap_spread",
    "bootstrap_weights",
    "combined_z",
    "critical_z",
    "feature_values",
    "gap_statistic",
    "gap_tests",
    "significant_groups",
    "split_mask",
]

_BOOTSTRAP = 200


def split_mask(observation: Observation, split: int) -> np.ndarray:
    """(n,) bool: frames of the even time blocks (``split`` 0) or of the odd ones (1)."""
    return observation.block % 2 == split


def bootstrap_weights(
    observation: Observation, mask: np.ndarray, rng: np.random.Generator, n: int = _BOOTSTRAP
) -> np.ndarray:
    """(n, frames) weights: whole time blocks of the masked frames resampled with replacement."""
    blocks = np.unique(observation.block[mask])
    draws = rng.integers(0, len(blocks), size=(n, len(blocks)))
    counts = np.zeros((n, observation.block.max() + 1))
    for row in range(n):
        np.add.at(counts[row], blocks[draws[row]], 1.0)
    return counts[:, observation.block] * mask


def bootstrap_spread(values: np.ndarray) -> np.ndarray:
    """(F,) standard deviation over bootstrap rows (B, F) of each feature, 0 where fewer than two are finite."""
    finite = np.isfinite(values)
    count = finite.sum(axis=0)
    mean = np.where(finite, values, 0.0).sum(axis=0) / np.maximum(count, 1)
    variance = np.where(finite, (values - mean) ** 2, 0.0).sum(axis=0) / np.maximum(count - 1, 1)
    return np.where(count >= 2, np.sqrt(variance), 0.0)


def feature_values(sums: np.ndarray, counts: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(rows, F) feature values for weight rows (rows, n); NaN where a feature has no sample."""
    total = weights @ counts
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, (weights @ sums) / np.where(total > 0, total, 1.0), np.nan)


def gap_statistic(values: np.ndarray, uncertainty: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Gap G of feature rows (rows, F): the mean over groups of the mean squared z-score in the group.

    z = value / uncertainty; each group counts once whatever its number of features, so a group
    with many bins (the residual map) does not outweigh one number (timing). G is about 1 or less
    when the simulation explains the recording.
    """
    z2 = (values / uncertainty) ** 2
    finite = np.isfinite(z2)
    per_group = []
    for group in np.unique(groups):
        columns = groups == group
        count = finite[:, columns].sum(axis=1)
        total = np.where(finite[:, columns], z2[:, columns], 0.0).sum(axis=1)
        per_group.append(np.where(count > 0, total / np.maximum(count, 1), np.nan))
    stacked = np.stack(per_group, axis=1)
    present = np.isfinite(stacked)
    return np.where(present, stacked, 0.0).sum(axis=1) / np.maximum(present.sum(axis=1), 1)


def critical_z(n_features: int, alpha: float = 0.05) -> float:
    """Two-sided Bonferroni critical z-score for ``n_features`` simultaneous tests at level ``alpha``."""
    return float(norm.isf(alpha / (2 * max(n_features, 1))))


def significant_groups(z: np.ndarray, groups: np.ndarray, alpha: float = 0.05) -> dict[str, bool]:
    """Whether each group's measures jointly differ: sum of z^2 beyond the chi-square quantile
    ``1 - alpha / n_groups`` with as many degrees of freedom as the group has measures (z standard normal
    when the simulation explains the data; the floors make it conservative)."""
    present = [g for g in np.unique(groups) if np.isfinite(z[groups == g]).any()]
    result = {}
    for group in present:
        values = z[groups == group]
        values = values[np.isfinite(values)]
        result[GROUPS[group]] = bool(np.sum(values**2) > chi2.isf(alpha / len(present), len(values)))
    return result


def combined_z(z_by_split: tuple[np.ndarray, ...]) -> np.ndarray:
    """(F,) z-score of each measure over the splits (Stouffer: their sum over the square root of their number,
    over the splits where the measure has samples; NaN where none has)."""
    stacked = np.stack(z_by_split)
    finite = np.isfinite(stacked)
    count = finite.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, np.where(finite, stacked, 0.0).sum(axis=0) / np.sqrt(count), np.nan)


def gap_tests(z_by_split: tuple[np.ndarray, ...], groups: np.ndarray) -> tuple[bool, np.ndarray]:
    """Whether the measures differ, and which measure does; ``z_by_split``: (F,) z-scores of each split.

    The splits are disjoint sets of time blocks, so their z-scores combine into one (Stouffer: their sum over the
    square root of their number, over the splits where the measure has samples). The frames that carry a
    signature may fall mostly in one split (the few frames at first contact): the combined score keeps their
    evidence, which the held-out split alone dilutes. A measure differs beyond ``critical_z`` (Bonferroni over the
    measures), or its group jointly (chi-square, see :func:`significant_groups`), in which case its measures beyond
    |z| = 2 are the ones named.
    """
    z = combined_z(z_by_split)
    beyond = np.abs(np.nan_to_num(z)) > critical_z(len(groups))
    group_gap = significant_groups(z, groups)
    in_gap_group = np.array([group_gap.get(GROUPS[g], False) for g in groups])
    significant = beyond | (in_gap_group & (np.abs(np.nan_to_num(z)) > 2))
    return bool(beyond.any()) or any(group_gap.values()), significant
