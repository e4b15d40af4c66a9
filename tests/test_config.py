"""The config resolvers (multirun job folders that always fit) and the one place of every
default (the YAML's), checked by parsing the package and composing its configs."""

import ast
import dataclasses
import importlib
import inspect
import os
import re
from collections.abc import Iterator, Mapping
from typing import Any

import helpers
import pytest
from hydra.utils import get_object
from omegaconf import DictConfig, ListConfig, OmegaConf

from locretrieval import config as config_module
from locretrieval.config import (
    JOB_DIRNAME_LENGTH,
    MOVED_KEYS,
    ConfigError,
    job_dirname,
    refuse_moved_keys,
    validated,
)
from locretrieval.metrics.subsets import SubsetSettings

#: 15 long overrides, as a sweep over the training's nested keys writes them.
LONG = [f"callbacks.localization_validation.some_rather_long_option_{i}=value_number_{i}" for i in range(15)]


def test_job_folders_of_15_long_overrides_are_short_unique_and_readable():
    names = [job_dirname(job, ",".join([f"loss=ap_{job}", *LONG])) for job in range(3)]
    assert all(len(name) == JOB_DIRNAME_LENGTH for name in names) and len(set(names)) == 3
    assert names[0].startswith("0_loss=ap_0,some_rather_long_option_0=value_number_0,")  # keys shortened
    # the hash is of the whole label: jobs whose start agrees differ by it
    assert len({name.rsplit("-", 1)[1] for name in names}) == 3
    assert len(os.fsencode(names[0])) < 255  # the file system's limit of a name


def test_short_labels_stay_as_they_are_and_nothing_can_leave_the_sweep_folder():
    assert job_dirname(2, "synthetic_mall_densevlad") == "2_synthetic_mall_densevlad"
    assert job_dirname(0, "loss=ap,sampler.anchors=3") == "0_loss=ap,anchors=3"
    assert "/" not in job_dirname(1, "model.name=../../outside") and job_dirname(1, "x/..") != "1_x/.."


def test_an_optuna_trial_s_folder_shows_its_values_rounded_to_three_digits():
    label = "augmentation.blur_probability=0.489309171116382,module.optimizer.lr=0.00012345678,sampler.anchors=6"
    assert job_dirname(0, label) == "0_blur_probability=0.489,lr=0.000123,anchors=6"
    assert job_dirname(1, "x=2.0,y=0.25,z=1.5e-05") == "1_x=2.0,y=0.25,z=1.5e-05"  # short values as they are


def test_both_entry_points_name_their_jobs_by_the_resolver():
    for name in ("train", "evaluate"):
        subdir = OmegaConf.load(helpers.CONFIGS / f"{name}.yaml").hydra.sweep._get_node("subdir")._value()
        assert subdir.startswith("${job_dirname:${hydra.job.num},"), name


# ------------------------------------------------- one place per default: the YAML's, never Python's too

PACKAGE = helpers.CONFIGS.parent / "locretrieval"
#: The entry points' configs, composed with their default choices.
ENTRY_POINTS = ("evaluate", "train", "export")
OWN_PLACE_DATA = (  # (dataset, overrides): its optional sections set, so their schemas are checked too
    (
        "colmap",
        "data.model=sparse",
        "data.images=images",
        "data.known_distance={images:[a.jpg,b.jpg],metres:12.5}",
        "paths.root_dir=/nonexistent",
    ),
    ("photos", "data.images=images", "paths.root_dir=/nonexistent"),
)


def defaults_of(target: Any) -> set[str]:
    """The parameters of a class or function (a dataclass: its fields) that have a default."""
    if dataclasses.is_dataclass(target):
        return {
            field.name
            for field in dataclasses.fields(target)
            if field.default is not dataclasses.MISSING or field.default_factory is not dataclasses.MISSING
        }
    parameters = inspect.signature(target).parameters.values()
    return {parameter.name for parameter in parameters if parameter.default is not inspect.Parameter.empty}


