"""Training pairs from the ground truth: which training images are relevant to each other, how
much, and which are surely unrelated.

Every training image is ranked against every other (itself excluded) with a ground-truth
definition of `locretrieval.groundtruth`: relative pose, frustum overlap, or co-observation
(3D points shared in the known-pose map of the training images, paradigm 2b's global map), the
same definition objects that rank the benchmark's queries (`Definition.graded`). Pairs the
definition calls relevant are positives, with a graded score (higher: more relevant).
Negatives come only from *surely unrelated* pairs: those whose viewing frusta (truncated at
``negatives.near``/``far`` metres) share no interior, or whose orientations differ by more
than ``negatives.max_rotation`` degrees (two cameras facing each
other share the volume between them but see its surfaces from opposite sides), whatever the
definition, so that two views of the same place that a strict definition does not call
relevant (e.g. 30 m apart looking the same way) are never pushed apart. Pairs that are
neither are ambiguous and ignored by every loss.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import sparse

from locretrieval import geometry
from locretrieval.config import ConfigError, SettingError, require
from locretrieval.frusta import TruncatedFrusta, pairwise_overlap_radii
from locretrieval.groundtruth import DefinitionContext, parse_definition
from locretrieval.scene import ImageSet

#: Image pairs scored at once.
PAIRS_PER_CHUNK = 1 << 18
#: What may serve as a negative: surely unrelated pairs only, or every pair that is not relevant.
NEGATIVE_RULES = ("unrelated", "not_relevant")


@dataclass
class NegativeSettings:
    """Which pairs may serve as negatives (``train_relevance.negatives``): ``rule`` ``unrelated``
    (pairs whose frusta, truncated at ``near``/``far`` metres, ``far`` ``None``: the scene's, do
    not overlap, or whose orientations differ by more than ``max_rotation`` degrees, ``None``:
    frusta only) or ``not_relevant`` (every pair that is not relevant, ambiguous ones included:
    harder batches, at the risk of pushing apart views of one place)."""

    rule: str
    near: float
    far: float | None
    max_rotation: float | None

    def __post_init__(self) -> None:
        require(self.rule in NEGATIVE_RULES, "rule", f"must be one of {list(NEGATIVE_RULES)}, got {self.rule!r}")
        require(self.near > 0, "near", f"must be a positive depth in metres, got {self.near}")
        require(
            self.far is None or self.far > self.near,
            "far",
            f"must exceed near ({self.near} m) or be null, got {self.far}",
        )
        require(
            self.max_rotation is None or 0 <= self.max_rotation <= 180,
            "max_rotation",
            f"must be degrees in [0, 180] or null, got {self.max_rotation}",
        )


@dataclass
class TrainingRelevanceSettings:
    """The ``train_relevance`` config group: the ground-truth ``definition`` of positives (a
    mapping with its ``_target_``, a `locretrieval.groundtruth.Definition` class, and that class's
    parameters, as in ``groundtruth.definitions``; parsed into the definition object) and which
    pairs are ``negatives``."""

    definition: Any
    negatives: NegativeSettings

    def __post_init__(self) -> None:
        if not hasattr(self.definition, "graded"):  # a mapping from the config (anything else is refused by name)
            try:
                self.definition = parse_definition(self.definition, "definition")
            except ConfigError as error:  # named under train_relevance by `validated`
                key, _, message = str(error).partition(": ")
                raise SettingError(key, message) from None


@dataclass(frozen=True)
class TrainingPairs:
    """``graded [N, N]`` (sparse float): the relevance score of each relevant pair (> 0), the
    diagonal empty; ``related [N, N]`` (sparse bool): pairs that may not serve as negatives
    (relevant ones, and unless negatives are ``not_relevant`` those whose frusta overlap, at a
    rotation within ``negatives.max_rotation``).
    Negatives are the pairs outside ``related`` (and off the diagonal)."""

    graded: sparse.csr_matrix
    related: sparse.csr_matrix

    @property
    def num_images(self) -> int:
        return self.graded.shape[0]

    def positives(self, image: int) -> np.ndarray:
        """The images relevant to ``image``."""
        return self.graded[image].indices

    def batch(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(relevance float32 [B, B], negatives bool [B, B])`` among the images ``indices``."""
        return self.block(indices, indices)

    def block(self, rows: np.ndarray, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(relevance float32 [R, C], negatives bool [R, C])`` of the images ``rows`` to the images
        ``columns``; an image paired with itself is neither."""
        relevance = self.graded[rows][:, columns].toarray().astype(np.float32)
        negatives = ~self.related[rows][:, columns].toarray()
        same = rows[:, None] == columns[None]
        relevance[same] = 0.0
        negatives[same] = False
        return relevance, negatives


def training_pairs(images: ImageSet, settings: TrainingRelevanceSettings, context: DefinitionContext) -> TrainingPairs:
    """Relevance among ``images`` (all posed) by ``settings``: graded by the definition
    (`Definition.graded`, with ``context``: the scene's far plane, SfM settings, cache and the
    world whose database ``images`` are), related pairs by ``settings.negatives``."""
    if not images.has_pose.all():
        missing = [n for n, posed in zip(images.names, images.has_pose) if not posed][:5]
        raise ValueError(f"training images need poses; without: {missing}")
    count = len(images)
    negatives = settings.negatives
    frusta = None
    if negatives.rule == "unrelated":
        far = negatives.far if negatives.far is not None else context.far
        if far is None:
            raise ConfigError(
                f"train_relevance.negatives.far is null (the dataset's frustum "
                f"far plane) but scene {context.scene!r} has no frustum_far"
            )
        frusta = TruncatedFrusta.of_images(images, np.arange(count), negatives.near, far)
    grade = settings.definition.graded(images, context)
    graded_blocks, related_blocks = [], []
    rows_per_chunk = max(1, PAIRS_PER_CHUNK // count)
    for start in range(0, count, rows_per_chunk):
        rows = np.arange(start, min(count, start + rows_per_chunk))
        graded = grade(rows)
        graded[rows - start, rows] = 0.0
        graded_blocks.append(sparse.csr_matrix(graded))
        related = graded > 0 if frusta is None else (_covisible(images, rows, frusta, negatives) | (graded > 0))
        related_blocks.append(sparse.csr_matrix(related))
    return TrainingPairs(sparse.vstack(graded_blocks).tocsr(), sparse.vstack(related_blocks).tocsr())


def _covisible(images: ImageSet, rows: np.ndarray, frusta: TruncatedFrusta, negatives: NegativeSettings) -> np.ndarray:
    """``[len(rows), N]``: pairs that may see one place: overlapping ``frusta``, at an orientation
    difference of at most ``max_rotation`` degrees when it is set."""
    overlap = pairwise_overlap_radii(frusta[rows], frusta) > 0
    if negatives.max_rotation is None:
        return overlap
    rotation = geometry.pairwise_rotation_errors_deg(images.qvec[rows], images.qvec)
    return overlap & (rotation <= negatives.max_rotation)


def combined_pairs(
    sets: Sequence[ImageSet], settings: TrainingRelevanceSettings, contexts: Sequence[DefinitionContext]
) -> TrainingPairs:
    """Training pairs of several image sets, in order (``contexts``: each set's); images of
    different sets (other worlds, e.g. separately rendered scenes) are unrelated."""
    pairs = [training_pairs(images, settings, context) for images, context in zip(sets, contexts, strict=True)]
    return TrainingPairs(
        sparse.block_diag([p.graded for p in pairs], format="csr"),
        sparse.block_diag([p.related for p in pairs], format="csr"),
    )
