"""The interface every global descriptor implements."""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any

import numpy as np

from locretrieval.scene import ImageSet, Scene

#: Tolerance on the L2 norm of every descriptor row (`validate_descriptors` enforces it).
NORM_TOLERANCE = 1e-3


class GlobalDescriptor(abc.ABC):
    """Maps images to L2-normalised ``float32`` global descriptors ``[N, D]``.

    ``name`` labels the ranking in results. ``identity()`` returns everything that
    determines the output (configuration, weight-file hash, preprocessing); the descriptor
    cache is keyed by it. Models with data-dependent parts (DenseVLAD's vocabulary and PCA)
    set ``learns_from_database`` and learn them in ``fit``, so their cache key also depends
    on the database. The cache stores descriptors only: a model that `describe_scene` served
    from the cache is not fitted.
    """

    learns_from_database: bool = False

    def __init__(self, name: str) -> None:
        self.name = name

    def bind_scene(self, scene: Scene) -> None:
        """Take scene-level side data the model reads besides the images, e.g. published
        feature files under ``scene.sources`` (default: nothing). Called before `identity`."""

    def missing_inputs(self, scene: Scene) -> list[str]:
        """The files it reads for ``scene`` that are absent, each ``<its key>: <problem>``, checked
        before any work (default: none; a weight file is read when the model is built)."""
        return []

    def rankings(self, scene: Scene, search: Callable[[GlobalDescriptor, Scene], Any]) -> list[Any]:
        """Its rankings of ``scene``'s queries (`locretrieval.retrieval.Ranking`): its descriptors
        searched by ``search`` (`locretrieval.retrieval.descriptors.DescriptorSearch`: described,
        cached, the top ``retrieval.depth`` database images of each query)."""
        return [search(self, scene)]

    def fit(self, database: ImageSet) -> None:
        """Learn data-dependent parameters on the database images (default: nothing)."""

    @abc.abstractmethod
    def describe(self, images: ImageSet) -> np.ndarray:
        """Descriptors ``float32 [len(images), D]``, each row of unit L2 norm."""

    @abc.abstractmethod
    def identity(self) -> dict[str, Any]:
        """JSON-serialisable description of what produces the descriptors."""
