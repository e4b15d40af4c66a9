"""`train(cfg, output_dir)`: what ``train.py`` runs. Instantiate from the config, train with
Lightning, validate by localization every epoch, write the validation curves and report."""

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
from hydra.utils import instantiate
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from locretrieval.benchmark import BenchmarkSettings
from locretrieval.config import ConfigError, built, check_node, require, validated
from locretrieval.folders import check_written_folder
from locretrieval.groundtruth import DefinitionContext, GroundTruthSettings, compute_groundtruths
from locretrieval.resources import configs_dir
from locretrieval.scene import ImageSet, Scene
from locretrieval.scene.datasets import instantiate_scene, load_synthetic_dataset
from locretrieval.scene.kapture_io import concatenate_image_sets
from locretrieval.training.callbacks import LocalizationValidation, every_validation_metrics, validation_metrics
from locretrieval.training.checkpoints import check_resume_checkpoint
from locretrieval.training.folders import CONFIG_FILE, FINISHED_FILE
from locretrieval.training.objective import Objective
from locretrieval.training.relevance import TrainingPairs, TrainingRelevanceSettings, combined_pairs
from locretrieval.training.report import TrainingReportSettings, write_training_report

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
    held_out: float = 0.0

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
        known = sorted(path.stem for path in (configs_dir() / "data").glob("*.yaml"))
        for index, entry in enumerate(self.scenes):
            require(
                isinstance(entry, str) or (isinstance(entry, dict) and isinstance(entry.get("config"), str)),
                f"scenes[{index}]",
                f"must be a data config's name or {{config: <name>, ...its keys}}, got {entry!r}",
            )
            name = entry if isinstance(entry, str) else entry["config"]
            require(name in known, f"scenes[{index}]", f"no data config {name!r}; expected one of {known}")


def training_worlds(cfg: DictConfig, scene: Scene, settings: TrainingSettings) -> list[Scene]:
    """Scenes whose databases are trained on, without queries: the validation scene's database,
    the databases of the ``scenes`` listed, and/or separately rendered scenes (all their images)."""
    worlds = [_without_queries(scene.name, scene.database, scene)] if settings.validation_database else []
    for index, entry in enumerate(settings.scenes):
        listed = listed_scene(cfg, entry)
        if listed.database.fingerprint() == scene.database.fingerprint():
            raise ValueError(
                f"training.scenes[{index}] ({entry!r}) is the validation "
                f"scene's database: training.validation_database trains on it"
            )
        worlds.append(_without_queries(f"{listed.name}_{index}", listed.database, listed))
    if settings.extra_renders:
        if "render" not in cfg.data:
            raise ValueError("training.extra_renders needs the synthetic data config (data=synthetic)")
        for override in settings.extra_renders:
            render = OmegaConf.merge(cfg.data.render, override)
            extra = load_synthetic_dataset(
                f"train_{render.environment}_{render.seed}",
                cfg.paths.cache_dir,
                render,
                ltvl_names=scene.ltvl_names,
                frustum_far=scene.frustum_far,
            )
            if extra.database.fingerprint() == scene.database.fingerprint():
                raise ValueError(f"training.extra_renders {dict(override)} renders the validation scene itself")
            images = concatenate_image_sets([extra.database, extra.queries])  # one world: paired together
            worlds.append(_without_queries(extra.name, images, scene))
    return worlds


def listed_scene(cfg: DictConfig, entry: Any) -> Scene:
    """The scene of a ``training.scenes`` entry: the data node of ``configs/data/<name>.yaml`` (its
    keys overridden by the entry's), instantiated with the run's config (paths)."""
    name, overrides = (
        (entry, {}) if isinstance(entry, str) else (entry["config"], {k: v for k, v in entry.items() if k != "config"})
    )
    node = composed_data(name)
    run = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))  # the run's config, its data node replaced
    run.data = OmegaConf.merge(node, overrides)
    return instantiate_scene(run.data)


