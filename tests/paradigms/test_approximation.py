import numpy as np
import pytest
from helpers import evaluate_config
from scipy.spatial.transform import Rotation

from locretrieval import geometry
from locretrieval.benchmark import benchmark
from locretrieval.build import benchmark_settings
from locretrieval.config import ConfigError
from locretrieval.estimates import LOCALIZED
from locretrieval.paradigms import approximation
from locretrieval.paradigms.approximation import (
    DEGENERATE_BDI,
    EMPTY_RETRIEVAL,
    BarycentricWeights,
    CosineSimilarityWeights,
    EqualWeights,
    PrefixWeights,
    approximate_poses,
)
from locretrieval.retrieval import EMPTY, Ranking
from locretrieval.retrieval.index import search
from locretrieval.scene import Camera, ImageSet, Scene

CAMERA = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))


METHODS = ("ewb", "bdi", "csi")


def approximate(database, ranking, ks, methods=METHODS, alpha=8.0):
    """Paradigm 1 with every method and the paper's CSI exponent unless given."""
    built = {"ewb": EqualWeights(), "bdi": BarycentricWeights(), "csi": CosineSimilarityWeights(alpha)}
    return approximate_poses(database, ranking, ks, {name: built[name] for name in methods})


def image_set(qvec, centers) -> ImageSet:
    qvec = np.asarray(qvec, dtype=float)
    tvec = geometry.translations_from_centers(qvec, np.asarray(centers, dtype=float))
    n = len(qvec)
    return ImageSet([f"db/{i}.png" for i in range(n)], "/nonexistent", [CAMERA] * n, qvec, tvec)


def unit(v):
    v = np.asarray(v, dtype=np.float32)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def descriptor_ranking(indices, queries, db_desc, name="d") -> Ranking:
    """A descriptor ranking whose scores are ``d_q . d_i``, as `search` returns them."""
    indices = np.asarray(indices)
    scores = np.einsum("qd,qkd->qk", queries, db_desc[np.where(indices == EMPTY, 0, indices)])
    return Ranking(name, indices, np.where(indices == EMPTY, 0.0, scores), "descriptor", queries, db_desc)


def by_method(estimates):
    return {e.method: e for e in estimates}


@pytest.fixture
def two_images():
    angle = np.radians(40.0)
    q = [[np.cos(angle / 2), 0, np.sin(angle / 2), 0], [np.cos(angle / 2), 0, -np.sin(angle / 2), 0]]
    return image_set(q, [[0.0, 0.0, 0.0], [4.0, 2.0, 0.0]])


def test_k1_returns_the_top_pose_exactly_for_every_method(two_images):
    db_desc = unit(np.eye(2, 8))
    ranking = descriptor_ranking(
        [[1, 0], [0, 1]], unit([[0.2, 1, 0, 0, 0, 0, 0, 0], [1, 0.1, 0, 0, 0, 0, 0, 0]]), db_desc
    )
    estimates = approximate(two_images, ranking, [1])
    assert sorted(e.method for e in estimates) == ["bdi", "csi", "ewb"]
    for e in estimates:
        np.testing.assert_allclose(e.qvec[0], two_images.qvec[[1, 0]], atol=1e-12)
        np.testing.assert_allclose(e.tvec[0], two_images.tvec[[1, 0]], atol=1e-12)


def test_symmetric_weights_give_the_midpoint(two_images):
    db_desc = unit(np.eye(2, 8))
    query = unit(db_desc[0] + db_desc[1])[None]
    ranking = descriptor_ranking([[0, 1]], query, db_desc)
    for e in approximate(two_images, ranking, [2]):
        center = geometry.camera_centers(e.qvec[0, 0], e.tvec[0, 0])
        np.testing.assert_allclose(center, [2.0, 1.0, 0.0], atol=1e-9, err_msg=e.method)
        np.testing.assert_allclose(np.abs(e.qvec[0, 0]), [1, 0, 0, 0], atol=1e-9, err_msg=e.method)


def test_negated_quaternions_give_the_same_result(two_images):
    flipped = image_set(-two_images.qvec, two_images.centers)
    flipped.qvec[:] = -two_images.qvec  # ImageSet normalises w >= 0; force the flipped sign back
    ranking = Ranking("gt", [[0, 1]], [[1.0, 0.5]], "groundtruth")
    a = approximate(two_images, ranking, [2])[0]
    b = approximate(flipped, ranking, [2])[0]
    assert geometry.rotation_errors_deg(a.qvec, b.qvec)[0, 0] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(
        geometry.camera_centers(a.qvec, a.tvec), geometry.camera_centers(b.qvec, b.tvec), atol=1e-9
    )


