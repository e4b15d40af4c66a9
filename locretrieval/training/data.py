"""Training batches from ground-truth relevance: images decoded once into a memory-mapped cache
(`locretrieval.training.decoded`), a sampler of anchors with positives and negatives (hard
negatives mined with the current network), augmentations that keep the pose, applied to the
whole batch on the training device."""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from locretrieval.config import require
from locretrieval.processes import dataloader_workers
from locretrieval.training.decoded import decoded_images
from locretrieval.training.relevance import TrainingPairs


@dataclass
class TrainingAugmentation:
    """Augmentations of training images that keep each image's pose (poses define relevance),
    applied in this order: with ``zoom_probability``, a zoom about the image centre by a factor
    in ``zoom`` (a longer focal length at the same pose: query cameras with a narrower field of
    view than the map's, which a network trained on the map's views alone retrieves as if they
    stood further forward, docs/results.md); ``brightness``/``contrast``/``saturation``/``hue``,
    torchvision ``ColorJitter`` ranges; with ``low_light_probability``, the brightness scaled by a
    factor in ``low_light_brightness`` (night queries of a day-only map); with
    ``blur_probability``, a Gaussian blur of sigma in ``blur_sigma`` (pixels); with
    ``noise_probability``, Gaussian noise of standard deviation ``noise_sigma`` (intensities in
    [0, 1]). Each image of a batch draws its own parameters (kornia, on the batch's device: the
    distributions of torchvision's per-image transforms, tested); the order of the four colour
    operations is drawn once per batch (kornia's), where torchvision draws it per image."""

    zoom_probability: float
    zoom: list[float]
    brightness: float
    contrast: float
    saturation: float
    hue: float
    low_light_probability: float
    low_light_brightness: list[float]
    blur_probability: float
    blur_sigma: list[float]
    noise_probability: float
    noise_sigma: float

    def __post_init__(self) -> None:
        for name in ("zoom_probability", "low_light_probability", "blur_probability", "noise_probability"):
            require(0 <= getattr(self, name) <= 1, name, f"must be in [0, 1], got {getattr(self, name)}")
        require(
            len(self.zoom) == 2 and 1 <= self.zoom[0] <= self.zoom[1],
            "zoom",
            f"must be [min, max] focal-length factors, 1 <= min <= max "
            f"(a zoom in keeps the image filled), got {self.zoom}",
        )
        require(
            len(self.low_light_brightness) == 2
            and 0 < self.low_light_brightness[0] <= self.low_light_brightness[1] <= 1,
            "low_light_brightness",
            f"must be [min, max] factors, 0 < min <= max <= 1, got {self.low_light_brightness}",
        )
        require(
            len(self.blur_sigma) == 2 and 0 < self.blur_sigma[0] <= self.blur_sigma[1],
            "blur_sigma",
            f"must be [min, max] pixels, 0 < min <= max, got {self.blur_sigma}",
        )
        require(self.noise_sigma >= 0, "noise_sigma", f"must be >= 0, got {self.noise_sigma}")

    def augment(self, images: torch.Tensor) -> torch.Tensor:
        """The augmented ``uint8 [B, 3, H, W]`` images (on their device), each its own draw."""
        if not len(images):
            return images
        augmented = self._pipeline().to(images.device)(images.float() / 255.0)
        return (augmented.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)

    def _pipeline(self) -> torch.nn.Module:
        import kornia.augmentation as K

        return K.AugmentationSequential(
            K.RandomAffine(degrees=0.0, scale=tuple(self.zoom), p=self.zoom_probability),
            K.ColorJitter(self.brightness, self.contrast, self.saturation, self.hue, p=1.0),
            K.ColorJitter(brightness=tuple(self.low_light_brightness), p=self.low_light_probability),
            K.RandomGaussianBlur((9, 9), sigma=tuple(self.blur_sigma), p=self.blur_probability),
            K.RandomGaussianNoise(mean=0.0, std=self.noise_sigma, p=self.noise_probability),
        )


class TrainingImages(Dataset):
    """Training images from the decoded cache (`decoded_images`: ``uint8 [N, H, W, 3]``), as ``uint8 [3, H, W]``."""

    def __init__(self, decoded: np.ndarray) -> None:
        self.decoded = decoded

    def __len__(self) -> int:
        return len(self.decoded)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, int]:
        return torch.from_numpy(np.array(self.decoded[index])).permute(2, 0, 1).contiguous(), index


