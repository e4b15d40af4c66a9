"""The localization-validation callback and the hard-negative miner (`locretrieval.training.callbacks`):
its metrics equal a direct benchmark, a seeded subset of the queries, a time budget."""

import numpy as np
import pytest
import torch
from helpers import train
from hydra.utils import instantiate
from omegaconf import OmegaConf
from training_runs import AT_25M, RELATIVE_POSE
from training_runs import cheap_train_config as train_config

from locretrieval.benchmark import benchmark, build_rankings, relevances
from locretrieval.build import benchmark_settings
from locretrieval.config import ConfigError, validated
from locretrieval.groundtruth import GroundTruthSettings, RankedRelevance, compute_groundtruths
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.training.callbacks import TRAINED, metric_rows
from locretrieval.training.data import RelevanceBatchSampler
from locretrieval.training.relevance import training_pairs
from locretrieval.training.run import ValidationScope


@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory) -> str:
    """The override putting a run's caches in one folder for the file: the tiny scene rendered, its
    ground truths and reference descriptors computed by the first run, read by the others."""
    return f"paths.cache_dir={tmp_path_factory.mktemp('cache')}"


def test_callback_metrics_equal_a_direct_benchmark_and_evaluate_reads_the_checkpoint(tmp_path, shared_cache):
    cfg = train_config(
        tmp_path,
        shared_cache,
        "callbacks.localization_validation.sfm_every_n_epochs=1",
        "paradigms.global_sfm.k=[1,3]",
    )
    validator = train(cfg, tmp_path / "run")
    logged = validator.history[-1]
    checkpoint = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert checkpoint.exists()
    # evaluate.py's path: the zoo model reads the Lightning checkpoint unchanged
    model_cfg = OmegaConf.merge(cfg.model, {"weights": str(checkpoint), "max_side": 64})  # SMALL_VALIDATION_SIDE
    model = instantiate(model_cfg)
    settings = benchmark_settings(cfg)
    scene = instantiate(cfg.data)
    groundtruths = compute_groundtruths(
        scene, validated(GroundTruthSettings, cfg.groundtruth, "groundtruth"), settings.sfm, cfg.paths.cache_dir
    )
    descriptors = describe_scene(model, scene, cache_dir=None)
    rankings = build_rankings(scene, {TRAINED: descriptors}, groundtruths, settings.retrieval, random_seed=None)
    result = benchmark(
        scene,
        rankings,
        settings,
        {"all": np.ones(len(scene.queries), bool)},
        cfg.paths.cache_dir,
        relevances(groundtruths, RankedRelevance()),
    )
    direct = metric_rows(result, TRAINED, settings.paradigms.ks())
    assert direct.keys() == {k for k in logged if k != "epoch"}
    for key, value in direct.items():
        assert logged[key] == pytest.approx(value, abs=1e-6), key
    assert any(key.startswith("val/global_sfm/") for key in direct)
    assert {"val/local_sfm/pnp/k5/0.25m_2deg", "val/local_sfm/pnp/k10/0.25m_2deg"} <= direct.keys()  # 2a by default too
    sfm_validations = [entry for entry in validator.history if "val/local_sfm/pnp/k10/0.25m_2deg" in entry]
    assert len(sfm_validations) >= 2  # before training and after the epoch


def test_hard_negatives_are_the_highest_ranked_unrelated_images_by_the_current_network(scene):
    from types import SimpleNamespace

    from locretrieval.models import NetworkDescriptor
    from locretrieval.models.extraction import ExtractionSettings, Preprocessing
    from locretrieval.models.networks import GeMPooling, RetrievalNet
    from locretrieval.training.callbacks import HardNegativeMining

    torch.manual_seed(0)
    network = RetrievalNet(
        torch.nn.Sequential(torch.nn.Conv2d(3, 16, 5, stride=2), torch.nn.ReLU()),
        GeMPooling(16, 3.0, trainable=True),
        16,
    )
    pairs = training_pairs(scene.database, RELATIVE_POSE, AT_25M)
    sampler = RelevanceBatchSampler(pairs, anchors=4, positives=1, negatives=4, batches_per_epoch=1, seed=0)
    preprocessing = Preprocessing(max_side=None, scales=(1.0,))
    extraction = ExtractionSettings("cpu", 8, 0, False, False, None)
    mining = HardNegativeMining(
        [scene.database], pairs, sampler, preprocessing, extraction, every_n_steps=5, per_anchor=3
    )
    module = SimpleNamespace(network=network)
    for step in (0, 3, 4):  # not a multiple of 5 (or the first step): nothing mined
        mining.on_train_batch_start(SimpleNamespace(global_step=step, global_rank=0, world_size=1), module, None, step)
    assert sampler.hard == {}
    mining.on_train_batch_start(SimpleNamespace(global_step=5, global_rank=0, world_size=1), module, None, 5)
    descriptors = NetworkDescriptor("check", network, preprocessing, extraction).describe(scene.database)
    related = pairs.related.toarray()
    for anchor in sampler.anchors:
        similarity = descriptors @ descriptors[anchor]
        allowed = [i for i in np.argsort(-similarity, kind="stable") if i != anchor and not related[anchor, i]]
        assert set(sampler.hard[int(anchor)].tolist()) == set(allowed[:3])


