"""A train.py run (`locretrieval.training.run`) end to end through Hydra: validation before and
after training, checkpoints kept and resumed, DDP, extra rendered scenes, parallel multiruns, its
config checked before any work; training on several scenes at once (published datasets' miniatures,
a kapture folder of images, one's own place as a COLMAP scene), relevance within each scene only."""

import re
from pathlib import Path
from types import SimpleNamespace

import helpers
import numpy as np
import pandas as pd
import pytest
import torch
from helpers import train
from hydra.utils import instantiate
from own_place import render_walk, write_model
from published_layouts import LAYOUTS, install, write_kapture_folder
from published_layouts import SCENE as LAYOUTS_SCENE
from training_runs import AT_25M, METRIC, RELATIVE_POSE, SCENE, SMALL_DENSEVLAD, SMALL_VALIDATION_SIDE, TINY_TRAINING
from training_runs import cheap_train_config as train_config

from locretrieval.build import benchmark_settings, build_training
from locretrieval.cli import composed_training_scenes
from locretrieval.config import ConfigError, validated
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset
from locretrieval.sfm.features import extract_features
from locretrieval.training.callbacks import every_validation_metrics
from locretrieval.training.relevance import combined_pairs


@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory) -> str:
    """The override putting a run's caches in one folder for the file: the tiny scene rendered, its
    ground truths and reference descriptors computed by the first run, read by the others (the
    tests of a cold cache, or of a refusal before the scene is rendered, keep their own)."""
    return f"paths.cache_dir={tmp_path_factory.mktemp('cache')}"


@pytest.mark.smoke
def test_fast_dev_run_of_train_py_through_hydra_compose(tmp_path, shared_cache):
    cfg = train_config(tmp_path, shared_cache, "+trainer.fast_dev_run=true")
    validator = train(cfg, tmp_path / "run")
    epochs = sorted({entry["epoch"] for entry in validator.history})
    assert epochs == [-1, 0]  # before training, and after the one batch
    assert "val/approximation/ewb/k3/5m_10deg" in validator.history[0]
    assert (tmp_path / "run" / "validation.csv").exists() and (tmp_path / "run" / "report.md").exists()
    assert set(validator.reference) == {
        "densevlad",
        "gt_relative_pose",
        "gt_frustum",
        "random",
    }  # the reference rankings
    expected = every_validation_metrics(benchmark_settings(cfg), ["relative_pose", "frustum"])
    assert set(validator.history[1]) - {"epoch"} == set(expected)  # what checkpoints may monitor is what is logged


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory, shared_cache):
    """``python train.py debug=quick`` (its checkpoint and logging choices) on the tiny scene, with
    every gallery query: ``(validation callback, run folder, its log lines)``."""
    import logging

    root = tmp_path_factory.mktemp("quick")
    records, logger = [], logging.getLogger("locretrieval")
    handler, level = logging.Handler(), logger.level
    handler.emit = lambda record: records.append(record.getMessage())
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        cfg = train_config(root, shared_cache, "debug=quick", "callbacks.localization_validation.gallery_queries=8")
        validator = train(cfg, root / "run")
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    return validator, root / "run", records


def test_the_gallery_of_fixed_validation_queries_is_logged_to_tensorboard_and_the_report_at_each_validation(
    quick_run,
):
    validator, run, _ = quick_run
    # the gallery of the same validation queries at each validation, in TensorBoard and the report
    from io import BytesIO

    from PIL import Image
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tensorboard" / "version_0"), size_guidance={"images": 0})
    events.Reload()
    logged = events.Images("val/gallery")
    assert len(logged) == 2  # before training and after the batch
    last = np.asarray(Image.open(BytesIO(logged[-1].encoded_image_string)).convert("RGB"))
    np.testing.assert_array_equal(last, validator.galleries["last"])
    assert len(validator.gallery_rows) == 6 and (run / "gallery_before.jpg").exists()  # the 6 queries of the tiny scene
    assert "![gallery at the last validation](gallery_last.jpg)" in (run / "report.md").read_text()


