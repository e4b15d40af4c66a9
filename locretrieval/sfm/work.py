"""The work of the SfM paradigms, counted without doing any of it.

Per paradigm: the query-database pairs to match, the database pairs to match, the maps to
triangulate, the registrations and the queries they belong to, each as needed in all and new
(not in the caches); for the scene: the images whose local features are not cached. With the
rankings known the counts are exact; before (``evaluate.py dry_run=true``) they are upper
bounds: every ranking's top-k taken as disjoint from the others'.

`SfmPlan.stage_units` gives each stage of the pipeline its work in its own units (images,
pairs, maps, registrations): the totals of its progress bars.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from locretrieval.retrieval import Ranking
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.matching import pair_key
from locretrieval.sfm.query_tasks import QueryTask

#: The stages every run has, before each paradigm's two (`stage_names`), with their units.
FEATURES, MATCHING = "features", "match + verify"


def stage_names(paradigm: str) -> tuple[str, str]:
    """The names of a paradigm's triangulation and registration stages."""
    return f"{paradigm}: triangulate", f"{paradigm}: register"


@dataclass(frozen=True)
class Work:
    """``total`` items needed, ``new`` of them not cached."""

    total: int
    new: int

    def __str__(self) -> str:
        return f"{self.total:,} ({self.new:,} new)"


@dataclass
class ParadigmWork:
    """What one SfM paradigm needs: query-database and database pairs to match, maps to
    triangulate (with ``pairs_per_map`` matched pairs each, on average; ``shared_map``: one map
    every query uses, else each query's own), registrations,
    the database images they register against (summed over them) and the ``queries`` they are of."""

    paradigm: str
    query_pairs: Work
    database_pairs: Work
    maps: Work
    pairs_per_map: float
    registrations: Work
    registered_images: Work
    queries: Work
    shared_map: bool = False


@dataclass
class SfmPlan:
    """The SfM work of a run: ``features`` (images of both sets), one `ParadigmWork` per
    paradigm, whether the counts are ``exact`` (or upper bounds), and the pairs the run matches
    and verifies (``pairs_to_match``: those whose matches are not cached; None when not counted)."""

    features: Work
    paradigms: list[ParadigmWork]
    exact: bool
    pairs_to_match: int | None = None

    def new_pairs(self) -> int:
        """Pairs to match and verify: ``pairs_to_match`` (the run's, each once, when counted), else the
        new query pairs (shared by the paradigms: each query with its top max(k) of every ranking)
        and each paradigm's new database pairs (at most: maps of two paradigms may share pairs)."""
        if self.pairs_to_match is not None:
            return self.pairs_to_match
        return max((p.query_pairs.new for p in self.paradigms), default=0) + sum(
            p.database_pairs.new for p in self.paradigms
        )

    def stage_units(self) -> dict[str, tuple[int, str]]:
        """Each stage's new work and its unit, by stage name, in the order the pipeline runs them."""
        units = {FEATURES: (self.features.new, "images"), MATCHING: (self.new_pairs(), "pairs")}
        for p in self.paradigms:
            triangulate, register = stage_names(p.paradigm)
            units[triangulate] = (p.maps.new, "maps")
            units[register] = (p.registrations.new, "registrations")
        return units

    def describe(self) -> str:
        """The plan as log lines."""
        kind = "exact" if self.exact else "upper bounds: the rankings are not computed yet, each taken as disjoint"
        lines = [f"SfM plan ({kind}); local features of {self.features} images"]
        for p in self.paradigms:
            lines.append(
                f"  {p.paradigm}: query pairs {p.query_pairs}, database pairs {p.database_pairs}, "
                f"maps {p.maps}, registrations {p.registrations} of {p.queries} queries"
            )
        return "\n".join(lines)


def feature_work(inputs: SfmInputs) -> Work:
    """Images of both sets, and those whose features are not cached."""
    scene = inputs.scene
    new = len(inputs.database_features.store.missing(scene.database.names)) + len(
        inputs.query_features.store.missing(scene.queries.names)
    )
    return Work(len(scene.database) + len(scene.queries), new)


def query_pair_work(
    inputs: SfmInputs, rankings: Sequence[Ranking] | None, ks: Sequence[int], num_rankings: int
) -> Work:
    """Query-database pairs of every query's top ``max(ks)`` of each ranking (``None``: upper
    bounds for ``num_rankings`` rankings), and those not matched yet."""
    scene = inputs.scene
    if rankings is None:
        bound = min(
            num_rankings * len(scene.queries) * min(max(ks), len(scene.database)),
            len(scene.queries) * len(scene.database),
        )
        return Work(bound, bound)
    pairs = inputs.query_pairs.canonical(inputs.ranked_pairs(rankings, [r.clamp_ks(ks) for r in rankings]))
    return Work(len(pairs), len(inputs.query_pairs.raw.missing(map(pair_key, pairs))))


def database_pair_work(inputs: SfmInputs, pairs: Iterable[tuple[str, str]]) -> Work:
    """Database pairs (names), and those not matched yet."""
    pairs = inputs.database_pairs.canonical(pairs)
    return Work(len(pairs), len(inputs.database_pairs.raw.missing(map(pair_key, pairs))))


def registration_work(tasks: Sequence[QueryTask]) -> tuple[Work, Work]:
    """Registrations (a query in one set of images) of ``tasks``, and those not cached; and the
    same summed over the images of each set."""
    return (
        Work(sum(len(task.image_sets()) for task in tasks), sum(len(task.pending()) for task in tasks)),
        Work(
            sum(len(images) for task in tasks for images in task.image_sets()),
            sum(len(images) for task in tasks for images in task.pending()),
        ),
    )


def registration_bound(queries: int, database: int, ks: Sequence[int], num_rankings: int) -> tuple[Work, Work]:
    """`registration_work` at most, for ``num_rankings`` rankings not computed yet."""
    registrations = num_rankings * queries * len(ks)
    images = num_rankings * queries * sum(min(k, database) for k in ks)
    return Work(registrations, registrations), Work(images, images)


def queries_to_register(tasks: Sequence[QueryTask]) -> Work:
    """Queries of ``tasks``, and those with a registration not cached."""
    return Work(len(tasks), sum(not task.complete for task in tasks))
