"""Global descriptors of a scene, validated and cached on disk."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from locretrieval.cache import cached_arrays, config_key
from locretrieval.models.base import NORM_TOLERANCE, GlobalDescriptor
from locretrieval.scene import ImageSet, Scene

log = logging.getLogger(__name__)


def validate_descriptors(model: GlobalDescriptor, images: ImageSet, descriptors: np.ndarray) -> np.ndarray:
    """``descriptors`` if they are ``float32 [len(images), D]``, finite and of unit L2 norm.

    Otherwise a ``ValueError`` names the model and the first offending image.
    """
    if not isinstance(descriptors, np.ndarray) or descriptors.ndim != 2 or len(descriptors) != len(images):
        shape = getattr(descriptors, "shape", type(descriptors).__name__)
        raise ValueError(f"model {model.name!r} returned {shape} descriptors for {len(images)} images; expected [N, D]")
    if descriptors.dtype != np.float32:
        raise ValueError(f"model {model.name!r} returned {descriptors.dtype} descriptors; expected float32")
    finite = np.isfinite(descriptors).all(axis=1)
    if not finite.all():
        bad = int(np.argmin(finite))
        raise ValueError(f"model {model.name!r}: descriptor of image {images.names[bad]!r} has non-finite values")
    norms = np.linalg.norm(descriptors, axis=1)
    off = np.abs(norms - 1.0) > NORM_TOLERANCE
    if off.any():
        bad = int(np.argmax(off))
        raise ValueError(
            f"model {model.name!r}: descriptor of image {images.names[bad]!r} has L2 norm {norms[bad]:.6f}, expected 1"
        )
    return descriptors


#: How an image set is described: ``model.describe``, or that work split over processes.
Describer = Callable[[ImageSet], np.ndarray]


def _describe(model: GlobalDescriptor, images: ImageSet, describe: Describer) -> np.ndarray | None:
    """Validated descriptors of ``images``; ``None`` for an empty set (nothing to run)."""
    return validate_descriptors(model, images, describe(images)) if len(images) else None


class SceneDescriptors(NamedTuple):
    """L2-normalised ``float32`` descriptors of a scene's ``database [N, D]`` and ``queries [Q, D]``."""

    database: np.ndarray
    queries: np.ndarray


def describe_scene(
    model: GlobalDescriptor, scene: Scene, cache_dir: Path | None, describe: Describer | None = None
) -> SceneDescriptors:
    """The descriptors of a scene's database and queries.

    The model is bound to the scene (`GlobalDescriptor.bind_scene`) and, when it learns
    from the database, fitted on the database first. With a ``cache_dir`` both arrays are
    stored in ``cache_dir/descriptors/<key>.npz``, the key hashing ``model.identity()`` (for a
    network, the content of its weights as they are in memory) and both image sets'
    fingerprints; a later call with the same key runs no model at all and leaves the model
    unfitted (only the descriptors are cached, not what `fit` learned). ``cache_dir=None``
    always describes. ``describe``: how an image set is described (``model.describe`` by
    default; training's validation splits it over its processes).
    """
    model.bind_scene(scene)
    key = config_key(
        model.identity(),
        scene.database.fingerprint(include_poses=False),
        scene.queries.fingerprint(include_poses=False),
    )
    path = None if cache_dir is None else Path(cache_dir) / "descriptors" / f"{key}.npz"
    arrays, hit = cached_arrays(path, lambda: _describe_scene(model, scene, describe or model.describe))
    if hit:
        log.info("descriptor cache hit for %r: %s", model.name, path)
    elif path is not None:
        log.info("descriptor cache miss for %r (key %s): descriptors cached in %s", model.name, key, path)
    return SceneDescriptors(arrays["database"], arrays["queries"])


def _describe_scene(model: GlobalDescriptor, scene: Scene, describe: Describer) -> dict[str, np.ndarray]:
    """Database and query descriptors (fitting on the database first)."""
    log.info("describing %s with %r", scene.name, model.name)
    if model.learns_from_database:
        model.fit(scene.database)
    database = _describe(model, scene.database, describe)
    queries = _describe(model, scene.queries, describe)
    if queries is None:
        queries = np.zeros((0, database.shape[1]), dtype=np.float32)
    elif queries.shape[1] != database.shape[1]:
        raise ValueError(
            f"model {model.name!r}: query descriptors have {queries.shape[1]} dimensions, "
            f"database ones {database.shape[1]}"
        )
    return {"database": database, "queries": queries}
