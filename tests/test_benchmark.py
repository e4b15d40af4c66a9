"""The benchmark as a library: a network in memory, caches keyed by its weights, extraction that
leaves the network as it was, layers that import one way, and config sections checked by key."""

import ast
from dataclasses import dataclass
from pathlib import Path

import helpers
import numpy as np
import pandas as pd
import pytest
import torch
from helpers import evaluate_config, render_settings
from PIL import Image
from torch import nn

from locretrieval.benchmark import benchmark, build_rankings, check_unique_names, relevances
from locretrieval.build import benchmark_settings
from locretrieval.config import ConfigError
from locretrieval.estimates import PoseEstimates
from locretrieval.evaluation import export_ltvl
from locretrieval.groundtruth import RankedRelevance, compute_groundtruths
from locretrieval.models import NetworkDescriptor
from locretrieval.models.extraction import ExtractionSettings, Preprocessing, extract_descriptors
from locretrieval.models.networks import GeMPooling, RetrievalNet, l2_normalize
from locretrieval.paradigms.base import Paradigm
from locretrieval.retrieval import random_ranking
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset

PACKAGE = Path(__file__).resolve().parents[1] / "locretrieval"
SCENE = {"width": 96, "height": 72, "num_database": 24, "num_queries": 6, "texture_size": 64, "length": 20.0,
         "conditions": {"night": 0.0, "blur": 0.0, "dynamic": 0.0, "noise": 0.0}, "database_dynamic": 0.0,
         "hard_query_fraction": 0.0, "workers": 1, "seed": 4}  # fmt: skip
PREPROCESSING = Preprocessing(max_side=None, scales=(1.0,))
EXTRACTION = ExtractionSettings(
    device="cpu", batch_size=8, num_workers=0, mixed_precision=False, progress=False, memmap_dir=None
)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("core_scene")
    render_synthetic_dataset(render_settings(SCENE), root)
    return load_kapture_scene("tiny", [root / "mapping"], [root / "query"], frustum_far=25.0)


def tiny_network(seed: int) -> RetrievalNet:
    """A conv + batch-norm trunk with GeM pooling, seeded."""
    torch.manual_seed(seed)
    trunk = nn.Sequential(nn.Conv2d(3, 16, 5, stride=2), nn.BatchNorm2d(16), nn.ReLU(), nn.Conv2d(16, 32, 3))
    return RetrievalNet(trunk, GeMPooling(32, p=3.0, trainable=True), 32)


def by_hand(network: RetrievalNet, paths) -> np.ndarray:
    """Unit descriptors, one image at a time: ``(rgb / 255 - mean) / std``, eval-mode forward, L2."""
    mean, std = torch.tensor(PREPROCESSING.mean).view(1, 3, 1, 1), torch.tensor(PREPROCESSING.std).view(1, 3, 1, 1)
    was_training = network.training
    network.eval()
    with torch.no_grad():
        rows = []
        for path in paths:
            rgb = torch.from_numpy(np.array(Image.open(path).convert("RGB"))).permute(2, 0, 1)[None].float()
            rows.append(l2_normalize(network((rgb / 255 - mean) / std))[0].numpy())
    network.train(was_training)
    return np.stack(rows)


