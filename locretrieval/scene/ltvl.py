"""Poses -> visuallocalization.net (LTVL) submission files, with each dataset's image naming."""

from __future__ import annotations

import abc
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from locretrieval.cache import atomic_path


class LtvlNames(abc.ABC):
    """How a dataset's LTVL submissions name its images (a dataset fact, ``data.ltvl_names``, chosen
    by its ``_target_``: ``configs/data/ltvl_names/``). A new one subclasses this, in any package."""

    @abc.abstractmethod
    def __call__(self, name: str) -> str:
        """The image name LTVL expects for ``name`` (a records_data path); ``ValueError`` when it has none."""


@dataclass
class KaptureNames(LtvlNames):
    """The names as kapture lists them (GangnamStation, Baidu)."""

    def __call__(self, name: str) -> str:
        return name


@dataclass
class FileNames(LtvlNames):
    """The file name only (Aachen, InLoc)."""

    def __call__(self, name: str) -> str:
        return PurePosixPath(name).name


@dataclass
class WithoutFirstFolder(LtvlNames):
    """The name without its first folder (RobotCar: ``night/rear/123.jpg`` -> ``rear/123.jpg``,
    the camera name then the file name)."""

    def __call__(self, name: str) -> str:
        prefix, separator, rest = name.partition("/")
        if not separator or not rest:
            raise ValueError(f"LTVL names without the first folder: image name {name!r} has no leading folder to strip")
        return rest


def write_ltvl(
    path: str | Path, names: Sequence[str], qvec: np.ndarray, tvec: np.ndarray, ltvl_names: LtvlNames
) -> int:
    """Write a visuallocalization.net submission: ``name qw qx qy qz tx ty tz`` per line.

    Poses are world-to-camera (wxyz quaternion, translation -- not the camera centre), as
    kapture stores them; images are named by ``ltvl_names``. Rows with a NaN pose are not written;
    returns how many were skipped.
    """
    qvec = np.asarray(qvec, dtype=np.float64)
    tvec = np.asarray(tvec, dtype=np.float64)
    if qvec.shape != (len(names), 4) or tvec.shape != (len(names), 3):
        raise ValueError(
            f"write_ltvl: {len(names)} names need qvec [N, 4] and tvec [N, 3], got {qvec.shape} and {tvec.shape}"
        )
    known = np.isfinite(qvec).all(axis=1) & np.isfinite(tvec).all(axis=1)
    written = [ltvl_names(name) for name, ok in zip(names, known) if ok]
    clashes = sorted(n for n, count in Counter(written).items() if count > 1)
    if clashes:
        raise ValueError(f"write_ltvl: {ltvl_names} maps several images to the same name, e.g. {clashes[:3]}")
    spaced = [n for n in written if any(c.isspace() for c in n)]
    if spaced:
        raise ValueError(
            f"write_ltvl: LTVL lines are space-separated, image names must not contain whitespace: {spaced[:3]}"
        )
    values = np.concatenate([qvec, tvec], axis=1)[known]
    lines = [f"{name} {' '.join(repr(float(v)) for v in row)}\n" for name, row in zip(written, values)]
    with atomic_path(path) as temporary:
        temporary.write_text("".join(lines))
    return int((~known).sum())
