"""Retrieval metrics (paper Sec. 3.6.2): Precision@k, Recall@k and mAP@k of a `Ranking`.

Relevance is a boolean sparse ``[Q, N]`` matrix (query x database image) holding *every*
relevant database image of each query, not only those of a ground-truth top K.

Conventions (all metrics are fractions in [0, 1]):

- **P@k** (landmark retrieval, paradigm 3a): relevant images among the top ``k`` divided by
  ``k`` ("the percentage of relevant images among the retrieved k images", Sec. 4.2.1).
  Empty slots (``EMPTY``, a ranking shorter than ``k``) count as retrieved non-relevant.
- **R@k** (place recognition, paradigm 3b): 1 when at least one relevant image is among
  the top ``k``, else 0; averaged, the fraction of queries "with at least one relevant
  database image amongst the top k retrieved images" (Sec. 4.2.2). This is the
  place-recognition recall, not the fraction of all relevant images retrieved.
- **AP@k**: ``sum_{i<=k} P@i * rel_i / min(R, k)`` with ``R`` the number of relevant
  images of the query, as the Google Landmarks v2 mAP@k (the paper does not define its
  own). The ``min(R, k)`` normaliser makes a perfect ranking score 1 at every k; relevant
  images beyond the ranking's depth count as missed.
- **Queries**: only queries with a reference pose are evaluated (the others have no
  relevance). A query with a pose but no relevant image counts as 0 in P@k and R@k (the
  paper's R@k is over all queries, and Table 1's "missing" queries can never be
  recalled); its AP is undefined (NaN) and it is left out of mAP, as the revisited
  Oxford/Paris evaluation does. ``num_queries`` in the tables says how many were averaged.
- **Uncertainty**: ``value_low`` to ``value_high`` is each figure's interval over its queries
  (`locretrieval.metrics.uncertainty`): Wilson's for R@k (a share of queries), a seeded bootstrap
  over the queries for P@k and mAP@k (the same resamples for every ranking and ground truth).
- **Ties**: only the stored order of ``Ranking.indices`` matters; scores are ignored, so
  images with tied scores count in the order the ranking holds them (`top_k` puts the
  lower database index first). Nothing is averaged over tie permutations.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from scipy import sparse

from locretrieval.metrics.uncertainty import Uncertainty, default_uncertainty, share_interval
from locretrieval.retrieval import EMPTY, Ranking, relevant_hits
from locretrieval.scene import ImageSet

#: Columns of the tidy retrieval table (``retrieval.csv``), one row per
#: dataset x subset x ranking x ground truth x metric x k.
RETRIEVAL_COLUMNS = [
    "dataset",
    "subset",
    "ranking",
    "ranking_kind",
    "groundtruth",
    "metric",
    "k",
    "value",
    "num_queries",
    "value_low",
    "value_high",
]

#: Columns of the per-query retrieval table (``query_retrieval.csv.gz``).
QUERY_RETRIEVAL_COLUMNS = ["dataset", "ranking", "ranking_kind", "groundtruth", "metric", "k", "query", "value"]

#: Dataset-level metric names and the per-query quantity each one averages.
METRICS = {"precision": "precision", "recall": "recall", "map": "average_precision"}


def retrieval_metrics(indices: np.ndarray, relevance: sparse.csr_matrix, ks: Sequence[int]) -> dict[str, np.ndarray]:
    """Per-query ``precision``, ``recall`` and ``average_precision``, each ``[Q, len(ks)]``.

    ``indices [Q, K]`` are ranked database indices (``Ranking.indices``); ``k`` may exceed
    ``K`` (the missing slots are empty). AP is NaN for queries without a relevant image.
    """
    ks = np.asarray(ks, dtype=np.int64)
    if ks.size == 0 or ks.min() < 1:
        raise ValueError(f"k values must be >= 1, got {ks.tolist()}")
    hits = relevant_hits(indices, relevance)
    depth = max(int(ks.max()), hits.shape[1])
    hits = np.pad(hits, ((0, 0), (0, depth - hits.shape[1])))
    found = np.cumsum(hits, axis=1)  # relevant images among the top i, [Q, depth]
    ranks = np.arange(1, depth + 1)
    precision_sum = np.cumsum(np.where(hits, found / ranks, 0.0), axis=1)
    num_relevant = np.diff(relevance.indptr)[:, None]
    normaliser = np.minimum(num_relevant, ks[None])
    with np.errstate(invalid="ignore", divide="ignore"):
        average_precision = np.where(normaliser > 0, precision_sum[:, ks - 1] / normaliser, np.nan)
    return {
        "precision": found[:, ks - 1] / ks,
        "recall": (found[:, ks - 1] > 0).astype(np.float64),
        "average_precision": average_precision,
    }


def retrieval_tables(
    dataset: str,
    rankings: Sequence[Ranking],
    relevances: Mapping[str, sparse.csr_matrix],
    queries: ImageSet,
    subsets: Mapping[str, np.ndarray],
    ks: Sequence[int],
    query_ks: Sequence[int],
    uncertainty: Uncertainty | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Tidy retrieval table and per-query table of every ranking against every ground truth.

    ``relevances`` maps a ground-truth name to its ``[Q, N]`` relevance. The first table
    (`RETRIEVAL_COLUMNS`) averages over each subset's queries with a reference pose, for
    every k of ``ks`` (the paper: 1..50); a subset without such a query yields no rows, and
    mAP rows average over those of them that have a relevant image. The second
    (`QUERY_RETRIEVAL_COLUMNS`) holds every query with a reference pose for the k of
    ``query_ks`` (those of the paradigms, for the per-query correlation of Sec. 3.7). Each value has
    its interval at ``uncertainty``'s confidence (``value_low``, ``value_high``; see the module).
    """
    uncertainty = uncertainty or default_uncertainty()
    bootstrap = uncertainty.bootstrap(len(queries))
    wrong = {name: len(mask) for name, mask in subsets.items() if len(mask) != len(queries)}
    if wrong:
        raise ValueError(f"{dataset}: subset masks {wrong} do not have one entry per query ({len(queries)})")
    evaluable = queries.has_pose
    names = np.asarray(queries.names, dtype=object)
    table_ks, query_ks = sorted({int(k) for k in ks}), sorted({int(k) for k in query_ks})
    all_ks = sorted(set(table_ks) | set(query_ks))
    table_columns, query_columns = [all_ks.index(k) for k in table_ks], [all_ks.index(k) for k in query_ks]
    frames, query_frames = [], []
    for ranking in rankings:
        for groundtruth, relevance in relevances.items():
            _check_shapes(ranking, groundtruth, relevance, len(queries))
            per_query = retrieval_metrics(ranking.indices, relevance, all_ks)
            has_relevant = ~np.isnan(per_query["average_precision"][:, 0])  # AP is NaN without a relevant image
            labels = {
                "dataset": dataset,
                "ranking": ranking.name,
                "ranking_kind": ranking.kind,
                "groundtruth": groundtruth,
            }
            for subset, mask in subsets.items():
                members = np.asarray(mask, dtype=bool) & evaluable
                for metric, quantity in METRICS.items():
                    averaged = members & has_relevant if metric == "map" else members
                    if averaged.any():
                        per_k = per_query[quantity][:, table_columns]
                        values = per_k[averaged].mean(axis=0)
                        count = int(averaged.sum())
                        if metric == "recall":  # a share of queries
                            low, high = share_interval(per_k[averaged].sum(axis=0), count, uncertainty.confidence)
                        else:
                            low, high = bootstrap.mean_interval(per_k, averaged, uncertainty.confidence)
                        rows = {
                            "subset": subset,
                            "metric": metric,
                            "k": table_ks,
                            "value": values,
                            "num_queries": count,
                            "value_low": low,
                            "value_high": high,
                        }
                        frames.append(pd.DataFrame({**labels, **rows}))
            for quantity in METRICS.values():
                values = per_query[quantity][evaluable][:, query_columns]  # [Q', len(query_ks)]
                query_frames.append(
                    pd.DataFrame(
                        {
                            **labels,
                            "metric": quantity,
                            "k": np.repeat(query_ks, values.shape[0]),
                            "query": np.tile(names[evaluable], len(query_ks)),
                            "value": values.T.ravel(),
                        }
                    )
                )
    return _concat(frames, RETRIEVAL_COLUMNS), _concat(query_frames, QUERY_RETRIEVAL_COLUMNS)


def _concat(frames: list[pd.DataFrame], columns: list[str]) -> pd.DataFrame:
    return pd.concat(frames, ignore_index=True)[columns] if frames else pd.DataFrame(columns=columns)


def _check_shapes(ranking: Ranking, groundtruth: str, relevance: sparse.csr_matrix, num_queries: int) -> None:
    if not (sparse.issparse(relevance) and relevance.format == "csr"):
        kind = type(relevance).__name__
        raise TypeError(f"relevance of ground truth {groundtruth!r} must be a scipy.sparse CSR matrix, got {kind}")
    if relevance.shape[0] != num_queries or ranking.num_queries != num_queries:
        raise ValueError(
            f"ranking {ranking.name!r} has {ranking.num_queries} queries and ground truth {groundtruth!r} "
            f"{relevance.shape[0]}, but the query set has {num_queries}"
        )
    if ranking.indices.max(initial=EMPTY) >= relevance.shape[1]:
        raise ValueError(
            f"ranking {ranking.name!r} refers to database image {ranking.indices.max()} but ground truth "
            f"{groundtruth!r} covers {relevance.shape[1]} database images"
        )