def test_the_core_benchmarks_a_network_in_memory_twice_without_disk_caches(scene, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("LOCRETRIEVAL_CACHE", str(tmp_path / "cache"))
    cfg = evaluate_config(
        "paradigms.local_sfm.enabled=false",
        "paradigms.global_sfm.enabled=false",
        "paradigms.approximation.k=[1,3]",
        "paths.root_dir=/nonexistent",
    )
    settings = benchmark_settings(cfg)
    groundtruths = compute_groundtruths(
        scene, helpers.groundtruth_section({"relative_pose": cfg.groundtruth.definitions.relative_pose}, depth=50)
    )
    network = tiny_network(0)
    everyone = {"all": np.ones(len(scene.queries), dtype=bool)}
    top = []
    for seed in (0, 1):
        network.load_state_dict(tiny_network(seed).state_dict())  # the same module, new weights
        described = describe_scene(NetworkDescriptor("tiny", network, PREPROCESSING, EXTRACTION), scene, cache_dir=None)
        rankings = build_rankings(scene, {"tiny": described}, groundtruths, settings.retrieval, random_seed=None)
        result = benchmark(scene, rankings, settings, everyone, None, relevances(groundtruths, RankedRelevance()))

        similarity = by_hand(network, scene.queries.paths) @ by_hand(network, scene.database.paths).T
        ranking = rankings[0]
        best_first = -np.sort(-similarity, axis=1)
        np.testing.assert_allclose(np.take_along_axis(similarity, ranking.indices, 1), best_first, atol=1e-5)
        ewb = next(e for e in result.estimates if e.ranking == "tiny" and e.method == "ewb")
        np.testing.assert_allclose(
            ewb.tvec[0], scene.database.tvec[ranking.indices[:, 0]], atol=1e-9
        )  # k=1: the top image's pose
        assert set(result.localization["ranking"]) == {"tiny", "gt_relative_pose"}
        assert set(result.retrieval["ranking"]) == {"tiny", "gt_relative_pose"}
        top.append(ranking.indices)
    assert (top[0] != top[1]).any()
    assert list(tmp_path.iterdir()) == []  # no file written, no cache touched


def test_a_k_beyond_the_ranking_depth_keeps_its_label_in_every_paradigm(scene, tmp_path, caplog):
    cfg = evaluate_config(
        "retrieval.depth=3",
        "paradigms.approximation.k=[1,5,8]",
        "paradigms.local_sfm.k=[2,5]",
        "paradigms.global_sfm.k=[1,5,8]",
        "sfm.workers=1",
        "paths.root_dir=/nonexistent",
    )
    settings = benchmark_settings(cfg)
    groundtruths = compute_groundtruths(
        scene, helpers.groundtruth_section({"relative_pose": cfg.groundtruth.definitions.relative_pose}, depth=3)
    )
    described = describe_scene(
        NetworkDescriptor("tiny", tiny_network(0), PREPROCESSING, EXTRACTION), scene, cache_dir=None
    )
    rankings = build_rankings(scene, {"tiny": described}, groundtruths, settings.retrieval, random_seed=0)
    assert {r.depth for r in rankings} == {3}
    everyone = {"all": np.ones(len(scene.queries), dtype=bool)}
    with caplog.at_level("WARNING"):
        result = benchmark(scene, rankings, settings, everyone, tmp_path, relevances(groundtruths, RankedRelevance()))
    assert sum("exceed the images ranked per query" in r.getMessage() for r in caplog.records) == 1
    labels = result.localization.drop_duplicates(["paradigm", "k"]).set_index(["paradigm", "k"])["k_effective"]
    assert labels.to_dict() == {("approximation", 1): 1, ("approximation", 5): 3, ("approximation", 8): 3,
                                ("local_sfm", 2): 2, ("local_sfm", 5): 3,
                                ("global_sfm", 1): 1, ("global_sfm", 5): 3, ("global_sfm", 8): 3}  # fmt: skip
    for e in result.estimates:
        at = {k: n for n, k in enumerate(e.ks)}
        if 8 in at:  # k=5 and k=8 both use the 3 ranked images, under their own labels
            np.testing.assert_array_equal(e.tvec[at[5]], e.tvec[at[8]])
    assert set(result.query_retrieval["k"]) == {1, 2, 5, 8}
    export_ltvl(scene, result, tmp_path / "ltvl")
    written = {path.name for path in (tmp_path / "ltvl" / "tiny").iterdir()}
    assert {
        "approximation_ewb_k8.txt",
        "approximation_csi_k5.txt",
        "local_sfm_pnp_k5.txt",
        "global_sfm_pnp_k8.txt",
    } <= written
    assert not any("_k3." in name for name in written)


def test_one_parameter_changed_in_memory_gives_new_descriptors_not_the_cached_ones(scene, tmp_path):
    network = tiny_network(0)
    model = NetworkDescriptor("tiny", network, PREPROCESSING, EXTRACTION)
    forward_calls = []
    network.register_forward_hook(lambda *args: forward_calls.append(1))
    first = describe_scene(model, scene, tmp_path)
    forward_calls.clear()
    np.testing.assert_array_equal(describe_scene(model, scene, tmp_path).database, first.database)
    assert forward_calls == []  # served from the cache
    with torch.no_grad():
        network.pooling.p.add_(1.0)
    changed = describe_scene(model, scene, tmp_path)
    assert forward_calls and not np.allclose(changed.database, first.database, atol=1e-3)
    np.testing.assert_allclose(changed.database, by_hand(network, scene.database.paths), atol=1e-5)
    assert len(list((tmp_path / "descriptors").glob("*.npz"))) == 2


def test_extraction_runs_on_the_networks_device_and_restores_train_mode(scene):
    network = tiny_network(0).train()
    batch_norm = network.backbone[1]
    before = {name: tensor.clone() for name, tensor in network.state_dict().items()}
    settings = ExtractionSettings(
        device="cuda", batch_size=4, num_workers=0, mixed_precision=True, progress=False, memmap_dir=None
    )
    paths, sizes = scene.queries.paths, [(c.width, c.height) for c in scene.queries.cameras]
    descriptors, _ = extract_descriptors(
        network, paths, PREPROCESSING, settings, sizes
    )  # device is the network's (CPU)
    assert network.training and batch_norm.training
    assert all(
        torch.equal(before[name], tensor) for name, tensor in network.state_dict().items()
    )  # statistics untouched
    assert next(network.parameters()).device.type == "cpu" and network.backbone[0].weight.is_contiguous()
    np.testing.assert_allclose(descriptors, by_hand(network, paths), atol=1e-5)  # eval-mode batch norm
    images = torch.randint(0, 256, (2, 3, 5, 7), dtype=torch.uint8)
    expected = (images.float() / 255 - torch.tensor(PREPROCESSING.mean).view(1, 3, 1, 1)) / torch.tensor(
        PREPROCESSING.std
    ).view(1, 3, 1, 1)
    torch.testing.assert_close(PREPROCESSING.normalize(images), expected)


#: The data flow, lowest first: a module may import its own layer and those before it. An entry is a
#: package or module below ``locretrieval``; a module belongs to the longest entry that is it or a
#: package holding it (`part_of`): the reports of training runs read what training writes, and the
#: training run and the sweep write those reports at their end.
LAYERS = [
    {
        "scene",
        "geometry",
        "config",
        "cache",
        "device",
        "frusta",
        "chebyshev",
        "restricted_pickle",
        "processes",
        "pool",
        "threads",
        "errors",
        "estimates",
        "shard",
        "moved",
        "cli",
        "limits",
        "bounded_files",
        "parts",
        "folders",
        "resources",
        "console",
    },
    {"models"},
    {"retrieval"},
    {"sfm"},
    {"paradigms"},
    {"groundtruth"},
    {"metrics"},
    {"benchmark"},
    {"dry_run"},
    {"report"},
    {"evaluation"},
    {"training"},
    {"report.training", "report.training_runs", "report.training_summary"},
    {"training.run", "training.sweeps"},
    {"export"},
    {"build"},
    {"commands", "__main__"},
]


def part_of(module: str) -> str:
    """The entry of `LAYERS` the module ``module`` (dotted, below ``locretrieval``; a name in it
    too) belongs to: the longest that is it or a package above it."""
    names = module.split(".")
    for count in range(len(names), 0, -1):
        entry = ".".join(names[:count])
        if any(entry in layer for layer in LAYERS):
            return entry
    raise AssertionError(f"locretrieval.{module} is in no layer of LAYERS: add it where it reads")


def layer_of(part: str) -> int:
    return next(rank for rank, parts in enumerate(LAYERS) if part in parts)


def imported_parts(tree: ast.AST) -> set[str]:
    """The `LAYERS` entries (`part_of`) of the ``locretrieval`` modules a module imports, anywhere in it."""
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names += [f"{node.module}.{alias.name}" for alias in node.names]
    return {part_of(name.removeprefix("locretrieval.")) for name in names if name.startswith("locretrieval.")}


def test_no_module_imports_from_a_layer_above_it():
    violations = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE)
        if relative.name == "__init__.py" and len(relative.parts) == 1:
            continue
        part = part_of(".".join(relative.with_suffix("").parts).removesuffix(".__init__"))
        for imported in imported_parts(ast.parse(path.read_text())):
            if layer_of(imported) > layer_of(part):
                violations.append(f"{relative} imports locretrieval.{imported}")
    assert violations == []
    assert imported_parts(
        ast.parse("from locretrieval.metrics import x\ndef f():\n    import locretrieval.report.plots")
    ) == {"metrics", "report"}
    assert imported_parts(ast.parse("from locretrieval.report import training_summary")) == {"report.training_summary"}


