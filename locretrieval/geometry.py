"""Rotations, poses, pose errors and camera frusta, vectorised over leading axes.

Conventions used everywhere in locretrieval:

- a pose is world-to-camera ``(q, t)``: ``x_cam = R(q) @ x_world + t``, as kapture and COLMAP
  store it;
- quaternions are ``(w, x, y, z)`` (scalar first) and unit-norm; ``q`` and ``-q`` are the same
  rotation;
- the camera centre is ``c = -R^T t`` (world coordinates); the paper's Sec. 3.6.1 writes the
  same pose as ``x_cam = R (x_world - c)``;
- positions are in the scene's unit (metres for every dataset used here), angles in degrees at
  the public boundary.
"""

from __future__ import annotations

import numpy as np

UNIT_NORM_TOLERANCE = 1e-3
#: `dominant_quaternion`: Newton steps at most and their stopping size for the largest eigenvalue
#: (of the moments scaled to trace 1), and the residual above which LAPACK's ``eigh`` decides.
NEWTON_STEPS = 60
NEWTON_TOLERANCE = 1e-15
DOMINANT_RESIDUAL = 1e-12


def normalize_quaternions(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``[..., 4]`` (wxyz) with a non-negative scalar part."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def invalid_quaternion_rows(q: np.ndarray, tolerance: float = UNIT_NORM_TOLERANCE) -> np.ndarray:
    """Indices of rows of ``q [N, 4]`` that are not finite unit quaternions."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1)
    bad = ~np.isfinite(q).all(axis=-1) | (np.abs(norm - 1.0) > tolerance)
    return np.flatnonzero(bad)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` of quaternions ``[..., 4]`` (wxyz, normalised here)."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Quaternions ``[..., 4]`` (wxyz, w >= 0) of rotation matrices ``[..., 3, 3]``.

    Uses the symmetric 4x4 matrix of Bar-Itzhack, whose dominant eigenvector is the
    quaternion; robust for every rotation angle, including 180 degrees.
    """
    R = np.asarray(R, dtype=np.float64)
    r = {(i, j): R[..., i, j] for i in range(3) for j in range(3)}
    K = np.stack(
        [
            np.stack([r[0, 0] + r[1, 1] + r[2, 2], r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]], -1),
            np.stack([r[2, 1] - r[1, 2], r[0, 0] - r[1, 1] - r[2, 2], r[0, 1] + r[1, 0], r[0, 2] + r[2, 0]], -1),
            np.stack([r[0, 2] - r[2, 0], r[0, 1] + r[1, 0], r[1, 1] - r[0, 0] - r[2, 2], r[1, 2] + r[2, 1]], -1),
            np.stack([r[1, 0] - r[0, 1], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], r[2, 2] - r[0, 0] - r[1, 1]], -1),
        ],
        axis=-2,
    )
    _, vectors = np.linalg.eigh(K / 3.0)
    return normalize_quaternions(vectors[..., :, -1])


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of wxyz quaternions (rotation ``b`` first, then ``a``)."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quaternion_conjugate(q: np.ndarray) -> np.ndarray:
    """Inverse rotation of unit wxyz quaternions."""
    return np.asarray(q, dtype=np.float64) * np.array([1.0, -1.0, -1.0, -1.0])


