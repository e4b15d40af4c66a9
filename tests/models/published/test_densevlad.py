import logging
import math
import os
import pickle
import platform
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import helpers
import kornia
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image
from scipy.ndimage import gaussian_filter

from locretrieval.models import DenseVLAD
from locretrieval.models.published import densevlad, densevlad_kernels
from locretrieval.models.published.dense_sift import (
    cpu_lattice,
    cpu_rootsift,
    dense_rootsift,
    gradient_histograms,
    grid_layout,
    window_weights,
)
from locretrieval.models.published.vlad import kmeans_vocabulary, normalize_vlad, vlad_residuals
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.retrieval.index import search
from locretrieval.scene import Camera, ImageSet, Scene

# Small, fast settings: images are resized to 128 px; the algorithm is the default one.
SMALL = dict(max_side=128, step=3, vocabulary_samples=20_000, kmeans_iterations=10, device="cpu")


def small_densevlad_options(**options) -> dict:
    """The values of ``configs/model/densevlad.yaml``, `SMALL` and ``options`` over them."""
    values = OmegaConf.to_container(OmegaConf.load(helpers.CONFIGS / "model" / "densevlad.yaml"))
    values.pop("_target_")
    return {**values, **SMALL, **options}


def small_densevlad(kind: type = DenseVLAD, **options) -> DenseVLAD:
    """``kind`` (DenseVLAD or a subclass) with `small_densevlad_options`."""
    return kind(**small_densevlad_options(**options))


def texture(seed: int, size: int = 176) -> np.ndarray:
    """Grey random texture with structure at two scales, uint8."""
    rng = np.random.default_rng(seed)
    image = gaussian_filter(rng.random((size, size)), 1.5) + 0.6 * gaussian_filter(rng.random((size, size)), 4.0)
    image = (image - image.min()) / (image.max() - image.min())
    return (255 * image).astype(np.uint8)


def image_set(root: Path, images: dict[str, np.ndarray]) -> ImageSet:
    for name, pixels in images.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(pixels).save(root / name)
    cameras = [Camera("PINHOLE", w, h, (100.0, 100.0, w / 2, h / 2)) for h, w in (p.shape for p in images.values())]
    count = len(images)
    positions = np.arange(3 * count).reshape(count, 3)
    return ImageSet(list(images), root, cameras, np.tile([1.0, 0, 0, 0], (count, 1)), positions)


@pytest.fixture(scope="module")
def textures_scene(tmp_path_factory) -> Scene:
    """Six textures; each query is a shifted, slightly larger crop of one of them (resized back)."""
    root = tmp_path_factory.mktemp("textures")
    sources = {seed: texture(seed) for seed in range(6)}
    database = image_set(root, {f"db/{seed}.png": pixels[:128, :128] for seed, pixels in sources.items()})
    queries = image_set(root, {f"query/{seed}.png": sources[seed][9:147, 5:143] for seed in (4, 0, 2)})
    return Scene("textures", database, queries)


@pytest.fixture(scope="module")
def fitted(textures_scene) -> DenseVLAD:
    model = small_densevlad()
    model.fit(textures_scene.database)
    return model


# -- dense RootSIFT -----------------------------------------------------------------------


#: VLFeat vl_dsift's magnification and window size (bins), the values `explicit_rootsift` uses.
VL_DSIFT = (6.0, 1.5)


