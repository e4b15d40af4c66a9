"""Localization metrics (`locretrieval.metrics.localization`): % localized per threshold with its
interval, per-query errors, and the median errors per ranking x paradigm x method x k, as the
reference tools report them, and a run's log free of faiss's loader."""

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from helpers import evaluate_config
from scipy import stats

from locretrieval import geometry
from locretrieval.config import validated
from locretrieval.estimates import PoseEstimates
from locretrieval.metrics.localization import (
    MEDIAN_ERROR_COLUMNS,
    MetricsSettings,
    localization_tables,
    localized,
    median_errors,
    query_error_table,
    query_subsets,
)
from locretrieval.scene import Camera, ImageSet

CAMERA = Camera("SIMPLE_PINHOLE", 64, 48, (50.0, 32.0, 24.0))
THRESHOLDS = [[0.25, 2.0], [0.5, 5.0], [5.0, 10.0]]


def queries_with_poses():
    q = np.tile([1.0, 0, 0, 0], (4, 1))
    t = np.zeros((4, 3))
    q[3] = t[3] = np.nan  # no reference pose: never evaluated
    tags = [frozenset({"day"}), frozenset({"night"}), frozenset({"day"}), frozenset({"night"})]
    return ImageSet([f"q/{i}.png" for i in range(4)], "/x", [CAMERA] * 4, q, t, tags)


def estimate(position_offsets, rotation_degrees):
    """Estimates whose errors are the given offsets (m, along x) and angles (deg, about z)."""
    offsets = np.asarray(position_offsets, dtype=float)
    angles = np.radians(np.asarray(rotation_degrees, dtype=float))
    qvec = np.stack([np.cos(angles / 2), 0 * angles, 0 * angles, np.sin(angles / 2)], -1)[None]
    centers = np.stack([offsets, 0 * offsets, 0 * offsets], -1)[None]
    tvec = geometry.translations_from_centers(qvec, centers)
    failures = np.where(np.isnan(offsets), "no estimate", "")[None]
    qvec[np.isnan(offsets)[None]] = np.nan
    tvec[np.isnan(offsets)[None]] = np.nan
    return PoseEstimates("r", "descriptor", "approximation", "ewb", [1], qvec, tvec, failures)


def test_thresholds_include_equality_by_default_and_nan_is_not_localized():
    position, rotation = np.array([0.25, 0.2, 0.2, np.nan]), np.array([1.0, 2.0, 2.5, 1.0])
    inclusive = validated(MetricsSettings, evaluate_config("paths.root_dir=/nonexistent").metrics, "metrics").inclusive
    assert inclusive and localized(position, rotation, [[0.25, 2.0]], inclusive).tolist() == [
        [True, True, False, False]
    ]
    # the YAML's default: <=, the reference's
    assert localized(position, rotation, [[0.25, 2.0]], inclusive=False).tolist() == [[False, False, False, False]]
    queries = queries_with_poses()
    at_threshold = estimate([0.25, 0.1, 0.3, 0.0], [1.0, 2.0, 1.0, 0.0])
    table, _ = localization_tables(
        "toy", [at_threshold], queries, [[0.25, 2.0]], query_subsets(queries), inclusive=False, confidence=0.95
    )
    assert table.set_index("subset")["localized_pct"]["all"] == pytest.approx(0.0)


