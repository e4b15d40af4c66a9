"""DenseVLAD's CPU kernels (numba, single-threaded, released GIL): orientation histograms, their
bilinear pooling on the SIFT lattice, RootSIFT built straight from the pooled lattice, the
assignment of descriptors to visual words with the residual sums, the vocabulary's normalisation
and the VLAD's.

They replace chains of tensor operations that each pass over every pixel or descriptor (scatter
of the orientation votes, two depthwise convolutions, gather of the 16 cells, window, L2 norm,
clipping, L1 norm, square root, index_add) with one pass per stage that stays in cache.
`locretrieval.models.published.densevlad` runs one image per thread with them; its torch code stays the
reference and the GPU path, and both agree within float32 rounding (tests). Indices in inner
loops are unsigned so that numba emits no negative-index check and LLVM vectorises the loops.

The same bits on every CPU: no ``fastmath`` where it would change a result, so LLVM neither
reorders a sum (a vectorised reduction follows the machine's vector width) nor fuses a product and
a sum (FMA, which older CPUs lack); the 128-term sums of RootSIFT are eight partial sums in the
code's order (scalar: `rootsift_rows` takes about 25 % longer than with fastmath's vectorised
sums). A word assignment, the argmax of a matrix product whose last bits follow the machine's BLAS
kernels, is settled by `assign_to_words` in float64 (see there). Compiled on first use, cached
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


@njit(nogil=True, cache=True)
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
            # Eight scalar sums (one per angle), each over the taps in order.
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


@njit(nogil=True, cache=True, inline="always")
def sum_of_squares(vector):
    """``sum(vector ** 2)`` of a 128-vector in a fixed order: eight partial sums of every eighth
    value, then added pairwise."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = np.float32(0.0)
    for k in range(np.uint64(0), _DIM, _BINS):
        s0 += vector[k] * vector[k]
        s1 += vector[k + np.uint64(1)] * vector[k + np.uint64(1)]
        s2 += vector[k + np.uint64(2)] * vector[k + np.uint64(2)]
        s3 += vector[k + np.uint64(3)] * vector[k + np.uint64(3)]
        s4 += vector[k + np.uint64(4)] * vector[k + np.uint64(4)]
        s5 += vector[k + np.uint64(5)] * vector[k + np.uint64(5)]
        s6 += vector[k + np.uint64(6)] * vector[k + np.uint64(6)]
        s7 += vector[k + np.uint64(7)] * vector[k + np.uint64(7)]
    return ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))