def explicit_rootsift(image: torch.Tensor, bin_size: int, step: int, max_bin_size: int) -> np.ndarray:
    """Per-point loops over cells: bilinear pooling of kornia's gradient histograms, Gaussian
    cell window (`VL_DSIFT`), SIFT normalisation with clipping at 0.2, then RootSIFT."""
    magnification, window_size = VL_DSIFT
    sigma = math.sqrt((bin_size / magnification) ** 2 - 0.25)
    size = 2 * math.ceil(3 * sigma) + 1
    smoothed = kornia.filters.gaussian_blur2d(image, (size, size), (sigma, sigma))
    histograms = kornia.feature.DenseSIFTDescriptor().get_gradient_histograms(smoothed)[0].double().numpy()
    _, height, width = histograms.shape
    first_y, rows = grid_layout(height, max_bin_size, step)
    first_x, cols = grid_layout(width, max_bin_size, step)
    window = [math.exp(-0.5 * ((cell - 1.5) / window_size) ** 2) for cell in range(4)]

    def bilinear(centre: int, length: int) -> np.ndarray:
        return np.maximum(0.0, 1.0 - np.abs(np.arange(length) - centre) / bin_size)

    out = []
    for row in range(rows):
        for col in range(cols):
            vector = []
            for cell_y in range(4):
                for cell_x in range(4):
                    y = first_y + row * step - (3 * bin_size) // 2 + cell_y * bin_size
                    x = first_x + col * step - (3 * bin_size) // 2 + cell_x * bin_size
                    weights = np.outer(bilinear(y, height), bilinear(x, width)) * window[cell_y] * window[cell_x]
                    vector.extend((histograms * weights).sum(axis=(1, 2)))
            vector = np.minimum(np.array(vector) / np.linalg.norm(vector), 0.2)
            vector /= np.linalg.norm(vector)
            out.append(np.sqrt(vector / vector.sum()))
    return np.array(out)


def test_gradient_histograms_equal_kornias():
    image = torch.from_numpy(texture(5, 80).astype(np.float32) / 255.0)[None, None].repeat(2, 1, 1, 1)
    image[1, :, 20:50, 10:60] = 0.25  # flat: zero gradients vote nowhere
    expected = kornia.feature.DenseSIFTDescriptor().get_gradient_histograms(image)
    histograms = gradient_histograms(image)
    assert histograms.shape == (2, 8, 80, 80) and histograms.is_contiguous(memory_format=torch.channels_last)
    np.testing.assert_allclose(histograms.numpy(), expected.numpy(), atol=2e-6)
    assert (histograms[1, :, 21:49, 11:59] == 0).all()


# (bin size, step, largest bin): the last puts the lattice origin on an odd pixel (3) with a
# stride of 2, where the first cells' triangles reach the image border at pixel 0.
LATTICES = [(4, 3, 6), (6, 3, 6), (8, 2, 10), (10, 2, 10)]


@pytest.mark.parametrize("bin_size, step, max_bin_size", LATTICES)
def test_dense_rootsift_matches_explicit_loops(bin_size, step, max_bin_size):
    image = torch.from_numpy(texture(7, 64)[:44, :52].astype(np.float32) / 255.0)[None, None]
    descriptors, contrast = dense_rootsift(image, bin_size, step, max_bin_size, *VL_DSIFT)
    expected = explicit_rootsift(image, bin_size, step=step, max_bin_size=max_bin_size)
    assert descriptors.shape == (1, len(expected), 128)
    np.testing.assert_allclose(descriptors[0].numpy(), expected, atol=2e-5)
    assert (contrast > 0).all()


@pytest.mark.parametrize("bin_size, step, max_bin_size", LATTICES)
def test_cpu_kernels_build_the_same_rootsift(bin_size, step, max_bin_size):
    image = torch.from_numpy(texture(7, 64)[:44, :52].astype(np.float32) / 255.0)[None]
    pooled, geometry = cpu_lattice(image, bin_size, step, max_bin_size, VL_DSIFT[0])
    window = window_weights(VL_DSIFT[1], torch.device("cpu")).numpy()
    descriptors, contrast = cpu_rootsift(pooled, geometry, slice(0, geometry.rows), window)
    np.testing.assert_allclose(descriptors, explicit_rootsift(image[None], bin_size, step, max_bin_size), atol=2e-5)
    expected_descriptors, expected_contrast = dense_rootsift(image[None], bin_size, step, max_bin_size, *VL_DSIFT)
    np.testing.assert_allclose(descriptors, expected_descriptors[0].numpy(), atol=1e-6)
    np.testing.assert_allclose(contrast, expected_contrast[0].numpy(), rtol=1e-5)
    # A few rows into a larger buffer: the same rows.
    buffer = np.full((5 * geometry.cols, 128), np.nan, np.float32)
    part, _ = cpu_rootsift(pooled, geometry, slice(2, 4), window, buffer)
    np.testing.assert_array_equal(part, descriptors[2 * geometry.cols : 4 * geometry.cols])


