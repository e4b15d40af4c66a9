"""Fixtures shared by test modules: an evaluation run of a hostile dataset (built once a session, by
the first of the test processes that asks: `once_per_session`), a
rendered scene the datasets' miniatures are installed from (once a module).

The test processes of `make test` (pytest-xdist) share the machine's cores: each, and every process
it starts, gets its share of threads for the threaded libraries (torch, OpenMP, BLAS), which would
otherwise each take every core and spin against one another. The files with the most slow tests are
handed out first (`pytest_collection_modifyitems`), so that the two processes end together."""

import collections
import fcntl
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

TEST_PROCESSES = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if TEST_PROCESSES > 1:
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(variable, str(max(1, (os.cpu_count() or 1) // TEST_PROCESSES)))

from helpers import (  # noqa: E402 (after the thread limits: it imports torch)
    HOSTILE_IMAGE,
    HOSTILE_MODEL,
    HOSTILE_QUERY_FOLDER,
    HOSTILE_TAG,
    evaluate_config,
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The test files with the most tests marked ``slow`` first, each file's tests in their order:
    pytest-xdist (``--dist loadfile``) hands out whole files in this order, and a long file handed
    out last would keep one process busy while the other waits (longest first balances the two)."""
    slow = collections.Counter(item.path for item in items if item.get_closest_marker("slow"))
    items.sort(key=lambda item: -slow[item.path])  # a stable sort: ties keep the collection order


@dataclass(frozen=True)
class HostileRun:
    root: Path  # everything the run may write is below root/run and root/cache
    run: Path
    cache: Path


def hostile_dataset(root: Path) -> tuple[Path, Path]:
    """A tiny rendered scene as kapture folders whose query folder, one query image and one tag are
    the markup above; returns ``(mapping folder, query folder)``."""
    from helpers import render_settings

    from locretrieval.scene.synthetic import render_synthetic_dataset

    render = root / "render"
    settings = {"width": 160, "height": 120, "num_database": 16, "num_queries": 8, "texture_size": 64}
    render_synthetic_dataset(render_settings({**settings, "length": 20.0, "workers": 1, "seed": 3}), render)
    query = root / "data" / HOSTILE_QUERY_FOLDER
    shutil.copytree(render / "query", query)
    for folder in (query / "sensors" / "records_data", query / "masks"):
        target = folder / HOSTILE_IMAGE
        target.parent.mkdir(parents=True, exist_ok=True)
        (folder / "query" / "000001.png").rename(target)
    for text_file in (query / "sensors" / "records_camera.txt", query / "tags.txt"):
        text_file.write_text(text_file.read_text().replace("query/000001.png", HOSTILE_IMAGE))
    with (query / "tags.txt").open("a") as tags:
        tags.write(f"query/000002.png, {HOSTILE_TAG}\n")
    return render / "mapping", query


def once_per_session(tmp_path_factory: pytest.TempPathFactory, name: str, build: Callable[[Path], None]) -> Path:
    """The folder ``name`` filled by ``build(folder)`` once for the whole session: under pytest-xdist
    each test process runs a session fixture, so the first one that asks builds it in the folder the
    processes share, under a lock, and the others wait and read it (pytest-xdist's documented pattern,
    with `fcntl.flock` for its lock). A build that fails is retried by the next process that asks."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # the session's folder, above each process's own
    folder, done = base / name, base / f"{name}.done"
    with (base / f"{name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def hostile_run(tmp_path_factory) -> HostileRun:
    """`evaluate` of `hostile_dataset` with ``model.name`` `HOSTILE_MODEL`, the approximation paradigm
    only (read, never changed, by tests/whole/test_hostile_input.py and tests/report/test_html.py)."""
    root = once_per_session(tmp_path_factory, "hostile", hostile_evaluation)
    return HostileRun(root, root / "run", root / "cache")


def hostile_evaluation(root: Path) -> None:
    """`hostile_run`'s evaluation, everything it writes under ``root``."""
    from helpers import evaluate

    mapping, query = hostile_dataset(root)
    config = evaluate_config(
        "data=kapture", f"paths.root_dir={root}", f"paths.cache_dir={root / 'cache'}", "device=cpu",
        "report.figure_formats=[png]", "model.max_side=160", "model.step=4", "subsets.blur_width=160",
        "paradigms.local_sfm.enabled=false", "paradigms.global_sfm.enabled=false", "data.mapping=x", "data.queries=[x]",
    )  # fmt: skip
    config.data.mapping, config.data.queries, config.model.name = str(mapping), [str(query)], HOSTILE_MODEL
    evaluate(config, root / "run")


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A tiny rendered scene and its local features, from which the datasets' miniatures are installed
    (`published_layouts.install`): ``(scene, {image name: features})``."""
    import helpers
    from published_layouts import SCENE

    from locretrieval.scene.kapture_io import load_kapture_scene
    from locretrieval.scene.synthetic import render_synthetic_dataset
    from locretrieval.sfm.features import extract_features

    root = tmp_path_factory.mktemp("published_source")
    render_synthetic_dataset(helpers.render_settings(SCENE), root)
    scene = load_kapture_scene("rendered", [root / "mapping"], [root / "query"])
    features = extract_features(scene.database, helpers.sfm_settings().features, root / "cache", 1)
    query_features = extract_features(scene.queries, helpers.sfm_settings().features, root / "cache", 1)
    local = {**features.load(scene.database.names), **query_features.load(scene.queries.names)}
    return scene, local
