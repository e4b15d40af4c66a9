"""Revisited Oxford/Paris evaluation (Radenovic et al., CVPR 2018; the paper's Table 2).

The ground truth is the published pickle ``gnd_roxford5k.pkl`` / ``gnd_rparis6k.pkl``: a dict
with ``imlist`` (database image names), ``qimlist`` (query names) and ``gnd``, one dict per
query with database indices ``easy``, ``hard``, ``junk`` and the query box ``bbx``. The three
protocols take as positives / ignored ("junk") images:

- Easy: ``easy`` / ``junk + hard``;  Medium: ``easy + hard`` / ``junk``;  Hard: ``hard`` /
  ``junk + easy``.

Metrics follow the revisitop evaluation code: junk images are removed from the ranking;
with ``r_j`` the 0-based position of the ``j``-th positive (0-based) in what remains and
``n`` the number of positives, ``AP = sum_j (P0_j + P1_j) / (2 n)`` (trapezoids of the
precision-recall curve), ``P0_j = j / r_j`` (1 when ``r_j = 0``), ``P1_j = (j + 1) / (r_j +
1)``; ``mP@k`` uses ``k' = min(k, position of the last positive)`` (1-based) and counts
the positives among the first ``k'``. Queries without a positive under a protocol are left
out of its averages. A ranking may be truncated (``EMPTY``-padded ``[Q, K]``): positives
it does not hold count as never retrieved, and a query with no positive retrieved has
``P@k = 0`` (the reference code assumes full rankings and has no such case).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import sparse

from locretrieval.errors import FIX_DATA_FILE, DataFileError
from locretrieval.restricted_pickle import load_plain_pickle
from locretrieval.retrieval import EMPTY, Ranking, relevant_hits

#: Where the authors publish the ground-truth files.
GROUNDTRUTH_URLS = {
    "roxford5k": "http://cmp.felk.cvut.cz/revisitop/data/datasets/roxford5k/gnd_roxford5k.pkl",
    "rparis6k": "http://cmp.felk.cvut.cz/revisitop/data/datasets/rparis6k/gnd_rparis6k.pkl",
}

#: Protocol -> (lists of positives, lists of junk).
PROTOCOLS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "easy": (("easy",), ("junk", "hard")),
    "medium": (("easy", "hard"), ("junk",)),
    "hard": (("hard",), ("junk", "easy")),
}

#: Columns of the tidy table (``revisited.csv``); ``k`` is 0 for mAP rows.
REVISITED_COLUMNS = ["dataset", "ranking", "protocol", "metric", "k", "value", "num_queries"]


@dataclass(frozen=True)
class RevisitedGroundTruth:
    """The content of a ``gnd_*.pkl`` file; ``gnd`` entries index ``imlist``."""

    imlist: list[str]
    qimlist: list[str]
    gnd: list[dict]

    def labels(self, protocol: str) -> tuple[sparse.csr_matrix, sparse.csr_matrix]:
        """Boolean ``[Q, N]`` positives and junk of ``protocol`` (easy, medium or hard)."""
        if protocol not in PROTOCOLS:
            raise ValueError(f"unknown protocol {protocol!r}; expected one of {list(PROTOCOLS)}")
        return tuple(self._matrix(keys) for keys in PROTOCOLS[protocol])  # type: ignore[return-value]

    def _matrix(self, keys: Sequence[str]) -> sparse.csr_matrix:
        lists = [np.concatenate([np.asarray(entry[key], dtype=np.int64).ravel() for key in keys]) for entry in self.gnd]
        rows = np.repeat(np.arange(len(lists)), [len(values) for values in lists])
        columns = np.concatenate(lists) if lists else np.empty(0, dtype=np.int64)
        # duplicates are merged by the conversion to CSR
        return sparse.csr_matrix(
            (np.ones(len(rows), dtype=bool), (rows, columns)), shape=(len(self.qimlist), len(self.imlist))
        )


def load_revisited_groundtruth(path: str | Path) -> RevisitedGroundTruth:
    """Read a revisited Oxford/Paris ``gnd_*.pkl`` file, checking its structure.

    The file is unpickled with `load_plain_pickle`: anything but plain data (builtin containers and
    scalars, numeric numpy arrays) is refused (`RefusedPickleError` naming the file and what was
    refused); a structure other than the published one is a `DataFileError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"revisited ground-truth file not found: {path}; the authors publish it at "
            + " and ".join(GROUNDTRUTH_URLS.values())
        )
    content = load_plain_pickle(path)  # a published file: plain data only, no code runs

    def wrong(problem: str) -> DataFileError:
        return DataFileError(path, problem, FIX_DATA_FILE)

    if not isinstance(content, dict) or not {"imlist", "qimlist", "gnd"} <= set(content):
        found = sorted(map(str, content)) if isinstance(content, dict) else type(content).__name__
        raise wrong(f"expected a dict with imlist, qimlist and gnd, found {found}")
    lists = {key: content[key] for key in ("imlist", "qimlist", "gnd")}
    if not all(isinstance(value, (list, tuple)) for value in lists.values()):
        raise wrong(f"imlist, qimlist and gnd must be lists, found {[type(v).__name__ for v in lists.values()]}")
    imlist, qimlist, gnd = (list(value) for value in lists.values())
    if not all(isinstance(name, str) for name in [*imlist, *qimlist]):
        raise wrong("imlist and qimlist must hold image names (strings)")
    if len(gnd) != len(qimlist):
        raise wrong(f"{len(gnd)} gnd entries for {len(qimlist)} queries")
    for q, entry in enumerate(gnd):
        if not isinstance(entry, dict) or {"easy", "hard", "junk"} - set(entry):
            found = sorted(map(str, entry)) if isinstance(entry, dict) else type(entry).__name__
            raise wrong(f"gnd entry {q} ({qimlist[q]}) must be a dict with easy, hard and junk, found {found}")
        for key in ("easy", "hard", "junk"):
            values = _indices(entry[key])
            if values is None:
                raise wrong(f"gnd entry {q} ({qimlist[q]}) has {key} that are not integer indices")
            if values.size and (values.min() < 0 or values.max() >= len(imlist)):
                raise wrong(f"gnd entry {q} ({qimlist[q]}) has {key} indices outside 0..{len(imlist) - 1}")
            entry[key] = values
    return RevisitedGroundTruth(imlist, qimlist, gnd)


def _indices(value: object) -> np.ndarray | None:
    """``value`` (a list or array of integers) as ``int64 [n]``; ``None`` when it is not that."""
    try:
        array = np.asarray(value) if isinstance(value, (list, tuple, np.ndarray)) else None
    except (ValueError, OverflowError):  # ragged or out of range
        return None
    if array is None or array.dtype == object or (array.size and array.dtype.kind not in "iu"):
        return None
    if array.size and array.dtype.kind == "u" and array.max() > np.iinfo(np.int64).max:
        return None
    return array.astype(np.int64).ravel()


def revisited_scores(
    indices: np.ndarray, positives: sparse.csr_matrix, junk: sparse.csr_matrix, kappas: Sequence[int]
) -> tuple[np.ndarray, np.ndarray]:
    """Per-query ``AP [Q]`` and ``P@kappa [Q, len(kappas)]``; NaN for queries without positives."""
    indices = np.asarray(indices)
    is_positive = relevant_hits(indices, positives)
    is_junk = relevant_hits(indices, junk) & ~is_positive
    rank = np.cumsum(~is_junk, axis=1) - 1  # position once junk is removed, 0-based
    order = np.cumsum(is_positive, axis=1) - 1  # j: how many positives come before
    num_positives = np.diff(positives.indptr)
    with np.errstate(invalid="ignore", divide="ignore"):  # slots that are not positives divide by 0
        before = np.where(rank == 0, 1.0, order / rank)
        after = (order + 1) / (rank + 1)
        ap = np.where(is_positive, before + after, 0.0).sum(axis=1) / (2.0 * num_positives)
        last = np.where(is_positive, rank + 1, 0).max(axis=1)  # 1-based position of the last positive
        precision = np.stack(
            [
                np.where(is_positive & (rank + 1 <= np.minimum(last, k)[:, None]), 1, 0).sum(axis=1)
                / np.maximum(np.minimum(last, k), 1)
                for k in kappas
            ],
            axis=1,
        ).astype(np.float64)
    empty = num_positives == 0
    ap[empty] = np.nan
    precision[empty] = np.nan
    return ap, precision


def evaluate_revisited(
    ranking: Ranking,
    groundtruth: RevisitedGroundTruth,
    dataset: str,
    kappas: Sequence[int] = (1, 5, 10),
) -> pd.DataFrame:
    """mAP and mP@k of a ranking under the Easy, Medium and Hard protocols (tidy rows).

    ``ranking`` holds, per query of ``qimlist`` (in that order), indices into ``imlist``
    best first (`Ranking` checks the shape and that empty slots come last). Values are
    fractions in [0, 1].
    """
    name, indices = ranking.name, ranking.indices
    if len(indices) != len(groundtruth.qimlist):
        raise ValueError(
            f"{dataset}: ranking {name!r} has {len(indices)} rows, qimlist {len(groundtruth.qimlist)} queries"
        )
    if indices.max(initial=EMPTY) >= len(groundtruth.imlist):
        raise ValueError(f"{dataset}: ranking {name!r} indices must lie in 0..{len(groundtruth.imlist) - 1}")
    rows = []
    for protocol in PROTOCOLS:
        ap, precision = revisited_scores(indices, *groundtruth.labels(protocol), kappas)
        evaluated = ~np.isnan(ap)
        if not evaluated.any():
            continue
        count = int(evaluated.sum())
        rows.append((dataset, name, protocol, "map", 0, float(ap[evaluated].mean()), count))
        rows += [
            (dataset, name, protocol, "mp", int(k), float(value), count)
            for k, value in zip(kappas, precision[evaluated].mean(axis=0))
        ]
    return pd.DataFrame(rows, columns=REVISITED_COLUMNS)