def required(schema: type) -> set[str]:
    """The fields of a dataclass without a default."""
    return {field.name for field in dataclasses.fields(schema)} - defaults_of(schema)


def repeated(target: Any, node: Any) -> list[str]:
    """The keys ``node`` (a config node) sets whose default ``target`` holds as well, sorted."""
    keys = node.keys() if isinstance(node, (Mapping, DictConfig)) else ()
    return sorted(defaults_of(target) & {str(key) for key in keys})


def target_nodes(node: Any, key: str = "") -> Iterator[tuple[str, DictConfig]]:
    """Every ``_target_`` node in a config (the node itself, nested mappings and lists), with its key."""
    if isinstance(node, DictConfig):
        if "_target_" in node:
            yield key, node
        children = ((name, node._get_node(name)) for name in node.keys())
    elif isinstance(node, ListConfig):
        children = ((f"[{index}]", node._get_node(index)) for index in range(len(node)))
    else:
        return
    for name, child in children:
        yield from target_nodes(child, f"{key}.{name}".lstrip(".") if not name.startswith("[") else f"{key}{name}")


def validated_sections() -> list[tuple[type, str]]:
    """(schema, config key) of every ``validated(Schema, ..., "key")`` call of the package with a
    literal key (the sections it checks), found by parsing its modules; the schema by the name
    its module imports (at the top or in a function)."""
    sections = []
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text())
        calls = [
            node
            for node in ast.walk(tree)
            if isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id == "validated"
            and len(node.args) == 3
            and isinstance(node.args[0], ast.Name)
            and isinstance(node.args[2], ast.Constant)
        ]
        if not calls:
            continue
        module = importlib.import_module(".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts))
        imported = {
            alias.asname or alias.name: node.module
            for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom) and node.module
            for alias in node.names
        }
        for call in calls:
            name = call.args[0].id
            owner = module if hasattr(module, name) else importlib.import_module(imported[name])
            sections.append((getattr(owner, name), call.args[2].value))
    return list(dict.fromkeys(sections))