def test_weights_against_independent_solutions():
    rng = np.random.default_rng(0)
    n, k, dim = 12, 5, 16
    rotations = Rotation.random(n, random_state=2).as_quat()[:, [3, 0, 1, 2]]
    centers = rng.normal(size=(n, 3)) * 5
    database = image_set(rotations, centers)
    db_desc = unit(rng.normal(size=(n, dim)))
    query = unit(rng.normal(size=(1, dim)))
    order = np.argsort(-(db_desc @ query[0]))
    ranking = Ranking("d", order[None], (db_desc @ query[0])[order][None], "descriptor", query, db_desc)
    estimates = by_method(approximate(database, ranking, [k]))
    top = order[:k]

    # BDI: eliminate the constraint (w_k = 1 - sum of the others) and solve least squares.
    d = db_desc[top].astype(float)
    A = (d[:-1] - d[-1]).T
    free, *_ = np.linalg.lstsq(A, query[0] - d[-1], rcond=None)
    bdi = np.append(free, 1 - free.sum())
    # CSI: explicit formula with alpha = 8 (similarities clamped at 0).
    csi = np.clip(d @ query[0], 0, None) ** 8
    csi /= csi.sum()
    for method, weights in (("bdi", bdi), ("csi", csi), ("ewb", np.full(k, 1 / k))):
        e = estimates[method]
        np.testing.assert_allclose(
            geometry.camera_centers(e.qvec, e.tvec)[0, 0], weights @ centers[top], atol=1e-6, err_msg=method
        )
        expected_q = geometry.average_quaternions(rotations[top], weights)
        assert geometry.rotation_errors_deg(e.qvec[0, 0], expected_q) < 1e-5, method


def test_bdi_handles_duplicated_database_descriptors():
    database = image_set(np.tile([1.0, 0, 0, 0], (3, 1)), [[0, 0, 0], [2, 0, 0], [10, 0, 0]])
    db_desc = unit([[1, 0, 0], [1, 0, 0], [0, 1, 0]])
    query = unit([[1, 0.0, 0]])
    ranking = Ranking("d", [[0, 1, 2]], [[1, 1, 0]], "descriptor", query, db_desc)
    bdi = by_method(approximate(database, ranking, [2, 3]))["bdi"]
    centers = geometry.camera_centers(bdi.qvec, bdi.tvec)
    np.testing.assert_allclose(centers[:, 0], [[1.0, 0, 0], [1.0, 0, 0]], atol=1e-6)


def test_empty_and_short_rankings():
    database = image_set(np.tile([1.0, 0, 0, 0], (3, 1)), [[0, 0, 0], [2, 0, 0], [4, 0, 0]])
    ranking = Ranking("gt", [[EMPTY, EMPTY, EMPTY], [2, 0, EMPTY]], np.zeros((2, 3)), "groundtruth")
    (ewb,) = approximate(database, ranking, [1, 3, 5])
    assert ewb.ks == [1, 3]  # 5 is clamped to the ranking depth (the benchmark labels it 5 again)
    assert list(ewb.failures[:, 0]) == [EMPTY_RETRIEVAL, EMPTY_RETRIEVAL]
    assert np.isnan(ewb.qvec[:, 0]).all()
    centers = geometry.camera_centers(ewb.qvec[:, 1], ewb.tvec[:, 1])
    np.testing.assert_allclose(centers, [[4, 0, 0], [2, 0, 0]], atol=1e-9)


def test_descriptor_free_rankings_get_ewb_only(two_images):
    ranking = Ranking("gt", [[0, 1]], [[1.0, 0.5]], "groundtruth")
    assert [e.method for e in approximate(two_images, ranking, [1, 2])] == ["ewb"]


def test_the_configured_methods_are_the_papers_and_an_unknown_name_is_an_error():
    settings = benchmark_settings(evaluate_config("paths.root_dir=/nonexistent")).paradigms.approximation
    assert settings.chosen() == {
        "ewb": EqualWeights(),
        "bdi": BarycentricWeights(),
        "csi": CosineSimilarityWeights(8.0),
    }
    with pytest.raises(
        ConfigError,
        match=r"paradigms.approximation.methods: must be a non-empty list of names of paradigms.approximation.weights "
        r"\['ewb', 'bdi', 'csi'\], got \['ewb', 'median'\]",
    ):
        benchmark_settings(
            evaluate_config("paths.root_dir=/nonexistent", "paradigms.approximation.methods=[ewb,median]")
        )
    with pytest.raises(ConfigError, match=r"paradigms.approximation.weights.csi.alpha: must be positive, got 0"):
        benchmark_settings(
            evaluate_config("paths.root_dir=/nonexistent", "paradigms.approximation.weights.csi.alpha=0")
        )


