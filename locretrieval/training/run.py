"""`train(run, output_dir)`: what ``train.py`` runs, from the objects the build step made of its config
(`Training`, `locretrieval.build.build_training`): train with Lightning, validate by localization every
epoch, write the validation curves and report."""

from __future__ import annotations

import dataclasses
import json
import logging
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import yaml
from lightning.pytorch.utilities import rank_zero_only

from locretrieval.benchmark import BenchmarkSettings
from locretrieval.config import ConfigError, require
from locretrieval.errors import require_built
from locretrieval.groundtruth import DefinitionContext, GroundTruthSettings
from locretrieval.report.training import TrainingReportSettings, write_training_report
from locretrieval.report.training_runs import CONFIG_FILE, FINISHED_FILE
from locretrieval.scene import ImageSet, Scene
from locretrieval.scene.kapture_io import concatenate_image_sets
from locretrieval.training.callbacks import LocalizationValidation
from locretrieval.training.objective import Objective
from locretrieval.training.relevance import TrainingPairs, TrainingRelevanceSettings, combined_pairs

log = logging.getLogger(__name__)


@dataclass
class ValidationScope:
    """How much of the validation scene each validation localizes, so that it fits a large scene:
    ``max_queries`` (a fixed subset drawn with ``seed``; null: every query), the SfM paradigms'
    local features capped at ``sfm_max_keypoints`` per image (null: ``sfm.features``' own), and
    ``budget_minutes``: the first validation (before training) localizes its queries in an order
    drawn with ``seed`` until that many minutes are spent, and every validation then uses the queries
    it reached (`LocalizationValidation`; null: no bound); ``held_out``: the share of the validation
    queries (drawn with ``seed``) kept out of every selection (checkpoints, early stopping, a sweep's
    objective read ``val/`` metrics of the others; ``held_out/`` metrics report on them; 0: none)."""

    max_queries: int | None
    seed: int
    sfm_max_keypoints: int | None
    budget_minutes: float | None
    held_out: float

    def __post_init__(self) -> None:
        require(
            self.max_queries is None or self.max_queries >= 1,
            "max_queries",
            f"must be >= 1 or null, got {self.max_queries}",
        )
        require(
            self.sfm_max_keypoints is None or self.sfm_max_keypoints >= 1,
            "sfm_max_keypoints",
            f"must be >= 1 or null, got {self.sfm_max_keypoints}",
        )
        require(
            self.budget_minutes is None or self.budget_minutes > 0,
            "budget_minutes",
            f"must be positive or null, got {self.budget_minutes}",
        )
        require(0 <= self.held_out < 1, "held_out", f"must be a share in [0, 1), got {self.held_out}")

    def scene(self, scene: Scene) -> Scene:
        """``scene`` with its ``max_queries`` validation queries (all when there are fewer), in their order."""
        if self.max_queries is None or self.max_queries >= len(scene.queries):
            return scene
        rows = np.sort(
            np.random.default_rng(self.seed).choice(len(scene.queries), size=self.max_queries, replace=False)
        )
        return dataclasses.replace(scene, queries=scene.queries.subset(rows))

    def settings(self, settings: BenchmarkSettings) -> BenchmarkSettings:
        """The benchmark settings of a validation: the local features capped at ``sfm_max_keypoints``."""
        features = settings.sfm.features
        if self.sfm_max_keypoints is None or (
            features.max_keypoints is not None and features.max_keypoints <= self.sfm_max_keypoints
        ):
            return settings
        sfm = dataclasses.replace(
            settings.sfm, features=dataclasses.replace(features, max_keypoints=self.sfm_max_keypoints)
        )
        return dataclasses.replace(settings, sfm=sfm)


@dataclass
class TrainingSettings:
    """The ``training`` config section, which images are trained on: ``validation_database``, the
    validation scene's own database (map-specific training); ``scenes``, the databases of other
    scenes, each a data config's name (``aachen``) or ``{config: <name>, <its keys>}`` (``{config:
    kapture, mapping: /my/mapping, queries: []}``); ``extra_renders``, render overrides of
    separately rendered synthetic scenes (all their images); and the ``validation`` scope.
    Relevance is computed within each scene, never across."""

    validation_database: bool
    scenes: list[Any]
    extra_renders: list[dict]
    validation: ValidationScope

    def __post_init__(self) -> None:
        require(
            self.validation_database or bool(self.extra_renders) or bool(self.scenes),
            "validation_database",
            "no training images: set validation_database=true or give scenes or extra_renders",
        )
        for index, entry in enumerate(self.scenes):
            require(
                isinstance(entry, str) or (isinstance(entry, dict) and isinstance(entry.get("config"), str)),
                f"scenes[{index}]",
                f"must be a data config's name or {{config: <name>, ...its keys}}, got {entry!r}",
            )