def test_a_quick_run_keeps_one_checkpoint_in_a_few_tens_of_megabytes_and_ends_naming_what_it_wrote(quick_run):
    """debug=quick keeps last.ckpt only (EfficientNet-Lite0, its Adam state and the validation's
    galleries: 44 MB, its weights stored once); caches stay in paths.cache_dir, none is copied in."""
    _, run, records = quick_run
    sizes = {path.relative_to(run).as_posix(): path.stat().st_size for path in run.rglob("*") if path.is_file()}
    assert [name for name in sizes if name.startswith("checkpoints/")] == ["checkpoints/last.ckpt"]
    assert sum(sizes.values()) < 50e6, sorted(sizes.items(), key=lambda item: -item[1])[:5]
    assert max(size for name, size in sizes.items() if name != "checkpoints/last.ckpt") < 5e6
    assert records[-3:] == [
        f"run folder: {run}",
        f"checkpoint, last: {run / 'checkpoints' / 'last.ckpt'}",
        f"report: {run / 'report.md'}",
    ]


def test_a_checkpoint_monitoring_a_metric_never_logged_fails_at_start_up_naming_those_logged(tmp_path):
    cfg = train_config(tmp_path, "callbacks.best_checkpoint.monitor=val/approximation/ewb/k4/5m_10deg")
    with pytest.raises(
        ConfigError,
        match=r"callbacks.best_checkpoint.monitor: 'val/approximation/ewb/k4/5m_10deg' is not logged at "
        r"every validation; .* the metrics are: .*val/approximation/ewb/k3/5m_10deg",
    ):
        train(cfg, tmp_path / "run")
    assert not (Path(cfg.paths.cache_dir) / "synthetic").exists()  # before the scene is rendered
    sfm_only = train_config(tmp_path, "callbacks.best_checkpoint.monitor=val/global_sfm/pnp/k5/0.25m_2deg")
    with pytest.raises(ConfigError, match="is not logged at every validation"):  # logged every sfm_every_n_epochs only
        train(sfm_only, tmp_path / "run")


@pytest.mark.slow
def test_resuming_from_the_last_checkpoint_continues_the_same_curve(tmp_path, shared_cache):
    common = (shared_cache, "~augmentation", "trainer.deterministic=true")
    straight = train(
        train_config(tmp_path / "straight", *common, "trainer.max_epochs=2"), tmp_path / "straight" / "run"
    )
    checkpoints = tmp_path / "straight" / "run" / "checkpoints"
    assert torch.load(checkpoints / "last.ckpt", weights_only=False)["epoch"] == 1  # the last epoch, whichever was best
    # Interrupted after its first epoch: the same run (max_epochs, hence the cosine schedule) as the straight one.
    first = train_config(
        tmp_path / "resumed",
        *common,
        "trainer.max_epochs=2",
        "+callbacks.interrupt={_target_: helpers.StopAfterEpoch, epoch: 0}",
    )
    assert [entry["epoch"] for entry in train(first, tmp_path / "resumed" / "run").history] == [-1, 0]
    last = tmp_path / "resumed" / "run" / "checkpoints" / "last.ckpt"
    resumed = train(
        train_config(tmp_path / "resumed", *common, "trainer.max_epochs=2", f"ckpt_path={last}"),
        tmp_path / "resumed" / "run",
    )
    assert [entry["epoch"] for entry in resumed.history] == [-1, 0, 1]  # the callback's history came back
    for expected, found in zip(straight.history, resumed.history):
        assert found.keys() == expected.keys()
        for key, value in expected.items():
            assert found[key] == pytest.approx(value, abs=1e-6), (expected["epoch"], key)


