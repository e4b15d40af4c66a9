"""Gallery speed: the report's galleries of every query (``report.gallery.queries=all``), top 5.

    .venv/bin/python benchmarks/bench_gallery.py [--queries 1000] [--database 1000] [--size 1024x768]

Writes JPEG images of the given size (smooth noise, like photos in file size) and a run folder
holding what galleries read (``images.csv``, a descriptor ranking, relevance, per-query errors),
then times `gallery_section` twice in this process: cold (every thumbnail made and cached on disk)
and warm (a new `Thumbnails` reading the disk cache, as a rebuilt report or a second run does).
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image
from scipy import sparse

import locretrieval  # noqa: F401
from locretrieval.cache import save_arrays
from locretrieval.report.gallery import GallerySettings, gallery_section, write_gallery_inputs
from locretrieval.report.markdown import ReportWriter
from locretrieval.scene import Camera, ImageSet, Scene


def write_images(folder: Path, count: int, size: tuple[int, int], rng: np.random.Generator) -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"{i:06d}.jpg" for i in range(count)]
    for name in names:
        small = rng.integers(0, 256, size=(size[1] // 32, size[0] // 32, 3), dtype=np.uint8)
        Image.fromarray(small).resize(size, Image.Resampling.BILINEAR).save(folder / name, quality=90)
    return names


def image_set(root: Path, names: list[str], size: tuple[int, int]) -> ImageSet:
    camera = Camera("SIMPLE_PINHOLE", size[0], size[1], (size[0] * 0.8, size[0] / 2, size[1] / 2))
    return ImageSet(
        names, root, [camera] * len(names), np.tile([1.0, 0, 0, 0], (len(names), 1)), np.zeros((len(names), 3))
    )


def write_run(run: Path, scene: Scene, rng: np.random.Generator, depth: int = 50) -> None:
    """A descriptor ranking, a relevance matrix and the approximation paradigm's errors at k=5."""
    num_queries, num_database = len(scene.queries), len(scene.database)
    indices = np.argsort(rng.random((num_queries, num_database)), axis=1)[:, :depth]
    save_arrays(run / "rankings" / "bench.npz", {"indices": indices, "kind": np.asarray("descriptor")})
    write_gallery_inputs(
        scene, {"relative_pose": sparse.csr_matrix(rng.random((num_queries, num_database)) < 0.01)}, run
    )
    position = rng.exponential(2.0, num_queries)
    pd.DataFrame({
        "dataset": "bench", "ranking": "bench", "ranking_kind": "descriptor", "paradigm": "approximation",
        "method": "ewb", "k": 5, "query": scene.queries.names, "position_error_m": position,
        "rotation_error_deg": 3 * position, "failure": "",
    }).to_csv(run / "query_errors.csv.gz", index=False)  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=1000)
    parser.add_argument("--database", type=int, default=1000)
    parser.add_argument("--size", default="1024x768", help="image width x height")
    parser.add_argument("--k", type=int, default=5)
    args = parser.parse_args()
    size = tuple(int(value) for value in args.size.split("x"))
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        started = time.perf_counter()
        database = write_images(root / "images" / "db", args.database, size, rng)
        queries = write_images(root / "images" / "query", args.queries, size, rng)
        print(
            f"{args.database + args.queries} JPEG images of {args.size} "
            f"written in {time.perf_counter() - started:.1f} s"
        )
        scene = Scene(
            "bench",
            image_set(root / "images" / "db", database, size),
            image_set(root / "images" / "query", queries, size),
        )
        write_run(root / "run", scene, rng)
        settings = GallerySettings("all", args.k, 0, 0, 0, 160)
        for label in ("cold (thumbnails made)", "warm (thumbnails from the disk cache)"):
            writer = ReportWriter(root / "report", "bench")
            started = time.perf_counter()
            gallery_section(
                writer, [root / "run"], "relative_pose", settings, (5.0, 10.0), root / "thumbnails", [root / "images"]
            )
            writer.write(root / "report" / "report.md")
            elapsed = time.perf_counter() - started
            print(
                f"galleries of {args.queries} queries x top {args.k}, {label}: {elapsed:.2f} s "
                f"({1000 * elapsed / args.queries:.2f} ms per query)"
            )


if __name__ == "__main__":
    main()
