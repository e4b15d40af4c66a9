"""Compute the configured ground-truth definitions (``configs/groundtruth/``), with a cache."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import sparse

from locretrieval.cache import cached_arrays, config_key, safe_name
from locretrieval.config import ConfigError, require, validated
from locretrieval.groundtruth.base import Definition, DefinitionContext, GroundTruth
from locretrieval.groundtruth.co_observation import CoObservationDefinition
from locretrieval.groundtruth.frustum import FrustumDefinition
from locretrieval.groundtruth.relative_pose import RelativePoseDefinition
from locretrieval.localization.sfm import SfmSettings
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene

log = logging.getLogger(__name__)


#: The built-in ground-truth definition types by name (the ``type`` of a ``definitions`` entry
#: and of ``train_relevance.definition``): each a `Definition` (its module: schema, ranking,
#: training relevance). Another one, in any package, is chosen by its ``_target_`` instead.
DEFINITIONS: dict[str, type[Definition]] = {
    "relative_pose": RelativePoseDefinition,
    "frustum": FrustumDefinition,
    "co_observation": CoObservationDefinition,
}


def parse_definition(parameters: Mapping[str, Any], key: str, default_type: str | None = None) -> Definition:
    """The checked definition of ``parameters``: its ``_target_`` (a `Definition` class of any
    package), else its ``type`` (default ``default_type``) picks the `DEFINITIONS` entry; the rest
    are its schema's fields. Errors name ``key``."""
    if not isinstance(parameters, Mapping):
        raise ConfigError(
            f"{key}: must be a mapping with a type of {sorted(DEFINITIONS)} (or a _target_) and its parameters, "
            f"got {parameters!r}"
        )
    parameters = dict(parameters)
    if "_target_" in parameters:
        return validated(definition_class(str(parameters.pop("_target_")), key), parameters, key)
    kind = parameters.pop("type", default_type)
    if kind not in DEFINITIONS:
        raise ConfigError(f"{key}.type: unknown definition type {kind!r}; known: {sorted(DEFINITIONS)}")
    return validated(DEFINITIONS[kind], parameters, key)


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
        require(
            not unknown,
            "enabled",
            f"{unknown} have no entry in groundtruth.definitions (defined: {sorted(definitions)})",
        )
        # a definition set to null is switched off (e.g. groundtruth.definitions.co_observation=null)
        self.definitions = {name: definitions[name] for name in enabled if definitions[name] is not None}
        for name, parameters in self.definitions.items():  # each checked now, by its type's schema
            parse_definition(parameters, f"groundtruth.definitions.{name}", name)

    def parsed(self) -> dict[str, Definition]:
        """``name -> checked definition`` of every enabled one, in ``enabled`` order."""
        return {
            name: parse_definition(parameters, f"groundtruth.definitions.{name}", name)
            for name, parameters in self.definitions.items()
        }


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
    for name, definition in settings.parsed().items():
        produced_by: dict[str, Any] = {
            **dataclasses.asdict(definition),
            "scene_far": scene.frustum_far,
        }  # far: null is the scene's
        context = DefinitionContext(
            scene.frustum_far,
            cache_dir=Path(cache_dir) if cache_dir is not None else None,
            key=f"groundtruth.definitions.{name}",
            scene=scene.name,
        )
        if definition.uses_sfm:
            if sfm is None:
                raise ConfigError(
                    f"groundtruth.definitions.{name}: "
                    f"the {definition_type(definition)} ground truth needs the sfm settings"
                )
            context = dataclasses.replace(
                context, sfm=dataclasses.replace(sfm, map_pairs=sfm.map_pairs.for_scene(scene))
            )
            sfm = context.sfm
            produced_by["sfm"] = {
                "features": sfm.features.identity(),
                "triangulation": sfm.triangulation.identity(),
                "map_pairs": dataclasses.asdict(sfm.map_pairs),
            }
            produced_by["sfm"]["matching"] = context.sfm.matching.identity()
        path = None
        if cache_dir is not None:
            key = config_key(CACHE_VERSION, definition_type(definition), produced_by, settings.depth, *fingerprints)
            path = Path(cache_dir) / "groundtruth" / f"{safe_name(name)}-{key}.npz"

        def build(
            definition: Definition = definition, context: DefinitionContext = context, name: str = name
        ) -> dict[str, np.ndarray]:
            return _to_arrays(definition.groundtruth(database, queries, settings.depth, f"gt_{name}", context))

        arrays, hit = cached_arrays(path, build)
        if hit:
            log.info("ground truth %s loaded from %s", name, path)
        groundtruths[name] = _from_arrays(arrays, f"gt_{name}")
    return groundtruths


def definition_class(target: str, key: str) -> type[Definition]:
    """The `Definition` class a ``_target_`` names; a `ConfigError` naming ``<key>._target_`` otherwise."""
    from hydra.utils import get_class

    try:
        kind = get_class(target)
    except Exception as error:  # Hydra wraps the import error
        raise ConfigError(f"{key}._target_: cannot import {target!r} ({error})") from None
    if not dataclasses.is_dataclass(kind) or not all(
        hasattr(kind, name) for name in ("uses_sfm", "groundtruth", "graded")
    ):
        raise ConfigError(
            f"{key}._target_: {target} is not a ground-truth definition "
            f"(a dataclass with uses_sfm, groundtruth and graded)"
        )
    return kind


def definition_type(definition: Definition) -> str:
    """The `DEFINITIONS` name of ``definition``'s type, or its class's import path (part of its cache key)."""
    kind = type(definition)
    return next(
        (name for name, known in DEFINITIONS.items() if kind is known), f"{kind.__module__}.{kind.__qualname__}"
    )


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
        (
            np.ones(len(arrays["relevance_indices"]), dtype=bool),
            arrays["relevance_indices"],
            arrays["relevance_indptr"],
        ),
        shape=tuple(arrays["relevance_shape"]),
    )
    ranking = Ranking(name, arrays["indices"], arrays["scores"], "groundtruth")
    return GroundTruth(ranking, relevance, arrays["query_has_pose"])
