"""Fixtures of the ground-truth tests."""

import numpy as np
import pytest
from posed_cameras import about, image_set


@pytest.fixture
def pose_scene():
    """A query at the origin (identity rotation) and five database images with known errors.

    (c_diff m, R_diff deg) -> s = c/25 + R/45: d0 (10, 0) 0.4; d1 (0, 30) 0.667;
    d2 (20, 60) 2.133; d3 (30, 0) 1.2; d4 (5, 20) 0.644. Relevant: d0, d1, d4.
    """
    database = image_set(
        [about("x", 0), about("y", 30), about("z", 60), about("x", 0), about("x", 20)],
        [[10, 0, 0], [0, 0, 0], [20, 0, 0], [0, 30, 0], [3, 4, 0]],
        prefix="db",
    )
    queries = image_set(
        [about("x", 0), [np.nan] * 4, about("z", 10)], [[0, 0, 0], [np.nan] * 3, [500, 0, 0]], prefix="q"
    )
    return database, queries