@pytest.mark.slow
def test_two_process_cpu_ddp_smoke_run(tmp_path, shared_cache):
    import subprocess
    import sys

    tiny = [f"data.render.{key}={value}" for key, value in SCENE.items() if key != "conditions"]
    tiny += [f"data.render.conditions.{key}={value}" for key, value in SCENE["conditions"].items()]
    command = [
        sys.executable,
        str(helpers.CONFIGS.parent / "train.py"),
        "trainer=ddp",
        "trainer.accelerator=cpu",
        "trainer.devices=2",
        f"paths.root_dir={tmp_path}",
        shared_cache,  # the scene, its ground truths and references as the file's earlier runs left them
        f"hydra.run.dir={tmp_path}/run",
        "device=cpu",
        *tiny,
        SMALL_VALIDATION_SIDE,
        *TINY_TRAINING,
        *SMALL_DENSEVLAD,  # the references of the shared cache
        "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false",
        "model/backbone=torchvision",
        "model.backbone.name=resnet18",
        "model.weights=null",
        "model.random_init=true",
        "logger={}",
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Initializing distributed: GLOBAL_RANK: 1, MEMBER: 2/2" in done.stderr + done.stdout
    assert (tmp_path / "run" / "checkpoints" / "last.ckpt").exists()
    history = pd.read_csv(tmp_path / "run" / "validation.csv")
    assert sorted(set(history["epoch"])) == [-1, 0]


def test_extra_rendered_scenes_are_trained_on_with_their_queries_and_never_the_validation_queries(tmp_path, scene):
    from locretrieval.build import extra_renders
    from locretrieval.training.run import TrainingSettings, training_worlds

    cfg = train_config(tmp_path, "training.extra_renders=[{seed: 7}]")
    validation_scene = instantiate(cfg.data)
    settings = validated(TrainingSettings, cfg.training, "training")
    worlds = training_worlds(validation_scene, settings, [], extra_renders(cfg, settings, validation_scene))
    assert all(len(world.queries) == 0 for world in worlds)
    sets = [world.database for world in worlds]
    assert [len(images) for images in sets] == [24, 30]  # the validation database; the other world's database + queries
    assert not set(validation_scene.queries.paths) & {p for images in sets for p in images.paths}
    pairs = combined_pairs(sets, RELATIVE_POSE, [AT_25M] * len(sets))
    graded = pairs.graded.toarray()
    assert graded[24:48, 48:].any()  # the extra scene's database and queries are paired with each other
    itself = train_config(tmp_path, f"training.extra_renders=[{{seed: {SCENE['seed']}}}]")
    with pytest.raises(ValueError, match="renders the validation scene itself"):
        settings = validated(TrainingSettings, itself.training, "training")
        training_worlds(validation_scene, settings, [], extra_renders(itself, settings, validation_scene))


def test_an_output_dir_holding_a_link_out_of_it_is_refused_before_anything_is_written(tmp_path):
    """``output_dir`` may be another folder than Hydra's (which its callback checked)."""
    from locretrieval.errors import DataFileError

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").symlink_to(tmp_path / "victim.yaml")
    with pytest.raises(
        DataFileError, match=rf"^{run / 'config.yaml'}: a symbolic link to {tmp_path / 'victim.yaml'}, "
    ):
        train(train_config(tmp_path), run)
    assert not (tmp_path / "victim.yaml").exists() and sorted(path.name for path in run.iterdir()) == ["config.yaml"]


@pytest.mark.slow
def test_a_parallel_training_multirun_as_documented_shares_one_cache_without_corrupting_it(tmp_path):
    """docs/training.md's ``python train.py -m hydra/launcher=joblib_local loss=ap,triplet``, with the
    default worker counts (renderer, DataLoader, SfM) and as many overrides as a real sweep: two jobs
    at once on a cold cache render the scene once (the other job waits for it), share features,
    matches, maps and ground truths, get short job folders, and both validate exactly as a run alone
    on the finished cache does.

    The joblib launcher alone: its two jobs are two processes at once on one cache, what the cache's
    locks are for, and its loky workers are the launcher whose start method DataLoaders and pools
    must not inherit (`locretrieval.processes`). Submitit's local executor (as on SLURM) also runs
    two processes at once on one cache, which tests/test_shard.py checks on it with a cold cache
    (the scene rendered in a job, features, matches and maps shared), so it was dropped here."""
    import subprocess
    import sys

    tiny = [f"data.render.{key}={value}" for key, value in SCENE.items() if key not in ("conditions", "workers")]
    tiny += [f"data.render.conditions.{key}={value}" for key, value in SCENE["conditions"].items()]
    common = [
        f"paths.root_dir={tmp_path}",
        f"paths.cache_dir={tmp_path}/cache",
        "device=cpu",
        *tiny,
        SMALL_VALIDATION_SIDE,
        *(override for override in TINY_TRAINING if not override.startswith("datamodule.num_workers")),
        "callbacks.localization_validation.sfm_every_n_epochs=1",
        "paradigms.global_sfm.k=[1,3]",
        "paradigms.local_sfm.k=[3]",
        "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false",
        "~logger",
        *SMALL_DENSEVLAD,  # as the run alone's: the jobs' references cached for it
    ]
    command = [
        sys.executable,
        str(helpers.CONFIGS.parent / "train.py"),
        "-m",
        "hydra/launcher=joblib_local",
        "loss=ap,triplet",
        f"hydra.sweep.dir={tmp_path}/multirun",
        *common,
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=900, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    jobs = sorted(path.parent for path in (tmp_path / "multirun").glob("*/validation.csv"))
    assert [job.name.split("_")[0] for job in jobs] == ["0", "1"]
    assert all(len(job.name) <= 96 for job in jobs)  # 35 overrides: cut, with a hash
    logs = [(job / "train.log").read_text() for job in jobs]
    assert sum(log.count("rendering the synthetic scene") for log in logs) == 1  # one job rendered, the other read it
    # the two jobs' console lines interleave in the terminal: each says its job
    lines = re.findall(r"^\[\d{4}-[^]]+\](\[job \d\])?\[locretrieval\.", done.stdout, re.M)
    assert set(lines) == {"[job 0]", "[job 1]"}, done.stdout[-3000:]
    alone = train(
        train_config(
            tmp_path / "alone",
            f"paths.cache_dir={tmp_path}/cache",
            "callbacks.localization_validation.sfm_every_n_epochs=1",
            "paradigms.global_sfm.k=[1,3]",
            "paradigms.local_sfm.k=[3]",
            "~logger",
        ),
        tmp_path / "alone" / "run",
    )
    before_training = {key: value for key, value in alone.history[0].items()}
    assert any(key.startswith("val/global_sfm/") for key in before_training) and any(
        key.startswith("val/local_sfm/") for key in before_training
    )
    for job in jobs:
        history = pd.read_csv(job / "validation.csv")
        first = history[history["epoch"] == -1].set_index("metric")["value"]
        assert set(first.index) == set(before_training) - {"epoch"}
        for key, value in first.items():
            assert value == pytest.approx(before_training[key], abs=1e-6), (job, key)

    # the multirun's summary (the Hydra callback at its end), and report.py's of the folder afterwards
    summary = pd.read_csv(tmp_path / "multirun" / "summary.csv")
    validations = [pd.read_csv(job / "validation.csv") for job in jobs]
    objectives = [table[(table["epoch"] >= 0) & (table["metric"] == METRIC)]["value"].max() for table in validations]
    assert summary["objective"].tolist() == objectives and summary["state"].tolist() == ["finished", "finished"]
    assert summary["overrides"].str.contains("loss=ap").tolist() == [True, False]
    assert summary["best"].tolist() == [objectives[0] >= objectives[1], objectives[0] < objectives[1]]
    gap = pd.read_csv(jobs[0] / "gap.csv").set_index("metric")
    for metric, row in gap.iterrows():
        assert summary.loc[0, f"{metric} trained"] == pytest.approx(row["trained"]), metric
    markdown = (tmp_path / "multirun" / "summary.md").read_text()
    assert "| loss=ap " in markdown and "(best)" in markdown and "nan" not in markdown.lower()
    report = subprocess.run(
        [sys.executable, str(helpers.CONFIGS.parent / "report.py"), str(tmp_path / "multirun"), "--output", "again"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert report.returncode == 0, report.stderr[-3000:]
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "again" / "summary.csv"), summary)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("sampler.anchors=abc", r"sampler.anchors: Value 'abc' of type 'str' could not be converted to Integer"),
        (
            "+sampler.anchor=3",
            r"sampler.anchor: unknown key; expected one of \['pairs', "
            r"'anchors', 'negatives', 'batches_per_epoch', 'seed', 'positives'\]",
        ),
        (
            "augmentation.brightness=abc",
            r"augmentation.brightness: Value 'abc' of type 'str' could not be converted to Float",
        ),
        (
            "callbacks.localization_validation.every_n_epochs=often",
            r"callbacks.localization_validation.every_n_epochs: Value 'often'",
        ),
        (
            "train_relevance.definition=relative_pose",
            r"train_relevance.definition: must be a mapping with a _target_, the definition's class",
        ),
    ],
)
def test_every_object_node_is_checked_by_its_full_key_before_the_scene_is_prepared(tmp_path, override, message):
    cfg = train_config(tmp_path, override)
    with pytest.raises(ConfigError, match=message):
        train(cfg, tmp_path / "run")
    assert not (Path(cfg.paths.cache_dir) / "synthetic").exists()