def test_dense_rootsift_is_nonnegative_unit_norm_and_zero_on_flat_images():
    images = torch.stack(
        [
            torch.from_numpy(texture(3, 96).astype(np.float32) / 255.0)[None],
            torch.full((1, 96, 96), 0.5),
        ]
    )
    descriptors, contrast = dense_rootsift(images, 8, 2, 10, *VL_DSIFT)
    first, count = grid_layout(96, 10, 2)
    assert (first, count) == (15, 33)
    assert descriptors.shape == (2, 33 * 33, 128)
    assert (descriptors[0] >= 0).all()
    np.testing.assert_allclose(descriptors[0].norm(dim=-1).numpy(), 1.0, atol=1e-5)
    # RootSIFT: the squares form an L1-normalised (non-negative) SIFT.
    np.testing.assert_allclose((descriptors[0] ** 2).sum(-1).numpy(), 1.0, atol=1e-5)
    assert (contrast[1] == 0).all() and (descriptors[1] == 0).all()


# -- VLAD -----------------------------------------------------------------------------------


def explicit_vlad(descriptors: np.ndarray, valid: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    residuals = np.zeros_like(centroids, dtype=np.float64)
    for descriptor, keep in zip(descriptors, valid):
        if keep:
            word = int(np.argmin(((descriptor - centroids) ** 2).sum(axis=1)))
            residuals[word] += descriptor - centroids[word]
    for word in range(len(centroids)):
        norm = np.linalg.norm(residuals[word])
        if norm > 0:
            residuals[word] /= norm
    vector = residuals.reshape(-1)
    return vector / np.linalg.norm(vector)


@pytest.mark.parametrize("cpu_kernels", [True, False])
def test_vlad_matches_explicit_loops(cpu_kernels):
    rng = np.random.default_rng(0)
    descriptors = rng.random((2, 40, 6))
    centroids = rng.random((5, 6))
    valid = rng.random((2, 40)) > 0.3
    valid[1, :] &= ~(np.arange(40) < 20)
    torch_inputs = [torch.from_numpy(a) for a in (descriptors, valid, centroids)]
    vlads = normalize_vlad(vlad_residuals(*torch_inputs, cpu_kernels=cpu_kernels)).numpy()
    for image in range(2):
        np.testing.assert_allclose(vlads[image], explicit_vlad(descriptors[image], valid[image], centroids), atol=1e-12)


@pytest.mark.parametrize("cpu_kernels", [True, False])
def test_assignment_takes_the_first_of_tied_words(cpu_kernels):
    centroids = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # words 0 and 1 are the same
    descriptors = torch.tensor([[[0.9, 0.1], [0.2, 0.8], [1.0, 0.0]]])
    residuals = vlad_residuals(descriptors, torch.ones(1, 3, dtype=torch.bool), centroids, cpu_kernels)[0]
    np.testing.assert_allclose(residuals.numpy(), [[-0.1, 0.1], [0.0, 0.0], [0.2, -0.2]], atol=1e-7)


def test_vlad_intra_normalisation_and_global_norm():
    rng = np.random.default_rng(1)
    centroids = torch.from_numpy(rng.normal(size=(4, 8)))
    # Only words 0 and 2 receive descriptors (each descriptor sits next to its word).
    descriptors = centroids[[0, 0, 2, 0, 2]][None] + 0.01 * torch.from_numpy(rng.normal(size=(1, 5, 8)))
    vlad = normalize_vlad(vlad_residuals(descriptors, torch.ones(1, 5, dtype=torch.bool), centroids))
    blocks = vlad.view(4, 8).norm(dim=-1).numpy()
    np.testing.assert_allclose(blocks, [2**-0.5, 0.0, 2**-0.5, 0.0], atol=1e-12)
    assert vlad.norm().item() == pytest.approx(1.0)


def test_a_word_is_settled_exactly_whatever_the_float32_product_says():
    """Word 2 is word 1 with one coordinate one float32 step larger: its score is ~1e-9 higher,
    beneath float32's resolution. The product's scores lean the other way (within their error
    bound); the word is the exact winner, found with Python's rational arithmetic."""
    rng = np.random.default_rng(3)
    centroids = rng.random((4, 128)).astype(np.float32)
    centroids /= np.linalg.norm(centroids, axis=1, keepdims=True)
    centroids[2] = centroids[1]
    centroids[2, 7] = np.nextafter(centroids[1, 7], np.float32(1))
    descriptors = np.stack([centroids[1] + 0.01 * rng.random(128, dtype=np.float32), centroids[3]])
    half_norms = np.zeros(4)
    scores = descriptors @ centroids.T
    scores[0, 1], scores[0, 2] = scores[0, 2] + 1e-7, scores[0, 2] - 1e-7  # word 1 ahead in float32
    sums, counts = np.zeros((4, 128)), np.zeros(4, dtype=np.int64)
    densevlad_kernels.assign_to_words(
        descriptors, scores, scores.argmax(1), centroids, half_norms, np.ones(2, dtype=bool), sums, counts
    )
    exact = [
        [sum(Fraction(float(a)) * Fraction(float(b)) for a, b in zip(row, c)) for c in centroids] for row in descriptors
    ]
    assert exact[0][2] > exact[0][1] and scores[0].argmax() == 1
    words = [int(np.argmax(row)) for row in exact]
    assert words == [2, 3]
    np.testing.assert_array_equal(counts, [0, 0, 1, 1])
    np.testing.assert_array_equal(sums[words], descriptors)


def reference_kmeans(points: np.ndarray, num_words: int, iterations: int, seed: int) -> tuple[np.ndarray, int]:
    """`kmeans_vocabulary`'s algorithm in plain numpy (float64 argmax over every word, ``np.add.at``
    sums), and how many words restarted empty."""
    rng = np.random.default_rng(seed)
    centroids = points[np.sort(rng.choice(len(points), num_words, replace=False))].astype(np.float64)
    centroids /= np.linalg.norm(centroids, axis=1, keepdims=True)
    restarts = 0
    for iteration in range(iterations):
        words = centroids.astype(np.float32).astype(np.float64)
        assignment = (points.astype(np.float64) @ words.T).argmax(1)
        sums = np.zeros_like(centroids)
        np.add.at(sums, assignment, points.astype(np.float64))
        empty = np.flatnonzero(np.bincount(assignment, minlength=num_words) == 0)
        sums[empty] = points[np.random.default_rng([seed, iteration]).choice(len(points), len(empty), replace=False)]
        restarts += len(empty)
        centroids = sums / np.linalg.norm(sums, axis=1, keepdims=True)
    return centroids.astype(np.float32), restarts


def test_kmeans_vocabulary_is_spherical_kmeans_with_restarts_of_empty_words():
    rng = np.random.default_rng(4)
    points = rng.random((3000, 16), dtype=np.float32)
    points[:1500] = points[0]  # the initial words are mostly copies of one point: all but one start empty
    centroids = kmeans_vocabulary(points, 12, 6, seed=5)
    expected, restarts = reference_kmeans(points, 12, 6, seed=5)
    assert restarts >= 3
    # the same assignments; float64 sums in another order: at most one float32 rounding apart
    np.testing.assert_array_max_ulp(centroids, expected, maxulp=1)
    np.testing.assert_allclose(np.linalg.norm(centroids, axis=1), 1.0, atol=1e-6)


def test_word_assignments_do_not_follow_the_order_of_the_float32_sums():
    """Descriptors halfway between two words (their scores ~1e-8 apart, below float32's resolution),
    scored by float32 products summed in two orders as two machines' BLAS kernels would: the
    argmaxes differ, the words `assign_to_words` settles do not, and they are plain float64's."""
    rng = np.random.default_rng(6)
    centroids = rng.random((16, 128), dtype=np.float32)
    centroids /= np.linalg.norm(centroids, axis=1, keepdims=True)
    pairs = rng.integers(0, 16, (2000, 2))
    descriptors = (0.5 * (centroids[pairs[:, 0]] + centroids[pairs[:, 1]])).astype(np.float32)
    half_norms = densevlad_kernels.half_squared_norms(centroids)
    blas = descriptors @ centroids.T - half_norms.astype(np.float32)
    backwards = np.zeros_like(blas)  # one product at a time, the last coordinate first
    for k in reversed(range(128)):
        backwards += descriptors[:, k, None] * centroids[None, :, k]
    backwards -= half_norms.astype(np.float32)
    assert (blas.argmax(1) != backwards.argmax(1)).sum() > 10

    exact = descriptors.astype(np.float64) @ centroids.astype(np.float64).T - half_norms
    top_two = np.sort(exact, axis=1)[:, -2:]
    assert (top_two[:, 1] - top_two[:, 0] > 1e-12).all()  # float64 tells every row's word apart
    expected_sums, words = np.zeros((16, 128)), exact.argmax(1)
    np.add.at(expected_sums, words, descriptors.astype(np.float64))
    for scores in (blas, backwards):
        sums, counts = np.zeros((16, 128)), np.zeros(16, dtype=np.int64)
        keep = np.ones(len(descriptors), dtype=bool)
        densevlad_kernels.assign_to_words(
            descriptors, scores, scores.argmax(1), centroids, half_norms, keep, sums, counts
        )
        np.testing.assert_array_equal(counts, np.bincount(words, minlength=16))
        np.testing.assert_array_equal(sums, expected_sums)


#: Another machine's kernels, emulated: OpenBLAS's for numpy (faiss's too), MKL's for torch's matrix
#: products (its code path for any CPU) and numba's code for a CPU without AVX2 or FMA (x86-64 only).
OTHER_MACHINE = {"OPENBLAS_CORETYPE": "Sandybridge", "MKL_CBWR": "COMPATIBLE", "NUMBA_CPU_NAME": "sandybridge"}
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")
KMEANS = """
import sys
import numpy as np
from locretrieval.models.published.vlad import kmeans_vocabulary
rng = np.random.default_rng(0)
points = rng.random((20_000, 128), dtype=np.float32) ** 4
points = np.sqrt(points / points.sum(1, keepdims=True)).astype(np.float32)  # RootSIFT-like
np.save(sys.argv[1], kmeans_vocabulary(points, 64, 25, seed=0))
"""


@pytest.mark.slow
@pytest.mark.skipif(platform.machine() != "x86_64", reason="the kernels emulated are x86-64 ones")
def test_the_vocabulary_does_not_depend_on_the_blas_kernels_or_the_thread_count(tmp_path):
    """The k-means in one process with 1 thread and this machine's kernels, in another with 2 threads
    and `OTHER_MACHINE`'s: the same centroids, bit for bit (faiss's k-means, single-threaded,
    gave other centroids on these points under OpenBLAS's Sandybridge kernels than under Haswell's
    or Zen's)."""
    vocabularies = []
    for threads, kernels in ((1, {}), (2, OTHER_MACHINE)):
        environment = {**os.environ, **{variable: str(threads) for variable in THREAD_VARIABLES}, **kernels}
        output = tmp_path / f"{threads}.npy"
        done = subprocess.run(
            [sys.executable, "-c", KMEANS, str(output)], env=environment, capture_output=True, text=True, timeout=300
        )
        assert done.returncode == 0, done.stderr[-2000:]
        vocabularies.append(np.load(output))
    assert vocabularies[0].shape == (64, 128)
    np.testing.assert_array_equal(vocabularies[0], vocabularies[1])


# -- the model -----------------------------------------------------------------------------


def fitted_arrays(model: DenseVLAD) -> dict[str, np.ndarray]:
    """What `fit` learned: vocabulary, PCA mean and whitening projection."""
    return {
        "centroids": model._centroids.cpu().numpy(),
        "pca_mean": model._pca_mean.cpu().numpy(),
        "pca_projection": model._pca_projection.cpu().numpy(),
    }


def test_fitted_model_shapes_norms_and_small_database_pca(textures_scene, fitted):
    state = fitted_arrays(fitted)
    assert state["centroids"].shape == (128, 128)
    np.testing.assert_allclose(np.linalg.norm(state["centroids"], axis=1), 1.0, atol=1e-5)
    # Six database images: at most 5 principal components instead of 4096.
    assert state["pca_projection"].shape == (128 * 128, 5) and state["pca_mean"].shape == (128 * 128,)
    largest = np.abs(state["pca_projection"]).argmax(axis=0)  # each component's sign: its largest entry positive
    assert (state["pca_projection"][largest, np.arange(5)] > 0).all()
    queries = fitted.describe(textures_scene.queries)
    assert queries.shape == (3, 5) and queries.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(queries, axis=1), 1.0, atol=1e-5)


