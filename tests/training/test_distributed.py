"""Training on several processes as one, with two gloo processes on the CPU (Lightning DDP): every
loss, the cross-batch memory and the miner see the union of the ranks' batches; validation is
split over the ranks and equals one process's; a rank that fails ends every rank; a checkpoint
resumes on another number of ranks."""

import os
import subprocess
import sys
from functools import partial
from pathlib import Path
from unittest import mock

import ddp_steps
import helpers
import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from lightning.pytorch.utilities import rank_zero as pytorch_rank_zero
from lightning_utilities.core import rank_zero
from omegaconf import OmegaConf
from training_runs import SCENE, SMALL_DENSEVLAD, TINY_TRAINING

from locretrieval.models.files.weights import load_torch_file
from locretrieval.training.data import RelevanceBatchSampler, TrainingData, collate
from locretrieval.training.distributed import Ranks

ROOT = Path(__file__).resolve().parents[2]
#: The tiny scene with 16 database images and 4 queries: 4 extraction batches of 4 images (2 a rank)
#: and 2 SfM queries a rank, as few as still split every validation's work over both ranks.
RUN_SCENE = {**SCENE, "num_database": 16, "num_queries": 4}
#: train.py's overrides of the tiny runs: the scene, short trainings (4 sampler batches an epoch), a
#: cheap DenseVLAD reference.
TINY_RUN = [
    *(f"data.render.{key}={value}" for key, value in RUN_SCENE.items() if key != "conditions"),
    *(f"data.render.conditions.{key}={value}" for key, value in RUN_SCENE["conditions"].items()),
    "device=cpu",
    *(override for override in TINY_TRAINING if "sfm_every_n_epochs" not in override),
    "sampler.batches_per_epoch=4",
    "trainer.enable_progress_bar=false",
    "logger={}",
    *SMALL_DENSEVLAD,
]
#: A small random ResNet-18; the SfM paradigms at small k validated before training and every second epoch.
RESNET_WITH_SFM = [
    "model/backbone=torchvision",
    "model.backbone.name=resnet18",
    "model.weights=null",
    "model.random_init=true",
    "model.max_side=96",
    "callbacks.localization_validation.sfm_every_n_epochs=2",
    "paradigms.global_sfm.k=[1,3]",
    "paradigms.local_sfm.k=[3]",
]
#: A run of 2 epochs (the cosine schedule's length) stopped after the first, as an interrupted one.
FIRST_EPOCH = [
    "trainer.max_epochs=2",
    "+callbacks.interrupt={_target_: helpers.StopAfterEpoch, epoch: 0}",
]
#: The subprocesses import this checkout's package and the test helpers (``_target_: helpers....``).
PYTHONPATH = os.pathsep.join([str(ROOT), str(ROOT / "tests")])


def train_py(root: Path, run: str, processes: int, *overrides: str, timeout: int = 240) -> subprocess.CompletedProcess:
    """``python train.py`` on ``processes`` gloo processes (``trainer=ddp``) or one (``trainer=cpu``),
    everything under ``root`` (the cache too), the outputs in ``root/<run>``, with `TINY_RUN` and
    ``overrides``; each with the threads it gets (Lightning gives each of two DDP processes half the
    cores): the numbers do not depend on them."""
    trainer = ["trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"] if processes == 2 else ["trainer=cpu"]
    paths = [f"paths.root_dir={root}", f"hydra.run.dir={root}/{run}"]
    root.mkdir(parents=True, exist_ok=True)
    return subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *trainer, *paths, *TINY_RUN, *overrides],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=root,
        env={**os.environ, "PYTHONPATH": PYTHONPATH},
    )


def succeeded(done: subprocess.CompletedProcess) -> str:
    """The console output of a run that succeeded."""
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-4000:]
    return output


