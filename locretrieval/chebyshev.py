"""Batched exact Chebyshev radius of small polytopes ``{x in R^3: A x <= b}``.

The radius of the largest ball inside the polytope is the optimum of the linear program

    (P)  maximise r   subject to   a_i . x + r <= b_i   (x in R^3 and r free; ||a_i|| = 1)

whose optimum is negative when the polytope is empty. We solve its dual in standard form,

    (D)  minimise b . y   subject to   sum_i y_i (a_i, 1) = (0, 0, 0, 1),   y >= 0,

with a tableau simplex vectorised over a batch of problems (4 rows, m columns each). The
caller supplies a dual-feasible starting basis, which the frustum problem has for free (two
opposite parallel planes plus two more; see `locretrieval.frusta`), so no phase 1
is needed. Pivots use Dantzig's rule, then Bland's rule (which cannot cycle) after a few
iterations. The final basis is certified by recomputing the vertex with a fresh 4x4 solve and
checking primal feasibility (every slack >= 0) and dual feasibility (every multiplier >= 0)
to ``CERTIFICATE_TOLERANCE``; the radius is then the LP optimum up to rounding. Problems that
fail the certificate (ill-conditioned bases) are solved again by `scipy.optimize.linprog`
(HiGHS) one at a time, and counted in a log message.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.optimize import linprog

log = logging.getLogger(__name__)

#: Reduced costs above ``-OPTIMALITY_TOLERANCE`` count as optimal (problems scaled to |b| <= 1).
OPTIMALITY_TOLERANCE = 1e-11
#: Pivot elements below this are never used in the ratio test.
PIVOT_TOLERANCE = 1e-9
#: Slacks and dual multipliers of the final basis must be >= -CERTIFICATE_TOLERANCE.
CERTIFICATE_TOLERANCE = 1e-9
#: Dantzig's rule for this many pivots, then Bland's rule.
DANTZIG_PIVOTS = 20
#: Problems still unsolved after this many pivots go to the linprog fallback.
MAX_PIVOTS = 200


def chebyshev_radius(A: np.ndarray, b: np.ndarray, initial_basis: np.ndarray) -> np.ndarray:
    """Signed Chebyshev radius ``[P]`` of the polytopes ``A [P, m, 3] x <= b [P, m]``.

    Rows of ``A`` must be unit normals and the polytopes bounded. ``initial_basis [4]`` are
    constraint indices whose dual basic solution is feasible for every problem (e.g. two
    opposite parallel planes and two planes whose normals span the rest of R^3). A negative
    result means the polytope is empty (its magnitude is the smallest uniform relaxation
    of the constraints that makes it non-empty); zero means it has no interior.
    """
    A = np.asarray(A, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if len(A) == 0:
        return np.zeros(0)
    # Centre and scale each problem: the tolerances are then relative to the polytope's size.
    origin = _interior_guess(A, b)
    b = b - (A @ origin[..., None])[..., 0]
    scale = np.abs(b).max(axis=1)
    b = b / scale[:, None]
    G = np.concatenate([A, np.ones(A.shape[:2] + (1,))], axis=2)  # rows g_i = (a_i, 1)

    basis = _simplex(G, b, np.asarray(initial_basis, dtype=np.int64))
    radius, certified = _certified_optimum(G, b, basis)
    failed = np.flatnonzero(~certified)
    if failed.size:
        log.info("Chebyshev radius: %d of %d problems re-solved with scipy linprog", failed.size, len(A))
        radius[failed] = [_linprog_radius(G[p], b[p]) for p in failed]
    return radius * scale


def _interior_guess(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A point near the polytopes ``[P, 3]``: the least-squares point on all their planes."""
    A_transposed = A.transpose(0, 2, 1)
    return np.linalg.solve(A_transposed @ A, A_transposed @ b[..., None])[..., 0]


