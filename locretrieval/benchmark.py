"""The benchmark core: rankings -> paradigms -> metrics, computed in memory, no file written.

`evaluate.py` (through `locretrieval.evaluation`) and the training callback both call it:

    settings = BenchmarkSettings.from_config(cfg)                     # every section checked
    groundtruths = compute_groundtruths(scene, gt_settings, settings.sfm, cache_dir)
    descriptors = describe_scene(model, scene, cache_dir=None)       # e.g. a network in memory
    rankings = build_rankings(scene, {model.name: descriptors}, groundtruths, settings.retrieval, seed)
    result = benchmark(scene, rankings, settings, subsets, cache_dir, relevances(groundtruths))

``cache_dir`` only holds what the SfM paradigms reuse across runs (local features, matches,
maps), keyed by what produced them; it is never a place results are written to.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy import sparse

from locretrieval.cache import config_key
from locretrieval.config import ConfigError, validated
from locretrieval.groundtruth import GroundTruth
from locretrieval.localization import approximation, global_sfm, local_sfm
from locretrieval.localization.approximation import ApproximationSettings
from locretrieval.localization.estimates import PoseEstimates
from locretrieval.localization.global_sfm import GlobalSfmSettings
from locretrieval.localization.local_sfm import LocalSfmSettings
from locretrieval.localization.paradigm import ParadigmSettings
from locretrieval.localization.pipeline import SfmStages, run_sfm
from locretrieval.localization.plan import SfmPlan, UnitCosts, feature_work, measure_unit_costs, prepare_workers
from locretrieval.localization.sfm import SfmInputs, SfmSettings
from locretrieval.metrics.localization import MetricsSettings, localization_table, query_error_table, query_subsets
from locretrieval.metrics.retrieval import retrieval_tables
from locretrieval.metrics.subsets import SubsetSettings, image_subsets
from locretrieval.retrieval import Ranking, random_ranking
from locretrieval.retrieval.descriptors import SceneDescriptors
from locretrieval.retrieval.index import RetrievalSettings, search
from locretrieval.scene import Scene

log = logging.getLogger(__name__)

#: How often training validates a paradigm: every validation, or every ``sfm_every_n_epochs``.
PARADIGM_COSTS = ("cheap", "sfm")


@dataclass(frozen=True)
class Paradigm:
    """A localization paradigm: its ``settings`` schema (a `ParadigmSettings`, the section of
    ``configs/paradigms`` of its name), its entry point ``run(scene, rankings, settings, sfm,
    cache_dir) -> [PoseEstimates]``, and what it needs: ``uses_local_features`` (the ``sfm``
    group's features and matches), ``missing_inputs(settings) -> [problem]`` (files it reads that are absent), ``cost``:
    ``cheap`` (run at every training validation) or ``sfm`` (every ``sfm_every_n_epochs``), and
    ``map_points(scene, settings, sfm, cache_dir) -> [P, 3] or None`` (the 3D points of a map it
    built, for the report's 3D view). An SfM paradigm gives its ``stages`` of the SfM pipeline
    (`SfmStages`, its work counted by their ``plan``): the benchmark runs every enabled one
    through one pipeline (`run_sfm`)."""

    settings: type[ParadigmSettings]
    run: Callable[..., list[PoseEstimates]]
    stages: SfmStages | None = None
    missing_inputs: Callable[[Any], list[str]] | None = None
    cost: str = "cheap"
    map_points: Callable[..., np.ndarray | None] | None = None

    @property
    def uses_local_features(self) -> bool:
        """Whether it reads the ``sfm`` group's local features and matches."""
        return self.stages is not None

    def __post_init__(self) -> None:
        if self.cost not in PARADIGM_COSTS:
            raise ValueError(f"paradigm {self.run.__module__}: cost must be one of {PARADIGM_COSTS}, got {self.cost!r}")


#: The paradigms, in the order they run, by their section name in ``configs/paradigms``. A new
#: paradigm is its module (settings schema, ``run``) and one entry here (and its YAML section).
PARADIGMS: dict[str, Paradigm] = {
    "approximation": Paradigm(ApproximationSettings, approximation.run),
    "local_sfm": Paradigm(LocalSfmSettings, local_sfm.run, local_sfm.STAGES, cost="sfm"),
    "global_sfm": Paradigm(
        GlobalSfmSettings,
        global_sfm.run,
        global_sfm.STAGES,
        missing_inputs=global_sfm.missing_inputs,
        cost="sfm",
        map_points=global_sfm.map_points,
    ),
}
#: Unit costs measured in this process, by what they were measured on (`sfm_plan`).
_unit_costs: dict[str, UnitCosts] = {}


@dataclass
class ParadigmsSettings:
    """The ``paradigms`` config group: one checked section per `PARADIGMS` entry, read as an
    attribute of its name (``settings.paradigms.local_sfm``)."""

    sections: dict[str, ParadigmSettings]

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any], key: str) -> "ParadigmsSettings":
        """Each section of ``mapping`` checked by its paradigm's schema (`locretrieval.config.validated`);
        an unknown or missing section is a `ConfigError` naming it."""
        unknown = sorted(set(mapping) - set(PARADIGMS))
        if unknown:
            raise ConfigError(f"{key}.{unknown[0]}: unknown key; expected one of {list(PARADIGMS)}")
        missing = [name for name in PARADIGMS if name not in mapping]
        if missing:
            raise ConfigError(
                f"{key}.{missing[0]}: missing; every paradigm needs its section (enabled: false switches it off)"
            )
        return cls(
            {name: validated(paradigm.settings, mapping[name], f"{key}.{name}") for name, paradigm in PARADIGMS.items()}
        )

    def __getattr__(self, name: str) -> ParadigmSettings:
        sections = self.__dict__.get("sections", {})
        if name in sections:
            return sections[name]
        raise AttributeError(f"no paradigm section {name!r}; known: {list(sections)}")

    def enabled(self) -> list[str]:
        """The enabled paradigms, in the order of `PARADIGMS`."""
        return [name for name, section in self.sections.items() if section.enabled]

    def ks(self) -> list[int]:
        """Every k of an enabled paradigm, sorted."""
        return sorted({k for name in self.enabled() for k in self.sections[name].k})

    def only(self, keep: Callable[[Paradigm], bool]) -> "ParadigmsSettings":
        """These settings with the paradigms ``keep`` refuses switched off."""
        return ParadigmsSettings(
            {
                name: section if keep(PARADIGMS[name]) else dataclasses.replace(section, enabled=False)
                for name, section in self.sections.items()
            }
        )


