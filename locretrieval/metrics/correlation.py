"""Correlation between retrieval and localization metrics (paper Sec. 3.7), from tidy tables.

Three analyses, each returning a tidy table with ``coefficient``, ``p_value``,
``num_points`` and ``undefined_reason``:

- `dataset_pearson` (Tables 3 and 6): per descriptor, Pearson's r between a retrieval
  metric (P@k, R@k or mAP@k) and the % of queries localised, over the k values both
  tables hold (eq. 5);
- `dataset_spearman` (Tables 4 and 5): per k, Spearman's rho between the two metrics over
  the descriptors, i.e. whether they order the descriptors alike (eq. 6);
- `query_pearson` (violins of Figs. 8 and 11): per query and descriptor, Pearson's r over k
  between the query's retrieval metric and its localisation accuracy, taken as the
  *negated* capped pose error ``min(1, max(c / tau_c, R / tau_R))`` (position and rotation
  errors over the loosest accuracy threshold, 1 where the query is not localised at it or got
  no estimate), so that, as for the dataset-level coefficients, a positive r means "better
  retrieval goes with better localisation" and failures count as the worst accuracy. A
  query's coefficient needs at least 3 k values.

Only descriptor rankings are correlated (the paper's ``j`` runs over global
representations); ground-truth and baseline rankings are not.

Undefined cases are never an error: the coefficient and p-value are NaN and
``undefined_reason`` says why, ``"fewer than <n> points"`` (after dropping missing values)
or ``"constant <metric>"`` (a series with a single value, where r has no meaning);
``undefined_reason`` is empty where the coefficient is defined. Coefficients and p-values
are `scipy.stats.pearsonr`'s; Spearman's rho is Pearson's r of the average ranks
(`scipy.stats.rankdata`), which is how `scipy.stats.spearmanr` defines it.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats

#: Keys shared by the dataset-level correlation tables.
LOCALIZATION_KEYS = ["paradigm", "method", "position_threshold_m", "rotation_threshold_deg"]
STATISTIC_COLUMNS = ["coefficient", "p_value", "num_points", "undefined_reason"]

#: Fewest points of a per-query coefficient (with 2, r is always +-1).
MIN_QUERY_POINTS = 3


def pearson_rows(
    x: np.ndarray, y: np.ndarray, x_name: str = "x", y_name: str = "y", min_points: int = 2
) -> pd.DataFrame:
    """Pearson's r between the rows of ``x`` and ``y`` (``[G, n]``), NaN entries dropped pairwise;
    undefined for rows with fewer than ``min_points`` pairs left.

    Returns one row per input row with `STATISTIC_COLUMNS`. Rows sharing a pattern of
    missing values go to `scipy.stats.pearsonr` together, so the work is vectorised.
    """
    return _correlate_rows(
        np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), x_name, y_name, False, min_points
    )


def spearman_rows(
    x: np.ndarray, y: np.ndarray, x_name: str = "x", y_name: str = "y", min_points: int = 2
) -> pd.DataFrame:
    """Spearman's rho between the rows of ``x`` and ``y``; see `pearson_rows`."""
    return _correlate_rows(
        np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), x_name, y_name, True, min_points
    )


def _correlate_rows(
    x: np.ndarray, y: np.ndarray, x_name: str, y_name: str, rank: bool, min_points: int
) -> pd.DataFrame:
    if x.shape != y.shape or x.ndim != 2:
        raise ValueError(f"x and y must both be [G, n], got {x.shape} and {y.shape}")
    if min_points < 2:
        raise ValueError(f"a correlation needs at least 2 points, got min_points={min_points}")
    valid = np.isfinite(x) & np.isfinite(y)
    coefficient = np.full(len(x), np.nan)
    p_value = np.full(len(x), np.nan)
    reason = np.full(len(x), "", dtype=object)
    packed = np.ascontiguousarray(np.packbits(valid, axis=1))
    keys = packed.view(np.dtype((np.void, packed.shape[1]))).ravel()  # one key per row's pattern
    _, first, group = np.unique(keys, return_index=True, return_inverse=True)
    order = np.argsort(group, kind="stable")
    for pattern, rows in zip(valid[first], np.split(order, np.cumsum(np.bincount(group))[:-1])):
        if pattern.sum() < min_points:
            reason[rows] = f"fewer than {min_points} points"
            continue
        a, b = x[np.ix_(rows, pattern)], y[np.ix_(rows, pattern)]
        constant_a, constant_b = np.ptp(a, axis=1) == 0, np.ptp(b, axis=1) == 0
        reason[rows[constant_b]] = f"constant {y_name}"
        reason[rows[constant_a]] = f"constant {x_name}"
        defined = ~(constant_a | constant_b)
        if defined.any():
            a, b = a[defined], b[defined]
            if rank:
                a, b = stats.rankdata(a, axis=1), stats.rankdata(b, axis=1)
            result = stats.pearsonr(a, b, axis=1)
            coefficient[rows[defined]] = result.statistic
            p_value[rows[defined]] = result.pvalue
    return pd.DataFrame(
        {"coefficient": coefficient, "p_value": p_value, "num_points": valid.sum(axis=1), "undefined_reason": reason}
    )


def _descriptors(table: pd.DataFrame) -> pd.DataFrame:
    return table[table["ranking_kind"] == "descriptor"]


