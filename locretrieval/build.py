"""The build step: a composed config becomes the run's objects here, and nowhere else.

An entry point (``evaluate.py``, ``export.py``, ``train.py``) composes its config with Hydra and hands
it to one function here, which returns what the run is made of: every section checked against its
schema (`locretrieval.config.validated_sections`: each error names its full key), every object built
from its node (`locretrieval.config.built`), the run's ``limits`` made the budgets of the process
(`locretrieval.limits.use`), before any work. What runs (`locretrieval.evaluation.evaluate`,
`locretrieval.export.run.export`, `locretrieval.training.run.train`) takes those objects and never
reads the config. A config the user runs is code: its ``_target_`` name any class
(docs/configuration.md, "What is code and what is data").
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf

from locretrieval import limits
from locretrieval.benchmark import BenchmarkSettings
from locretrieval.config import ConfigError, built, check_node, validated, validated_sections
from locretrieval.evaluation import Evaluation, ReportSettings
from locretrieval.export.onnx import OnnxSettings, torch_network
from locretrieval.export.pairs import PairsSettings
from locretrieval.export.run import Export, check_export, check_scene
from locretrieval.export.scene import DescriptorSettings
from locretrieval.folders import check_written_folder
from locretrieval.groundtruth import GroundTruthSettings, compute_groundtruths
from locretrieval.metrics.localization import MetricsSettings
from locretrieval.metrics.subsets import SubsetSettings
from locretrieval.paradigms.base import Paradigms
from locretrieval.report.gallery import GallerySettings
from locretrieval.report.run_files import literal, load_yaml, mapping_at, run_file
from locretrieval.retrieval.index import RetrievalSettings
from locretrieval.scene import Scene
from locretrieval.scene.datasets import load_synthetic_dataset
from locretrieval.sfm.settings import SfmSettings
from locretrieval.shard import Shard
from locretrieval.training.objective import Objective
from locretrieval.training.relevance import TrainingRelevanceSettings

if TYPE_CHECKING:
    from locretrieval.training.run import Training, TrainingSettings

log = logging.getLogger(__name__)

#: The sections of the benchmark core's settings and their schemas (`BenchmarkSettings`).
BENCHMARK_SECTIONS = {
    "retrieval": RetrievalSettings,
    "paradigms": Paradigms,
    "sfm": SfmSettings,
    "metrics": MetricsSettings,
}


def use_limits(cfg: Any) -> limits.Limits:
    """The run's ``limits`` section, checked and made the budgets of this process (`limits.use`)."""
    return limits.use(validated(limits.Limits, cfg.limits, "limits"))


def benchmark_settings(cfg: Any) -> BenchmarkSettings:
    """The benchmark core's settings of an ``evaluate``/``train`` config (its sections of the same names)."""
    return BenchmarkSettings(**validated_sections(cfg, BENCHMARK_SECTIONS))


def scene_of(node: Any) -> Scene:
    """The scene a ``data`` config node builds (its loader, by ``_target_``)."""
    return built(node, "data")


def plain_config(cfg: Any) -> dict:
    """The config as run: every interpolation resolved, plain data (a run's ``config.yaml``)."""
    return OmegaConf.to_container(cfg, resolve=True)


def build_evaluation(cfg: Any) -> Evaluation:
    """The `Evaluation` of an ``evaluate.yaml`` config: its limits used, its sections checked, the model
    built before the scene is loaded (a missing weight file is named with where to get it first)."""
    use_limits(cfg)
    sections = validated_sections(
        cfg,
        {
            **BENCHMARK_SECTIONS,
            "groundtruth": GroundTruthSettings,
            "subsets": SubsetSettings,
            "report": ReportSettings,
        },
    )
    benchmark = BenchmarkSettings(**{key: sections[key] for key in BENCHMARK_SECTIONS})
    shard = Shard.parse(cfg.shard, "shard")
    model = built(cfg.model, "model")
    return Evaluation(
        scene=scene_of(cfg.data),
        model=model,
        benchmark=benchmark,
        groundtruth=sections["groundtruth"],
        subsets=sections["subsets"],
        report=sections["report"],
        cache_dir=Path(cfg.paths.cache_dir),
        random_seed=int(cfg.seed) if cfg.baselines.random else None,
        shard=shard,
        dry_run=bool(cfg.dry_run),
        ltvl=bool(cfg.output.ltvl),
        config=plain_config(cfg),
    )


