"""Training steps of every loss under Lightning on the CPU, for tests/training/test_distributed.py: on
``processes`` DDP processes (gloo; Lightning launches the others by running this script again),
each drawing its batches by global rank, or on one process given, at each step, the union of the
batches the ranks of ``RANKS`` processes draw.

    python tests/ddp_steps.py <rendered scene folder> <output folder> <processes>

Per loss (``configs/loss/<name>.yaml``) and rank, ``<output>/<loss>-rank<r>.npz`` holds the loss
of each step, the network's parameters after each step and the memory's images; then the hard
negatives the miner gives every anchor (``mined-rank<r>.npz``). SGD (its step is the gradient
times the learning rate, so a gradient of the wrong scale shows) and a cross-batch memory (every
step after the first ranks the batch against the memory too)."""

import sys
from functools import partial
from pathlib import Path

import lightning as L
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
#: The losses of configs/loss/, multi_similarity through the pytorch-metric-learning adapter.
LOSSES = ("listwise", "ap", "triplet", "contrastive", "multi_similarity")
#: The DDP processes whose batches one process is given joined.
RANKS = 2
#: Sampler batches: 3 anchors, 1 positive each, 2 negatives (8 images); 2 steps of 2 ranks.
SAMPLER = dict(anchors=3, positives=1, negatives=2, batches_per_epoch=2 * RANKS, seed=0)
IMAGE_SIZE = (48, 36)
MEMORY_SIZE = 12


def network():
    """A small `RetrievalNet`, the same on every process (seeded)."""
    from locretrieval.models.networks import GeMPooling, RetrievalNet

    torch.manual_seed(0)
    trunk = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 5, stride=2), torch.nn.ReLU(), torch.nn.Conv2d(8, 16, 3))
    return RetrievalNet(trunk, GeMPooling(16, 3.0, trainable=True), 16, whitening=torch.nn.Linear(16, 16))


class Recorder(L.Callback):
    """The loss of each step and the network's parameters after it."""

    def __init__(self) -> None:
        self.losses, self.parameters = [], []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        self.losses.append(float(outputs["loss"]))
        self.parameters.append(torch.cat([p.detach().flatten() for p in module.network.parameters()]).numpy())


def scene_pairs(scene_dir: Path):
    """The database images of the scene rendered in ``scene_dir`` and their training pairs
    (relative pose, 10 m and 30 degrees)."""
    from locretrieval.groundtruth import DefinitionContext
    from locretrieval.scene.kapture_io import load_kapture_scene
    from locretrieval.training.relevance import TrainingRelevanceSettings, UnrelatedNegatives, training_pairs

    images = load_kapture_scene("tiny", [scene_dir / "mapping"], [scene_dir / "query"]).database
    settings = TrainingRelevanceSettings(
        {
            "_target_": "locretrieval.groundtruth.RelativePoseDefinition",
            "position_threshold": 10.0,
            "rotation_threshold": 30.0,
            "ranked": "within_thresholds",
        },
        UnrelatedNegatives(0.1, None, None),
    )
    return images, training_pairs(images, settings, DefinitionContext(far=25.0))


def batches_of(images, pairs, cache_dir: Path, processes: int):
    """The training batches: the datamodule train.py builds (each rank draws its batches by global
    rank), or on one process a loader of the union of ``RANKS`` ranks' batches at each step."""
    from torch.utils.data import DataLoader

    from locretrieval.training.data import RelevanceBatchSampler, TrainingData, collate

    data = TrainingData(images.paths, pairs, RelevanceBatchSampler(pairs, **SAMPLER), None, IMAGE_SIZE, 0, cache_dir)
    if processes > 1:
        return data
    batches = list(data.sampler)
    unions = [sum(batches[start : start + RANKS], []) for start in range(0, len(batches), RANKS)]
    return DataLoader(data.dataset, batch_sampler=unions, collate_fn=collate(pairs))


def train_steps(loss_name: str, pairs, batches, processes: int, **options):
    """One epoch (two steps) on ``batches`` (a datamodule or loader) with ``loss_name``: the
    recorder, the module and its trainer."""
    import helpers

    from locretrieval.training.memory import CrossBatchMemory

    loss = instantiate(OmegaConf.load(CONFIGS / "loss" / f"{loss_name}.yaml"))
    memory = partial(CrossBatchMemory, size=MEMORY_SIZE)
    module = helpers.training_module(
        network(), loss, partial(torch.optim.SGD, lr=0.5), pairs=pairs, memory=memory, **options
    )
    recorder = Recorder()
    trainer = L.Trainer(
        accelerator="cpu",
        devices=processes,
        strategy="ddp" if processes > 1 else "auto",
        max_epochs=1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        use_distributed_sampler=False,
        callbacks=[recorder],
    )
    trainer.fit(module, batches)
    return recorder, module, trainer


def main(scene_dir: Path, out: Path, processes: int) -> None:
    from locretrieval.models.extraction import ExtractionSettings, Preprocessing
    from locretrieval.training.callbacks import HardNegativeMining
    from locretrieval.training.data import RelevanceBatchSampler
    from locretrieval.training.distributed import Ranks

    out.mkdir(parents=True, exist_ok=True)
    images, pairs = scene_pairs(scene_dir)
    batches = batches_of(images, pairs, out / "cache", processes)
    trainer = None
    for loss_name in LOSSES:
        recorder, module, trainer = train_steps(loss_name, pairs, batches, processes)
        np.savez(
            out / f"{loss_name}-rank{trainer.global_rank}.npz",
            losses=np.array(recorder.losses),
            parameters=np.stack(recorder.parameters),
            memory=module.loss.memory.indices.numpy(),
        )
    if processes > 1:  # today's per-rank losses, for comparison: each rank's of its own batch
        recorder, _, trainer = train_steps("listwise", pairs, batches, processes, global_batch=False)
        np.savez(out / f"per_rank-rank{trainer.global_rank}.npz", losses=np.array(recorder.losses))
    extraction = ExtractionSettings("cpu", 4, 0, False, False, None)
    preprocessing = Preprocessing(max_side=None, scales=(1.0,))
    sampler = RelevanceBatchSampler(pairs, **SAMPLER)
    miner = HardNegativeMining([images], pairs, sampler, preprocessing, extraction, every_n_steps=1, per_anchor=3)
    miner.mine(network(), Ranks.of(trainer))
    anchors = sorted(sampler.hard)
    np.savez(
        out / f"mined-rank{trainer.global_rank}.npz",
        anchors=np.array(anchors),
        counts=np.array([len(sampler.hard[a]) for a in anchors]),
        negatives=np.concatenate([sampler.hard[a] for a in anchors]),
    )


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))  # helpers
    main(Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]))
