"""The work of the SfM paradigms, counted and forecast before any of it is done.

Per paradigm: the query-database pairs to match, the database pairs to match, the maps to
triangulate and the registrations, each as needed in all and new (not in the caches); for the
scene: the images whose local features are not cached. With the rankings known the counts are
exact; before (``evaluate.py dry_run=true``) they are upper bounds: every ranking's top-k taken
as disjoint from the others'.

The forecast multiplies the new work by unit costs measured on a small sample of the scene on
this machine and device (`measure_unit_costs`: a database image, its nearest neighbours and a
query: their features, matches, a map of them and a registration, all in memory).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from locretrieval.localization.features import read_or_extract
from locretrieval.localization.matching import pair_key
from locretrieval.localization.pnp import estimate_absolute_pose
from locretrieval.localization.sfm import QueryTask, SfmInputs, SfmSettings, correspondences
from locretrieval.localization.triangulation import triangulate_known_poses
from locretrieval.localization.verification import epipolar_inliers
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene

log = logging.getLogger(__name__)

#: Database images of the sample that unit costs are measured on (one query besides).
SAMPLE_IMAGES = 3


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
    triangulate (with ``pairs_per_map`` matched pairs each, on average) and registrations."""

    paradigm: str
    query_pairs: Work
    database_pairs: Work
    maps: Work
    pairs_per_map: float
    registrations: Work


@dataclass(frozen=True)
class UnitCosts:
    """Seconds per unit, measured on a sample: local features of an image (one process), a
    matched pair (this process's threads or the GPU), a matched pair triangulated into a map,
    and a registration (one process); ``keypoints``: mean per image in the sample."""

    features: float
    matching: float
    triangulation: float
    registration: float
    keypoints: float
    device: str


@dataclass
class SfmPlan:
    """The SfM work of a run: ``features`` (images of both sets), one `ParadigmWork` per
    paradigm, whether the counts are ``exact`` (or upper bounds), the worker ``processes``."""

    features: Work
    paradigms: list[ParadigmWork]
    exact: bool
    processes: int
    costs: UnitCosts | None = field(default=None)

    def new_pairs(self) -> int:
        """Pairs to match: new query pairs (shared by the paradigms: the largest) and new database pairs."""
        query = max((p.query_pairs.new for p in self.paradigms), default=0)
        return query + sum(p.database_pairs.new for p in self.paradigms)

    def forecast(self) -> dict[str, float]:
        """Seconds per stage for the new work (`costs` required): single-threaded stages are
        spread over the worker processes; matching already uses every core (or the GPU)."""
        costs = self.costs
        assert costs is not None, "forecast needs measured unit costs"
        triangulated = sum(p.maps.new * p.pairs_per_map for p in self.paradigms)
        return {
            "features": self.features.new * costs.features / self.processes,
            "matching": self.new_pairs() * costs.matching,
            "triangulation": triangulated * costs.triangulation / self.processes,
            "registration": sum(p.registrations.new for p in self.paradigms) * costs.registration / self.processes,
        }

    def describe(self) -> str:
        """The plan as log lines."""
        kind = "exact" if self.exact else "upper bounds: the rankings are not computed yet, each taken as disjoint"
        lines = [f"SfM plan ({kind}); local features of {self.features} images"]
        for p in self.paradigms:
            lines.append(f"  {p.paradigm}: query pairs {p.query_pairs}, database pairs {p.database_pairs}, "
                         f"maps {p.maps} (~{p.pairs_per_map:,.0f} pairs each), registrations {p.registrations}")
        if self.costs is not None:
            c = self.costs
            lines.append(f"  measured on {SAMPLE_IMAGES + 1} images of the scene ({c.keypoints:.0f} keypoints each, matching on {c.device}): "
                         f"features {c.features:.3f} s/image, matching {c.matching:.4f} s/pair, triangulation "
                         f"{c.triangulation:.4f} s/pair, registration {c.registration:.4f} s/query; {self.processes} worker process(es)")
            stages = self.forecast()
            lines.append("  forecast: " + ", ".join(f"{stage} {_duration(seconds)}" for stage, seconds in stages.items())
                         + f"; total {_duration(sum(stages.values()))}" + ("" if self.exact else " at most"))
        return "\n".join(lines)


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.1f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def feature_work(inputs: SfmInputs) -> Work:
    """Images of both sets, and those whose features are not cached."""
    scene = inputs.scene
    new = len(inputs.database_features.store.missing(scene.database.names)) + len(inputs.query_features.store.missing(scene.queries.names))
    return Work(len(scene.database) + len(scene.queries), new)


