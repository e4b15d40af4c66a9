"""`GroundTruth`: a ground-truth ranking, its binary relevance and the statistics of Table 1."""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Protocol

import numpy as np
import pandas as pd
from scipy import sparse
from tqdm import tqdm

from locretrieval.config import ConfigError
from locretrieval.retrieval import EMPTY, Ranking, relevant_hits, top_k
from locretrieval.scene import ImageSet, Scene
from locretrieval.scene.reconstruction import Observations

if TYPE_CHECKING:
    from locretrieval.sfm.settings import SfmSettings

#: Query-database pairs scored at once; bounds the memory of every definition.
PAIRS_PER_CHUNK = 1 << 17

#: ``score_block(query_rows) -> (similarity, rankable, relevant)``, each ``[len(rows), N]``:
#: the similarity of every pair (higher is better), which pairs may be ranked at all, and
#: which are relevant.
ScoreBlock = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
#: ``grade(rows) -> [len(rows), N]``: the graded relevance of images ``rows`` of a set to all of its images.
GradedRows = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class DefinitionContext:
    """Where a definition is evaluated, for what it needs besides the images' poses and cameras
    (each definition derives its own data from these): ``far``, the far plane (metres) of frusta
    whose definition leaves it ``None`` (the scene's); the SfM paradigms' ``sfm`` settings and
    ``cache_dir`` (for definitions that match local features, ``uses_sfm``); for training relevance,
    the ``world`` whose database images are graded (co-observation reads its known-pose map);
    ``key``: the config key of the definition and the ``scene``'s name, named in errors;
    ``observations``: the 3D points each image of the scene observes when a reconstruction gave
    them (``data=colmap``, ``data=photos``; co-observation counts them instead of an SfM of ours)."""

    far: float | None = None
    sfm: "SfmSettings | None" = None
    cache_dir: Path | None = None
    world: Scene | None = None
    key: str = "groundtruth.definitions"
    scene: str = ""
    observations: Observations | None = None

    def far_plane(self, far: float | None) -> float:
        """``far`` (metres), or the scene's ``far`` where it is ``None``; a `ConfigError` naming
        ``<key>.far`` when neither is set."""
        if far is not None:
            return float(far)
        if self.far is None:
            raise ConfigError(
                f"{self.key}.far is null (the dataset's frustum far plane) but scene {self.scene!r} has no frustum_far"
            )
        return float(self.far)


class Definition(Protocol):
    """A ground-truth definition (a typed parameter schema, checked in ``__post_init__``) that
    gives both the benchmark's ranking and relevance of queries against the database and the
    graded relevance of training pairs. ``uses_sfm``: it matches local features (the SfM
    paradigms' settings, features and caches). Chosen by its ``_target_`` (the built-in ones:
    ``configs/groundtruth/definitions/``), in any package."""

    uses_sfm: ClassVar[bool]

    def groundtruth(
        self, database: ImageSet, queries: ImageSet, depth: int, name: str, context: DefinitionContext
    ) -> "GroundTruth":
        """The ranking (top ``depth``) and relevance of ``queries`` against ``database``."""

    def graded(self, images: ImageSet, context: DefinitionContext) -> GradedRows:
        """``grade(rows)``: the ``[len(rows), N]`` relevance of images ``rows`` to every image of
        ``images``: > 0 where relevant, higher for more relevant pairs, 0 elsewhere (the diagonal
        is the caller's). What every row needs is computed here, once; ``grade`` is called per
        chunk of rows."""


@dataclass(frozen=True)
class GroundTruth:
    """A ground-truth definition evaluated on a scene (paper Sec. 3.6.3).

    ``ranking [Q, K]`` holds the top ``K`` (= ``depth``, 50 by default) database images per
    query by the definition's score, used like a descriptor's ranking (the upper bound).
    ``relevance`` is a boolean sparse ``[Q, N]`` matrix of *all* relevant database images,
    not only the top ``K``. ``query_has_pose [Q]`` marks queries with a known pose; the
    others have an all-``EMPTY`` ranking row and no relevant image.
    """

    ranking: Ranking
    relevance: sparse.csr_matrix
    query_has_pose: np.ndarray

    def __post_init__(self) -> None:
        name = self.ranking.name
        if self.ranking.kind != "groundtruth":
            raise ValueError(f"ground truth {name!r}: ranking kind is {self.ranking.kind!r}, not 'groundtruth'")
        if self.relevance.dtype != bool or self.relevance.shape[0] != self.ranking.num_queries:
            raise ValueError(
                f"ground truth {name!r}: relevance must be bool [{self.ranking.num_queries}, N], "
                f"got {self.relevance.dtype} {self.relevance.shape}"
            )
        if self.query_has_pose.shape != (self.ranking.num_queries,):
            raise ValueError(f"ground truth {name!r}: query_has_pose must have one entry per query")
        unposed = ~self.query_has_pose
        if (self.ranking.lengths[unposed] > 0).any() or self.relevance[np.flatnonzero(unposed)].nnz:
            raise ValueError(f"ground truth {name!r}: queries without a pose must have no ranking and no relevance")

    @property
    def name(self) -> str:
        return self.ranking.name

    def of_queries(self, rows: np.ndarray) -> "GroundTruth":
        """The ground truth of the queries ``rows`` (indices), in that order."""
        return GroundTruth(self.ranking.of_queries(rows), self.relevance[rows], self.query_has_pose[rows])

    def relevance_in_ranking(self) -> sparse.csr_matrix:
        """``relevance`` restricted to the images of the top-``depth`` ranking: the paper reduces
        the ground-truth rankings to the top 50 (Sec. 3.6.3), and so its relevance."""
        indices = self.ranking.indices
        rows, slots = np.nonzero(relevant_hits(indices, self.relevance))
        data = np.ones(len(rows), dtype=bool)
        return sparse.csr_matrix((data, (rows, indices[rows, slots])), shape=self.relevance.shape)

    @property
    def num_database(self) -> int:
        return self.relevance.shape[1]

    def statistics(self) -> dict[str, float | int]:
        """The statistics of the paper's Table 1, over the queries with a known pose.

        - ``avg_relevant``: mean number of relevant database images per query, counting
          *all* of them (not capped at the ranking depth);
        - ``avg_relevant_in_ranking``: the same count within the top-``depth`` ranking; the
          paper's "avg. k" saturates at 50, so it most likely counted this one;
        - ``missing_pct``: percentage of queries without any relevant database image;
        - ``queries``, ``queries_without_pose``: queries in all, and those left out of the
          statistics because their pose is unknown.
        """
        posed = np.flatnonzero(self.query_has_pose)
        relevant_per_query = np.diff(self.relevance.indptr)
        relevant = relevant_per_query[posed]
        in_ranking = relevant_hits(self.ranking.indices, self.relevance).sum(axis=1)[posed]
        has_queries = len(posed) > 0
        return {
            "queries": self.ranking.num_queries,
            "queries_without_pose": self.ranking.num_queries - len(posed),
            "depth": self.ranking.depth,
            "avg_relevant": float(relevant.mean()) if has_queries else float("nan"),
            "avg_relevant_in_ranking": float(in_ranking.mean()) if has_queries else float("nan"),
            "missing_pct": float(100.0 * (relevant == 0).mean()) if has_queries else float("nan"),
        }


