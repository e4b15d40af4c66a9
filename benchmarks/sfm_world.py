"""A generated world whose images' local features are written as published kapture features (R2D2's layout).

Used by ``bench_scale.py``: 3D points with a descriptor each fill the space around the cameras;
an image's keypoints are the projections of the nearest points it sees (a share of its
``keypoints``, with half a pixel of noise) and clutter, its descriptors the points' descriptors
plus noise (clutter: random ones), float32 as R2D2's. Matching then finds true correspondences,
pose verification keeps them, maps get points and queries register: every SfM stage does the
work it does on real data, read through the same kapture reader.
"""

from __future__ import annotations

from pathlib import Path

import kapture
import kapture.io.csv as kapture_csv
import kapture.io.features as kapture_features
import numpy as np

from locretrieval import geometry
from locretrieval.scene import ImageSet

DIMENSION = 128
#: Share of an image's keypoints that observe world points (the rest: clutter).
OBSERVED_SHARE = 0.6
#: Points per cubic metre, and the height of the space they fill (metres).
DENSITY, HEIGHT = 1.5, 6.0
#: Standard deviation of the descriptor noise (each dimension of a point's descriptor is N(0, 1)).
DESCRIPTOR_NOISE = 0.35


class FeatureWorld:
    """Points (``[P, 3]``, metres) with descriptors in the box around ``centers`` widened by ``margin`` metres."""

    def __init__(self, centers: np.ndarray, margin: float, rng: np.random.Generator) -> None:
        low, high = centers[:, :2].min(0) - margin, centers[:, :2].max(0) + margin
        count = int(DENSITY * np.prod(high - low) * HEIGHT)
        self.points = np.column_stack(
            [rng.uniform(low[0], high[0], count), rng.uniform(low[1], high[1], count), rng.uniform(0, HEIGHT, count)]
        )
        self.descriptors = rng.normal(size=(count, DIMENSION)).astype(np.float32)
        self.rng = rng

    def features(
        self, images: ImageSet, index: int, keypoints: int, far: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keypoints ``float32 [n, 3]`` (x, y, scale; OpenCV pixel centres, as R2D2 writes them),
        descriptors ``float32 [n, 128]`` of image ``index``, and the point each keypoint observes
        (``int64 [n]``, -1: clutter)."""
        camera = images.cameras[index]
        in_camera = self.points @ geometry.quaternion_to_matrix(images.qvec[index]).T + images.tvec[index]
        depth = in_camera[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = in_camera[:, :2] / depth[:, None] * camera.params[:2] + camera.params[2:4] - 0.5
        visible = np.flatnonzero(
            (depth > 0.5)
            & (depth < far)
            & (pixels >= 0).all(1)
            & (pixels[:, 0] < camera.width - 1)
            & (pixels[:, 1] < camera.height - 1)
        )
        seen = visible[np.argsort(depth[visible], kind="stable")[: int(OBSERVED_SHARE * keypoints)]]
        clutter = keypoints - len(seen)
        xy = np.concatenate(
            [
                pixels[seen] + self.rng.normal(0.0, 0.5, (len(seen), 2)),
                self.rng.uniform(0, [camera.width - 1, camera.height - 1], (clutter, 2)),
            ]
        )
        values = np.concatenate(
            [
                self.descriptors[seen] + DESCRIPTOR_NOISE * self.rng.normal(size=(len(seen), DIMENSION)),
                self.rng.normal(size=(clutter, DIMENSION)),
            ]
        ).astype(np.float32)
        order = self.rng.permutation(keypoints)
        observed = np.concatenate([seen, np.full(clutter, -1)])
        return np.column_stack([xy, np.ones(keypoints)]).astype(np.float32)[order], values[order], observed[order]

    def write(self, images: ImageSet, indices, keypoints: int, far: float, feature_name: str) -> None:
        """The features of ``images[indices]`` as kapture files under the kapture folder the images
        live in (``<root>/sensors/records_data/<name>``): ``reconstruction/{keypoints,descriptors}/<feature_name>/``."""
        root = str(Path(images.image_root).parents[1])
        kapture_csv.keypoints_to_file(
            kapture_csv.get_feature_csv_fullpath(kapture.Keypoints, feature_name, root),
            kapture.Keypoints(feature_name, np.float32, 3),
        )
        kapture_csv.descriptors_to_file(
            kapture_csv.get_feature_csv_fullpath(kapture.Descriptors, feature_name, root),
            kapture.Descriptors(feature_name, np.float32, DIMENSION, feature_name, "L2"),
        )
        for index in indices:
            points, values, _ = self.features(images, int(index), keypoints, far)
            name = images.names[int(index)]
            kapture_features.image_keypoints_to_file(
                kapture_features.get_keypoints_fullpath(feature_name, root, name), points
            )
            kapture_features.image_descriptors_to_file(
                kapture_features.get_descriptors_fullpath(feature_name, root, name), values
            )
