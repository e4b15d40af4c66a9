"""What the training tests share: a tiny rendered scene, train.py's config for a short training of it,
random training pairs, and a finished train.py run's files."""

import json
from pathlib import Path

import helpers
import numpy as np
import pandas as pd
from omegaconf import OmegaConf
from scipy import sparse

from locretrieval.training.relevance import TrainingPairs

SCENE = {"width": 96, "height": 72, "num_database": 24, "num_queries": 6, "texture_size": 64, "length": 20.0,
         "conditions": {"night": 0.0, "blur": 0.0, "dynamic": 0.0, "noise": 0.0}, "database_dynamic": 0.0,
         "hard_query_fraction": 0.0, "workers": 1, "seed": 5}  # fmt: skip
#: A short training of the tiny scene: small batches, no SfM validation.
TINY_TRAINING = (
    "datamodule.image_size=[96,72]",
    "datamodule.num_workers=0",
    "sampler.batches_per_epoch=2",
    "sampler.anchors=3",
    "sampler.negatives=2",
    "callbacks.localization_validation.sfm_every_n_epochs=null",
)


def train_config(root, *overrides, image_side="model.max_side=96"):
    """configs/train.yaml on a tiny rendered scene, everything under ``root``; ``image_side``:
    the override that shrinks validation images (the model's key)."""
    tiny = [f"data.render.{key}={value}" for key, value in SCENE.items() if key != "conditions"]
    tiny += [f"data.render.conditions.{key}={value}" for key, value in SCENE["conditions"].items()]
    return helpers.compose_config(
        "train",
        f"paths.root_dir={root}",
        f"output_dir={root}/run",
        "device=cpu",
        *tiny,
        image_side,
        *TINY_TRAINING,
        "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false",
        *overrides,
    )


def random_pairs(size: int, seed: int) -> TrainingPairs:
    """Graded relevance and related pairs among ``size`` images, symmetric, drawn at random."""
    rng = np.random.default_rng(seed)
    graded = np.triu(rng.uniform(0.2, 1.0, (size, size)) * (rng.random((size, size)) < 0.3), 1)
    graded = graded + graded.T
    related = np.triu(rng.random((size, size)) < 0.3, 1)
    related = related | related.T | (graded > 0)
    return TrainingPairs(sparse.csr_matrix(graded), sparse.csr_matrix(related))


#: train.py's default objective (optimized_metric).
METRIC = "val/approximation/ewb/k3/5m_10deg"


def validation_table(rows):
    return pd.DataFrame(rows, columns=["epoch", "metric", "value"])


def gap_run(folder: Path, label: str, objective: float, rows: list[tuple], seconds: float = 12.0) -> Path:
    """A finished train.py run's files as the summary reads them: ``gap.csv`` of ``rows``
    (metric, untrained, trained, densevlad, ground truth), validation.csv, summary.json, config.yaml, .hydra."""
    run = folder / label
    (run / ".hydra").mkdir(parents=True)
    config = OmegaConf.create({"optimized_metric": METRIC, "optimized_validation": "best"})
    OmegaConf.save(config, run / "config.yaml")  # train.py writes it
    OmegaConf.save(OmegaConf.create([f"seed={label}", "debug=quick"]), run / ".hydra" / "overrides.yaml")
    gap = pd.DataFrame(
        [
            {"metric": m, "untrained": u, "trained": t, "densevlad": d, "groundtruth": "gt_relative_pose",
             "groundtruth_value": g, "gap_closed_pct": 100 * (t - d) / (g - d) if g != d else float("nan")}
            for m, u, t, d, g in rows
        ]
    )  # fmt: skip
    gap.to_csv(run / "gap.csv", index=False)
    validation_table([(-1, METRIC, 1.0), (0, METRIC, objective - 1), (1, METRIC, objective)]).to_csv(
        run / "validation.csv", index=False
    )
    (run / "summary.json").write_text(json.dumps({"seconds": seconds}))
    return run