def test_each_rank_draws_the_batches_of_one_process_in_turn_by_global_rank(tmp_path):
    helpers.rendered_scene(tmp_path, SCENE)
    _, pairs = ddp_steps.scene_pairs(tmp_path)
    settings = {**ddp_steps.SAMPLER, "batches_per_epoch": 8}
    alone = list(RelevanceBatchSampler(pairs, **settings))
    for world_size in (2, 4):  # 2 ranks, or 2 nodes of 2 devices (global ranks 0-3)
        ranks = []
        for rank in range(world_size):
            sampler = RelevanceBatchSampler(pairs, **settings)
            sampler.shard(rank, world_size)
            ranks.append(list(sampler))
        assert [len(batches) for batches in ranks] == [8 // world_size] * world_size
        assert [batch for step in zip(*ranks) for batch in step] == alone  # step by step, in rank order


def test_the_slurm_recipe_gives_lightning_the_rendezvous_and_the_sampler_its_global_rank(tmp_path, monkeypatch):
    """docs/training.md's multi-node command, composed: in the 4th task of a 2-node job of 2
    tasks each (SLURM's variables), the trainer is rank 3 of 4 at the first node's address, and
    the datamodule's sampler draws every 4th batch from the 4th."""
    recipe = ["hydra/launcher=slurm", "trainer=ddp", "trainer.devices=2", "trainer.num_nodes=2"]
    recipe += ["hydra.launcher.nodes=2", "hydra.launcher.tasks_per_node=2", "hydra.launcher.gpus_per_node=2"]
    slurm = {"SLURM_NTASKS": "4", "SLURM_NTASKS_PER_NODE": "2", "SLURM_PROCID": "3", "SLURM_LOCALID": "1"}
    slurm |= {"SLURM_NODEID": "1", "SLURM_NODELIST": "node[07-08]", "SLURM_JOB_ID": "4321", "SLURM_JOB_NAME": "train"}
    for shared in (rank_zero.rank_zero_only, pytorch_rank_zero.rank_zero_only):  # the DDP strategy sets its rank
        monkeypatch.setattr(shared, "rank", shared.rank)
    with initialize_config_dir(config_dir=str(helpers.CONFIGS), version_base="1.3"):
        overrides = [*recipe, "trainer.accelerator=cpu", f"paths.root_dir={tmp_path}", f"output_dir={tmp_path}/run"]
        cfg = compose("train", overrides=overrides, return_hydra_config=True)
    assert (
        cfg.hydra.launcher.nodes == cfg.trainer.num_nodes and cfg.hydra.launcher.tasks_per_node == cfg.trainer.devices
    )
    helpers.rendered_scene(tmp_path / "scene", SCENE)
    images, pairs = ddp_steps.scene_pairs(tmp_path / "scene")
    settings = {**ddp_steps.SAMPLER, "batches_per_epoch": 8}
    data = TrainingData(images.paths, pairs, RelevanceBatchSampler(pairs, **settings), None, (48, 36), 0, tmp_path)
    with mock.patch.dict(os.environ, slurm):  # then as it was (Lightning adds MASTER_ADDR)
        trainer = instantiate(cfg.trainer)(callbacks=[], logger=False)  # a partial: the build step adds them
        assert (trainer.global_rank, trainer.world_size, trainer.node_rank, trainer.local_rank) == (3, 4, 1, 1)
        assert trainer.strategy.cluster_environment.main_address == "node07"
        data.trainer = trainer
        batches = list(data.train_dataloader().batch_sampler)
    assert batches == list(RelevanceBatchSampler(pairs, **settings))[3::4]


@pytest.fixture(scope="module")
def steps(tmp_path_factory):
    """``ddp_steps.py`` on two DDP processes, and on one given the union of their batches."""
    root = tmp_path_factory.mktemp("ddp_steps")
    helpers.rendered_scene(root / "scene", SCENE)
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "tests" / "ddp_steps.py"),
            str(root / "scene"),
            str(root / "two"),
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": PYTHONPATH},
    )
    assert done.returncode == 0, (done.stdout + done.stderr)[-4000:]
    ddp_steps.main(root / "scene", root / "one", 1)
    return root


