"""The batched Chebyshev radius (`locretrieval.chebyshev`) against scipy's linprog."""

import logging

import numpy as np
import pytest
from posed_cameras import (
    frusta,
    random_cameras,
    reference_radii,
)

from locretrieval import chebyshev
from locretrieval.chebyshev import chebyshev_radius
from locretrieval.frusta import INITIAL_BASIS, TruncatedFrusta, overlap_radii


@pytest.fixture(scope="module")
def random_pairs():
    """300 random frustum pairs (far 20 m, centres within 15 m) and their linprog radii."""
    rng = np.random.default_rng(0)
    first, second = frusta(random_cameras(rng, 300, 15.0), 20.0), frusta(random_cameras(rng, 300, 15.0), 20.0)
    return first, second, reference_radii(first, second)


def signed_radii(first: TruncatedFrusta, second: TruncatedFrusta) -> np.ndarray:
    A = np.concatenate([first.A, second.A], axis=1)
    b = np.concatenate([first.b, second.b], axis=1)
    return chebyshev_radius(A, b, INITIAL_BASIS)  # every pair, empty intersections included


def test_batched_solver_equals_linprog_on_random_pairs(random_pairs):
    first, second, expected = random_pairs
    assert 0.2 < (expected > 0).mean() < 0.8  # both overlapping and empty pairs are exercised
    np.testing.assert_allclose(signed_radii(first, second), expected, rtol=1e-6, atol=1e-6 * 20.0)
    np.testing.assert_allclose(overlap_radii(first, second), np.maximum(expected, 0.0), rtol=1e-6, atol=1e-6 * 20.0)


@pytest.mark.parametrize("constant, value", [("DANTZIG_PIVOTS", 0), ("MAX_PIVOTS", 2)])
def test_bland_rule_and_linprog_fallback_agree_with_linprog(random_pairs, monkeypatch, caplog, constant, value):
    first, second, expected = random_pairs
    monkeypatch.setattr(chebyshev, constant, value)
    with caplog.at_level(logging.INFO, logger=chebyshev.__name__):
        radii = signed_radii(first, second)
    np.testing.assert_allclose(radii, expected, rtol=1e-6, atol=1e-6 * 20.0)
    assert ("re-solved with scipy linprog" in caplog.text) == (constant == "MAX_PIVOTS")
