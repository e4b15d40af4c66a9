"""Shared test helpers: the project's configs composed by Hydra, zoo models built from them, a
callback that interrupts training, a network that fails on one rank, the hostile names of conftest's hostile run."""

import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import lightning as L
from hydra import compose, initialize_config_dir
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from locretrieval.config import validated
from locretrieval.scene import Scene
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import RenderSettings, render_synthetic_dataset
from locretrieval.sfm.settings import SfmSettings

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
#: The overrides of a tiny built-in scene for a run of the command line: 32 database images and 16 queries of
#: 160 x 120 pixels, DenseVLAD on them.
TINY_SCENE = [
    "data.render.width=160",
    "data.render.height=120",
    "data.render.num_database=32",
    "data.render.num_queries=16",
    "data.render.texture_size=64",
    "data.render.length=20.0",
    "data.render.workers=1",
    "data.render.seed=3",
    "model.max_side=160",
    "model.step=4",
    "subsets.blur_width=160",
]
#: Extraction overrides for tests: CPU, in this process, no progress bars.
QUIET_EXTRACTION = ("device=cpu", "model.extraction.num_workers=0", "model.extraction.progress=false")

#: Markup a hostile dataset and configuration put where names go: each handler would set a global the
#: browser test reads back, and none may ever run. ``$`` and ``\\input`` probe matplotlib and LaTeX.
HOSTILE_QUERY_FOLDER = "<img src=x onerror=window.__pwned=8>"
HOSTILE_TAG = "<svg/onload=window.__pwned=7>$x$"
HOSTILE_IMAGE = "query/`<svg/onload=window.__pwned=1>`.png"  # a backtick would close a code span
HOSTILE_MODEL = "../../../<img src=x onerror=window.__pwned=5>\\input{x}"


def compose_config(name: str, *overrides: str) -> DictConfig:
    """``configs/<name>.yaml`` composed by Hydra with ``overrides``."""
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name=name, overrides=list(overrides))


def evaluate_config(*overrides: str) -> DictConfig:
    """``configs/evaluate.yaml`` composed by Hydra with ``overrides``."""
    return compose_config("evaluate", *overrides)


def training_module(network, loss=None, optimizer=None, scheduler=None, **options):
    """`RetrievalTraining` of ``network`` with ``configs/module/retrieval.yaml``'s options (Adam at
    1e-3 unless ``optimizer``; no memory), ``options`` overriding them."""
    from functools import partial

    import torch

    from locretrieval.models.extraction import Preprocessing
    from locretrieval.training.module import RetrievalTraining

    settings = OmegaConf.to_container(OmegaConf.load(CONFIGS / "module" / "retrieval.yaml"))
    parts = {"loss": loss, "optimizer": optimizer or partial(torch.optim.Adam, lr=1e-3), "scheduler": scheduler}
    settings = {key: value for key, value in settings.items() if not key.startswith("_") and key not in parts}
    return RetrievalTraining(
        network, Preprocessing(max_side=None, scales=(1.0,)), model="gem", architecture={}, **parts,
        **{**settings, **options},
    )  # fmt: skip


def zoo_model(model: str, **options):
    """The model of ``configs/model/<model>.yaml`` (on CPU, quiet), its keys overridden by ``options``."""
    config = evaluate_config(f"model={model}", "paths.root_dir=/nonexistent", *QUIET_EXTRACTION)
    parameters = OmegaConf.to_container(config.model, resolve=True)
    model_class = get_class(parameters.pop("_target_"))
    return model_class(**{**parameters, **options})


def groundtruth_section(definitions: Mapping, depth: int) -> dict:
    """A ``groundtruth`` section of ``definitions`` (name -> node, every one enabled), ``depth``
    images per query and the YAML's default relevance (``configs/groundtruth/relevance/top_k.yaml``)."""
    relevance = OmegaConf.to_container(OmegaConf.load(CONFIGS / "groundtruth" / "relevance" / "top_k.yaml"))
    return {"depth": depth, "definitions": dict(definitions), "enabled": None, "relevance": relevance}


def precomputed(**keys):
    """A `PrecomputedDescriptor` of ``keys``, built in Python; its other keys as
    ``configs/model/precomputed.yaml`` sets them (``name``: ``None``, named after its folders)."""
    from locretrieval.models import PrecomputedDescriptor

    node = OmegaConf.to_container(OmegaConf.load(CONFIGS / "model" / "precomputed.yaml"))
    literal = {key: value for key, value in node.items() if not key.startswith("_") and key != "name"}
    return PrecomputedDescriptor(**{"name": None, **literal, **keys})


def render_settings(settings: Mapping = {}) -> RenderSettings:  # noqa: B006  (read only)
    """``data.render`` as ``configs/data/synthetic.yaml`` composes it (seed 0, on the CPU), the keys
    of ``settings`` (``conditions`` too) merged in, checked."""
    render = compose_config("evaluate", "device=cpu", "paths.root_dir=/nonexistent").data.render
    plain = OmegaConf.to_container(render, resolve=True)
    return validated(RenderSettings, OmegaConf.merge(plain, dict(settings)), "data.render")


def rendered_scene(root: Path, settings: Mapping) -> Scene:
    """A synthetic scene rendered with ``settings`` (`render_settings`) into ``root`` and read back
    from its kapture folders."""
    render_synthetic_dataset(render_settings(settings), root)
    return load_kapture_scene("tiny", [root / "mapping"], [root / "query"])


