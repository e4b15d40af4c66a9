import numpy as np
import pandas as pd
import pytest
from scipy import stats

from locretrieval.metrics.correlation import (
    dataset_pearson,
    dataset_spearman,
    paired_metrics,
    pearson_rows,
    query_pearson,
    spearman_rows,
)
from locretrieval.metrics.localization import QUERY_ERROR_COLUMNS, RESULT_COLUMNS
from locretrieval.metrics.retrieval import QUERY_RETRIEVAL_COLUMNS, RETRIEVAL_COLUMNS
from locretrieval.report.tables import LOCALIZATION_DEFAULTS


def test_rows_equal_scipy_with_missing_values_dropped_pairwise():
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(6, 7)), rng.normal(size=(6, 7))
    x[1, 2] = np.nan
    y[2, [0, 5]] = np.nan
    x[3, 4] = y[4, 4] = np.nan
    y[5] = np.round(y[5])  # ties, for Spearman
    pearson, spearman = pearson_rows(x, y), spearman_rows(x, y)
    for row in range(6):
        valid = np.isfinite(x[row]) & np.isfinite(y[row])
        expected = stats.pearsonr(x[row, valid], y[row, valid])
        assert pearson["coefficient"][row] == pytest.approx(expected.statistic)
        assert pearson["p_value"][row] == pytest.approx(expected.pvalue)
        assert pearson["num_points"][row] == valid.sum()
        expected = stats.spearmanr(x[row, valid], y[row, valid])
        assert spearman["coefficient"][row] == pytest.approx(expected.statistic)
        assert spearman["p_value"][row] == pytest.approx(expected.pvalue)
    assert (pearson["undefined_reason"] == "").all()


