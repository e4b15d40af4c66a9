"""Which differences between rankings are real: paired comparisons of two rankings run on the same queries.

Every two rankings of a dataset are compared per paradigm, method, k and threshold
(`comparison_table`, ``comparisons.csv``) and at each one's best k (`best_k_comparisons`, the
report's headline), from the per-query outcomes (``query_localized.csv.gz``, `QUERY_LOCALIZED_COLUMNS`):
the difference in points with its exact paired interval and the exact McNemar test
(`locretrieval.metrics.uncertainty.paired_difference`) on the queries both were evaluated on; and
the share of the gap between a baseline and a ground truth that a trained ranking closed, where
there is a gap (`gap_closed`).

Conventions:

- A pair is written ``ranking`` against ``other``, descriptors first, then ground truths, then the
  baselines (by name within a kind): ``difference_pts`` is ranking minus other, and ``verdict``
  says whether the ranking is ``better`` than the other, ``worse``, or ``not distinguishable``.
- A method panel compares the rankings that have the method (BDI, CSI: descriptors only) with the
  others at `REFERENCE_METHOD` (EWB), as the paper's figures draw them; two rankings both at the
  reference method are compared in its own panel only.
- Many pairs are tested at once: Bonferroni's correction over a family, every pair of one dataset,
  paradigm, method, threshold and (per k) k. Each interval is at the confidence that keeps the whole
  family's (``1 - (1 - confidence) / pairs``), and ``p_adjusted`` is the single test's ``p_value``
  times the pairs: a verdict says ``better`` or ``worse`` exactly where the interval excludes 0,
  where ``p_adjusted`` is below ``1 - confidence``. The interval conditions on the discordant
  queries (as the exact test does): it says how the discordant queries split, so it ends at the
  share they make up (``only_ranking + only_other`` of ``num_queries``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from locretrieval.metrics.uncertainty import Uncertainty, default_uncertainty, paired_difference, percentile_interval

#: The method of pose approximation every ranking has (equal weights): rankings without a panel's
#: method (ground truths and baselines have no descriptors for BDI and CSI) are compared with it.
REFERENCE_METHOD = "ewb"
#: The order of ranking kinds in a pair: a pair is written from the earlier kind's side.
KIND_ORDER = ("descriptor", "groundtruth", "baseline")
#: The verdicts of a comparison, from the first ranking's side.
BETTER, WORSE, SAME = "better", "worse", "not distinguishable"
THRESHOLDS = ["position_threshold_m", "rotation_threshold_deg"]
#: What one estimate is: a ranking's outcomes at one paradigm, method and k.
ESTIMATE = ["ranking", "ranking_kind", "paradigm", "method", "k"]
#: The figures of a pair, after the columns that say which pair it is.
PAIR_COLUMNS = [
    "num_queries",
    "ranking_pct",
    "other_pct",
    "only_ranking",
    "only_other",
    "difference_pts",
    "difference_low_pts",
    "difference_high_pts",
    "p_value",
    "p_adjusted",
    "verdict",
]
#: Columns of ``comparisons.csv``: one row per pair per dataset x paradigm x method x k x threshold.
COMPARISON_COLUMNS = [
    "dataset",
    "paradigm",
    "method",
    "k",
    *THRESHOLDS,
    "ranking",
    "ranking_kind",
    "ranking_method",
    "other",
    "other_kind",
    "other_method",
    *PAIR_COLUMNS,
]
#: Columns of the best-over-k comparisons: each ranking at the k where it localizes most (``ranking_k``).
BEST_K_COLUMNS = [
    "dataset",
    "paradigm",
    "method",
    *THRESHOLDS,
    "ranking",
    "ranking_kind",
    "ranking_method",
    "ranking_k",
    "other",
    "other_kind",
    "other_method",
    "other_k",
    *PAIR_COLUMNS,
]


def outcome_matrix(query_localized: pd.DataFrame) -> pd.DataFrame:
    """One dataset's outcomes as a matrix: a row per estimate and threshold (`ESTIMATE` and
    `THRESHOLDS` as its index), a column per query, 1 or 0 (NaN: not evaluated by that estimate)."""
    keys = [*ESTIMATE, *THRESHOLDS, "query"]
    return query_localized.set_index(keys)["localized"].astype(np.float64).unstack("query")


def panel(rows: pd.DataFrame, method: str) -> tuple[pd.DataFrame, np.ndarray]:
    """The rows of one method's panel among ``rows`` (one paradigm): the rankings with ``method``,
    and the others at `REFERENCE_METHOD`; with a boolean per row, whether it is there by that fallback."""
    methods = rows.index.get_level_values("method")
    rankings = rows.index.get_level_values("ranking")
    own = methods == method
    fallback = (methods == REFERENCE_METHOD) & ~np.isin(rankings, rankings[own])
    chosen = rows[own | fallback]
    return chosen, fallback[own | fallback]


def compared_pairs(outcomes: pd.DataFrame, fallback: np.ndarray, uncertainty: Uncertainty) -> dict[str, np.ndarray]:
    """Every pair of the rows of ``outcomes`` (a ranking each, columns the queries) but two fallback
    rows, in `KIND_ORDER`: their paired figures (`PAIR_COLUMNS`, Bonferroni's family being all of
    them) with the ranking, kind, method and k of each side, as columns of arrays."""
    labels = outcomes.index.to_frame(index=False)
    order = np.lexsort((labels["ranking"].to_numpy(), labels["ranking_kind"].map(_kind_rank).to_numpy()))
    values, fallback = outcomes.to_numpy()[order], fallback[order]
    evaluated = ~np.isnan(values)
    hit = np.where(evaluated, values, 0.0)
    miss = evaluated - hit
    num_queries = evaluated.astype(np.float64) @ evaluated.T  # queries both were evaluated on
    only = hit @ miss.T  # [i, j]: localized by i, not by j
    first, second = np.triu_indices(len(labels), k=1)
    keep = ~(fallback[first] & fallback[second])
    first, second = first[keep], second[keep]
    together = num_queries[first, second]
    family = max(int((together > 0).sum()), 1)
    confidence = 1 - uncertainty.alpha / family  # Bonferroni: the family's confidence is uncertainty's
    difference = paired_difference(only[first, second], only[second, first], together, confidence)
    both = hit @ evaluated.T  # [i, j]: localized by i among the queries j was evaluated on
    with np.errstate(invalid="ignore", divide="ignore"):
        ranking_pct, other_pct = 100 * both[first, second] / together, 100 * both[second, first] / together
    p_adjusted = np.minimum(1.0, difference.p_value * family)
    verdict = np.where(p_adjusted < uncertainty.alpha, np.where(difference.difference > 0, BETTER, WORSE), SAME)
    columns = {}
    for side, rows in (("ranking", order[first]), ("other", order[second])):
        columns |= {
            side: labels["ranking"].to_numpy()[rows],
            f"{side}_kind": labels["ranking_kind"].to_numpy()[rows],
            f"{side}_method": labels["method"].to_numpy()[rows],
            f"{side}_k": labels["k"].to_numpy()[rows],
        }
    return columns | {
        "num_queries": together.astype(np.int64),
        "ranking_pct": ranking_pct,
        "other_pct": other_pct,
        "only_ranking": np.asarray(difference.only_first),
        "only_other": np.asarray(difference.only_second),
        "difference_pts": 100 * difference.difference,
        "difference_low_pts": 100 * difference.low,
        "difference_high_pts": 100 * difference.high,
        "p_value": difference.p_value,
        "p_adjusted": p_adjusted,
        "verdict": verdict.astype(object),
    }


def pair_table(frames: list[dict[str, np.ndarray]], columns: list[str]) -> pd.DataFrame:
    """The pairs of several panels (`compared_pairs`, their labels added) as one table of ``columns``."""
    if not frames:
        return pd.DataFrame(columns=columns)
    return pd.DataFrame({column: np.concatenate([frame[column] for frame in frames]) for column in columns})


def labelled(pairs: dict[str, np.ndarray], **labels: object) -> dict[str, np.ndarray]:
    """``pairs`` with a column per label, its value repeated for every pair."""
    count = len(pairs["ranking"])
    return pairs | {
        name: np.full(count, value, dtype=object if isinstance(value, str) else None) for name, value in labels.items()
    }


def _kind_rank(kind: str) -> int:
    return KIND_ORDER.index(kind) if kind in KIND_ORDER else len(KIND_ORDER)


def comparison_table(query_localized: pd.DataFrame, uncertainty: Uncertainty | None = None) -> pd.DataFrame:
    """``comparisons.csv``: every pair of rankings of a dataset per paradigm, method panel (`panel`),
    k and threshold, compared on the queries both were evaluated on (`compared_pairs`)."""
    uncertainty = uncertainty or default_uncertainty()
    frames = []
    for dataset, of_dataset in query_localized.groupby("dataset", sort=True):
        matrix = outcome_matrix(of_dataset)
        for (paradigm, k, *threshold), rows in matrix.groupby(["paradigm", "k", *THRESHOLDS], sort=True):
            for method in sorted(set(rows.index.get_level_values("method"))):
                chosen, fallback = panel(rows, method)
                if len(chosen) < 2:
                    continue
                pairs = compared_pairs(chosen, fallback, uncertainty)
                labels = {"dataset": dataset, "paradigm": paradigm, "method": method, "k": k}
                frames.append(labelled(pairs, **labels, **dict(zip(THRESHOLDS, threshold))))
    return pair_table(frames, COMPARISON_COLUMNS)


def best_k_comparisons(query_localized: pd.DataFrame, uncertainty: Uncertainty | None = None) -> pd.DataFrame:
    """Every pair of rankings of a dataset per paradigm, method panel and threshold, each ranking at
    the k where it localizes the most queries (the smallest such k; the report's best over k)
    (`BEST_K_COLUMNS`). The k is chosen on the same
    queries, so a ranking's share at its best k is an optimistic estimate; both sides are chosen alike.
    Bonferroni's family: the pairs of one panel and threshold."""
    uncertainty = uncertainty or default_uncertainty()
    frames = []
    for dataset, of_dataset in query_localized.groupby("dataset", sort=True):
        matrix = outcome_matrix(of_dataset)
        for (paradigm, *threshold), rows in matrix.groupby(["paradigm", *THRESHOLDS], sort=True):
            for method in sorted(set(rows.index.get_level_values("method"))):
                chosen, fallback = panel(rows, method)
                best = best_k_rows(chosen)
                if len(best) < 2:
                    continue
                pairs = compared_pairs(chosen.iloc[best], fallback[best], uncertainty)
                labels = {"dataset": dataset, "paradigm": paradigm, "method": method}
                frames.append(labelled(pairs, **labels, **dict(zip(THRESHOLDS, threshold))))
    return pair_table(frames, BEST_K_COLUMNS)


def best_k_rows(outcomes: pd.DataFrame) -> np.ndarray:
    """The position in ``outcomes`` of each ranking's row (its method) with the highest share
    localized, the smallest k among equals."""
    labels = outcomes.index.to_frame(index=False)
    labels["share"] = np.nanmean(outcomes.to_numpy(), axis=1)
    labels["row"] = np.arange(len(labels))
    ordered = labels.sort_values(["share", "k"], ascending=[False, True], kind="stable")
    return np.sort(ordered.drop_duplicates(["ranking", "ranking_kind", "method"])["row"].to_numpy())


def separation(best_k: pd.DataFrame) -> pd.DataFrame:
    """Per dataset, paradigm and threshold where ground truths and a baseline were compared (at
    their best k, `best_k_comparisons`): whether any ground truth is distinguishable from the
    baseline (``separates``), and the pairs' figures in words (``pairs``). A paradigm that does
    not separate them cannot rank descriptors on this scene at this threshold."""
    columns = ["dataset", "paradigm", *THRESHOLDS, "separates", "pairs"]
    bounds = best_k[(best_k["ranking_kind"] == "groundtruth") & (best_k["other_kind"] == "baseline")]
    if bounds.empty:
        return pd.DataFrame(columns=columns)
    bounds = bounds[bounds["method"] == bounds["ranking_method"]]  # each pair once: in its own panel
    records = []
    for keys, rows in bounds.groupby(["dataset", "paradigm", *THRESHOLDS], sort=True):
        pairs = "; ".join(
            f"{row.ranking} {row.ranking_pct:.1f} % vs {row.other} {row.other_pct:.1f} % ({row.verdict})"
            for row in rows.itertuples()
        )
        records.append((*keys, bool((rows["verdict"] != SAME).any()), pairs))
    return pd.DataFrame(records, columns=columns)


@dataclass
class Gap:
    """What a trained ranking closed of the gap between a baseline and a ground truth on the same
    queries (`gap_closed`): the ``gap`` (ground truth minus baseline, points) with its interval and
    whether it is one (``exists``); the share closed, ``(trained - baseline) / gap`` in %, with its
    interval (NaN where there is no gap); ``note``: why there is no share, or empty."""

    gap: float
    gap_low: float
    gap_high: float
    exists: bool
    closed: float
    closed_low: float
    closed_high: float
    note: str


def gap_closed(
    trained: np.ndarray, baseline: np.ndarray, truth: np.ndarray, uncertainty: Uncertainty, baseline_name: str
) -> Gap:
    """The `Gap` of per-query outcomes (booleans ``[Q]``, the same queries): a share of the gap
    closed exists only where the ground truth localizes more queries than the baseline by a
    distinguishable margin (exact McNemar test at ``uncertainty``'s confidence): a gap within the
    queries' noise, or a ground truth below the baseline, has no share to close, whatever the trained
    ranking did. Its interval is a seeded paired bootstrap over the queries of the ratio of the three
    shares (resamples without a positive gap left out)."""
    trained, baseline, truth = (np.asarray(a, dtype=bool) for a in (trained, baseline, truth))
    n = len(truth)
    difference = paired_difference(
        int((truth & ~baseline).sum()), int((~truth & baseline).sum()), n, uncertainty.confidence
    )
    gap, low, high = (100 * float(v) for v in (difference.difference, difference.low, difference.high))
    exists = bool(difference.p_value < uncertainty.alpha and gap > 0)
    if not exists:
        relation = "below" if gap < 0 else "not distinguishable from"
        note = (
            f"no gap to close: the ground truth ({100 * truth.mean():.1f} %) is {relation} {baseline_name} "
            f"({100 * baseline.mean():.1f} %) on these {n} queries"
        )
        return Gap(gap, low, high, False, float("nan"), float("nan"), float("nan"), note)
    closed = 100 * (trained.mean() - baseline.mean()) / (truth.mean() - baseline.mean())
    weights = uncertainty.bootstrap(n).counts.astype(np.float64)
    means = weights @ np.stack([trained, baseline, truth], axis=1).astype(np.float64) / n  # [resamples, 3]
    span = means[:, 2] - means[:, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        ratios = np.where(span > 0, 100 * (means[:, 0] - means[:, 1]) / span, np.nan)
    closed_low, closed_high = percentile_interval(ratios[:, None], uncertainty.confidence)
    return Gap(gap, low, high, True, float(closed), float(closed_low[0]), float(closed_high[0]), "")
