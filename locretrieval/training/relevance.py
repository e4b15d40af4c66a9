"""Training pairs from the ground truth: which training images are relevant to each other, how
much, and which are surely unrelated.

Every training image is ranked against every other (itself excluded) with a ground-truth
definition of `locretrieval.groundtruth`: relative pose, frustum overlap, or co-observation
(3D points shared in the known-pose map of the training images, paradigm 2b's global map), the
same definition objects that rank the benchmark's queries (`Definition.graded`). Pairs the
definition calls relevant are positives, with a graded score (higher: more relevant).
Which other pairs may be negatives is a rule chosen by ``_target_`` (``train_relevance.negatives``,
a `NegativesRule`): by default (`UnrelatedNegatives`) only *surely unrelated* pairs, those whose
viewing frusta (truncated at ``negatives.near``/``far`` metres) share no interior, or whose
orientations differ by more than ``negatives.max_rotation`` degrees (two cameras facing each
other share the volume between them but see its surfaces from opposite sides), whatever the
definition, so that two views of the same place that a strict definition does not call
relevant (e.g. 30 m apart looking the same way) are never pushed apart. Pairs that are
neither are ambiguous and ignored by every loss.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import sparse

from locretrieval import geometry
from locretrieval.config import ConfigError, SettingError, part, require
from locretrieval.frusta import TruncatedFrusta, pairwise_overlap_radii
from locretrieval.groundtruth import DefinitionContext, parse_definition
from locretrieval.scene import ImageSet

#: Image pairs scored at once.
PAIRS_PER_CHUNK = 1 << 18
#: ``covisible(rows) -> [len(rows), N]``: pairs of images ``rows`` of a set that may not serve as
#: negatives although the definition does not call them relevant (they may see one place).
CovisibleRows = Callable[[np.ndarray], np.ndarray]


class NegativesRule(abc.ABC):
    """Which pairs may serve as negatives besides the relevant ones (``train_relevance.negatives``,
    chosen by its ``_target_``; ``configs/train_relevance/negatives/``)."""

    @abc.abstractmethod
    def covisible(self, images: ImageSet, context: DefinitionContext) -> CovisibleRows:
        """``covisible(rows)``: the pairs of images ``rows`` to every image of ``images`` that are
        no negatives (beside the relevant ones); what every row needs is computed here, once."""


@dataclass
class UnrelatedNegatives(NegativesRule):
    """Surely unrelated pairs only: those whose frusta, truncated at ``near``/``far`` metres
    (``far`` ``None``: the scene's), do not overlap, or whose orientations differ by more than
    ``max_rotation`` degrees (``None``: frusta only)."""

    near: float
    far: float | None
    max_rotation: float | None

    def __post_init__(self) -> None:
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

    def covisible(self, images: ImageSet, context: DefinitionContext) -> CovisibleRows:
        far = self.far if self.far is not None else context.far
        if far is None:
            raise ConfigError(
                f"train_relevance.negatives.far is null (the dataset's frustum "
                f"far plane) but scene {context.scene!r} has no frustum_far"
            )
        frusta = TruncatedFrusta.of_images(images, np.arange(len(images)), self.near, far)

        def covisible(rows: np.ndarray) -> np.ndarray:
            overlap = pairwise_overlap_radii(frusta[rows], frusta) > 0
            if self.max_rotation is None:
                return overlap
            rotation = geometry.pairwise_rotation_errors_deg(images.qvec[rows], images.qvec)
            return overlap & (rotation <= self.max_rotation)

        return covisible


@dataclass
class NotRelevantNegatives(NegativesRule):
    """Every pair that is not relevant, ambiguous ones included: harder batches, at the risk of
    pushing apart views of one place."""

    def covisible(self, images: ImageSet, context: DefinitionContext) -> CovisibleRows:
        return lambda rows: np.zeros((len(rows), len(images)), dtype=bool)


@dataclass
class TrainingRelevanceSettings:
    """The ``train_relevance`` config group: the ground-truth ``definition`` of positives (a
    mapping with its ``_target_``, a `locretrieval.groundtruth.Definition` class, and that class's
    parameters, as in ``groundtruth.definitions``; parsed into the definition object) and which
    pairs are ``negatives`` (a `NegativesRule` chosen by its ``_target_``)."""

    definition: Any
    negatives: Any = part(NegativesRule, "train_relevance/negatives")

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
    (relevant ones, and those the negatives rule calls covisible, `NegativesRule.covisible`).
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
    covisible = settings.negatives.covisible(images, context)
    grade = settings.definition.graded(images, context)
    graded_blocks, related_blocks = [], []
    rows_per_chunk = max(1, PAIRS_PER_CHUNK // count)
    for start in range(0, count, rows_per_chunk):
        rows = np.arange(start, min(count, start + rows_per_chunk))
        graded = grade(rows)
        graded[rows - start, rows] = 0.0
        graded_blocks.append(sparse.csr_matrix(graded))
        related_blocks.append(sparse.csr_matrix(covisible(rows) | (graded > 0)))
    return TrainingPairs(sparse.vstack(graded_blocks).tocsr(), sparse.vstack(related_blocks).tocsr())


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
