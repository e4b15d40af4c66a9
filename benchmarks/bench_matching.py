"""Pairs per second of local-feature matching against the naive torch matcher and the bare product.

    .venv/bin/python benchmarks/bench_matching.py [--keypoints 2000 5000 20000] [--repeats 3]
        [--partners 8] [--pipeline-images 6]

For each keypoint count n, on the device the SfM pipeline uses (a CUDA GPU when there is one,
else the CPU), in the same process:

- ``bare``: the similarity product alone, ``a @ b.T`` into a preallocated ``[n, n]`` output (the
  GEMM's own speed on this device: the floor);
- ``naive``: six lines of plain torch on the full matrix: ``s = a @ b.T``, ``s.topk(2, 1)``,
  ``s.max(0)``, the mutual check, the ratio test 0.8 (float32, and float16 on a GPU);
- ``matcher``: the project's matcher on this device, per pair: on a CPU the cache-blocked
  `NearestNeighbourMatcher` (numpy in, matches out); on a GPU the `BatchedMatcher` matching one
  image against ``--partners`` partners in one batched product, descriptors resident;
- ``pipeline``: `PairMatcher.ensure` over every pair of ``--pipeline-images`` images whose
  features are in a feature store: reading them, matching on this device, writing the matches
  (and on a GPU the CPU workers storing while the GPU matches), per pair.

Descriptors: two images of n 128-D float32 descriptors, half of the second noisy copies of rows of
the first, the rest distractors (as R2D2 or SIFT pairs with overlap). The share of the float32
matches that float16 reproduces is printed (on a GPU, for the batched matcher; on a CPU at the
smallest size).
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from locretrieval.config import validated
from locretrieval.device import resolve_device
from locretrieval.scene import Camera, ImageSet
from locretrieval.sfm.features import SiftFeatures, feature_store
from locretrieval.sfm.matching import MatchingSettings, PairMatcher
from locretrieval.sfm.nearest_neighbours import (
    CPU_BLOCK_BYTES,
    BatchedMatcher,
    NearestNeighbourMatcher,
    normalized_on_device,
)
from locretrieval.sfm.verification import NoVerification

DIMENSION = 128
RATIO = 0.8
#: Similarities of one batch of the GPU matchers compared here (1 GiB, one pair's product at 20,000 keypoints).
BATCH_BYTES = 1 << 30
CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def descriptor_pair(count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` descriptors each; half of the second image's are noisy copies of the first's."""
    first = rng.normal(size=(count, DIMENSION)).astype(np.float32)
    copies = rng.permutation(count)[: count // 2]
    second = np.concatenate(
        [
            first[copies] + 0.5 * rng.normal(size=(len(copies), DIMENSION)),
            rng.normal(size=(count - len(copies), DIMENSION)),
        ]
    ).astype(np.float32)
    return first, second


def timed(function, repeats: int, synchronize=lambda: None) -> tuple[float, float]:
    """Best and median seconds of ``repeats`` calls (after one warm-up call)."""
    function()
    synchronize()
    seconds = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        synchronize()
        seconds.append(time.perf_counter() - started)
    return min(seconds), float(np.median(seconds))


def agreement(reference: np.ndarray, other: np.ndarray) -> float:
    """Share of ``reference``'s matches that ``other`` has too."""
    common = {tuple(m) for m in reference.tolist()} & {tuple(m) for m in other.tolist()}
    return len(common) / max(1, len(reference))


def naive_matches(a: torch.Tensor, b: torch.Tensor, ratio: float) -> torch.Tensor:
    """The six lines of plain torch: the whole matrix, top 2 per row, best per column, mutual, ratio."""
    s = a @ b.T
    values, columns = s.topk(2, dim=1)
    back = s.max(0).indices
    keep = (back[columns[:, 0]] == torch.arange(len(a), device=a.device)) & (
        2 - 2 * values[:, 0] <= ratio**2 * (2 - 2 * values[:, 1])
    )
    return torch.stack([torch.nonzero(keep).squeeze(1), columns[keep, 0]], 1)


def pipeline_seconds(
    images: int, count: int, rng: np.random.Generator, device: str, precision: str
) -> tuple[float, int]:
    """Seconds per pair of `PairMatcher.ensure` over all pairs of ``images`` images of ``count``
    generated descriptors held in a feature store (raw matches written), and the pairs."""
    base = rng.normal(size=(count, DIMENSION)).astype(np.float32)
    camera = Camera("PINHOLE", 1024, 768, (500.0, 500.0, 512.0, 384.0))
    image_set = ImageSet(
        [f"db/{i:03d}.jpg" for i in range(images)],
        Path("/nonexistent"),
        [camera] * images,
        np.tile([1.0, 0.0, 0.0, 0.0], (images, 1)),
        np.zeros((images, 3)),
    )
    with tempfile.TemporaryDirectory(prefix="bench_matching-") as cache:
        store = feature_store(
            image_set, SiftFeatures(None, 640, 0, 4096, 0.0066667), cache
        )  # any key: the store is filled here
        for name in image_set.names:
            store.store.write(
                {
                    name: {
                        "keypoints": rng.uniform(0, 768, (count, 2)).astype(np.float32),
                        "descriptors": (base + 0.5 * rng.normal(size=base.shape)).astype(np.float32),
                    }
                }
            )
        matcher = PairMatcher(image_set, store, image_set, store, matching_settings(device, precision), cache)
        pairs = [(a, b) for a in image_set.names for b in image_set.names if a < b]
        started = time.perf_counter()
        matcher.ensure(pairs, 1, NoVerification())
        return (time.perf_counter() - started) / len(pairs), len(pairs)


def _config(section: str) -> dict:
    """A section of ``configs/sfm/default.yaml``."""
    return OmegaConf.to_container(OmegaConf.load(CONFIGS / "sfm" / "default.yaml")[section], resolve=False)


def matching_settings(device: str, precision: str) -> MatchingSettings:
    """The default matching settings on ``device`` with ``precision`` similarities."""
    return validated(
        MatchingSettings, {**_config("matching"), "device": device, "precision": precision}, "sfm.matching"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keypoints", type=int, nargs="+", default=[2000, 5000, 20000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--partners", type=int, default=8, help="partners of one image per batched product (GPU)")
    parser.add_argument(
        "--pipeline-images",
        type=int,
        default=None,
        help="images whose every pair the pipeline matches (default: 16 on a GPU, 4 on a CPU)",
    )
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    device = resolve_device("auto")
    on_gpu = device.type == "cuda"
    synchronize = torch.cuda.synchronize if on_gpu else (lambda: None)
    name = torch.cuda.get_device_name() if on_gpu else (platform.processor() or platform.machine())
    print(f"device: {device} ({name}), torch {torch.__version__} on {torch.get_num_threads()} threads")
    precisions = ("float32", "float16") if on_gpu else ("float32",)
    print(
        f"{'keypoints':>9} | {'precision':>9} | {'bare product':>12} | "
        f"{'naive torch':>11} | {'matcher':>9} | {'pipeline':>9} | pairs/s "
        "(best of repeats; bare, naive, matcher, pipeline)"
    )
    pairs = {}
    for count in args.keypoints:
        first, second = pairs[count] = descriptor_pair(count, rng)
        partners = [second] + [descriptor_pair(count, rng)[1] for _ in range(args.partners - 1)] if on_gpu else [second]
        for precision in precisions:
            dtype = getattr(torch, precision)
            a, b = (normalized_on_device(x, device, dtype) for x in (first, second))
            output = torch.empty((count, count), device=device, dtype=dtype)
            bare = timed(lambda: torch.mm(a, b.T, out=output), args.repeats, synchronize)[0]
            naive = timed(lambda: naive_matches(a, b, RATIO).cpu(), args.repeats, synchronize)[0]
            matcher = matching_settings(str(device), precision).matcher()
            if isinstance(matcher, BatchedMatcher):
                resident = [normalized_on_device(x, device, dtype) for x in partners]
                matched = timed(lambda: matcher.match(a, resident), args.repeats, synchronize)[0] / len(resident)
            else:
                matched = timed(lambda: matcher(first, [second]), args.repeats)[0]
            images = args.pipeline_images or (16 if on_gpu else 4)
            pipeline, _ = pipeline_seconds(images, count, rng, str(device), precision)
            print(
                f"{count:>9} | {precision:>9} | {1 / bare:12.1f} | "
                f"{1 / naive:11.1f} | {1 / matched:9.1f} | {1 / pipeline:9.1f} | "
                f"matcher: {matched / bare:.2f}x the bare product's time, "
                f"{naive / matched:.2f}x the naive matcher's speed",
                flush=True,
            )
    smallest = min(args.keypoints)
    first, second = pairs[smallest]
    if on_gpu:
        for count in args.keypoints:
            first, second = pairs[count]
            reference = BatchedMatcher(RATIO, str(device), "float32", BATCH_BYTES)(first, [second])[0]
            half = BatchedMatcher(RATIO, str(device), "float16", BATCH_BYTES)(first, [second])[0]
            cpu = NearestNeighbourMatcher(RATIO, "float32", CPU_BLOCK_BYTES)(first, [second])[0]
            print(
                f"{count} keypoints: float16 keeps {100 * agreement(reference, half):.2f} % of float32's matches; "
                f"GPU float32 keeps {100 * agreement(cpu, reference):.2f} % of the CPU's"
            )
    else:
        half = agreement(
            NearestNeighbourMatcher(RATIO, "float32", CPU_BLOCK_BYTES)(first, [second])[0],
            NearestNeighbourMatcher(RATIO, "float16", CPU_BLOCK_BYTES)(first, [second])[0],
        )
        print(f"CPU float16 at {smallest} keypoints: {100 * half:.2f} % of float32's matches")
        print("no CUDA GPU: the GPU figures (batched matcher, float16 floors) are not measured here")


if __name__ == "__main__":
    main()
