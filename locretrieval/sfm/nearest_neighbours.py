"""Mutual nearest neighbours with Lowe's ratio test between local descriptors: two matchers,
one shaped for a CPU's cache and one for a GPU, with identical results.

Both normalise descriptors to unit L2 norm and find, for each row of the first image, its best
and second-best similarity and its best column; a row is matched to its best column when that
column's best row is the row (mutual) and ``d_best <= ratio * d_second`` for the distances
``d = sqrt(2 - 2 s)`` of unit vectors. Ties go to the lowest index both ways (numpy's
``argmax``); a tie for the best value makes the second-best equal to it; with a single column
there is no ratio test. Matches are ``int32 [m, 2]`` (row in the first image, row in the other),
ordered by the first.

- `NearestNeighbourMatcher` (CPU): one pair at a time, the similarity matrix in about square
  blocks that are reduced while they are in the last-level cache (1.4x the bare product at
  20,000 keypoints, docs/performance.md).
- `BatchedMatcher` (GPU): one image against many partners in one product, on descriptors kept on
  the device (`DeviceDescriptors`), reduced with whole-tensor maxima, matches returned in bulk.

Why by hand: faiss and kornia give nearest neighbours but neither the mutual check with these
tie rules nor the second-best value in the same pass, and a full ``[n, m]`` matrix per pair (the
naive torch version) costs memory bandwidth the blocked and batched forms avoid.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from locretrieval.config import require

if TYPE_CHECKING:
    import torch  # imported where it is used: precomputed features are matched in workers that import it

#: Bytes of one block of similarities on a CPU: reduced while it is in the last-level cache.
CPU_BLOCK_BYTES = 8 << 20
#: Width of the column tiles through which each row's best column is found, and height of the
#: groups of rows through which each column's is.
TILE = 128
#: Floating-point types of the similarities.
PRECISIONS = ("float32", "float16")
#: Smallest norm a descriptor is divided by (zero rows stay zero).
NORM_EPSILON = 1e-12


def normalized_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """Float32 rows of unit L2 norm (zero rows stay zero)."""
    values = np.asarray(descriptors, dtype=np.float32)
    return values / np.maximum(np.linalg.norm(values, axis=1, keepdims=True), NORM_EPSILON)


def ratio_passes(best: torch.Tensor, second: torch.Tensor, ratio: float) -> torch.Tensor:
    """Lowe's test on squared distances of unit vectors (``2 - 2 s``), in float32 on both
    matchers' devices (the same operations, so the same outcome); ``second = -inf``: passes."""
    best, second = best.float(), second.float()
    return (2 - 2 * best).clamp_min(0) <= ratio**2 * (2 - 2 * second).clamp_min(0)


