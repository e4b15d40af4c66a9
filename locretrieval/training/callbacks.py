"""Validation by localization: the benchmark core run on the network being trained."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Collection, Mapping, Sequence
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


def metric_rows(result: BenchmarkResult, ranking: str, retrieval_ks: Collection[int]) -> dict[str, float]:
    """``{key: value}`` of one ranking on all queries: ``val/<paradigm>/<method>/k<k>/<X>m_<Y>deg``
    (% localized) and ``val/retrieval/<groundtruth>/<metric>@<k>`` for ``k`` in ``retrieval_ks``."""
    metrics = {}
    table = result.localization
    rows = table[(table["subset"] == "all") & (table["ranking"] == ranking)]
    for row in rows.itertuples():
        threshold = f"{row.position_threshold_m:g}m_{row.rotation_threshold_deg:g}deg"
        metrics[f"val/{row.paradigm}/{row.method}/k{row.k}/{threshold}"] = float(row.localized_pct)
    if len(result.retrieval):
        table = result.retrieval
        rows = table[(table["subset"] == "all") & (table["ranking"] == ranking) & table["k"].isin(list(retrieval_ks))]
        for row in rows.itertuples():
            metrics[f"val/retrieval/{row.groundtruth}/{row.metric}@{row.k}"] = float(row.value)
    return metrics


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
    thresholds = [f"{position:g}m_{rotation:g}deg" for position, rotation in settings.metrics.thresholds]
    keys = [
        f"val/{name}/{method}/k{k}/{threshold}"
        for name in paradigms.enabled()
        for method in getattr(paradigms, name).method_names()
        for k in getattr(paradigms, name).k
        for threshold in thresholds
    ]
    ks = [k for k in settings.paradigms.ks() if k <= settings.retrieval.depth]
    return keys + [
        f"val/retrieval/{groundtruth}/{metric}@{k}" for groundtruth in groundtruths for metric in METRICS for k in ks
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
    ``history`` holds every validation (epoch -1: before training).

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
        self.cache_dir, self.random_seed = cache_dir, random_seed
        self.subsets = {"all": np.ones(len(scene.queries), dtype=bool)}
        self.history: list[dict[str, float]] = []
        self.reference: dict[str, dict[str, float]] = {}
        self.sfm_stages: dict[str, dict] = {}  # per validation with SfM: its stages' seconds and work
        self.gallery_queries, self.gallery_k, self.gallery_size = gallery_queries, gallery_k, gallery_size
        self.gallery_rows = self._gallery_rows()
        self.budget_minutes, self.budget_seed = budget_minutes, budget_seed
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

    def _keep_queries(self, rows: np.ndarray) -> None:
        """Validate on the queries ``rows`` only (sorted indices), from now on."""
        self.scene = dataclasses.replace(self.scene, queries=self.scene.queries.subset(rows))
        self.groundtruths = {name: groundtruth.of_queries(rows) for name, groundtruth in self.groundtruths.items()}
        self.relevance = relevances(self.groundtruths, self.relevance_scope)
        self.subsets = {"all": np.ones(len(rows), dtype=bool)}
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
        if ranks.count == 1 or not settings.paradigms.sfm_stages():
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

            def report(result: BenchmarkResult) -> dict[str, dict[str, float]]:
                if result.sfm_stages:
                    self.sfm_stages["references"] = result.sfm_stages
                return {r.name: metric_rows(result, r.name, self.settings.paradigms.ks()) for r in rankings}

            self.reference = self._benchmark(rankings, self.sfm_every_n_epochs is not None, ranks, report)
            for name, metrics in self.reference.items():
                if trainer.is_global_zero:
                    log.info("reference %s: %s", name, headline_line(metrics, self.headline))
                if trainer.logger is not None:
                    trainer.logger.log_metrics(
                        {k.replace("val/", f"reference/{name}/"): v for k, v in metrics.items()}, step=0
                    )
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

    def _record(
        self, trainer: L.Trainer, pl_module: L.LightningModule, epoch: int, ranking: Ranking | None = None
    ) -> dict[str, float]:
        """Validate the module's network after ``epoch`` (-1: before training; its ``ranking`` when
        computed already), keep the metrics (every rank) and, on rank 0, print them and log the
        gallery of the fixed validation queries."""
        ranks = Ranks.of(trainer)
        ranking = ranking if ranking is not None else self._trained_ranking(pl_module.network, ranks)

        def report(result: BenchmarkResult) -> dict[str, float]:
            if result.sfm_stages:
                self.sfm_stages[f"epoch {epoch}"] = result.sfm_stages
            metrics = metric_rows(result, TRAINED, self.settings.paradigms.ks())
            log.info(
                "validation after epoch %d:\n%s",
                epoch,
                headline_table({TRAINED: metrics, **self.reference}, self.headline),
            )
            if len(self.gallery_rows):
                self._log_gallery(trainer, ranking, epoch)
            return metrics

        metrics = self._benchmark([ranking], self._wants_sfm(epoch), ranks, report)
        self.history.append({"epoch": epoch, **metrics})
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
        """Tidy ``epoch, metric, value`` of every validation."""
        rows = [
            (entry["epoch"], key, value) for entry in self.history for key, value in entry.items() if key != "epoch"
        ]
        return pd.DataFrame(rows, columns=["epoch", "metric", "value"])

    def state_dict(self) -> dict:
        galleries = {
            key: torch.from_numpy(image) for key, image in self.galleries.items()
        }  # tensors: a safe load reads them
        state = {"history": self.history, "reference": self.reference, "galleries": galleries}
        return state | ({"validated_queries": self.validated_queries} if self.validated_queries is not None else {})

    def load_state_dict(self, state_dict: dict) -> None:
        self.history = list(state_dict["history"])
        self.reference = dict(state_dict["reference"])
        self.galleries = {key: image.numpy() for key, image in state_dict.get("galleries", {}).items()}
        if state_dict.get("validated_queries") is not None:  # a run with a budget goes on with its queries
            position = {name: row for row, name in enumerate(self.scene.queries.names)}
            missing = [name for name in state_dict["validated_queries"] if name not in position]
            if missing:
                raise ValueError(
                    f"the checkpoint was validated on queries the validation scene does not have: {missing[:5]}"
                )
            self._keep_queries(np.sort([position[name] for name in state_dict["validated_queries"]]))


def headline_line(metrics: Mapping[str, float], keys: Sequence[str]) -> str:
    """The metrics ``keys`` of a validation (those present) as one line."""
    return ", ".join(f"{key.removeprefix('val/')}={metrics[key]:.3g}" for key in keys if key in metrics)


def headline_table(rankings: Mapping[str, Mapping[str, float]], keys: Sequence[str]) -> str:
    """The metrics ``keys`` of several rankings as a console table (rankings as rows; none: their count)."""
    table = pd.DataFrame(
        {name: {key.removeprefix("val/"): metrics.get(key) for key in keys} for name, metrics in rankings.items()}
    ).T
    table = table.dropna(axis=1, how="all")
    if not len(table.columns):
        return f"{len(next(iter(rankings.values()), {}))} metrics (no headline configured)"
    return table.to_string(float_format=lambda value: f"{value:.3g}")


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