def training_worlds(
    scene: Scene, settings: TrainingSettings, listed: Sequence[Scene], extra: Sequence[Scene]
) -> list[Scene]:
    """Scenes whose databases are trained on, without queries: the validation scene's database, the
    databases of the scenes ``training.scenes`` lists (``listed``, in its order), and the separately
    rendered scenes of ``training.extra_renders`` (``extra``: all their images)."""
    worlds = [_without_queries(scene.name, scene.database, scene)] if settings.validation_database else []
    for index, (entry, other) in enumerate(zip(settings.scenes, listed)):
        if other.database.fingerprint() == scene.database.fingerprint():
            raise ValueError(
                f"training.scenes[{index}] ({entry!r}) is the validation "
                f"scene's database: training.validation_database trains on it"
            )
        worlds.append(_without_queries(f"{other.name}_{index}", other.database, other))
    for override, rendered in zip(settings.extra_renders, extra):
        if rendered.database.fingerprint() == scene.database.fingerprint():
            raise ValueError(f"training.extra_renders {dict(override)} renders the validation scene itself")
        images = concatenate_image_sets([rendered.database, rendered.queries])  # one world: paired together
        worlds.append(_without_queries(rendered.name, images, scene))
    return worlds


def _without_queries(name: str, images: ImageSet, scene: Scene) -> Scene:
    """A scene of ``images`` as its database, no queries, ``scene``'s dataset facts (and a reconstruction's tracks)."""
    return Scene(
        name,
        images,
        images.subset(np.arange(0)),
        ltvl_names=scene.ltvl_names,
        frustum_far=scene.frustum_far,
        observations=scene.observations,
    )


@dataclass
class Training:
    """What ``train.py`` runs, built from its config by `locretrieval.build.build_training` (every key,
    ``_target_``, monitor and the objective checked there, the scene and ground truths prepared): the
    Lightning ``trainer``, ``module`` and ``datamodule``, the ``worlds`` trained on (`training_worlds`),
    the ``validator`` (its callback among the trainer's), the training ``report`` settings and the gap
    rows validation cannot fill (``unfilled``: metric -> why), the ``objective`` train.py returns, the
    checkpoint it resumes (``ckpt_path``), the ``config`` as run (plain data) and when the build
    ``started`` (``time.perf_counter``)."""

    trainer: Any
    module: Any
    datamodule: Any
    worlds: list[Scene]
    validator: LocalizationValidation
    report: TrainingReportSettings
    unfilled: dict[str, str]
    objective: Objective
    ckpt_path: str | None
    config: dict = dataclasses.field(repr=False)
    started: float = dataclasses.field(default_factory=time.perf_counter)


def train(run: Training, output_dir: Path) -> LocalizationValidation:
    """Train ``run``'s module and write, on rank 0, its training report, validation tables and the
    file that says it finished; returns the validation callback (its ``history``; `optimized_value`:
    what train.py returns)."""
    require_built(run, Training, "build_training")
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / CONFIG_FILE).write_text(yaml.safe_dump(run.config, sort_keys=False))  # as run, resolved
    if run.module.freeze_batch_norm:  # Lightning warns of the (intended) eval-mode batch norm
        warnings.filterwarnings("ignore", message=r"Found \d+ module\(s\) in eval mode at the start of training")
    run.trainer.fit(run.module, datamodule=run.datamodule, ckpt_path=run.ckpt_path)
    if run.trainer.is_global_zero:
        write_training_report(run.validator, output_dir, run.report, run.unfilled)
        summary = {
            "seconds": round(time.perf_counter() - run.started, 1),  # the whole run: the sweep summary's time
            "SfM stages per validation": run.validator.sfm_stages,  # per stage: seconds, work done, its unit
        }
        (output_dir / FINISHED_FILE).write_text(json.dumps(summary, indent=2))  # last: the run finished
        for line in outputs_lines(output_dir, run.trainer):
            log.info("%s", line)
    return run.validator