def test_fit_and_describe_are_deterministic(textures_scene, fitted, caplog):
    again = small_densevlad()
    with caplog.at_level(logging.INFO, logger="locretrieval.models.published.densevlad"):
        again.fit(textures_scene.database)
    assert "6 database images support 5 PCA dimensions (configured 4096)" in caplog.text
    for name, value in fitted_arrays(fitted).items():
        np.testing.assert_array_equal(fitted_arrays(again)[name], value, err_msg=name)
    np.testing.assert_array_equal(again.describe(textures_scene.queries), fitted.describe(textures_scene.queries))


def test_database_descriptors_from_fit_equal_a_fresh_pass(textures_scene, fitted):
    # A subset has another fingerprint, so it is described afresh rather than taken from fit.
    recomputed = fitted.describe(textures_scene.database.subset(np.arange(5)))
    np.testing.assert_allclose(fitted.describe(textures_scene.database)[:5], recomputed, atol=1e-6)


def test_cpu_vlads_a_few_rows_at_a_time_equal_the_torch_whole_image_computation(monkeypatch, textures_scene, fitted):
    monkeypatch.setattr(densevlad, "CPU_CHUNK_POINTS", 50)  # many chunks per scale
    expected = []
    for index in range(len(textures_scene.queries)):
        image = fitted._load(textures_scene.queries, index)[None]
        residuals = 0
        for bin_size in fitted.bin_sizes:
            descriptors, contrast = dense_rootsift(
                image, bin_size, fitted.step, max(fitted.bin_sizes), fitted.magnification, fitted.window_size
            )
            kept = (contrast >= fitted.contrast_threshold) & (contrast > 0)
            residuals = residuals + vlad_residuals(descriptors, kept, fitted._centroids, cpu_kernels=False)
        expected.append(normalize_vlad(residuals)[0].numpy())
    np.testing.assert_allclose(fitted._vlads(textures_scene.queries), np.array(expected), atol=1e-6)


