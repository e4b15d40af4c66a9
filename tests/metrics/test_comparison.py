"""Paired comparisons of rankings built to differ by a known number of queries (locretrieval.metrics.comparison)."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from locretrieval.metrics.comparison import (
    BETTER,
    SAME,
    WORSE,
    best_k_comparisons,
    comparison_table,
    gap_closed,
    separation,
)
from locretrieval.metrics.localization import QUERY_LOCALIZED_COLUMNS
from locretrieval.metrics.uncertainty import default_uncertainty

QUERIES = [f"q{i:02d}" for i in range(40)]
#: Which queries each ranking localizes (at 5 m), per k; ground truth and random have EWB only.
LOCALIZED = {
    ("a", "descriptor"): {1: range(20), 5: range(30)},
    ("b", "descriptor"): {1: range(18), 5: range(20)},
    ("gt", "groundtruth"): {1: range(40), 5: range(38)},
    ("random", "baseline"): {1: range(0), 5: range(2)},
}


def outcomes() -> pd.DataFrame:
    """Per-query outcomes of four rankings: at (5 m, 10 deg) as `LOCALIZED` says, at (50 m, 20 deg)
    every query by every ranking, and the descriptors' BDI as their EWB."""
    rows = []
    for (ranking, kind), per_k in LOCALIZED.items():
        methods = ["ewb", "bdi"] if kind == "descriptor" else ["ewb"]
        for method in methods:
            for k, hits in per_k.items():
                for query_index, query in enumerate(QUERIES):
                    for threshold, localized in (((5.0, 10.0), query_index in hits), ((50.0, 20.0), True)):
                        rows.append(("d", ranking, kind, "approximation", method, k, *threshold, query, int(localized)))
    return pd.DataFrame(rows, columns=QUERY_LOCALIZED_COLUMNS)


def test_every_pair_per_k_has_its_counts_difference_and_bonferroni_verdict():
    table = comparison_table(outcomes(), default_uncertainty())
    at = table[(table["position_threshold_m"] == 5.0) & (table["method"] == "ewb") & (table["k"] == 5)]
    assert len(at) == 6  # the pairs of four rankings
    row = at[(at["ranking"] == "a") & (at["other"] == "b")].iloc[0]
    # a localizes queries 0-29, b 0-19: 10 queries by a only, none by b only
    assert (row["only_ranking"], row["only_other"], row["num_queries"]) == (10, 0, 40)
    assert (row["ranking_pct"], row["other_pct"], row["difference_pts"]) == pytest.approx((75.0, 50.0, 25.0))
    p_value = stats.binomtest(10, 10, 0.5).pvalue
    assert row["p_value"] == pytest.approx(p_value) and row["p_adjusted"] == pytest.approx(6 * p_value)
    assert row["verdict"] == BETTER
    split = stats.binomtest(10, 10).proportion_ci(confidence_level=1 - 0.05 / 6, method="exact")
    assert (row["difference_low_pts"], row["difference_high_pts"]) == pytest.approx(
        (100 * (2 * split.low - 1) * 10 / 40, 25.0)
    )
    # written from the descriptor's side: worse than the ground truth, which localizes 8 more
    against_truth = at[(at["ranking"] == "b") & (at["other"] == "gt")].iloc[0]
    assert (against_truth["only_ranking"], against_truth["only_other"], against_truth["verdict"]) == (0, 18, WORSE)
    # every ranking localizes every query at 50 m: nothing to tell apart
    loose = table[table["position_threshold_m"] == 50.0]
    assert set(loose["verdict"]) == {SAME} and set(loose["difference_pts"]) == {0.0}


def test_a_method_panel_compares_the_rankings_without_it_at_ewb_once():
    table = comparison_table(outcomes(), default_uncertainty())
    bdi = table[(table["method"] == "bdi") & (table["k"] == 1) & (table["position_threshold_m"] == 5.0)]
    # a and b at BDI, the ground truth and random at EWB; ground truth against random only in EWB's panel
    assert sorted(zip(bdi["ranking"], bdi["other"])) == [
        ("a", "b"),
        ("a", "gt"),
        ("a", "random"),
        ("b", "gt"),
        ("b", "random"),
    ]
    assert set(bdi.loc[bdi["other"] == "gt", "other_method"]) == {"ewb"}
    assert set(bdi["ranking_method"]) == {"bdi"}


def test_best_over_k_pairs_each_ranking_at_its_own_best_k_and_say_whether_a_paradigm_separates():
    best = best_k_comparisons(outcomes(), default_uncertainty())
    at = best[(best["method"] == "ewb") & (best["position_threshold_m"] == 5.0)].set_index(["ranking", "other"])
    assert at.loc[("a", "b"), ["ranking_k", "other_k"]].tolist() == [5, 5]
    assert at.loc[("gt", "random"), ["ranking_k", "other_k", "verdict"]].tolist() == [1, 5, BETTER]
    separated = separation(best).set_index("position_threshold_m")
    assert bool(separated.loc[5.0, "separates"]) and not bool(separated.loc[50.0, "separates"])
    assert "gt 100.0 % vs random 100.0 % (not distinguishable)" in separated.loc[50.0, "pairs"]


def test_gap_closed_exists_only_above_a_distinguishable_gap_and_has_its_interval():
    n = 40
    baseline, truth, trained = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
    baseline[:10], truth[:30], trained[:20] = True, True, True
    gap = gap_closed(trained, baseline, truth, default_uncertainty(), "densevlad")
    assert gap.exists and gap.closed == pytest.approx(50.0) and gap.gap == pytest.approx(50.0)
    assert gap.closed_low < 50.0 < gap.closed_high
    # a model worse than the baseline closes a negative share, never a positive one
    worse = gap_closed(np.zeros(n, bool), baseline, truth, default_uncertainty(), "densevlad")
    assert worse.closed == pytest.approx(-50.0) and worse.closed_high < 0
    # the ground truth below the baseline (the local SfM row): no gap, whatever training did
    below = gap_closed(trained, truth, baseline, default_uncertainty(), "densevlad")
    assert not below.exists and np.isnan(below.closed) and "below densevlad" in below.note
    # a gap of one query: within the queries' noise
    close = truth.copy()
    close[:30], close[:11] = False, True
    within = gap_closed(trained, baseline, close, default_uncertainty(), "densevlad")
    assert not within.exists and "not distinguishable from densevlad" in within.note
