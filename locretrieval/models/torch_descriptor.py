"""`TorchGlobalDescriptor`: a `RetrievalNet` + its preprocessing + the extraction engine."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from locretrieval.cache import config_key, safe_name
from locretrieval.config import validated
from locretrieval.device import resolve_device
from locretrieval.models.base import GlobalDescriptor
from locretrieval.models.extraction import (
    ExtractionSettings,
    ExtractionStats,
    Preprocessing,
    extract_descriptors,
    network_device,
)
from locretrieval.models.files.weights import plain, save_checkpoint
from locretrieval.models.networks import RetrievalNet, WeightsInfo, state_sha256
from locretrieval.scene import ImageSet

log = logging.getLogger(__name__)

#: Bumped whenever a code change alters the descriptors (part of the cache key).
IMPLEMENTATION_VERSION = 1
#: Appended to the ranking name of a model with randomly initialised parameters.
RANDOM_INIT_SUFFIX = "_random-init"


class TorchGlobalDescriptor(GlobalDescriptor):
    """A `GlobalDescriptor` computed by a `RetrievalNet` through the extraction engine.

    With ``place``, the network is moved to ``extraction.device`` (channels-last on CUDA) when
    the model is built; `describe` then runs wherever the network is (a training loop may move it) and
    leaves it in the mode it found it. ``identity()`` holds the zoo model name, the
    architecture settings, where the weights came from (`WeightsInfo`), a hash of the
    network's current state dict (so a network changed in memory is never served stale
    descriptors from the cache), the preprocessing and the numeric precision. A model with
    random parameters carries `RANDOM_INIT_SUFFIX` in its name, so results say so.
    """

    model: ClassVar[str]

    def __init__(
        self,
        name: str,
        network: RetrievalNet,
        preprocessing: Preprocessing,
        architecture: Mapping[str, Any],
        weights: WeightsInfo,
        extraction: ExtractionSettings | Mapping[str, Any],
        place: bool = True,
    ) -> None:
        if weights.random_init:
            log.warning(
                "%s: %d parameters are randomly initialised (seed %s)",
                name,
                len(weights.random_parameters),
                weights.seed,
            )
            name = f"{name}{RANDOM_INIT_SUFFIX}"
        super().__init__(name)
        self.settings = validated(ExtractionSettings, extraction, "model.extraction")
        if place:
            device = resolve_device(self.settings.device)
            network = network.eval().to(device)
            network = network.to(memory_format=torch.channels_last) if device.type == "cuda" else network
        self.network = network
        self.preprocessing = preprocessing
        self.architecture = plain(dict(architecture))
        self.weights = weights
        self.last_stats: ExtractionStats | None = None

    @property
    def precision(self) -> str:
        device = network_device(self.network)
        return "float16-autocast" if self.settings.mixed_precision and device.type == "cuda" else "float32"

    def identity(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "version": IMPLEMENTATION_VERSION,
            "architecture": self.architecture,
            "weights": self.weights.identity(),
            "state_sha256": state_sha256(self.network),
            "preprocessing": self.preprocessing.identity(),
            "precision": self.precision,
        }

    def describe(self, images: ImageSet) -> np.ndarray:
        out = None
        if self.settings.memmap_dir is not None:
            key = config_key(self.identity(), images.fingerprint(include_poses=False))
            path = Path(self.settings.memmap_dir) / f"{safe_name(self.name)}-{key}.npy"
            path.parent.mkdir(parents=True, exist_ok=True)
            out = np.lib.format.open_memmap(
                path, mode="w+", dtype=np.float32, shape=(len(images), self.network.output_dim)
            )
        sizes = [(camera.width, camera.height) for camera in images.cameras]
        descriptors, self.last_stats = extract_descriptors(
            self.network, images.paths, self.preprocessing, self.settings, sizes, out, label=self.name
        )
        stats = self.last_stats
        log.info(
            "%s: %d images in %.1f s (%.2f img/s; decode %.1f s, resize %.1f s, forward %.1f s)",
            self.name,
            stats.images,
            stats.wall_s,
            stats.images / max(stats.wall_s, 1e-9),
            stats.decode_s,
            stats.resize_s,
            stats.forward_s,
        )
        return descriptors

    def save_checkpoint(self, path: str | os.PathLike, extra: Mapping[str, Any] | None = None) -> None:
        """Write the network as a plain locretrieval checkpoint the zoo loaders read back."""
        save_checkpoint(
            path, self.model, self.architecture, asdict(self.preprocessing), self.network.state_dict(), extra
        )


class NetworkDescriptor(TorchGlobalDescriptor):
    """A network its caller holds and changes (e.g. a training loop's): described on its own
    device and never moved; its identity hashes the current state dict, so descriptors cached
    for earlier weights are never served for new ones. ``extraction.device`` is not read."""

    model = "network"

    def __init__(
        self,
        name: str,
        network: RetrievalNet,
        preprocessing: Preprocessing,
        extraction: ExtractionSettings | Mapping[str, Any],
    ) -> None:
        super().__init__(name, network, preprocessing, {}, WeightsInfo(sha256=None), extraction, place=False)
