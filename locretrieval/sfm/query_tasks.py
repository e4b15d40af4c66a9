"""One query's registrations (`QueryTask`): its top images per ranking, the ks of each and the
outcomes already cached; a query is registered once per distinct set of images
(`outcomes_per_image_set`), however many rankings and ks select it."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from locretrieval.retrieval import EMPTY, Ranking
from locretrieval.sfm.pose_cache import Outcome, PoseCache


@dataclass(frozen=True)
class QueryTask:
    """One query's top database images per ranking (``EMPTY`` removed), the ks of each, and
    the outcomes already known (cached) of some of its image sets (sorted index tuples)."""

    query: int
    top: tuple[tuple[int, ...], ...]
    ks: tuple[tuple[int, ...], ...]
    known: dict[tuple[int, ...], Outcome] = field(default_factory=dict, compare=False)

    def image_sets(self) -> set[tuple[int, ...]]:
        """Every distinct top-k image set (sorted) of every ranking and k."""
        return {tuple(sorted(top[:k])) for top, ks in zip(self.top, self.ks) for k in ks}

    def pending(self) -> set[tuple[int, ...]]:
        """The image sets whose outcome is not known."""
        return self.image_sets() - self.known.keys()

    @property
    def complete(self) -> bool:
        return not self.pending()


def outcomes_per_image_set(task: QueryTask, localize: Callable[[tuple[int, ...]], Outcome]) -> list[list[Outcome]]:
    """Outcomes ``[ranking][k]`` of one query, where ``localize(images)`` gives the outcome of
    the top-k database images as a sorted tuple; it runs once per distinct image set that is not
    known already, however many rankings and ks (or orders within a ranking) select it."""
    localize = functools.cache(localize)

    def outcome(images: tuple[int, ...]) -> Outcome:
        return task.known[images] if images in task.known else localize(images)

    return [[outcome(tuple(sorted(top[:k]))) for k in ks] for top, ks in zip(task.top, task.ks)]


def query_tasks(
    rankings: Sequence[Ranking], ks: Sequence[Sequence[int]], cache: PoseCache, queries: Sequence[int] | None = None
) -> list[QueryTask]:
    """Per query (of ``queries``, or every one), its top ``max(k)`` database images of each
    ranking and its cached outcomes."""
    rows = [ranking.indices[:, : max(ranking_ks)] for ranking, ranking_ks in zip(rankings, ks)]
    tasks = []
    for q in range(rankings[0].num_queries) if queries is None else queries:
        task = QueryTask(q, tuple(tuple(int(i) for i in row[q] if i != EMPTY) for row in rows), tuple(map(tuple, ks)))
        for images in task.image_sets():
            outcome = cache.get(q, images)
            if outcome is not None:
                task.known[images] = outcome
        tasks.append(task)
    return tasks