def module_imports(sources: dict[str, str]) -> dict[str, set[str]]:
    """``module -> the locretrieval modules it imports`` (anywhere in it, type-checking blocks
    included), from the modules' ``sources``: ``from package import name`` is an import of the
    submodule ``package.name`` where there is one, else of the package."""
    graph = {}
    for module, source in sources.items():
        package = module if module.endswith("__init__") else module.rpartition(".")[0]
        package = package.removesuffix(".__init__")
        imported = set()
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.Import):
                imported.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
                for alias in node.names:
                    name = f"{base}.{alias.name}"
                    imported.add(name if {name, f"{name}.__init__"} & sources.keys() else base)
        graph[module] = set()
        for name in imported:
            while name and not ({name, f"{name}.__init__"} & sources.keys()):
                name = name.rpartition(".")[0]
            target = name if name in sources else f"{name}.__init__"
            if name.startswith("locretrieval") and target != module:
                graph[module].add(target)
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index, low, stack, on_stack, circles = {}, {}, [], set(), []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, successors = work[-1]
            for successor in successors:
                if successor not in index:
                    index[successor] = low[successor] = len(index)
                    stack.append(successor)
                    on_stack.add(successor)
                    work.append((successor, iter(sorted(graph[successor]))))
                    break
                if successor in on_stack:
                    low[node] = min(low[node], index[successor])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        circles.append(sorted(component))
    return circles