@dataclass(frozen=True)
class NearestNeighbourMatcher:
    """Mutual nearest neighbours with Lowe's ratio test on the CPU, one block of similarities at a time.

    The similarity matrix of a pair is computed one block at a time, about square, of
    ``block_bytes`` (small enough to be reduced while it is in cache, which also keeps the
    matrix product as fast as one whole product). Each block updates running per-row and
    per-column state, so nothing of the size of the matrix is kept:

    - per row: the best and second-best values and the best column, found through the maxima
      of column tiles of `TILE` (``amax``, one vectorised pass: ``argmax`` over a long
      row is several times slower on a CPU) and merged with the earlier blocks of the row;
    - per column: the best value in each group of `TILE` rows (``amax`` again). A row's best
      column is a mutual match only if that column's best value is the row's and first reached
      in the row's group; only for those candidates is the column's first best row in the
      group found, from their similarities recomputed (each candidate's column with its group's
      rows: at most ``TILE / columns`` of the whole product).

    (The recomputed candidate similarities may round differently from the blocked product: two
    rows within one rounding step of each other for a column can then be ordered differently;
    exact ties, as the tests use, cannot.) ``precision``: ``float32`` or ``float16`` similarities.
    """

    ratio: float
    precision: str
    block_bytes: int

    def __post_init__(self) -> None:
        require(0 < self.ratio <= 1, "ratio", f"must be in (0, 1], got {self.ratio}")
        require(self.precision in PRECISIONS, "precision", f"must be one of {list(PRECISIONS)}, got {self.precision!r}")
        require(
            self.block_bytes >= 4 * TILE**2,
            "block_bytes",
            f"must hold {TILE} x {TILE} float32 similarities, got {self.block_bytes}",
        )

    @property
    def device(self) -> str:
        return "cpu"

    def __call__(self, first: np.ndarray, others: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Matches ``int32 [m, 2]`` (row in ``first``, row in the other) with each of ``others``."""
        import torch

        dtype = getattr(torch, self.precision)
        query = torch.from_numpy(normalized_descriptors(first)).to(dtype)
        return [self._match(query, torch.from_numpy(normalized_descriptors(other)).to(dtype)) for other in others]

    def block_shape(self, rows: int, columns: int, element_size: int) -> tuple[int, int]:
        """Rows (all, or a multiple of `TILE`) and columns (a multiple of `TILE`) of the blocks
        of similarities: about square, at most ``block_bytes``, of equal sizes."""
        tiles = -(-columns // TILE)
        column_blocks = -(-tiles // max(1, int((self.block_bytes / element_size) ** 0.5) // TILE))
        width = -(-tiles // column_blocks) * TILE
        max_height = self.block_bytes // (width * element_size) // TILE * TILE
        if rows <= max_height:
            return rows, width
        return -(-rows // -(-rows // max_height) // TILE) * TILE, width

    def _match(self, query: torch.Tensor, partner: torch.Tensor) -> np.ndarray:
        import torch

        rows, columns = len(query), len(partner)
        if not rows or not columns:
            return np.empty((0, 2), dtype=np.int32)
        height, width = self.block_shape(rows, columns, query.element_size())
        state = _BestValues(rows, columns, query)
        buffer = torch.empty((height, width), dtype=query.dtype)  # reused: no page faults
        for first_column in range(0, columns, width):
            tile = torch.zeros((query.shape[1], width), dtype=query.dtype)
            valid = min(width, columns - first_column)
            tile[:, :valid] = partner[first_column : first_column + valid].T
            for first_row in range(0, rows, height):
                stop = min(rows, first_row + height)
                similarity = torch.mm(query[first_row:stop], tile, out=buffer[: stop - first_row])
                similarity[:, valid:] = -torch.inf
                state.update(similarity, first_row, first_column, valid)
        keep = state.mutual(query, partner) & ratio_passes(state.row_best, state.row_second, self.ratio)
        return torch.column_stack([torch.nonzero(keep).squeeze(1), state.row_argmax[keep]]).numpy().astype(np.int32)


class _BestValues:
    """Running best values of the rows (best, second best, first best column) and the best value
    of each column in each group of `TILE` rows, of a similarity matrix seen a block at a time."""

    def __init__(self, rows: int, columns: int, like: torch.Tensor) -> None:
        import torch

        def full(shape: tuple[int, ...], value: float, dtype: torch.dtype = like.dtype) -> torch.Tensor:
            return torch.full(shape, value, device=like.device, dtype=dtype)

        self.row_best, self.row_second, self.row_argmax = (
            full((rows,), -torch.inf),
            full((rows,), -torch.inf),
            full((rows,), 0, torch.int64),
        )
        self.column_best = full((-(-rows // TILE), columns), -torch.inf)  # [group of rows, column]

    def update(self, similarity: torch.Tensor, first_row: int, first_column: int, valid: int) -> None:
        """Merge one block: rows from ``first_row`` (a multiple of `TILE`; fewer than a multiple
        of `TILE` rows only in the last block), columns from ``first_column``, of which the
        first ``valid`` are real (the rest: -inf padding)."""
        import torch

        group, columns, whole = first_row // TILE, slice(first_column, first_column + valid), len(similarity) // TILE
        if whole:
            self.column_best[group : group + whole, columns] = (
                similarity[: whole * TILE].view(whole, TILE, -1).amax(1)[:, :valid]
            )
        if whole * TILE < len(similarity):
            self.column_best[group + whole, columns] = similarity[whole * TILE :].amax(0)[:valid]
        rows = slice(first_row, first_row + len(similarity))
        best, second, argmax = row_best_two(similarity)
        old_best = self.row_best[rows]
        self.row_second[rows] = torch.maximum(
            torch.maximum(self.row_second[rows], second), torch.minimum(old_best, best)
        )
        self.row_argmax[rows] = torch.where(best > old_best, argmax + first_column, self.row_argmax[rows])
        self.row_best[rows] = torch.maximum(old_best, best)

    def mutual(self, query: torch.Tensor, partner: torch.Tensor) -> torch.Tensor:
        """Boolean ``[rows]``: the row is its best column's first best row (``query``, ``partner``:
        the descriptors whose products the blocks held)."""
        import torch

        column_best = self.column_best.amax(0)
        first_group = first_equal(self.column_best.T, column_best)
        group = torch.arange(len(self.row_best), device=query.device) // TILE
        candidate = (self.row_best == column_best[self.row_argmax]) & (first_group[self.row_argmax] == group)
        mutual = torch.zeros_like(candidate)
        for index in torch.unique(group[candidate]).tolist():
            members = torch.nonzero(candidate & (group == index)).squeeze(1)
            start = index * TILE
            recomputed = partner[self.row_argmax[members]] @ query[start : start + TILE].T  # [candidates, group rows]
            mutual[members] = first_equal(recomputed, recomputed.amax(1)) + start == members
        return mutual


def row_best_two(similarity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each row's best value, second-best value (equal to the best on a tie) and first best
    column, of a ``[rows, columns]`` block whose width is a multiple of `TILE`: one pass of tile
    maxima over the block, then work on one tile per row."""
    import torch

    rows = torch.arange(len(similarity), device=similarity.device)
    tiles = similarity.view(len(similarity), -1, TILE)
    tile_best = tiles.amax(2)
    best = tile_best.amax(1)
    tile = first_equal(tile_best, best)
    within_tile = tiles[rows, tile]  # a copy: [rows, TILE]
    column = first_equal(within_tile, best)
    within_tile[rows, column] = -torch.inf
    tile_best[rows, tile] = within_tile.amax(1)
    return best, tile_best.amax(1), tile * TILE + column