def test_small_images_keep_their_size_unless_upsampled(tmp_path):
    images = image_set(tmp_path, {"small.png": texture(1, 96)[:72], "large.png": texture(2, 256)[:192]})
    assert small_densevlad()._load(images, 0).shape == (1, 72, 96)
    assert small_densevlad(upsample=True)._load(images, 0).shape == (1, 96, 128)
    for upsample in (False, True):
        assert small_densevlad(upsample=upsample)._load(images, 1).shape == (1, 96, 128)
    assert small_densevlad().identity() != small_densevlad(upsample=True).identity()


def test_shifted_crops_retrieve_their_source_texture(textures_scene, fitted):
    database = fitted.describe(textures_scene.database)
    queries = fitted.describe(textures_scene.queries)
    ranking = search(queries, database, depth=3, name="densevlad", chunk_size=256)
    np.testing.assert_array_equal(ranking.indices[:, 0], [4, 0, 2])
    assert (ranking.scores[:, 0] > ranking.scores[:, 1] + 0.1).all()


def test_describe_scene_cache_hit_runs_nothing_and_leaves_the_model_unfitted(tmp_path, textures_scene):
    class Counting(DenseVLAD):
        describe_calls = 0

        def describe(self, images):
            Counting.describe_calls += 1
            return super().describe(images)

    first = small_densevlad(Counting)
    database, queries = describe_scene(first, textures_scene, tmp_path)
    assert Counting.describe_calls == 2
    fresh = small_densevlad(Counting)
    cached_database, cached_queries = describe_scene(fresh, textures_scene, tmp_path)
    assert Counting.describe_calls == 2
    np.testing.assert_array_equal(cached_database, database)
    np.testing.assert_array_equal(cached_queries, queries)
    with pytest.raises(RuntimeError, match="not fitted.*cache hit leaves the model unfitted"):
        fresh.describe(textures_scene.queries)