def test_no_import_circle_among_the_modules():
    """Each package reads top-down: no module imports, even inside a function or for type checking
    only, a module that (through others) imports it."""
    sources = {
        ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts): path.read_text()
        for path in PACKAGE.rglob("*.py")
    }
    assert len(sources) > 100
    assert import_circles(module_imports(sources)) == []
    planted = {  # the scan finds a circle through a function-level import and a package's re-export
        "locretrieval.a": "from locretrieval.b import f",
        "locretrieval.b": "def f():\n    from locretrieval.pkg import g",
        "locretrieval.pkg.__init__": "from locretrieval.pkg.c import g",
        "locretrieval.pkg.c": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from locretrieval import a",
    }
    assert import_circles(module_imports(planted)) == [sorted(planted)]


@pytest.mark.parametrize(
    "override, message",
    [
        (
            "paradigms.approximation.k=[1.5]",
            r"paradigms.approximation.k\[0\]: Value '1.5' of type "
            r"'float' could not be converted to Integer; expected int",
        ),
        ("paradigms.approximation.k=[]", r"paradigms.approximation.k: must list at least one value"),
        (
            "paradigms.approximation.k=5",
            r"paradigms.approximation.k: .* not a ListConfig, list or tuple.; expected list\[int\]",
        ),
        (
            "paradigms.approximation.k=[abc]",
            r"paradigms.approximation.k\[0\]: Value 'abc' .* could not be converted to Integer",
        ),
        ("metrics.thresholds=[[0.25]]", r"metrics.thresholds: must be a non-empty list of \[metres, degrees\] pairs"),
        (
            "+paradigms.local_sfm.kk=3",
            r"paradigms.local_sfm.kk: unknown key; expected one of \['enabled', 'k', 'map_matches'\]",
        ),
        ("sfm.pnp.max_error=-1", r"sfm.pnp.max_error: must be"),
        (
            "paradigms.local_sfm.map_matches=query",
            r"paradigms.local_sfm.map_matches: a MapMatches is chosen by its config group now: "
            r"paradigms/local_sfm/map_matches=query \(configs/paradigms/local_sfm/map_matches/query.yaml\)",
        ),
        (
            "+paradigms.approximation.alpha=4",
            r"paradigms.approximation.alpha: moved, now paradigms.approximation.weights.csi.alpha",
        ),
        ("retrieval.depth=0", r"retrieval.depth: must be >= 1"),
    ],
)
def test_config_values_of_the_wrong_type_or_range_name_the_full_key(override, message):
    with pytest.raises(ConfigError, match=message):
        benchmark_settings(evaluate_config(override, "paths.root_dir=/nonexistent"))


