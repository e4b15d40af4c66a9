"""Intervals and paired tests of locretrieval.metrics.uncertainty, against scipy and explicit resamples."""

import warnings

import numpy as np
import pytest
from scipy import stats

from locretrieval.metrics.uncertainty import (
    QueryBootstrap,
    Uncertainty,
    default_uncertainty,
    exact_interval,
    paired_difference,
    percentile_interval,
    share_interval,
)


@pytest.mark.parametrize("successes, trials", [(0, 64), (32, 64), (64, 64), (7, 16), (1, 3), (51, 64)])
@pytest.mark.parametrize("confidence", [0.9, 0.95])
def test_share_intervals_are_scipys_wilson_and_exact_intervals(successes, trials, confidence):
    wilson = stats.binomtest(successes, trials).proportion_ci(confidence_level=confidence, method="wilson")
    exact = stats.binomtest(successes, trials).proportion_ci(confidence_level=confidence, method="exact")
    assert share_interval(successes, trials, confidence) == pytest.approx((wilson.low, wilson.high), abs=1e-12)
    assert exact_interval(successes, trials, confidence) == pytest.approx((exact.low, exact.high), abs=1e-12)


def test_shares_are_computed_for_whole_arrays_and_none_of_no_query():
    low, high = share_interval(np.array([[0, 5], [10, 3]]), np.array([10, 0]), 0.95)
    assert low.shape == (2, 2) and np.isnan(low[:, 1]).all() and np.isnan(high[:, 1]).all()
    assert low[1, 0] == pytest.approx(stats.binomtest(10, 10).proportion_ci(method="wilson").low)


def test_the_one_query_of_the_notes_is_what_the_paired_test_says():
    # uncertainty-facts.md: 7 queries against 2 discordant ones of 64: p = 0.18, not a difference
    result = paired_difference(7, 2, 64, 0.95)
    assert float(result.p_value) == pytest.approx(stats.binomtest(2, 9, 0.5).pvalue)
    assert float(result.difference) == pytest.approx(5 / 64)
    split = stats.binomtest(7, 9).proportion_ci(confidence_level=0.95, method="exact")
    # the difference's interval maps the exact interval of how the 9 discordant queries split
    assert (float(result.low), float(result.high)) == pytest.approx(
        ((2 * split.low - 1) * 9 / 64, (2 * split.high - 1) * 9 / 64)
    )
    assert result.low < 0 < result.high  # not a difference: the interval holds 0, as the test says


@pytest.mark.parametrize("first, second, n", [(12, 1, 64), (1, 12, 64), (5, 0, 20), (9, 4, 30), (40, 30, 200)])
def test_the_paired_interval_excludes_zero_exactly_where_the_test_rejects(first, second, n):
    result = paired_difference(first, second, n, 0.95)
    rejects = float(result.p_value) < 0.05
    assert rejects == (not (result.low <= 0 <= result.high))
    assert float(result.p_value) == pytest.approx(stats.binomtest(first, first + second, 0.5).pvalue)


def test_rankings_that_agree_on_every_query_still_have_an_interval():
    result = paired_difference(0, 0, 64, 0.95)
    bound = stats.binomtest(0, 64).proportion_ci(confidence_level=0.95, method="exact").high
    assert float(result.difference) == 0 and float(result.p_value) == 1.0
    assert (float(result.low), float(result.high)) == pytest.approx((-bound, bound))


def test_bootstrap_intervals_are_the_percentiles_of_the_resampled_statistic():
    rng = np.random.default_rng(3)
    values = rng.random((40, 2))
    mask = np.ones(40, dtype=bool)
    mask[:5] = False
    bootstrap = QueryBootstrap(40, 400, seed=7)
    # each resample spelled out: its queries repeated as often as drawn, the mask's only
    expanded = [np.repeat(values[mask], counts[mask], axis=0) for counts in bootstrap.counts]
    means = np.array([sample.mean(axis=0) for sample in expanded])
    medians = np.array([np.median(sample[:, 0]) for sample in expanded])
    low, high = bootstrap.mean_interval(values, mask, 0.9)
    assert low == pytest.approx(np.quantile(means, 0.05, axis=0)) and high == pytest.approx(
        np.quantile(means, 0.95, axis=0)
    )
    assert bootstrap.median_interval(values[:, 0], mask, 0.9) == pytest.approx(
        (np.quantile(medians, 0.05), np.quantile(medians, 0.95))
    )


def test_the_same_seed_gives_the_same_resamples_and_a_bounded_mean_of_zeros_is_not_a_point():
    first, second = QueryBootstrap(64, 200, seed=0), QueryBootstrap(64, 200, seed=0)
    assert np.array_equal(first.counts, second.counts) and (first.counts.sum(axis=1) == 64).all()
    low, high = first.mean_interval(np.zeros((64, 1)), np.ones(64, dtype=bool), 0.95)
    # 0 of 64 queries: the exact interval, as a share of queries would have it
    assert (float(low[0]), float(high[0])) == pytest.approx(tuple(map(float, exact_interval(0, 64, 0.95))))


def test_uncertainty_settings_refuse_what_makes_no_interval():
    with pytest.raises(ValueError, match="confidence"):
        Uncertainty(confidence=1.0, resamples=1000, seed=0)
    with pytest.raises(ValueError, match="resamples"):
        Uncertainty(confidence=0.95, resamples=10, seed=0)
    assert default_uncertainty() == Uncertainty(0.95, 1000, 0)  # configs/metrics/default.yaml's


@pytest.mark.parametrize("missing", ["none", "rows", "scattered", "all"])
def test_the_percentile_interval_is_numpys_nanquantile_over_the_resamples_that_have_a_value(missing):
    """NaN in whole rows (a resample without a query of the subset) take the vectorised path, NaN
    anywhere else numpy's column by column; both give nanquantile's bounds."""
    rng = np.random.default_rng(7)
    samples = np.round(rng.random((400, 9)) * 16) / 16  # ties, as shares of 16 queries have
    if missing == "rows":
        samples[rng.random(400) < 0.2] = np.nan
    elif missing == "scattered":
        samples[rng.random((400, 9)) < 0.1] = np.nan
    elif missing == "all":
        samples[:] = np.nan
    low, high = percentile_interval(samples, 0.9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns
        expected = np.nanquantile(samples, [0.05, 0.95], axis=0)
    np.testing.assert_allclose(np.stack([low, high]), expected, rtol=1e-12, atol=1e-15)
