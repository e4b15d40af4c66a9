"""The build step (locretrieval.build): a config becomes the run's objects in one place; nothing
below it reads a config (a test over the package's source), and a new kind of part needs no
edit elsewhere (tests/test_parts.py adds one)."""

import ast
from pathlib import Path

import pytest
from helpers import compose_config, evaluate_config

from locretrieval.build import build_evaluation, build_export
from locretrieval.config import ConfigError
from locretrieval.evaluation import Evaluation

PACKAGE = Path(__file__).resolve().parents[1] / "locretrieval"
#: The modules that may read a config: the build step and the validation under it, the commands (the
#: Hydra applications) and their command line's helpers, and Hydra's plugins (the sweeper and the
#: callbacks Hydra hands its config to).
READ_CONFIGS = {"build.py", "config.py", "commands.py", "cli.py", "training/sweeps.py", "folders.py"}
#: What reading a config is: its types, and OmegaConf's readers (registering a resolver is not).
CONFIG_NAMES = {"DictConfig", "ListConfig", "Container"}
OMEGACONF_READERS = {
    "to_container",
    "to_object",
    "merge",
    "select",
    "create",
    "load",
    "save",
    "is_config",
    "structured",
}


def config_uses(source: str) -> list[str]:
    """Where a module's source names a config type or calls one of OmegaConf's readers."""
    uses = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Name) and node.id in CONFIG_NAMES:
            uses.append(f"line {node.lineno}: {node.id}")
        elif isinstance(node, ast.Attribute) and node.attr in OMEGACONF_READERS:
            if isinstance(node.value, ast.Name) and node.value.id == "OmegaConf":
                uses.append(f"line {node.lineno}: OmegaConf.{node.attr}")
    return uses


def test_no_module_below_the_build_step_takes_or_reads_a_config():
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE).as_posix()
        if relative not in READ_CONFIGS and (uses := config_uses(path.read_text())):
            found[relative] = uses
    assert found == {}
    assert config_uses("def f(cfg: DictConfig):\n    return OmegaConf.to_container(cfg)") == [
        "line 1: DictConfig",
        "line 2: OmegaConf.to_container",
    ]


def test_the_build_step_checks_the_config_before_it_loads_anything(tmp_path, monkeypatch):
    from locretrieval import build

    monkeypatch.setattr(build, "scene_of", lambda *arguments: pytest.fail("the scene was loaded"))
    for override, message in (
        ("metrics.uncertainty.confidence=1.5", r"^metrics.uncertainty.confidence: must be in \[0.5, 1\)"),
        ("report.gallery.k=0", r"^report.gallery.k"),
        ("paradigms.approximation.k=[0]", r"^paradigms.approximation.k"),
        ("shard=5/4", r"^shard: must be 'i/n'"),
    ):
        with pytest.raises(ConfigError, match=message):
            build_evaluation(evaluate_config(override, f"paths.root_dir={tmp_path}"))
    with pytest.raises(ConfigError, match=r"^export: lists what to write"):
        build_export(compose_config("export", "export=[nothing]", f"paths.root_dir={tmp_path}"))


def test_an_evaluation_is_its_objects_and_its_config_as_run(tmp_path):
    run = build_evaluation(
        evaluate_config(f"paths.root_dir={tmp_path}", "data.render.num_database=8", "data.render.num_queries=4",
                        "data.render.width=96", "data.render.height=72", "data.render.texture_size=32",
                        "data.render.length=20.0", "seed=5", "baselines.random=true")
    )  # fmt: skip
    assert isinstance(run, Evaluation) and len(run.scene.database) == 8 and len(run.scene.queries) == 4
    assert run.random_seed == 5 and run.shard is None and run.cache_dir == tmp_path / ".cache"
    assert run.model.name == "densevlad" and run.report.figure_formats == ["png"]
    assert run.config["seed"] == 5 and "${" not in str(run.config)  # the config as run: resolved, plain


def test_the_entry_functions_given_a_config_name_the_build_step_that_makes_their_run(tmp_path):
    from locretrieval.benchmark import BenchmarkSettings
    from locretrieval.evaluation import evaluate
    from locretrieval.export.run import export
    from locretrieval.training.run import train

    cfg = evaluate_config()
    for function, builder in ((evaluate, "build_evaluation"), (export, "build_export"), (train, "build_training")):
        with pytest.raises(TypeError, match=rf"not a DictConfig: .*locretrieval\.build\.{builder}\(cfg\)"):
            function(cfg, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    with pytest.raises(AttributeError, match=r"locretrieval\.build\.benchmark_settings\(cfg\)"):
        BenchmarkSettings.from_config(cfg)
