"""How sure a figure is: intervals over the queries it was computed on, and paired tests.

Every figure of the benchmark is a statistic of its queries, so its uncertainty is the queries'
(`Uncertainty`, the ``metrics.uncertainty`` config section):

- **A share of queries** (% localized, R@k, % with an estimate): Wilson's score interval
  (`share_interval`), which keeps its coverage at 0 % and 100 % and for a few dozen queries.
- **A mean or a median over queries** (P@k, mAP@k, median errors): a percentile bootstrap over the
  queries, seeded (`QueryBootstrap`): the same run gives the same interval on any machine.
- **Two rankings on the same queries** (`paired_difference`): only the queries where exactly one
  of them localizes count. The exact McNemar test (a binomial test of those discordant queries,
  scipy) says whether they differ; the interval of the difference is the exact (Clopper-Pearson)
  interval of the discordant queries' split, which excludes 0 exactly when the test rejects.
- **Many comparisons at once**: Bonferroni's correction within a family
  (`locretrieval.metrics.comparison`): intervals at ``1 - (1 - confidence) / tests``, which keeps
  every interval's verdict that of its adjusted test.

By hand, each in a few vectorised lines, where scipy answers one figure per call
(``binomtest(...).proportion_ci``, ``bootstrap``): a run has thousands of figures, and one set of
bootstrap resamples shared by every ranking keeps their intervals paired.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from locretrieval.errors import require


def _stats():
    """scipy.stats, imported on first use: a figure worker imports this module's constants only."""
    from scipy import stats

    return stats


@dataclass
class Uncertainty:
    """The ``metrics.uncertainty`` section (``configs/metrics/default.yaml`` holds the defaults):
    ``confidence``, the intervals' level (0.95: a 95 % interval; 1 - confidence is the tests'
    significance level); ``resamples``, bootstrap resamples of the queries (means and medians);
    ``seed``, the bootstrap's seed."""

    confidence: float
    resamples: int
    seed: int

    def __post_init__(self) -> None:
        require(0.5 <= self.confidence < 1, "confidence", f"must be in [0.5, 1), got {self.confidence}")
        require(self.resamples >= 100, "resamples", f"must be >= 100, got {self.resamples}")

    @property
    def alpha(self) -> float:
        """The significance level of a test, ``1 - confidence``."""
        return 1.0 - self.confidence

    def bootstrap(self, num_queries: int) -> QueryBootstrap:
        """Resamples of ``num_queries`` queries with this seed."""
        return QueryBootstrap(num_queries, self.resamples, self.seed)


#: The defaults of the ``metrics`` config group (its one file, in the shipped configs).
DEFAULTS_FILE = ("metrics", "default.yaml")


@functools.cache
def default_uncertainty() -> Uncertainty:
    """The ``metrics.uncertainty`` of `DEFAULTS_FILE`: for what runs without a run's config (``report.py``
    over runs, a sweep's summary)."""
    import yaml

    from locretrieval.resources import configs_dir

    return Uncertainty(**yaml.safe_load(configs_dir().joinpath(*DEFAULTS_FILE).read_text())["uncertainty"])