def query_pair_work(inputs: SfmInputs, rankings: Sequence[Ranking] | None, ks: Sequence[int], num_rankings: int) -> Work:
    """Query-database pairs of every query's top ``max(ks)`` of each ranking (``None``: upper
    bounds for ``num_rankings`` rankings), and those not matched yet."""
    scene = inputs.scene
    if rankings is None:
        bound = min(num_rankings * len(scene.queries) * min(max(ks), len(scene.database)), len(scene.queries) * len(scene.database))
        return Work(bound, bound)
    pairs = inputs.query_pairs.canonical(inputs.ranked_pairs(rankings, [r.clamp_ks(ks) for r in rankings]))
    return Work(len(pairs), len(inputs.query_pairs.raw.missing(map(pair_key, pairs))))


def database_pair_work(inputs: SfmInputs, pairs: Iterable[tuple[str, str]]) -> Work:
    """Database pairs (names), and those not matched yet."""
    pairs = inputs.database_pairs.canonical(pairs)
    return Work(len(pairs), len(inputs.database_pairs.raw.missing(map(pair_key, pairs))))


def registration_work(tasks: Sequence[QueryTask]) -> Work:
    """Registrations (a query in one set of images) of ``tasks``, and those not cached."""
    return Work(sum(len(task.image_sets()) for task in tasks), sum(len(task.pending()) for task in tasks))


def measure_unit_costs(scene: Scene, settings: SfmSettings) -> UnitCosts:
    """Unit costs on a sample of the scene, in memory: the first posed database image and its
    nearest posed neighbours (by camera centre), and the first query: their local features,
    every pair's matches, the database images' map with their known poses, the query's
    registration in it."""
    database = scene.database
    posed = np.flatnonzero(database.has_pose)
    if len(posed) < 2:
        raise ValueError(f"scene {scene.name!r}: fewer than 2 database images with a pose; the SfM paradigms cannot run")
    distances = np.linalg.norm(database.centers[posed] - database.centers[posed[0]], axis=1)
    sample = posed[np.argsort(distances, kind="stable")[:SAMPLE_IMAGES]].tolist()
    features = read_or_extract(settings.features)
    started = time.perf_counter()
    records = [features(database.names[i], database.paths[i]) for i in sample]
    query = features(scene.queries.names[0], scene.queries.paths[0])
    feature_seconds = (time.perf_counter() - started) / (len(sample) + 1)

    matcher = settings.matching.matcher()
    matcher(records[0]["descriptors"][:2], [records[1]["descriptors"][:2]])  # torch's first call: not a pair's cost
    pairs = [(a, b) for a in range(len(sample)) for b in range(a + 1, len(sample))]
    started = time.perf_counter()
    matches = {(a, b): matcher(records[a]["descriptors"], [records[b]["descriptors"]])[0] for a, b in pairs}
    query_matches = dict(enumerate(matcher(query["descriptors"], [r["descriptors"] for r in records])))
    matching_seconds = (time.perf_counter() - started) / (len(pairs) + len(sample))

    started = time.perf_counter()
    verified = {}
    for (a, b), pair_matches in matches.items():
        i, j = sample[a], sample[b]
        verified[(a, b)] = pair_matches[epipolar_inliers(
            records[a]["keypoints"], records[b]["keypoints"], pair_matches, database.cameras[i], (database.qvec[i], database.tvec[i]),
            database.cameras[j], (database.qvec[j], database.tvec[j]), settings.matching.max_epipolar_error,
        )]
    sparse_map = triangulate_known_poses(
        [database.cameras[i] for i in sample], database.qvec[sample], database.tvec[sample],
        [r["keypoints"] for r in records], verified, settings.triangulation,
    )
    triangulation_seconds = (time.perf_counter() - started) / len(pairs)

    started = time.perf_counter()
    points2D, points3D = correspondences(query["keypoints"], query_matches, sparse_map, {s: s for s in range(len(sample))})
    if len(points2D):
        estimate_absolute_pose(points2D, points3D, scene.queries.cameras[0], settings.pnp)
    registration_seconds = time.perf_counter() - started
    keypoints = float(np.mean([len(r["keypoints"]) for r in [*records, query]]))
    return UnitCosts(feature_seconds, matching_seconds, triangulation_seconds, registration_seconds, keypoints, matcher.device)
