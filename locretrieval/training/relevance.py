"""Training pairs from the ground truth: which training images are relevant to each other, how
much, and which are surely unrelated.

Every training image is ranked against every other (itself excluded) with a ground-truth
definition of `locretrieval.groundtruth`. Pairs the definition calls relevant are positives,
with a graded score (higher: more relevant). Negatives come only from *surely unrelated*
pairs: those whose viewing frusta (truncated at ``near``/``far`` metres) share no interior,
whatever the definition, so that two views of the same place that a strict definition does
not call relevant (e.g. 30 m apart looking the same way) are never pushed apart. Pairs that
are neither are ambiguous and ignored by every loss.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from locretrieval.config import require
from locretrieval.frusta import TruncatedFrusta, pairwise_overlap_radii
from locretrieval.groundtruth import FrustumDefinition, RelativePoseDefinition, relative_pose_scores
from locretrieval.scene import ImageSet

#: Image pairs scored at once.
PAIRS_PER_CHUNK = 1 << 18


@dataclass
class TrainingRelevanceSettings:
    """The ``train_relevance`` config group: ``type`` (``relative_pose`` or ``frustum``) and its
    parameters (the ground-truth definition's); ``negatives``: ``unrelated`` (pairs whose frusta,
    truncated at ``near``/``far`` metres, ``far`` ``None``: the scene's, do not overlap) or
    ``not_relevant`` (every pair that is not relevant, ambiguous ones included: harder batches,
    at the risk of pushing apart views of one place)."""

    type: str
    parameters: dict
    negatives: str
    near: float
    far: float | None

    def __post_init__(self) -> None:
        require(self.type in RELEVANCE_TYPES, "type", f"must be one of {sorted(RELEVANCE_TYPES)}, got {self.type!r}"
                " (co-observation training relevance needs a joint SfM map of the training images: not built yet)")
        self.parameters = dict(self.parameters)
        RELEVANCE_TYPES[self.type](**self.parameters)  # range checks of the definition
        require(self.near > 0, "near", f"must be a positive depth in metres, got {self.near}")
        require(self.negatives in NEGATIVES, "negatives", f"must be one of {list(NEGATIVES)}, got {self.negatives!r}")


RELEVANCE_TYPES = {"relative_pose": RelativePoseDefinition, "frustum": FrustumDefinition}
NEGATIVES = ("unrelated", "not_relevant")


@dataclass(frozen=True)
class TrainingPairs:
    """``graded [N, N]`` (sparse float): the relevance score of each relevant pair (> 0), the
    diagonal empty; ``related [N, N]`` (sparse bool): pairs that may not serve as negatives
    (relevant ones, and those whose frusta overlap unless negatives are ``not_relevant``).
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
        relevance = self.graded[indices][:, indices].toarray().astype(np.float32)
        negatives = ~self.related[indices][:, indices].toarray()
        same = indices[:, None] == indices[None]
        relevance[same] = 0.0
        negatives[same] = False
        return relevance, negatives


def training_pairs(images: ImageSet, settings: TrainingRelevanceSettings, far: float) -> TrainingPairs:
    """Relevance among ``images`` (all posed) by ``settings``; ``far`` (metres) is the resolved
    far plane of the frusta deciding surely unrelated pairs (and of a frustum definition whose
    ``far`` is ``None``)."""
    if not images.has_pose.all():
        missing = [n for n, posed in zip(images.names, images.has_pose) if not posed][:5]
        raise ValueError(f"training images need poses; without: {missing}")
    count = len(images)
    frusta = TruncatedFrusta.of_images(images, np.arange(count), settings.near, far)
    scored = _definition_frusta(images, settings, far, frusta)
    graded_blocks, related_blocks = [], []
    rows_per_chunk = max(1, PAIRS_PER_CHUNK // count)
    for start in range(0, count, rows_per_chunk):
        rows = np.arange(start, min(count, start + rows_per_chunk))
        overlap = pairwise_overlap_radii(frusta[rows], frusta)
        definition_overlap = overlap if scored is frusta or scored is None else pairwise_overlap_radii(scored[rows], scored)
        graded = _graded(images, rows, definition_overlap, settings)
        graded[rows - start, rows] = 0.0
        graded_blocks.append(sparse.csr_matrix(graded))
        related = graded > 0 if settings.negatives == "not_relevant" else (overlap > 0) | (graded > 0)
        related_blocks.append(sparse.csr_matrix(related))
    return TrainingPairs(sparse.vstack(graded_blocks).tocsr(), sparse.vstack(related_blocks).tocsr())


def _definition_frusta(images: ImageSet, settings: TrainingRelevanceSettings, far: float, frusta: TruncatedFrusta) -> TruncatedFrusta | None:
    """The frusta a frustum definition scores with: ``frusta`` when its planes are the same
    (``far`` ``None``: the scene's); ``None`` for other definitions."""
    if settings.type != "frustum":
        return None
    definition = FrustumDefinition(**settings.parameters)
    planes = (definition.near, definition.far if definition.far is not None else far)
    if planes == (settings.near, far):
        return frusta
    return TruncatedFrusta.of_images(images, np.arange(len(images)), *planes)


def _graded(images: ImageSet, rows: np.ndarray, overlap: np.ndarray, settings: TrainingRelevanceSettings) -> np.ndarray:
    """Graded relevance ``[len(rows), N]`` of a block of images against all; ``overlap``: the
    block's frustum-overlap radii with the definition's planes (frustum definitions)."""
    parameters = settings.parameters
    if settings.type == "frustum":
        return np.where(overlap > FrustumDefinition(**parameters).min_radius, overlap, 0.0)
    definition = RelativePoseDefinition(**parameters)
    score, position, rotation = relative_pose_scores(
        images.qvec[rows], images.centers[rows], images.qvec, images.centers,
        definition.position_threshold, definition.rotation_threshold,
    )
    relevant = (position < definition.position_threshold) & (rotation < definition.rotation_threshold)
    return np.where(relevant, 1.0 - score / 2.0, 0.0)  # s < 2 inside both thresholds: (0, 1]


def combined_pairs(sets: Sequence[ImageSet], settings: TrainingRelevanceSettings, far: float) -> TrainingPairs:
    """Training pairs of several image sets, in order; images of different sets (other worlds,
    e.g. separately rendered scenes) are unrelated."""
    pairs = [training_pairs(images, settings, far) for images in sets]
    return TrainingPairs(sparse.block_diag([p.graded for p in pairs], format="csr"),
                         sparse.block_diag([p.related for p in pairs], format="csr"))
