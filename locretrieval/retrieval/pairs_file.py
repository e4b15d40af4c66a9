"""Rankings read from pairs files: the retrieval results of a method run elsewhere.

Two formats, told apart per line:

- hloc's (``pairs-query-netvlad50.txt``): ``query database`` separated by whitespace, best
  first per query (image names hold no whitespace);
- the reference tools' (kapture-localization's ``pairs_localization_<k>.txt``): ``query,
  database, score`` separated by commas, ``#`` comment lines (its header).

Each query's pairs are ordered by a `PairOrder` chosen by ``_target_`` (``model/order=file|score``):
the file's order (`FileOrder`) or decreasing score (`ScoreOrder`, ties in file order; every line
then needs a score). The ranking has no
descriptors: paradigm 1 runs EWB only (BDI and CSI are skipped with the reason logged), as for
the ground-truth rankings. A query without a pair in the file has an empty ranking (counted
as not localized, "empty retrieval").
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from locretrieval.config import ConfigError, build_part
from locretrieval.retrieval.ranking import EMPTY, Ranking
from locretrieval.scene import Scene

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairLine:
    """One pair of a pairs file: its 1-based line number, the two image names, the score (or None)."""

    line: int
    query: str
    database: str
    score: float | None


class PairOrder(abc.ABC):
    """How a pairs file's pairs of one query are ordered, best first (``model.order``, chosen by
    its ``_target_``: ``configs/model/order/``). A new one subclasses this, in any package."""

    @abc.abstractmethod
    def arranged(self, rows: dict[int, list[PairLine]], path: Path) -> dict[int, list[PairLine]]:
        """Each query's pairs of ``rows`` (in the file's order) best first; errors name ``path``."""


@dataclass
class FileOrder(PairOrder):
    """The file's order (hloc's files: best first)."""

    def arranged(self, rows: dict[int, list[PairLine]], path: Path) -> dict[int, list[PairLine]]:
        return rows


@dataclass
class ScoreOrder(PairOrder):
    """Decreasing score (the third column; ties in the file's order): every line needs one."""

    def arranged(self, rows: dict[int, list[PairLine]], path: Path) -> dict[int, list[PairLine]]:
        unscored = [pair.line for ranked in rows.values() for pair in ranked if pair.score is None]
        if unscored:
            raise ConfigError(
                f"model.order (ScoreOrder): {path}:{min(unscored)} has no score "
                "(model/order=file keeps the file's order)"
            )
        return {q: sorted(ranked, key=lambda p: -p.score) for q, ranked in rows.items()}  # stable: ties in file order


class PairsFileRanking:
    """The ``model=pairs`` config node: the ranking named ``name`` read from the pairs file
    ``path``, each query's pairs in ``order`` (a `PairOrder`, or its config node)."""

    def __init__(self, *, name: str, path: str, order: Any) -> None:
        self.name, self.path = name, path
        self.order = build_part(PairOrder, order, "model.order", "model/order")

    def missing_inputs(self, scene: Scene) -> list[str]:
        """The pairs file, if it is absent (``path: ...``)."""
        return [] if Path(self.path).is_file() else [f"path: pairs file {self.path} not found"]

    def rankings(self, scene: Scene, search: Callable[..., Ranking]) -> list[Ranking]:
        """Its one ranking of ``scene`` (`ranking`), as deep as ``search`` ranks descriptors
        (`locretrieval.retrieval.descriptors.DescriptorSearch`; the file has no descriptors)."""
        return [self.ranking(scene, search.settings.depth)]

    def ranking(self, scene: Scene, depth: int) -> Ranking:
        """The top-``depth`` database images of each query of ``scene`` as the file ranks them."""
        path = Path(self.path)
        if not path.is_file():
            raise FileNotFoundError(f"model.path: pairs file {path} not found")
        return ranking_from_pairs(self.name, list(read_pairs(path)), scene, depth, self.order, path)


def read_pairs(path: Path) -> Iterator[PairLine]:
    """The pairs of a file in either format; ``ValueError`` naming ``file:line`` otherwise."""
    with open(path, encoding="utf-8") as stream:
        for number, text in enumerate(stream, start=1):
            text = text.strip()
            if not text or text.startswith("#"):
                continue
            fields = [field.strip() for field in text.split(",")] if "," in text else text.split()
            if len(fields) not in (2, 3) or not all(fields):
                raise ValueError(
                    f"{path}:{number}: expected 'query database' or 'query, database, score', got {text!r}"
                )
            try:
                score = float(fields[2]) if len(fields) == 3 else None
            except ValueError:
                raise ValueError(f"{path}:{number}: score {fields[2]!r} is not a number") from None
            yield PairLine(number, fields[0], fields[1], score)


def ranking_from_pairs(
    name: str, pairs: list[PairLine], scene: Scene, depth: int, order: PairOrder, path: Path
) -> Ranking:
    """The ranking of ``pairs`` over the scene's queries (rows) and database images (indices).

    Every name must be a query, respectively a database image, of the scene, and a pair may
    appear once: otherwise ``ValueError`` naming ``file:line``. Scores: the file's, or minus
    the position in the query's list where the file has none (higher is better)."""
    queries = {n: i for i, n in enumerate(scene.queries.names)}
    database = {n: i for i, n in enumerate(scene.database.names)}
    rows: dict[int, list[PairLine]] = {}
    seen: dict[tuple[str, str], int] = {}
    for pair in pairs:
        if pair.query not in queries:
            where = (
                "a database image, not a query (a mapping pairs file?)"
                if pair.query in database
                else "not a query of the scene"
            )
            raise ValueError(f"{path}:{pair.line}: {pair.query!r} is {where}")
        if pair.database not in database:
            raise ValueError(f"{path}:{pair.line}: {pair.database!r} is not a database image of the scene")
        if (pair.query, pair.database) in seen:
            raise ValueError(
                f"{path}:{pair.line}: pair ({pair.query}, {pair.database}) "
                f"repeats line {seen[(pair.query, pair.database)]}"
            )
        seen[(pair.query, pair.database)] = pair.line
        rows.setdefault(queries[pair.query], []).append(pair)
    rows = order.arranged(rows, path)
    depth = min(depth, len(database))  # as `search` clamps it
    indices = np.full((len(queries), depth), EMPTY, dtype=np.int64)
    scores = np.zeros((len(queries), depth), dtype=np.float32)
    for q, ranked in rows.items():
        kept = ranked[:depth]
        indices[q, : len(kept)] = [database[p.database] for p in kept]
        scores[q, : len(kept)] = [
            p.score if p.score is not None else -float(position) for position, p in enumerate(kept)
        ]
    deeper = sum(len(ranked) > depth for ranked in rows.values())
    if deeper:
        log.warning(
            "%s: %d queries have more than %d pairs; the first %d are kept (retrieval.depth)",
            path,
            deeper,
            depth,
            depth,
        )
    missing = len(queries) - len(rows)
    log.info(
        "ranking %r from %s: %d pairs, %d of %d queries ranked%s",
        name,
        path,
        len(pairs),
        len(rows),
        len(queries),
        f" ({missing} without a pair: empty retrieval)" if missing else "",
    )
    return Ranking(name, indices, scores, "descriptor")