def test_contrast_threshold_drops_faint_regions_from_the_vlad(tmp_path, fitted):
    pixels = texture(5, 128)
    pixels[:, 64:] = 100 + np.arange(64)[None, :] // 16  # right half: a ramp of one grey level per 16 px
    images = image_set(tmp_path, {"half_faint.png": pixels})
    threshold = 0.1
    model = small_densevlad(bin_sizes=(4,), contrast_threshold=threshold)
    model._centroids = fitted._centroids
    vlad = model._vlads(images)[0]

    descriptors, contrast = dense_rootsift(
        torch.from_numpy(pixels / np.float32(255))[None, None], 4, model.step, 4, model.magnification, model.window_size
    )
    descriptors, contrast = descriptors[0].double().numpy(), contrast[0].numpy()
    faint = (contrast > 0) & (contrast < threshold)
    assert faint.sum() > 400 and (contrast >= threshold).sum() > 400
    centroids = fitted._centroids.double().numpy()
    np.testing.assert_allclose(vlad, explicit_vlad(descriptors, contrast >= threshold, centroids), atol=1e-5)
    with_faint = explicit_vlad(descriptors, contrast > 0, centroids)
    assert float(vlad @ with_faint) < 0.98  # keeping the faint descriptors gives another VLAD


def test_whitening_regularisation_bounds_the_gain_of_small_components(textures_scene, fitted):
    """With ``U``, ``lambda``: eigenvectors and eigenvalues of the centred database VLADs' Gram matrix,
    the whitened database descriptors have the cosine similarities of ``U diag(g) U^T`` with gains
    ``g_i = lambda_i / (lambda_i + r lambda_1)``; without regularisation all gains are 1 and the
    images become equidistant (cosine ``-1 / (N - 1)``)."""
    vlads = fitted._vlads(textures_scene.database).astype(np.float64)
    centred = vlads - vlads.mean(axis=0)
    eigenvalues, vectors = np.linalg.eigh(centred @ centred.T)
    eigenvalues, vectors = eigenvalues[::-1][:5], vectors[:, ::-1][:, :5]  # the N - 1 = 5 non-zero components
    grams = {}
    for regularization in (0.0, 1.0):
        model = small_densevlad(whitening_regularization=regularization)
        model.fit(textures_scene.database)
        descriptors = model.describe(textures_scene.database).astype(np.float64)
        gains = eigenvalues / (eigenvalues + regularization * eigenvalues[0])
        expected = (vectors * gains) @ vectors.T
        expected /= np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
        grams[regularization] = descriptors @ descriptors.T
        np.testing.assert_allclose(grams[regularization], expected, atol=1e-4, err_msg=f"r={regularization}")
    off_diagonal = ~np.eye(len(vlads), dtype=bool)
    np.testing.assert_allclose(grams[0.0][off_diagonal], -1 / (len(vlads) - 1), atol=1e-4)
    assert np.abs(grams[1.0] - grams[0.0]).max() > 5e-3  # well beyond the tolerance above


