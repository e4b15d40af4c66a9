"""Blurry and dynamic-scene query subsets (paper Sec. 4.3).

**Blur.** The paper follows pyimagesearch's FFT blur detector ("mean absolute difference
between the original image and its reconstructed version when removing the high
frequencies ... threshold of 20"). Implemented exactly as that detector: the image is
resized to ``width`` = 500 pixels wide (aspect ratio kept, height ``int(h * 500 / w)``,
area averaging), converted to 8-bit grayscale (ITU-R 601 luma, ``0.299 R + 0.587 G +
0.114 B``), Fourier transformed, the centred ``2 radius x 2 radius`` square of lowest
frequencies (``radius`` = 60 bins, DC included) is zeroed, and the inverse transform is the
*high-pass residual*. Since the transform is linear, that residual is exactly the
difference between the image and its low-frequency reconstruction, which is the paper's
"difference". The score is the mean over pixels of ``20 ln |residual|`` (natural log, as
the reference code; an exactly flat image scores ``-inf``). Low scores mean little
high-frequency content: an image is **blurry when score <= threshold** (20, the reference
code's default and the paper's value).

**Dynamic scenes.** The fraction of pixels on dynamic objects, from per-image masks
(``ImageSet.mask_paths``: non-zero on dynamic objects, e.g. the synthetic scene's exact
masks) or from torchvision's Mask R-CNN (ResNet-50 FPN, COCO weights read from a local
file): the union of the masks (probability >= ``mask_threshold``) of detections scoring
>= ``score_threshold`` whose class is in `DYNAMIC_CATEGORIES`. An image is a **dynamic
scene when fraction >= 0.2**.
"""

from __future__ import annotations

import logging
import os
import pickle
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from PIL import Image
from tqdm import tqdm

from locretrieval.cache import cached_arrays, config_key, file_signature
from locretrieval.config import require
from locretrieval.scene import ImageSet
from locretrieval.scene.images import read_image

log = logging.getLogger(__name__)

#: Bump when the meaning of cached scores changes.
CACHE_VERSION = 1

#: Names of the subsets `subset_masks` returns (distinct from the synthetic scene's tags).
BLURRY = "blurry"
DYNAMIC_SCENE = "dynamic_scene"

#: COCO classes counted as dynamic: the paper names persons, vehicles ("car"), animals and
#: "objects"; we read objects as the things people carry (COCO's accessory and sports
#: super-categories) and leave out furniture, appliances and other static indoor classes.
DYNAMIC_CATEGORIES = (
    # person
    "person",
    # vehicle
    "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    # animal
    "bird", "cat", "dog", "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe",
    # accessory
    "backpack", "umbrella", "handbag", "tie", "suitcase",
    # sports
    "frisbee", "skis", "snowboard", "sports ball", "kite", "baseball bat", "baseball glove",
    "skateboard", "surfboard", "tennis racket",
)  # fmt: skip

MASKRCNN_WEIGHTS_FILE = "maskrcnn_resnet50_fpn_coco-bf2d0c1e.pth"

#: Columns of the per-image table (``subsets.csv``), before one boolean column per subset.
SUBSET_COLUMNS = ["dataset", "image", "blur_score", "dynamic_fraction", "mask_source"]

#: Mask sources of ``configs/subsets``.
MASK_SOURCES = ("auto", "masks", "maskrcnn", "none")


