"""What a trained checkpoint buys on the five validation scenes of docs/results.md: per scene, the
gap rows of train.yaml's training report (``report.gap``: paradigms 1, 2a and 2b) for DenseVLAD (the
``report.baseline``), the untrained network, the checkpoint and the ground truth, written as each
scene's folder in the layout of a train.py run (``gap.csv``, ``validation.csv``: the untrained
network as epoch -1, the checkpoint as epoch 0; ``config.yaml``, ``summary.json``), so that
``report.py <output>/*_* --output <output>`` summarizes them: a row per scene and the mean row.

    python benchmarks/training_gain.py <run>/checkpoints/last.ckpt <output folder> [--overrides key=value ...]

The five scenes (``SCENES``: the mall with seeds 0, 1 and 2, the street with seeds 0 and 1) are
those of docs/results.md's "Training: what it buys on five scenes". Each is composed from
``configs/train.yaml`` with ``seed``, ``data.render.environment`` and ``--overrides`` (the ground
truths, the device), and benchmarked in one pass over every ranking (`locretrieval.benchmark`):
the three descriptors and the ground truths the gap rows name, the paradigms at the gap rows' k
only (a k's result does not depend on the others). The untrained network is the checkpoint's
model with its initial weights (``model``), the trained one ``model=checkpoint``. Also prints how
many steps and epochs the checkpoint was trained (used by ``gpu_training_gain.sh``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

import locretrieval  # noqa: F401  (config resolvers)

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
#: (environment, seed) of the five validation scenes, named ``<environment>_<seed>`` as in docs/results.md.
SCENES = (("mall", 0), ("mall", 1), ("mall", 2), ("street", 0), ("street", 1))
#: The ranking names of the gap table's columns (`locretrieval.report.training.gap_table`).
UNTRAINED, TRAINED = "untrained", "trained"


def composed(overrides: list[str]):
    """``configs/train.yaml`` with ``overrides``."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose("train", overrides=overrides)


def with_gap_ks(cfg, report) -> None:
    """``cfg``'s paradigms enabled and evaluated at the k of the gap rows only, the others disabled."""
    ks: dict[str, set[int]] = {}
    for row in report.gap:
        ks.setdefault(row.paradigm, set()).add(row.k)
    for name, section in cfg.paradigms.items():
        section.enabled = name in ks
        if name in ks:
            section.k = sorted(ks[name])


def checkpoint_progress(checkpoint: Path) -> str:
    """``"<steps> steps, in epoch <epoch>"`` (counted from 1) of a Lightning checkpoint, read by the
    restricted unpickler: a run stopped by ``trainer.max_time`` ends within an epoch."""
    from locretrieval.models.files.weights import load_torch_file

    content = load_torch_file(checkpoint)
    return f"{content['global_step']} steps, in epoch {content['epoch'] + 1}"


def scene_gaps(cfg, trained_model, report, cache_dir: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The gap table of one scene (DenseVLAD, the untrained and the trained network, the ground
    truths) and its validation history (``epoch, metric, value``: the untrained network -1, trained 0)."""
    from hydra.utils import instantiate

    from locretrieval.benchmark import benchmark, build_rankings, relevances
    from locretrieval.build import benchmark_settings, scene_of
    from locretrieval.config import validated
    from locretrieval.groundtruth import GroundTruthSettings, compute_groundtruths
    from locretrieval.report.training import gap_table
    from locretrieval.retrieval.descriptors import describe_scene
    from locretrieval.training.callbacks import VALIDATION_COLUMNS, figure_rows, query_outcomes
    from locretrieval.training.run import TrainingSettings

    settings = validated(TrainingSettings, cfg.training, "training").validation.settings(benchmark_settings(cfg))
    groundtruth_settings = validated(GroundTruthSettings, cfg.groundtruth, "groundtruth")
    scene = scene_of(cfg.data)
    groundtruths = compute_groundtruths(scene, groundtruth_settings, settings.sfm, cache_dir)
    models = {
        report.baseline: instantiate(cfg.validation_references[report.baseline]),
        UNTRAINED: instantiate(cfg.model),
        TRAINED: trained_model,
    }
    described = {name: describe_scene(model, scene, cache_dir) for name, model in models.items()}
    rankings = build_rankings(scene, described, groundtruths, settings.retrieval, random_seed=None)
    everything = {"all": np.ones(len(scene.queries), dtype=bool)}
    result = benchmark(
        scene, rankings, settings, everything, cache_dir, relevances(groundtruths, groundtruth_settings.relevance)
    )
    ks = settings.paradigms.ks()
    history = pd.DataFrame(
        [
            (epoch, metric, figure.value, figure.low, figure.high, figure.num_queries)
            for epoch, name in ((-1, UNTRAINED), (0, TRAINED))
            for metric, figure in figure_rows(result, name, ks).items()
        ],
        columns=VALIDATION_COLUMNS,
    )
    outcomes = {r.name: query_outcomes(result, r.name, scene.queries.names) for r in rankings}
    # gap_table reads a validation's per-query outcomes (before training: the untrained network; last: trained)
    validation = SimpleNamespace(
        outcomes=[outcomes[UNTRAINED], outcomes[TRAINED]],
        reference_outcomes={name: found for name, found in outcomes.items() if name not in (UNTRAINED, TRAINED)},
        splits={"val": "all"},
        subsets=everything,
        settings=settings,
    )
    return gap_table(validation, report), history


def main() -> None:
    from hydra.utils import instantiate

    from locretrieval.config import validated
    from locretrieval.report.training import TrainingReportSettings

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path, help="a Lightning checkpoint of train.py (its default model)")
    parser.add_argument("output", type=Path, help="folder of the per-scene <environment>_<seed>/gap.csv")
    parser.add_argument("--overrides", nargs="*", default=[], help="train.yaml overrides of every scene")
    arguments = parser.parse_args()
    if not arguments.checkpoint.is_file():
        parser.error(f"no checkpoint {arguments.checkpoint} (train.py writes <run>/checkpoints/last.ckpt)")
    print(f"checkpoint {arguments.checkpoint}: {checkpoint_progress(arguments.checkpoint)}", flush=True)
    for environment, seed in SCENES:
        started = time.perf_counter()
        scene = [f"seed={seed}", f"data.render.environment={environment}", *arguments.overrides]
        cfg = composed(scene)
        trained = composed([*scene, "model=checkpoint", f"model.weights={arguments.checkpoint}"]).model
        report = validated(TrainingReportSettings, cfg.report, "report")
        with_gap_ks(cfg, report)
        gaps, history = scene_gaps(cfg, instantiate(trained), report, Path(cfg.paths.cache_dir))
        folder = arguments.output / f"{environment}_{seed}"
        folder.mkdir(parents=True, exist_ok=True)
        gaps.to_csv(folder / "gap.csv", index=False)
        history.to_csv(folder / "validation.csv", index=False)
        OmegaConf.save(cfg, folder / "config.yaml")
        (folder / "summary.json").write_text(json.dumps({"seconds": round(time.perf_counter() - started, 1)}))
        print(f"{folder.name} ({time.perf_counter() - started:.0f} s):", flush=True)
        print(gaps.to_markdown(index=False, floatfmt=".1f"), flush=True)


if __name__ == "__main__":
    main()