def composed_data(name: str) -> DictConfig:
    """The ``data`` node of ``configs/data/<name>.yaml`` as Hydra composes it (its defaults list, e.g.
    its LTVL names, applied), interpolations left for the run's config to resolve."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():  # in train.py's Hydra app
        return compose(config_name="train", overrides=[f"data={name}"]).data
    with initialize_config_dir(config_dir=str(configs_dir()), version_base="1.3"):
        return compose(config_name="train", overrides=[f"data={name}"]).data


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


#: The config nodes of the objects train.py builds (besides callbacks and loggers), checked first;
#: the module's own parts (its loss, optimizer, scheduler and memory) are checked below it.
OBJECT_NODES = ("sampler", "augmentation", "datamodule", "module", "miner", "trainer")
MODULE_PARTS = ("loss", "optimizer", "scheduler", "memory")


@dataclass
class TrainingParts:
    """What the training loop consumes: the image ``sets`` trained on (one per world), their
    ``pairs``, the ``sampler`` of batches and the ``datamodule``."""

    sets: list[ImageSet]
    pairs: TrainingPairs
    sampler: Any
    datamodule: Any


def train(cfg: DictConfig, output_dir: Path) -> LocalizationValidation:
    """Train the configured model; returns the validation callback (its ``history``; `optimized_value`:
    what train.py returns). Every object is built from its config group (`built`); what can be
    checked without the scene (the sections and object nodes, the resumed checkpoint, the metrics
    checkpoints monitor, the ``optimized_metric``) is checked before it is prepared."""
    started = time.perf_counter()
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)  # the seed is in config.yaml
    settings = BenchmarkSettings.from_config(cfg)
    training = validated(TrainingSettings, cfg.training, "training")
    relevance = validated(TrainingRelevanceSettings, cfg.train_relevance, "train_relevance")
    groundtruth_settings = validated(GroundTruthSettings, cfg.groundtruth, "groundtruth")
    report = validated(TrainingReportSettings, cfg.report, "report")
    unfilled = unfilled_report_rows(cfg, report, training.validation.settings(settings), groundtruth_settings)
    callbacks = checked_callbacks(cfg, settings, groundtruth_settings)
    sfm_validated = cfg.callbacks.localization_validation.get("sfm_every_n_epochs") is not None
    Objective.from_config(cfg).check(validation_metrics(settings, list(groundtruth_settings.parsed()), sfm_validated))
    check_written_folder(output_dir, "run folder (output_dir)")  # Hydra's was checked; output_dir may be another
    output_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, output_dir / CONFIG_FILE, resolve=True)
    cache_dir = Path(cfg.paths.cache_dir)

    descriptor = instantiate(cfg.model)  # the zoo model: network, preprocessing, weights checked
    if cfg.get("ckpt_path"):  # before the scene and ground truth are prepared
        check_resume_checkpoint(cfg.ckpt_path, descriptor.model, descriptor.architecture)
    scene: Scene = instantiate_scene(cfg.data)
    validation_scene, validation_settings = training.validation.scene(scene), training.validation.settings(settings)
    parts = training_parts(cfg, scene, descriptor.preprocessing, settings, relevance, training)
    groundtruths = compute_groundtruths(validation_scene, groundtruth_settings, validation_settings.sfm, cache_dir)
    validator = built(
        cfg.callbacks.localization_validation,
        "callbacks.localization_validation",
        scene=validation_scene,
        groundtruths=groundtruths,
        settings=validation_settings,
        preprocessing=descriptor.preprocessing,
        extraction=descriptor.settings,
        cache_dir=cache_dir,
        random_seed=int(cfg.seed) if cfg.baselines.random else None,
        relevance_scope=groundtruth_settings.relevance,
        reference_models={name: instantiate(node) for name, node in (cfg.get("validation_references") or {}).items()},
        headline=report.metrics(),
        budget_minutes=training.validation.budget_minutes,
        budget_seed=training.validation.seed,
        held_out=training.validation.held_out,
    )
    callbacks = {"localization_validation": validator, **callbacks}  # first: early stopping reads what it logged
    if cfg.get("miner"):
        callbacks["miner"] = built(
            cfg.miner,
            "miner",
            sets=parts.sets,
            pairs=parts.pairs,
            sampler=parts.sampler,
            preprocessing=descriptor.preprocessing,
            extraction=descriptor.settings,
        )
    module = training_module(cfg, descriptor, parts.pairs)
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values()]
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=list(callbacks.values()), logger=loggers or False)
    if module.freeze_batch_norm:  # Lightning warns of the (intended) eval-mode batch norm
        warnings.filterwarnings("ignore", message=r"Found \d+ module\(s\) in eval mode at the start of training")
    trainer.fit(module, datamodule=parts.datamodule, ckpt_path=cfg.get("ckpt_path"))
    if trainer.is_global_zero:
        write_training_report(validator, output_dir, report, unfilled)
        summary = {
            "seconds": round(time.perf_counter() - started, 1),  # the whole run: the sweep summary's time
            "SfM stages per validation": validator.sfm_stages,  # per stage: seconds, work done, its unit
        }
        (output_dir / FINISHED_FILE).write_text(json.dumps(summary, indent=2))  # last: the run finished
        for line in outputs_lines(output_dir, trainer):
            log.info("%s", line)
    return validator


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


def optimized_value(cfg: DictConfig, validator: LocalizationValidation) -> float | None:
    """What train.py returns, a sweep's objective: the ``optimized_metric`` at the
    ``optimized_validation`` (`Objective`), the value ``validation.csv`` holds; None on the DDP
    ranks other than 0, which do not validate."""
    if rank_zero_only.rank != 0:
        return None
    return Objective.from_config(cfg).value(validator.history_table())[1]


def unfilled_report_rows(
    cfg: DictConfig, report: TrainingReportSettings, settings: BenchmarkSettings, groundtruths: GroundTruthSettings
) -> dict[str, str]:
    """The gap rows (``report.gap``) that validation cannot fill with these settings: metric ->
    why, each logged as a warning; a ``report.baseline`` that is no validation reference is an error."""
    references = list(cfg.get("validation_references") or {})
    if report.baseline not in references:
        raise ConfigError(
            f"report.baseline: {report.baseline!r} is not a validation reference (validation_references: {references})"
        )
    sfm_validated = cfg.callbacks.localization_validation.get("sfm_every_n_epochs") is not None
    unfilled = {
        row.metric: why for row in report.gap if (why := row.unfilled(settings, groundtruths.parsed(), sfm_validated))
    }
    for metric, why in unfilled.items():
        log.warning("report.gap row %s cannot be filled: %s", metric.removeprefix("val/"), why)
    return unfilled


def checked_callbacks(
    cfg: DictConfig, settings: BenchmarkSettings, groundtruths: GroundTruthSettings
) -> dict[str, L.Callback]:
    """Check every object node (`check_node`: keys and types) and build the callbacks that need
    nothing from the run (checkpoints, ...), their monitors checked (`check_monitors`); the
    validation callback is built once the scene is there."""
    for part in MODULE_PARTS:  # a config of before the nesting (a finetune or experiment file's `optimizer:`)
        if part in cfg:
            raise ConfigError(
                f"{part}: moved, now module.{part} (the {part} group's package; a key of it: module.{part}.<key>)"
            )
    nodes = {key: cfg[key] for key in OBJECT_NODES if cfg.get(key)}
    nodes |= {f"module.{part}": cfg.module[part] for part in MODULE_PARTS if cfg.module.get(part)}
    nodes |= {f"callbacks.{name}": node for name, node in (cfg.get("callbacks") or {}).items() if node is not None}
    nodes |= {f"logger.{name}": node for name, node in (cfg.get("logger") or {}).items() if node is not None}
    nodes |= {f"validation_references.{name}": node for name, node in (cfg.get("validation_references") or {}).items()}
    for key, node in nodes.items():
        check_node(node, key)
    if "callbacks.localization_validation" not in nodes:
        raise ConfigError(
            "callbacks.localization_validation: missing; training is validated by localization (callbacks=default)"
        )
    callbacks = {
        name: built(node, f"callbacks.{name}")
        for name, node in cfg.callbacks.items()
        if node is not None and name != "localization_validation"
    }
    check_monitors(callbacks, every_validation_metrics(settings, list(groundtruths.parsed())))
    return callbacks


def training_parts(
    cfg: DictConfig,
    scene: Scene,
    preprocessing: Any,
    settings: BenchmarkSettings,
    relevance: TrainingRelevanceSettings,
    training: TrainingSettings,
) -> TrainingParts:
    """The training images of ``scene`` (and the extra renders), their relevance pairs, the sampler
    and the datamodule, from their config nodes."""
    worlds = training_worlds(cfg, scene, training)
    sets = [world.database for world in worlds]
    cache_dir = Path(cfg.paths.cache_dir)
    pairs = combined_pairs(sets, relevance, [pair_context(world, settings, cache_dir) for world in worlds])
    log.info(
        "training on %d images (%d with a relevant partner), validating on %d queries of %s",
        pairs.num_images,
        int((np.diff(pairs.graded.indptr) > 0).sum()),
        len(scene.queries),
        scene.name,
    )
    sampler = built(cfg.sampler, "sampler", pairs=pairs)
    augmentation = built(cfg.augmentation, "augmentation") if cfg.get("augmentation") else None
    paths = [path for images in sets for path in images.paths]
    datamodule = built(
        cfg.datamodule,
        "datamodule",
        paths=paths,
        pairs=pairs,
        sampler=sampler,
        augmentation=augmentation,
        cache_dir=cache_dir,
    )
    return TrainingParts(sets, pairs, sampler, datamodule)


def training_module(cfg: DictConfig, descriptor: Any, pairs: TrainingPairs) -> Any:
    """The LightningModule of ``cfg.module``, its nested loss, optimizer, scheduler and memory
    instantiated with it by Hydra, training the model's network on the training ``pairs``."""
    return built(
        cfg.module,
        "module",
        network=descriptor.network.train(),
        preprocessing=descriptor.preprocessing,
        model=descriptor.model,
        architecture=descriptor.architecture,
        pairs=pairs,
    )


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
