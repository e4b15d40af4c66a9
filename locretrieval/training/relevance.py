"""Training pairs from the ground truth: which training images are relevant to each other, how
much, and which are surely unrelated.

Every training image is ranked against every other (itself excluded) with a ground-truth
definition of `locretrieval.groundtruth`: relative pose, frustum overlap, or co-observation
(3D points shared in the known-pose map of the training images, paradigm 2b's global map). Pairs the definition calls relevant are positives,
with a graded score (higher: more relevant). Negatives come only from *surely unrelated*
pairs: those whose viewing frusta (truncated at ``near``/``far`` metres) share no interior, or
whose orientations differ by more than ``unrelated_rotation`` degrees (two cameras facing each
other share the volume between them but see its surfaces from opposite sides), whatever the
definition, so that two views of the same place that a strict definition does not call
relevant (e.g. 30 m apart looking the same way) are never pushed apart. Pairs that are
neither are ambiguous and ignored by every loss.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from locretrieval import geometry
from locretrieval.config import require
from locretrieval.frusta import TruncatedFrusta, pairwise_overlap_radii
from locretrieval.groundtruth import FrustumDefinition, RelativePoseDefinition, relative_pose_scores
from locretrieval.scene import ImageSet

#: Image pairs scored at once.
PAIRS_PER_CHUNK = 1 << 18


@dataclass
class TrainingRelevanceSettings:
    """The ``train_relevance`` config group: ``type`` (``relative_pose``, ``frustum`` or
    ``co_observation``) and its parameters (the ground-truth definition's; co-observation:
    `SharedPoints`); ``negatives``: ``unrelated`` (pairs whose frusta,
    truncated at ``near``/``far`` metres, ``far`` ``None``: the scene's, do not overlap, or whose
    orientations differ by more than ``unrelated_rotation`` degrees, ``None``: frusta only) or
    ``not_relevant`` (every pair that is not relevant, ambiguous ones included: harder batches,
    at the risk of pushing apart views of one place)."""

    type: str
    parameters: dict
    negatives: str
    near: float
    far: float | None
    unrelated_rotation: float | None = None

    def __post_init__(self) -> None:
        require(self.type in RELEVANCE_TYPES, "type", f"must be one of {sorted(RELEVANCE_TYPES)}, got {self.type!r}")
        self.parameters = dict(self.parameters)
        RELEVANCE_TYPES[self.type](**self.parameters)  # range checks of the definition
        require(self.near > 0, "near", f"must be a positive depth in metres, got {self.near}")
        require(self.negatives in NEGATIVES, "negatives", f"must be one of {list(NEGATIVES)}, got {self.negatives!r}")
        require(self.unrelated_rotation is None or 0 <= self.unrelated_rotation <= 180, "unrelated_rotation",
                f"must be degrees in [0, 180] or null, got {self.unrelated_rotation}")


@dataclass
class SharedPoints:
    """Co-observation training relevance: a pair is relevant when both images observe at least
    ``min_shared`` 3D points of the map, graded by the share of the anchor's points the partner
    also observes (in (0, 1])."""

    min_shared: int

    def __post_init__(self) -> None:
        require(self.min_shared >= 1, "min_shared", f"must be >= 1 shared 3D point, got {self.min_shared}")


RELEVANCE_TYPES = {"relative_pose": RelativePoseDefinition, "frustum": FrustumDefinition, "co_observation": SharedPoints}
NEGATIVES = ("unrelated", "not_relevant")


@dataclass(frozen=True)
class TrainingPairs:
    """``graded [N, N]`` (sparse float): the relevance score of each relevant pair (> 0), the
    diagonal empty; ``related [N, N]`` (sparse bool): pairs that may not serve as negatives
    (relevant ones, and unless negatives are ``not_relevant`` those whose frusta overlap, at a
    rotation within ``unrelated_rotation``).
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


def training_pairs(
    images: ImageSet, settings: TrainingRelevanceSettings, far: float, shared_points: sparse.csr_matrix | None = None
) -> TrainingPairs:
    """Relevance among ``images`` (all posed) by ``settings``; ``far`` (metres) is the resolved
    far plane of the frusta deciding surely unrelated pairs (and of a frustum definition whose
    ``far`` is ``None``). Co-observation needs ``shared_points [N, N]``: the 3D points each pair
    observes, the diagonal each image's own (`database_co_observations`)."""
    if not images.has_pose.all():
        missing = [n for n, posed in zip(images.names, images.has_pose) if not posed][:5]
        raise ValueError(f"training images need poses; without: {missing}")
    count = len(images)
    if settings.type == "co_observation" and (shared_points is None or shared_points.shape != (count, count)):
        raise ValueError(f"co-observation training relevance needs the shared 3D points of the {count} images")
    frusta = TruncatedFrusta.of_images(images, np.arange(count), settings.near, far)
    scored = _definition_frusta(images, settings, far, frusta)
    graded_blocks, related_blocks = [], []
    rows_per_chunk = max(1, PAIRS_PER_CHUNK // count)
    for start in range(0, count, rows_per_chunk):
        rows = np.arange(start, min(count, start + rows_per_chunk))
        overlap = pairwise_overlap_radii(frusta[rows], frusta)
        definition_overlap = overlap if scored is frusta or scored is None else pairwise_overlap_radii(scored[rows], scored)
        graded = (_shared_share(shared_points, rows, SharedPoints(**settings.parameters).min_shared)
                  if settings.type == "co_observation" else _graded(images, rows, definition_overlap, settings))
        graded[rows - start, rows] = 0.0
        graded_blocks.append(sparse.csr_matrix(graded))
        related = graded > 0 if settings.negatives == "not_relevant" else (_covisible(images, rows, overlap, settings) | (graded > 0))
        related_blocks.append(sparse.csr_matrix(related))
    return TrainingPairs(sparse.vstack(graded_blocks).tocsr(), sparse.vstack(related_blocks).tocsr())


def _covisible(images: ImageSet, rows: np.ndarray, overlap: np.ndarray, settings: TrainingRelevanceSettings) -> np.ndarray:
    """``[len(rows), N]``: pairs that may see one place: overlapping frusta, at an orientation
    difference of at most ``unrelated_rotation`` degrees when it is set."""
    if settings.unrelated_rotation is None:
        return overlap > 0
    rotation = geometry.pairwise_rotation_errors_deg(images.qvec[rows], images.qvec)
    return (overlap > 0) & (rotation <= settings.unrelated_rotation)


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


def _shared_share(shared_points: sparse.csr_matrix, rows: np.ndarray, min_shared: int) -> np.ndarray:
    """``[len(rows), N]`` share of each row image's 3D points that the other image observes too,
    where they share at least ``min_shared``."""
    shared = shared_points[rows].toarray().astype(np.float64)
    own = np.maximum(shared[np.arange(len(rows)), rows], 1.0)[:, None]
    return np.where(shared >= min_shared, shared / own, 0.0)


def combined_pairs(
    sets: Sequence[ImageSet], settings: TrainingRelevanceSettings, far: float,
    shared_points: Sequence[sparse.csr_matrix] | None = None,
) -> TrainingPairs:
    """Training pairs of several image sets, in order (``shared_points``: each set's, for
    co-observation); images of different sets (other worlds, e.g. separately rendered scenes)
    are unrelated."""
    shared_points = shared_points or [None] * len(sets)
    pairs = [training_pairs(images, settings, far, shared) for images, shared in zip(sets, shared_points, strict=True)]
    return TrainingPairs(sparse.block_diag([p.graded for p in pairs], format="csr"),
                         sparse.block_diag([p.related for p in pairs], format="csr"))
