"""Percentile-bootstrap confidence intervals for the evaluation's per-episode metrics.

numpy only (no scipy): resample the episodes with replacement ``resamples`` times, apply
the statistic to each resample, and take the ``(1 - confidence) / 2`` and
``(1 + confidence) / 2`` quantiles of those statistics. Seeded, so a table built from the
same per-episode numbers always prints the same intervals.

`paired_difference_ci` is for two controllers run on the SAME episodes (same start, target,
noise and parameter draw, as every evaluation here is): it bootstraps the per-episode
differences ``a_i - b_i``, which removes the episode-to-episode spread that both share.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

Stat = Callable[..., float | np.ndarray]

DEFAULT_RESAMPLES = 10_000
DEFAULT_CONFIDENCE = 0.95


def _as_sample(values: Sequence[float] | np.ndarray) -> np.ndarray:
    arr = np.asarray(values, dtype=float).ravel()
    if arr.size == 0:
        raise ValueError("need at least one value to bootstrap")
    if not np.all(np.isfinite(arr)):
        raise ValueError("values must be finite")
    return arr


def bootstrap_distribution(
    values: Sequence[float] | np.ndarray,
    stat: Stat = np.mean,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
) -> np.ndarray:
    """``stat`` of ``resamples`` resamples (with replacement) of ``values``."""
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    arr = _as_sample(values)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, arr.size, size=(resamples, arr.size))
    samples = arr[idx]
    try:
        out = np.asarray(stat(samples, axis=1), dtype=float)
    except TypeError:  # a statistic without an axis argument
        out = np.array([float(stat(row)) for row in samples])
    if out.shape != (resamples,):
        out = np.array([float(stat(row)) for row in samples])
    return out


def bootstrap_ci(
    values: Sequence[float] | np.ndarray,
    stat: Stat = np.mean,
    confidence: float = DEFAULT_CONFIDENCE,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile-bootstrap ``confidence`` interval (low, high) of ``stat`` of ``values``."""
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    dist = bootstrap_distribution(values, stat, resamples, seed)
    alpha = 1.0 - confidence
    low, high = np.quantile(dist, [alpha / 2.0, 1.0 - alpha / 2.0])
    return float(low), float(high)


def seed_episode_bootstrap(
    values: Sequence[Sequence[float]] | np.ndarray,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
    episodes: np.ndarray | None = None,
) -> np.ndarray:
    """Means of ``resamples`` two-level resamples of ``values`` (seeds x episodes): the
    training seeds with replacement, then the episodes with replacement. Both levels vary,
    so the spread counts run-to-run differences as well as episode ones.

    ``episodes`` ((resamples, n_episodes) indices) shares the episode draws between two
    calls: two configurations scored on the same episodes are then compared pairwise there,
    while their seeds (independent trainings) are drawn independently."""
    arr = np.asarray(values, dtype=float)
    if arr.ndim != 2 or arr.size == 0:
        raise ValueError(f"need a (seeds, episodes) array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("values must be finite")
    rng = np.random.default_rng(seed)
    n_seeds, n_episodes = arr.shape
    if episodes is None:
        episodes = rng.integers(0, n_episodes, size=(resamples, n_episodes))
    if episodes.shape[0] != resamples or episodes.max(initial=0) >= n_episodes:
        raise ValueError("episode draws do not match the resamples or the episodes")
    seeds = rng.integers(0, n_seeds, size=(resamples, n_seeds))
    out = np.empty(resamples)
    for r in range(resamples):
        out[r] = arr[seeds[r]][:, episodes[r]].mean()
    return out


def interval(dist: np.ndarray, confidence: float = DEFAULT_CONFIDENCE) -> tuple[float, float]:
    """The percentile interval of a bootstrap distribution."""
    alpha = 1.0 - confidence
    low, high = np.quantile(dist, [alpha / 2.0, 1.0 - alpha / 2.0])
    return float(low), float(high)


@dataclass(frozen=True)
class PairedDifference:
    """``stat(a - b)`` over paired episodes, its bootstrap interval, and how often a < b."""

    estimate: float
    low: float
    high: float
    n: int
    a_better: int
    """episodes with a_i < b_i (lower is better for every Table I metric)"""
    ties: int = 0
    """episodes with a_i == b_i"""

    @property
    def excludes_zero(self) -> bool:
        """The interval lies strictly on one side of 0: the sign of the difference is
        resolved at this confidence."""
        return self.high < 0.0 or self.low > 0.0


def paired_difference_ci(
    a: Sequence[float] | np.ndarray,
    b: Sequence[float] | np.ndarray,
    stat: Stat = np.mean,
    confidence: float = DEFAULT_CONFIDENCE,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
) -> PairedDifference:
    """Bootstrap interval of ``stat(a - b)``, ``a[i]`` and ``b[i]`` from the same episode."""
    a_arr, b_arr = _as_sample(a), _as_sample(b)
    if a_arr.shape != b_arr.shape:
        raise ValueError(f"paired samples differ in length: {a_arr.size} vs {b_arr.size}")
    diff = a_arr - b_arr
    low, high = bootstrap_ci(diff, stat, confidence, resamples, seed)
    return PairedDifference(
        estimate=float(stat(diff)),
        low=low,
        high=high,
        n=int(diff.size),
        a_better=int(np.sum(a_arr < b_arr)),
        ties=int(np.sum(a_arr == b_arr)),
    )


__all__ = [
    "interval",
    "seed_episode_bootstrap",
    "DEFAULT_CONFIDENCE",
    "DEFAULT_RESAMPLES",
    "PairedDifference",
    "bootstrap_ci",
    "bootstrap_distribution",
    "paired_difference_ci",
]
