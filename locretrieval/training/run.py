"""`train(cfg, output_dir)`: what ``train.py`` runs. Instantiate from the config, train with
Lightning, validate by localization every epoch, write the validation curves and report."""

from __future__ import annotations

import fnmatch
import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import lightning as L
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from locretrieval.benchmark import BenchmarkSettings
from locretrieval.config import require, validated
from locretrieval.groundtruth import GroundTruthSettings, compute_groundtruths
from locretrieval.groundtruth.co_observation import database_co_observations
from locretrieval.scene import ImageSet, Scene
from locretrieval.scene.datasets import load_synthetic_dataset
from locretrieval.scene.kapture_io import concatenate_image_sets
from locretrieval.training.callbacks import HardNegativeMining, LocalizationValidation
from locretrieval.training.checkpoints import check_resume_checkpoint
from locretrieval.training.data import AugmentSettings, BatchSettings, RelevanceBatchSampler, TrainingData
from locretrieval.training.module import RetrievalTraining
from locretrieval.training.relevance import TrainingRelevanceSettings, combined_pairs
from locretrieval.training.report import write_training_report

log = logging.getLogger(__name__)


@dataclass
class TrainingSettings:
    """The ``training`` config section: which images are trained on (``validation_database``:
    the validation scene's own database, map-specific training; ``extra_renders``: render
    overrides of separately rendered synthetic scenes, all their images), the ``image_size``
    ``[width, height]`` of training batches, ``batch``, ``augment``, hard-negative mining every
    ``hard_negatives_every_n_steps`` training steps (0: off, ``hard_negatives_per_anchor`` kept per image),
    DataLoader ``num_workers``, ``compile`` (``torch.compile``), ``freeze_batch_norm`` (batch-norm
    layers in eval mode while training, `RetrievalTraining`) and ``frozen`` (`freeze_parameters`)."""

    validation_database: bool
    extra_renders: list[dict]
    image_size: list[int]
    batch: BatchSettings
    augment: AugmentSettings
    hard_negatives_every_n_steps: int
    hard_negatives_per_anchor: int
    num_workers: int
    compile: bool
    freeze_batch_norm: bool
    frozen: list[str]

    def __post_init__(self) -> None:
        require(self.validation_database or bool(self.extra_renders), "validation_database",
                "no training images: set validation_database=true or give extra_renders")
        require(len(self.image_size) == 2 and min(self.image_size) >= 32, "image_size", f"must be [width, height] >= 32 px, got {self.image_size}")
        require(self.hard_negatives_every_n_steps >= 0, "hard_negatives_every_n_steps",
                f"must be >= 0, got {self.hard_negatives_every_n_steps}")


@dataclass
class ValidationSettings:
    """The ``validation`` config section: paradigm 1 every ``every_n_epochs``, the SfM paradigms
    every ``sfm_every_n_epochs`` (``None``: never)."""

    every_n_epochs: int
    sfm_every_n_epochs: int | None

    def __post_init__(self) -> None:
        require(self.every_n_epochs >= 1, "every_n_epochs", f"must be >= 1, got {self.every_n_epochs}")
        require(self.sfm_every_n_epochs is None or self.sfm_every_n_epochs >= 1, "sfm_every_n_epochs", "must be >= 1 or null")


def freeze_parameters(network: torch.nn.Module, patterns: Sequence[str]) -> list[str]:
    """Keep the parameters whose names match a shell-style ``pattern`` (``backbone.blocks.[0-9].*``)
    fixed; returns their names. A pattern that matches no parameter is an error naming some."""
    names = [name for name, _ in network.named_parameters()]
    for pattern in patterns:
        if not any(fnmatch.fnmatchcase(name, pattern) for name in names):
            raise ValueError(f"training.frozen: {pattern!r} matches no parameter of the network "
                             f"(names are like {names[0]!r}, {names[len(names) // 2]!r}, {names[-1]!r})")
    frozen = []
    for name, parameter in network.named_parameters():
        if any(fnmatch.fnmatchcase(name, pattern) for pattern in patterns):
            parameter.requires_grad_(False)
            frozen.append(name)
    return frozen


