"""Training images decoded once, at the training resolution, into one memory-mapped file.

Decoding a JPEG and resizing it costs milliseconds per image; a training step draws each image
many times. `DecodedImages` decodes every training image once (RGB, resized to the training
size with the bilinear filter, as a step used to), in parallel threads (PIL releases the GIL
while it decodes and resizes), into ``<cache_dir>/decoded/<key>.npy``: ``uint8 [N, H, W, 3]``,
read back as a memory map, so every DataLoader worker shares the pages and a batch is a copy.

The key holds the images (their paths, sizes in bytes and modification times) and the training
size: a changed image gives another file, decoded again. Concurrent jobs (a Hydra multirun, DDP
ranks) share one file: the first to take its lock decodes it into a temporary file and renames it
into place; the others wait for the lock, then read it.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from filelock import FileLock
from PIL import Image

from locretrieval.cache import atomic_path, config_key, file_signature
from locretrieval.scene.images import read_image

log = logging.getLogger(__name__)

#: Bump when the meaning of decoded images changes.
CACHE_VERSION = 1


def decode(path: str | Path, size: Sequence[int]) -> np.ndarray:
    """``uint8 [height, width, 3]``: the image at ``path``, RGB, resized to ``size`` ``(width, height)`` (bilinear)."""
    return np.asarray(Image.fromarray(read_image(path)).resize((int(size[0]), int(size[1])), Image.Resampling.BILINEAR))


def decoded_images(
    paths: Sequence[str | Path], size: Sequence[int], cache_dir: str | Path, workers: int | None = None
) -> np.ndarray:
    """The images of ``paths`` decoded at ``size`` ``(width, height)``: a read-only memory map
    ``uint8 [N, height, width, 3]`` of the cache file, decoded first (``workers`` threads, null:
    one per core) unless another run already did."""
    width, height = int(size[0]), int(size[1])
    key = config_key(CACHE_VERSION, [width, height], [(str(Path(p).resolve()), *file_signature(p)) for p in paths])
    target = Path(cache_dir) / "decoded" / f"{key}.npy"
    target.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(f"{target}.lock"):
        if not target.is_file():
            log.info("decoding %d training images at %d x %d into %s", len(paths), width, height, target)
            with atomic_path(target) as temporary:
                out = np.lib.format.open_memmap(
                    temporary, mode="w+", dtype=np.uint8, shape=(len(paths), height, width, 3)
                )

                def fill(index: int) -> None:
                    out[index] = decode(paths[index], (width, height))

                with ThreadPoolExecutor(workers or os.cpu_count() or 1) as pool:
                    list(pool.map(fill, range(len(paths))))
                out.flush()
                del out
    return np.load(target, mmap_mode="r")