def _simplex(G: np.ndarray, b: np.ndarray, initial_basis: np.ndarray) -> np.ndarray:
    """Optimal bases ``[P, 4]`` of (D); ``-1`` rows for problems that did not converge."""
    P, m, _ = G.shape
    M = G.transpose(0, 2, 1)  # [P, 4, m], the equality constraints of (D)
    B_inverse = np.linalg.inv(M[:, :, initial_basis])
    tableau = B_inverse @ M  # [P, 4, m]
    rhs = B_inverse[:, :, 3].copy()  # B^-1 e4: the basic dual solution
    if (rhs < -CERTIFICATE_TOLERANCE).any():
        raise ValueError(f"initial basis {initial_basis.tolist()} is not dual feasible for every problem")
    basis = np.broadcast_to(initial_basis, (P, 4)).copy()
    reduced = b - (b[:, None, initial_basis] @ tableau)[:, 0]  # reduced costs = slacks of the vertex

    result = np.full((P, 4), -1, dtype=np.int64)
    alive = np.arange(P)
    for pivot in range(MAX_PIVOTS + 1):
        bland = pivot >= DANTZIG_PIVOTS
        rows = np.arange(len(alive))
        # Entering column: the most negative reduced cost (Dantzig) or the first negative (Bland).
        entering = (reduced < -OPTIMALITY_TOLERANCE).argmax(axis=1) if bland else reduced.argmin(axis=1)
        optimal = reduced[rows, entering] >= -OPTIMALITY_TOLERANCE
        result[alive[optimal]] = basis[optimal]
        if optimal.all() or pivot == MAX_PIVOTS:
            break
        column = tableau[rows, :, entering]  # [P, 4]
        eligible = column > PIVOT_TOLERANCE
        pivoting = ~optimal & eligible.any(axis=1)  # no eligible row: unbounded, never for bounded polytopes
        if not pivoting.all():
            alive, tableau, rhs, basis, reduced, entering, column, eligible = (
                array[pivoting] for array in (alive, tableau, rhs, basis, reduced, entering, column, eligible)
            )
            rows = np.arange(len(alive))
        ratio = np.where(eligible, np.maximum(rhs, 0.0) / np.where(eligible, column, 1.0), np.inf)
        if bland:  # ties go to the smallest basic index
            ties = ratio <= ratio.min(axis=1, keepdims=True) + OPTIMALITY_TOLERANCE
            leaving = np.where(ties, basis, m).argmin(axis=1)
        else:
            leaving = ratio.argmin(axis=1)
        pivot_value = column[rows, leaving]
        pivot_row = tableau[rows, leaving] / pivot_value[:, None]
        pivot_rhs = rhs[rows, leaving] / pivot_value
        tableau -= column[:, :, None] * pivot_row[:, None, :]
        rhs -= column * pivot_rhs[:, None]
        tableau[rows, leaving] = pivot_row
        rhs[rows, leaving] = pivot_rhs
        reduced -= reduced[rows, entering][:, None] * pivot_row
        basis[rows, leaving] = entering
    return result


def _certified_optimum(G: np.ndarray, b: np.ndarray, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Radius ``[P]`` of each basis' vertex and whether the basis is provably optimal."""
    P = len(G)
    radius = np.full(P, np.nan)
    certified = np.zeros(P, dtype=bool)
    converged = np.flatnonzero(basis[:, 0] >= 0)
    rows = converged[:, None]
    G_basis = G[rows, basis[converged]]  # [P', 4, 4], rows g_i of the active constraints
    solvable = np.abs(np.linalg.det(G_basis)) > PIVOT_TOLERANCE
    converged, G_basis = converged[solvable], G_basis[solvable]
    vertex = np.linalg.solve(G_basis, b[converged[:, None], basis[converged]][..., None])[..., 0]
    e4 = np.broadcast_to([0.0, 0.0, 0.0, 1.0], vertex.shape)[..., None]
    multipliers = np.linalg.solve(G_basis.transpose(0, 2, 1), e4)[..., 0]
    slacks = b[converged] - (G[converged] @ vertex[..., None])[..., 0]
    certified[converged] = (slacks.min(axis=1) >= -CERTIFICATE_TOLERANCE) & (
        multipliers.min(axis=1) >= -CERTIFICATE_TOLERANCE
    )
    radius[converged] = vertex[:, 3]
    return radius, certified


def _linprog_radius(G: np.ndarray, b: np.ndarray) -> float:
    """Optimum of (P) for one problem by HiGHS."""
    solution = linprog(c=[0.0, 0.0, 0.0, -1.0], A_ub=G, b_ub=b, bounds=[(None, None)] * 4, method="highs")
    if solution.status != 0:
        raise RuntimeError(f"linprog failed on a Chebyshev-centre problem: {solution.message}")
    return float(-solution.fun)
