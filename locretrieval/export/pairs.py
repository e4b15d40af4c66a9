"""A ranking's top k as pairs files, read back by ``model=pairs`` (`locretrieval.retrieval.pairs_file`).

- hloc's (``pairs-query-netvlad50.txt``, what ``pairs_from_retrieval`` writes and
  ``localize_sfm`` reads): ``query database`` per line, each query's database images best first;
- kapture-localization's (``kapture_compute_image_pairs.py``): kapture's CSV header, a
  ``# query_image, map_image, score`` line, then ``query, database, score`` per line, written by
  kapture's own ``table_to_file``; scores as the ranking holds them (higher is better: cosine
  similarities, or a ground truth's negated distance), exactly (each reads back as the same float32).

Queries without a ranked image have no line (``model=pairs`` reads them as empty retrievals).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import kapture.io.csv

from locretrieval.cache import atomic_path, safe_name
from locretrieval.config import require
from locretrieval.retrieval.ranking import EMPTY, Ranking

#: Pairs file formats -> the folder below the export folder they are written to.
PAIRS_FORMATS = ("hloc", "kapture")
#: The header kapture-localization writes below kapture's format line.
KAPTURE_PAIRS_HEADER = "# query_image, map_image, score"


@dataclass
class PairsSettings:
    """The ``pairs`` config section: the ``formats`` written (`PAIRS_FORMATS`), each ranking's first
    ``k`` images per query (at most ``retrieval.depth``, the depth rankings have)."""

    formats: list[str]
    k: int

    def __post_init__(self) -> None:
        unknown = sorted(set(self.formats) - set(PAIRS_FORMATS))
        require(not unknown, "formats", f"unknown {unknown}; known: {list(PAIRS_FORMATS)}")
        require(self.k >= 1, "k", f"must be >= 1, got {self.k}")


#: One pair: query name, database name, the ranking's score.
Pair = tuple[str, str, float]


def ranked_pairs(ranking: Ranking, k: int, queries: Sequence[str], database: Sequence[str]) -> list[Pair]:
    """The first ``k`` filled slots of each query's row of ``ranking``, best first, queries in order."""
    indices, scores = ranking.indices[:, :k], ranking.scores[:, :k]
    return [
        (queries[q], database[i], float(score))
        for q in range(ranking.num_queries)
        for i, score in zip(indices[q], scores[q])
        if i != EMPTY
    ]


def write_hloc_pairs(path: str | os.PathLike, pairs: Sequence[Pair]) -> Path:
    """hloc's pairs file (``query database`` per line), written whole or not at all."""
    with atomic_path(path) as temporary:
        temporary.write_text("".join(f"{query} {image}\n" for query, image, _ in pairs), encoding="utf-8")
    return Path(path)


def write_kapture_pairs(path: str | os.PathLike, pairs: Sequence[Pair]) -> Path:
    """kapture-localization's pairs file (``query, database, score``), written whole or not at all."""
    with atomic_path(path) as temporary:
        with open(temporary, "w", encoding="utf-8") as stream:
            kapture.io.csv.table_to_file(stream, pairs, header=KAPTURE_PAIRS_HEADER)  # floats as repr: exact
    return Path(path)


def pairs_file(folder: Path, kind: str, ranking: str, k: int) -> Path:
    """Where the pairs file of ``kind`` (`PAIRS_FORMATS`) of the ranking named ``ranking`` goes:
    ``<folder>/hloc/pairs-query-<ranking><k>.txt`` (hloc's naming) or
    ``<folder>/kapture/pairs_localization_<ranking>_<k>.txt`` (kapture-localization's, with the ranking)."""
    name = safe_name(ranking)
    return folder / kind / (f"pairs-query-{name}{k}.txt" if kind == "hloc" else f"pairs_localization_{name}_{k}.txt")


WRITERS = {"hloc": write_hloc_pairs, "kapture": write_kapture_pairs}


def export_pairs(
    folder: Path, ranking: Ranking, queries: Sequence[str], database: Sequence[str], settings: PairsSettings
) -> list[Path]:
    """``ranking``'s pairs files of every format of ``settings`` in ``folder`` (`pairs_file`); the
    names are the scene's (checked by the caller: `locretrieval.scene.names.check_exported_names`)."""
    k = min(settings.k, ranking.depth)  # a ranking of fewer database images is shallower: named as deep as it is
    pairs = ranked_pairs(ranking, k, queries, database)
    return [WRITERS[kind](pairs_file(folder, kind, ranking.name, k), pairs) for kind in settings.formats]
