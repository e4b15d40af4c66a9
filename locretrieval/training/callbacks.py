"""Validation by localization: the benchmark core run on the network being trained."""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import lightning as L
import numpy as np
import pandas as pd
import torch

from locretrieval.benchmark import (
    BenchmarkResult,
    BenchmarkSettings,
    benchmark,
    build_rankings,
    relevances,
    run_sfm_shard,
    sfm_within_budget,
)
from locretrieval.config import ConfigError, require
from locretrieval.groundtruth import GroundTruth, RelevanceScope
from locretrieval.metrics.retrieval import METRICS
from locretrieval.models import GlobalDescriptor, NetworkDescriptor
from locretrieval.models.extraction import ExtractionSettings, Preprocessing
from locretrieval.retrieval import EMPTY, Ranking, relevant_hits
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.retrieval.index import search
from locretrieval.scene import ImageSet, Scene
from locretrieval.training.data import RelevanceBatchSampler
from locretrieval.training.distributed import Ranks, describe_across_ranks
from locretrieval.training.relevance import TrainingPairs

log = logging.getLogger(__name__)

Reported = TypeVar("Reported")

#: The ranking name of the network being trained in validation tables.
TRAINED = "trained"


#: The prefixes of the validation metrics: ``val/`` on the queries a run may select on (checkpoints,
#: early stopping, a sweep's objective), ``held_out/`` on the validation queries kept out of every
#: selection (``training.validation.held_out``), whose figures a sweep reports.
SELECTION, HELD_OUT = "val", "held_out"
#: The subsets of the validation queries the two prefixes are computed on.
SPLIT_SUBSETS = {SELECTION: "selection", HELD_OUT: "held_out"}
#: Columns of ``validation.csv`` (`LocalizationValidation.history_table`), and what a figure's
#: interval is when a checkpoint of an earlier version kept none.
VALIDATION_COLUMNS = ["epoch", "metric", "value", "low", "high", "num_queries"]
UNKNOWN_DETAIL = [float("nan"), float("nan"), float("nan")]
#: Columns of ``validation_queries.csv.gz`` (`LocalizationValidation.outcome_table`).
OUTCOME_COLUMNS = ["ranking", "epoch", "metric", "query", "split", "localized"]
#: Points of % localized (the half width of a 95 % interval at 50 %) beyond which the queries a run
#: selects on are too few to tell its epochs or trials apart (`LocalizationValidation.warn_coarse`).
COARSE_POINTS = 10.0


@dataclass(frozen=True)
class Figure:
    """A validation figure: its ``value`` (% localized, or a retrieval metric's fraction), its
    interval ``low`` to ``high`` (`locretrieval.metrics.uncertainty`) and the ``num_queries`` it is over."""

    value: float
    low: float
    high: float
    num_queries: int


def localization_key(paradigm: str, method: str, k: int, position: float, rotation: float) -> str:
    """``<paradigm>/<method>/k<k>/<X>m_<Y>deg``: a localization figure's key after its prefix."""
    return f"{paradigm}/{method}/k{k}/{position:g}m_{rotation:g}deg"


def figure_rows(
    result: BenchmarkResult, ranking: str, retrieval_ks: Collection[int], subset: str = "all", prefix: str = SELECTION
) -> dict[str, Figure]:
    """``{key: Figure}`` of one ranking on a subset of the queries: ``<prefix>/<paradigm>/<method>/k<k>/<X>m_<Y>deg``
    (% localized) and ``<prefix>/retrieval/<groundtruth>/<metric>@<k>`` for ``k`` in ``retrieval_ks``."""
    figures = {}
    table = result.localization
    rows = table[(table["subset"] == subset) & (table["ranking"] == ranking)]
    for row in rows.itertuples():
        key = localization_key(row.paradigm, row.method, row.k, row.position_threshold_m, row.rotation_threshold_deg)
        figures[f"{prefix}/{key}"] = Figure(
            float(row.localized_pct), float(row.localized_low_pct), float(row.localized_high_pct), int(row.num_queries)
        )
    if len(result.retrieval):
        table = result.retrieval
        rows = table[(table["subset"] == subset) & (table["ranking"] == ranking) & table["k"].isin(list(retrieval_ks))]
        for row in rows.itertuples():
            figures[f"{prefix}/retrieval/{row.groundtruth}/{row.metric}@{row.k}"] = Figure(
                float(row.value), float(row.value_low), float(row.value_high), int(row.num_queries)
            )
    return figures


