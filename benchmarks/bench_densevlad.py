"""DenseVLAD speed: images/s of `describe` at its default settings.

    .venv/bin/python benchmarks/bench_densevlad.py [--images 16] [--sizes 480x360 640x480]
        [--max-side 640] [--upsample] [--step 2] [--device auto]

For each image size (default: the synthetic scene's 480x360 renders, which DenseVLAD keeps at
their size, and VGA 640x480, its largest size) writes random-texture images to a temporary
folder, fits the model on them (vocabulary + PCA, timed separately) and times `describe` on as
many other images; image decoding and resizing are included. Target (issue #13): >= 10 images/s.

Then the cost of the same numbers on every machine (issues #48, #68): the steps whose sums would
follow the thread count or the machine's kernels (the vocabulary's k-means, the PCA, the faiss
search) as shipped (assignments settled in float64, float64 PCA, fixed single-threaded units,
chunks in parallel threads) against faiss's own k-means and PCA and its search left to its
threads, at the published datasets' sizes, beside the bare product's GFLOP/s with every thread
(the machine's limit).
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from PIL import Image
from scipy.ndimage import gaussian_filter

import locretrieval  # noqa: F401
from locretrieval.models import DenseVLAD
from locretrieval.models.published.vlad import kmeans_vocabulary, pca_whitening
from locretrieval.retrieval.index import search
from locretrieval.scene import Camera, ImageSet

#: The model's config: its defaults.
CONFIG = Path(__file__).resolve().parents[1] / "configs" / "model" / "densevlad.yaml"


def texture_images(root: Path, prefix: str, count: int, width: int, height: int, seed: int) -> ImageSet:
    rng = np.random.default_rng(seed)
    names = []
    for index in range(count):
        noise = gaussian_filter(rng.random((height, width)), 2.0)
        pixels = (255 * (noise - noise.min()) / (noise.max() - noise.min())).astype(np.uint8)
        names.append(f"{prefix}/{index:04d}.png")
        (root / names[-1]).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(pixels).save(root / names[-1])
    camera = Camera("PINHOLE", width, height, (500.0, 500.0, width / 2, height / 2))
    return ImageSet(names, root, [camera] * count, np.tile([1.0, 0, 0, 0], (count, 1)), np.zeros((count, 3)))


def benchmark(args: argparse.Namespace, width: int, height: int) -> None:
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        database = texture_images(root, "db", args.images, width, height, seed=0)
        queries = texture_images(root, "query", args.images, width, height, seed=1)
        values = OmegaConf.to_container(OmegaConf.load(CONFIG))  # the model's defaults: its YAML
        values.pop("_target_")
        model = DenseVLAD(
            **{
                **values,
                "max_side": args.max_side,
                "upsample": args.upsample,
                "step": args.step,
                "batch_size": args.batch_size,
                "device": args.device,
            }
        )
        start = time.perf_counter()
        model.fit(database)
        fit_seconds = time.perf_counter() - start
        model.describe(queries.subset(np.arange(1)))  # warm-up
        if model.device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        descriptors = model.describe(queries)
        describe_seconds = time.perf_counter() - start

    print(
        f"device {model.device} ({torch.get_num_threads()} torch threads), images {width}x{height}, "
        f"max side {args.max_side}{' (upsampled)' if args.upsample else ''}, step {args.step} px, "
        f"bins {list(model.bin_sizes)}"
    )
    print(f"  fit on {args.images} images (vocabulary + PCA to {descriptors.shape[1]} dims): {fit_seconds:.2f} s")
    print(f"  describe {args.images} images: {describe_seconds:.2f} s = {args.images / describe_seconds:.2f} images/s")


def seconds(function) -> float:
    start = time.perf_counter()
    function()
    return time.perf_counter() - start


def invariance_cost(args: argparse.Namespace) -> None:
    """The thread-invariant steps against the libraries' own threading, on random data."""
    import faiss

    values = OmegaConf.to_container(OmegaConf.load(CONFIG))
    rng = np.random.default_rng(0)
    points = rng.standard_normal((values["vocabulary_samples"], 128)).astype(np.float32)
    vlads = rng.standard_normal((args.pca_images, values["num_words"] * 128)).astype(np.float32)
    queries = rng.standard_normal((args.search[0], values["pca_dim"])).astype(np.float32)
    database = rng.standard_normal((args.search[1], values["pca_dim"])).astype(np.float32)
    dim = min(values["pca_dim"], args.pca_images - 1)

    def threaded_kmeans() -> None:
        faiss.Kmeans(128, values["num_words"], niter=values["kmeans_iterations"], seed=0, spherical=True).train(points)

    def threaded_pca() -> None:
        faiss.PCAMatrix(vlads.shape[1], dim, 0.0, False).train(vlads)

    def threaded_search() -> None:
        index = faiss.IndexFlatIP(database.shape[1])
        index.add(database)
        index.search(queries, 50)

    bare = torch.from_numpy(queries), torch.from_numpy(database)
    product = seconds(lambda: bare[0] @ bare[1].T)
    gflop = 2 * queries.shape[0] * database.shape[0] * queries.shape[1] / 1e9
    print(
        f"machine invariance ({torch.get_num_threads()} threads; as shipped vs faiss with its own threads; "
        f"bare product {gflop / product:.0f} GFLOP/s):"
    )
    steps = {
        f"k-means ({len(points):,} x 128, {values['num_words']} words)": (
            lambda: kmeans_vocabulary(points, values["num_words"], values["kmeans_iterations"], 0),
            threaded_kmeans,
        ),
        f"PCA ({len(vlads):,} x {vlads.shape[1]:,} -> {dim})": (lambda: pca_whitening(vlads, dim, 1e-3), threaded_pca),
        f"search ({len(queries):,} x {len(database):,} x {queries.shape[1]:,}, {gflop:.0f} GFLOP)": (
            lambda: search(queries, database, 50, "bench", 256),
            threaded_search,
        ),
    }
    for label, (shipped, threaded) in steps.items():
        fixed, free = seconds(shipped), seconds(threaded)
        print(f"  {label}: {fixed:.2f} s as shipped, {free:.2f} s threaded ({fixed / free:.2f}x)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=16, help="database images, and as many described ones")
    parser.add_argument("--sizes", nargs="+", default=["480x360", "640x480"], help="WIDTHxHEIGHT of the images")
    parser.add_argument("--max-side", type=int, default=640)
    parser.add_argument("--upsample", action="store_true", help="enlarge smaller images to --max-side")
    parser.add_argument("--step", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=4)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--pca-images", type=int, default=1000, help="VLADs of the invariance PCA")
    parser.add_argument("--search", type=int, nargs=2, default=[1000, 5000], help="queries and database searched")
    args = parser.parse_args()
    for size in args.sizes:
        width, height = (int(value) for value in size.split("x"))
        benchmark(args, width, height)
    invariance_cost(args)


if __name__ == "__main__":
    main()
