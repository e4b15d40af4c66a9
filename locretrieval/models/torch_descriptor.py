"""`TorchGlobalDescriptor`: a `RetrievalNet` + its preprocessing + the extraction engine."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from locretrieval.cache import config_key
from locretrieval.device import resolve_device
from locretrieval.models.base import GlobalDescriptor
from locretrieval.models.extraction import ExtractionSettings, ExtractionStats, Preprocessing, extract_descriptors
from locretrieval.models.heads import RetrievalNet
from locretrieval.models.weights import plain, save_checkpoint
from locretrieval.scene import ImageSet

log = logging.getLogger(__name__)

#: Bumped whenever a code change alters the descriptors (part of the cache key).
IMPLEMENTATION_VERSION = 1
#: Appended to the ranking name of a model with randomly initialised parameters.
RANDOM_INIT_SUFFIX = "_random-init"


@dataclass(frozen=True)
class WeightsInfo:
    """What the parameters came from: the weight file's SHA-256 and any random initialisation."""

    sha256: str | None
    random_parameters: tuple[str, ...] = ()
    seed: int | None = None

    @property
    def random_init(self) -> bool:
        return bool(self.random_parameters)

    def identity(self) -> dict[str, Any]:
        return {
            "sha256": self.sha256,
            "random_parameters": list(self.random_parameters),
            "seed": self.seed if self.random_init else None,
        }


def build_network(
    factory: Callable[[], RetrievalNet],
    state_dict: Mapping[str, torch.Tensor] | None,
    source: str,
    random_init: bool = False,
    seed: int = 0,
) -> tuple[RetrievalNet, tuple[str, ...]]:
    """The network with ``state_dict`` loaded, and the names of parameters left random.

    Without ``random_init`` every parameter must come from ``state_dict`` (the network is
    built empty, then filled: fast even for VGG16's 134M-parameter whitening). With it, the
    network is built with the seeded default initialisation and ``state_dict`` (if any)
    overrides what it holds. ``source`` names the weights in error messages.
    """
    if not random_init:
        if state_dict is None:
            raise ValueError(f"{source}: no weights to load; set model.random_init=true for random weights")
        with torch.device("meta"):
            network = factory()
        network.to_empty(device="cpu")
        for name, buffer in network.named_buffers():
            if name.endswith("num_batches_tracked"):
                buffer.zero_()
        missing = _load(network, state_dict, source)
        if missing:
            raise ValueError(
                f"{source}: holds no values for {len(missing)} parameters, e.g. {missing[:6]}; "
                "set model.random_init=true to initialise them randomly"
            )
        return network, ()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        network = factory()
    if state_dict is None:
        return network, tuple(name for name, _ in network.named_parameters())
    return network, tuple(_load(network, state_dict, source))


def _load(network: RetrievalNet, state_dict: Mapping[str, torch.Tensor], source: str) -> list[str]:
    """Load ``state_dict`` (no unexpected names allowed); return the parameters it lacks."""
    try:
        result = network.load_state_dict(dict(state_dict), strict=False)
    except RuntimeError as error:
        raise ValueError(f"{source}: does not fit the network: {error}") from error
    if result.unexpected_keys:
        raise ValueError(f"{source}: holds {len(result.unexpected_keys)} values the network has no place for, "
                         f"e.g. {result.unexpected_keys[:6]}")
    return [name for name in result.missing_keys if not name.endswith("num_batches_tracked")]


class TorchGlobalDescriptor(GlobalDescriptor):
    """A `GlobalDescriptor` computed by a `RetrievalNet` through the extraction engine.

    ``identity()`` holds the zoo model name, the architecture settings, the weight file's
    SHA-256 (or which parameters were randomly initialised, with the seed), the
    preprocessing and the numeric precision. A model with random parameters carries
    `RANDOM_INIT_SUFFIX` in its name, so results say so. ``memmap_dir``: write descriptors
    into ``.npy`` memory maps there instead of RAM. The zoo models take the fields of
    `ExtractionSettings` (``device``, ``batch_size``, ``num_workers``, ``mixed_precision``,
    ``progress``) as extra keyword arguments.
    """

    model: ClassVar[str]

    def __init__(
        self,
        name: str,
        network: RetrievalNet,
        preprocessing: Preprocessing,
        architecture: Mapping[str, Any],
        weights: WeightsInfo,
        settings: ExtractionSettings,
        memmap_dir: str | os.PathLike | None = None,
    ) -> None:
        if weights.random_init:
            log.warning("%s: %d parameters are randomly initialised (seed %s)", name, len(weights.random_parameters), weights.seed)
            name = f"{name}{RANDOM_INIT_SUFFIX}"
        super().__init__(name)
        self.network = network
        self.preprocessing = preprocessing
        self.architecture = plain(dict(architecture))
        self.weights = weights
        self.device = resolve_device(settings.device)
        self.settings = replace(settings, device=str(self.device))
        self.memmap_dir = None if memmap_dir is None else Path(memmap_dir)
        self.last_stats: ExtractionStats | None = None

    @property
    def precision(self) -> str:
        return "float16-autocast" if self.settings.mixed_precision and self.device.type == "cuda" else "float32"

    def identity(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "version": IMPLEMENTATION_VERSION,
            "architecture": self.architecture,
            "weights": self.weights.identity(),
            "preprocessing": self.preprocessing.identity(),
            "precision": self.precision,
        }

    def describe(self, images: ImageSet) -> np.ndarray:
        out = None
        if self.memmap_dir is not None:
            path = self.memmap_dir / f"{self.name}-{config_key(self.identity(), images.fingerprint(include_poses=False))}.npy"
            path.parent.mkdir(parents=True, exist_ok=True)
            out = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(len(images), self.network.output_dim))
        sizes = [(camera.width, camera.height) for camera in images.cameras]
        descriptors, self.last_stats = extract_descriptors(
            self.network, images.paths, self.preprocessing, self.settings, sizes, out, label=self.name
        )
        stats = self.last_stats
        log.info(
            "%s: %d images in %.1f s (%.2f img/s; decode %.1f s, resize %.1f s, forward %.1f s)",
            self.name, stats.images, stats.wall_s, stats.images / max(stats.wall_s, 1e-9),
            stats.decode_s, stats.resize_s, stats.forward_s,
        )
        return descriptors

    def save_checkpoint(self, path: str | os.PathLike, extra: Mapping[str, Any] | None = None) -> None:
        """Write the network as a plain locretrieval checkpoint the zoo loaders read back."""
        save_checkpoint(path, self.model, self.architecture, asdict(self.preprocessing), self.network.state_dict(), extra)