class RelevanceBatchSampler(Sampler[list[int]]):
    """``batches_per_epoch`` batches of image indices: ``anchors`` images that have a positive,
    ``positives`` random positives of each (anchor by anchor; all of an anchor's, some twice, when
    it has fewer), then ``negatives`` more images. Several positives per anchor let a graded loss learn
    their order (the closest views first). An anchor's negatives are surely
    unrelated to it (`TrainingPairs`): its mined hard negatives when `set_hard_negatives` gave
    some, random ones otherwise. Each epoch draws new batches from ``seed`` and the epoch
    number (`set_epoch`)."""

    def __init__(
        self, pairs: TrainingPairs, *, anchors: int, negatives: int, batches_per_epoch: int, seed: int, positives: int
    ) -> None:
        require(anchors >= 1, "anchors", f"must be >= 1, got {anchors}")
        require(positives >= 1, "positives", f"must be >= 1, got {positives}")
        require(negatives >= 0, "negatives", f"must be >= 0, got {negatives}")
        require(batches_per_epoch >= 1, "batches_per_epoch", f"must be >= 1, got {batches_per_epoch}")
        self.pairs = pairs
        self.num_anchors, self.num_positives, self.num_negatives = anchors, positives, negatives
        self.batches_per_epoch = batches_per_epoch
        self.seed = seed
        self.epoch = 0
        self.anchors = np.flatnonzero(np.diff(pairs.graded.indptr) > 0)
        if not len(self.anchors):
            raise ValueError("no training image has a relevant partner: check the relevance thresholds and the poses")
        self.hard: dict[int, np.ndarray] = {}
        self.rank, self.world_size = 0, 1

    def shard(self, rank: int, world_size: int) -> None:
        """Under DDP: every rank draws the same batches and keeps every ``world_size``-th one."""
        self.rank, self.world_size = rank, world_size

    def __len__(self) -> int:
        return max(1, self.batches_per_epoch // self.world_size)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def set_hard_negatives(self, hard: dict[int, np.ndarray]) -> None:
        """``{anchor: images}`` ranked highest by the current network among its surely unrelated ones."""
        self.hard = hard

    def __iter__(self) -> Iterator[list[int]]:
        """The epoch's batches, built as they are asked for (hard negatives set meanwhile apply);
        every rank draws the same sequence and keeps every ``world_size``-th batch."""
        rng = np.random.default_rng([self.seed, self.epoch])
        for index in range(len(self) * self.world_size):
            batch = self._batch(rng)
            if index % self.world_size == self.rank:
                yield batch

    def _batch(self, rng: np.random.Generator) -> list[int]:
        anchors = rng.choice(self.anchors, size=min(self.num_anchors, len(self.anchors)), replace=False)
        chosen = list(anchors)
        for anchor in anchors:
            chosen.extend(self._positives(int(anchor), rng))
        for anchor in rng.choice(anchors, size=self.num_negatives):
            chosen.append(self._negative(int(anchor), rng))
        return [int(i) for i in chosen]

    def _positives(self, anchor: int, rng: np.random.Generator) -> np.ndarray:
        """``positives`` distinct positives of ``anchor``; all of them, some twice, when it has fewer."""
        candidates = self.pairs.positives(anchor)
        if len(candidates) >= self.num_positives:
            return rng.choice(candidates, size=self.num_positives, replace=False)
        return np.concatenate([candidates, rng.choice(candidates, size=self.num_positives - len(candidates))])

    def _negative(self, anchor: int, rng: np.random.Generator) -> int:
        hard = self.hard.get(anchor)
        if hard is not None and len(hard):
            return int(rng.choice(hard))
        related = set(self.pairs.related[anchor].indices) | {anchor}
        while True:
            candidate = int(rng.integers(self.pairs.num_images))
            if candidate not in related:
                return candidate


def collate(pairs: TrainingPairs):
    """The collate function of a batch: ``(images uint8 [B, 3, H, W], relevance [B, B], negatives
    [B, B], indices int64 [B])``, ``indices`` the images' rows in ``pairs``."""

    def stack(items: list[tuple[torch.Tensor, int]]) -> tuple[torch.Tensor, ...]:
        indices = np.array([index for _, index in items])
        relevance, negatives = pairs.batch(indices)
        images = torch.stack([image for image, _ in items])
        return images, torch.from_numpy(relevance), torch.from_numpy(negatives), torch.from_numpy(indices)

    return stack


class TrainingData(L.LightningDataModule):
    """The training images (``paths``, decoded once at ``image_size`` ``[width, height]`` into the
    cache of ``cache_dir``), batched by ``sampler`` and read by ``num_workers`` DataLoader
    processes (null: half the cores, at most 8), into pinned memory when training on a GPU; each
    batch is augmented by ``augmentation`` (when given) on the training device, after its transfer
    (validation is the `LocalizationValidation` callback's)."""

    def __init__(
        self,
        paths: Sequence[Path],
        pairs: TrainingPairs,
        sampler: RelevanceBatchSampler,
        augmentation: TrainingAugmentation | None,
        image_size: Sequence[int],
        num_workers: int | None,
        cache_dir: str | Path,
    ) -> None:
        require(
            len(image_size) == 2 and min(image_size) >= 32,
            "image_size",
            f"must be [width, height] >= 32 px, got {list(image_size)}",
        )
        require(num_workers is None or num_workers >= 0, "num_workers", f"must be >= 0 or null, got {num_workers}")
        super().__init__()
        self.paths, self.pairs, self.sampler, self.augmentation = list(paths), pairs, sampler, augmentation
        self.dataset = TrainingImages(decoded_images(self.paths, image_size, cache_dir))
        self.num_workers = num_workers if num_workers is not None else default_workers()

    def train_dataloader(self) -> DataLoader:
        on_gpu = False
        if self.trainer is not None:
            self.sampler.shard(self.trainer.global_rank, self.trainer.world_size)
            on_gpu = self.trainer.strategy.root_device.type == "cuda"
        return DataLoader(
            self.dataset,
            batch_sampler=self.sampler,
            collate_fn=collate(self.pairs),
            persistent_workers=self.num_workers > 0,
            **dataloader_workers(self.num_workers),
            pin_memory=on_gpu,
        )

    def on_after_batch_transfer(self, batch: tuple[torch.Tensor, ...], dataloader_idx: int) -> tuple[torch.Tensor, ...]:
        """Training batches augmented on their device (`TrainingAugmentation.augment`)."""
        if self.augmentation is None or self.trainer is None or not self.trainer.training:
            return batch
        images, *rest = batch
        return (self.augmentation.augment(images), *rest)


def default_workers() -> int:
    """DataLoader processes when ``num_workers`` is null: half the cores, at least 1, at most 8
    (they copy decoded images; the augmentation runs on the training device)."""
    return max(1, min(8, (os.cpu_count() or 2) // 2))
