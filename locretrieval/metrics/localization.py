"""Localization metrics (paper Sec. 3.6.1): % of queries within (X m, Y deg), per-query errors."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from locretrieval.config import require
from locretrieval.estimates import LOCALIZED, PoseEstimates
from locretrieval.metrics.uncertainty import Uncertainty, default_uncertainty, share_interval
from locretrieval.scene import ImageSet
from locretrieval.scene.types import METRES

#: Columns of the tidy localization table, one row per
#: dataset x subset x ranking x paradigm x method x k x threshold; ``k`` is the requested k,
#: ``k_effective`` the top images it used (fewer when the ranking is shorter). ``localized`` of
#: ``num_queries`` queries were localized: ``localized_pct``, within the interval ``localized_low_pct``
#: to ``localized_high_pct`` (`share_interval`, ``metrics.uncertainty.confidence``). The position
#: threshold is in ``position_unit`` (`METRES`, or `MODEL_UNITS` for a scene without a metric scale).
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
    "localized",
    "localized_low_pct",
    "localized_high_pct",
    "position_unit",
]

#: Columns of the per-query error table (errors NaN where the query was not localised; positions
#: in ``position_unit``).
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
    "position_unit",
]


@dataclass
class MetricsSettings:
    """The ``metrics`` config section: ``thresholds``, a list of ``[X metres, Y degrees]``
    accuracy levels (the paper: high, medium, low); ``inclusive``: an error equal to a threshold
    counts as localised (the reference evaluation's ``<=``), else only a smaller one; ``uncertainty``:
    the intervals of every figure and the tests of every comparison (`Uncertainty`)."""

    thresholds: list[Any]
    inclusive: bool
    uncertainty: Uncertainty

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


#: Columns of the per-query outcome table (``query_localized.csv.gz``): each query with a reference
#: pose, localized (1) or not (0) by each estimate at each threshold; `RESULT_COLUMNS`' shares count them.
QUERY_LOCALIZED_COLUMNS = [
    "dataset",
    "ranking",
    "ranking_kind",
    "paradigm",
    "method",
    "k",
    "position_threshold_m",
    "rotation_threshold_deg",
    "query",
    "localized",
]


def localization_tables(
    dataset: str,
    estimates: Sequence[PoseEstimates],
    queries: ImageSet,
    thresholds: Sequence[Sequence[float]],
    subsets: Mapping[str, np.ndarray],
    inclusive: bool,
    confidence: float,
    position_unit: str = METRES,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The tidy % localised over the queries with a reference pose, for each subset mask
    (``inclusive``: see `localized`), with the count localized and its ``confidence`` interval
    (`RESULT_COLUMNS`), and the per-query outcomes it counts (`QUERY_LOCALIZED_COLUMNS`, every
    query with a reference pose; the paired comparisons read them).

    A subset with no evaluable query yields no rows.
    """
    evaluable = queries.has_pose
    names = np.asarray(queries.names, dtype=object)[evaluable]
    rows, outcomes = [], []
    for e in estimates:
        hits = localized(*e.errors(queries.qvec, queries.tvec), thresholds, inclusive)  # [T, len(ks), Q]
        outcomes.append(estimate_outcomes(dataset, e, thresholds, names, hits[:, :, evaluable]))
        for subset, mask in subsets.items():
            members = np.asarray(mask, dtype=bool) & evaluable
            count = int(members.sum())
            if not count:
                continue
            successes = hits[:, :, members].sum(axis=-1)  # [T, len(ks)]
            low, high = share_interval(successes, count, confidence)
            for (X, Y), per_k, low_k, high_k in zip(thresholds, successes, low, high):
                for k, used, value, lo, hi in zip(e.ks, e.k_effective, per_k, low_k, high_k):
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
                            100.0 * value / count,
                            count,
                            int(value),
                            100.0 * lo,
                            100.0 * hi,
                            position_unit,
                        )
                    )
    per_query = pd.concat(outcomes, ignore_index=True) if outcomes else pd.DataFrame(columns=QUERY_LOCALIZED_COLUMNS)
    return pd.DataFrame(rows, columns=RESULT_COLUMNS), per_query


def estimate_outcomes(
    dataset: str, e: PoseEstimates, thresholds: Sequence[Sequence[float]], names: np.ndarray, hits: np.ndarray
) -> pd.DataFrame:
    """The rows of `QUERY_LOCALIZED_COLUMNS` of one set of estimates: ``hits [T, len(ks), Q']`` of
    the queries ``names [Q']``."""
    num_thresholds, num_ks, num_queries = hits.shape
    position, rotation = np.asarray(thresholds, dtype=np.float64).reshape(-1, 2).T
    return pd.DataFrame(
        {
            "dataset": dataset,
            "ranking": e.ranking,
            "ranking_kind": e.ranking_kind,
            "paradigm": e.paradigm,
            "method": e.method,
            "k": np.tile(np.repeat(np.asarray(e.ks), num_queries), num_thresholds),
            "position_threshold_m": np.repeat(position, num_ks * num_queries),
            "rotation_threshold_deg": np.repeat(rotation, num_ks * num_queries),
            "query": np.tile(names, num_thresholds * num_ks),
            "localized": hits.reshape(-1).astype(np.int8),
        }
    )


