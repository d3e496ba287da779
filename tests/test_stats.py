"""policy/campaigns/stats.py: percentile-bootstrap intervals, numpy only."""

from __future__ import annotations

import numpy as np
import pytest

from policy.campaigns.stats import bootstrap_ci, bootstrap_distribution, paired_difference_ci


def test_coverage_on_a_known_normal_sample() -> None:
    """A 95 % interval of the mean covers the true mean about 95 % of the time."""
    rng = np.random.default_rng(1)
    trials, n, mu = 300, 40, 3.0
    covered = 0
    for t in range(trials):
        x = rng.normal(mu, 2.0, size=n)
        low, high = bootstrap_ci(x, resamples=2000, seed=t)
        assert low < x.mean() < high
        covered += low <= mu <= high
    # the percentile bootstrap under-covers slightly at n = 40 (about 93-94 %)
    assert 0.88 <= covered / trials <= 0.99


def test_width_matches_the_normal_theory() -> None:
    rng = np.random.default_rng(2)
    x = rng.normal(0.0, 1.0, size=400)
    low, high = bootstrap_ci(x)
    expected = 2 * 1.96 * x.std(ddof=1) / np.sqrt(x.size)
    assert high - low == pytest.approx(expected, rel=0.1)


def test_paired_difference_of_identical_arrays_is_exactly_zero() -> None:
    x = np.random.default_rng(3).normal(size=25)
    d = paired_difference_ci(x, x.copy())
    assert (d.estimate, d.low, d.high) == (0.0, 0.0, 0.0)
    assert d.a_better == 0 and d.n == 25 and not d.excludes_zero


def test_pairing_removes_the_shared_spread() -> None:
    """b = a + 0.01: episodes vary by ~1, the difference not at all."""
    a = np.random.default_rng(4).normal(size=30)
    b = a + 0.01
    d = paired_difference_ci(a, b)
    assert d.estimate == pytest.approx(-0.01)
    assert d.low == pytest.approx(-0.01) and d.high == pytest.approx(-0.01)
    assert d.excludes_zero and d.a_better == 30
    # unpaired, the two means' intervals overlap almost entirely
    la, ha = bootstrap_ci(a)
    lb, hb = bootstrap_ci(b)
    assert la < lb < ha


def test_deterministic_with_a_seed() -> None:
    x = np.random.default_rng(5).exponential(size=20)
    assert bootstrap_ci(x, seed=7) == bootstrap_ci(x, seed=7)
    assert bootstrap_ci(x, seed=7) != bootstrap_ci(x, seed=8)
    np.testing.assert_array_equal(
        bootstrap_distribution(x, resamples=50, seed=1),
        bootstrap_distribution(x, resamples=50, seed=1),
    )


def test_other_statistics() -> None:
    x = np.arange(11.0)
    low, high = bootstrap_ci(x, stat=np.median, resamples=500)
    assert 0.0 <= low <= 5.0 <= high <= 10.0
    # a statistic without an axis argument is applied per resample
    low2, high2 = bootstrap_ci(x, stat=lambda v: float(np.max(v)), resamples=200)
    assert low2 <= high2 == 10.0


def test_a_constant_sample_has_a_zero_width_interval() -> None:
    assert bootstrap_ci([2.5] * 8) == (2.5, 2.5)
    assert bootstrap_ci([1.0]) == (1.0, 1.0)


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="at least one"):
        bootstrap_ci([])
    with pytest.raises(ValueError, match="finite"):
        bootstrap_ci([1.0, float("nan")])
    with pytest.raises(ValueError, match="confidence"):
        bootstrap_ci([1.0, 2.0], confidence=1.0)
    with pytest.raises(ValueError, match="length"):
        paired_difference_ci([1.0, 2.0], [1.0])