def metric_rows(
    result: BenchmarkResult, ranking: str, retrieval_ks: Collection[int], subset: str = "all", prefix: str = SELECTION
) -> dict[str, float]:
    """The values of `figure_rows`: what a validation logs."""
    return {key: figure.value for key, figure in figure_rows(result, ranking, retrieval_ks, subset, prefix).items()}


def query_outcomes(result: BenchmarkResult, ranking: str, queries: Sequence[str]) -> dict[str, np.ndarray]:
    """``{localization key: int8 [Q]}`` of one ranking: each of ``queries`` localized (1) or not (0), -1
    where it was not evaluated (no reference pose); the keys as `localization_key`'s."""
    rows = result.query_localized[result.query_localized["ranking"] == ranking]
    position = pd.Index(queries)
    outcomes = {}
    keys = ["paradigm", "method", "k", "position_threshold_m", "rotation_threshold_deg"]
    for (paradigm, method, k, x, y), group in rows.groupby(keys, sort=False):
        outcome = np.full(len(queries), -1, dtype=np.int8)
        outcome[position.get_indexer(group["query"])] = group["localized"].to_numpy(dtype=np.int8)
        outcomes[localization_key(paradigm, method, k, x, y)] = outcome
    return outcomes


def every_validation_settings(settings: BenchmarkSettings) -> BenchmarkSettings:
    """``settings`` with only the paradigms that run at every validation (those without SfM,
    `Paradigm.uses_sfm`)."""
    return dataclasses.replace(settings, paradigms=settings.paradigms.only(lambda paradigm: not paradigm.uses_sfm))


def every_validation_metrics(settings: BenchmarkSettings, groundtruths: Collection[str]) -> list[str]:
    """The `metric_rows` keys logged at every validation (those a checkpoint or early stopping may
    monitor): the localization of the paradigms without SfM per method, k and threshold, and the retrieval
    metrics against each ground truth in ``groundtruths`` at every k within the ranking depth."""
    return validation_metrics(settings, groundtruths, with_sfm=False)


def validation_metrics(settings: BenchmarkSettings, groundtruths: Collection[str], with_sfm: bool) -> list[str]:
    """The `metric_rows` keys a validation logs: `every_validation_metrics`, and ``with_sfm`` those
    of the SfM paradigms too (a validation every ``sfm_every_n_epochs``)."""
    paradigms = (settings if with_sfm else every_validation_settings(settings)).paradigms
    keys = [
        f"{SELECTION}/{localization_key(name, method, k, position, rotation)}"
        for name in paradigms.enabled()
        for method in getattr(paradigms, name).method_names()
        for k in getattr(paradigms, name).k
        for position, rotation in settings.metrics.thresholds
    ]
    ks = [k for k in settings.paradigms.ks() if k <= settings.retrieval.depth]
    return keys + [
        f"{SELECTION}/retrieval/{groundtruth}/{metric}@{k}"
        for groundtruth in groundtruths
        for metric in METRICS
        for k in ks
    ]