@dataclass
class BenchmarkSettings:
    """What the benchmark core reads, each part checked under its own config key."""

    retrieval: RetrievalSettings
    paradigms: ParadigmsSettings
    sfm: SfmSettings
    metrics: MetricsSettings

    @classmethod
    def from_config(cls, cfg: Any) -> "BenchmarkSettings":
        """The settings in a composed ``evaluate``/``train`` config (sections of the same names)."""
        return cls(
            retrieval=validated(RetrievalSettings, cfg.retrieval, "retrieval"),
            paradigms=validated(ParadigmsSettings, cfg.paradigms, "paradigms"),
            sfm=validated(SfmSettings, cfg.sfm, "sfm"),
            metrics=validated(MetricsSettings, cfg.metrics, "metrics"),
        )


@dataclass
class BenchmarkResult:
    """Everything the benchmark computed for one scene.

    ``localization``: % localised per subset x ranking x paradigm x method x k x threshold
    (`RESULT_COLUMNS`); ``query_errors``: per query; ``retrieval`` / ``query_retrieval``:
    P@k, R@k, mAP@k of every ranking against every ground truth (empty without ground truth);
    ``sfm_stages``: per SfM stage, its forecast and measured seconds (`stage_times`).
    """

    dataset: str
    rankings: list[Ranking]
    estimates: list[PoseEstimates]
    localization: pd.DataFrame
    query_errors: pd.DataFrame
    retrieval: pd.DataFrame
    query_retrieval: pd.DataFrame
    sfm_stages: dict[str, dict[str, float | None]] = dataclasses.field(default_factory=dict)


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