def share_interval(successes: np.ndarray, trials: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray]:
    """Wilson's score interval ``(low, high)``, fractions, of ``successes`` among ``trials`` (arrays
    of counts, broadcast; NaN where ``trials`` is 0); equal to scipy's
    ``binomtest(k, n).proportion_ci(confidence, method="wilson")``."""
    k = np.asarray(successes, dtype=np.float64)
    n = np.asarray(trials, dtype=np.float64)
    z = _stats().norm.ppf(0.5 + confidence / 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = k / n
        centre = (k + z * z / 2) / (n + z * z)
        half = z * np.sqrt(n * p * (1 - p) + z * z / 4) / (n + z * z)
    return centre - half, centre + half


def exact_interval(successes: np.ndarray, trials: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray]:
    """The exact (Clopper-Pearson) interval ``(low, high)`` of ``successes`` among ``trials``
    (fractions; NaN where ``trials`` is 0); scipy's ``binomtest(...).proportion_ci(method="exact")``."""
    k = np.asarray(successes, dtype=np.float64)
    n = np.asarray(trials, dtype=np.float64)
    tail = (1 - confidence) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        low = np.where(k > 0, _stats().beta.ppf(tail, k, n - k + 1), 0.0)
        high = np.where(k < n, _stats().beta.ppf(1 - tail, k + 1, n - k), 1.0)
    undefined = n <= 0
    return np.where(undefined, np.nan, low), np.where(undefined, np.nan, high)


class QueryBootstrap:
    """Seeded bootstrap resamples of ``num_queries`` queries, as counts ``[resamples, num_queries]``
    (how often each query is drawn), shared by every statistic asked of it: intervals of different
    rankings on the same queries come from the same resamples.

    A statistic of a subset of the queries (a mask) is taken over the subset's queries in each
    resample, so its size varies as a subset's size does across samples of the queries.
    """

    def __init__(self, num_queries: int, resamples: int, seed: int) -> None:
        rng = np.random.default_rng([seed, num_queries])
        self.num_queries = num_queries
        self.counts = rng.multinomial(num_queries, np.full(num_queries, 1.0 / max(num_queries, 1)), size=resamples)

    def mean_interval(
        self, values: np.ndarray, mask: np.ndarray, confidence: float, bounded: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` percentile intervals of the means of ``values [Q, M]`` (a column per
        figure) over the queries of ``mask [Q]``. ``bounded``: values in ``[0, 1]``; where every
        value of a column is 0 (or 1) the resamples cannot vary, and the interval is the exact one
        of 0 (or all) of the queries (`exact_interval`), not a point."""
        values = np.asarray(values, dtype=np.float64).reshape(self.num_queries, -1)[mask]
        weights = self.counts[:, mask].astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            means = (weights @ values) / weights.sum(axis=1, keepdims=True)  # [resamples, M]
        low, high = percentile_interval(means, confidence)
        if bounded and len(values):
            n = len(values)
            exact_low, exact_high = exact_interval(np.array([0, n]), np.array([n, n]), confidence)
            zeros, ones = (values == 0).all(axis=0), (values == 1).all(axis=0)
            low, high = np.where(ones, exact_low[1], low), np.where(zeros, exact_high[0], high)
        return low, high

    def median_interval(self, values: np.ndarray, mask: np.ndarray, confidence: float) -> tuple[float, float]:
        """``(low, high)`` percentile interval of the median of ``values [Q]`` over the queries of
        ``mask [Q]`` (the median of an even count: the mean of the middle two, as numpy's)."""
        order = np.argsort(np.asarray(values, dtype=np.float64)[mask], kind="stable")
        sorted_values = np.asarray(values, dtype=np.float64)[mask][order]
        if not len(sorted_values):
            return float("nan"), float("nan")
        cumulative = np.cumsum(self.counts[:, mask][:, order], axis=1)  # [resamples, n]
        total = cumulative[:, -1:]
        lower = (cumulative >= (total + 1) // 2).argmax(axis=1)  # the middle draws' ranks, 1-based
        upper = (cumulative >= total // 2 + 1).argmax(axis=1)
        medians = np.where(total[:, 0] > 0, (sorted_values[lower] + sorted_values[upper]) / 2, np.nan)
        low, high = percentile_interval(medians[:, None], confidence)
        return float(low[0]), float(high[0])


def percentile_interval(samples: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray]:
    """The ``(1 - confidence) / 2`` and ``(1 + confidence) / 2`` quantiles of ``samples [R, M]``
    over its rows, NaN rows (a resample without a query of the subset) left out."""
    tail = (1 - confidence) / 2
    missing = np.isnan(samples)
    if not samples.size or missing.all():
        return np.full(samples.shape[1:], np.nan), np.full(samples.shape[1:], np.nan)
    if (missing == missing[:, :1]).all():  # NaN in whole rows only: one vectorised quantile over the others
        low, high = np.quantile(samples[~missing[:, 0]], [tail, 1 - tail], axis=0)
    else:  # numpy's nanquantile goes column by column (hundreds of times slower)
        low, high = np.nanquantile(samples, [tail, 1 - tail], axis=0)
    return low, high


@dataclass
class PairedDifference:
    """Two rankings' outcomes on the same ``num_queries`` queries: ``only_first`` and ``only_second``
    queries localized by one of them only (the discordant queries), the ``difference`` of their
    shares (first minus second, a fraction) with its exact interval ``low, high``, and the exact
    McNemar test's two-sided ``p_value``."""

    num_queries: np.ndarray
    only_first: np.ndarray
    only_second: np.ndarray
    difference: np.ndarray
    low: np.ndarray
    high: np.ndarray
    p_value: np.ndarray


def paired_difference(
    only_first: np.ndarray, only_second: np.ndarray, num_queries: np.ndarray, confidence: float
) -> PairedDifference:
    """Compare two rankings on the same ``num_queries`` queries from their discordant queries:
    ``only_first`` localized by the first ranking only, ``only_second`` by the second only (counts,
    broadcast): the difference of the shares localized and its interval, and the exact McNemar test.

    Given ``m`` discordant queries of which ``b`` favour the first, the difference is
    ``(2b - m) / n``; its interval maps the exact interval of ``b / m``, so it excludes 0 exactly
    where the test's p-value is below ``1 - confidence`` (both condition on ``m``). Where no query is
    discordant the difference is 0 and its interval is ``+-`` the exact upper bound of 0 discordant
    queries of ``n`` (how far apart they could still be), not a point.
    """
    b, c = np.asarray(only_first, dtype=np.int64), np.asarray(only_second, dtype=np.int64)
    n = np.asarray(num_queries, dtype=np.int64)
    m = b + c
    split_low, split_high = exact_interval(b, m, confidence)
    _, none_high = exact_interval(np.zeros_like(n), n, confidence)
    with np.errstate(invalid="ignore", divide="ignore"):
        low = np.where(m > 0, (2 * split_low - 1) * m / n, -none_high)
        high = np.where(m > 0, (2 * split_high - 1) * m / n, none_high)
        difference = (b - c) / n
    # exact two-sided McNemar: twice the smaller tail of Binomial(m, 1/2), at most 1 (scipy's binomtest)
    p_value = np.where(m > 0, np.minimum(1.0, 2 * _stats().binom.cdf(np.minimum(b, c), m, 0.5)), 1.0)
    return PairedDifference(n, b, c, difference, low, high, p_value)
