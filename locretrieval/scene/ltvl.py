"""Poses -> visuallocalization.net (LTVL) submission files, with each dataset's image naming."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from pathlib import Path, PurePosixPath

import numpy as np

from locretrieval.cache import atomic_path
from locretrieval.scene.types import LTVL_NAME_STYLES


def ltvl_name(name: str, style: str) -> str:
    """The image name LTVL expects for ``name`` (a records_data path) under ``style``."""
    if style == "full":
        return name
    if style == "basename":
        return PurePosixPath(name).name
    if style == "strip_prefix":
        prefix, separator, rest = name.partition("/")
        if not separator or not rest:
            raise ValueError(f"LTVL name style 'strip_prefix': image name {name!r} has no leading folder to strip")
        return rest
    raise ValueError(f"unknown LTVL name style {style!r}; expected one of {LTVL_NAME_STYLES}")


def write_ltvl(
    path: str | Path, names: Sequence[str], qvec: np.ndarray, tvec: np.ndarray, name_style: str = "full"
) -> int:
    """Write a visuallocalization.net submission: ``name qw qx qy qz tx ty tz`` per line.

    Poses are world-to-camera (wxyz quaternion, translation -- not the camera centre), as
    kapture stores them. Rows with a NaN pose are not written; returns how many were skipped.
    """
    if name_style not in LTVL_NAME_STYLES:
        raise ValueError(f"unknown LTVL name style {name_style!r}; expected one of {LTVL_NAME_STYLES}")
    qvec = np.asarray(qvec, dtype=np.float64)
    tvec = np.asarray(tvec, dtype=np.float64)
    if qvec.shape != (len(names), 4) or tvec.shape != (len(names), 3):
        raise ValueError(
            f"write_ltvl: {len(names)} names need qvec [N, 4] and tvec [N, 3], got {qvec.shape} and {tvec.shape}"
        )
    known = np.isfinite(qvec).all(axis=1) & np.isfinite(tvec).all(axis=1)
    written = [ltvl_name(name, name_style) for name, ok in zip(names, known) if ok]
    clashes = sorted(n for n, count in Counter(written).items() if count > 1)
    if clashes:
        raise ValueError(
            f"write_ltvl: name style {name_style!r} maps several images to the same name, e.g. {clashes[:3]}"
        )
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