def build_export(cfg: Any) -> Export:
    """The `Export` of an ``export.yaml`` config: its limits used, the sections of what ``export``
    lists checked, the packages ONNX needs present, the model built before the scene is loaded, the
    scene's names and the model's inputs checked."""
    use_limits(cfg)
    wanted = list(cfg.export)
    schemas = {"pairs": PairsSettings, "descriptors": DescriptorSettings, "onnx": OnnxSettings}
    sections = validated_sections(cfg, {"retrieval": RetrievalSettings, "sfm": SfmSettings})
    chosen = validated_sections(cfg, {key: schema for key, schema in schemas.items() if key in wanted})
    pairs, descriptors, onnx = (chosen.get(key) for key in schemas)
    groundtruth = validated(GroundTruthSettings, cfg.groundtruth, "groundtruth") if pairs is not None else None
    check_export(wanted, pairs, sections["retrieval"])
    if onnx is not None:
        onnx.check_packages()
    model = built(cfg.model, "model")  # a missing weight file is named with where to get it
    network = torch_network(model) if onnx is not None else None  # one ONNX cannot hold: said now
    scene = scene_of(cfg.data) if pairs is not None or descriptors is not None else None
    if scene is not None:
        check_scene(scene, model, groundtruth)
    return Export(
        pairs=pairs,
        descriptors=descriptors,
        onnx=onnx,
        model=model,
        network=network,
        scene=scene,
        retrieval=sections["retrieval"],
        groundtruth=groundtruth,
        sfm=sections["sfm"],
        cache_dir=Path(cfg.paths.cache_dir),
        config=plain_config(cfg),
    )


#: The config nodes of the objects train.py builds (besides callbacks, loggers and validation references),
#: checked first; the module's own parts (its loss, optimizer, scheduler and memory) are checked below it.
OBJECT_NODES = ("sampler", "augmentation", "datamodule", "module", "miner", "trainer")
MODULE_PARTS = ("loss", "optimizer", "scheduler", "memory")


def build_training(cfg: Any, listed: Sequence[Any] = ()) -> Training:
    """The `Training` of a ``train.yaml`` config (``listed``: the data nodes of the scenes
    ``training.scenes`` names, in its order, as the entry point composed them, `locretrieval.cli`).
    What needs no scene is checked first (the sections and object nodes, the run folder, the resumed
    checkpoint, the metrics checkpoints monitor, the ``optimized_metric``), then the scenes are
    loaded, the training pairs and the validation's ground truths prepared, every object built."""
    # Lightning and what imports it, here and not at the top: an evaluation or an export does not pay
    # for importing it (5 s of CPU with torchmetrics and scipy.signal in every process that builds).
    import lightning as L

    from locretrieval.report.training import TrainingReportSettings
    from locretrieval.training.callbacks import validation_metrics
    from locretrieval.training.checkpoints import check_resume_checkpoint
    from locretrieval.training.run import (
        Training,
        TrainingSettings,
        training_pairs,
        training_worlds,
        unfilled_report_rows,
    )

    started = time.perf_counter()
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)  # the seed is in config.yaml
    use_limits(cfg)
    sections = validated_sections(
        cfg,
        {
            **BENCHMARK_SECTIONS,
            "training": TrainingSettings,
            "train_relevance": TrainingRelevanceSettings,
            "groundtruth": GroundTruthSettings,
            "report": TrainingReportSettings,
        },
    )
    settings = BenchmarkSettings(**{key: sections[key] for key in BENCHMARK_SECTIONS})
    training, groundtruth_settings = sections["training"], sections["groundtruth"]
    validation_settings = training.validation.settings(settings)
    sfm_validated = cfg.callbacks.localization_validation.get("sfm_every_n_epochs") is not None
    references = dict(cfg.get("validation_references") or {})
    unfilled = unfilled_report_rows(
        sections["report"], validation_settings, groundtruth_settings, list(references), sfm_validated
    )
    callbacks = checked_callbacks(cfg, settings, groundtruth_settings)
    objective = Objective.from_config(cfg)
    objective.check(validation_metrics(settings, list(groundtruth_settings.parsed()), sfm_validated))
    check_written_folder(Path(cfg.output_dir), "run folder (output_dir)")  # Hydra's was checked; it may be another
    cache_dir = Path(cfg.paths.cache_dir)

    descriptor = built(cfg.model, "model")  # the zoo model: network, preprocessing, weights checked
    if cfg.get("ckpt_path"):  # before the scene and ground truth are prepared
        check_resume_checkpoint(cfg.ckpt_path, descriptor.model, descriptor.architecture)
    if len(listed) != len(training.scenes):
        raise ConfigError(
            f"training.scenes: {len(training.scenes)} scene(s) listed, {len(listed)} composed; the entry point "
            "composes them (locretrieval.cli.composed_training_scenes)"
        )
    scene = scene_of(cfg.data)
    listed_scenes = [scene_of(listed_data(cfg, node, entry)) for node, entry in zip(listed, training.scenes)]
    worlds = training_worlds(scene, training, listed_scenes, extra_renders(cfg, training, scene))
    pairs = training_pairs(worlds, sections["train_relevance"], settings, cache_dir)
    sampler = built(cfg.sampler, "sampler", pairs=pairs)
    datamodule = built(
        cfg.datamodule,
        "datamodule",
        paths=[path for world in worlds for path in world.database.paths],
        pairs=pairs,
        sampler=sampler,
        augmentation=built(cfg.augmentation, "augmentation") if cfg.get("augmentation") else None,
        cache_dir=cache_dir,
    )
    validation_scene = training.validation.scene(scene)
    log.info("validating on %d queries of %s", len(validation_scene.queries), scene.name)
    validator = built(
        cfg.callbacks.localization_validation,
        "callbacks.localization_validation",
        scene=validation_scene,
        groundtruths=compute_groundtruths(validation_scene, groundtruth_settings, validation_settings.sfm, cache_dir),
        settings=validation_settings,
        preprocessing=descriptor.preprocessing,
        extraction=descriptor.settings,
        cache_dir=cache_dir,
        random_seed=int(cfg.seed) if cfg.baselines.random else None,
        relevance_scope=groundtruth_settings.relevance,
        reference_models={name: built(node, f"validation_references.{name}") for name, node in references.items()},
        headline=sections["report"].metrics(),
        budget_minutes=training.validation.budget_minutes,
        budget_seed=training.validation.seed,
        held_out=training.validation.held_out,
    )
    callbacks = {"localization_validation": validator, **callbacks}  # first: early stopping reads what it logged
    if cfg.get("miner"):
        callbacks["miner"] = built(
            cfg.miner,
            "miner",
            sets=[world.database for world in worlds],
            pairs=pairs,
            sampler=sampler,
            preprocessing=descriptor.preprocessing,
            extraction=descriptor.settings,
        )
    module = built(
        cfg.module,
        "module",
        network=descriptor.network.train(),
        preprocessing=descriptor.preprocessing,
        model=descriptor.model,
        architecture=descriptor.architecture,
        pairs=pairs,
    )
    loggers = [built(node, f"logger.{name}") for name, node in (cfg.get("logger") or {}).items() if node is not None]
    trainer = built(cfg.trainer, "trainer", callbacks=list(callbacks.values()), logger=loggers or False)
    return Training(
        trainer=trainer,
        module=module,
        datamodule=datamodule,
        worlds=worlds,
        validator=validator,
        report=sections["report"],
        unfilled=unfilled,
        objective=objective,
        ckpt_path=cfg.get("ckpt_path"),
        config=plain_config(cfg),
        started=started,
    )


