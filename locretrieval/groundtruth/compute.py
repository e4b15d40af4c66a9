"""Compute the configured ground-truth definitions (``configs/groundtruth/``), with a cache."""

from __future__ import annotations

import functools
import inspect
import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf
from scipy import sparse

from locretrieval.cache import cached_arrays, config_key
from locretrieval.groundtruth.base import GroundTruth
from locretrieval.groundtruth.co_observation import co_observation_groundtruth
from locretrieval.groundtruth.frustum import frustum_groundtruth
from locretrieval.groundtruth.relative_pose import relative_pose_groundtruth
from locretrieval.retrieval import Ranking
from locretrieval.scene import ImageSet

log = logging.getLogger(__name__)

#: Parameters that change how a ground truth is computed, not what: left out of cache keys.
RESULT_NEUTRAL_PARAMETERS = ("workers",)

#: Ground-truth builders by definition type, each called as
#: ``builder(database, queries, depth=..., name=..., **parameters)``, plus ``cache_dir=`` for
#: builders that take it (their features and matches are cached there).
DEFINITIONS: dict[str, Callable[..., GroundTruth]] = {
    "relative_pose": relative_pose_groundtruth,
    "frustum": frustum_groundtruth,
    "co_observation": co_observation_groundtruth,
}

#: Bump when the meaning of cached ground-truth files changes.
CACHE_VERSION = 1


def compute_groundtruths(
    database: ImageSet,
    queries: ImageSet,
    config: Mapping[str, Any] | DictConfig,
    cache_dir: str | Path | None = None,
) -> dict[str, GroundTruth]:
    """Every definition of ``config`` (``depth`` and ``definitions``), keyed by its name.

    Each entry of ``definitions`` maps a name to its parameters; the optional ``type``
    parameter picks the builder in `DEFINITIONS` (default: the name itself), so one type can
    appear twice, e.g. ``frustum_25m: {type: frustum, far: 25.0}``. Rankings are named
    ``gt_<name>``. With ``cache_dir``, results are stored under ``<cache_dir>/groundtruth``,
    keyed by both image sets' fingerprints and the definition's parameters.
    """
    if isinstance(config, DictConfig):
        config = OmegaConf.to_container(config, resolve=True)
    if "definitions" not in config:
        raise ValueError(f"ground-truth config needs a 'definitions' mapping, got keys {sorted(config)}")
    depth = int(config.get("depth", 50))
    fingerprints = (database.fingerprint(), queries.fingerprint()) if cache_dir is not None else ()
    groundtruths = {}
    for name, parameters in (config["definitions"] or {}).items():
        kind, parameters = _definition(name, parameters)
        path = None
        if cache_dir is not None:
            produced_by = {k: v for k, v in parameters.items() if k not in RESULT_NEUTRAL_PARAMETERS}
            key = config_key(CACHE_VERSION, kind, produced_by, depth, *fingerprints)
            path = Path(cache_dir) / "groundtruth" / f"{name}-{key}.npz"
        builder = DEFINITIONS[kind]
        extra = {"cache_dir": cache_dir} if "cache_dir" in inspect.signature(builder).parameters else {}
        build = functools.partial(builder, database, queries, depth=depth, name=f"gt_{name}", **parameters, **extra)
        arrays, hit = cached_arrays(path, lambda: _to_arrays(build()))
        if hit:
            log.info("ground truth %s loaded from %s", name, path)
        groundtruths[name] = _from_arrays(arrays, f"gt_{name}")
    return groundtruths


def _definition(name: str, parameters: Mapping[str, Any] | None) -> tuple[str, dict[str, Any]]:
    """``(type, parameters)`` of one config entry, checked against its builder's signature."""
    parameters = dict(parameters or {})
    kind = parameters.pop("type", name)
    if kind not in DEFINITIONS:
        raise ValueError(f"ground-truth definition {name!r}: unknown type {kind!r}; known: {sorted(DEFINITIONS)}")
    accepted = set(inspect.signature(DEFINITIONS[kind]).parameters) - {"database", "queries", "depth", "name", "cache_dir"}
    unknown = sorted(set(parameters) - accepted)
    if unknown:
        raise ValueError(f"ground-truth definition {name!r}: unknown parameters {unknown}; {kind} takes {sorted(accepted)}")
    return kind, parameters


def _to_arrays(groundtruth: GroundTruth) -> dict[str, np.ndarray]:
    relevance = groundtruth.relevance
    return {
        "indices": groundtruth.ranking.indices,
        "scores": groundtruth.ranking.scores,
        "relevance_indptr": relevance.indptr,
        "relevance_indices": relevance.indices,
        "relevance_shape": np.array(relevance.shape),
        "query_has_pose": groundtruth.query_has_pose,
    }


def _from_arrays(arrays: dict[str, np.ndarray], name: str) -> GroundTruth:
    relevance = sparse.csr_matrix(
        (np.ones(len(arrays["relevance_indices"]), dtype=bool), arrays["relevance_indices"], arrays["relevance_indptr"]),
        shape=tuple(arrays["relevance_shape"]),
    )
    ranking = Ranking(name, arrays["indices"], arrays["scores"], "groundtruth")
    return GroundTruth(ranking, relevance, arrays["query_has_pose"])
