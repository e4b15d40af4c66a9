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

**Dynamic scenes.** The fraction of pixels on dynamic objects, from a `MaskSource` chosen by
``_target_`` (``subsets.mask_sources``; the first of ``subsets.dynamic_masks`` that can serve
every query is used): per-image mask files (`MaskFiles`, ``ImageSet.mask_paths``: non-zero on
dynamic objects, e.g. the synthetic scene's exact masks) or torchvision's Mask R-CNN
(`MaskRcnn`, ResNet-50 FPN, COCO weights read from a local file): the union of the masks
(probability >= ``mask_threshold``) of detections scoring >= ``score_threshold`` whose class is
in `DYNAMIC_CATEGORIES`. An image is a **dynamic scene when fraction >= 0.2**.
"""

from __future__ import annotations

import abc
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from PIL import Image
from tqdm import tqdm

from locretrieval.bounded_files import check_npy
from locretrieval.cache import cached_arrays, config_key, file_signature
from locretrieval.config import named_parts, require
from locretrieval.scene import ImageSet
from locretrieval.scene.images import read_image

log = logging.getLogger(__name__)

#: Bump when the meaning of cached scores changes.
CACHE_VERSION = 2

#: Names of the subsets `subset_masks` returns.
BLURRY = "blurry"
DYNAMIC_SCENE = "dynamic_scene"
#: The query tags of a scene that knows which queries are blurred or show dynamic objects (the
#: synthetic renderer's): such a tag is the subset, reported under the subset's name (`known_subsets`).
SUBSET_TAGS = {BLURRY: "blur", DYNAMIC_SCENE: "dynamic"}

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

#: The ``mask_source`` of images without one (no dynamic-scene subset).
NO_MASK_SOURCE = "none"


class MaskSource(abc.ABC):
    """Where the fraction of each image's pixels on dynamic objects comes from. A new source
    subclasses this, in any package, and is chosen by its ``_target_`` (``subsets.mask_sources``)."""

    @abc.abstractmethod
    def unavailable(self, images: ImageSet) -> str | None:
        """Why it cannot serve ``images`` (e.g. no mask files), or ``None`` when it can."""

    def missing_inputs(self, images: ImageSet) -> list[str]:
        """The files it names that are absent, checked before any work (default: none)."""
        return []

    @abc.abstractmethod
    def key(self, images: ImageSet) -> list[Any]:
        """What its fractions of ``images`` depend on beyond the images (the cache key)."""

    @abc.abstractmethod
    def fractions(self, images: ImageSet) -> np.ndarray:
        """The dynamic fraction ``[N]`` of every image, in [0, 1]."""


@dataclass
class MaskFiles(MaskSource):
    """The image set's mask files (``ImageSet.mask_paths``; `mask_fraction`)."""

    def unavailable(self, images: ImageSet) -> str | None:
        absent = [name for name, path in zip(images.names, images.mask_paths or [None] * len(images)) if path is None]
        if absent:
            return (
                f"{len(absent)} of {len(images)} images have no mask file (<kapture>/masks/<name>), e.g. {absent[0]!r}"
            )
        return None

    def key(self, images: ImageSet) -> list[Any]:
        # mask paths relative to the images: a moved or copied dataset and cache keep the key
        relative = [os.path.relpath(p, images.image_root) for p in images.mask_paths]
        return ["masks", relative, [file_signature(p) for p in images.mask_paths]]

    def fractions(self, images: ImageSet) -> np.ndarray:
        return mask_fractions(images)


@dataclass
class MaskRcnn(MaskSource):
    """torchvision's Mask R-CNN with COCO ``weights`` read from a local file (`load_maskrcnn`:
    ``min_size``, ``score_threshold``; `maskrcnn_fractions`: ``mask_threshold``) on ``device``;
    unavailable while ``weights`` is null."""

    weights: str | None
    min_size: int
    score_threshold: float
    mask_threshold: float
    device: str

    def __post_init__(self) -> None:
        require(self.min_size >= 32, "min_size", f"must be >= 32 pixels, got {self.min_size}")
        for name in ("score_threshold", "mask_threshold"):
            require(0 <= getattr(self, name) <= 1, name, f"must be in [0, 1], got {getattr(self, name)}")

    def unavailable(self, images: ImageSet) -> str | None:
        return None if self.weights else f"no weights (the path of torchvision's {MASKRCNN_WEIGHTS_FILE})"

    def missing_inputs(self, images: ImageSet) -> list[str]:
        if self.weights and not Path(self.weights).is_file():
            return [f"weights: {self.weights} not found (torchvision's {MASKRCNN_WEIGHTS_FILE})"]
        return []

    def key(self, images: ImageSet) -> list[Any]:
        weights = Path(self.weights)
        return [
            "maskrcnn",
            str(weights),
            file_signature(weights),
            self.min_size,
            self.score_threshold,
            self.mask_threshold,
        ]

    def fractions(self, images: ImageSet) -> np.ndarray:
        from locretrieval.device import resolve_device

        model = load_maskrcnn(self.weights, resolve_device(self.device), self.min_size, self.score_threshold)
        return maskrcnn_fractions(images, model, self.mask_threshold)


@dataclass
class SubsetSettings:
    """The ``subsets`` config group (``configs/subsets/default.yaml`` documents each key):
    ``dynamic_masks`` names the ``mask_sources`` (name -> `MaskSource`, chosen by ``_target_``)
    tried in order (`mask_source`)."""

    enabled: bool
    blur_threshold: float
    blur_radius: int
    blur_width: int
    dynamic_fraction: float
    dynamic_masks: list[str]
    mask_sources: dict[str, Any] = named_parts(MaskSource)

    def __post_init__(self) -> None:
        require(self.blur_radius >= 1, "blur_radius", f"must be >= 1 frequency bin, got {self.blur_radius}")
        require(
            self.blur_width > 2 * self.blur_radius,
            "blur_width",
            f"must exceed twice blur_radius ({2 * self.blur_radius}), got {self.blur_width}",
        )
        require(0 <= self.dynamic_fraction <= 1, "dynamic_fraction", f"must be in [0, 1], got {self.dynamic_fraction}")
        unknown = [name for name in self.dynamic_masks if name not in self.mask_sources]
        require(
            not unknown,
            "dynamic_masks",
            f"{unknown} are not names of subsets.mask_sources {list(self.mask_sources)}",
        )


def blur_score(image: np.ndarray, radius: int, width: int) -> float:
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


def blur_scores(images: ImageSet, radius: int, width: int) -> np.ndarray:
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
    if path.suffix == ".npy":
        check_npy(path)  # numpy allocates what the header declares before reading
        mask = np.load(path, allow_pickle=False)
    else:
        mask = read_image(path).any(axis=-1)
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


def load_maskrcnn(weights: str | Path, device: Any, min_size: int, score_threshold: float) -> Any:
    """torchvision ``maskrcnn_resnet50_fpn`` in eval mode with COCO weights from a local file.

    ``min_size`` is the shorter image side the model resizes to (torchvision's default
    800; the longer side is capped at ``1333 / 800`` of it); the model keeps only detections
    scoring above ``score_threshold`` (the one place it is applied).
    """
    from torchvision.models.detection import MaskRCNN_ResNet50_FPN_Weights, maskrcnn_resnet50_fpn

    from locretrieval.models.files.weights import load_torch_file

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
    state = load_torch_file(weights)  # the restricted unpickler, after its scan (DataFileError naming the file)
    try:
        model.load_state_dict(state)
    except (RuntimeError, KeyError, TypeError) as error:
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


def mask_source(images: ImageSet, settings: SubsetSettings) -> tuple[str, MaskSource | None]:
    """The first of ``settings.dynamic_masks`` that can serve every image of ``images`` (its name
    and source), logged; ``(NO_MASK_SOURCE, None)`` when none can (no dynamic-scene subset)."""
    reasons = {}
    for name in settings.dynamic_masks:
        source = settings.mask_sources[name]
        reasons[name] = source.unavailable(images)
        if reasons[name] is None:
            log.info("dynamic-scene subset: mask source %s", name)
            return name, source
    log.info("dynamic-scene subset: none (%s)", "; ".join(f"{n}: {r}" for n, r in reasons.items()) or "no mask source")
    return NO_MASK_SOURCE, None


def missing_mask_inputs(images: ImageSet, settings: SubsetSettings) -> list[str]:
    """What the dynamic-scene subset of ``images`` lacks: the files its mask source names
    (`MaskSource.missing_inputs`), or, when ``subsets.dynamic_masks`` names one source alone,
    why that one cannot serve them."""
    if not settings.enabled:
        return []
    name, source = mask_source(images, settings)
    if source is not None:
        return [f"subsets.mask_sources.{name}.{problem}" for problem in source.missing_inputs(images)]
    if len(settings.dynamic_masks) == 1:  # the one source asked for
        (name,) = settings.dynamic_masks
        return [f"subsets.dynamic_masks=[{name}]: {settings.mask_sources[name].unavailable(images)}"]
    return []


def _cached(cache_dir: str | Path | None, parts: list, compute: Callable[[], np.ndarray]) -> np.ndarray:
    path = None if cache_dir is None else Path(cache_dir) / "subsets" / f"{config_key(CACHE_VERSION, *parts)}.npz"
    return cached_arrays(path, lambda: {"values": compute()})[0]["values"]


def subset_scores(images: ImageSet, settings: SubsetSettings, cache_dir: str | Path | None) -> pd.DataFrame:
    """Per-image ``blur_score`` and ``dynamic_fraction`` (NaN without a mask source) and the
    ``mask_source`` used (`mask_source`); cached under ``<cache_dir>/subsets`` by the image set's
    fingerprint and what produces each score (thresholds are applied later, uncached).
    """
    name, source = mask_source(images, settings)
    fingerprint = images.fingerprint(include_poses=False)
    radius, width = settings.blur_radius, settings.blur_width
    blur = _cached(cache_dir, ["blur", fingerprint, radius, width], lambda: blur_scores(images, radius, width))
    if source is not None:
        dynamic = _cached(cache_dir, ["dynamic", fingerprint, source.key(images)], lambda: source.fractions(images))
    else:
        dynamic = np.full(len(images), np.nan)
    return pd.DataFrame({"image": images.names, "blur_score": blur, "dynamic_fraction": dynamic, "mask_source": name})


def subset_masks(scores: pd.DataFrame, settings: SubsetSettings) -> dict[str, np.ndarray]:
    """``{blurry: score <= blur_threshold, dynamic_scene: fraction >= dynamic_fraction}``.

    ``dynamic_scene`` is absent when no mask source was available.
    """
    masks = {BLURRY: scores["blur_score"].to_numpy() <= settings.blur_threshold}
    if (scores["mask_source"] != NO_MASK_SOURCE).all():
        masks[DYNAMIC_SCENE] = scores["dynamic_fraction"].to_numpy() >= settings.dynamic_fraction
    return masks


def image_subsets(
    dataset: str, images: ImageSet, settings: SubsetSettings, cache_dir: str | Path | None
) -> tuple[dict[str, np.ndarray], pd.DataFrame]:
    """Subset masks of ``images`` and the per-image table written as ``subsets.csv``.

    With ``settings.enabled`` false: no subsets and an empty table.
    """
    if not settings.enabled:
        return {}, pd.DataFrame(columns=SUBSET_COLUMNS)
    scores = subset_scores(images, settings, cache_dir)
    masks = subset_masks(scores, settings)
    table = scores.assign(**{name: mask for name, mask in masks.items()})
    table.insert(0, "dataset", dataset)
    for name, mask in masks.items():
        log.info("subset %s: %d of %d images", name, int(mask.sum()), len(mask))
    return masks, table


def known_subsets(
    tag_masks: dict[str, np.ndarray], image_masks: dict[str, np.ndarray], table: pd.DataFrame
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], pd.DataFrame]:
    """One name per subset: where the queries carry the tag of an image subset (`SUBSET_TAGS`), the
    tag's queries are that subset (what the scene knows rather than what a detector finds), under
    the subset's name, the tag's own subset dropped; ``(tag masks, image masks, table)`` with the
    table's column of the subset holding the tag's. The detectors' agreement is logged."""
    tag_masks, image_masks, table = dict(tag_masks), dict(image_masks), table.copy()
    for subset, tag in SUBSET_TAGS.items():
        if subset in image_masks and tag in tag_masks:
            known, detected = tag_masks.pop(tag), image_masks[subset]
            log.info(
                "subset %s: the %d queries the scene tags %r (the detector finds %d, %d of them tagged)",
                subset,
                int(known.sum()),
                tag,
                int(detected.sum()),
                int((known & detected).sum()),
            )
            image_masks[subset] = known
            table[subset] = known
    return tag_masks, image_masks, table