def sweep_config() -> DictConfig:
    """train.py's config of an Optuna study, with its Hydra node (hydra.sweeper: the sweeper's keys)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(helpers.CONFIGS), version_base="1.3"):
        overrides = ["hparams_search=localization", "paths.root_dir=/nonexistent"]
        return compose(config_name="train", overrides=overrides, return_hydra_config=True)


def test_no_schema_or_constructor_built_from_yaml_has_a_default_the_yaml_also_sets(monkeypatch):
    """A default lives in the YAML alone: no schema checked by `validated` (nested sections and
    parts included) and no class or function a ``_target_`` names (in any YAML file, or in the
    entry points' composed configs) has a default for a key its YAML node sets."""
    composed = {name: helpers.compose_config(name, "paths.root_dir=/nonexistent") for name in ENTRY_POINTS}
    composed["train -m hparams_search=localization"] = sweep_config()  # the sweeper's section, hydra.sweeper
    for data, *overrides in OWN_PLACE_DATA:  # sections only these datasets have
        composed[f"evaluate data={data}"] = helpers.compose_config("evaluate", f"data={data}", *overrides)
    files = {str(path.relative_to(helpers.CONFIGS)): OmegaConf.load(path) for path in helpers.CONFIGS.rglob("*.yaml")}
    violations = [
        f"{source}:{key or '<root>'}: {node._target_} defaults {repeated(get_object(node._target_), node)}"
        for source, config in sorted({**files, **{f"{name}.yaml composed": c for name, c in composed.items()}}.items())
        for key, node in target_nodes(config)
        if node._target_.startswith("locretrieval.")
    ]
    built = []  # (schema, key) of every section `validated` builds, nested ones too
    real_build = config_module._build
    monkeypatch.setattr(
        config_module, "_build", lambda schema, node, key: built.append((schema, key)) or real_build(schema, node, key)
    )
    unchecked = []
    for schema, key in validated_sections():
        checked = False
        for config in composed.values():
            node = OmegaConf.select(config, key)
            if node is None:
                continue
            if isinstance(node, DictConfig) and "_target_" in node:  # a Hydra plugin's node: its own keys
                node = {name: value for name, value in node.items() if not name.startswith("_")}
            if dataclasses.is_dataclass(schema) and key == "data":  # a schema of some of the dataset's keys
                node = {name: value for name, value in node.items() if name in defaults_of(schema) | required(schema)}
            try:
                validated(schema, node, key)
            except ConfigError:  # another entry point's section of that name
                continue
            checked = True
        unchecked += [] if checked else [f"{schema.__name__} at {key}"]
    for schema, key in dict.fromkeys(built):
        for config in composed.values():
            node = OmegaConf.select(config, key)
            if node is not None and dataclasses.is_dataclass(schema):
                violations += [f"{key}: {schema.__name__} defaults {repeated(schema, node)}"]
    found = [violation for violation in dict.fromkeys(violations) if not violation.endswith("defaults []")]
    assert not found, "\n".join(found)
    assert unchecked == [] and len(dict.fromkeys(built)) > 20  # every section found was checked, nested ones too

    @dataclasses.dataclass
    class Section:  # the test's own check of its detector
        depth: int
        chunk_size: int = 256

    assert repeated(Section, OmegaConf.create({"depth": 50, "chunk_size": 256})) == ["chunk_size"]
    assert repeated(Section, OmegaConf.create({"depth": 50})) == []
    assert repeated(lambda depth, name="x": None, {"name": "y"}) == ["name"]
    nested = OmegaConf.create({"a": {"_target_": "x.Y", "b": [{"_target_": "x.Z"}]}})
    assert [key for key, _ in target_nodes(nested)] == ["a", "a.b[0]"]


@pytest.mark.parametrize("old", sorted(MOVED_KEYS))
def test_a_moved_key_is_refused_naming_its_new_spelling(old):
    for override in (f"{old}=1", f"+{old}=1", f"~{old}"):
        with pytest.raises(ConfigError, match=rf"^{re.escape(old)}: moved, now {re.escape(MOVED_KEYS[old])} "):
            refuse_moved_keys(["model=netvlad", override])
    refuse_moved_keys(["model=netvlad", f"{old}_other=1", f"x.{old}=1"])  # other keys pass


def test_moved_keys_are_refused_on_the_command_line_and_in_a_section():
    completed = helpers.run_python(
        "import sys; sys.argv = ['evaluate.py', 'paradigms.approximation.alpha=4']; "
        "import runpy; runpy.run_path('evaluate.py', run_name='__main__')"
    )
    assert completed.returncode == 1 and "Traceback" not in completed.stderr  # a mistake: its message alone
    assert completed.stderr.startswith(
        "paradigms.approximation.alpha: moved, now paradigms.approximation.weights.csi.alpha"
    )
    cfg = helpers.evaluate_config("paths.root_dir=/nonexistent", "+subsets.maskrcnn_weights=/w.pth")
    with pytest.raises(
        ConfigError, match=r"subsets.maskrcnn_weights: moved, now subsets.mask_sources.maskrcnn.weights"
    ):
        validated(SubsetSettings, cfg.subsets, "subsets")


@pytest.mark.parametrize(
    ("overrides", "loss", "optimizer"),
    [
        ([], "ListwiseLoss", "Adam"),
        (["loss=ap", "optimizer=adamw"], "APLoss", "AdamW"),
        (["loss=triplet", "memory=cross_batch", "module.memory.size=4"], "TripletLoss", "Adam"),
        (["data=baidu", "loss=multi_similarity", "~scheduler"], "MetricLearningLoss", "Adam"),
        (["finetune=salad", "module.frozen=[]", "loss=contrastive"], "ContrastiveLoss", "AdamW"),
    ],
)
def test_the_training_groups_compose_under_the_module_and_instantiate_with_it(overrides, loss, optimizer):
    """``python train.py data=baidu loss=ap``: the group names choose the module's parts, which
    nest under it (module.loss, module.optimizer, module.scheduler, module.memory) as the objects
    do, and Hydra builds them with it (`training_module`'s call), each with its YAML's values."""
    import torch
    from training_runs import random_pairs

    from locretrieval.config import built
    from locretrieval.models.extraction import Preprocessing
    from locretrieval.models.networks import GeMPooling, RetrievalNet
    from locretrieval.training.losses import PerAnchorMean
    from locretrieval.training.memory import CrossBatchMemory

    cfg = helpers.compose_config("train", "trainer.max_epochs=3", *overrides)
    assert not {"loss", "optimizer", "scheduler", "memory"} & set(cfg)  # no sibling groups left
    network = RetrievalNet(torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3)), GeMPooling(4, 3.0, trainable=False), 4)
    module = built(
        cfg.module, "module", network=network, preprocessing=Preprocessing(max_side=None, scales=(1.0,)),
        model="gem", architecture={}, pairs=random_pairs(8, 0),
    )  # fmt: skip
    memory = "memory=cross_batch" in overrides
    wrapped = module.loss.loss if memory else module.loss
    assert type(module.loss).__name__ == ("CrossBatchMemory" if memory else loss) and type(wrapped).__name__ == loss
    if memory:
        assert isinstance(module.loss, CrossBatchMemory) and module.loss.memory.size == 4
    if loss in ("TripletLoss", "ContrastiveLoss"):  # pytorch-metric-learning's parts, injected from the YAML
        assert type(wrapped.loss.distance).__name__ == "CosineSimilarity"
        assert any(
            isinstance(part, PerAnchorMean) for part in wrapped.loss.reducer.modules()
        )  # contrastive: per pair kind
    # the parts hold no state of their own: a checkpoint of before the nesting resumes (its state_dict)
    assert all(key.startswith(("network.", "forward_network.")) for key in module.state_dict())
    optimizers = module.configure_optimizers()
    chosen = optimizers if "~scheduler" in overrides else optimizers["optimizer"]
    assert type(chosen).__name__ == optimizer
    assert chosen.param_groups[0]["lr"] == cfg.module.optimizer.lr and cfg.module.optimizer.lr > 0
    if "~scheduler" not in overrides:
        assert optimizers["lr_scheduler"].T_max == 3  # ${trainer.max_epochs}, resolved inside the module's node