def test_undefined_cases_are_nan_with_a_reason():
    x = np.array([[1.0, 2.0, 3.0], [1.0, 1.0, 1.0], [1.0, np.nan, np.nan], [np.nan] * 3, [1.0, 2.0, 3.0]])
    y = np.array([[2.0, 2.0, 2.0], [1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [3.0, 2.0, 1.0]])
    result = pearson_rows(x, y, "precision", "accuracy")
    assert result["undefined_reason"].tolist() == [
        "constant accuracy",
        "constant precision",
        "fewer than 2 points",
        "fewer than 2 points",
        "",
    ]
    assert result["coefficient"][:4].isna().all() and result["p_value"][:4].isna().all()
    assert result["coefficient"][4] == pytest.approx(-1.0)
    assert result["num_points"].tolist() == [3, 3, 1, 0, 3]
    assert spearman_rows(x, y)["undefined_reason"][1] == "constant x"


def retrieval_rows(ranking, kind, values, ks, metric="precision", groundtruth="gt_relative_pose"):
    return [("toy", "all", ranking, kind, groundtruth, metric, k, v, 10) for k, v in zip(ks, values)]


def result_rows(ranking, kind, values, ks, paradigm="approximation", method="ewb", threshold=(5.0, 10.0)):
    return [("toy", "all", ranking, kind, paradigm, method, k, k, *threshold, v, 10) for k, v in zip(ks, values)]


KS = [1, 2, 3, 5]
RETRIEVAL = {"a": [0.9, 0.7, 0.6, 0.5], "b": [0.8, 0.8, 0.4, 0.3], "c": [0.5, 0.4, 0.4, 0.2]}  # k=3: b and c tie
LOCALIZED = {"a": [60.0, 55.0, 50.0, 52.0], "b": [40.0, 45.0, 30.0, 20.0], "c": [70.0, 60.0, 65.0, 50.0]}


def tables():
    retrieval = sum((retrieval_rows(r, "descriptor", v, KS) for r, v in RETRIEVAL.items()), [])
    retrieval += retrieval_rows("gt_relative_pose", "groundtruth", [1.0, 1.0, 1.0, 0.9], KS)
    retrieval += retrieval_rows("flat", "descriptor", [0.5] * 4, KS)
    results = sum((result_rows(r, "descriptor", v, KS) for r, v in LOCALIZED.items()), [])
    results += result_rows("gt_relative_pose", "groundtruth", [90.0, 91.0, 92.0, 93.0], KS)
    results += result_rows("flat", "descriptor", [10.0, 20.0, 30.0, 40.0], KS)
    # the columns correlations read: the figures without their intervals
    figures = [column for column in RESULT_COLUMNS if column not in LOCALIZATION_DEFAULTS]
    retrieval_figures = [column for column in RETRIEVAL_COLUMNS if column not in ("value_low", "value_high")]
    return pd.DataFrame(retrieval, columns=retrieval_figures), pd.DataFrame(results, columns=figures)


def test_dataset_pearson_per_descriptor_over_k():
    retrieval, results = tables()
    table = dataset_pearson(paired_metrics(retrieval, results)).set_index("ranking")
    assert set(table.index) == {"a", "b", "c", "flat"}  # ground truth is not correlated
    for ranking in "abc":
        expected = stats.pearsonr(RETRIEVAL[ranking], LOCALIZED[ranking])
        assert table.loc[ranking, "coefficient"] == pytest.approx(expected.statistic)
        assert table.loc[ranking, "num_points"] == len(KS)
    assert (
        np.isnan(table.loc["flat", "coefficient"])
        and table.loc["flat", "undefined_reason"] == "constant retrieval metric"
    )


def test_dataset_spearman_per_k_over_descriptors():
    retrieval, results = tables()
    retrieval, results = retrieval[retrieval["ranking"] != "flat"], results[results["ranking"] != "flat"]
    table = dataset_spearman(paired_metrics(retrieval, results)).set_index("k")
    for n, k in enumerate(KS):
        expected = stats.spearmanr([RETRIEVAL[r][n] for r in "abc"], [LOCALIZED[r][n] for r in "abc"])
        assert table.loc[k, "coefficient"] == pytest.approx(expected.statistic)
        assert table.loc[k, "num_points"] == 3
    # k=1: precision orders a > b > c, localization c > a > b
    assert table.loc[1, "coefficient"] == pytest.approx(-0.5)


def test_query_pearson_scores_failures_and_rotation_with_a_capped_error():
    ks, queries = [1, 2, 3, 5], ["q0", "q1", "q2", "q3"]
    precision = {
        "q0": [1.0, 0.5, 1 / 3, 0.2],
        "q1": [0.0, 0.5, 2 / 3, 0.6],
        "q2": [0.0, 0.0, 0.0, 0.0],
        "q3": [1.0, 0.5, 0.2, 0.1],
    }
    position = {
        "q0": [0.1, 0.5, np.nan, 2.0],
        "q1": [3.0, 2.0, 1.0, 0.5],
        "q2": [1.0, 2.0, 3.0, 4.0],
        "q3": [1.0, 1.0, 1.0, 1.0],
    }
    rotation = {"q0": [1.0, 1.0, np.nan, 1.0], "q1": [1.0, 1.0, 1.0, 1.0], "q2": [1.0] * 4, "q3": [1.0, 2.0, 30.0, 8.0]}
    retrieval = pd.DataFrame(
        [
            ("toy", "a", "descriptor", "gt", "precision", k, q, precision[q][n])
            for q in queries
            for n, k in enumerate(ks)
        ],
        columns=QUERY_RETRIEVAL_COLUMNS,
    )
    errors = pd.DataFrame(
        [
            (
                "toy",
                "a",
                "descriptor",
                "approximation",
                "ewb",
                k,
                q,
                position[q][n],
                rotation[q][n],
                "" if np.isfinite(position[q][n]) else "failed",
            )
            for q in queries
            for n, k in enumerate(ks)
        ],
        columns=QUERY_ERROR_COLUMNS[:-1],  # position_unit: metres, as a run of an earlier version's,
    )
    table = query_pearson(retrieval, errors, (5.0, 10.0)).set_index("query")
    # max(c / 5, R / 10) capped at 1; the failed k=3 scores 1, the worst, instead of being dropped
    q0 = [-max(0.1 / 5, 0.1), -max(0.5 / 5, 0.1), -1.0, -max(2.0 / 5, 0.1)]
    assert table.loc["q0", "coefficient"] == pytest.approx(stats.pearsonr(precision["q0"], q0).statistic)
    assert table.loc["q0", "num_points"] == 4
    q1 = [-max(p / 5, 0.1) for p in position["q1"]]
    assert (
        table.loc["q1", "coefficient"] == pytest.approx(stats.pearsonr(precision["q1"], q1).statistic)
        and table.loc["q1", "coefficient"] > 0
    )
    assert table.loc["q2", "undefined_reason"] == "constant retrieval metric"
    # the same position at every k: rotation alone (0.1, 0.2, capped 1, 0.8) carries the correlation
    q3 = [-0.2, -0.2, -1.0, -0.8]
    assert (
        table.loc["q3", "coefficient"] == pytest.approx(stats.pearsonr(precision["q3"], q3).statistic)
        and table.loc["q3", "coefficient"] > 0
    )
    short = errors[errors["k"] <= 2]
    assert (
        query_pearson(retrieval[retrieval["k"] <= 2], short, (5.0, 10.0))["undefined_reason"] == "fewer than 3 points"
    ).all()


def test_duplicate_rows_are_an_error_not_a_silent_choice():
    retrieval, results = tables()
    with pytest.raises(ValueError, match="duplicate"):
        dataset_pearson(paired_metrics(pd.concat([retrieval, retrieval.iloc[:1]]), results))