class LocalizationValidation(L.Callback):
    """Every ``every_n_epochs`` (and once before training): describe the validation ``scene``
    with the current network, rank with faiss, run paradigm 1 and the retrieval metrics on all
    its queries; every ``sfm_every_n_epochs`` also the SfM paradigms (features and matches are
    cached in ``cache_dir``, so only new pairs are matched). Metrics are logged as
    `metric_rows` keys, so ``ModelCheckpoint`` and early stopping can monitor them; the
    ``reference_models`` (descriptors by name, e.g. DenseVLAD), ground-truth and random rankings
    are benchmarked once, logged as ``reference/<name>/...``.
    ``relevance_scope``: the retrieval metrics' relevance (`relevances`). ``gallery_queries`` fixed
    validation queries have their top ``gallery_k`` logged as an image at each validation.
    ``headline``: the metrics a validation prints (the training report's gap rows).
    ``held_out``: the share of the validation queries kept out of every selection (drawn with
    ``budget_seed``): ``val/`` metrics are on the others (what checkpoints, early stopping and a
    sweep's objective read), ``held_out/`` metrics on them (what a sweep reports); 0: ``val/`` on all.
    ``history`` holds every validation (epoch -1: before training), ``details`` each figure's
    interval and number of queries (`Figure`), ``outcomes`` each query's outcome per localization
    key (`query_outcomes`); ``reference*`` the same of the reference rankings.

    Under DDP every rank takes part (`locretrieval.training.distributed`): each describes a share
    of the images and every rank holds all descriptors; each does its share of the SfM paradigms'
    work (`Ranks.shard`) into the shared cache; rank 0 then runs the benchmark (the SfM results
    read from the cache), logs the gallery and prints, and every rank logs its metrics. The
    reference models are described by rank 0 (once per run, cached). The metrics equal a single
    process's; a rank whose share raises ends every rank with its error."""

    def __init__(
        self,
        scene: Scene,
        groundtruths: Mapping[str, GroundTruth],
        settings: BenchmarkSettings,
        preprocessing: Preprocessing,
        extraction: ExtractionSettings,
        cache_dir: str | Path | None,
        random_seed: int | None,
        relevance_scope: RelevanceScope,
        every_n_epochs: int,
        sfm_every_n_epochs: int | None,
        gallery_queries: int,
        gallery_k: int,
        gallery_size: int,
        reference_models: Mapping[str, GlobalDescriptor] | None = None,
        headline: Sequence[str] = (),
        budget_minutes: float | None = None,
        budget_seed: int = 0,
        held_out: float = 0.0,
    ) -> None:
        require(every_n_epochs >= 1, "every_n_epochs", f"must be >= 1, got {every_n_epochs}")
        require(
            sfm_every_n_epochs is None or sfm_every_n_epochs >= 1,
            "sfm_every_n_epochs",
            f"must be >= 1 or null, got {sfm_every_n_epochs}",
        )
        require(
            gallery_queries >= 0 and gallery_k >= 1,
            "gallery_queries",
            f"must be >= 0 queries of gallery_k >= 1 images, got {gallery_queries}, {gallery_k}",
        )
        self.scene, self.groundtruths, self.settings = scene, dict(groundtruths), settings
        self.relevance_scope = relevance_scope
        self.relevance = relevances(self.groundtruths, relevance_scope)
        self.preprocessing, self.extraction = preprocessing, extraction
        self.every_n_epochs, self.sfm_every_n_epochs = every_n_epochs, sfm_every_n_epochs
        require(0 <= held_out < 1, "held_out", f"must be a share in [0, 1), got {held_out}")
        self.cache_dir, self.random_seed = cache_dir, random_seed
        self.history: list[dict[str, float]] = []
        self.details: list[dict[str, list[float]]] = []  # per validation: key -> [low, high, num_queries]
        self.outcomes: list[dict[str, np.ndarray]] = []  # per validation: localization key -> int8 per query
        self.reference: dict[str, dict[str, float]] = {}
        self.reference_details: dict[str, dict[str, list[float]]] = {}
        self.reference_outcomes: dict[str, dict[str, np.ndarray]] = {}
        self.sfm_stages: dict[str, dict] = {}  # per validation with SfM: its stages' seconds and work
        self.gallery_queries, self.gallery_k, self.gallery_size = gallery_queries, gallery_k, gallery_size
        self.gallery_rows = self._gallery_rows()
        self.budget_minutes, self.budget_seed = budget_minutes, budget_seed
        self.held_out = float(held_out)
        self.subsets, self.splits = self._split_queries()
        self.validated_queries: list[str] | None = None  # with a budget: the queries every validation uses
        # relevance marks by relative pose, else the first ground truth there is
        self.gallery_groundtruth = (
            "relative_pose" if "relative_pose" in self.relevance else next(iter(self.relevance), None)
        )
        self.galleries: dict[str, np.ndarray] = {}  # "before" training and the "last" validation
        self.reference_models = dict(reference_models or {})
        self.headline = list(headline)
        self._thumbnails = None

    def _gallery_rows(self) -> np.ndarray:
        """A fixed set of ``gallery_queries`` posed queries: the same at every validation."""
        posed = np.flatnonzero(self.scene.queries.has_pose)
        return np.sort(
            np.random.default_rng(0).choice(posed, size=min(self.gallery_queries, len(posed)), replace=False)
        )

    def _split_queries(self) -> tuple[dict[str, np.ndarray], dict[str, str]]:
        """The query subsets a validation's benchmark computes (``all``, and with ``held_out`` the
        selection and held-out queries, drawn with ``budget_seed``), and the subset of each metric
        prefix (`SELECTION`, `HELD_OUT`)."""
        count = len(self.scene.queries)
        everything = np.ones(count, dtype=bool)
        if not self.held_out:
            return {"all": everything}, {SELECTION: "all"}
        held = np.zeros(count, dtype=bool)
        held[np.random.default_rng(self.budget_seed).permutation(count)[: round(self.held_out * count)]] = True
        if held.all() or not held.any():
            raise ConfigError(
                f"training.validation.held_out: {self.held_out:g} of {count} validation queries leaves "
                f"{'none to select on' if held.all() else 'none held out'}; validate on more queries or change it"
            )
        return {"all": everything, "selection": ~held, "held_out": held}, dict(SPLIT_SUBSETS)

    def resolution(self) -> str:
        """The queries of each split and what one of them is worth, in words (the validation log's)."""
        counts = {prefix: int(self.subsets[subset].sum()) for prefix, subset in self.splits.items()}
        names = {SELECTION: "selected on", HELD_OUT: "held out"}
        return "; ".join(
            f"{count} queries {names[prefix]} (one query: {100 / count:.3g} points)" for prefix, count in counts.items()
        )

    @property
    def selected_queries(self) -> int:
        """How many validation queries the ``val/`` metrics are over."""
        return int(self.subsets[self.splits[SELECTION]].sum())

    def warn_coarse(self) -> None:
        """A warning when the queries selected on are too few to tell a few points apart: the half
        width of a 95 % interval at 50 % localized is over `COARSE_POINTS`."""
        count = self.selected_queries
        half_width = 100 * 1.96 * math.sqrt(0.25 / count)
        if half_width > COARSE_POINTS:
            log.warning(
                "validation selects on %d queries: one query is %.3g points and a 95 %% interval at 50 %% localized "
                "spans +-%.1f points, so epochs (and a sweep's trials) closer than that are not told apart; "
                "validate on more queries for finer differences (a larger render, training.validation.max_queries)",
                count,
                100 / count,
                half_width,
            )

    def _keep_queries(self, rows: np.ndarray) -> None:
        """Validate on the queries ``rows`` only (sorted indices), from now on."""
        self.scene = dataclasses.replace(self.scene, queries=self.scene.queries.subset(rows))
        self.groundtruths = {name: groundtruth.of_queries(rows) for name, groundtruth in self.groundtruths.items()}
        self.relevance = relevances(self.groundtruths, self.relevance_scope)
        self.subsets, self.splits = self._split_queries()
        self.gallery_rows = self._gallery_rows()
        self.validated_queries = list(self.scene.queries.names)

    def _settle_queries(self, rankings: list[Ranking], ranks: Ranks, started: float) -> np.ndarray:
        """With ``budget_minutes``: the first validation's SfM work on ``rankings``, its queries in an
        order drawn with ``budget_seed``, until the budget (counted from ``started``) is spent
        (`sfm_within_budget`); the queries it reached, sorted, which every validation then uses. A
        `ConfigError` when the budget is spent before one query is localized."""
        budget = float(self.budget_minutes) * 60
        order = np.random.default_rng(self.budget_seed).permutation(len(self.scene.queries))
        settings = self._settings(self.sfm_every_n_epochs is not None)
        described = time.perf_counter() - started

        def localize() -> tuple[int, float]:
            return sfm_within_budget(self.scene, rankings, settings, self.cache_dir, order, budget - described)

        reached, seconds = ranks.first(localize)
        if described + seconds > budget and reached <= 1:
            raise ConfigError(
                f"training.validation.budget_minutes: {self.budget_minutes:g} min cannot hold one validation query: "
                f"describing the {len(self.scene.database) + len(self.scene.queries):,} validation images took "
                f"{described:.1f} s and localizing {reached} query {seconds:.1f} s. Raise the budget, lower "
                "training.validation.sfm_max_keypoints, or validate without the SfM paradigms "
                "(callbacks.localization_validation.sfm_every_n_epochs=null)"
            )
        rows = np.sort(order[:reached])
        log.info(
            "validation budget of %g min: %d of %d queries reached (describing %.1f s, their SfM work %.1f s, "
            "%.2f s a query); every validation localizes them",
            self.budget_minutes,
            reached,
            len(order),
            described,
            seconds,
            seconds / max(reached, 1),
        )
        return rows

    def _settings(self, with_sfm: bool) -> BenchmarkSettings:
        """The benchmark settings of a validation: every paradigm, or those without SfM (`Paradigm.uses_sfm`)."""
        return self.settings if with_sfm else every_validation_settings(self.settings)

    def _references(self, ranks: Ranks) -> list[Ranking]:
        """The rankings the trained network is compared with: the reference models' (described by
        rank 0, cached in ``cache_dir``), the ground truths' and the random one."""
        described = {
            name: ranks.first(lambda model=model: describe_scene(model, self.scene, self.cache_dir))
            for name, model in self.reference_models.items()
        }
        return build_rankings(self.scene, described, self.groundtruths, self.settings.retrieval, self.random_seed)

    def _trained_ranking(self, network, ranks: Ranks) -> Ranking:
        """The ranking of ``network`` (a `RetrievalNet`) on the validation scene, every rank
        describing its share of the images."""
        model = NetworkDescriptor(TRAINED, network, self.preprocessing, self.extraction)
        described = describe_scene(model, self.scene, None, lambda images: describe_across_ranks(model, images, ranks))
        return build_rankings(self.scene, {TRAINED: described}, {}, self.settings.retrieval, random_seed=None)[0]

    def _run_sfm_shards(self, rankings: list[Ranking], settings: BenchmarkSettings, ranks: Ranks) -> None:
        """Under DDP, each rank's share of the SfM paradigms' work on ``rankings`` (`Ranks.shard`:
        its rank of all), into the cache the benchmark then reads it from."""
        if ranks.count == 1 or not settings.paradigms.sfm_paradigms():
            return
        ranks.gather(lambda: run_sfm_shard(self.scene, rankings, settings, self.cache_dir, ranks.shard))

    def _benchmark(
        self, rankings: list[Ranking], with_sfm: bool, ranks: Ranks, report: Callable[[BenchmarkResult], Reported]
    ) -> Reported:
        """``report(result)`` of the benchmark of ``rankings`` (run on rank 0, the SfM work shared
        by every rank), on every rank."""
        settings = self._settings(with_sfm)
        self._run_sfm_shards(rankings, settings, ranks)
        return ranks.first(
            lambda: report(benchmark(self.scene, rankings, settings, self.subsets, self.cache_dir, self.relevance))
        )

    def _wants_sfm(self, epoch: int) -> bool:
        return self.sfm_every_n_epochs is not None and (epoch < 0 or (epoch + 1) % self.sfm_every_n_epochs == 0)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.history:  # resumed: the curve goes on (on the queries it was validated on)
            return
        ranks = Ranks.of(trainer)
        rankings, trained = self._references(ranks), None
        if self.budget_minutes is not None:
            started = time.perf_counter()
            trained = self._trained_ranking(pl_module.network, ranks)
            rows = self._settle_queries([*rankings, trained], ranks, started)
            self._keep_queries(rows)
            rankings, trained = [r.of_queries(rows) for r in rankings], trained.of_queries(rows)
        if rankings:

            def report(result: BenchmarkResult) -> dict[str, tuple[dict[str, Figure], dict[str, np.ndarray]]]:
                if result.sfm_stages:
                    self.sfm_stages["references"] = result.sfm_stages
                return {r.name: self._measured(result, r.name) for r in rankings}

            measured = self._benchmark(rankings, self.sfm_every_n_epochs is not None, ranks, report)
            for name, (figures, outcomes) in measured.items():
                self.reference[name] = {key: figure.value for key, figure in figures.items()}
                self.reference_details[name] = {key: figure_detail(figure) for key, figure in figures.items()}
                self.reference_outcomes[name] = outcomes
                if trainer.is_global_zero:
                    log.info("reference %s: %s", name, headline_line(self.reference[name], self.headline))
                if trainer.logger is not None:
                    trainer.logger.log_metrics(
                        {f"reference/{name}/{key}": value for key, value in self.reference[name].items()}, step=0
                    )
        if trainer.is_global_zero:
            self.warn_coarse()
        metrics = self._record(trainer, pl_module, epoch=-1, ranking=trained)
        if trainer.logger is not None:  # before training: no pl_module.log outside the loop
            trainer.logger.log_metrics(metrics, step=trainer.global_step)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        epoch = trainer.current_epoch
        if (epoch + 1) % self.every_n_epochs:
            return
        # logged by every rank, where checkpointing monitors them; each rank holds rank 0's values
        # (`Ranks.first`), so their maximum over the ranks is that value, exactly (a mean might round)
        for key, value in self._record(trainer, pl_module, epoch).items():
            pl_module.log(key, value, sync_dist=True, reduce_fx="max")

    def _measured(self, result: BenchmarkResult, ranking: str) -> tuple[dict[str, Figure], dict[str, np.ndarray]]:
        """One ranking's figures on each split (`figure_rows`) and its per-query outcomes (`query_outcomes`)."""
        ks = self.settings.paradigms.ks()
        figures = {
            key: figure
            for prefix, subset in self.splits.items()
            for key, figure in figure_rows(result, ranking, ks, subset, prefix).items()
        }
        return figures, query_outcomes(result, ranking, self.scene.queries.names)

    def _record(
        self, trainer: L.Trainer, pl_module: L.LightningModule, epoch: int, ranking: Ranking | None = None
    ) -> dict[str, float]:
        """Validate the module's network after ``epoch`` (-1: before training; its ``ranking`` when
        computed already), keep the figures and per-query outcomes (every rank) and, on rank 0, print
        them and log the gallery of the fixed validation queries."""
        ranks = Ranks.of(trainer)
        ranking = ranking if ranking is not None else self._trained_ranking(pl_module.network, ranks)

        def report(result: BenchmarkResult) -> tuple[dict[str, Figure], dict[str, np.ndarray]]:
            if result.sfm_stages:
                self.sfm_stages[f"epoch {epoch}"] = result.sfm_stages
            figures, outcomes = self._measured(result, TRAINED)
            metrics = {key: figure.value for key, figure in figures.items()}
            log.info(
                "validation after epoch %d, %s:\n%s",
                epoch,
                self.resolution(),
                headline_table({TRAINED: metrics, **self.reference}, self.headline, self.selected_queries),
            )
            if len(self.gallery_rows):
                self._log_gallery(trainer, ranking, epoch)
            return figures, outcomes

        figures, outcomes = self._benchmark([ranking], self._wants_sfm(epoch), ranks, report)
        metrics = {key: figure.value for key, figure in figures.items()}
        self.history.append({"epoch": epoch, **metrics})
        self.details.append({key: figure_detail(figure) for key, figure in figures.items()})
        self.outcomes.append(outcomes)
        return metrics

    def _log_gallery(self, trainer: L.Trainer, ranking: Ranking, epoch: int) -> None:
        """The top ``gallery_k`` of the gallery queries, framed relevant or not under
        ``gallery_groundtruth``, to TensorBoard (``val/gallery``) and the training report."""
        from lightning.pytorch.loggers import TensorBoardLogger

        from locretrieval.report.gallery import Thumbnails, gallery_image

        if self._thumbnails is None:
            self._thumbnails = Thumbnails(
                self.gallery_size, Path(self.cache_dir) / "thumbnails" if self.cache_dir is not None else None
            )
        indices = ranking.indices[self.gallery_rows, : self.gallery_k]
        groundtruth = self.gallery_groundtruth
        relevant = (
            relevant_hits(indices, self.relevance[groundtruth][self.gallery_rows]) if groundtruth is not None else None
        )
        queries, database = self.scene.queries.paths, self.scene.database.paths
        image = gallery_image([queries[q] for q in self.gallery_rows], database, indices, relevant, self._thumbnails)
        self.galleries["before" if epoch < 0 else "last"] = image
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                logger.experiment.add_image("val/gallery", image, global_step=trainer.global_step, dataformats="HWC")

    def history_table(self) -> pd.DataFrame:
        """Tidy ``epoch, metric, value, low, high, num_queries`` of every validation (`VALIDATION_COLUMNS`;
        the interval unknown, NaN, for the validations of a checkpoint of an earlier version)."""
        rows = [
            (entry["epoch"], key, value, *details.get(key, UNKNOWN_DETAIL))
            for entry, details in itertools.zip_longest(self.history, self.details, fillvalue={})
            for key, value in entry.items()
            if key != "epoch"
        ]
        return pd.DataFrame(rows, columns=VALIDATION_COLUMNS)

    def outcome_table(self) -> pd.DataFrame:
        """Tidy per-query outcomes (`OUTCOME_COLUMNS`): the trained network's at each validation,
        the reference rankings' (epoch -1); ``split`` is the query's (`SELECTION`, `HELD_OUT`)."""
        names = np.asarray(self.scene.queries.names, dtype=object)
        split = np.full(len(names), SELECTION, dtype=object)
        if HELD_OUT in self.splits:
            split[self.subsets[self.splits[HELD_OUT]]] = HELD_OUT
        runs = [(TRAINED, entry["epoch"], outcomes) for entry, outcomes in zip(self.history, self.outcomes)]
        runs += [(name, -1, outcomes) for name, outcomes in self.reference_outcomes.items()]
        frames = [
            pd.DataFrame(
                {
                    "ranking": ranking,
                    "epoch": epoch,
                    "metric": key,
                    "query": names,
                    "split": split,
                    "localized": outcome,
                }
            )[outcome >= 0]
            for ranking, epoch, outcomes in runs
            for key, outcome in outcomes.items()
        ]
        return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=OUTCOME_COLUMNS)

    def state_dict(self) -> dict:
        def tensors(outcomes: Mapping[str, np.ndarray]) -> dict[str, torch.Tensor]:  # a safe load reads tensors
            return {key: torch.from_numpy(outcome) for key, outcome in outcomes.items()}

        state = {
            "history": self.history,
            "reference": self.reference,
            "galleries": {key: torch.from_numpy(image) for key, image in self.galleries.items()},
            "details": self.details,
            "reference_details": self.reference_details,
            "outcomes": [tensors(outcomes) for outcomes in self.outcomes],
            "reference_outcomes": {name: tensors(outcomes) for name, outcomes in self.reference_outcomes.items()},
        }
        return state | ({"validated_queries": self.validated_queries} if self.validated_queries is not None else {})

    def load_state_dict(self, state_dict: dict) -> None:
        def arrays(outcomes: Mapping[str, torch.Tensor]) -> dict[str, np.ndarray]:
            return {key: outcome.numpy() for key, outcome in outcomes.items()}

        self.history = list(state_dict["history"])
        self.reference = dict(state_dict["reference"])
        self.galleries = {key: image.numpy() for key, image in state_dict.get("galleries", {}).items()}
        self.details = list(state_dict.get("details", []))
        self.reference_details = dict(state_dict.get("reference_details", {}))
        self.outcomes = [arrays(outcomes) for outcomes in state_dict.get("outcomes", [])]
        self.reference_outcomes = {
            name: arrays(outcomes) for name, outcomes in state_dict.get("reference_outcomes", {}).items()
        }
        if state_dict.get("validated_queries") is not None:  # a run with a budget goes on with its queries
            position = {name: row for row, name in enumerate(self.scene.queries.names)}
            missing = [name for name in state_dict["validated_queries"] if name not in position]
            if missing:
                raise ValueError(
                    f"the checkpoint was validated on queries the validation scene does not have: {missing[:5]}"
                )
            self._keep_queries(np.sort([position[name] for name in state_dict["validated_queries"]]))