def test_an_old_spelling_of_a_training_key_is_refused_naming_the_nested_one(tmp_path):
    """``python train.py loss.margin=0.2`` (before the nesting) is refused naming
    ``module.loss.margin``; a config file's top-level ``optimizer:`` section, naming
    ``module.optimizer``, before any work."""
    from helpers import train
    from training_runs import train_config

    completed = helpers.run_python(
        "import sys; sys.argv = ['train.py', 'loss=triplet', 'loss.margin=0.2']; "
        "import runpy; runpy.run_path('train.py', run_name='__main__')"
    )
    assert completed.returncode == 1 and completed.stderr.startswith("loss.margin: moved, now module.loss.margin")
    for old, new in (("optimizer.lr", "module.optimizer.lr"), ("module.memory_size", "memory=cross_batch")):
        with pytest.raises(ConfigError, match=rf"^{re.escape(old)}: moved, now {re.escape(new)}"):
            refuse_moved_keys(["loss=ap", "optimizer=adamw", f"{old}=1"])
    refuse_moved_keys(["loss=ap", "optimizer=adamw", "scheduler=cosine", "module.loss.bins=30"])  # the new keys pass
    cfg = train_config(tmp_path, "+optimizer.momentum=0.9")  # as a config file of before the nesting sets it
    with pytest.raises(ConfigError, match=r"^optimizer: moved, now module.optimizer "):
        train(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()  # refused before any work
    cfg = train_config(tmp_path, "+module.memory_size=16")
    with pytest.raises(ConfigError, match=r"^module.memory_size: moved, now memory=cross_batch module.memory.size"):
        train(cfg, tmp_path / "run")