def training_worlds(cfg: DictConfig, scene: Scene, settings: TrainingSettings) -> list[Scene]:
    """Scenes whose databases are trained on, without queries: the validation scene's database
    and/or separately rendered scenes (all their images)."""
    worlds = [_without_queries(scene.name, scene.database, scene)] if settings.validation_database else []
    if settings.extra_renders:
        if "render" not in cfg.data:
            raise ValueError("training.extra_renders needs the synthetic data config (data=synthetic)")
        for override in settings.extra_renders:
            render = OmegaConf.merge(cfg.data.render, override)
            extra = load_synthetic_dataset(f"train_{render.environment}_{render.seed}", cfg.paths.cache_dir, render,
                                           ltvl_name_style="full", frustum_far=scene.frustum_far)
            if extra.database.fingerprint() == scene.database.fingerprint():
                raise ValueError(f"training.extra_renders {dict(override)} renders the validation scene itself")
            images = concatenate_image_sets([extra.database, extra.queries])  # one world: paired together
            worlds.append(_without_queries(extra.name, images, scene))
    return worlds


def _without_queries(name: str, images: ImageSet, scene: Scene) -> Scene:
    """A scene of ``images`` as its database, no queries, ``scene``'s dataset facts."""
    return Scene(name, images, images.subset(np.arange(0)), ltvl_name_style=scene.ltvl_name_style, frustum_far=scene.frustum_far)


def train(cfg: DictConfig, output_dir: Path) -> LocalizationValidation:
    """Train the configured model; returns the validation callback (its ``history``)."""
    L.seed_everything(int(cfg.seed), workers=True)
    settings = BenchmarkSettings.from_config(cfg)
    training = validated(TrainingSettings, cfg.training, "training")
    validation = validated(ValidationSettings, cfg.validation, "validation")
    relevance = validated(TrainingRelevanceSettings, cfg.train_relevance, "train_relevance")
    groundtruth_settings = validated(GroundTruthSettings, cfg.groundtruth, "groundtruth")
    output_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, output_dir / "config.yaml", resolve=True)
    cache_dir = Path(cfg.paths.cache_dir)

    descriptor = instantiate(cfg.model)  # the zoo model: network, preprocessing, weights checked
    if cfg.get("ckpt_path"):  # before the scene and ground truth are prepared
        check_resume_checkpoint(cfg.ckpt_path, descriptor.model, descriptor.architecture)
    scene: Scene = instantiate(cfg.data)
    network, preprocessing = descriptor.network.train(), descriptor.preprocessing
    frozen = freeze_parameters(network, training.frozen)
    if frozen:
        log.info("%d of %d parameter tensors frozen (training.frozen)", len(frozen), len(list(network.parameters())))
    worlds = training_worlds(cfg, scene, training)
    sets = [world.database for world in worlds]
    far = scene.far_plane(relevance.far, "train_relevance.far")
    shared_points = ([database_co_observations(world, settings.sfm, cache_dir) for world in worlds]
                     if relevance.type == "co_observation" else None)
    pairs = combined_pairs(sets, relevance, far, shared_points)
    log.info("training on %d images (%d with a relevant partner), validating on %d queries of %s",
             pairs.num_images, int((np.diff(pairs.graded.indptr) > 0).sum()), len(scene.queries), scene.name)
    sampler = RelevanceBatchSampler(pairs, training.batch, int(cfg.seed))
    paths = [path for images in sets for path in images.paths]
    data = TrainingData(paths, pairs, sampler, training.image_size, training.augment, training.num_workers)

    groundtruths = compute_groundtruths(scene, groundtruth_settings, settings.sfm, cache_dir)
    extraction = descriptor.settings
    validator = LocalizationValidation(
        scene, groundtruths, settings, preprocessing, extraction, validation.every_n_epochs,
        validation.sfm_every_n_epochs, cache_dir, int(cfg.seed) if cfg.baselines.random else None,
        groundtruth_settings.relevance,
    )
    module = RetrievalTraining(
        network, preprocessing, instantiate(cfg.loss), instantiate(cfg.optimizer),
        instantiate(cfg.scheduler) if cfg.get("scheduler") else None,
        descriptor.model, descriptor.architecture, training.compile, training.freeze_batch_norm,
    )
    callbacks = [validator, *(instantiate(c) for c in (cfg.callbacks or {}).values())]
    if training.hard_negatives_every_n_steps:
        callbacks.append(HardNegativeMining(sets, pairs, sampler, training.hard_negatives_every_n_steps,
                                            training.hard_negatives_per_anchor, preprocessing, extraction))
    loggers = [instantiate(c) for c in (cfg.logger or {}).values()]
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)
    if training.freeze_batch_norm:  # Lightning warns of the (intended) eval-mode batch norm
        warnings.filterwarnings("ignore", message=r"Found \d+ module\(s\) in eval mode at the start of training")
    trainer.fit(module, datamodule=data, ckpt_path=cfg.get("ckpt_path"))
    if trainer.is_global_zero:
        write_training_report(validator, output_dir)
    return validator