def checked_callbacks(cfg: Any, settings: BenchmarkSettings, groundtruths: GroundTruthSettings) -> dict[str, Any]:
    """Check every object node of a train.py config (`check_node`: keys and types) and build the
    callbacks that need nothing from the run (checkpoints, ...), their monitors checked
    (`check_monitors`); the validation callback is built once the scene is there."""
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
    from locretrieval.training.callbacks import every_validation_metrics  # with Lightning (build_training)
    from locretrieval.training.run import check_monitors

    callbacks = {
        name: built(node, f"callbacks.{name}")
        for name, node in cfg.callbacks.items()
        if node is not None and name != "localization_validation"
    }
    check_monitors(callbacks, every_validation_metrics(settings, list(groundtruths.parsed())))
    return callbacks


def listed_data(cfg: Any, node: Any, entry: Any) -> Any:
    """The data node of a ``training.scenes`` ``entry`` (a data config's name, or ``{config: <name>, <its
    keys>}``): ``node``, that data config as the entry point composed it, with the entry's keys, its
    interpolations resolved against the run's config (paths)."""
    overrides = {key: value for key, value in entry.items() if key != "config"} if isinstance(entry, dict) else {}
    run = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))  # the run's config, its data node replaced
    run.data = OmegaConf.merge(node, overrides)
    return run.data


def extra_renders(cfg: Any, training: TrainingSettings, scene: Scene) -> list[Scene]:
    """The separately rendered scenes of ``training.extra_renders``: the run's render with each entry's keys."""
    if training.extra_renders and "render" not in cfg.data:
        raise ConfigError("training.extra_renders needs the synthetic data config (data=synthetic)")
    scenes = []
    for override in training.extra_renders:
        render = OmegaConf.to_container(OmegaConf.merge(cfg.data.render, override), resolve=True)
        name = f"train_{render['environment']}_{render['seed']}"
        scenes.append(
            load_synthetic_dataset(
                name, cfg.paths.cache_dir, render, ltvl_names=scene.ltvl_names, frustum_far=scene.frustum_far
            )
        )
    return scenes


def build_report_gallery(run: Path, overrides: Sequence[str] = ()) -> GallerySettings | None:
    """What ``report.py`` builds of a run folder: its ``report.gallery`` settings (its ``config.yaml``,
    data read as written: `load_yaml`), ``overrides`` applied (``key=value`` below ``report.gallery``,
    e.g. ``queries=all``); ``None`` when its config has no gallery section."""
    path = run_file(run, "config.yaml")
    section = mapping_at(load_yaml(path) if path.is_file() else {}, "report", "gallery")
    if not section:
        return None
    merged = OmegaConf.merge(literal(section), OmegaConf.from_dotlist(list(overrides)))
    return validated(GallerySettings, merged, "report.gallery")