@dataclass
class TopImage(Paradigm):
    """A paradigm from outside the package: the pose of the top-ranked database image."""

    def method_names(self):
        return ["top_image"]

    def run(self, scene, rankings, sfm, cache_dir):
        database, ks, estimates = scene.database, list(self.k), []
        for ranking in rankings:
            top = ranking.indices[:, 0]
            qvec, tvec = database.qvec[top][None].repeat(len(ks), 0), database.tvec[top][None].repeat(len(ks), 0)
            failures = np.full((len(ks), len(top)), "", dtype=object)
            estimates.append(
                PoseEstimates(ranking.name, ranking.kind, "top_image", "top_image", ks, qvec, tvec, failures)
            )
        return estimates


def test_a_new_paradigm_is_one_class_and_one_config_section(scene, monkeypatch):
    """A paradigm added through the config alone (its ``_target_``, a class of this module) runs on
    every ranking, after the built-in ones, under its section's name: the pose of the top-ranked
    database image, which must equal paradigm 1 (EWB) at k=1."""
    cfg = evaluate_config(
        "paradigms.local_sfm.enabled=false",
        "paradigms.global_sfm.enabled=false",
        "paradigms.approximation.k=[1]",
        f"+paradigms.top_image={{_target_: {__name__}.TopImage, enabled: true, k: [1]}}",
        "paths.root_dir=/nonexistent",
    )
    settings = benchmark_settings(cfg)
    assert settings.paradigms.enabled() == ["approximation", "top_image"]
    assert not settings.paradigms.top_image.uses_sfm and settings.paradigms.local_sfm.uses_sfm
    groundtruths = compute_groundtruths(
        scene, helpers.groundtruth_section({"relative_pose": cfg.groundtruth.definitions.relative_pose}, depth=50)
    )
    rankings = build_rankings(scene, {}, groundtruths, settings.retrieval, random_seed=0)
    table = benchmark(
        scene,
        rankings,
        settings,
        {"all": np.ones(len(scene.queries), dtype=bool)},
        None,
        relevances(groundtruths, RankedRelevance()),
    ).localization
    columns = ["ranking", "k", "position_threshold_m", "localized_pct"]
    mine = table[table["paradigm"] == "top_image"][columns].sort_values(columns[:3]).reset_index(drop=True)
    ewb = (
        table[(table["paradigm"] == "approximation") & (table["method"] == "ewb")][columns]
        .sort_values(columns[:3])
        .reset_index(drop=True)
    )
    assert len(mine) == 2 * len(settings.metrics.thresholds)  # random and the ground truth, each threshold
    pd.testing.assert_frame_equal(mine, ewb)
    for section, message in (
        ("{enabled: true, k: [1]}", r"paradigms.top_image: a paradigm section without _target_"),
        (
            f"{{_target_: {__name__}.tiny_network, enabled: true}}",
            r"paradigms.top_image._target_: .* not a part of paradigms.top_image: a function there must be annotated",
        ),
        (f"{{_target_: {__name__}.NoSuchParadigm}}", r"paradigms.top_image._target_: cannot import"),
        ("{_target_: no.such.Paradigm}", r"paradigms.top_image._target_: cannot import 'no.such.Paradigm'"),
        (f"{{_target_: {__name__}.TopImage, enabled: true, k: [1], depth: 3}}", r"paradigms.top_image.depth: unknown"),
    ):
        with pytest.raises(ConfigError, match=message):
            benchmark_settings(evaluate_config(f"+paradigms.top_image={section}", "paths.root_dir=/nonexistent"))


def test_rankings_sharing_a_name_are_an_error():
    check_unique_names([random_ranking(3, 5, 2, seed=0)])
    with pytest.raises(ValueError, match=r"\['random'\] are named twice"):
        check_unique_names([random_ranking(3, 5, 2, seed=0), random_ranking(3, 5, 2, seed=1)])