def test_csi_with_a_huge_exponent_keeps_the_most_similar_image():
    database = image_set(np.tile([1.0, 0, 0, 0], (3, 1)), [[0, 0, 0], [2, 0, 0], [4, 0, 0]])
    db_desc = unit([[1, 0.2, 0], [1, 0.5, 0], [0.3, 1, 0]])
    query = unit([[1, 0.1, 0]])
    ranking = Ranking("d", [[0, 1, 2]], (db_desc @ query[0])[None], "descriptor", query, db_desc)
    csi = by_method(approximate(database, ranking, [3], alpha=5000.0))["csi"]
    assert csi.failures[0, 0] == LOCALIZED
    # (0.83 / 0.995)^5000 ~ 1e-400: the plain power underflows every weight to 0, the ratio keeps 1 for the first
    np.testing.assert_allclose(geometry.camera_centers(csi.qvec, csi.tvec)[0, 0], [0, 0, 0], atol=1e-9)


def test_bdi_with_a_query_equal_to_a_database_descriptor_takes_that_pose():
    database = image_set(np.tile([1.0, 0, 0, 0], (3, 1)), [[0, 0, 0], [2, 0, 0], [10, 0, 0]])
    db_desc = unit([[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    query = db_desc[1:2].copy()
    ranking = Ranking("d", [[1, 0, 2]], [[1, 0, 0]], "descriptor", query, db_desc)
    bdi = by_method(approximate(database, ranking, [1, 3]))["bdi"]
    assert list(bdi.failures[:, 0]) == [LOCALIZED, LOCALIZED]
    np.testing.assert_allclose(geometry.camera_centers(bdi.qvec, bdi.tvec)[:, 0], [[2, 0, 0], [2, 0, 0]], atol=1e-6)


def test_bdi_with_non_finite_descriptors_is_a_reported_failure():
    database = image_set(np.tile([1.0, 0, 0, 0], (2, 1)), [[0, 0, 0], [2, 0, 0]])
    db_desc = np.array([[1, 0, 0], [np.inf, 0, 0]], dtype=np.float32)
    ranking = descriptor_ranking([[0, 1]], unit([[1, 0.1, 0]]), db_desc)
    (bdi,) = approximate(database, ranking, [2], methods=["bdi"])
    assert bdi.failures[0, 0] == DEGENERATE_BDI and np.isnan(bdi.tvec[0, 0]).all()


def _bdi_by_least_squares(db_desc, query, top):
    """BDI weights of one query by eliminating the constraint (w_k = 1 - sum of the others)."""
    d = db_desc[top].astype(float)
    if len(top) == 1:
        return np.ones(1)
    free, *_ = np.linalg.lstsq((d[:-1] - d[-1]).T, query - d[-1], rcond=None)
    return np.append(free, 1 - free.sum())


def test_bdi_for_several_k_and_a_short_ranking_in_chunks(monkeypatch):
    rng = np.random.default_rng(3)
    n, dim, ks = 20, 32, [1, 2, 3, 5, 8]
    rotations = Rotation.random(n, random_state=4).as_quat()[:, [3, 0, 1, 2]]
    centers = rng.normal(size=(n, 3)) * 5
    database = image_set(rotations, centers)
    db_desc = unit(rng.normal(size=(n, dim)))
    queries = unit(rng.normal(size=(3, dim)))
    indices = np.array([rng.permutation(n)[:8], np.append(rng.permutation(n)[:4], [EMPTY] * 4), rng.permutation(n)[:8]])
    ranking = descriptor_ranking(indices, queries, db_desc)
    whole = by_method(approximate(database, ranking, ks, methods=["bdi"]))["bdi"]
    monkeypatch.setattr(approximation, "CHUNK_QUERIES", 2)  # two chunks, the second of one query
    monkeypatch.setattr(approximation, "PRODUCT_TABLE_BYTES", 0)  # products from gathered descriptors
    (chunked,) = approximate(database, ranking, ks, methods=["bdi"])
    np.testing.assert_allclose(chunked.tvec, whole.tvec, atol=1e-9)
    for q, row in enumerate(indices):
        filled = row[row != EMPTY]
        for n_k, k in enumerate(ks):
            top = filled[:k]  # the short ranking uses all its 4 images for k = 5, 8
            weights = _bdi_by_least_squares(db_desc, queries[q], top)
            center = geometry.camera_centers(whole.qvec[n_k, q], whole.tvec[n_k, q])
            np.testing.assert_allclose(center, weights @ centers[top], atol=1e-6, err_msg=f"query {q}, k={k}")


def _float64_bdi_weights(db_desc, query, top):
    """BDI weights of one query from its float64 residual Gram matrix, ``G^-1 1 / 1^T G^-1 1``."""
    residuals = db_desc[top].astype(np.float64) - query.astype(np.float64)
    solved = np.linalg.solve(residuals @ residuals.T, np.ones(len(top)))
    return solved / solved.sum()


@pytest.mark.parametrize("table_bytes", [0, 1 << 28], ids=["gathered", "table"])
def test_bdi_from_float32_products_equals_the_float64_solution(monkeypatch, table_bytes):
    """Unrelated descriptors (well conditioned, float32 products kept) and near-duplicates of a
    few places (ill conditioned: those queries' Gram matrices are recomputed in float64)."""
    monkeypatch.setattr(approximation, "PRODUCT_TABLE_BYTES", table_bytes)
    rng = np.random.default_rng(5)
    n, dim, k = 60, 256, 10
    places = unit(rng.normal(size=(6, dim)))
    for db_desc in (
        unit(rng.normal(size=(n, dim))),
        unit(places[rng.integers(6, size=n)] + 0.05 * rng.normal(size=(n, dim))),
    ):
        queries = unit(db_desc[:20] + 0.3 * rng.normal(size=(20, dim)))
        ranking = search(queries, db_desc, depth=k, name="d", chunk_size=256)
        for axis in range(3):  # interpolated centres are the weights applied to random centres
            centers = np.zeros((n, 3))
            centers[:, axis] = rng.normal(size=n)
            database = image_set(np.tile([1.0, 0, 0, 0], (n, 1)), centers)
            (bdi,) = approximate(database, ranking, [k], methods=["bdi"])
            estimated = geometry.camera_centers(bdi.qvec[0], bdi.tvec[0])[:, axis]
            expected = [
                _float64_bdi_weights(db_desc, queries[q], ranking.indices[q]) @ centers[ranking.indices[q], axis]
                for q in range(20)
            ]
            np.testing.assert_allclose(estimated, expected, atol=1e-6 * np.abs(centers).max())


def test_bdi_refuses_scores_that_are_not_the_descriptors_products(two_images):
    db_desc = unit(np.eye(2, 8))
    ranking = Ranking("netvlad", [[0, 1]], [[0.2, 0.1]], "descriptor", db_desc[:1], db_desc)
    with pytest.raises(ValueError, match="ranking 'netvlad'.*score 0.200000, d_q . d_i = 1.000000"):
        approximate(two_images, ranking, [2], methods=["bdi"])


def test_only_ill_conditioned_queries_take_the_float64_path(monkeypatch):
    """Descriptors of places along a route (neighbours alike, scores ~0.6: squared pivots ~0.4)
    stay on float32 products and match the float64 solution; near-duplicates go to float64."""
    exact = []
    real = approximation._exact_grams
    monkeypatch.setattr(
        approximation, "_exact_grams", lambda ranked, queries: exact.append(len(queries)) or real(ranked, queries)
    )
    rng = np.random.default_rng(2)
    n, dim, k = 200, 1024, 20
    frequencies, phases = rng.normal(size=(dim, 1)) / 3.0, rng.uniform(0, 2 * np.pi, dim)

    def along_route(positions, noise):
        return unit(
            np.cos(positions[:, None] @ frequencies.T + phases) + noise * rng.normal(size=(len(positions), dim))
        )

    route = along_route(np.arange(n, dtype=float), 0.5)
    duplicates = unit(np.repeat(route[::20], 20, axis=0) + 0.01 * rng.normal(size=(n, dim)))
    centers = np.column_stack([rng.normal(size=n), np.zeros((n, 2))])
    database = image_set(np.tile([1.0, 0, 0, 0], (n, 1)), centers)
    for db_desc, takes_float64 in ((route, False), (duplicates, True)):
        exact.clear()
        queries = (
            along_route(rng.uniform(0, n, 30), 0.5)
            if not takes_float64
            else unit(db_desc[::7] + 0.01 * rng.normal(size=(29, dim)))
        )
        ranking = search(queries, db_desc, depth=k, name="d", chunk_size=256)
        (bdi,) = approximate(database, ranking, [k], methods=["bdi"])
        assert (sum(exact) > 0) == takes_float64
        expected = [
            _float64_bdi_weights(db_desc, q, ranking.indices[i]) @ centers[ranking.indices[i], 0]
            for i, q in enumerate(queries)
        ]
        np.testing.assert_allclose(
            geometry.camera_centers(bdi.qvec[0], bdi.tvec[0])[:, 0], expected, atol=1e-6 * np.abs(centers).max()
        )
    residuals = route[:5].astype(np.float64) - route[7].astype(np.float64)
    np.testing.assert_allclose(real(route[None, :5], route[7][None]), (residuals @ residuals.T)[None], atol=1e-12)


def test_chunks_run_in_parallel_threads_keep_each_querys_result_in_its_place(monkeypatch):
    rng = np.random.default_rng(5)
    n, dim, ks = 15, 16, [1, 3, 6]
    database = image_set(Rotation.random(n, random_state=6).as_quat()[:, [3, 0, 1, 2]], rng.normal(size=(n, 3)) * 5)
    db_desc = unit(rng.normal(size=(n, dim)))
    queries = unit(rng.normal(size=(9, dim)))
    indices = np.argsort(-(queries @ db_desc.T), axis=1)[:, :6]  # ranked by similarity, as `search` ranks
    indices[[2, 7]] = EMPTY  # failures must stay on their own queries
    ranking = descriptor_ranking(indices, queries, db_desc)
    whole = by_method(approximate(database, ranking, ks))
    monkeypatch.setattr(approximation, "CHUNK_QUERIES", 1)
    monkeypatch.setattr(approximation, "resolve_workers", lambda workers: 4)  # more threads than cores here
    chunked = by_method(approximate(database, ranking, ks))
    for method in METHODS:
        np.testing.assert_array_equal(chunked[method].failures, whole[method].failures)
        np.testing.assert_allclose(chunked[method].qvec, whole[method].qvec, atol=1e-12, err_msg=method)
        np.testing.assert_allclose(chunked[method].tvec, whole[method].tvec, atol=1e-12, err_msg=method)
    assert (whole["bdi"].failures[:, [2, 7]] == EMPTY_RETRIEVAL).all()


class TopImageWeights(PrefixWeights):
    """A method from outside the package: all the weight on the best-ranked image, at every k."""

    uses_descriptors = False

    def raw_weights(self, scores, valid):
        return (np.arange(valid.shape[1]) == 0)[None, :] & valid


def test_a_method_from_outside_the_package_is_chosen_through_the_config(two_images, monkeypatch):
    """``TopImageWeights``, named in the config alone, runs on every ranking beside EWB: at every k
    it gives the top image's pose, as EWB does at k=1."""
    cfg = evaluate_config(
        "paths.root_dir=/nonexistent",
        f"+paradigms.approximation.weights.top={{_target_: {__name__}.TopImageWeights}}",
        "paradigms.approximation.methods=[ewb,top]",
        "paradigms.approximation.k=[1,2]",
        "paradigms.local_sfm.enabled=false",
        "paradigms.global_sfm.enabled=false",
    )
    settings = benchmark_settings(cfg)
    queries = image_set(two_images.qvec[[1, 0]], two_images.centers[[1, 0]] + 0.5)
    scene = Scene("two", two_images, queries)
    ranking = Ranking("gt", [[0, 1], [1, 0]], [[1.0, 0.5], [1.0, 0.5]], "groundtruth")
    everyone = {"all": np.ones(2, dtype=bool)}
    estimates = {e.method: e for e in benchmark(scene, [ranking], settings, everyone, None, {}).estimates}
    assert list(estimates) == ["ewb", "top"]
    for at in range(2):  # k=1 and k=2
        np.testing.assert_allclose(estimates["top"].qvec[at], two_images.qvec[[0, 1]], atol=1e-12)
        np.testing.assert_allclose(estimates["top"].tvec[at], two_images.tvec[[0, 1]], atol=1e-12)
    np.testing.assert_allclose(estimates["top"].tvec[0], estimates["ewb"].tvec[0], atol=1e-12)
    assert not np.allclose(estimates["top"].tvec[1], estimates["ewb"].tvec[1])  # EWB at k=2 averages two poses