def outputs_lines(output_dir: Path, trainer: L.Trainer) -> list[str]:
    """What a finished run wrote, train.py's last lines: its folder, each checkpoint it keeps (a
    `ModelCheckpoint`'s best by its monitor, with the value, or its latest) and its report."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    lines = [f"run folder: {output_dir}"]
    for callback in trainer.checkpoint_callbacks:
        if isinstance(callback, ModelCheckpoint) and callback.best_model_path:
            score = callback.best_model_score
            kind = (
                f"best by {callback.monitor} ({float(score):.4g})" if callback.monitor and score is not None else "last"
            )
            lines.append(f"checkpoint, {kind}: {callback.best_model_path}")
    if len(lines) == 1:
        lines.append("checkpoint: none (no ModelCheckpoint among the callbacks)")
    lines.append(f"report: {output_dir / 'report.md'}")
    return lines


def optimized_value(objective: Objective, validator: LocalizationValidation) -> float | None:
    """What train.py returns, a sweep's objective: the ``optimized_metric`` at the
    ``optimized_validation`` (`Objective`), the value ``validation.csv`` holds; None on the DDP
    ranks other than 0, which do not validate."""
    if rank_zero_only.rank != 0:
        return None
    return objective.value(validator.history_table())[1]


def unfilled_report_rows(
    report: TrainingReportSettings,
    settings: BenchmarkSettings,
    groundtruths: GroundTruthSettings,
    references: Sequence[str],
    sfm_validated: bool,
) -> dict[str, str]:
    """The gap rows (``report.gap``) that validation cannot fill with these settings (the validation
    ``references``' names, whether it validates the SfM paradigms): metric -> why, each logged as a
    warning; a ``report.baseline`` that is no validation reference is an error."""
    if report.baseline not in references:
        raise ConfigError(
            f"report.baseline: {report.baseline!r} is not a validation reference (validation_references: "
            f"{list(references)})"
        )
    unfilled = {
        row.metric: why for row in report.gap if (why := row.unfilled(settings, groundtruths.parsed(), sfm_validated))
    }
    for metric, why in unfilled.items():
        log.warning("report.gap row %s cannot be filled: %s", metric.removeprefix("val/"), why)
    return unfilled


def training_pairs(
    worlds: Sequence[Scene], relevance: TrainingRelevanceSettings, settings: BenchmarkSettings, cache_dir: Path
) -> TrainingPairs:
    """The relevance pairs of the ``worlds``' databases (each graded within its world), logged."""
    sets = [world.database for world in worlds]
    pairs = combined_pairs(sets, relevance, [pair_context(world, settings, cache_dir) for world in worlds])
    log.info(
        "training on %d images (%d with a relevant partner) of %d scene(s)",
        pairs.num_images,
        int((np.diff(pairs.graded.indptr) > 0).sum()),
        len(worlds),
    )
    return pairs


def pair_context(world: Scene, settings: BenchmarkSettings, cache_dir: Path) -> DefinitionContext:
    """Where the training definition grades ``world``'s database: its far plane (the validation
    scene's for its database and the extra renders, a listed scene's own), the SfM settings and
    cache (a definition that matches features reads the world's known-pose map from them)."""
    return DefinitionContext(
        far=world.frustum_far,
        sfm=settings.sfm,
        cache_dir=cache_dir,
        world=world,
        key="train_relevance.definition",
        scene=world.name,
    )


def check_monitors(callbacks: Mapping[str, Any], metrics: Sequence[str]) -> None:
    """Raise `ConfigError` naming the callback when one monitors (``monitor``) a metric that is not
    logged at every validation (``metrics``, `every_validation_metrics`), listing those that are."""
    for name, callback in callbacks.items():
        monitor = getattr(callback, "monitor", None)
        if monitor is not None and monitor not in metrics:
            raise ConfigError(
                f"callbacks.{name}.monitor: {monitor!r} is not logged at every validation; with these paradigms, "
                f"k and thresholds the metrics are: {', '.join(metrics)}"
            )
