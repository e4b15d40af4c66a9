"""Compute the configured ground-truth definitions (``configs/groundtruth/``), with a cache."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import sparse

from locretrieval.cache import cached_arrays, config_key
from locretrieval.config import ConfigError, require, validated
from locretrieval.groundtruth.base import GroundTruth
from locretrieval.groundtruth.co_observation import CoObservationDefinition, co_observation_groundtruth
from locretrieval.groundtruth.frustum import FrustumDefinition, frustum_groundtruth
from locretrieval.groundtruth.relative_pose import RelativePoseDefinition, relative_pose_groundtruth
from locretrieval.localization.sfm import SfmSettings
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DefinitionType:
    """A ground-truth definition: its parameter schema and its builder, called as
    ``build(database, queries, depth=..., name=..., **parameters)`` (plus ``sfm=`` and
    ``cache_dir=`` when ``uses_sfm``: its features and matches are the SfM paradigms')."""

    schema: type
    build: Callable[..., GroundTruth]
    uses_sfm: bool = False


#: Ground-truth definition types by name (the ``type`` of a ``definitions`` entry).
DEFINITIONS: dict[str, DefinitionType] = {
    "relative_pose": DefinitionType(RelativePoseDefinition, relative_pose_groundtruth),
    "frustum": DefinitionType(FrustumDefinition, frustum_groundtruth),
    "co_observation": DefinitionType(CoObservationDefinition, co_observation_groundtruth, uses_sfm=True),
}

#: Bump when the meaning of cached ground-truth files changes.
CACHE_VERSION = 2


@dataclass
class GroundTruthSettings:
    """The ``groundtruth`` config group: ``depth`` images kept per query in each ranking,
    ``definitions`` mapping a name to its parameters, and ``enabled`` the names of those
    computed, in order (``[]``: none; ``None``, or left out of a mapping given in Python: every
    definition). The optional ``type`` parameter picks the definition type in `DEFINITIONS`
    (default: the name itself), so one type can appear twice, e.g. ``frustum_25m: {type:
    frustum, far: 25.0, ...}``. A definition set to ``null`` is switched off, even when enabled;
    ``definitions: null`` switches every one off."""

    depth: int
    definitions: dict[str, Any] | None
    enabled: list[str] | None = None  # the one default: a mapping written in Python may leave it out
    relevance: str = "top_k"  # the retrieval metrics' relevance: in the top-depth ranking (the paper's) | all

    def __post_init__(self) -> None:
        require(self.depth >= 1, "depth", f"must be >= 1, got {self.depth}")
        require(self.relevance in ("top_k", "all"), "relevance", f"must be top_k or all, got {self.relevance!r}")
        definitions = self.definitions if self.definitions is not None else {}  # null: none
        enabled = list(definitions) if self.enabled is None or self.definitions is None else self.enabled
        unknown = [name for name in enabled if name not in definitions]
        require(not unknown, "enabled", f"{unknown} have no entry in groundtruth.definitions (defined: {sorted(definitions)})")
        # a definition set to null is switched off (e.g. groundtruth.definitions.co_observation=null)
        self.definitions = {name: definitions[name] for name in enabled if definitions[name] is not None}
        for name, parameters in self.definitions.items():
            kind = (parameters or {}).get("type", name)
            require(kind in DEFINITIONS, f"definitions.{name}.type", f"unknown definition type {kind!r}; known: {sorted(DEFINITIONS)}")

    def parsed(self) -> dict[str, tuple[str, Any]]:
        """``name -> (type, checked parameters)`` of every enabled definition, in ``enabled`` order."""
        parsed = {}
        for name, parameters in self.definitions.items():
            parameters = dict(parameters or {})
            kind = parameters.pop("type", name)
            parsed[name] = (kind, validated(DEFINITIONS[kind].schema, parameters, f"groundtruth.definitions.{name}"))
        return parsed


def compute_groundtruths(
    scene: Scene, settings: GroundTruthSettings, sfm: SfmSettings | None = None, cache_dir: str | Path | None = None
) -> dict[str, GroundTruth]:
    """Every definition of ``settings`` on ``scene``'s queries, keyed by its name; rankings are
    named ``gt_<name>``.

    A frustum ``far`` left ``null`` (in a definition or in ``sfm.map_pairs``) is the scene's
    `Scene.frustum_far`. ``sfm``: needed by definitions that match local features
    (co-observation). With ``cache_dir``, results are stored under
    ``<cache_dir>/groundtruth``, keyed by both image sets' fingerprints and what produced them.
    """
    settings = validated(GroundTruthSettings, settings, "groundtruth")
    database, queries = scene.database, scene.queries
    fingerprints = (database.fingerprint(), queries.fingerprint()) if cache_dir is not None else ()
    groundtruths = {}
    for name, (kind, definition) in settings.parsed().items():
        definition_type = DEFINITIONS[kind]
        parameters = dataclasses.asdict(definition)
        if "far" in parameters:  # a frustum far plane left null is the scene's
            parameters["far"] = scene.far_plane(parameters["far"], f"groundtruth.definitions.{name}.far")
        produced_by: dict[str, Any] = dict(parameters)
        if definition_type.uses_sfm:
            if sfm is None:
                raise ConfigError(f"groundtruth.definitions.{name}: the {kind} ground truth needs the sfm settings")
            sfm_for_scene = dataclasses.replace(sfm, map_pairs=sfm.map_pairs.for_scene(scene))
            parameters.update(sfm=sfm_for_scene, cache_dir=cache_dir)
            produced_by["sfm"] = {key: dataclasses.asdict(getattr(sfm_for_scene, key)) for key in ("features", "triangulation", "map_pairs")}
            produced_by["sfm"]["matching"] = sfm_for_scene.matching.identity()
        path = None
        if cache_dir is not None:
            key = config_key(CACHE_VERSION, kind, produced_by, settings.depth, *fingerprints)
            path = Path(cache_dir) / "groundtruth" / f"{name}-{key}.npz"

        def build(parameters: dict[str, Any] = parameters, name: str = name) -> dict[str, np.ndarray]:
            return _to_arrays(definition_type.build(database, queries, depth=settings.depth, name=f"gt_{name}", **parameters))

        arrays, hit = cached_arrays(path, build)
        if hit:
            log.info("ground truth %s loaded from %s", name, path)
        groundtruths[name] = _from_arrays(arrays, f"gt_{name}")
    return groundtruths


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
