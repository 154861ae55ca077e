"""Carrying nodal fields between hexahedral meshes of one body (`registration.prolong`)."""
import numpy as np
import pytest

from registration.prolong import carry, locate_points


def _box(n, size=(10.0, 6.0, 4.0), warp=0.0):
    """Structured hexahedral box of n = (nx, ny, nz) elements (VTK order), its interior
    nodes moved by a smooth warp (a fraction of an element) so the elements are not
    parallelepipeds and the trilinear inversion has work to do."""
    nx, ny, nz = n
    g = np.stack(np.meshgrid(*(np.linspace(0, s, k + 1) for s, k in zip(size, n)), indexing="ij"), -1)
    if warp:
        s = np.array(size)
        b = np.prod(np.sin(np.pi * g / s), axis=-1)            # 0 on the boundary
        g = g + warp * b[..., None] * np.array([1.0, -0.7, 0.4])
    nodes = g.reshape(-1, 3)
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    hexes = np.stack([idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
                      idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1]], 1)
    return nodes, hexes


def test_an_affine_field_is_carried_exactly_and_points_land_inside():
    # trilinear interpolation reproduces affine fields exactly, in any element shape: the
    # carried field agrees to the Newton inversion's round-off (1e-9 mm on a 10 mm body)
    X, H = _box((3, 2, 2), warp=0.4)
    P, _ = _box((7, 5, 3), warp=0.0)
    loc = locate_points(P, X, H)
    assert np.all(np.abs(loc.xi) <= 1.0 + 1e-9)
    assert np.all(loc.outside_mm <= 1e-9)
    A = np.array([[1.1, 0.2, -0.3], [0.05, 0.9, 0.1], [-0.2, 0.3, 1.2]])
    b = np.array([3.0, -1.0, 2.0])
    carried = carry(loc, H, X @ A.T + b)
    np.testing.assert_allclose(carried, P @ A.T + b, atol=1e-9)


def test_a_trilinear_field_is_carried_exactly_in_its_own_elements():
    # a field trilinear within each coarse element (the product x y z on axis-aligned boxes)
    # is what the interpolation is: exact at every located point
    X, H = _box((2, 3, 2))
    P = np.random.default_rng(0).uniform([0, 0, 0], [10, 6, 4], size=(200, 3))
    loc = locate_points(P, X, H)
    f = lambda x: (x[:, 0] * x[:, 1] * x[:, 2])[:, None]
    # x y z is not trilinear across elements, but it is inside each axis-aligned one
    np.testing.assert_allclose(carry(loc, H, f(X)), f(P), atol=1e-8)


def test_points_outside_take_the_nearest_element_and_extrapolate():
    # a point 0.3 mm beyond a face: distance reported to 1e-9, an affine field extrapolated
    X, H = _box((2, 2, 2))
    P = np.array([[5.0, 3.0, 4.3], [-0.3, 1.0, 1.0]])
    loc = locate_points(P, X, H)
    np.testing.assert_allclose(loc.outside_mm, [0.3, 0.3], atol=1e-9)
    np.testing.assert_allclose(carry(loc, H, 2.0 * X + 1.0), 2.0 * P + 1.0, atol=1e-9)


def test_groups_keep_points_on_their_side_of_a_slit():
    # two blocks with a 0.2 mm slit between them, their fields differing by 5: a point of the
    # lower block's group just inside the slit (nearer the upper block's elements) must take
    # the lower block's value
    Xl, Hl = _box((2, 2, 1), size=(4.0, 4.0, 2.0))
    Xu, Hu = Xl + np.array([0.0, 0.0, 2.2]), Hl + len(Xl)
    X, H = np.vstack([Xl, Xu]), np.vstack([Hl, Hu])
    field = np.concatenate([np.zeros(len(Xl)), np.full(len(Xu), 5.0)])[:, None]
    group = np.concatenate([np.ones(len(Hl)), np.full(len(Hu), 2)]).astype(int)
    P = np.array([[2.0, 2.0, 2.15], [2.0, 2.0, 2.05]])      # both nearer the upper block
    free = carry(locate_points(P, X, H), H, field)[:, 0]
    assert free[0] == pytest.approx(5.0)                     # ungrouped: the nearest block
    loc = locate_points(P, X, H, point_group=[1, 1], element_group=group)
    np.testing.assert_allclose(carry(loc, H, field)[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(loc.outside_mm, [0.15, 0.05], atol=1e-9)
