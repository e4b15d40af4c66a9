"""The benchmark core: rankings -> paradigms -> metrics, computed in memory, no file written.

`evaluate.py` (through `locretrieval.evaluation`) and the training callback both call it:

    settings = build.benchmark_settings(cfg)                          # every section checked
    groundtruths = compute_groundtruths(scene, gt_settings, settings.sfm, cache_dir)
    descriptors = describe_scene(model, scene, cache_dir=None)       # e.g. a network in memory
    rankings = build_rankings(scene, {model.name: descriptors}, groundtruths, settings.retrieval, seed)
    result = benchmark(scene, rankings, settings, subsets, cache_dir, relevances(groundtruths, gt_settings.relevance))

``cache_dir`` only holds what the SfM paradigms reuse across runs (local features, matches,
maps), keyed by what produced them; it is never a place results are written to.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import sparse

from locretrieval.config import ConfigError
from locretrieval.estimates import PoseEstimates
from locretrieval.groundtruth import GroundTruth, RelevanceScope
from locretrieval.metrics.localization import MetricsSettings, localization_tables, query_error_table, query_subsets
from locretrieval.metrics.retrieval import retrieval_tables
from locretrieval.metrics.subsets import SubsetSettings, image_subsets, known_subsets
from locretrieval.paradigms.base import Paradigms
from locretrieval.paradigms.sfm import run_sfm
from locretrieval.retrieval import Ranking, random_ranking
from locretrieval.retrieval.descriptors import SceneDescriptors
from locretrieval.retrieval.index import RetrievalSettings, search
from locretrieval.scene import Scene
from locretrieval.sfm.inputs import sfm_inputs
from locretrieval.sfm.settings import SfmSettings
from locretrieval.shard import Shard

log = logging.getLogger(__name__)


@dataclass
class BenchmarkSettings:
    """What the benchmark core reads, each part checked under its own config key."""

    retrieval: RetrievalSettings
    paradigms: Paradigms
    sfm: SfmSettings
    metrics: MetricsSettings

    @classmethod
    def from_config(cls, cfg: object) -> BenchmarkSettings:
        """Moved in 0.12: the settings of a composed config are built by `locretrieval.build.benchmark_settings`."""
        raise AttributeError("BenchmarkSettings.from_config moved: locretrieval.build.benchmark_settings(cfg)")


@dataclass
class BenchmarkResult:
    """Everything the benchmark computed for one scene.

    ``localization``: % localised per subset x ranking x paradigm x method x k x threshold, with its
    interval (`RESULT_COLUMNS`); ``query_localized``: the per-query outcomes it counts
    (`QUERY_LOCALIZED_COLUMNS`, which the paired comparisons read); ``query_errors``: per query;
    ``retrieval`` / ``query_retrieval``: P@k, R@k, mAP@k of every ranking against every ground truth
    (empty without ground truth), with their intervals;
    ``sfm_stages``: per SfM stage, its seconds, work done and unit (`StageRecord`); ``sfm_seconds``:
    the SfM paradigms' wall-clock seconds.
    """

    dataset: str
    rankings: list[Ranking]
    estimates: list[PoseEstimates]
    localization: pd.DataFrame
    query_errors: pd.DataFrame
    retrieval: pd.DataFrame
    query_retrieval: pd.DataFrame
    query_localized: pd.DataFrame = dataclasses.field(default_factory=pd.DataFrame)
    sfm_stages: dict[str, dict[str, float | int | str]] = dataclasses.field(default_factory=dict)
    sfm_seconds: float = 0.0


def build_rankings(
    scene: Scene,
    descriptors: Mapping[str, SceneDescriptors],
    groundtruths: Mapping[str, GroundTruth],
    retrieval: RetrievalSettings,
    random_seed: int | None,
    given: Sequence[Ranking] = (),
) -> list[Ranking]:
    """The descriptor rankings (faiss search, one per named set of descriptors), the ``given``
    rankings (e.g. read from pairs files), the ground-truth rankings and, with a ``random_seed``,
    the random baseline; names are unique."""
    rankings = [
        search(described.queries, described.database, retrieval.depth, name, retrieval.chunk_size)
        for name, described in descriptors.items()
    ]
    rankings += [*given, *(groundtruth.ranking for groundtruth in groundtruths.values())]
    if random_seed is not None:
        rankings.append(random_ranking(len(scene.queries), len(scene.database), retrieval.depth, random_seed))
    check_unique_names(rankings)
    return rankings


def check_unique_names(rankings: Sequence[Ranking]) -> None:
    """Ranking names label every table row and output folder: two rankings must not share one."""
    names = [r.name for r in rankings]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"rankings {repeated} are named twice ({names}): rename the model (model.name=...)")


def check_supported(scene: Scene, names: Sequence[str]) -> None:
    """Raise `ConfigError` when a paradigm or ground truth in ``names`` is one the scene's dataset
    cannot run (`Scene.unsupported`), saying why and how to switch it off."""
    refused = [f"{name}: {scene.unsupported[name]}" for name in names if name in scene.unsupported]
    if refused:
        raise ConfigError(
            f"dataset {scene.name!r} does not support "
            + "; ".join(refused)
            + " (switch it off, e.g. paradigms.<name>.enabled=false)"
        )


def warn_shallow_rankings(rankings: Sequence[Ranking], ks: Sequence[int]) -> None:
    """Warn once about the ks beyond a ranking's depth: the paradigms use all its images, and
    results keep the requested k as label (``k_effective`` says how many were used)."""
    shallow = {r.name: r.depth for r in rankings if ks and r.depth < max(ks)}
    if shallow:
        beyond = sorted(k for k in ks if k > min(shallow.values()))
        log.warning(
            "k values %s exceed the images ranked per query %s: those k use them all; results, LTVL files and "
            "figures keep the requested k, results.csv's k_effective holds the k used",
            beyond,
            shallow,
        )


def warn_whole_database_ks(scene: Scene, paradigms: Paradigms) -> None:
    """Warn about the ks of the SfM paradigms that reach the whole database (a small place of one's own):
    there every ranking, random included, hands the paradigm the same images, so no ranking can differ."""
    size = len(scene.database)
    whole = {name: [k for k in getattr(paradigms, name).k if k >= size] for name in paradigms.sfm_paradigms()}
    whole = {name: ks for name, ks in whole.items() if ks}
    if whole:
        log.warning(
            "%s: k %s reach all %d database images: every ranking, random included, gives those paradigms the same "
            "images there, so their results cannot tell rankings apart (a smaller k list: paradigms.<name>.k=[...])",
            scene.name,
            "; ".join(f"{name} {ks}" for name, ks in whole.items()),
            size,
        )


def relevances(groundtruths: Mapping[str, GroundTruth], scope: RelevanceScope) -> dict[str, sparse.csr_matrix]:
    """Each ground truth's ``[Q, N]`` relevance the retrieval metrics count, by name (``scope``:
    ``groundtruth.relevance``, e.g. the images of its top-``depth`` ranking, the paper's)."""
    return {name: scope(gt) for name, gt in groundtruths.items()}


def scene_subsets(
    scene: Scene, settings: SubsetSettings, cache_dir: str | Path | None
) -> tuple[dict[str, np.ndarray], pd.DataFrame]:
    """The query subsets every metric is reported on (``all``, one per query tag, ``blurry``,
    ``dynamic_scene``: a tag of those, `known_subsets`) and the per-query table behind the image
    subsets (``subsets.csv``)."""
    image_masks, table = image_subsets(scene.name, scene.queries, settings, cache_dir)
    tag_masks, image_masks, table = known_subsets(query_subsets(scene.queries), image_masks, table)
    clash = sorted(set(tag_masks) & set(image_masks))
    if clash:
        raise ValueError(f"query tags {clash} clash with the subsets of configs/subsets")
    return tag_masks | image_masks, table


def run_sfm_shard(
    scene: Scene,
    rankings: Sequence[Ranking],
    settings: BenchmarkSettings,
    cache_dir: str | Path | None,
    shard: Shard,
) -> None:
    """This job's ``shard`` of the enabled SfM paradigms' work, into the shared cache
    (`locretrieval.paradigms.sfm.run_sfm`); the run without a shard then finds all of it."""
    check_supported(scene, settings.paradigms.enabled())
    paradigms = settings.paradigms.sfm_paradigms()
    if not paradigms:
        log.info("shard=%s: no SfM paradigm is enabled, nothing to do", shard)
        return
    run_sfm(sfm_inputs(scene, settings.sfm, cache_dir, paradigms), rankings, paradigms, shard=shard)
    log.info(
        "shard=%s: this job's share of %s is in %s; once every shard has run, the same command without "
        "shard writes the results",
        shard,
        " and ".join(paradigms),
        cache_dir,
    )


def sfm_within_budget(
    scene: Scene,
    rankings: Sequence[Ranking],
    settings: BenchmarkSettings,
    cache_dir: str | Path | None,
    order: Sequence[int],
    seconds: float,
) -> tuple[int, float]:
    """The enabled SfM paradigms' work on ``rankings`` for the queries in ``order``, until ``seconds``
    are spent: how many of them were reached, and the seconds it took. Chunks of queries grow with
    the throughput measured so far: one query first, then as many as the time left holds (at most
    twice the last chunk), so the budget is overrun by one chunk at most. All queries at once
    without an SfM paradigm (the rest of a validation is vectorised: seconds at most)."""
    paradigms = settings.paradigms.sfm_paradigms()
    started = time.perf_counter()
    if not paradigms:
        return len(order), 0.0
    inputs = sfm_inputs(scene, settings.sfm, cache_dir, paradigms)
    reached, chunk = 0, 1
    while reached < len(order):
        run_sfm(inputs, rankings, paradigms, queries=order[reached : reached + chunk])
        reached = min(len(order), reached + chunk)
        spent = time.perf_counter() - started
        if spent >= seconds:
            break
        chunk = max(1, min(2 * chunk, int((seconds - spent) / (spent / reached))))
    return reached, time.perf_counter() - started


def benchmark(
    scene: Scene,
    rankings: Sequence[Ranking],
    settings: BenchmarkSettings,
    subsets: Mapping[str, np.ndarray],
    cache_dir: str | Path | None,
    relevance: Mapping[str, sparse.csr_matrix],
) -> BenchmarkResult:
    """Run every enabled paradigm on every ranking, then the localization and retrieval metrics.

    Estimates and tables are labelled by the requested k, even beyond a ranking's depth (the
    paradigms then use every ranked image; `PoseEstimates.k_effective`, logged once).
    ``subsets``: boolean query masks by name (``all`` at least); ``relevance``: ground-truth
    relevance by name, for the retrieval tables (none: empty tables). Writes no file.
    """
    check_supported(scene, settings.paradigms.enabled())
    warn_shallow_rankings(rankings, settings.paradigms.ks())
    warn_whole_database_ks(scene, settings.paradigms)
    depths = {ranking.name: ranking.depth for ranking in rankings}
    sfm_paradigms = settings.paradigms.sfm_paradigms()
    sfm_estimates, sfm_stages, sfm_seconds = {}, {}, 0.0
    if sfm_paradigms:
        run = run_sfm(sfm_inputs(scene, settings.sfm, cache_dir, sfm_paradigms), rankings, sfm_paradigms)
        sfm_estimates, sfm_seconds = run.estimates or {}, run.seconds
        sfm_stages = {stage: dataclasses.asdict(record) for stage, record in run.stages.items()}
    estimates: list[PoseEstimates] = []
    for name in settings.paradigms.enabled():
        paradigm = getattr(settings.paradigms, name)
        log.info("paradigm %s, k=%s", name, paradigm.k)
        computed = (
            sfm_estimates[name] if name in sfm_estimates else paradigm.run(scene, rankings, settings.sfm, cache_dir)
        )
        # labelled by the section's name: a paradigm class may run under several names
        estimates += [dataclasses.replace(e.labelled(paradigm.k, depths[e.ranking]), paradigm=name) for e in computed]
    metrics = settings.metrics
    localization, query_localized = localization_tables(
        scene.name,
        estimates,
        scene.queries,
        metrics.thresholds,
        subsets,
        metrics.inclusive,
        metrics.uncertainty.confidence,
        scene.position_unit,
    )
    query_errors = query_error_table(scene.name, estimates, scene.queries, scene.position_unit)
    retrieval, query_retrieval = pd.DataFrame(), pd.DataFrame()
    if relevance:
        retrieval, query_retrieval = retrieval_tables(
            scene.name,
            rankings,
            relevance,
            scene.queries,
            subsets,
            range(1, settings.retrieval.depth + 1),
            settings.paradigms.ks(),
            metrics.uncertainty,
        )
    return BenchmarkResult(
        scene.name,
        list(rankings),
        estimates,
        localization,
        query_errors,
        retrieval,
        query_retrieval,
        query_localized,
        sfm_stages,
        sfm_seconds,
    )