def test_the_report_says_which_requested_gap_row_it_cannot_fill(tmp_path, caplog, shared_cache):
    cfg = train_config(
        tmp_path,
        shared_cache,
        "paradigms.approximation.k=[1,5]",
        "callbacks.localization_validation.sfm_every_n_epochs=null",
        "callbacks.best_checkpoint.monitor=val/approximation/ewb/k5/5m_10deg",
        "optimized_metric=val/approximation/ewb/k5/5m_10deg",
        "+trainer.fast_dev_run=true",
    )
    with caplog.at_level("WARNING"):
        train(cfg, tmp_path / "run")
    text = (tmp_path / "run" / "report.md").read_text()
    assert (
        "Requested row approximation/ewb/k3/5m_10deg (report.gap) "
        "is not filled: k=3 is not in paradigms.approximation.k [1, 5]." in text  # Markdown text: plain brackets
    )
    assert (
        "Requested row local_sfm/pnp/k10/0.25m_2deg (report.gap) is not filled: the SfM paradigms are not validated"
        in text
    )
    assert "report.gap row approximation/ewb/k3/5m_10deg cannot be filled" in caplog.text
    moved = train_config(
        tmp_path / "moved",
        shared_cache,
        "+trainer.fast_dev_run=true",
        "callbacks.localization_validation.sfm_every_n_epochs=null",
        "report.gap=[{paradigm: approximation, method: ewb, k: 1, "
        "threshold: [5.0, 10.0], groundtruths: [relative_pose]}]",
    )
    train(moved, tmp_path / "moved" / "run")
    gaps = pd.read_csv(tmp_path / "moved" / "run" / "gap.csv")
    assert list(gaps["metric"]) == ["approximation/ewb/k1/5m_10deg"] and list(gaps["groundtruth"]) == [
        "gt_relative_pose"
    ]
    wrong = train_config(tmp_path / "wrong", "report.baseline=netvlad")
    with pytest.raises(
        ConfigError,
        match=r"report.baseline: 'netvlad' is not a validation reference \(validation_references: \['densevlad'\]\)",
    ):
        train(wrong, tmp_path / "wrong" / "run")