def first_equal(values: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Per row, the first column of ``values`` equal to that row's target."""
    import torch

    return (values == targets[:, None]).to(torch.uint8).argmax(1)


def normalized_on_device(descriptors: np.ndarray, device: torch.device | str, dtype: torch.dtype) -> torch.Tensor:
    """``descriptors [n, D]`` moved to ``device`` as they are stored (uint8 SIFT: a quarter of the
    bytes), normalised there in float32 and cast to ``dtype``."""
    import torch

    values = torch.from_numpy(np.ascontiguousarray(descriptors)).to(device, non_blocking=True).float()
    return (values / values.norm(dim=1, keepdim=True).clamp_min(NORM_EPSILON)).to(dtype)


@dataclass(frozen=True)
class BatchedMatcher:
    """Mutual nearest neighbours with Lowe's ratio test of one image against many partners, on a GPU.

    The partners' descriptors are stacked, each padded to a common width (a multiple of `TILE`),
    and multiplied with the first image's in one product per batch of at most ``batch_bytes`` of
    similarities ``[rows, partners x width]`` (rows split only when one partner alone exceeds
    it). Each batch is reduced with whole-tensor kernels: the best row of every column (``max``
    over the rows, merged across row blocks keeping the first on ties) and per row and partner
    the best, second-best and first best column (`row_best_two`). The mutual check, the ratio
    test and the gathering of every partner's matches run on the device; one transfer returns
    them. Results equal `NearestNeighbourMatcher`'s at the same precision (same tie rules).
    """

    ratio: float
    device: str
    precision: str
    batch_bytes: int

    def __post_init__(self) -> None:
        require(0 < self.ratio <= 1, "ratio", f"must be in (0, 1], got {self.ratio}")
        require(self.precision in PRECISIONS, "precision", f"must be one of {list(PRECISIONS)}, got {self.precision!r}")
        require(
            self.batch_bytes >= 4 * TILE**2,
            "batch_bytes",
            f"must hold {TILE} x {TILE} float32 similarities, got {self.batch_bytes}",
        )

    @property
    def dtype(self) -> torch.dtype:
        import torch

        return getattr(torch, self.precision)

    def __call__(self, first: np.ndarray, others: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Matches ``int32 [m, 2]`` of ``first`` with each of ``others`` (numpy in, numpy out)."""
        return self.match(
            normalized_on_device(first, self.device, self.dtype),
            [normalized_on_device(other, self.device, self.dtype) for other in others],
        )

    def match(self, first: torch.Tensor, partners: Sequence[torch.Tensor]) -> list[np.ndarray]:
        """Matches of ``first`` with each of ``partners``: unit-norm descriptors on the device (`DeviceDescriptors`)."""
        empty = np.empty((0, 2), dtype=np.int32)
        results: list[np.ndarray] = [empty] * len(partners)
        useful = [j for j, partner in enumerate(partners) if len(partner)]
        if not len(first) or not useful:
            return results
        for batch in self._batches(len(first), [len(partners[j]) for j in useful], first.element_size()):
            selected = [useful[j] for j in batch]
            for j, matches in zip(selected, self._match_batch(first, [partners[j] for j in selected])):
                results[j] = matches
        return results

    def _batches(self, rows: int, widths: Sequence[int], element_size: int) -> list[list[int]]:
        """Consecutive groups of partners whose similarities with all ``rows``, each partner
        padded to the group's widest (a multiple of `TILE`), fit ``batch_bytes``; a partner that
        alone exceeds it is a group of its own (its rows are then split, `_match_batch`)."""
        batches: list[list[int]] = []
        widest = 0
        for j, width in enumerate(widths):
            padded = max(widest, -(-width // TILE) * TILE)
            if batches and widest and rows * padded * (len(batches[-1]) + 1) * element_size <= self.batch_bytes:
                batches[-1].append(j)
                widest = padded
            else:
                batches.append([j])
                widest = -(-width // TILE) * TILE
        return batches

    def _match_batch(self, first: torch.Tensor, partners: Sequence[torch.Tensor]) -> list[np.ndarray]:
        import torch

        rows, count = len(first), len(partners)
        widths = [len(partner) for partner in partners]
        width = -(-max(widths) // TILE) * TILE
        stacked = torch.zeros((count, width, first.shape[1]), device=first.device, dtype=first.dtype)
        for j, partner in enumerate(partners):
            stacked[j, : widths[j]] = partner
        stacked = stacked.view(count * width, -1)
        height = min(rows, max(TILE, self.batch_bytes // (count * width * first.element_size()) // TILE * TILE))
        column_best = torch.full((count * width,), -torch.inf, device=first.device, dtype=first.dtype)
        column_argmax = torch.zeros(count * width, device=first.device, dtype=torch.int64)
        row_best, row_second, row_argmax = [], [], []
        for start in range(0, rows, height):
            similarity = (first[start : start + height] @ stacked.T).view(-1, count, width)
            for j, used in enumerate(widths):
                similarity[:, j, used:] = -torch.inf  # padding is nobody's neighbour
            best, argmax = similarity.view(len(similarity), -1).max(0)
            improved = best > column_best  # strictly: an earlier row block keeps a tie
            column_argmax = torch.where(improved, argmax + start, column_argmax)
            column_best = torch.maximum(column_best, best)
            block_best = row_best_two(similarity.view(-1, width))
            for collected, values in zip((row_best, row_second, row_argmax), block_best):
                collected.append(values.view(-1, count))
        best, second, argmax = (torch.cat(values) for values in (row_best, row_second, row_argmax))  # [rows, count]
        back = column_argmax.view(count, width).gather(
            1, argmax.T
        )  # [count, rows]: the best row of each row's best column
        keep = (back == torch.arange(rows, device=first.device)) & ratio_passes(best, second, self.ratio).T
        partner, row = torch.nonzero(keep, as_tuple=True)  # sorted by partner, then row
        found = torch.stack([row, argmax.T[partner, row]], 1).to(torch.int32).cpu().numpy()
        counts = torch.bincount(partner, minlength=count).cpu().numpy()
        return np.split(found, np.cumsum(counts)[:-1])


class DeviceDescriptors:
    """Unit-norm descriptors of images kept on a device, least recently used dropped first beyond
    ``capacity_bytes``; ``load(names) -> {name: descriptors [n, D]}`` reads those not resident."""

    def __init__(
        self,
        load: Callable[[Sequence[str]], dict[str, np.ndarray]],
        device: str,
        dtype: torch.dtype,
        capacity_bytes: int,
    ) -> None:

        self._load, self.device, self.dtype, self.capacity_bytes = load, device, dtype, capacity_bytes
        self._resident: OrderedDict[str, torch.Tensor] = OrderedDict()
        self._bytes = 0

    def __contains__(self, name: str) -> bool:
        return name in self._resident

    def get(self, names: Sequence[str], loaded: dict[str, np.ndarray] | None = None) -> list[torch.Tensor]:
        """The descriptors of ``names`` on the device; ``loaded`` may hold some already read (prefetched)."""
        loaded = dict(loaded or {})
        absent = [name for name in dict.fromkeys(names) if name not in self._resident and name not in loaded]
        if absent:
            loaded.update(self._load(absent))
        for name in names:
            if name in self._resident:
                self._resident.move_to_end(name)
            else:
                tensor = normalized_on_device(loaded[name], self.device, self.dtype)
                self._resident[name] = tensor
                self._bytes += tensor.nbytes
        result = [self._resident[name] for name in names]
        while self._bytes > self.capacity_bytes and len(self._resident) > len(set(names)):
            _, dropped = self._resident.popitem(last=False)
            self._bytes -= dropped.nbytes
        return result
