"""The extraction engine: images -> `RetrievalNet` -> L2-normalised ``float32 [N, D]`` descriptors.

Images are decoded and resized in DataLoader workers (PIL, RGB), batched by size (each batch
holds images of one size; batches are formed from the image sizes the caller knows, e.g.
the cameras, and split again if a file's real size differs), sent to the network's device
as ``uint8``, normalised there (`Preprocessing.normalize`, which training batches go
through too), run at every scale the model declares, and written into a preallocated
``[N, D]`` array (or a caller's ``np.memmap``). Only the batches in flight are held in
memory, so the footprint does not grow with the number of images. The network is left as
it was found: on its device, in its memory layout, in train mode if it was.
"""

from __future__ import annotations

import contextlib
import itertools
import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from locretrieval.config import require
from locretrieval.models.networks import RetrievalNet, l2_normalize
from locretrieval.processes import dataloader_workers
from locretrieval.scene.images import read_image

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class Preprocessing:
    """How an image file becomes network input.

    ``max_side``: images whose longer side exceeds it are shrunk (aspect kept, sides rounded)
    with PIL's bilinear filter, which antialiases when shrinking; ``None`` keeps full size.
    ``size``: ``(width, height)`` every image is resized to instead (e.g. a network trained at
    a fixed size). ``multiple_of``: then each side is rounded to the nearest positive multiple
    (a ViT's patch size), at every scale too.
    ``scales``: the network runs on the image resized by each factor (bilinear, half-pixel
    centres, no antialiasing, as ``tf.image.resize``); per-scale descriptors are summed, then
    L2-normalised. Input is ``(rgb / 255 - mean) / std`` per RGB channel.
    """

    max_side: int | None = None
    scales: tuple[float, ...] = (1.0,)
    mean: tuple[float, ...] = IMAGENET_MEAN
    std: tuple[float, ...] = IMAGENET_STD
    size: tuple[int, int] | None = None
    multiple_of: int | None = None

    def __post_init__(self) -> None:
        for name in ("scales", "mean", "std"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        if self.max_side is not None:
            object.__setattr__(self, "max_side", int(self.max_side))
            if self.max_side <= 0:
                raise ValueError(f"max_side must be positive or null, got {self.max_side}")
        if self.size is not None:
            object.__setattr__(self, "size", tuple(int(v) for v in self.size))
            if len(self.size) != 2 or min(self.size) <= 0:
                raise ValueError(f"size must be [width, height] in pixels or null, got {list(self.size)}")
        if self.multiple_of is not None and int(self.multiple_of) <= 0:
            raise ValueError(f"multiple_of must be a positive number of pixels or null, got {self.multiple_of}")
        if not self.scales or min(self.scales) <= 0:
            raise ValueError(f"scales must be a non-empty list of positive factors, got {list(self.scales)}")
        if len(self.mean) != 3 or len(self.std) != 3 or min(self.std) <= 0:
            raise ValueError(f"mean and std need 3 values (RGB), std positive; got mean={self.mean}, std={self.std}")

    def target_size(self, width: int, height: int) -> tuple[int, int]:
        """``(width, height)`` after the ``size`` or ``max_side`` resize, in ``multiple_of`` steps."""
        longest = max(width, height)
        if self.size is not None:
            width, height = self.size
        elif self.max_side is not None and longest > self.max_side:
            factor = self.max_side / longest
            width, height = max(1, round(width * factor)), max(1, round(height * factor))
        return self._multiple(width), self._multiple(height)

    def scaled_size(self, height: int, width: int, scale: float) -> tuple[int, int]:
        """``(height, width)`` of an input of that size at ``scale``, in ``multiple_of`` steps."""
        return self._multiple(max(1, round(height * scale))), self._multiple(max(1, round(width * scale)))

    def _multiple(self, side: int) -> int:
        if self.multiple_of is None:
            return side
        step = int(self.multiple_of)
        return max(step, round(side / step) * step)

    def identity(self) -> dict[str, Any]:
        identity = {**asdict(self), "resize": "PIL bilinear to max_side; scales: bilinear half-pixel"}
        for key in ("size", "multiple_of"):  # unset: the identity (and cache keys) of before they existed
            if identity[key] is None:
                del identity[key]
        return identity

    def normalize(self, images: torch.Tensor) -> torch.Tensor:
        """``float32 [B, 3, H, W]`` network input ``(rgb / 255 - mean) / std`` of ``uint8`` RGB images
        (on their device)."""
        mean = torch.tensor(self.mean, device=images.device).view(1, 3, 1, 1) * 255.0
        std = torch.tensor(self.std, device=images.device).view(1, 3, 1, 1) * 255.0
        return (images.float() - mean) / std


@dataclass
class ExtractionSettings:
    """The ``model.extraction`` config node. ``device``: ``auto|cpu|cuda``, where a zoo model
    puts its network; ``batch_size`` images per forward pass (equal sizes only);
    ``num_workers`` DataLoader processes decoding and resizing; float16 autocast on CUDA when
    ``mixed_precision``; ``progress`` bars; ``memmap_dir``: write descriptors into ``.npy``
    memory maps there instead of RAM (``None``: RAM)."""

    device: str
    batch_size: int
    num_workers: int
    mixed_precision: bool
    progress: bool
    memmap_dir: str | None

    def __post_init__(self) -> None:
        require(
            self.device == "auto" or self.device.split(":")[0] in ("cpu", "cuda"),
            "device",
            f"must be auto, cpu or cuda[:N], got {self.device!r}",
        )
        require(self.batch_size >= 1, "batch_size", f"must be >= 1, got {self.batch_size}")
        require(self.num_workers >= 0, "num_workers", f"must be >= 0, got {self.num_workers}")


@dataclass
class ExtractionStats:
    """Where the time went. ``decode_s``/``resize_s`` are summed over images (they run in
    parallel when there are workers); ``forward_s`` is device time: transfer, normalisation,
    every scale and copying the result back; ``forward_calls`` counts network batches."""

    images: int = 0
    forward_calls: int = 0
    decode_s: float = 0.0
    resize_s: float = 0.0
    forward_s: float = 0.0
    wall_s: float = 0.0
    sizes: set[tuple[int, int]] = field(default_factory=set)


class LoadedImage(NamedTuple):
    index: int
    image: torch.Tensor  # uint8 [3, H, W]
    decode_s: float
    resize_s: float


class ImageFiles(Dataset):
    """Decodes (RGB) and shrinks image files to ``preprocessing.max_side``."""

    def __init__(self, paths: Sequence[Path], preprocessing: Preprocessing) -> None:
        self.paths = list(paths)
        self.preprocessing = preprocessing

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> LoadedImage:
        start = time.perf_counter()
        pixels = read_image(self.paths[index])
        decoded = time.perf_counter()
        height, width = pixels.shape[:2]
        size = self.preprocessing.target_size(width, height)
        if size != (width, height):
            pixels = np.asarray(Image.fromarray(pixels).resize(size, Image.Resampling.BILINEAR))
        resized = time.perf_counter()
        image = torch.from_numpy(np.require(pixels, requirements=["C", "W"])).permute(2, 0, 1)
        return LoadedImage(index, image, decoded - start, resized - decoded)


def size_batches(sizes: Sequence[tuple[int, int]], batch_size: int) -> list[list[int]]:
    """Batches of image indices sharing a size, sizes in order of first appearance."""
    groups: dict[tuple[int, int], list[int]] = {}
    for index, size in enumerate(sizes):
        groups.setdefault(tuple(size), []).append(index)
    return [group[i : i + batch_size] for group in groups.values() for i in range(0, len(group), batch_size)]


def _as_list(items: list[LoadedImage]) -> list[LoadedImage]:
    return items


def _split_by_shape(items: list[LoadedImage]) -> list[list[LoadedImage]]:
    groups: dict[tuple[int, ...], list[LoadedImage]] = {}
    for item in items:
        groups.setdefault(tuple(item.image.shape), []).append(item)
    return list(groups.values())


def describe_batch(
    network: RetrievalNet, images: torch.Tensor, preprocessing: Preprocessing, mixed_precision: bool = False
) -> torch.Tensor:
    """Unit descriptors ``float32 [B, D]`` of ``uint8 [B, 3, H, W]`` RGB images (on the network's
    device): normalise, run every scale, sum the per-scale descriptors, L2, ``finalize``.
    Gradients flow when the caller allows them (training); extraction runs it under
    ``torch.inference_mode``."""
    device = images.device
    x = preprocessing.normalize(images)
    if device.type == "cuda":
        x = x.contiguous(memory_format=torch.channels_last)
    total = None
    for scale in preprocessing.scales:
        scaled = x
        size = preprocessing.scaled_size(x.shape[2], x.shape[3], scale)
        if size != tuple(x.shape[2:]):
            scaled = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        with torch.autocast(device.type, dtype=torch.float16, enabled=mixed_precision and device.type == "cuda"):
            descriptors = network(scaled).float()
        total = descriptors if total is None else total + descriptors
    return network.finalize(l2_normalize(total)).float()


@contextlib.contextmanager
def evaluation_mode(network: torch.nn.Module) -> Iterator[None]:
    """The network in eval mode (frozen batch-norm statistics, no dropout); afterwards every
    module's own mode is restored (a network trained with frozen batch norm keeps it frozen)."""
    modes = [(module, module.training) for module in network.modules()]
    network.eval()
    try:
        yield
    finally:
        for module, training in modes:
            module.training = training


def network_device(network: torch.nn.Module) -> torch.device:
    """The device of a network's parameters (or buffers: a network of a plain function has one)."""
    return next(itertools.chain(network.parameters(), network.buffers())).device


def extract_descriptors(
    network: RetrievalNet,
    paths: Sequence[Path],
    preprocessing: Preprocessing,
    settings: ExtractionSettings,
    sizes: Sequence[tuple[int, int]] | None = None,
    out: np.ndarray | None = None,
    label: str = "describing",
) -> tuple[np.ndarray, ExtractionStats]:
    """Descriptors ``float32 [len(paths), network.output_dim]`` and timing statistics.

    Runs on the network's own device, in eval mode (restored afterwards); ``settings.device``
    is not read here (a zoo model placed its network at construction). ``sizes``:
    ``(width, height)`` of each file as stored (e.g. from the cameras), used to batch equal
    sizes together; without them every batch holds one image. ``out``: a preallocated
    ``float32 [N, D]`` array (e.g. ``np.lib.format.open_memmap``) to write into.
    """
    started = time.perf_counter()
    device = network_device(network)
    shape = (len(paths), network.output_dim)
    if out is None:
        out = np.empty(shape, dtype=np.float32)
    elif out.shape != shape or out.dtype != np.float32:
        raise ValueError(f"output array is {out.dtype} {out.shape}; expected float32 {shape}")
    if sizes is not None and len(sizes) != len(paths):
        raise ValueError(f"{len(sizes)} image sizes given for {len(paths)} images")
    batches = size_batches(sizes, settings.batch_size) if sizes is not None else [[i] for i in range(len(paths))]
    loader = DataLoader(
        ImageFiles(paths, preprocessing),
        batch_sampler=batches,
        **dataloader_workers(settings.num_workers),
        collate_fn=_as_list,
        pin_memory=device.type == "cuda",
    )
    stats = ExtractionStats()
    with (
        evaluation_mode(network),
        torch.inference_mode(),
        tqdm(total=len(paths), unit="img", desc=label, disable=not settings.progress) as bar,
    ):
        for items in loader:
            for group in _split_by_shape(items):
                start = time.perf_counter()
                images = torch.stack([item.image for item in group]).to(device, non_blocking=True)
                descriptors = describe_batch(network, images, preprocessing, settings.mixed_precision)
                out[[item.index for item in group]] = descriptors.cpu().numpy()
                stats.forward_s += time.perf_counter() - start
                stats.forward_calls += 1
                stats.sizes.add((images.shape[3], images.shape[2]))
            stats.images += len(items)
            stats.decode_s += sum(item.decode_s for item in items)
            stats.resize_s += sum(item.resize_s for item in items)
            bar.update(len(items))
    stats.wall_s = time.perf_counter() - started
    return out, stats