@pytest.mark.slow
@pytest.mark.parametrize("loss", ddp_steps.LOSSES)
def test_two_ddp_processes_take_the_steps_of_one_process_given_the_union_of_their_batches(steps, loss):
    """The same loss at each of two steps and the same parameters after each (SGD: the step is the
    gradient's); the second step ranks the batch against the memory too, which holds the same images."""
    alone = np.load(steps / "one" / f"{loss}-rank0.npz")
    assert alone["parameters"].shape[0] == 2 and not np.allclose(alone["parameters"][0], alone["parameters"][1])
    for rank in (0, 1):
        ranked = np.load(steps / "two" / f"{loss}-rank{rank}.npz")
        np.testing.assert_allclose(ranked["losses"], alone["losses"], rtol=1e-5)
        np.testing.assert_allclose(ranked["parameters"], alone["parameters"], atol=1e-5)
        np.testing.assert_array_equal(ranked["memory"], alone["memory"])
    assert len(alone["memory"]) == ddp_steps.MEMORY_SIZE


def test_per_rank_losses_without_the_global_batch_and_the_same_hard_negatives_on_every_rank(steps):
    """``module.global_batch=false``: each rank's first loss is that of its own batch alone. The
    miner (each rank describing half of the images) gives every rank one process's negatives."""
    images, pairs = ddp_steps.scene_pairs(steps / "scene")
    data = ddp_steps.batches_of(images, pairs, steps / "one" / "cache", 2)
    for rank, batch in enumerate(list(data.sampler)[:2]):
        loss = instantiate(OmegaConf.load(ddp_steps.CONFIGS / "loss" / "listwise.yaml"))
        module = helpers.training_module(ddp_steps.network(), loss, partial(torch.optim.SGD, lr=0.5), pairs=pairs)
        own = module.batch_loss(collate(pairs)([data.dataset[index] for index in batch])).item()
        assert np.load(steps / "two" / f"per_rank-rank{rank}.npz")["losses"][0] == pytest.approx(own, rel=1e-5)
        assert abs(own - np.load(steps / "one" / "listwise-rank0.npz")["losses"][0]) > 1e-3  # not the union's
    alone = np.load(steps / "one" / "mined-rank0.npz")
    for rank in (0, 1):
        mined = np.load(steps / "two" / f"mined-rank{rank}.npz")
        for key in ("anchors", "counts", "negatives"):
            np.testing.assert_array_equal(mined[key], alone[key])


