"""The run behind ``export.py``: check, instantiate, compute the rankings (`DescriptorSearch`: the
descriptor cache evaluate.py fills), write."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from locretrieval.benchmark import check_supported, check_unique_names
from locretrieval.cache import safe_name
from locretrieval.config import ConfigError, built, check_run_config, validated
from locretrieval.export.onnx import OnnxSettings, export_onnx, torch_network
from locretrieval.export.pairs import PairsSettings
from locretrieval.export.scene import DescriptorSettings, check_scene_names, export_scene
from locretrieval.groundtruth import GroundTruthSettings, compute_groundtruths
from locretrieval.retrieval.descriptors import DescriptorSearch
from locretrieval.retrieval.index import RetrievalSettings
from locretrieval.retrieval.ranking import Ranking
from locretrieval.scene import Scene
from locretrieval.scene.datasets import instantiate_scene
from locretrieval.sfm.inputs import SfmSettings

log = logging.getLogger(__name__)

#: What ``export`` may list.
EXPORTS = ("pairs", "descriptors", "onnx")


def export(cfg: DictConfig, output_dir: Path) -> list[Path]:
    """Write what ``cfg.export`` lists into ``output_dir`` (files named in docs/export.md): ``pairs``
    (`PairsSettings`: the model's rankings and those of the ground truth ``groundtruth`` enables),
    ``descriptors`` (`DescriptorSettings`: the model's global descriptors), ``onnx`` (`OnnxSettings`:
    the model's network). The limits and every ``_target_`` (`check_run_config`), every section, the
    packages ONNX needs, the model's inputs and the scene's image names are checked before any work.
    Returns the files and folders written."""
    started = time.perf_counter()
    check_run_config(cfg)  # the run's limits; every _target_ a part, before anything it names is imported
    wanted = list(cfg.export)
    unknown = sorted(set(wanted) - set(EXPORTS))
    if unknown or not wanted:
        raise ConfigError(f"export: lists what to write, some of {list(EXPORTS)}; got {wanted}")
    pairs = validated(PairsSettings, cfg.pairs, "pairs") if "pairs" in wanted else None
    descriptors = validated(DescriptorSettings, cfg.descriptors, "descriptors") if "descriptors" in wanted else None
    onnx = validated(OnnxSettings, cfg.onnx, "onnx") if "onnx" in wanted else None
    retrieval = validated(RetrievalSettings, cfg.retrieval, "retrieval")
    groundtruth = validated(GroundTruthSettings, cfg.groundtruth, "groundtruth") if pairs is not None else None
    if pairs is not None and pairs.k > retrieval.depth:
        raise ConfigError(f"pairs.k: {pairs.k} is more than retrieval.depth={retrieval.depth}, the rankings' depth")
    if onnx is not None:
        onnx.check_packages()
    model = built(cfg.model, "model")  # a missing weight file is named with where to get it
    network = torch_network(model) if onnx is not None else None
    scene = instantiate_scene(cfg.data) if pairs is not None or descriptors is not None else None
    if scene is not None:
        check_scene_names(scene)
        problems = model.missing_inputs(scene)
        if problems:
            raise FileNotFoundError("nothing was exported: " + "; ".join(f"model.{p}" for p in problems))
        if groundtruth is not None:
            check_supported(scene, list(groundtruth.parsed()))
    output_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, output_dir / "config.yaml", resolve=True)  # as run; .hydra/ keeps the interpolations
    written = []
    if scene is not None:
        cache_dir = Path(cfg.paths.cache_dir)
        rankings = list(model.rankings(scene, DescriptorSearch(retrieval, cache_dir)))
        if groundtruth is not None:
            rankings += groundtruth_rankings(scene, groundtruth, cfg, cache_dir)
        check_unique_names(rankings)
        written += export_scene(scene, rankings, output_dir, pairs, descriptors)
    if network is not None:
        written.append(export_onnx(network, output_dir / f"{safe_name(model.name)}.onnx", onnx))
    log.info("exported %d files and folders in %.1f s to %s", len(written), time.perf_counter() - started, output_dir)
    return written


def groundtruth_rankings(
    scene: Scene, settings: GroundTruthSettings, cfg: DictConfig, cache_dir: Path
) -> list[Ranking]:
    """The rankings of the ground truth ``settings`` enables (cached in ``cache_dir``, as evaluate.py
    computes them; co-observation with ``cfg.sfm``'s local features); none when no query has a
    reference pose."""
    if not settings.parsed():
        return []
    if not scene.queries.has_pose.any():
        log.warning("no query has a reference pose: no ground-truth pairs")
        return []
    sfm = validated(SfmSettings, cfg.sfm, "sfm")
    return [truth.ranking for truth in compute_groundtruths(scene, settings, sfm, cache_dir).values()]
