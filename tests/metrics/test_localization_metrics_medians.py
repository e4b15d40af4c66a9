"""Median errors per ranking x paradigm x method x k, as the reference tools report them, and a
run's log free of faiss's loader."""

import subprocess
import sys

import numpy as np
import pandas as pd

from locretrieval.metrics.localization import MEDIAN_ERROR_COLUMNS, median_errors


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