@dataclass
class SubsetSettings:
    """The ``subsets`` config group (``configs/subsets/default.yaml`` documents each key)."""

    enabled: bool
    blur_threshold: float
    blur_radius: int
    blur_width: int
    dynamic_fraction: float
    mask_source: str
    maskrcnn_weights: str | None
    maskrcnn_min_size: int
    maskrcnn_score_threshold: float
    maskrcnn_mask_threshold: float

    def __post_init__(self) -> None:
        require(self.blur_radius >= 1, "blur_radius", f"must be >= 1 frequency bin, got {self.blur_radius}")
        require(
            self.blur_width > 2 * self.blur_radius,
            "blur_width",
            f"must exceed twice blur_radius ({2 * self.blur_radius}), got {self.blur_width}",
        )
        require(0 <= self.dynamic_fraction <= 1, "dynamic_fraction", f"must be in [0, 1], got {self.dynamic_fraction}")
        require(
            self.mask_source in MASK_SOURCES,
            "mask_source",
            f"must be one of {list(MASK_SOURCES)}, got {self.mask_source!r}",
        )
        require(
            self.mask_source != "maskrcnn" or bool(self.maskrcnn_weights),
            "maskrcnn_weights",
            f"mask_source=maskrcnn needs the path of torchvision's {MASKRCNN_WEIGHTS_FILE}",
        )
        require(
            self.maskrcnn_min_size >= 32, "maskrcnn_min_size", f"must be >= 32 pixels, got {self.maskrcnn_min_size}"
        )
        for name in ("maskrcnn_score_threshold", "maskrcnn_mask_threshold"):
            require(0 <= getattr(self, name) <= 1, name, f"must be in [0, 1], got {getattr(self, name)}")


def blur_score(image: np.ndarray, radius: int = 60, width: int = 500) -> float:
    """FFT blur score of an RGB ``uint8 [H, W, 3]`` image (module docstring); higher is sharper."""
    height = int(image.shape[0] * width / image.shape[1])
    gray = np.asarray(
        Image.fromarray(image).resize((width, height), Image.Resampling.BOX).convert("L"), dtype=np.float64
    )
    spectrum = np.fft.fftshift(np.fft.fft2(gray))
    cy, cx = height // 2, width // 2
    spectrum[max(cy - radius, 0) : cy + radius, max(cx - radius, 0) : cx + radius] = 0
    residual = np.fft.ifft2(np.fft.ifftshift(spectrum))
    with np.errstate(divide="ignore"):
        return float(np.mean(20.0 * np.log(np.abs(residual))))


def blur_scores(images: ImageSet, radius: int = 60, width: int = 500) -> np.ndarray:
    """`blur_score` of every image ``[N]``."""
    return np.array(
        [
            blur_score(read_image(path), radius, width)
            for path in tqdm(images.paths, desc="blur", unit="image", disable=None)
        ]
    )