def paired_metrics(retrieval: pd.DataFrame, results: pd.DataFrame) -> pd.DataFrame:
    """Descriptor rankings' retrieval rows (`RETRIEVAL_COLUMNS`) joined with their localisation rows
    (`RESULT_COLUMNS`) of the same dataset, subset, ranking and k (``metric``/``value`` renamed
    ``retrieval_metric``/``retrieval_value``): the input of `dataset_pearson` and `dataset_spearman`."""
    retrieval = _descriptors(retrieval).rename(columns={"metric": "retrieval_metric", "value": "retrieval_value"})
    results = _descriptors(results)
    return retrieval.drop(columns="num_queries").merge(
        results.drop(columns="num_queries"), on=["dataset", "subset", "ranking", "ranking_kind", "k"]
    )


def _wide(frame: pd.DataFrame, keys: list[str], across: str, columns: list[str]) -> pd.DataFrame:
    """``columns`` of ``frame`` with one column per value of ``across``, a row per ``keys``."""
    try:
        return frame.set_index(keys + [across])[columns].unstack(across)
    except ValueError as error:
        duplicated = frame.duplicated(keys + [across])
        if not duplicated.any():
            raise
        example = frame.loc[duplicated, keys + [across]].iloc[0].to_dict()
        raise ValueError(
            f"the tables hold {int(duplicated.sum())} duplicate rows, e.g. {example}; drop duplicates first"
        ) from error


def _correlate_paired(paired: pd.DataFrame, keys: list[str], across: str, rank: bool) -> pd.DataFrame:
    """Correlate ``retrieval_value`` with ``localized_pct`` over the values of ``across`` per ``keys``."""
    if paired.empty:
        return pd.DataFrame(columns=keys + STATISTIC_COLUMNS)
    wide = _wide(paired, keys, across, ["retrieval_value", "localized_pct"])
    correlate = spearman_rows if rank else pearson_rows
    x, y = wide["retrieval_value"].to_numpy(), wide["localized_pct"].to_numpy()
    statistics = correlate(x, y, "retrieval metric", "localization metric")
    return pd.concat([wide.index.to_frame(index=False), statistics], axis=1)


def dataset_pearson(paired: pd.DataFrame) -> pd.DataFrame:
    """Pearson's r over k between each retrieval metric and % localised (Tables 3 and 6), from
    `paired_metrics`. One row per dataset x subset x ground truth x retrieval metric x paradigm
    x method x threshold x ranking.
    """
    keys = ["dataset", "subset", "groundtruth", "retrieval_metric", *LOCALIZATION_KEYS, "ranking"]
    return _correlate_paired(paired, keys, "k", rank=False)


def dataset_spearman(paired: pd.DataFrame) -> pd.DataFrame:
    """Spearman's rho over the descriptors, per k, between a retrieval metric and % localised.

    One row per dataset x subset x ground truth x retrieval metric x paradigm x method x
    threshold x k (Tables 4 and 5); ``num_points`` is the number of descriptors.
    """
    keys = ["dataset", "subset", "groundtruth", "retrieval_metric", *LOCALIZATION_KEYS, "k"]
    return _correlate_paired(paired, keys, "ranking", rank=True)


def query_pearson(
    query_retrieval: pd.DataFrame, query_errors: pd.DataFrame, scale: tuple[float, float]
) -> pd.DataFrame:
    """Per-query Pearson's r over k between a retrieval metric and the negated capped pose error
    (Figs. 8 and 11), for descriptor rankings; ``scale``: the loosest accuracy threshold
    ``(metres, degrees)`` (see the module docstring).

    Inputs are the per-query retrieval table (`QUERY_RETRIEVAL_COLUMNS`) and the per-query
    error table (`QUERY_ERROR_COLUMNS`). One row per dataset x ground truth x retrieval
    metric x paradigm x method x ranking x query.
    """
    shared = ["dataset", "ranking", "query"]
    keys = ["dataset", "groundtruth", "retrieval_metric", "paradigm", "method", "ranking", "query"]
    retrieval = _descriptors(query_retrieval).rename(columns={"metric": "retrieval_metric"})
    errors = _descriptors(query_errors).assign(accuracy=lambda t: -capped_pose_error(t, scale))
    if retrieval.empty or errors.empty:
        return pd.DataFrame(columns=keys + STATISTIC_COLUMNS)
    x = _wide(retrieval, ["dataset", "ranking", "groundtruth", "retrieval_metric", "query"], "k", ["value"])["value"]
    y = _wide(errors, ["dataset", "ranking", "paradigm", "method", "query"], "k", ["accuracy"])["accuracy"]
    ks = sorted(set(x.columns) | set(y.columns))
    rows = (
        x.index.to_frame(index=False)
        .reset_index(names="x_row")
        .merge(y.index.to_frame(index=False).reset_index(names="y_row"), on=shared)
    )
    x_values = x.reindex(columns=ks).to_numpy()[rows["x_row"]]
    y_values = y.reindex(columns=ks).to_numpy()[rows["y_row"]]
    statistics = pearson_rows(x_values, y_values, "retrieval metric", "-capped pose error", MIN_QUERY_POINTS)
    return pd.concat([rows[keys], statistics], axis=1)


def capped_pose_error(errors: pd.DataFrame, scale: tuple[float, float]) -> pd.Series:
    """``min(1, max(c / tau_c, R / tau_R))`` of each row of a per-query error table, 1 where the
    query got no estimate; ``scale = (tau_c metres, tau_R degrees)``."""
    position, rotation = scale
    normalised = np.maximum(errors["position_error_m"] / position, errors["rotation_error_deg"] / rotation)
    return normalised.fillna(1.0).clip(upper=1.0)