#: Which relevant images the retrieval metrics count (`relevances`).
RELEVANCE_SCOPES = ("top_k", "all")


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


def relevances(groundtruths: Mapping[str, GroundTruth], scope: str = "top_k") -> dict[str, sparse.csr_matrix]:
    """Each ground truth's ``[Q, N]`` relevance, by name: of the images in its top-``depth``
    ranking (``scope="top_k"``, the paper's) or of every database image (``"all"``)."""
    if scope not in RELEVANCE_SCOPES:
        raise ConfigError(f"groundtruth.relevance must be one of {list(RELEVANCE_SCOPES)}, got {scope!r}")
    return {name: gt.relevance_in_ranking() if scope == "top_k" else gt.relevance for name, gt in groundtruths.items()}


def scene_subsets(
    scene: Scene, settings: SubsetSettings, cache_dir: str | Path | None, device: str
) -> tuple[dict[str, np.ndarray], pd.DataFrame]:
    """The query subsets every metric is reported on (``all``, one per query tag, ``blurry``,
    ``dynamic_scene``) and the per-query table behind the image subsets (``subsets.csv``)."""
    image_masks, table = image_subsets(scene.name, scene.queries, settings, cache_dir, device)
    tag_masks = query_subsets(scene.queries)
    clash = sorted(set(tag_masks) & set(image_masks))
    if clash:
        raise ValueError(f"query tags {clash} clash with the subsets of configs/subsets")
    return tag_masks | image_masks, table


def sfm_plan(
    scene: Scene,
    rankings: Sequence[Ranking] | None,
    settings: BenchmarkSettings,
    cache_dir: str | Path | None,
    num_rankings: int = 0,
) -> SfmPlan | None:
    """The work of the enabled SfM paradigms (`SfmPlan`; ``None`` when none is enabled or there
    is no cache): exact for ``rankings``, or upper bounds for ``num_rankings`` rankings not
    computed yet (``None``). When there is new work, unit costs are measured on a sample of the
    scene (`measure_unit_costs`, once per scene and settings in a process) for the forecast, and
    the worker pool is started when a stage will need it."""
    paradigms = sfm_paradigms(settings)
    if not paradigms or cache_dir is None:
        return None
    cache_dir = Path(cache_dir)
    inputs = SfmInputs.prepare(scene, settings.sfm, cache_dir, extract=False)
    work = [
        stages.plan(scene, rankings, paradigm_settings, settings.sfm, cache_dir, num_rankings)
        for stages, paradigm_settings in paradigms.values()
    ]
    plan = SfmPlan(feature_work(inputs), work, rankings is not None, settings.sfm.processes)
    if plan.has_new_work:
        key = config_key(
            scene.database.fingerprint(),
            scene.queries.fingerprint(),
            dataclasses.asdict(settings.sfm),
            {name: dataclasses.asdict(paradigm_settings) for name, (_, paradigm_settings) in paradigms.items()},
        )
        if key not in _unit_costs:
            _unit_costs[key] = measure_unit_costs(scene, settings.sfm, paradigms, cache_dir)
        plan.costs = _unit_costs[key]
        prepare_workers(plan)
    return plan


def sfm_paradigms(settings: BenchmarkSettings) -> dict[str, tuple[SfmStages, ParadigmSettings]]:
    """The enabled SfM paradigms: name -> (their pipeline stages, their settings)."""
    return {
        name: (PARADIGMS[name].stages, getattr(settings.paradigms, name))
        for name in settings.paradigms.enabled()
        if PARADIGMS[name].stages is not None
    }


