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
from locretrieval.config import ConfigError, part, require, validated
from locretrieval.groundtruth.base import Definition, DefinitionContext, GroundTruth, RelevanceScope
from locretrieval.parts import import_part
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.settings import SfmSettings

log = logging.getLogger(__name__)


def parse_definition(parameters: Mapping[str, Any], key: str) -> Definition:
    """The checked definition of ``parameters``: its ``_target_`` (a `Definition` class of any
    package, the built-in ones of ``configs/groundtruth/definitions/`` too) and the parameters
    of that class's schema. Errors name ``key``."""
    if not isinstance(parameters, Mapping) or "_target_" not in parameters:
        retired = isinstance(parameters, Mapping) and "type" in parameters  # before 0.12: {type: frustum, ...}
        raise ConfigError(
            f"{key}: must be a mapping with a _target_, the definition's class (e.g. "
            "locretrieval.groundtruth.FrustumDefinition, configs/groundtruth/definitions/), and its parameters"
            + (", not a type" if retired else "")
            + f"; got {parameters!r}"
        )
    parameters = dict(parameters)
    return validated(definition_class(str(parameters.pop("_target_")), key), parameters, key)


#: Bump when the meaning of cached ground-truth files changes.
CACHE_VERSION = 2


@dataclass
class GroundTruthSettings:
    """The ``groundtruth`` config group: ``depth`` images kept per query in each ranking,
    ``definitions`` mapping a name to its definition (a ``_target_``, the `Definition` class, and
    its parameters; `parse_definition`), and ``enabled`` the names of those computed, in order
    (``[]``: none; ``None``: every definition), and the retrieval metrics' ``relevance`` (a
    `RelevanceScope` chosen by its ``_target_``). One class
    can appear under two names, e.g. ``frustum_25m: {_target_: ...FrustumDefinition, far: 25.0,
    ...}``. A definition set to ``null`` is switched off, even when enabled; ``definitions: null``
    switches every one off."""

    depth: int
    definitions: dict[str, Any] | None
    enabled: list[str] | None
    relevance: Any = part(RelevanceScope, "groundtruth/relevance")

    def __post_init__(self) -> None:
        require(self.depth >= 1, "depth", f"must be >= 1, got {self.depth}")
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
        for name, parameters in self.definitions.items():  # each checked now, by its class's schema
            parse_definition(parameters, f"groundtruth.definitions.{name}")

    def parsed(self) -> dict[str, Definition]:
        """``name -> checked definition`` of every enabled one, in ``enabled`` order."""
        return {
            name: parse_definition(parameters, f"groundtruth.definitions.{name}")
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
        context = definition_context(scene, name, definition, sfm, cache_dir)
        produced_by: dict[str, Any] = {
            **dataclasses.asdict(definition),
            "scene_far": scene.frustum_far,
        }  # far: null is the scene's
        if scene.observations is not None:  # a reconstruction's tracks
            produced_by["observations"] = scene.observations.fingerprint()
        if context.sfm is not None:
            used = context.sfm
            produced_by["sfm"] = {
                "features": used.features.identity(),
                "triangulation": used.triangulation.identity(),
                "map_pairs": dataclasses.asdict(used.map_pairs),
                "matching": used.matching.identity(),
                "database_verification": repr(used.database_verification),
            }
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


def definition_context(
    scene: Scene, name: str, definition: Definition, sfm: SfmSettings | None, cache_dir: str | Path | None
) -> DefinitionContext:
    """Where definition ``name`` is evaluated on ``scene`` (`DefinitionContext`): the SfM settings,
    their ``map_pairs`` far plane the scene's where left null, for a definition that uses them."""
    context = DefinitionContext(
        scene.frustum_far,
        cache_dir=Path(cache_dir) if cache_dir is not None else None,
        key=f"groundtruth.definitions.{name}",
        scene=scene.name,
        observations=scene.observations,
    )
    if not definition.uses_sfm:
        return context
    if sfm is None:
        raise ConfigError(f"groundtruth.definitions.{name}: {definition_type(definition)} needs the sfm settings")
    return dataclasses.replace(context, sfm=dataclasses.replace(sfm, map_pairs=sfm.map_pairs.for_scene(scene)))


def groundtruth_sfm_pairs(
    scene: Scene, settings: GroundTruthSettings, sfm: SfmSettings
) -> tuple[set[tuple[str, str]], set[tuple[str, str]]]:
    """The database pairs and (query, database) pairs (names) that the enabled definitions using
    SfM match (their ``sfm_pairs``), for a dry run's count; a definition without ``sfm_pairs`` is
    left out with a warning."""
    database_pairs, query_pairs = set(), set()
    for name, definition in settings.parsed().items():
        if not definition.uses_sfm:
            continue
        if not hasattr(definition, "sfm_pairs"):
            log.warning("groundtruth.definitions.%s states no sfm_pairs: its matching is not counted", name)
            continue
        context = definition_context(scene, name, definition, sfm, None)  # with the scene's tracks, if any
        found = definition.sfm_pairs(scene.database, scene.queries, context)
        database_pairs.update(found[0])
        query_pairs.update(found[1])
    return database_pairs, query_pairs


def definition_class(target: str, key: str) -> type[Definition]:
    """The `Definition` class a ``_target_`` names (`import_part`); a `ConfigError` naming
    ``<key>._target_`` otherwise."""
    kind = import_part(target, key)
    if not dataclasses.is_dataclass(kind) or not all(
        hasattr(kind, name) for name in ("uses_sfm", "groundtruth", "graded")
    ):
        raise ConfigError(
            f"{key}._target_: {target} is not a ground-truth definition "
            f"(a dataclass with uses_sfm, groundtruth and graded)"
        )
    return kind


def definition_type(definition: Definition) -> str:
    """The import path of ``definition``'s class (its ``_target_``; part of its cache key)."""
    kind = type(definition)
    return f"{kind.__module__}.{kind.__qualname__}"


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