def figure_detail(figure: Figure) -> list[float]:
    """``[low, high, num_queries]`` of a figure: what a checkpoint keeps of it besides its value."""
    return [figure.low, figure.high, figure.num_queries]


def headline_line(metrics: Mapping[str, float], keys: Sequence[str]) -> str:
    """The metrics ``keys`` of a validation (those present) as one line."""
    return ", ".join(f"{key.removeprefix('val/')}={metrics[key]:.3g}" for key in keys if key in metrics)


def headline_table(
    rankings: Mapping[str, Mapping[str, float]], keys: Sequence[str], num_queries: int | None = None
) -> str:
    """The metrics ``keys`` of several rankings as a console table (rankings as rows; none: their count);
    with ``num_queries`` each % localized also as the queries it is (``43.8 (7/16)``)."""

    def cell(key: str, value: float | None) -> str | None:
        if value is None or not np.isfinite(value):
            return None
        count = (
            f" ({round(value * num_queries / 100)}/{num_queries})" if num_queries and "/retrieval/" not in key else ""
        )
        return f"{value:.3g}{count}"

    table = pd.DataFrame(
        {
            name: {key.removeprefix(f"{SELECTION}/"): cell(key, metrics.get(key)) for key in keys}
            for name, metrics in rankings.items()
        }
    ).T
    table = table.dropna(axis=1, how="all")
    if not len(table.columns):
        return f"{len(next(iter(rankings.values()), {}))} metrics (no headline configured)"
    return table.fillna("–").to_string()