def query_error_table(
    dataset: str, estimates: Sequence[PoseEstimates], queries: ImageSet, position_unit: str = METRES
) -> pd.DataFrame:
    """One row per ranking x paradigm x method x k x query with its errors (position in
    ``position_unit``) and failure reason."""
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
                    "position_unit": position_unit,
                }
            )
        )
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=QUERY_ERROR_COLUMNS)


#: Columns of the median-error table (`median_errors`), one row per dataset x ranking x paradigm x method x k:
#: the medians over the ``num_errors`` queries with an estimate and a reference pose, each with its bootstrap
#: interval (``_low`` / ``_high``); ``estimated`` of ``num_queries`` queries had an estimate (``estimated_pct``,
#: its Wilson interval); positions in ``position_unit``.
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
    "median_position_error_low_m",
    "median_position_error_high_m",
    "median_rotation_error_low_deg",
    "median_rotation_error_high_deg",
    "num_errors",
    "estimated",
    "estimated_low_pct",
    "estimated_high_pct",
    "position_unit",
]
#: The columns of a per-query error table that name one set of estimates (a median-error row).
ESTIMATE_KEYS = ["dataset", "ranking", "ranking_kind", "paradigm", "method", "k"]


def median_errors(query_errors: pd.DataFrame, uncertainty: Uncertainty | None = None) -> pd.DataFrame:
    """Median position and rotation (deg) errors over the queries with an estimate (and a reference
    pose), and the % of queries with an estimate, per dataset x ranking x paradigm x method x k of a
    per-query error table (`query_error_table`), as the reference tools report them, each with its
    interval (`MEDIAN_ERROR_COLUMNS`): a seeded bootstrap over a dataset's queries for the medians
    (`QueryBootstrap`, the same resamples for every row of a dataset), Wilson's for the share."""
    if query_errors.empty:
        return pd.DataFrame(columns=MEDIAN_ERROR_COLUMNS)
    uncertainty = uncertainty or default_uncertainty()
    rows = query_errors.assign(estimated=query_errors["failure"].fillna("") == LOCALIZED)
    if "position_unit" not in rows:  # a run of an earlier version: metres
        rows = rows.assign(position_unit=METRES)
    records = []
    for dataset, of_dataset in rows.groupby("dataset", sort=False):
        names = pd.Index(pd.unique(of_dataset["query"]))
        bootstrap = uncertainty.bootstrap(len(names))
        for keys, group in of_dataset.groupby(ESTIMATE_KEYS, sort=False):
            where = names.get_indexer(group["query"])
            record = dict(zip(ESTIMATE_KEYS, keys)) | {"position_unit": group["position_unit"].iloc[0]}
            for stem, unit in (("position_error", "m"), ("rotation_error", "deg")):
                values = np.full(len(names), np.nan)
                values[where] = group[f"{stem}_{unit}"].to_numpy(dtype=np.float64)
                measured = np.isfinite(values)  # an estimate and a reference pose
                record[f"median_{stem}_{unit}"] = float(np.median(values[measured])) if measured.any() else np.nan
                low, high = bootstrap.median_interval(values, measured, uncertainty.confidence)
                record[f"median_{stem}_low_{unit}"], record[f"median_{stem}_high_{unit}"] = low, high
            record["num_errors"] = int(measured.sum())
            estimated, count = int(group["estimated"].sum()), len(group)
            low, high = share_interval(estimated, count, uncertainty.confidence)
            record |= {
                "estimated_pct": 100.0 * estimated / count,
                "num_queries": count,
                "estimated": estimated,
                "estimated_low_pct": 100.0 * float(low),
                "estimated_high_pct": 100.0 * float(high),
            }
            records.append(record)
    return pd.DataFrame(records, columns=MEDIAN_ERROR_COLUMNS)


def query_subsets(queries: ImageSet) -> dict[str, np.ndarray]:
    """``all`` plus one subset per query tag (when tags split the queries)."""
    subsets = {"all": np.ones(len(queries), dtype=bool)}
    for tag in queries.all_tags:
        mask = queries.tag_mask(tag)
        if not mask.all():
            subsets[tag] = mask
    return subsets
