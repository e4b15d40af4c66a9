"""DenseVLAD's CPU kernels (numba, single-threaded, released GIL): orientation histograms, their
bilinear pooling on the SIFT lattice, RootSIFT built straight from the pooled lattice, and the
residual sums of assigned descriptors.

They replace chains of tensor operations that each pass over every pixel or descriptor (scatter
of the orientation votes, two depthwise convolutions, gather of the 16 cells, window, L2 norm,
clipping, L1 norm, square root, index_add) with one pass per stage that stays in cache.
`locretrieval.models.published.densevlad` runs one image per thread with them; its torch code stays the
reference and the GPU path, and both agree within float32 rounding (tests). Indices in inner
loops are unsigned so that numba emits no negative-index check and LLVM vectorises the loops;
``fastmath`` lets it reorder the sums (float32 rounding only). Compiled on first use, cached
beside this file.
"""

from __future__ import annotations

import numpy as np
from numba import njit

ANGLE_BINS = 8
#: SIFT's clipping of single dominant bins, applied between two L2 normalisations.
SIFT_CLIP = np.float32(0.2)
#: Norms below this count as zero (a zero descriptor stays zero).
EPS = np.float32(1e-12)
_BINS = np.uint64(ANGLE_BINS)
_DIM = np.uint64(4 * 4 * ANGLE_BINS)


@njit(nogil=True, cache=True)
def orientation_histograms(magnitude, position):
    """``[H, W * 8]`` per-pixel histograms: ``magnitude [H, W]`` voting linearly into the two
    bins around ``position [H, W]`` (the orientation in bins, bin 0 centred on angle 0)."""
    height, width = magnitude.shape
    histograms = np.zeros((height, width * ANGLE_BINS), np.float32)
    for y in range(height):
        row = histograms[y]
        for x in range(width):
            lower = np.floor(position[y, x])
            upper_vote = (position[y, x] - lower) * magnitude[y, x]
            bin_ = int(lower) % ANGLE_BINS
            row[x * ANGLE_BINS + bin_] += magnitude[y, x] - upper_vote
            row[x * ANGLE_BINS + (bin_ + 1) % ANGLE_BINS] += upper_vote
    return histograms


@njit(nogil=True, cache=True, fastmath=True)
def pooled_lattice(histograms, triangle, origin_y, origin_x, stride, rows, cols):
    """``[rows, cols * 8]``: ``histograms [H, W * 8]`` pooled by the separable ``triangle``
    filter (odd length, centred) at pixels ``(origin_y + j * stride, origin_x + i * stride)``;
    pixels outside the image count as zero."""
    height, width8 = histograms.shape
    width = width8 // ANGLE_BINS
    half = (len(triangle) - 1) // 2
    vertical = np.zeros((rows, width8), np.float32)
    for j in range(rows):
        centre = origin_y + j * stride
        target = vertical[j]
        for tap in range(max(0, half - centre), min(len(triangle), height + half - centre)):
            weight = triangle[tap]
            source = histograms[centre + tap - half]
            for k in range(np.uint64(width8)):
                target[k] += weight * source[k]
    pooled = np.empty((rows, cols * ANGLE_BINS), np.float32)
    for j in range(rows):
        source = vertical[j]
        target = pooled[j]
        for i in range(cols):
            centre = origin_x + i * stride
            # Eight scalar sums (one per angle), which LLVM turns into one vector register.
            s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = np.float32(0.0)
            for tap in range(max(0, half - centre), min(len(triangle), width + half - centre)):
                weight = triangle[tap]
                k = np.uint64((centre + tap - half) * ANGLE_BINS)
                s0 += weight * source[k]
                s1 += weight * source[k + np.uint64(1)]
                s2 += weight * source[k + np.uint64(2)]
                s3 += weight * source[k + np.uint64(3)]
                s4 += weight * source[k + np.uint64(4)]
                s5 += weight * source[k + np.uint64(5)]
                s6 += weight * source[k + np.uint64(6)]
                s7 += weight * source[k + np.uint64(7)]
            k = np.uint64(i * ANGLE_BINS)
            target[k], target[k + np.uint64(1)], target[k + np.uint64(2)], target[k + np.uint64(3)] = s0, s1, s2, s3
            target[k + np.uint64(4)], target[k + np.uint64(5)], target[k + np.uint64(6)], target[k + np.uint64(7)] = (
                s4,
                s5,
                s6,
                s7,
            )
    return pooled


@njit(nogil=True, cache=True, fastmath=True)
def rootsift_rows(pooled, window, first_row, last_row, cols, cell_step, grid_step, out, contrast):
    """RootSIFT of grid rows ``first_row:last_row`` (all ``cols`` columns, row-major) of a lattice.

    ``pooled [Y, X * 8]``: pooled orientation histograms; grid point ``(r, c)``'s cells are the
    lattice entries ``(r * grid_step + i * cell_step, c * grid_step + j * cell_step)``, weighted
    by ``window [16]`` (row-major). Writes ``out [M, 128]`` (cell row, cell column, angle; SIFT's
    L2 / clip 0.2, then RootSIFT's L1 and square root, zero for zero contrast) and
    ``contrast [M]``, the L2 norm of the window-weighted histogram."""
    m = 0
    for r in range(first_row, last_row):
        for c in range(cols):
            descriptor = out[m]
            for cell_y in range(4):
                source = pooled[r * grid_step + cell_y * cell_step]
                for cell_x in range(4):
                    weight = window[cell_y * 4 + cell_x]
                    first = np.uint64((c * grid_step + cell_x * cell_step) * ANGLE_BINS)
                    target = np.uint64((cell_y * 4 + cell_x) * ANGLE_BINS)
                    for angle in range(_BINS):
                        descriptor[target + angle] = source[first + angle] * weight
            energy = np.float32(0.0)
            for k in range(_DIM):
                energy += descriptor[k] * descriptor[k]
            norm = np.sqrt(energy)
            contrast[m] = norm
            inverse = np.float32(1.0) / max(norm, EPS)
            total = np.float32(0.0)
            for k in range(_DIM):
                value = min(descriptor[k] * inverse, SIFT_CLIP)
                descriptor[k] = value
                total += value
            inverse = np.float32(1.0) / max(total, EPS)
            for k in range(_DIM):
                descriptor[k] = np.sqrt(descriptor[k] * inverse)
            m += 1


@njit(nogil=True, cache=True, fastmath=True)
def add_to_words(descriptors, words, keep, sums, counts):
    """``sums[words[m]] += descriptors[m]`` and ``counts[words[m]] += 1`` for every kept row
    (``keep [M]``); ``sums [K, D]``, ``counts [K]``."""
    dim = np.uint64(descriptors.shape[1])
    for m in range(len(words)):
        if keep[m]:
            word = words[m]
            counts[word] += 1
            target = sums[word]
            source = descriptors[m]
            for k in range(dim):
                target[k] += source[k]