def test_resizing_makes_the_descriptor_resolution_independent(tmp_path, fitted):
    pixels = texture(11, 256)[:192, :256]
    images = image_set(
        tmp_path,
        {
            "full.png": pixels,
            "half.png": np.asarray(Image.fromarray(pixels).resize((128, 96), Image.BILINEAR)),
        },
    )
    full, half = fitted.describe(images)
    assert float(full @ half) > 0.9


def test_errors(tmp_path, textures_scene):
    with pytest.raises(RuntimeError, match="not fitted"):
        small_densevlad().describe(textures_scene.queries)
    with pytest.raises(ValueError, match="step must be positive"):
        small_densevlad(step=0)
    tiny = image_set(tmp_path, {"a.png": texture(1, 64), "b.png": texture(2, 64)})
    with pytest.raises(ValueError, match=r"a\.png .* too small for SIFT bins of 10 px"):
        small_densevlad(max_side=24).fit(tiny)
    flat = image_set(tmp_path / "flat", {name: np.full((64, 64), 90, np.uint8) for name in ("a.png", "b.png")})
    with pytest.raises(ValueError, match="fewer than the 128 visual words"):
        small_densevlad().fit(flat)
    with pytest.raises(ValueError, match="at least 2 database images"):
        small_densevlad().fit(textures_scene.database.subset(np.array([0])))


