"""What the training tests share: a tiny rendered scene, train.py's config for a short training of it,
random training pairs, a finished train.py run's files, and relative-pose training relevance."""

import dataclasses
import json
from pathlib import Path

import helpers
import numpy as np
import pandas as pd
from omegaconf import OmegaConf
from scipy import sparse

from locretrieval.groundtruth import DefinitionContext
from locretrieval.training.relevance import (
    TrainingPairs,
    TrainingRelevanceSettings,
    UnrelatedNegatives,
)

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

#: Validation's DenseVLAD reference of the tiny scene, cheap: one scale of dense SIFT every 4 px on
#: images halved to 48 px, 16 words learned from 2,000 descriptors (the published settings take
#: seconds of CPU per validation that a test of the training loop does not need).
SMALL_DENSEVLAD = (
    "validation_references.densevlad.max_side=48",
    "validation_references.densevlad.step=4",
    "validation_references.densevlad.bin_sizes=[4]",
    "validation_references.densevlad.num_words=16",
    "validation_references.densevlad.vocabulary_samples=2000",
    "validation_references.densevlad.kmeans_iterations=10",
)
#: A run whose validations are cheap: the tiny scene with half its database and 2 queries (each
#: validation describes every image with the trained network), `SMALL_DENSEVLAD`.
SMALL_VALIDATION = ("data.render.num_database=12", "data.render.num_queries=2", *SMALL_DENSEVLAD)

#: Validation images shrunk to 64 px (the tiny scene's are 96 x 72): describing every image of the
#: scene at each validation is most of a run's time, and what the tests check of a validation holds
#: at any size.
SMALL_VALIDATION_SIDE = "model.max_side=64"


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


def cheap_train_config(root, *overrides):
    """`train_config` validated against `SMALL_DENSEVLAD` on images of `SMALL_VALIDATION_SIDE`, for
    tests that read the trained descriptor's validation, not the reference's."""
    return train_config(root, *SMALL_DENSEVLAD, *overrides, image_side=SMALL_VALIDATION_SIDE)


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


def outcomes(percent: float, queries: int) -> np.ndarray:
    """Per-query outcomes (int8, 1: localized) of ``queries`` queries, the first ``percent`` % localized:
    nested, so that a larger share localizes every query a smaller one does."""
    return (np.arange(queries) < round(percent * queries / 100)).astype(np.int8)


def gap_run(
    folder: Path,
    label: str,
    objective: float,
    rows: list[tuple],
    seconds: float = 12.0,
    queries: int = 100,
    held_out: float | None = None,
) -> Path:
    """A finished train.py run's files as the summary reads them: ``gap.csv`` of ``rows`` (metric and
    the % untrained, trained, densevlad and ground truth localized of ``queries`` validation queries, as
    `gap_row` writes it), validation.csv (the objective with its interval), summary.json, config.yaml, .hydra;
    with ``held_out`` (% localized), as many held-out queries again, the objective's metric on them at its
    best validation and every query's outcome there (``validation_queries.csv.gz``)."""
    from locretrieval.metrics.uncertainty import default_uncertainty, share_interval
    from locretrieval.report.training import gap_row

    run = folder / label
    (run / ".hydra").mkdir(parents=True)
    config = OmegaConf.create({"optimized_metric": METRIC, "optimized_validation": "best"})
    OmegaConf.save(config, run / "config.yaml")  # train.py writes it
    OmegaConf.save(OmegaConf.create([f"seed={label}", "debug=quick"]), run / ".hydra" / "overrides.yaml")
    everyone = np.ones(queries, dtype=bool)
    gap = pd.DataFrame(
        [
            gap_row(
                metric,
                "all",
                everyone,
                {name: outcomes(value, queries) for name, value in zip(GAP_OUTCOMES, values)},
                default_uncertainty(),
                "densevlad",
            )
            | {"groundtruth": "gt_relative_pose"}
            for metric, *values in rows
        ]
    )
    gap.to_csv(run / "gap.csv", index=False)
    figures = [(-1, 1.0), (0, objective - 1), (1, objective)]
    intervals = [share_interval(round(value * queries / 100), queries, 0.95) for _, value in figures]
    validation = pd.DataFrame(
        [
            (epoch, METRIC, value, 100 * low, 100 * high, queries)
            for (epoch, value), (low, high) in zip(figures, intervals)
        ],
        columns=["epoch", "metric", "value", "low", "high", "num_queries"],
    )
    if held_out is not None:
        low, high = share_interval(round(held_out * queries / 100), queries, 0.95)
        held = ("held_out/" + METRIC.removeprefix("val/"), held_out, 100 * low, 100 * high, queries)
        validation.loc[len(validation)] = (1, *held)
        key = METRIC.removeprefix("val/")
        names = [f"q{index:03d}" for index in range(2 * queries)]
        split = ["val"] * queries + ["held_out"] * queries
        localized = np.concatenate([outcomes(objective, queries), outcomes(held_out, queries)])
        pd.DataFrame(
            {"ranking": "trained", "epoch": 1, "metric": key, "query": names, "split": split, "localized": localized}
        ).to_csv(run / "validation_queries.csv.gz", index=False)
    validation.to_csv(run / "validation.csv", index=False)
    (run / "summary.json").write_text(json.dumps({"seconds": seconds}))
    return run


#: The outcomes of a gap row, in `gap_run`'s order.
GAP_OUTCOMES = ("untrained", "trained", "baseline", "groundtruth")


RELATIVE_POSE = TrainingRelevanceSettings(
    {
        "_target_": "locretrieval.groundtruth.RelativePoseDefinition",
        "position_threshold": 10.0,
        "rotation_threshold": 30.0,
        "ranked": "within_thresholds",
    },
    UnrelatedNegatives(0.1, None, None),
)


AT_25M = DefinitionContext(far=25.0)


def negatives(rule=None, **changes):
    """`RELATIVE_POSE` with another negatives ``rule``, or its rule with other settings."""
    return dataclasses.replace(RELATIVE_POSE, negatives=rule or dataclasses.replace(RELATIVE_POSE.negatives, **changes))
