"""The run behind ``export.py``: compute the rankings (`DescriptorSearch`: the descriptor cache
evaluate.py fills) and write them, from the objects the build step made of the config (`Export`,
`locretrieval.build.build_export`)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from locretrieval.benchmark import check_supported, check_unique_names
from locretrieval.cache import safe_name
from locretrieval.config import ConfigError
from locretrieval.errors import require_built
from locretrieval.export.onnx import OnnxSettings, export_onnx
from locretrieval.export.pairs import PairsSettings
from locretrieval.export.scene import DescriptorSettings, check_scene_names, export_scene
from locretrieval.groundtruth import GroundTruthSettings, compute_groundtruths
from locretrieval.retrieval.descriptors import DescriptorSearch
from locretrieval.retrieval.index import RetrievalSettings
from locretrieval.retrieval.ranking import Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.settings import SfmSettings

log = logging.getLogger(__name__)

#: What ``export`` may list.
EXPORTS = ("pairs", "descriptors", "onnx")


@dataclass
class Export:
    """What ``export.py`` writes, built from its config by `locretrieval.build.build_export` (every key,
    ``_target_``, the packages ONNX needs and the model's inputs checked there): the ``pairs``,
    ``descriptors`` and ``onnx`` settings of what ``export`` lists (None: not listed), the ``model``,
    its torch ``network`` (for ONNX; None: not listed), the ``scene`` (None: ONNX alone needs none), the
    ``retrieval`` depth, the ground truths whose pairs
    are written too (``groundtruth``, None without pairs) and the ``sfm`` settings of those that match
    local features, the ``cache_dir`` evaluate.py fills and the ``config`` as run (plain data)."""

    pairs: PairsSettings | None
    descriptors: DescriptorSettings | None
    onnx: OnnxSettings | None
    model: Any
    network: Any
    scene: Scene | None
    retrieval: RetrievalSettings
    groundtruth: GroundTruthSettings | None
    sfm: SfmSettings
    cache_dir: Path
    config: dict = field(repr=False)


def check_export(wanted: list[str], pairs: PairsSettings | None, retrieval: RetrievalSettings) -> None:
    """A `ConfigError` when ``export`` lists nothing or what cannot be written, or ``pairs.k`` is
    deeper than the rankings."""
    unknown = sorted(set(wanted) - set(EXPORTS))
    if unknown or not wanted:
        raise ConfigError(f"export: lists what to write, some of {list(EXPORTS)}; got {wanted}")
    if pairs is not None and pairs.k > retrieval.depth:
        raise ConfigError(f"pairs.k: {pairs.k} is more than retrieval.depth={retrieval.depth}, the rankings' depth")


def check_scene(scene: Scene, model: Any, groundtruth: GroundTruthSettings | None) -> None:
    """Before any work: the scene's image names (pairs files hold them), the model's inputs and the
    ground truths the scene supports."""
    check_scene_names(scene)
    problems = model.missing_inputs(scene)
    if problems:
        raise FileNotFoundError("nothing was exported: " + "; ".join(f"model.{p}" for p in problems))
    if groundtruth is not None:
        check_supported(scene, list(groundtruth.parsed()))


def export(run: Export, output_dir: Path) -> list[Path]:
    """Write what ``run`` lists into ``output_dir`` (files named in docs/export.md): ``pairs``
    (`PairsSettings`: the model's rankings and those of the ground truth ``groundtruth`` enables),
    ``descriptors`` (`DescriptorSettings`: the model's global descriptors), ``onnx`` (`OnnxSettings`:
    the model's network). Returns the files and folders written."""
    require_built(run, Export, "build_export")
    started = time.perf_counter()
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / "config.yaml").write_text(yaml.safe_dump(run.config, sort_keys=False))  # as run, resolved
    written = []
    if run.scene is not None:
        rankings = list(run.model.rankings(run.scene, DescriptorSearch(run.retrieval, run.cache_dir)))
        if run.groundtruth is not None:
            rankings += groundtruth_rankings(run.scene, run.groundtruth, run.sfm, run.cache_dir)
        check_unique_names(rankings)
        written += export_scene(run.scene, rankings, output_dir, run.pairs, run.descriptors)
    if run.network is not None:
        written.append(export_onnx(run.network, output_dir / f"{safe_name(run.model.name)}.onnx", run.onnx))
    log.info("exported %d files and folders in %.1f s to %s", len(written), time.perf_counter() - started, output_dir)
    return written


def groundtruth_rankings(
    scene: Scene, settings: GroundTruthSettings, sfm: SfmSettings, cache_dir: Path
) -> list[Ranking]:
    """The rankings of the ground truth ``settings`` enables (cached in ``cache_dir``, as evaluate.py
    computes them; co-observation with ``sfm``'s local features); none when no query has a
    reference pose."""
    if not settings.parsed():
        return []
    if not scene.queries.has_pose.any():
        log.warning("no query has a reference pose: no ground-truth pairs")
        return []
    return [truth.ranking for truth in compute_groundtruths(scene, settings, sfm, cache_dir).values()]