def test_localization_table_percentages_with_their_intervals_and_the_outcomes_they_count():
    queries = queries_with_poses()
    e = estimate([0.1, 0.4, np.nan, 0.0], [1.0, 3.0, 0.0, 0.0])
    table, outcomes = localization_tables(
        "toy", [e], queries, THRESHOLDS, query_subsets(queries), inclusive=True, confidence=0.9, position_unit="m"
    )
    lookup = table.set_index(["subset", "position_threshold_m"])
    assert lookup["localized_pct"][("all", 0.25)] == pytest.approx(100 / 3)
    assert lookup["localized_pct"][("all", 0.5)] == pytest.approx(200 / 3)
    assert lookup["localized_pct"][("day", 5.0)] == pytest.approx(50.0)  # query 2 has no estimate
    assert lookup["localized_pct"][("night", 0.5)] == pytest.approx(100.0)  # query 3 has no reference pose
    assert set(table["num_queries"]) == {3, 2, 1}
    assert len(table) == 3 * 3  # subsets x thresholds x k
    # Wilson's 90 % interval of 2 of 3 queries, as scipy computes it
    interval = stats.binomtest(2, 3).proportion_ci(confidence_level=0.9, method="wilson")
    row = lookup.loc[("all", 0.5)]
    assert (row["localized"], row["num_queries"]) == (2, 3)
    assert (row["localized_low_pct"], row["localized_high_pct"]) == pytest.approx(
        (100 * interval.low, 100 * interval.high)
    )
    assert set(table["position_unit"]) == {"m"}
    # one row per query with a reference pose and threshold: what the shares count, query 3 left out
    at = outcomes.set_index(["position_threshold_m", "query"])["localized"]
    assert sorted(set(outcomes["query"])) == ["q/0.png", "q/1.png", "q/2.png"]
    assert [at[(0.25, q)] for q in ("q/0.png", "q/1.png", "q/2.png")] == [1, 0, 0]
    assert [at[(0.5, q)] for q in ("q/0.png", "q/1.png", "q/2.png")] == [1, 1, 0]


def test_query_error_table_matches_hand_computed_errors():
    queries = queries_with_poses()
    table = query_error_table("toy", [estimate([0.1, 0.4, np.nan, 0.0], [1.0, 3.0, 0.0, 0.0])], queries)
    np.testing.assert_allclose(table["position_error_m"][:2], [0.1, 0.4], atol=1e-9)
    np.testing.assert_allclose(table["rotation_error_deg"][:2], [1.0, 3.0], atol=1e-9)
    assert table["failure"].tolist() == ["", "", "no estimate", ""]
    assert np.isnan(table["position_error_m"][3])


def test_median_errors_are_over_the_queries_with_an_estimate_with_their_share():
    rows = []
    for k, errors in ((1, [(0.1, 1.0), (0.3, 3.0), (None, None), (9.0, 40.0)]), (5, [(None, None)] * 4)):
        for query, error in enumerate(errors):
            position, rotation = error if error[0] is not None else (np.nan, np.nan)
            rows.append(
                (
                    "d",
                    "r",
                    "descriptor",
                    "global_sfm",
                    "pnp",
                    k,
                    f"q{query}",
                    position,
                    rotation,
                    "" if error[0] is not None else "too few inliers",
                )
            )
    # a query localised without a reference pose: an estimate, no error
    rows.append(("d", "r", "descriptor", "global_sfm", "pnp", 1, "q4", np.nan, np.nan, ""))
    table = pd.DataFrame(
        rows,
        columns=[
            "dataset",
            "ranking",
            "ranking_kind",
            "paradigm",
            "method",
            "k",
            "query",
            "position_error_m",
            "rotation_error_deg",
            "failure",
        ],
    )
    medians = median_errors(table)
    assert list(medians.columns) == MEDIAN_ERROR_COLUMNS
    first, second = medians.iloc[0], medians.iloc[1]
    assert (first["k"], first["median_position_error_m"], first["median_rotation_error_deg"]) == (
        1,
        0.3,
        3.0,
    )  # of 0.1, 0.3, 9.0
    assert first["estimated_pct"] == 80.0 and first["num_queries"] == 5
    assert second["k"] == 5 and np.isnan(second["median_position_error_m"]) and second["estimated_pct"] == 0.0
    assert median_errors(table.iloc[:0]).empty


def test_importing_the_package_and_faiss_logs_nothing_at_info():
    code = "import logging; logging.basicConfig(level=logging.INFO); import locretrieval; import faiss; print('ok')"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.stdout.strip() == "ok" and "faiss.loader" not in done.stderr, done.stderr