def test_runs_on_the_configured_device(textures_scene, fitted):
    if not torch.cuda.is_available():
        pytest.skip("no CUDA GPU on this machine")
    gpu = small_densevlad(device="cuda")
    gpu._centroids, gpu._pca_mean, gpu._pca_projection = (
        torch.from_numpy(array).cuda() for array in fitted_arrays(fitted).values()
    )
    np.testing.assert_allclose(gpu.describe(textures_scene.queries), fitted.describe(textures_scene.queries), atol=1e-3)


#: The fit and descriptors of `small_densevlad_options` in a process of its own, with ``threads`` torch
#: threads: a script importing DenseVLAD alone (this test module would import Lightning, Hydra and
#: kornia first, seconds of CPU for each process).
FIT = """
import pickle, sys
import numpy as np
import torch
from locretrieval.models import DenseVLAD
with open(sys.argv[1], "rb") as job:  # written by the test that started this process
    threads, options, scene = pickle.load(job)
torch.set_num_threads(threads)
model = DenseVLAD(**options)
model.fit(scene.database)
fitted = {"centroids": model._centroids, "pca_mean": model._pca_mean, "pca_projection": model._pca_projection}
fitted = {name: array.cpu().numpy() for name, array in fitted.items()}
np.savez(sys.argv[2], **fitted, vlads=model._vlads(scene.queries), queries=model.describe(scene.queries))
"""


@pytest.mark.slow
@pytest.mark.skipif(platform.machine() != "x86_64", reason="the kernels emulated are x86-64 ones")
def test_the_fit_and_the_descriptors_do_not_depend_on_the_machine_or_the_thread_count(textures_scene, tmp_path):
    """One process with 1 thread and this machine's kernels, one with 2 threads and another machine's
    (`OTHER_MACHINE`): the same dense RootSIFTs, vocabulary and VLADs, bit for bit (faiss's k-means,
    numba's fastmath and an argmax of torch's product each differed); the float64 PCA's eigenvectors
    follow LAPACK's kernels by ~1e-16, which may move a float32 value by one unit in the last place."""
    options = small_densevlad_options(vocabulary_samples=60_000)
    outcomes = []
    for threads, kernels in ((1, {}), (2, OTHER_MACHINE)):
        job, output = tmp_path / f"{threads}.pickle", tmp_path / f"{threads}.npz"
        job.write_bytes(pickle.dumps((threads, options, textures_scene)))
        done = subprocess.run(  # the kernels' variables set before any library loads
            [sys.executable, "-c", FIT, str(job), str(output)],
            env={**os.environ, **kernels},
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr[-2000:]
        with np.load(output) as arrays:
            outcomes.append(dict(arrays))
    for name in ("centroids", "vlads"):
        np.testing.assert_array_equal(outcomes[0][name], outcomes[1][name], err_msg=name)
    for name in ("pca_mean", "pca_projection", "queries"):
        np.testing.assert_allclose(outcomes[0][name], outcomes[1][name], rtol=0, atol=1e-6, err_msg=name)