class HardNegativeMining(L.Callback):
    """Every ``every_n_steps`` training steps, describe the training images with the current network (under
    DDP, each rank a share) and
    give the sampler each anchor's ``per_anchor`` highest-ranked images among those it may be
    pushed from. The sampler builds batches lazily, so they apply from the next batches it builds
    (a DataLoader prefetches a few)."""

    def __init__(
        self,
        sets: Sequence[ImageSet],
        pairs: TrainingPairs,
        sampler: RelevanceBatchSampler,
        preprocessing: Preprocessing,
        extraction: ExtractionSettings,
        every_n_steps: int,
        per_anchor: int,
    ) -> None:
        require(
            every_n_steps >= 1,
            "every_n_steps",
            f"must be >= 1 (~miner on the command line: no mining), got {every_n_steps}",
        )
        require(per_anchor >= 1, "per_anchor", f"must be >= 1, got {per_anchor}")
        self.sets, self.pairs, self.sampler = list(sets), pairs, sampler
        self.every, self.per_anchor = every_n_steps, per_anchor
        self.preprocessing, self.extraction = preprocessing, extraction
        self.mined_at_step = 0

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch, batch_idx: int) -> None:
        step = trainer.global_step
        if step and step % self.every == 0 and step != self.mined_at_step:  # once per step under gradient accumulation
            self.mine(pl_module.network, Ranks.of(trainer))
            self.mined_at_step = step

    def mine(self, network, ranks: Ranks) -> None:
        """Hard negatives of every anchor by ``network`` (a `RetrievalNet`), given to the sampler;
        under DDP every rank describes a share of the images and mines the same negatives."""
        model = NetworkDescriptor("mining", network, self.preprocessing, self.extraction)
        descriptors = np.concatenate([describe_across_ranks(model, images, ranks) for images in self.sets])
        anchors = self.sampler.anchors
        related = np.diff(self.pairs.related.indptr)
        depth = min(len(descriptors), self.per_anchor + 1 + int(related[anchors].max()))
        top = search(descriptors[anchors], descriptors, depth, "mining", 4096).indices
        valid = top != EMPTY
        safe = np.where(valid, top, anchors[:, None])
        negative = (
            valid & (safe != anchors[:, None]) & ~self.pairs.related[anchors[:, None], safe].toarray().astype(bool)
        )
        rank = np.cumsum(negative, axis=1)  # keep the first per_anchor negatives of each row
        keep = negative & (rank <= self.per_anchor)
        self.sampler.set_hard_negatives({int(a): top[row][keep[row]] for row, a in enumerate(anchors)})
        log.info("hard negatives mined for %d anchors", len(anchors))