def test_train_py_takes_a_step_with_a_pytorch_metric_learning_loss(tmp_path, shared_cache):
    cfg = train_config(tmp_path, shared_cache, "loss=multi_similarity", "+trainer.fast_dev_run=true")
    validator = train(cfg, tmp_path / "run")
    assert [entry["epoch"] for entry in validator.history] == [-1, 0]


def place(root, seed: int, count: int):
    """A walk of ``count`` photos and its COLMAP model, 3D points on the shops across it; returns
    ``(model folder, photo folder, image names, [images, points] membership of the tracks)``."""
    walk = render_walk(root / "photos", count, 96, 72, gps=False, seed=seed)
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.uniform(0.0, 20.0, 200), rng.uniform(3.0, 5.0, 200), rng.uniform(0.0, 4.0, 200)])
    tracks = [list(rng.choice(count, size=rng.integers(2, 5), replace=False)) for _ in points]
    write_model(root / "sparse", walk.names, walk.camera, walk.qvec, walk.tvec, tracks, points)
    membership = np.zeros((count, len(tracks)), dtype=int)
    for point, track in enumerate(tracks):
        membership[track, point] = 1
    return root / "sparse", walk.folder, walk.names, membership


@pytest.fixture(scope="module")
def places(tmp_path_factory):
    root = tmp_path_factory.mktemp("own_place_training")
    return root, place(root / "a", 0, 15), place(root / "b", 1, 10)


