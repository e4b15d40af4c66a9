"""Truncated camera frusta and the inscribed radius of their overlap (`locretrieval.frusta`)."""

import numpy as np
import pytest
from posed_cameras import WIDE, about, frusta, image_set, linprog_radius, random_cameras, reference_radii

from locretrieval.frusta import may_overlap, overlap_radii
from locretrieval.scene import Camera

# Same image, twice the focal length: half field of view atan(0.5).
NARROW = Camera("PINHOLE", 100, 100, (100.0, 100.0, 50.0, 50.0))


def inscribed_radius_symmetric(tan_half_fov: float, far: float) -> float:
    """Closed form for a square symmetric pyramid truncated at ``far`` (near plane inactive).

    A ball on the axis at depth z touches the side planes at radius z sin(a) and the far
    plane at far - z; both are equal at the optimum: r = far sin(a) / (1 + sin(a)).
    """
    sine = np.sin(np.arctan(tan_half_fov))
    return far * sine / (1.0 + sine)


def test_identical_frusta_give_the_inscribed_radius_of_one():
    images = image_set([about("y", 0), about("y", 0)], [[0, 0, 0], [0, 0, 0]], [WIDE, NARROW])
    radii = overlap_radii(frusta(images, 10.0), frusta(images, 10.0))
    np.testing.assert_allclose(
        radii, [inscribed_radius_symmetric(1.0, 10.0), inscribed_radius_symmetric(0.5, 10.0)], rtol=1e-9
    )
    # A non-square, off-centre camera against scipy linprog on its own 6 half-spaces.
    odd = image_set(about("x", 30), [1, 2, 3], [Camera("PINHOLE", 640, 360, (400.0, 420.0, 300.0, 200.0))])
    single = frusta(odd, 10.0)
    assert overlap_radii(single, single)[0] == pytest.approx(linprog_radius(single.A[0], single.b[0]), rel=1e-9)


def test_contained_frustum_gives_the_radius_of_the_smaller_one():
    wide = image_set(about("y", 0), [0, 0, 0], [WIDE])
    narrow = image_set(about("y", 0), [0, 0, 0], [NARROW])
    shorter = overlap_radii(frusta(wide, 10.0), frusta(wide, 4.0))[0]
    assert shorter == pytest.approx(inscribed_radius_symmetric(1.0, 4.0), rel=1e-9)
    narrower = overlap_radii(frusta(wide, 10.0), frusta(narrow, 10.0))[0]
    assert narrower == pytest.approx(inscribed_radius_symmetric(0.5, 10.0), rel=1e-9)


def test_disjoint_and_touching_frusta_have_zero_radius():
    # Back to back at one centre (the near planes keep them apart), 100 m apart, and
    # facing each other with far planes meeting in the plane z = 10 (touching only).
    first = image_set([about("y", 0)] * 3, [[0, 0, 0]] * 3)
    second = image_set([about("y", 180), about("y", 0), about("y", 180)], [[0, 0, 0], [100, 0, 0], [0, 0, 20]])
    radii = overlap_radii(frusta(first, 10.0), frusta(second, 10.0))
    assert radii[:2].tolist() == [0.0, 0.0]
    assert radii[2] == 0.0
    assert not may_overlap(frusta(first, 10.0)[:2], frusta(second, 10.0)[:2]).any()


def test_prefilter_keeps_every_pair_that_linprog_says_overlaps():
    rng = np.random.default_rng(1)
    first, second = frusta(random_cameras(rng, 400, 40.0), 15.0), frusta(random_cameras(rng, 400, 40.0), 15.0)
    kept = may_overlap(first, second)
    expected = reference_radii(first, second)
    assert (~kept).sum() > 100  # the prefilter does discard pairs
    assert (expected[~kept] <= 1e-9).all()
    assert (expected > 1e-9).sum() > 20