def test_validation_on_a_seeded_subset_of_the_queries_with_capped_sfm_features(tmp_path, shared_cache):
    scope = ValidationScope(max_queries=4, seed=3, sfm_max_keypoints=200, budget_minutes=None, held_out=0.0)
    cfg = train_config(
        tmp_path,
        shared_cache,
        "training.validation.max_queries=4",
        "training.validation.seed=3",
        "training.validation.sfm_max_keypoints=200",
        "+trainer.fast_dev_run=true",
    )
    validator = train(cfg, tmp_path / "run")
    full = instantiate(cfg.data)
    expected = np.sort(np.random.default_rng(3).choice(len(full.queries), size=4, replace=False))
    assert validator.scene.queries.names == [
        full.queries.names[q] for q in expected
    ]  # the same queries at every validation
    assert validator.settings.sfm.features.max_keypoints == 200
    settings = scope.settings(benchmark_settings(cfg))
    assert (
        settings.sfm.features.max_keypoints == 200 and scope.scene(full).queries.names == validator.scene.queries.names
    )
    assert ValidationScope(None, 0, None, None, 0.0).scene(full) is full


class FakeClock:
    """A clock that SfM work advances by ``per_query`` seconds a query (and describing by nothing):
    `sfm_within_budget`'s chunks as a machine of that throughput would cut them."""

    def __init__(self, per_query: float) -> None:
        self.now, self.per_query, self.chunks = 0.0, per_query, []

    def __call__(self) -> float:
        return self.now

    def install(self, monkeypatch) -> None:
        import locretrieval.benchmark as core
        import locretrieval.training.callbacks as callbacks

        real = core.run_sfm

        def run_sfm(inputs, rankings, paradigms, shard=None, queries=None):
            if queries is not None:  # a chunk of the budgeted validation
                self.chunks.append(list(queries))
                self.now += self.per_query * len(queries)
            return real(inputs, rankings, paradigms, shard, queries)

        monkeypatch.setattr(core, "run_sfm", run_sfm)
        monkeypatch.setattr(core.time, "perf_counter", self)
        monkeypatch.setattr(callbacks.time, "perf_counter", self)


@pytest.mark.parametrize("minutes, reached", [(0.5, 3), (0.9, 6)])
def test_the_first_validation_settles_the_queries_the_budget_holds_and_every_validation_keeps_them(
    tmp_path, monkeypatch, shared_cache, minutes, reached
):
    """10 s a query (a fake clock): 0.5 min reach 1, then 2 more (the 20 s left hold 2) = 30 s; 0.9 min
    reach 1, then 2 (at most twice the last chunk), 2 (24 s left), 1 (4 s left: one at least) = all 6."""
    clock = FakeClock(per_query=10.0)
    clock.install(monkeypatch)
    import locretrieval.training.callbacks as callbacks

    validated_on = []
    real_benchmark = callbacks.benchmark
    monkeypatch.setattr(
        callbacks,
        "benchmark",
        lambda scene, *args: validated_on.append(scene.queries.names) or real_benchmark(scene, *args),
    )
    cfg = train_config(  # one epoch: the validation before training settles the queries, the one after keeps them
        tmp_path,
        shared_cache,
        "callbacks.localization_validation.sfm_every_n_epochs=1",
        f"training.validation.budget_minutes={minutes}",
        "training.validation.seed=7",
        "paradigms.local_sfm.k=[2]",
        "paradigms.global_sfm.k=[1]",
    )
    validator = train(cfg, tmp_path / "run")
    order = np.random.default_rng(7).permutation(6)
    sizes = [len(chunk) for chunk in clock.chunks]
    assert sizes == ([1, 2] if reached == 3 else [1, 2, 2, 1]) and [q for c in clock.chunks for q in c] == list(
        order[:reached]
    )
    names = [instantiate(cfg.data).queries.names[q] for q in np.sort(order[:reached])]
    assert validator.scene.queries.names == validator.validated_queries == names
    # references, then epochs -1 and 0: every validation on the same queries
    assert len(validated_on) == 3 and all(queries == names for queries in validated_on)
    assert sorted({entry["epoch"] for entry in validator.history}) == [-1, 0]


def test_a_budget_too_small_for_one_validation_query_is_a_clear_error(tmp_path, monkeypatch, shared_cache):
    FakeClock(per_query=10.0).install(monkeypatch)
    cfg = train_config(
        tmp_path,
        shared_cache,
        "callbacks.localization_validation.sfm_every_n_epochs=1",
        "training.validation.budget_minutes=0.1",
    )
    with pytest.raises(
        ConfigError,
        match=r"training.validation.budget_minutes: 0.1 min cannot hold one validation query: describing the 30 "
        r"validation images took 0.0 s and localizing 1 query 10.0 s",
    ):
        train(cfg, tmp_path / "run")
    assert not (tmp_path / "run" / "checkpoints").exists()  # before any training step