def test_train_py_trains_on_a_colmap_scene_beside_another_with_relevance_from_its_tracks(tmp_path, places):
    root, (model, images, names, membership), (other_model, other_images, other_names, other_membership) = places
    listed = f"{{config: colmap, name: other, model: {other_model}, images: {other_images}, metres_per_unit: 1.0}}"
    cfg = helpers.compose_config(
        "train", f"paths.root_dir={tmp_path}", f"output_dir={tmp_path}/run", "device=cpu", "data=colmap",
        f"data.model={model}", f"data.images={images}", "data.metres_per_unit=1.0", SMALL_VALIDATION_SIDE,
        *TINY_TRAINING, "datamodule.image_size=[96,72]", "trainer.max_epochs=1", "trainer.enable_progress_bar=false",
        "+trainer.fast_dev_run=true", "train_relevance=co_observation", "train_relevance.definition.min_shared=1",
        f"training.scenes=[{listed}]", "sampler.anchors=4", *SMALL_DENSEVLAD,
    )  # fmt: skip
    scene = instantiate(cfg.data)
    run = build_training(cfg, composed_training_scenes(cfg))  # what train.py builds
    parts = SimpleNamespace(
        sets=[world.database for world in run.worlds], pairs=run.datamodule.pairs, sampler=run.datamodule.sampler
    )
    other_database = [name for index, name in enumerate(other_names) if index % 5]  # a listed scene's database
    assert [s.names for s in parts.sets] == [scene.database.names, other_database]
    graded = parts.pairs.graded.toarray()
    for offset, (images, rows_of, tracks) in enumerate(
        [(parts.sets[0], names, membership), (parts.sets[1], other_names, other_membership)]
    ):
        start = sum(len(s) for s in parts.sets[:offset])
        block = graded[start : start + len(images), start : start + len(images)]
        rows = tracks[[rows_of.index(name) for name in images.names]]
        shared = rows @ rows.T  # the tracks' co-observations, counted by hand
        expected = np.where(shared >= 1, shared / np.maximum(np.diag(shared), 1)[:, None], 0.0)
        np.fill_diagonal(expected, 0.0)
        np.testing.assert_allclose(block, expected)
    assert not graded[: len(parts.sets[0]), len(parts.sets[0]) :].any()  # never related across scenes
    assert not (tmp_path / ".cache" / "features").exists()  # no SfM of ours: the tracks are the model's
    validator = train(cfg, tmp_path / "run")  # a training step, then validation on the model's queries
    assert validator.scene.queries.names == scene.queries.names and validator.history


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    """Aachen's and Baidu's downloader layouts and a plain kapture folder of JPEG images, from a rendered scene."""
    root = tmp_path_factory.mktemp("training_scenes")
    render_synthetic_dataset(helpers.render_settings({**LAYOUTS_SCENE, "seed": 9}), root / "source")
    scene = load_kapture_scene("source", [root / "source" / "mapping"], [root / "source" / "query"])
    local = {
        **extract_features(scene.database, helpers.sfm_settings().features, root / "cache", 1).load(
            scene.database.names
        ),
        **extract_features(scene.queries, helpers.sfm_settings().features, root / "cache", 1).load(scene.queries.names),
    }
    for name in ("aachen", "baidu"):
        install(LAYOUTS[name], (scene, local), root / "data")
    write_kapture_folder(
        root / "data" / "photos" / "mapping", scene.database, np.arange(8), "street/{i:03d}.jpg", posed=True
    )
    write_kapture_folder(
        root / "data" / "photos" / "query", scene.queries, np.arange(2), "phone/{i:03d}.jpg", posed=True
    )
    return root / "data"


SCENES = "training.scenes=[aachen,baidu,{config:kapture,mapping:photos/mapping,queries:[photos/query]}]"


@pytest.mark.slow
def test_several_scenes_are_trained_on_and_never_related_across(tmp_path, data_dir):
    cfg = train_config(
        tmp_path, f"paths.data_dir={data_dir}", SCENES, "sampler.anchors=6", "+trainer.fast_dev_run=true"
    )
    scene = instantiate(cfg.data)
    run = build_training(cfg, composed_training_scenes(cfg))  # what train.py builds
    parts = SimpleNamespace(
        sets=[world.database for world in run.worlds], pairs=run.datamodule.pairs, sampler=run.datamodule.sampler
    )
    sizes = [len(images) for images in parts.sets]
    assert sizes == [len(scene.database), 12, 12, 8]  # the validation scene's database, Aachen's, Baidu's, the photos'
    assert parts.sets[1].names[0].startswith("db/") and parts.sets[3].names[0].startswith("street/")
    starts = np.cumsum([0, *sizes])
    scene_of = np.repeat(np.arange(len(sizes)), sizes)
    graded, related = parts.pairs.graded.toarray(), parts.pairs.related.toarray()
    across = scene_of[:, None] != scene_of[None]
    assert not graded[across].any() and not related[across].any()  # relevance within each scene, never across
    for index in range(1, 4):  # each listed scene has relevant pairs of its own
        block = slice(starts[index], starts[index + 1])
        assert graded[block, block].any()
    drawn = [scene_of[batch] for batch in parts.sampler]
    assert any(len(set(batch)) > 1 for batch in drawn)  # batches drawn across scenes
    for batch in parts.sampler:
        relevance, _ = parts.pairs.batch(np.array(batch))
        assert not relevance[scene_of[batch][:, None] != scene_of[batch][None]].any()
    validator = train(cfg, tmp_path / "run")  # a training step, then validation on the synthetic scene's queries
    assert validator.scene.queries.names == scene.queries.names and validator.history


def test_a_listed_scene_that_is_no_data_config_is_named_before_any_work(tmp_path):
    cfg = train_config(tmp_path, "training.scenes=[aachen,atlantis]")
    with pytest.raises(ConfigError, match=r"training.scenes: no data config 'atlantis'; expected one of \[.*'baidu'"):
        train(cfg, tmp_path / "run")
    assert not (Path(cfg.paths.cache_dir) / "synthetic").exists()  # the validation scene was not rendered