def test_with_one_process_the_work_runs_here_and_its_error_is_raised_unchanged():
    assert Ranks(0, 1).gather(lambda: 7) == [7] and Ranks(0, 1).first(lambda: 7) == 7
    with pytest.raises(ZeroDivisionError):
        Ranks(0, 1).gather(lambda: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        Ranks(0, 1).first(lambda: 1 / 0)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """train.py's first epoch of a 2-epoch run, on two ranks and on one (separate caches): the
    runs' folder, their console output and the last lines of its standard output (the log)."""
    root = tmp_path_factory.mktemp("ddp_runs")
    done = {
        processes: train_py(root / f"ranks{processes}", "run", processes, *RESNET_WITH_SFM, *FIRST_EPOCH)
        for processes in (2, 1)
    }
    logs = {processes: succeeded(run) for processes, run in done.items()}
    return root, logs, {processes: run.stdout.splitlines()[-4:] for processes, run in done.items()}


def validation(run: Path) -> pd.DataFrame:
    return pd.read_csv(run / "validation.csv")


@pytest.mark.slow
def test_validation_on_two_ranks_equals_one_process_exactly(runs):
    root, logs, _ = runs
    two, one = root / "ranks2" / "run", root / "ranks1" / "run"
    before = [validation(run).query("epoch == -1").set_index("metric")["value"] for run in (two, one)]
    assert any(metric.startswith("val/global_sfm/") for metric in before[0].index)
    assert any(metric.startswith("val/local_sfm/") for metric in before[0].index)
    pd.testing.assert_series_equal(before[0], before[1], check_exact=True)
    references = [load_torch_file(run / "checkpoints" / "last.ckpt")["callbacks"] for run in (two, one)]
    references = [
        next(state["reference"] for key, state in r.items() if "LocalizationValidation" in key) for r in references
    ]
    assert references[0] == references[1] and "densevlad" in references[0]
    assert (two / "gallery_before.jpg").read_bytes() == (one / "gallery_before.jpg").read_bytes()
    report = [(run / "report.md").read_text() for run in (two, one)]
    assert report[0].split("Reference rankings:")[1] == report[1].split("Reference rankings:")[1]
    # each rank described half of the images (extraction batches of 4) and did half of the SfM queries
    assert "trained: 8 images" in logs[2] and "trained: 16 images" not in logs[2] and "trained: 16 images" in logs[1]
    assert "SfM shard 0/2: 2 of 4 queries" in logs[2] and "SfM shard 1/2: 2 of 4 queries" in logs[2]
    assert logs[2].count("validation after epoch -1") == 1  # printed by rank 0 only
    # the epoch metrics, equal on every rank, are logged synchronised: no Lightning warning per metric
    assert "sync_dist" not in logs[2]


@pytest.mark.parametrize("processes", [2, 1])
def test_train_py_ends_naming_its_run_folder_checkpoints_and_report(runs, processes):
    root, _, last_lines = runs
    run = root / f"ranks{processes}" / "run"
    shown = [line.split(" - ", 1)[1] for line in last_lines[processes]]  # after Hydra's time and logger name
    assert shown[0] == f"run folder: {run}" and shown[-1] == f"report: {run / 'report.md'}", last_lines
    best = next(run.glob("checkpoints/best-*.ckpt"))
    assert shown[1].startswith("checkpoint, best by val/approximation/ewb/k3/5m_10deg (") and shown[1].endswith(
        f": {best}"
    )
    assert shown[2] == f"checkpoint, last: {run / 'checkpoints' / 'last.ckpt'}"


@pytest.mark.slow
@pytest.mark.parametrize(("trained", "resumed"), [(2, 1), (1, 2)])
def test_a_checkpoint_resumes_on_another_number_of_ranks(runs, trained, resumed):
    root, *_ = runs
    run = root / f"ranks{trained}"
    checkpoint = load_torch_file(run / "run" / "checkpoints" / "last.ckpt")
    steps_per_epoch = {1: 4, 2: 2}  # batches_per_epoch=4: a step of each rank per pair of batches
    assert checkpoint["epoch"] == 0 and checkpoint["global_step"] == steps_per_epoch[trained]
    resume = f"ckpt_path={run}/run/checkpoints/last.ckpt"
    succeeded(train_py(run, f"resumed{resumed}", resumed, *RESNET_WITH_SFM, "trainer.max_epochs=2", resume))
    after = load_torch_file(run / f"resumed{resumed}" / "checkpoints" / "last.ckpt")
    assert after["epoch"] == 1 and after["global_step"] == steps_per_epoch[trained] + steps_per_epoch[resumed]
    assert {int(state["step"]) for state in after["optimizer_states"][0]["state"].values()} == {after["global_step"]}
    history, first = validation(run / f"resumed{resumed}"), validation(run / "run")
    assert sorted(set(history["epoch"])) == [-1, 0, 1]
    pd.testing.assert_frame_equal(history[history["epoch"] < 1].reset_index(drop=True), first, check_exact=True)
    assert any(metric.startswith("val/global_sfm/") for metric in history.query("epoch == 1")["metric"])
    weights = [state["state_dict"] for state in (checkpoint, after)]
    assert not all(torch.equal(weights[0][key], weights[1][key]) for key in weights[0])  # it trained on


@pytest.mark.slow
def test_a_rank_failing_in_validation_ends_every_rank_with_its_error(tmp_path):
    """A network whose description raises on rank 1 only: both processes end, rank 1 with its
    error and rank 0 with rank 1's, within the timeout (a rank left in a collective would hang)."""
    failing = [
        "model=callable",
        "model.target=helpers:network_failing_on_rank",
        "+model.kwargs={rank: 1}",
    ]
    no_sfm = "callbacks.localization_validation.sfm_every_n_epochs=null"  # the fault is in describing: no SfM needed
    done = train_py(tmp_path, "run", 2, *failing, "model.preprocessing.max_side=96", no_sfm, timeout=120)
    output = done.stdout + done.stderr
    assert done.returncode != 0
    assert "RuntimeError: a validation fault of rank 1" in output  # rank 1's own error
    assert "RankFailed: rank 1 failed, so every rank stops" in output  # rank 0's, with rank 1's traceback
