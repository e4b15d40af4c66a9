"""`PoseEstimates`: what every paradigm returns for one ranking and one method."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from locretrieval import geometry

if TYPE_CHECKING:
    import pandas as pd  # imported by the table's function: the SfM workers, which import this module, need none

#: Failure reason of a query whose estimate exists.
LOCALIZED = ""


@dataclass
class PoseEstimates:
    """Estimated world-to-camera poses of every query for each k.

    ``qvec [len(ks), Q, 4]`` (wxyz) and ``tvec [len(ks), Q, 3]`` are NaN where no estimate
    exists; ``failures [len(ks), Q]`` then holds the reason (``""`` where estimated).
    ``k_effective``: the number of top images each k used (``ks`` when ``None``; see `labelled`).
    """

    ranking: str
    ranking_kind: str
    paradigm: str
    method: str
    ks: list[int]
    qvec: np.ndarray
    tvec: np.ndarray
    failures: np.ndarray
    k_effective: list[int] | None = None

    def __post_init__(self) -> None:
        self.k_effective = list(self.ks) if self.k_effective is None else self.k_effective
        if len(self.k_effective) != len(self.ks):
            raise ValueError(
                f"{self.ranking}/{self.paradigm}/{self.method}: k_effective {self.k_effective} for ks {self.ks}"
            )
        shape = (len(self.ks), self.qvec.shape[1])
        if self.qvec.shape != (*shape, 4) or self.tvec.shape != (*shape, 3) or self.failures.shape != shape:
            raise ValueError(
                f"{self.ranking}/{self.paradigm}/{self.method}: inconsistent estimate shapes "
                f"{self.qvec.shape}, {self.tvec.shape}, {self.failures.shape} for ks={self.ks}"
            )
        missing = ~np.isfinite(self.qvec).all(-1) | ~np.isfinite(self.tvec).all(-1)
        if (missing & (self.failures == LOCALIZED)).any():
            raise ValueError(f"{self.ranking}/{self.paradigm}/{self.method}: a missing estimate has no failure reason")

    def labelled(self, requested: Sequence[int], depth: int) -> "PoseEstimates":
        """These estimates (of ks clamped to the ranking's ``depth``) under the ``requested`` ks:
        a k beyond ``depth`` holds the estimates of k = ``depth``, its ``k_effective``."""
        ks = sorted({int(k) for k in requested})
        effective = [min(k, depth) for k in ks]
        rows = [self.ks.index(k) for k in effective]
        return dataclasses.replace(
            self, ks=ks, k_effective=effective, qvec=self.qvec[rows], tvec=self.tvec[rows], failures=self.failures[rows]
        )

    def errors(self, q_reference: np.ndarray, t_reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position (scene units) and rotation (degrees) errors ``[len(ks), Q]`` (paper eq. 3-4).

        NaN where there is no estimate or no reference pose.
        """
        c_estimated = geometry.camera_centers(self.qvec, self.tvec)
        c_reference = geometry.camera_centers(q_reference, t_reference)
        return (
            geometry.position_errors(c_estimated, c_reference[None]),
            geometry.rotation_errors_deg(self.qvec, np.asarray(q_reference)[None]),
        )


#: Columns of the estimated-pose table (``estimated_poses.csv.gz``): one row per ranking x
#: paradigm x method x k x query with an estimate, the world-to-camera pose ``q = (qw, qx, qy, qz)``,
#: ``t = (tx, ty, tz)`` (metres), as kapture stores it.
ESTIMATED_POSE_COLUMNS = [
    "dataset", "ranking", "ranking_kind", "paradigm", "method", "k", "query", "qw", "qx", "qy", "qz", "tx", "ty", "tz",
]  # fmt: skip


def estimated_pose_table(dataset: str, estimates: Sequence[PoseEstimates], query_names: Sequence[str]) -> pd.DataFrame:
    """The estimated poses of every ``estimates`` (queries named by ``query_names``, in order), one
    row per ranking x paradigm x method x k x query that has an estimate (`ESTIMATED_POSE_COLUMNS`)."""
    import pandas as pd

    frames = []
    for e in estimates:
        found = np.isfinite(e.qvec).all(-1) & np.isfinite(e.tvec).all(-1)  # [len(ks), Q]
        k_rows, query_rows = np.nonzero(found)
        labels = {
            "dataset": dataset,
            "ranking": e.ranking,
            "ranking_kind": e.ranking_kind,
            "paradigm": e.paradigm,
            "method": e.method,
            "k": np.asarray(e.ks)[k_rows],
            "query": np.asarray(query_names, dtype=object)[query_rows],
        }
        poses = np.concatenate([e.qvec[found], e.tvec[found]], axis=1)
        frames.append(
            pd.DataFrame({**labels, **dict(zip(ESTIMATED_POSE_COLUMNS[-7:], poses.T))}, columns=ESTIMATED_POSE_COLUMNS)
        )
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=ESTIMATED_POSE_COLUMNS)
