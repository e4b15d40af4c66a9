"""Whether a descriptor fails pose approximation (paradigm 1, EWB) on what its shortlist holds or on
the order of it: its % localized, then with each query's top K re-ordered by the relative-pose
ground truth's score (``s = c / tau_c + R / tau_R``, smallest first), for several K, then the
ground-truth ranking itself. Where re-ordering the top 10 gets near the ground truth, the views
EWB needs were retrieved and only ranked too low. ``--database`` asks the same of the database
images, each against the others (leave one out): on the images a network was trained on, against
the held-out queries, it tells what training reached from how far that carries to new views.

    python scripts/shortlist_oracle.py model=checkpoint model.weights=<run>/checkpoints/last.ckpt seed=1
    python scripts/shortlist_oracle.py model=densevlad data.render.environment=street --shortlists 3 10 50
    python scripts/shortlist_oracle.py --database model=checkpoint model.weights=<run>/checkpoints/last.ckpt seed=1

Arguments other than the options are evaluate.py's overrides (the scene, the model, the
thresholds); descriptors are read from and written to evaluate.py's cache.
"""

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from locretrieval.groundtruth.relative_pose import relative_pose_scores
from locretrieval.metrics.localization import localized
from locretrieval.paradigms.approximation import EqualWeights, approximate_poses
from locretrieval.retrieval.ranking import EMPTY, Ranking
from locretrieval.scene import Scene


def reordered(ranking: Ranking, pose_scores: np.ndarray, shortlist: int) -> Ranking:
    """``ranking`` with each query's first ``shortlist`` images sorted by ``pose_scores [Q, N]``
    (smaller: closer in pose; ties keep the descriptor's order), the rest as it was."""
    top = ranking.indices[:, :shortlist]
    empty = top == EMPTY
    keys = np.where(empty, np.inf, np.take_along_axis(pose_scores, np.where(empty, 0, top), axis=1))
    order = np.argsort(keys, axis=1, kind="stable")
    indices = ranking.indices.copy()
    indices[:, :shortlist] = np.take_along_axis(top, order, axis=1)
    return Ranking(f"{ranking.name} top {shortlist} by pose", indices, np.zeros(indices.shape), "groundtruth")


def ewb_localized(scene: Scene, ranking: Ranking, k: int, thresholds: list[list[float]], inclusive: bool) -> np.ndarray:
    """% of the queries with a reference pose that EWB over the top ``k`` localizes, per threshold."""
    estimate = approximate_poses(scene.database, ranking, [k], {"ewb": EqualWeights()})[0]
    hits = localized(*estimate.errors(scene.queries.qvec, scene.queries.tvec), thresholds, inclusive)[:, 0]
    return 100.0 * hits[:, scene.queries.has_pose].mean(axis=1)


def database_as_queries(scene: Scene) -> Scene:
    """``scene`` with its database images as the queries too (rank them with ``exclude_self``)."""
    return Scene(
        f"{scene.name} database",
        scene.database,
        scene.database,
        ltvl_names=scene.ltvl_names,
        frustum_far=scene.frustum_far,
    )


def shortlist_table(
    scene: Scene,
    ranking: Ranking,
    shortlists: list[int],
    k: int,
    position_threshold: float,
    rotation_threshold: float,
    thresholds: list[list[float]],
    inclusive: bool = True,
    exclude_self: bool = False,
) -> pd.DataFrame:
    """EWB over the top ``k`` (% localized per threshold) of ``ranking`` as it is, with its top K
    re-ordered by relative pose for each K of ``shortlists``, and of the relative-pose ranking of
    the whole database (``tau_c = position_threshold`` m, ``tau_R = rotation_threshold`` degrees).
    ``exclude_self``: the queries are the database (`database_as_queries`), and query ``i`` is
    not ranked by pose against itself."""
    scores, _, _ = relative_pose_scores(
        scene.queries.qvec,
        scene.queries.centers,
        scene.database.qvec,
        scene.database.centers,
        position_threshold,
        rotation_threshold,
    )
    if exclude_self:
        np.fill_diagonal(scores, np.inf)
    whole = np.argsort(scores, axis=1, kind="stable")[:, : ranking.depth]
    rankings = {
        "as ranked": ranking,
        **{f"top {K} by pose": reordered(ranking, scores, K) for K in shortlists},
        "relative pose (whole database)": Ranking("pose", whole, np.zeros(whole.shape), "groundtruth"),
    }
    rows = {name: ewb_localized(scene, ranked, k, thresholds, inclusive) for name, ranked in rankings.items()}
    return pd.DataFrame.from_dict(rows, orient="index", columns=[f"{x:g} m, {y:g} deg" for x, y in thresholds])


def main() -> None:
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from locretrieval.retrieval.descriptors import describe_scene
    from locretrieval.retrieval.index import search

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--shortlists", type=int, nargs="+", default=[3, 5, 10, 20, 50], help="the K re-ordered by pose"
    )
    parser.add_argument("--k", type=int, default=3, help="images EWB averages")
    parser.add_argument(
        "--database", action="store_true", help="the database images as queries, each against the others"
    )
    parser.add_argument("overrides", nargs="*", help="evaluate.py overrides")
    arguments = parser.parse_args()
    overrides = list(arguments.overrides)
    if not any(o.startswith("paths.root_dir=") for o in overrides):  # what evaluate.py takes from Hydra's run
        overrides.insert(0, f"paths.root_dir={Path.cwd()}")
    with initialize_config_dir(config_dir=str(Path(__file__).resolve().parents[1] / "configs"), version_base="1.3"):
        cfg = compose("evaluate", overrides)
    scene = instantiate(cfg.data)
    model = instantiate(cfg.model)
    described = describe_scene(model, scene, Path(cfg.paths.cache_dir))
    depth = max([arguments.k, *arguments.shortlists])
    if arguments.database:
        scene = database_as_queries(scene)
        ranking = search(
            described.database, described.database, depth, model.name, cfg.retrieval.chunk_size, exclude_self=True
        )
    else:
        ranking = search(described.queries, described.database, depth, model.name, cfg.retrieval.chunk_size)
    pose = cfg.groundtruth.definitions.relative_pose
    table = shortlist_table(
        scene,
        ranking,
        arguments.shortlists,
        arguments.k,
        pose.position_threshold,
        pose.rotation_threshold,
        [list(t) for t in cfg.metrics.thresholds],
        cfg.metrics.inclusive,
        exclude_self=arguments.database,
    )
    print(f"{scene.name}, {model.name}: % localized by EWB over the top {arguments.k}")
    print(table.to_markdown(floatfmt=".1f"))


if __name__ == "__main__":
    main()
