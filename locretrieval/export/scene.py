"""A scene's rankings as pairs files and a model's global descriptors as kapture and hloc feature
files, in one export folder:

- ``hloc/pairs-query-<ranking><k>.txt`` and ``kapture/pairs_localization_<ranking>_<k>.txt``
  (`locretrieval.export.pairs`);
- ``kapture/mapping/reconstruction/global_features/<ranking>/`` and
  ``kapture/query/reconstruction/global_features/<ranking>/``: kapture-localization's layout, a
  kapture folder for the database and one for the queries (read back by ``model=precomputed``
  with ``model.path`` the two feature folders);
- ``hloc/global-feats-<ranking>-db.h5`` and ``hloc/global-feats-<ranking>-query.h5``: hloc's
  ``pairs_from_retrieval`` takes them as ``db_descriptors`` and ``descriptors`` (a file per set:
  a database image and a query may share a name).

Ranking names in file names go through `safe_name`; image names are the scene's, checked first.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from locretrieval.cache import safe_name
from locretrieval.config import require
from locretrieval.export.pairs import PairsSettings, export_pairs
from locretrieval.models.files.feature_io import export_global_features, write_hloc_global_descriptors
from locretrieval.retrieval.ranking import Ranking
from locretrieval.scene import Scene
from locretrieval.scene.names import check_exported_names

log = logging.getLogger(__name__)

#: Descriptor file formats.
DESCRIPTOR_FORMATS = ("kapture", "hloc")


@dataclass
class DescriptorSettings:
    """The ``descriptors`` config section: the ``formats`` written (`DESCRIPTOR_FORMATS`)."""

    formats: list[str]

    def __post_init__(self) -> None:
        unknown = sorted(set(self.formats) - set(DESCRIPTOR_FORMATS))
        require(not unknown, "formats", f"unknown {unknown}; known: {list(DESCRIPTOR_FORMATS)}")


def export_scene(
    scene: Scene,
    rankings: Sequence[Ranking],
    folder: Path,
    pairs: PairsSettings | None,
    descriptors: DescriptorSettings | None,
) -> list[Path]:
    """The pairs files of every ranking (``pairs``) and the descriptor files of every ranking that
    holds descriptors (``descriptors``) in ``folder``; returns the files and folders written. The
    scene's image names are checked before anything is written."""
    check_scene_names(scene)
    written = []
    if pairs is not None:
        for ranking in rankings:
            written += export_pairs(folder, ranking, scene.queries.names, scene.database.names, pairs)
    if descriptors is not None:
        described = [ranking for ranking in rankings if ranking.has_descriptors]
        if not described:
            log.warning("no ranking holds descriptors (a pairs file, the ground truth): no descriptor files written")
        for ranking in described:
            written += export_descriptors(scene, ranking, folder, descriptors)
    return written


def check_scene_names(scene: Scene) -> None:
    """Raise ``ValueError`` naming the first image name of ``scene`` that the exports cannot write."""
    check_exported_names(scene.database.names, f"scene {scene.name}: database")
    check_exported_names(scene.queries.names, f"scene {scene.name}: queries")


def export_descriptors(scene: Scene, ranking: Ranking, folder: Path, settings: DescriptorSettings) -> list[Path]:
    """The database and query descriptors ``ranking`` holds, in every format of ``settings``."""
    name = safe_name(ranking.name)
    sets = {
        "mapping": (scene.database.names, ranking.database_descriptors),
        "query": (scene.queries.names, ranking.query_descriptors),
    }
    written = []
    if "kapture" in settings.formats:
        for kapture_folder, (names, descriptors) in sets.items():
            written.append(export_global_features(names, descriptors, folder / "kapture" / kapture_folder, name))
    if "hloc" in settings.formats:
        for suffix, (names, descriptors) in zip(("db", "query"), sets.values()):
            written.append(
                write_hloc_global_descriptors(folder / "hloc" / f"global-feats-{name}-{suffix}.h5", names, descriptors)
            )
    return written