def sfm_settings(*overrides: Mapping, choices: Sequence[str] = ()) -> SfmSettings:
    """The ``sfm`` group as ``evaluate.yaml`` composes it (``configs/sfm/default.yaml``, with the
    group ``choices``, e.g. ``sfm/features=kapture``), run in this process (``workers: 1``) on
    the CPU, ``overrides`` merged in order."""
    defaults = OmegaConf.to_container(
        compose_config("evaluate", *choices).sfm, resolve=True
    )  # plain: overrides may add keys
    return validated(
        SfmSettings, OmegaConf.merge(defaults, {"workers": 1, "matching": {"device": "cpu"}}, *overrides), "sfm"
    )


class StopAfterEpoch(L.Callback):
    """Stops training at the end of epoch ``epoch``, as an interrupted run would (its last checkpoint saved)."""

    def __init__(self, epoch: int) -> None:
        self.epoch = epoch

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.current_epoch == self.epoch:
            trainer.should_stop = True


class ObjectPointerArray:
    """Pickles as a numpy array (allowlisted globals only: ``numpy.dtype``, ``_reconstruct``) whose
    dtype declares an object field with numpy's "holds objects" flag cleared: numpy's own
    unpickling stores the 8 bytes ``AAAAAAAA`` where a Python object pointer is read (a crash)."""

    def __reduce__(self):
        import numpy as np

        state = (3, "|", None, ("a",), {"a": (np.dtype("O"), 0)}, 8, 1, 0)  # flags 0: "no objects"
        dtype = _Reduced(np.dtype, ("V8", False, True), state)
        return (np._core.multiarray._reconstruct, (np.ndarray, (0,), b"b"), (1, (1,), dtype, False, b"A" * 8))


class _Reduced:
    """Pickles as ``callable(*arguments)`` with ``state`` applied."""

    def __init__(self, callable, arguments, state):
        self.reduced = (callable, arguments, state)

    def __reduce__(self):
        return self.reduced


def run_python(code: str, timeout: float = 120):
    """``code`` run by a fresh interpreter (this checkout's package first on its path): the completed
    process, its output captured (a crash of that interpreter cannot take the test run with it)."""
    import os
    import subprocess
    import sys

    root = str(Path(__file__).resolve().parents[1])
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])}
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout, env=environment, cwd=root
    )


def error_in_subprocess(function: str, path: Path):
    """``function(path)`` (``module.name``) called by a fresh interpreter (`run_python`) that prints
    the `DataFileError` it raises and exits 0: the completed process (a crash: a negative code)."""
    module, name = function.rsplit(".", 1)
    return run_python(
        f"from locretrieval.errors import DataFileError\nfrom {module} import {name}\n"
        f"try:\n    {name}({str(path)!r})\nexcept DataFileError as error:\n    print(error)\n"
    )


def set_limits(monkeypatch, **values) -> None:
    """The default ``limits`` with ``values`` for this test's process (and those it starts), as a run with
    ``limits.<key>=<value>`` sets them; undone after the test."""
    import dataclasses

    from locretrieval import limits

    monkeypatch.setattr(limits, "_in_use", dataclasses.replace(limits.defaults(), **values))


def network_failing_on_rank(rank: int):
    """``model=callable`` of train.py: a small network whose description for validation (eval
    mode) raises on global rank ``rank`` of a DDP run, a fault of one process; it trains anywhere."""
    import torch

    class FailingOnRank(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.conv = torch.nn.Conv2d(3, 8, 5, stride=4)

        def forward(self, images: torch.Tensor) -> torch.Tensor:
            if not self.training and torch.distributed.is_initialized() and torch.distributed.get_rank() == rank:
                raise RuntimeError(f"a validation fault of rank {rank}")
            return self.conv(images).mean((2, 3))

    return FailingOnRank()


def evaluate(cfg: DictConfig, output_dir: Path):
    """What evaluate.py runs: the build step (`locretrieval.build.build_evaluation`), then the evaluation."""
    from locretrieval.build import build_evaluation
    from locretrieval.evaluation import evaluate as run

    return run(build_evaluation(cfg), Path(output_dir))


def export(cfg: DictConfig, output_dir: Path):
    """What export.py runs: the build step (`locretrieval.build.build_export`), then the export."""
    from locretrieval.build import build_export
    from locretrieval.export.run import export as run

    return run(build_export(cfg), Path(output_dir))


def train(cfg: DictConfig, output_dir: Path):
    """What train.py runs: the scenes ``training.scenes`` names composed, the build step
    (`locretrieval.build.build_training`), then the training; returns the validation callback."""
    from locretrieval.build import build_training
    from locretrieval.cli import composed_training_scenes
    from locretrieval.training.run import train as run

    return run(build_training(cfg, composed_training_scenes(cfg)), Path(output_dir))


#: A log line's start (Hydra's format) and a tqdm bar's (``12%|`` or ``| 3/16 [``).
STAMP = re.compile(r"\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}\]")
BAR = re.compile(r"\d+%\||\|\s*\d+/\d+ \[")


def collisions(screen: str) -> list[str]:
    """The pieces of a terminal's output where a log line and a bar share a line: each line cut at
    carriage returns and cursor moves (where a bar is drawn again), a log line's stamp after other
    text of its piece, or a bar after a log line's stamp."""
    pieces = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "\r", screen).replace("\n", "\r").split("\r")
    found = []
    for piece in pieces:
        stamp = STAMP.search(piece)
        if stamp and (piece[: stamp.start()].strip() or BAR.search(piece[stamp.end() :])):
            found.append(piece)
    return found
