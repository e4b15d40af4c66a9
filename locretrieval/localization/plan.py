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

import contextlib
import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from locretrieval.localization.features import read_or_extract
from locretrieval.localization.matching import pair_key
from locretrieval.localization.pnp import estimate_absolute_pose
from locretrieval.localization.sfm import QueryTask, SfmInputs, SfmSettings, correspondences
from locretrieval.localization.verification import PairVerification, VerificationBatch, verify_pairs
from locretrieval.retrieval import Ranking
from locretrieval.scene import ImageSet, Scene

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
    triangulate (with ``pairs_per_map`` matched pairs each, on average; ``parallel_maps``: in the
    worker processes, else one map in this process) and registrations."""

    paradigm: str
    query_pairs: Work
    database_pairs: Work
    maps: Work
    pairs_per_map: float
    registrations: Work
    parallel_maps: bool = True


@dataclass(frozen=True)
class UnitCosts:
    """Seconds per unit, measured on a sample: local features of an image (one process), a
    matched pair (one CPU worker's thread, or the GPU), a database pair verified against its poses
    and a query pair by ``sfm.matching.query_verification`` (one process), a matched pair
    triangulated into a map, and a registration (one process); ``keypoints``: mean per image of
    the ``sample_images`` database images and the query they were measured on."""

    features: float
    matching: float
    pose_verification: float
    query_verification: float
    triangulation: float
    registration: float
    keypoints: float
    device: str
    sample_images: int


@dataclass
class SfmPlan:
    """The SfM work of a run: ``features`` (images of both sets), one `ParadigmWork` per
    paradigm, whether the counts are ``exact`` (or upper bounds), the worker ``processes``."""

    features: Work
    paradigms: list[ParadigmWork]
    exact: bool
    processes: int
    costs: UnitCosts | None = field(default=None)

    def new_query_pairs(self) -> int:
        """New query pairs: shared by the paradigms (each query with its top max(k) of every ranking)."""
        return max((p.query_pairs.new for p in self.paradigms), default=0)

    def new_pairs(self) -> int:
        """Pairs to match: new query pairs and new database pairs."""
        return self.new_query_pairs() + sum(p.database_pairs.new for p in self.paradigms)

    def forecast(self) -> dict[str, float]:
        """Seconds per stage for the new work (`costs` required): single-threaded stages, and
        matching on a CPU, are spread over the worker processes (a map every query shares is one
        process's); on a GPU matching is one process's, fed by the others."""
        costs = self.costs
        assert costs is not None, "forecast needs measured unit costs"
        triangulated = sum(
            p.maps.new * p.pairs_per_map / (self.processes if p.parallel_maps else 1) for p in self.paradigms
        )
        verified = (
            sum(p.database_pairs.new for p in self.paradigms) * costs.pose_verification
            + self.new_query_pairs() * costs.query_verification
        )
        return {
            "features": self.features.new * costs.features / self.processes,
            "matching": self.new_pairs() * costs.matching / (self.processes if costs.device == "cpu" else 1),
            "verification": verified / self.processes,
            "triangulation": triangulated * costs.triangulation,
            "registration": sum(p.registrations.new for p in self.paradigms) * costs.registration / self.processes,
        }

    def describe(self) -> str:
        """The plan as log lines."""
        kind = "exact" if self.exact else "upper bounds: the rankings are not computed yet, each taken as disjoint"
        lines = [f"SfM plan ({kind}); local features of {self.features} images"]
        for p in self.paradigms:
            lines.append(
                f"  {p.paradigm}: query pairs {p.query_pairs}, database pairs {p.database_pairs}, "
                f"maps {p.maps} (~{p.pairs_per_map:,.0f} pairs each), registrations {p.registrations}"
            )
        if self.costs is not None:
            c = self.costs
            lines.append(
                f"  measured on {c.sample_images + 1} images of the scene "
                f"({c.keypoints:.0f} keypoints each, matching on {c.device}): "
                f"features {c.features:.3f} s/image, matching {c.matching:.4f} "
                f"s/pair, verification {c.pose_verification:.4f} "
                f"s/database pair and {c.query_verification:.4f} s/query "
                f"pair, triangulation {c.triangulation:.4f} s/pair, "
                f"registration {c.registration:.4f} s/query; {self.processes} worker process(es)"
            )
            stages = self.forecast()
            lines.append(
                "  forecast: "
                + ", ".join(f"{stage} {_duration(seconds)}" for stage, seconds in stages.items())
                + f"; total {_duration(sum(stages.values()))}"
                + ("" if self.exact else " at most")
            )
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


def registration_work(tasks: Sequence[QueryTask]) -> Work:
    """Registrations (a query in one set of images) of ``tasks``, and those not cached."""
    return Work(sum(len(task.image_sets()) for task in tasks), sum(len(task.pending()) for task in tasks))


def measure_unit_costs(scene: Scene, settings: SfmSettings, sample_images: int = SAMPLE_IMAGES) -> UnitCosts:
    """Unit costs on a sample of the scene, in memory: the first posed database image and its
    ``sample_images - 1`` nearest posed neighbours (by camera centre), and the first query: their
    local features, every pair's matches (each image against its later partners in one call, as
    the pipeline batches them) and verification, the database images' map with their known
    poses, the query's registration in it."""
    import pycolmap  # noqa: F401  (its first import is no unit's cost)

    database = scene.database
    posed = np.flatnonzero(database.has_pose)
    if len(posed) < 2:
        raise ValueError(
            f"scene {scene.name!r}: fewer than 2 database images with a pose; the SfM paradigms cannot run"
        )
    distances = np.linalg.norm(database.centers[posed] - database.centers[posed[0]], axis=1)
    sample = posed[np.argsort(distances, kind="stable")[:sample_images]].tolist()
    features = read_or_extract(settings.features)
    started = time.perf_counter()
    records = [features(database.names[i], database.paths[i]) for i in sample]
    query = features(scene.queries.names[0], scene.queries.paths[0])
    feature_seconds = (time.perf_counter() - started) / (len(sample) + 1)

    matcher = settings.matching.matcher()
    matcher(records[0]["descriptors"][:2], [records[1]["descriptors"][:2]])  # torch's first call: not a pair's cost
    pairs = [(a, b) for a in range(len(sample)) for b in range(a + 1, len(sample))]
    with matching_threads(matcher, settings.processes):
        started = time.perf_counter()
        matches = {}
        for a in range(len(sample) - 1):
            partners = list(range(a + 1, len(sample)))
            matches.update(
                zip(
                    [(a, b) for b in partners],
                    matcher(records[a]["descriptors"], [records[b]["descriptors"] for b in partners]),
                )
            )
        query_matches = dict(enumerate(matcher(query["descriptors"], [r["descriptors"] for r in records])))
        matching_seconds = (time.perf_counter() - started) / (len(pairs) + len(sample))

    keypoints = {database.names[i]: r["keypoints"] for i, r in zip(sample, records)}
    pose_seconds, kept = verification_seconds(
        settings.matching.database_verification,
        database,
        database,
        [(sample[a], sample[b]) for a, b in pairs],
        list(matches.values()),
        keypoints,
        keypoints,
    )
    verified = dict(zip(pairs, kept))
    query_seconds, _ = verification_seconds(
        settings.query_verification,
        scene.queries,
        database,
        [(0, i) for i in sample],
        list(query_matches.values()),
        {scene.queries.names[0]: query["keypoints"]},
        keypoints,
    )

    started = time.perf_counter()
    sparse_map = settings.triangulation.triangulate(
        [database.cameras[i] for i in sample],
        database.qvec[sample],
        database.tvec[sample],
        [r["keypoints"] for r in records],
        verified,
    )
    triangulation_seconds = (time.perf_counter() - started) / len(pairs)

    started = time.perf_counter()
    points2D, points3D = correspondences(
        query["keypoints"], query_matches, sparse_map, {s: s for s in range(len(sample))}
    )
    if len(points2D):
        estimate_absolute_pose(points2D, points3D, scene.queries.cameras[0], settings.pnp)
    registration_seconds = time.perf_counter() - started
    mean_keypoints = float(np.mean([len(r["keypoints"]) for r in [*records, query]]))
    return UnitCosts(
        feature_seconds,
        matching_seconds,
        pose_seconds,
        query_seconds,
        triangulation_seconds,
        registration_seconds,
        mean_keypoints,
        matcher.device,
        len(sample),
    )


@contextlib.contextmanager
def matching_threads(matcher: Any, processes: int) -> Iterator[None]:
    """Torch's threads as a matching worker has them: one when CPU workers share the cores
    (`SfmPlan.forecast` divides the matching then), all of them otherwise (one process, or the GPU)."""
    import torch

    threads = torch.get_num_threads()
    if matcher.device == "cpu" and processes > 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def verification_seconds(
    verification: PairVerification,
    images0: ImageSet,
    images1: ImageSet,
    pairs: Sequence[tuple[int, int]],
    matches: Sequence[np.ndarray],
    keypoints0: dict[str, np.ndarray],
    keypoints1: dict[str, np.ndarray],
) -> tuple[float, list[np.ndarray]]:
    """Seconds per pair of ``verification`` on a batch of pairs (indices) and what it keeps."""
    started = time.perf_counter()
    kept = verify_pairs(
        verification, VerificationBatch(images0, images1, list(pairs), list(matches), keypoints0, keypoints1)
    )
    return (time.perf_counter() - started) / max(1, len(pairs)), kept