class RelevanceScope(abc.ABC):
    """Which relevant images of a ground truth the retrieval metrics count (``groundtruth.relevance``,
    chosen by its ``_target_``: ``configs/groundtruth/relevance/``)."""

    @abc.abstractmethod
    def __call__(self, groundtruth: GroundTruth) -> sparse.csr_matrix:
        """The boolean ``[Q, N]`` relevance the metrics count."""


@dataclass(frozen=True)
class RankedRelevance(RelevanceScope):
    """The relevant images within the top-``depth`` ranking (`GroundTruth.relevance_in_ranking`):
    the paper reduces the ground-truth rankings to the top 50 (Sec. 3.6.3), and so its relevance."""

    def __call__(self, groundtruth: GroundTruth) -> sparse.csr_matrix:
        return groundtruth.relevance_in_ranking()


@dataclass(frozen=True)
class AllRelevance(RelevanceScope):
    """Every relevant database image (`GroundTruth.relevance`)."""

    def __call__(self, groundtruth: GroundTruth) -> sparse.csr_matrix:
        return groundtruth.relevance


def groundtruth_from_scores(
    name: str, database: ImageSet, queries: ImageSet, depth: int, score_block: ScoreBlock
) -> GroundTruth:
    """Rank and threshold the queries with a pose, a chunk of queries at a time.

    ``score_block`` is only called with rows of queries that have a pose; the ranking keeps
    the ``depth`` best rankable pairs per query (ties: lower database index first). Every
    database image must have a pose.
    """
    if not database.has_pose.all():
        missing = [n for n, posed in zip(database.names, database.has_pose) if not posed]
        raise ValueError(f"ground truth {name!r}: database images without a pose: {missing[:5]}")
    query_has_pose = queries.has_pose
    num_queries, num_database = len(queries), len(database)
    width = min(depth, num_database)
    indices = np.full((num_queries, width), EMPTY, dtype=np.int64)
    scores = np.zeros((num_queries, width), dtype=np.float32)
    relevant_rows, relevant_columns = [np.empty(0, dtype=np.int64)], [np.empty(0, dtype=np.int64)]
    posed = np.flatnonzero(query_has_pose)
    rows_per_chunk = max(1, PAIRS_PER_CHUNK // num_database)
    chunks = [posed[start : start + rows_per_chunk] for start in range(0, len(posed), rows_per_chunk)]
    for rows in tqdm(chunks, desc=name, unit="chunk", disable=None if len(chunks) > 1 else True, leave=False):
        similarity, rankable, relevant = score_block(rows)
        indices[rows], scores[rows] = top_k(similarity, depth, rankable)
        block_rows, block_columns = np.nonzero(relevant)
        relevant_rows.append(rows[block_rows])
        relevant_columns.append(block_columns)
    rows, columns = np.concatenate(relevant_rows), np.concatenate(relevant_columns)
    relevance = sparse.csr_matrix((np.ones(len(rows), dtype=bool), (rows, columns)), shape=(num_queries, num_database))
    return GroundTruth(Ranking(name, indices, scores, "groundtruth"), relevance, query_has_pose)


def statistics_table(dataset: str, groundtruths: Mapping[str, GroundTruth]) -> pd.DataFrame:
    """Table 1 (``groundtruth_statistics.csv``): one row of `GroundTruth.statistics` per definition."""
    return pd.DataFrame(
        [{"dataset": dataset, "groundtruth": name, **gt.statistics()} for name, gt in groundtruths.items()]
    )
