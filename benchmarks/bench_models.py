"""Global-descriptor extraction speed: images/s, decode+resize vs forward share, peak memory.

Each model runs in its own process (so peak memory is its own) on synthetic JPEGs, with the
preprocessing of its ``configs/model/<name>.yaml`` (max side, scales, batch size) and random
weights (speed does not depend on the values). One warm-up image, then the timed run.

    .venv/bin/python benchmarks/bench_models.py [--images 4] [--size 1600x1200] [--device auto]
        [--workers 0 2] [--models netvlad apgem delg gem]
"""

import argparse
import multiprocessing
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

import locretrieval  # noqa: F401

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "model"


def build(name: str):
    """The model's network (random weights) and its config file."""
    if name == "netvlad":
        from locretrieval.models.published.netvlad import build_netvlad_network

        return build_netvlad_network(64, 4096), "netvlad.yaml"
    if name == "apgem":
        from locretrieval.models.published.apgem import build_apgem_network

        return build_apgem_network("resnet101", 2048), "apgem.yaml"
    if name == "delg":
        from locretrieval.models.published.delg import build_delg_network

        return build_delg_network(), "delg.yaml"
    if name == "gem":
        from locretrieval.models.networks import build_retrieval_net
        from locretrieval.models.trainable.backbones import TorchvisionBackbone

        return build_retrieval_net(
            TorchvisionBackbone("resnet50"),
            {"_target_": "locretrieval.models.networks.GeMPooling", "p": 3.0, "trainable": True},
        ), "gem.yaml"
    raise ValueError(f"unknown model {name!r}")


def measure(name: str, paths: list[Path], sizes: list[tuple[int, int]], device: str, workers: int, results) -> None:
    import torch
    from omegaconf import OmegaConf

    from locretrieval.device import resolve_device
    from locretrieval.models.extraction import ExtractionSettings, Preprocessing, extract_descriptors

    network, config_file = build(name)
    config = OmegaConf.load(CONFIGS / config_file)
    extraction = OmegaConf.merge(OmegaConf.load(CONFIGS / "extraction" / "default.yaml"), config.get("extraction", {}))
    preprocessing = Preprocessing(max_side=config.max_side, scales=tuple(config.scales))
    settings = ExtractionSettings(device, int(extraction.batch_size), workers, True, False, None)
    network = network.to(resolve_device(device))
    extract_descriptors(network, paths[:1], preprocessing, settings, sizes[:1])
    _, stats = extract_descriptors(network, paths, preprocessing, settings, sizes)
    cuda = torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None
    results.put(
        {
            "model": name,
            "device": str(resolve_device(device)),
            "workers": workers,
            "input": ", ".join(f"{w}x{h}" for w, h in sorted(stats.sizes)),
            "scales": len(preprocessing.scales),
            "images_per_s": stats.images / stats.wall_s,
            "decode_s": stats.decode_s,
            "resize_s": stats.resize_s,
            "forward_s": stats.forward_s,
            "wall_s": stats.wall_s,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "cuda_peak_mib": cuda,
        }
    )


def write_images(folder: Path, count: int, width: int, height: int) -> list[Path]:
    rng = np.random.default_rng(0)
    paths = []
    for i in range(count):
        ramp = np.linspace(0, 255, width)[None, :, None] * np.linspace(0.3, 1.0, height)[:, None, None]
        pixels = np.clip(ramp + rng.normal(0, 25, size=(height, width, 3)), 0, 255).astype(np.uint8)
        paths.append(folder / f"{i:03d}.jpg")
        Image.fromarray(pixels).save(paths[-1], quality=90)
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=4)
    parser.add_argument("--size", default="1600x1200", help="WIDTHxHEIGHT of the synthetic JPEGs")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 2])
    parser.add_argument("--models", nargs="+", default=["netvlad", "apgem", "delg", "gem"])
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))

    context = multiprocessing.get_context("spawn")
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        paths = write_images(Path(folder), args.images, width, height)
        for name in args.models:
            for workers in args.workers:
                results = context.Queue()
                started = time.perf_counter()
                process = context.Process(
                    target=measure, args=(name, paths, [(width, height)] * len(paths), args.device, workers, results)
                )
                process.start()
                row = results.get()
                process.join()
                rows.append(row)
                print(f"{name} (workers={workers}) done in {time.perf_counter() - started:.0f} s", flush=True)

    print(f"\n{args.images} JPEGs of {width}x{height}; shares of summed decode + resize + forward time\n")
    print(
        "| model | device | workers | network input | scales | images/s "
        "| decode | resize | forward | peak RSS (MiB) | peak CUDA (MiB) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        total = r["decode_s"] + r["resize_s"] + r["forward_s"]
        cuda = "-" if r["cuda_peak_mib"] is None else f"{r['cuda_peak_mib']:.0f}"
        print(
            f"| {r['model']} | {r['device']} | {r['workers']} | "
            f"{r['input']} | {r['scales']} | {r['images_per_s']:.3f} | "
            f"{r['decode_s'] / total:.0%} | {r['resize_s'] / total:.0%} | {r['forward_s'] / total:.0%} | "
            f"{r['peak_rss_mib']:.0f} | {cuda} |"
        )


if __name__ == "__main__":
    main()
