"""Localization metrics (paper Sec. 3.6.1): % of queries within (X m, Y deg), per-query errors."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from locretrieval.config import require
from locretrieval.estimates import LOCALIZED, PoseEstimates
from locretrieval.scene import ImageSet

#: Columns of the tidy localization table, one row per
#: dataset x subset x ranking x paradigm x method x k x threshold; ``k`` is the requested k,
#: ``k_effective`` the top images it used (fewer when the ranking is shorter).
RESULT_COLUMNS = [
    "dataset",
    "subset",
    "ranking",
    "ranking_kind",
    "paradigm",
    "method",
    "k",
    "k_effective",
    "position_threshold_m",
    "rotation_threshold_deg",
    "localized_pct",
    "num_queries",
]

#: Columns of the per-query error table (errors NaN where the query was not localised).
QUERY_ERROR_COLUMNS = [
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
]


@dataclass
class MetricsSettings:
    """The ``metrics`` config section: ``thresholds``, a list of ``[X metres, Y degrees]``
    accuracy levels (the paper: high, medium, low); ``inclusive``: an error equal to a threshold
    counts as localised (the reference evaluation's ``<=``), else only a smaller one."""

    thresholds: list[Any]
    inclusive: bool

    def __post_init__(self) -> None:
        pairs = [t for t in self.thresholds if isinstance(t, (list, tuple)) and len(t) == 2]
        numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for t in pairs for v in t)
        require(
            bool(self.thresholds) and len(pairs) == len(self.thresholds) and numbers,
            "thresholds",
            f"must be a non-empty list of [metres, degrees] pairs of positive numbers, got {self.thresholds}",
        )
        self.thresholds = [[float(x), float(y)] for x, y in self.thresholds]


def localized(
    position_errors: np.ndarray,
    rotation_errors: np.ndarray,
    thresholds: Sequence[Sequence[float]],
    inclusive: bool,
) -> np.ndarray:
    """Boolean ``[T, ...]``: both errors within ``(X m, Y deg)``, for each threshold: ``<=``
    when ``inclusive`` (the reference evaluation's convention), else ``<``.

    A NaN error (no estimate) is never localised.
    """
    X, Y = np.asarray(thresholds, dtype=np.float64).reshape(-1, 2).T
    expand = (slice(None),) + (None,) * np.ndim(position_errors)
    within = np.less_equal if inclusive else np.less
    with np.errstate(invalid="ignore"):
        return within(position_errors[None], X[expand]) & within(rotation_errors[None], Y[expand])


def localization_table(
    dataset: str,
    estimates: Sequence[PoseEstimates],
    queries: ImageSet,
    thresholds: Sequence[Sequence[float]],
    subsets: Mapping[str, np.ndarray],
    inclusive: bool,
) -> pd.DataFrame:
    """Tidy % localised over the queries with a reference pose, for each subset mask (``inclusive``:
    see `localized`).

    A subset with no evaluable query yields no rows.
    """
    evaluable = queries.has_pose
    rows = []
    for e in estimates:
        hits = localized(*e.errors(queries.qvec, queries.tvec), thresholds, inclusive)  # [T, len(ks), Q]
        for subset, mask in subsets.items():
            members = np.asarray(mask, dtype=bool) & evaluable
            if not members.any():
                continue
            percentages = 100.0 * hits[:, :, members].mean(axis=-1)  # [T, len(ks)]
            for (X, Y), per_k in zip(thresholds, percentages):
                for k, used, value in zip(e.ks, e.k_effective, per_k):
                    rows.append(
                        (
                            dataset,
                            subset,
                            e.ranking,
                            e.ranking_kind,
                            e.paradigm,
                            e.method,
                            k,
                            used,
                            X,
                            Y,
                            value,
                            int(members.sum()),
                        )
                    )
    return pd.DataFrame(rows, columns=RESULT_COLUMNS)


def query_error_table(dataset: str, estimates: Sequence[PoseEstimates], queries: ImageSet) -> pd.DataFrame:
    """One row per ranking x paradigm x method x k x query with its errors and failure reason."""
    frames = []
    for e in estimates:
        position, rotation = e.errors(queries.qvec, queries.tvec)
        n_ks, n_queries = position.shape
        frames.append(
            pd.DataFrame(
                {
                    "dataset": dataset,
                    "ranking": e.ranking,
                    "ranking_kind": e.ranking_kind,
                    "paradigm": e.paradigm,
                    "method": e.method,
                    "k": np.repeat(e.ks, n_queries),
                    "query": np.tile(np.asarray(queries.names, dtype=object), n_ks),
                    "position_error_m": position.ravel(),
                    "rotation_error_deg": rotation.ravel(),
                    "failure": e.failures.ravel(),
                }
            )
        )
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=QUERY_ERROR_COLUMNS)


#: Columns of the median-error table (`median_errors`), one row per dataset x ranking x paradigm x method x k.
MEDIAN_ERROR_COLUMNS = [
    "dataset",
    "ranking",
    "ranking_kind",
    "paradigm",
    "method",
    "k",
    "median_position_error_m",
    "median_rotation_error_deg",
    "estimated_pct",
    "num_queries",
]


def median_errors(query_errors: pd.DataFrame) -> pd.DataFrame:
    """Median position (m) and rotation (deg) errors over the queries with an estimate (and a
    reference pose), and the % of queries with an estimate, per dataset x ranking x paradigm x
    method x k of a per-query error table (`query_error_table`), as the reference tools report them."""
    if query_errors.empty:
        return pd.DataFrame(columns=MEDIAN_ERROR_COLUMNS)
    keys = ["dataset", "ranking", "ranking_kind", "paradigm", "method", "k"]
    rows = query_errors.assign(estimated=query_errors["failure"].fillna("") == LOCALIZED)
    table = (
        rows.groupby(keys, sort=False)
        .agg(
            median_position_error_m=("position_error_m", "median"),
            median_rotation_error_deg=("rotation_error_deg", "median"),
            estimated_pct=("estimated", "mean"),
            num_queries=("query", "size"),
        )
        .reset_index()
    )
    table["estimated_pct"] *= 100.0
    return table[MEDIAN_ERROR_COLUMNS]


def query_subsets(queries: ImageSet) -> dict[str, np.ndarray]:
    """``all`` plus one subset per query tag (when tags split the queries)."""
    subsets = {"all": np.ones(len(queries), dtype=bool)}
    for tag in queries.all_tags:
        mask = queries.tag_mask(tag)
        if not mask.all():
            subsets[tag] = mask
    return subsets


def best_over_k(results: pd.DataFrame, across: str) -> pd.DataFrame:
    """Best % localised over k per paradigm x method x ranking (rows) x ``across`` (columns)."""
    return results.groupby(["paradigm", "method", "ranking", across])["localized_pct"].max().unstack(across)