def compose_poses(q_a: np.ndarray, t_a: np.ndarray, q_b: np.ndarray, t_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a o b``: the transform applying ``b`` then ``a`` (e.g. cam_from_rig o rig_from_world)."""
    q = quaternion_multiply(q_a, q_b)
    t = np.einsum("...ij,...j->...i", quaternion_to_matrix(q_a), t_b) + t_a
    return q, t


def camera_centers(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World positions ``c = -R^T t`` of world-to-camera poses."""
    return -np.einsum("...ji,...j->...i", quaternion_to_matrix(q), np.asarray(t, dtype=np.float64))


def translations_from_centers(q: np.ndarray, c: np.ndarray) -> np.ndarray:
    """World-to-camera translations ``t = -R c`` of cameras at world positions ``c``."""
    return -np.einsum("...ij,...j->...i", quaternion_to_matrix(q), np.asarray(c, dtype=np.float64))


def position_errors(c_estimated: np.ndarray, c_reference: np.ndarray) -> np.ndarray:
    """Euclidean distance between camera centres (paper eq. 3), in scene units."""
    return np.linalg.norm(np.asarray(c_estimated) - np.asarray(c_reference), axis=-1)


def rotation_errors_deg(q_estimated: np.ndarray, q_reference: np.ndarray) -> np.ndarray:
    """Angle in degrees of the smallest rotation aligning the two (paper eq. 4).

    Equal to ``arccos((trace(R_est^-1 R_ref) - 1) / 2)``; computed from the quaternion
    dot product, ``2 arccos(|<q_est, q_ref>|)``, so it is invariant to the sign of either
    quaternion and accurate for small angles.
    """
    a = np.asarray(q_estimated, dtype=np.float64)
    b = np.asarray(q_reference, dtype=np.float64)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    dot = np.abs(np.sum(a * b, axis=-1))
    relative = quaternion_multiply(quaternion_conjugate(a), b)
    sine = np.linalg.norm(relative[..., 1:], axis=-1)
    return np.degrees(2.0 * np.arctan2(sine, dot))


def pairwise_position_errors(c_a: np.ndarray, c_b: np.ndarray) -> np.ndarray:
    """``[A, B]`` `position_errors` of every pair of camera centres ``c_a [A, 3]``, ``c_b [B, 3]``."""
    return _pairwise_distances(c_a, c_b)


def _pairwise_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distances ``[A, B]`` between the rows of ``a`` and ``b`` (scipy's `cdist`:
    one C loop, no ``[A, B, dim]`` temporary)."""
    from scipy.spatial.distance import cdist  # scipy.spatial takes 0.4 s to import

    return cdist(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))


def pairwise_rotation_errors_deg(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """``[A, B]`` `rotation_errors_deg` of every pair of wxyz quaternions ``q_a [A, 4]``, ``q_b [B, 4]``.

    Unit quaternions at an angle ``phi`` have ``|a - b| = 2 sin(phi / 2)`` and ``|a + b| =
    2 cos(phi / 2)``; the rotation angle is ``2 min(phi, pi - phi)`` (either sign), so
    ``4 arctan2(min(|a - b|, |a + b|), max(...))``: accurate for small angles, 10x faster than
    the Hamilton products of `rotation_errors_deg` on all pairs.
    """
    a = np.asarray(q_a, dtype=np.float64)
    b = np.asarray(q_b, dtype=np.float64)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    minus, plus = _pairwise_distances(a, b), _pairwise_distances(a, -b)
    return np.degrees(4.0 * np.arctan2(np.minimum(minus, plus), np.maximum(minus, plus)))


def quaternion_outer_products(q: np.ndarray) -> np.ndarray:
    """``q q^T`` of quaternions ``[..., 4]``, flattened to ``[..., 16]``."""
    q = np.asarray(q, dtype=np.float64)
    return (q[..., :, None] * q[..., None, :]).reshape(*q.shape[:-1], 16)


def dominant_quaternion(moments: np.ndarray) -> np.ndarray:
    """Unit eigenvector (wxyz, w >= 0) of the largest eigenvalue of ``[..., 16]`` 4x4 moments
    (symmetric, positive semi-definite).

    Vectorised closed form: the largest root of the characteristic polynomial by Newton's
    method from the Gershgorin bound (monotone, as every root is real), then the longest column
    of the adjugate of ``M - lambda I``. Where the two largest eigenvalues nearly coincide the
    adjugate vanishes; matrices whose residual ``|M v - lambda v|`` exceeds
    ``DOMINANT_RESIDUAL * trace(M)`` go to LAPACK's ``eigh``. Equal to ``eigh`` within 1e-14,
    2-4x faster on the millions of small problems paradigm 1 solves.
    """
    shape = moments.shape[:-1]
    flat = np.asarray(moments, dtype=np.float64).reshape(-1, 16)
    trace = flat[:, [0, 5, 10, 15]].sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        entries = (flat / trace[:, None]).T  # trace 1: eigenvalues in [0, 1]
    m = [[entries[4 * i + j] for j in range(4)] for i in range(4)]
    largest = _largest_eigenvalue(m, entries)
    shifted = [[m[i][j] - largest if i == j else m[i][j] for j in range(4)] for i in range(4)]
    vector, length = np.zeros((4, len(flat))), np.zeros(len(flat))
    for j in range(4):  # column j of adj(M - lambda I): cofactors of row j
        rows = [r for r in range(4) if r != j]
        column = np.stack([(-1) ** (i + j) * _minor(shifted, rows, [c for c in range(4) if c != i]) for i in range(4)])
        column_length = np.einsum("in,in->n", column, column)
        longer = column_length > length
        vector = np.where(longer, column, vector)
        length = np.where(longer, column_length, length)
    with np.errstate(invalid="ignore", divide="ignore"):
        vector = (vector / np.sqrt(length)).T
        image = np.einsum("nij,nj->ni", entries.T.reshape(-1, 4, 4), vector)
        residual = np.linalg.norm(image - largest[:, None] * vector, axis=1)
    unsettled = ~(residual <= DOMINANT_RESIDUAL)
    if unsettled.any():
        vector[unsettled] = np.linalg.eigh(flat[unsettled].reshape(-1, 4, 4))[1][..., -1]
    return normalize_quaternions(vector).reshape(*shape, 4)


def _minor(m: list[list[np.ndarray]], rows: list[int], cols: list[int]) -> np.ndarray:
    """Determinant of the 3x3 submatrix ``m[rows][:, cols]`` (entries are arrays over matrices)."""
    (r0, r1, r2), (k0, k1, k2) = rows, cols
    return (
        m[r0][k0] * (m[r1][k1] * m[r2][k2] - m[r1][k2] * m[r2][k1])
        - m[r0][k1] * (m[r1][k0] * m[r2][k2] - m[r1][k2] * m[r2][k0])
        + m[r0][k2] * (m[r1][k0] * m[r2][k1] - m[r1][k1] * m[r2][k0])
    )


def _largest_eigenvalue(m: list[list[np.ndarray]], entries: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of symmetric 4x4 matrices of trace 1 (entries ``m[i][j]`` over matrices)."""
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    c2 = sum(m[i][i] * m[j][j] - m[i][j] * m[i][j] for i, j in pairs)
    c1 = sum(_minor(m, rows, rows) for rows in ([1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]))
    c0 = sum((-1) ** j * m[0][j] * _minor(m, [1, 2, 3], [c for c in range(4) if c != j]) for j in range(4))
    value = np.minimum(1.0, np.abs(entries).reshape(4, 4, -1).sum(axis=1).max(axis=0))  # Gershgorin
    for _ in range(NEWTON_STEPS):  # p(x) = x^4 - x^3 + c2 x^2 - c1 x + c0
        polynomial = (((value - 1.0) * value + c2) * value - c1) * value + c0
        slope = ((4.0 * value - 3.0) * value + 2.0 * c2) * value - c1
        with np.errstate(invalid="ignore", divide="ignore"):
            step = np.where(slope > 0, polynomial / slope, 0.0)
        value -= step
        if not (np.abs(step) > NEWTON_TOLERANCE).any():
            break
    return value


def average_quaternions(q: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted rotation average of ``q [..., k, 4]`` with ``weights [..., k]``.

    The eigenvector of the largest eigenvalue of ``sum_i w_i q_i q_i^T`` (Markley et al.
    2007), which is invariant to the sign of each ``q_i``. Returned wxyz with w >= 0.
    """
    moments = np.asarray(weights, dtype=np.float64)[..., None, :] @ quaternion_outer_products(q)
    return dominant_quaternion(moments[..., 0, :])


def frustum_halfspaces(
    q: np.ndarray,
    t: np.ndarray,
    intrinsics: np.ndarray,
    near: float,
    far: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Truncated viewing frusta as 6 half-spaces ``A x <= b`` in world coordinates.

    ``intrinsics [..., 6]`` holds ``(fx, fy, cx, cy, width, height)`` in pixels with the
    image spanning ``[0, width] x [0, height]`` (COLMAP's convention); lens distortion is
    ignored. ``near`` and ``far`` are depths along the optical axis (scene units). Rows of
    ``A`` are unit normals, so ``b - A x`` is the distance of ``x`` to each plane.
    Returns ``A [..., 6, 3]`` and ``b [..., 6]``.
    """
    fx, fy, cx, cy, width, height = np.moveaxis(np.asarray(intrinsics, dtype=np.float64), -1, 0)
    zeros, ones = np.zeros_like(fx), np.ones_like(fx)
    # Camera-frame normals: image side u >= 0 is  -fx x - cx z <= 0, i.e. x/z >= -cx/fx, etc.
    normals_cam = np.stack(
        [
            np.stack([-fx, zeros, -cx], -1),  # left   u >= 0
            np.stack([fx, zeros, cx - width], -1),  # right  u <= width
            np.stack([zeros, -fy, -cy], -1),  # top    v >= 0
            np.stack([zeros, fy, cy - height], -1),  # bottom v <= height
            np.stack([zeros, zeros, -ones], -1),  # near   z >= near
            np.stack([zeros, zeros, ones], -1),  # far    z <= far
        ],
        axis=-2,
    )
    offsets_cam = np.stack([zeros, zeros, zeros, zeros, -near * ones, far * ones], -1)
    norms = np.linalg.norm(normals_cam, axis=-1)
    normals_cam, offsets_cam = normals_cam / norms[..., None], offsets_cam / norms
    # n . x_cam <= o  with  x_cam = R x + t   =>   (R^T n) . x <= o - n . t
    R = quaternion_to_matrix(q)
    A = np.einsum("...pi,...ij->...pj", normals_cam, R)
    b = offsets_cam - np.einsum("...pi,...i->...p", normals_cam, np.asarray(t, dtype=np.float64))
    return A, b


def frustum_corners(q: np.ndarray, t: np.ndarray, intrinsics: np.ndarray, near: float, far: float) -> np.ndarray:
    """The 8 world-space corners ``[..., 8, 3]`` of truncated frusta (near corners first)."""
    fx, fy, cx, cy, width, height = np.moveaxis(np.asarray(intrinsics, dtype=np.float64), -1, 0)
    corners = []
    for depth in (near, far):
        for u, v in ((0.0, 0.0), (width, 0.0), (width, height), (0.0, height)):
            x = (u - cx) / fx * depth
            y = (v - cy) / fy * depth
            corners.append(np.stack([x, y, np.full_like(x, depth)], -1))
    corners_cam = np.stack(corners, axis=-2)
    R = quaternion_to_matrix(q)
    t = np.asarray(t, dtype=np.float64)
    return np.einsum("...ji,...kj->...ki", R, corners_cam - t[..., None, :])
