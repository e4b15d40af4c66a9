"""Kapture feature folders (keypoints, descriptors, global features): headers and raw arrays.

A feature folder holds a one-line header (``keypoints.txt``: ``name, dtype, dsize``;
``descriptors.txt``: ``name, dtype, dsize, keypoints_type, metric_type``;
``global_features.txt``: ``name, dtype, dsize, metric_type``) and one raw file per image
of ``dsize`` values of ``dtype`` per row. kapture's own header readers ``eval`` the dtype
field, which runs whatever a data file holds; headers are parsed here instead, and the
dtype must be one of `FEATURE_DTYPES` (optionally written ``np.float32`` /
``numpy.float32``, as kapture writes it either way).

Published features live in one of two layouts (`feature_folder_candidates`): kapture's own,
``<kapture>/reconstruction/<kind>/<name>/``, or the one ``kapture_download_dataset.py`` installs
beside the kapture folders, ``<dataset>/global_features/<name>/global_features/`` and
``<dataset>/local_features/<name>/{keypoints,descriptors}/`` (e.g. ``r2d2_WASF-N8_20k``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from locretrieval.scene.kapture_io import KaptureFormatError, read_csv_rows

#: The numpy dtypes a feature header may name (anything else is refused, never evaluated).
FEATURE_DTYPES: dict[str, np.dtype] = {
    name: np.dtype(name)
    for name in (
        "uint8",
        "int8",
        "uint16",
        "int16",
        "uint32",
        "int32",
        "uint64",
        "int64",
        "float16",
        "float32",
        "float64",
    )
}
#: Feature kind -> (its file suffix, the downloader's family folder).
FEATURE_KINDS: dict[str, tuple[str, str]] = {
    "keypoints": (".kpt", "local_features"),
    "descriptors": (".desc", "local_features"),
    "global_features": (".gfeat", "global_features"),
}
#: Ancestors of a kapture folder searched for the downloader's family folders (``<dataset>/mapping``,
#: ``<dataset>/<location>/mapping``, ``<dataset>/<building>/<release>/mapping``).
DOWNLOADER_DEPTH = 3
#: Header fields of each feature kind, in kapture's order.
HEADER_FIELDS: dict[str, tuple[str, ...]] = {
    "keypoints": ("name", "dtype", "dsize"),
    "descriptors": ("name", "dtype", "dsize", "keypoints_type", "metric_type"),
    "global_features": ("name", "dtype", "dsize", "metric_type"),
}


@dataclass(frozen=True)
class FeatureHeader:
    """A parsed feature header: ``fields`` holds every field by name as text."""

    path: Path
    kind: str
    dtype: np.dtype
    dsize: int
    fields: dict[str, str]

    @property
    def name(self) -> str:
        return self.fields["name"]

    @property
    def metric_type(self) -> str | None:
        return self.fields.get("metric_type")


def parse_dtype(text: str) -> np.dtype | None:
    """The dtype a header field names (``float32``, ``np.float32``, ``numpy.float32``), or ``None``."""
    name = text.strip()
    for prefix in ("numpy.", "np."):
        name = name.removeprefix(prefix)
    return FEATURE_DTYPES.get(name)


def read_feature_header(path: str | Path, kind: str) -> FeatureHeader:
    """The header of a ``kind`` feature folder (`HEADER_FIELDS`); a named error for anything else.

    Raises `FileNotFoundError` when ``path`` is missing and `KaptureFormatError` (file and
    line) for a wrong field count, an unknown dtype or a non-positive ``dsize``.
    """
    path = Path(path)
    expected = HEADER_FIELDS[kind]
    if not path.is_file():
        raise FileNotFoundError(f"kapture {kind} header not found: {path}")
    rows = read_csv_rows(path, len(expected), len(expected))
    if len(rows) != 1:
        raise ValueError(f"{path}: expected one header line '{', '.join(expected)}', found {len(rows)}")
    row = rows[0]
    fields = dict(zip(expected, row.fields))
    dtype = parse_dtype(fields["dtype"])
    if dtype is None:
        raise KaptureFormatError(
            path, row.line, row.text, f"dtype {fields['dtype']!r} is not one of {sorted(FEATURE_DTYPES)}"
        )
    try:
        dsize = int(fields["dsize"])
    except ValueError:
        raise row.error(f"dsize {fields['dsize']!r} is not an integer") from None
    smallest = 2 if kind == "keypoints" else 1  # keypoints hold at least x, y
    if dsize < smallest:
        raise row.error(f"dsize must be >= {smallest} for {kind}, got {dsize}")
    return FeatureHeader(path, kind, dtype, dsize, fields)


def read_feature_array(path: str | Path, header: FeatureHeader) -> np.ndarray:
    """The rows ``[n, dsize]`` of ``header.dtype`` stored raw in ``path``; a named error when the
    file size is not a whole number of rows."""
    path = Path(path)
    row_bytes = header.dsize * header.dtype.itemsize
    size = path.stat().st_size
    if size % row_bytes:
        raise ValueError(
            f"{path}: {size} bytes is not a whole number of {header.kind} rows of {header.dsize} x {header.dtype} "
            f"({row_bytes} bytes each; header {header.path})"
        )
    return np.fromfile(path, dtype=header.dtype).reshape(-1, header.dsize)


def feature_folder_candidates(kapture_root: str | Path, kind: str, name: str) -> list[Path]:
    """Where the published ``kind`` features ``name`` of a kapture folder may be, in search order:
    ``<kapture>/reconstruction/<kind>/<name>``, then ``<ancestor>/<family>/<name>/<kind>`` for
    the folder's `DOWNLOADER_DEPTH` nearest ancestors (the downloader's layout)."""
    root = Path(kapture_root)
    family = FEATURE_KINDS[kind][1]
    return [root / "reconstruction" / kind / name, *(a / family / name / kind for a in root.parents[:DOWNLOADER_DEPTH])]


def find_feature_folder(kapture_root: str | Path, kind: str, name: str) -> Path | None:
    """The first `feature_folder_candidates` folder holding the ``<kind>.txt`` header, or None."""
    return next((f for f in feature_folder_candidates(kapture_root, kind, name) if (f / f"{kind}.txt").is_file()), None)


def feature_names(kapture_root: str | Path, kind: str) -> set[str]:
    """The names of the ``kind`` features found for a kapture folder, in either layout."""
    root = Path(kapture_root)
    family = FEATURE_KINDS[kind][1]
    parents = [root / "reconstruction" / kind, *(a / family for a in root.parents[:DOWNLOADER_DEPTH])]
    return {
        child.name
        for parent in parents
        if parent.is_dir()
        for child in parent.iterdir()
        if find_feature_folder(root, kind, child.name) is not None
    }


def feature_file(folder: Path, kind: str, image_name: str) -> Path:
    """The file of ``image_name`` in a ``kind`` feature folder (``<folder>/<image name><suffix>``)."""
    return folder / f"{image_name}{FEATURE_KINDS[kind][0]}"
