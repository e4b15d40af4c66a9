"""Seconds per image pair of the local-feature matcher against the bare similarity product.

    .venv/bin/python benchmarks/bench_matching.py [--keypoints 2000 5000 20000] [--repeats 3]

For each keypoint count n: two images of n 128-D float32 descriptors (half of the second are
noisy copies of rows of the first, the rest distractors, as R2D2 or SIFT pairs with overlap),
and in the same process, on the same threads:

- ``bare``: the similarity product alone, ``torch.mm`` of the L2-normalised descriptors into a
  preallocated ``[n, n]`` output (no page faults: the GEMM's own speed on this machine);
- ``matcher``: `NearestNeighbourMatcher` as the SfM workers run it (normalisation, blocked
  product, mutual check, ratio test 0.8, numpy matches out);

with the best and median of ``--repeats`` runs and their ratio. On a CUDA machine the matcher
also runs on the GPU in float32 and float16 (pairs/s, and the share of float32's matches that
float16 reproduces); on the CPU float16 agreement is measured at the smallest size.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from locretrieval.localization.matching import NearestNeighbourMatcher, normalized_descriptors

DIMENSION = 128
RATIO = 0.8


def descriptor_pair(count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` descriptors each; half of the second image's are noisy copies of the first's."""
    first = rng.normal(size=(count, DIMENSION)).astype(np.float32)
    copies = rng.permutation(count)[: count // 2]
    second = np.concatenate([first[copies] + 0.5 * rng.normal(size=(len(copies), DIMENSION)),
                             rng.normal(size=(count - len(copies), DIMENSION))]).astype(np.float32)
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keypoints", type=int, nargs="+", default=[2000, 5000, 20000])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f"{platform.processor() or platform.machine()}, torch {torch.__version__} on {torch.get_num_threads()} threads; "
          f"matcher: CPU blocks of {NearestNeighbourMatcher(RATIO).block_bytes >> 20} MiB")
    print(f"{'keypoints':>9} | {'bare product s':>16} | {'matcher s/pair':>16} | {'ratio':>5} | matches")
    pairs = {}
    for count in args.keypoints:
        first, second = pairs[count] = descriptor_pair(count, rng)
        a, b = torch.from_numpy(normalized_descriptors(first)), torch.from_numpy(normalized_descriptors(second))
        output = torch.empty((count, count))
        bare = timed(lambda: torch.mm(a, b.T, out=output), args.repeats)
        matcher = NearestNeighbourMatcher(RATIO)
        matched = timed(lambda: matcher(first, [second]), args.repeats)
        found = len(matcher(first, [second])[0])
        print(f"{count:>9} | {bare[0]:7.3f} (med {bare[1]:5.3f}) | {matched[0]:7.3f} (med {matched[1]:5.3f}) | "
              f"{matched[0] / bare[0]:5.2f} | {found}", flush=True)
    smallest = min(args.keypoints)
    first, second = pairs[smallest]
    half = agreement(NearestNeighbourMatcher(RATIO)(first, [second])[0], NearestNeighbourMatcher(RATIO, precision="float16")(first, [second])[0])
    print(f"CPU float16 at {smallest} keypoints: {100 * half:.2f} % of float32's matches")
    if not torch.cuda.is_available():
        print("no CUDA GPU: GPU figures skipped")
        return
    print(f"GPU: {torch.cuda.get_device_name()}")
    for count in args.keypoints:
        first, second = pairs[count]
        on_cpu = NearestNeighbourMatcher(RATIO)(first, [second])[0]
        for precision in ("float32", "float16"):
            matcher = NearestNeighbourMatcher(RATIO, "cuda", precision, 1 << 30)
            best, median = timed(lambda: matcher(first, [second]), args.repeats, torch.cuda.synchronize)
            share = agreement(on_cpu, matcher(first, [second])[0])
            print(f"{count:>9} keypoints, {precision}: {1 / best:8.1f} pairs/s (median {1 / median:8.1f}); "
                  f"{100 * share:.2f} % of the CPU float32 matches")


if __name__ == "__main__":
    main()