def run_sfm_shard(
    scene: Scene, rankings: Sequence[Ranking], settings: BenchmarkSettings, cache_dir: str | Path | None
) -> None:
    """This job's share (``sfm.shard``) of the enabled SfM paradigms' work, into the shared cache
    (`locretrieval.localization.pipeline`); the run without ``sfm.shard`` then finds all of it."""
    check_supported(scene, settings.paradigms.enabled())
    paradigms = sfm_paradigms(settings)
    if not paradigms:
        log.info("sfm.shard=%s: no SfM paradigm is enabled, nothing to do", settings.sfm.shard)
        return
    run_sfm(scene, rankings, paradigms, settings.sfm, cache_dir)
    log.info(
        "sfm.shard=%s: this job's share of %s is in %s; once every shard has run, the same command without "
        "sfm.shard writes the results",
        settings.sfm.shard,
        " and ".join(paradigms),
        cache_dir,
    )


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
    depths = {ranking.name: ranking.depth for ranking in rankings}
    if settings.sfm.job_shard is not None:
        raise ValueError(
            f"sfm.shard={settings.sfm.shard}: a shard's job computes its share of the SfM work (run_sfm_shard), "
            "not results; run without sfm.shard to assemble them"
        )
    plan = sfm_plan(scene, rankings, settings, cache_dir)
    if plan is not None:
        log.info("%s", plan.describe())
    measured: dict[str, float] = {}
    sfm_estimates = (
        run_sfm(scene, rankings, sfm_paradigms(settings), settings.sfm, cache_dir, measured)
        if sfm_paradigms(settings)
        else {}
    )
    sfm_stages = stage_times(plan.forecast() if plan is not None and plan.costs else {}, measured)
    estimates: list[PoseEstimates] = []
    for paradigm in settings.paradigms.enabled():
        paradigm_settings = getattr(settings.paradigms, paradigm)
        log.info("paradigm %s, k=%s", paradigm, paradigm_settings.k)
        computed = (
            sfm_estimates[paradigm]
            if paradigm in sfm_estimates
            else PARADIGMS[paradigm].run(scene, rankings, paradigm_settings, settings.sfm, cache_dir)
        )
        estimates += [e.labelled(paradigm_settings.k, depths[e.ranking]) for e in computed]
    thresholds = settings.metrics.thresholds
    localization = localization_table(
        scene.name, estimates, scene.queries, thresholds, subsets, settings.metrics.inclusive
    )
    query_errors = query_error_table(scene.name, estimates, scene.queries)
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
        )
    return BenchmarkResult(
        scene.name, list(rankings), estimates, localization, query_errors, retrieval, query_retrieval, sfm_stages
    )


def stage_times(forecast: Mapping[str, float], measured: Mapping[str, float]) -> dict[str, dict[str, float | None]]:
    """Per SfM stage (and ``total``), its ``forecast_s`` and ``measured_s`` seconds (None where
    one is missing) and their ``ratio`` (measured / forecast), logged."""
    stages = {
        stage: {"forecast_s": forecast.get(stage), "measured_s": measured.get(stage)}
        for stage in dict.fromkeys([*forecast, *measured])
    }
    if forecast and measured:
        stages["total"] = {"forecast_s": sum(forecast.values()), "measured_s": sum(measured.values())}
    for times in stages.values():
        known = times["forecast_s"] is not None and times["measured_s"] is not None and times["forecast_s"] > 0
        times["ratio"] = times["measured_s"] / times["forecast_s"] if known else None
    if stages:
        log.info(
            "SfM stages, forecast -> measured: %s",
            ", ".join(
                f"{stage} {_seconds(times['forecast_s'])} -> {_seconds(times['measured_s'])}"
                + (f" ({times['ratio']:.2f}x)" if times["ratio"] is not None else "")
                for stage, times in stages.items()
            ),
        )
    return stages


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f} s"