@njit(nogil=True, cache=True, inline="always")
def sum_of_values(vector):
    """``sum(vector)`` of a 128-vector in `sum_of_squares`'s fixed order."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = np.float32(0.0)
    for k in range(np.uint64(0), _DIM, _BINS):
        s0 += vector[k]
        s1 += vector[k + np.uint64(1)]
        s2 += vector[k + np.uint64(2)]
        s3 += vector[k + np.uint64(3)]
        s4 += vector[k + np.uint64(4)]
        s5 += vector[k + np.uint64(5)]
        s6 += vector[k + np.uint64(6)]
        s7 += vector[k + np.uint64(7)]
    return ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))


@njit(nogil=True, cache=True)
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
            norm = np.sqrt(sum_of_squares(descriptor))
            contrast[m] = norm
            inverse = np.float32(1.0) / max(norm, EPS)
            for k in range(_DIM):
                descriptor[k] = min(descriptor[k] * inverse, SIFT_CLIP)
            inverse = np.float32(1.0) / max(sum_of_values(descriptor), EPS)
            for k in range(_DIM):
                descriptor[k] = np.sqrt(descriptor[k] * inverse)
            m += 1


@njit(nogil=True, cache=True, fastmath=True)
def sum_of_squares_any_order(vector):
    """``sum(vector ** 2)`` in float32, summed in whatever order LLVM vectorises (relative error
    below ``len * 2^-24``): for error bounds only, never for a result."""
    total = np.float32(0.0)
    for k in range(np.uint64(len(vector))):
        total += vector[k] * vector[k]
    return total


@njit(nogil=True, cache=True, fastmath=True)
def count_at_least(values, threshold):
    """How many of ``values`` are ``>= threshold``; a count is the same in any order."""
    count = np.float32(0.0)
    for k in range(np.uint64(len(values))):
        count += np.float32(values[k] >= threshold)
    return count


@njit(nogil=True, cache=True)
def exact_score(vector, centroid, half_norm):
    """``vector . centroid - half_norm`` in float64, the products summed in index order."""
    total = 0.0
    for k in range(len(vector)):
        total += np.float64(vector[k]) * np.float64(centroid[k])
    return total - half_norm


@njit(nogil=True, cache=True)
def assign_to_words(descriptors, scores, first_largest, centroids, half_norms, keep, sums, counts):
    """``sums[w] += descriptors[m]`` and ``counts[w] += 1`` for every kept row ``m`` of
    ``descriptors [M, D]`` (``keep [M]``), in row order, ``w`` the word ``k`` of the largest
    ``descriptors[m] . c_k - half_norms[k]`` as `exact_score` computes it (the first on ties).
    It is found through ``scores [M, K]``, the same from a float32 product in any order, and
    ``first_largest [M]``, their row argmax (numpy's is faster than a scan here); ``centroids
    [K, D]`` those of the product, ``half_norms [K]`` float64, ``sums [K, D]`` float32 or float64,
    ``counts [K]``.

    Each of ``scores`` is within ``error`` of the exact score, so only words within ``2 * error``
    of the row's largest can win (the winner's score is at most ``error`` below its exact one, any
    other's at most ``error`` above); where there are several, they are scored exactly. The words
    are thereby the same whatever the BLAS kernels, thread count or vector width behind ``scores``."""
    # A float32 sum of n products in any order (FMA or not) is within gamma_n = n u / (1 - n u)
    # (u = 2^-24) times sum |x_i c_i| <= |x| |c| of the exact one; n = D + 1 with the half norm, one
    # more for the half norm's own rounding to float32. Doubling covers 1 / (1 - n u) and the float64
    # scores' own error (~n 2^-53), so a lone candidate is also the word `exact_score` would pick;
    # |x| and |c| are bounded from float32 sums, 1 % over.
    gamma = 2.0 * (descriptors.shape[1] + 2) * 2.0**-24
    largest_centroid, largest_half_norm = 0.0, 0.0
    for word in range(len(centroids)):
        largest_centroid = max(largest_centroid, 1.01 * np.sqrt(np.float64(sum_of_squares_any_order(centroids[word]))))
        largest_half_norm = max(largest_half_norm, abs(half_norms[word]))
    dim = np.uint64(descriptors.shape[1])
    for m in range(len(descriptors)):
        if not keep[m]:
            continue
        row, word, source = scores[m], first_largest[m], descriptors[m]
        norm = 1.01 * np.sqrt(np.float64(sum_of_squares_any_order(source)))
        threshold = np.float64(row[word]) - 2.0 * gamma * (norm * largest_centroid + largest_half_norm)
        threshold = np.float32(threshold - abs(threshold) * 2.0**-23)  # rounded down: more candidates, never fewer
        if count_at_least(row, threshold) > 1.0:  # several: the exact scores decide
            best = -np.inf
            for candidate in range(len(row)):
                if row[candidate] >= threshold:
                    score = exact_score(source, centroids[candidate], half_norms[candidate])
                    if score > best:
                        word, best = candidate, score
        counts[word] += 1
        target = sums[word]
        for k in range(dim):
            target[k] += source[k]


@njit(nogil=True, cache=True)
def half_squared_norms(centroids):
    """``|c_k|^2 / 2`` of ``centroids [K, D]`` in float64, summed in index order."""
    out = np.empty(len(centroids))
    for word in range(len(centroids)):
        out[word] = 0.5 * exact_score(centroids[word], centroids[word], 0.0)
    return out


@njit(nogil=True, cache=True)
def normalize_rows(rows):
    """``rows [K, D]`` float64 divided in place by their L2 norms (summed in index order); a row of
    norm 0 stays 0."""
    for row in rows:
        norm = np.sqrt(exact_score(row, row, 0.0))
        if norm > 0.0:
            for k in range(len(row)):
                row[k] /= norm


@njit(nogil=True, cache=True)
def normalized_vlad(residuals, out):
    """``out [K * D]``: ``residuals [K, D]`` with each word's block L2-normalised, then the whole
    vector, in float64 with every sum in index order (norms below `EPS` divide by `EPS`, so a zero
    block stays zero); rounded to ``out``'s type once."""
    blocks = residuals.astype(np.float64)
    for block in blocks:
        inverse = 1.0 / max(np.sqrt(exact_score(block, block, 0.0)), np.float64(EPS))
        for k in range(len(block)):
            block[k] *= inverse
    flat = blocks.ravel()
    inverse = 1.0 / max(np.sqrt(exact_score(flat, flat, 0.0)), np.float64(EPS))
    for k in range(len(flat)):
        out[k] = flat[k] * inverse