def mask_fraction(path: Path) -> float:
    """Fraction of non-zero pixels of a mask file (an image, or a ``.npy`` array)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"dynamic-object mask not found: {path}")
    mask = np.load(path, allow_pickle=False) if path.suffix == ".npy" else read_image(path).any(axis=-1)
    if mask.size == 0:
        raise ValueError(f"dynamic-object mask {path} is empty")
    return float(np.count_nonzero(mask) / mask.size)


def mask_fractions(images: ImageSet) -> np.ndarray:
    """Dynamic fraction ``[N]`` of every image from ``images.mask_paths``."""
    missing = [name for name, path in zip(images.names, images.mask_paths or [None] * len(images)) if path is None]
    if missing:
        raise ValueError(f"{len(missing)} images have no dynamic-object mask, e.g. {missing[0]!r}")
    return np.array([mask_fraction(path) for path in images.mask_paths])


def dynamic_category_ids() -> np.ndarray:
    """torchvision COCO label ids (91-entry space) of `DYNAMIC_CATEGORIES`."""
    from torchvision.models.detection import MaskRCNN_ResNet50_FPN_Weights

    categories = MaskRCNN_ResNet50_FPN_Weights.COCO_V1.meta["categories"]
    return np.array([categories.index(name) for name in DYNAMIC_CATEGORIES])


def load_maskrcnn(weights: str | Path, device: Any = "cpu", min_size: int = 800, score_threshold: float = 0.5) -> Any:
    """torchvision ``maskrcnn_resnet50_fpn`` in eval mode with COCO weights from a local file.

    ``min_size`` is the shorter image side the model resizes to (torchvision's default
    800; the longer side is capped at ``1333 / 800`` of it); the model keeps only detections
    scoring above ``score_threshold`` (the one place it is applied).
    """
    import torch
    from torchvision.models.detection import MaskRCNN_ResNet50_FPN_Weights, maskrcnn_resnet50_fpn

    weights = Path(weights)
    if not weights.is_file():
        raise FileNotFoundError(
            f"Mask R-CNN weights not found: {weights}; expected torchvision's {MASKRCNN_WEIGHTS_FILE}, "
            f"published at {MaskRCNN_ResNet50_FPN_Weights.COCO_V1.url}"
        )
    model = maskrcnn_resnet50_fpn(
        weights=None,
        weights_backbone=None,
        num_classes=len(MaskRCNN_ResNet50_FPN_Weights.COCO_V1.meta["categories"]),
        min_size=min_size,
        max_size=round(min_size * 1333 / 800),
        box_score_thresh=score_threshold,
    )
    try:
        state = torch.load(weights, map_location="cpu", weights_only=True)
        model.load_state_dict(state)
    except (RuntimeError, OSError, KeyError, pickle.UnpicklingError) as error:
        raise ValueError(f"{weights}: not a maskrcnn_resnet50_fpn COCO state dict ({error})") from error
    return model.eval().to(device)


def dynamic_fraction(labels: Any, masks: Any, dynamic_ids: Any, mask_threshold: float) -> float:
    """Fraction of pixels covered by dynamic detections, computed where the tensors are.

    ``labels [D]`` (COCO ids) and soft ``masks [D, 1, H, W]`` (probabilities) are one image's
    detections (torch tensors, as Mask R-CNN returns them); a detection counts when its label
    is in ``dynamic_ids``; its pixels are those with probability >= ``mask_threshold``.
    """
    import torch

    dynamic = masks[torch.isin(labels, dynamic_ids), 0] >= mask_threshold
    return float(dynamic.any(dim=0).float().mean()) if len(dynamic) else 0.0


def maskrcnn_fractions(images: ImageSet, model, mask_threshold: float) -> np.ndarray:
    """Dynamic fraction ``[N]`` of every image from the detections of a `load_maskrcnn` model."""
    import torch

    device = next(model.parameters()).device
    dynamic_ids = torch.as_tensor(dynamic_category_ids(), device=device)
    fractions = []
    with torch.inference_mode():
        for path in tqdm(images.paths, desc="Mask R-CNN", unit="image", disable=None):
            tensor = torch.from_numpy(read_image(path).copy()).permute(2, 0, 1).float().div(255.0)
            output = model([tensor.to(device)])[0]
            fractions.append(dynamic_fraction(output["labels"], output["masks"], dynamic_ids, mask_threshold))
    return np.array(fractions)


def resolve_mask_source(images: ImageSet, settings: SubsetSettings) -> str:
    """``masks``, ``maskrcnn`` or ``none`` for the configured ``mask_source`` (``auto`` logged)."""
    source = settings.mask_source
    if source != "auto":
        return source
    has_masks = images.mask_paths is not None and all(path is not None for path in images.mask_paths)
    resolved = "masks" if has_masks else "maskrcnn" if settings.maskrcnn_weights else "none"
    log.info(
        "dynamic-scene subset: mask_source=auto -> %s (%s)",
        resolved,
        {"masks": "every image has a mask file", "maskrcnn": f"weights {settings.maskrcnn_weights}",
         "none": "no mask files and no subsets.maskrcnn_weights: no dynamic-scene subset"}[resolved],
    )  # fmt: skip
    return resolved


def missing_mask_inputs(images: ImageSet, settings: SubsetSettings) -> list[str]:
    """What the dynamic-scene subset of ``images`` lacks: mask files (``mask_source=masks``) or
    the Mask R-CNN weight file."""
    source = resolve_mask_source(images, settings) if settings.enabled else "none"
    if source == "masks":
        absent = [name for name, path in zip(images.names, images.mask_paths or [None] * len(images)) if path is None]
        return [f"subsets.mask_source=masks: {len(absent)} of {len(images)} queries have no mask file "
                f"(<kapture>/masks/<name>), e.g. {absent[0]!r}"] if absent else []  # fmt: skip
    if source == "maskrcnn" and not Path(settings.maskrcnn_weights).is_file():
        return [
            f"subsets.maskrcnn_weights: {settings.maskrcnn_weights} not found (torchvision's {MASKRCNN_WEIGHTS_FILE})"
        ]
    return []


def _cached(cache_dir: str | Path | None, parts: list, compute: Callable[[], np.ndarray]) -> np.ndarray:
    path = None if cache_dir is None else Path(cache_dir) / "subsets" / f"{config_key(CACHE_VERSION, *parts)}.npz"
    return cached_arrays(path, lambda: {"values": compute()})[0]["values"]


def subset_scores(
    images: ImageSet, settings: SubsetSettings, cache_dir: str | Path | None = None, device: str = "auto"
) -> pd.DataFrame:
    """Per-image ``blur_score`` and ``dynamic_fraction`` (NaN without a mask source) and the
    ``mask_source`` used; cached under ``<cache_dir>/subsets`` by the image set's fingerprint
    and the parameters that produce each score (thresholds are applied later, uncached).
    """
    source = resolve_mask_source(images, settings)
    fingerprint = images.fingerprint(include_poses=False)
    radius, width = settings.blur_radius, settings.blur_width
    blur = _cached(cache_dir, ["blur", fingerprint, radius, width], lambda: blur_scores(images, radius, width))
    if source == "masks":
        # mask paths relative to the images: a moved or copied dataset and cache keep the key
        relative = [os.path.relpath(p, images.image_root) for p in images.mask_paths]
        key = ["masks", fingerprint, relative, [file_signature(p) for p in images.mask_paths]]
        dynamic = _cached(cache_dir, key, lambda: mask_fractions(images))
    elif source == "maskrcnn":
        weights = Path(settings.maskrcnn_weights)
        min_size = settings.maskrcnn_min_size
        thresholds = settings.maskrcnn_score_threshold, settings.maskrcnn_mask_threshold
        key = ["maskrcnn", fingerprint, str(weights), file_signature(weights), min_size, *thresholds]

        def detect() -> np.ndarray:
            from locretrieval.device import resolve_device

            model = load_maskrcnn(weights, resolve_device(str(device)), min_size, thresholds[0])
            return maskrcnn_fractions(images, model, thresholds[1])

        dynamic = _cached(cache_dir, key, detect)
    else:
        dynamic = np.full(len(images), np.nan)
    return pd.DataFrame({"image": images.names, "blur_score": blur, "dynamic_fraction": dynamic, "mask_source": source})


def subset_masks(scores: pd.DataFrame, settings: SubsetSettings) -> dict[str, np.ndarray]:
    """``{blurry: score <= blur_threshold, dynamic_scene: fraction >= dynamic_fraction}``.

    ``dynamic_scene`` is absent when no mask source was available.
    """
    masks = {BLURRY: scores["blur_score"].to_numpy() <= settings.blur_threshold}
    if (scores["mask_source"] != "none").all():
        masks[DYNAMIC_SCENE] = scores["dynamic_fraction"].to_numpy() >= settings.dynamic_fraction
    return masks


def image_subsets(
    dataset: str, images: ImageSet, settings: SubsetSettings, cache_dir: str | Path | None = None, device: str = "auto"
) -> tuple[dict[str, np.ndarray], pd.DataFrame]:
    """Subset masks of ``images`` and the per-image table written as ``subsets.csv``.

    With ``settings.enabled`` false: no subsets and an empty table.
    """
    if not settings.enabled:
        return {}, pd.DataFrame(columns=SUBSET_COLUMNS)
    scores = subset_scores(images, settings, cache_dir, device)
    masks = subset_masks(scores, settings)
    table = scores.assign(**{name: mask for name, mask in masks.items()})
    table.insert(0, "dataset", dataset)
    for name, mask in masks.items():
        log.info("subset %s: %d of %d images", name, int(mask.sum()), len(mask))
    return masks, table
