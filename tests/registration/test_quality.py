"""Scaled Jacobian: analytic values on boxes and sheared/inverted hexahedra, exact gradient."""
import numpy as np
import pytest

from registration.quality import (corner_jacobians, min_scaled_jacobian, quality_summary,
                                  scaled_jacobian_gradient, scaled_jacobians)

UNIT = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                 [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
HEX = np.arange(8)[None]


def test_box_has_unit_scaled_jacobian_and_volume_determinant():
    box = UNIT * [3.0, 2.0, 0.5]
    assert np.allclose(scaled_jacobians(box, HEX), 1.0, atol=1e-14)
    # corner determinant = product of edge lengths; the centre one uses half-sums (same here)
    assert np.allclose(corner_jacobians(box, HEX), 3.0, atol=1e-14)


def test_shear_gives_cosine_of_shear_angle():
    # x' = x + tan(a) z: every corner's edges (x, y, z') -> sj = cos(a) exactly
    a = np.radians(35.0)
    sheared = UNIT.copy()
    sheared[:, 0] += np.tan(a) * sheared[:, 2]
    assert np.allclose(scaled_jacobians(sheared, HEX), np.cos(a), atol=1e-12)


def test_inverted_and_mirrored_elements_are_negative():
    collapsed = UNIT.copy()
    collapsed[6] = [0.2, 0.2, -0.5]  # top corner pushed through the bottom face
    q = scaled_jacobians(collapsed, HEX)[0]
    assert q[6] < 0 and min_scaled_jacobian(collapsed, HEX)[0] < 0
    mirrored = UNIT * [-1, 1, 1]
    assert np.allclose(scaled_jacobians(mirrored, HEX), -1.0)
    s = quality_summary(np.vstack([UNIT, collapsed]), np.array([np.arange(8), np.arange(8, 16)]))
    assert s["n_inverted"] == 1 and sum(s["histogram"]["counts"]) == 2


def test_gradient_matches_central_differences():
    rng = np.random.default_rng(3)
    x = UNIT + 0.15 * rng.standard_normal(UNIT.shape)
    sj, grad = scaled_jacobian_gradient(x, HEX)
    h = 1e-6
    fd = np.zeros_like(grad)
    for n in range(8):
        for d in range(3):
            xp, xm = x.copy(), x.copy()
            xp[n, d] += h
            xm[n, d] -= h
            fd[0, :, n, d] = (scaled_jacobians(xp, HEX)[0] - scaled_jacobians(xm, HEX)[0]) / (2 * h)
    # central differences are O(h^2) ~ 1e-12 accurate; round-off ~ 1e-16 / 1e-6 = 1e-10
    assert np.abs(grad - fd).max() < 1e-7
    assert np.allclose(sj, scaled_jacobians(x, HEX))


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_scale_invariance(scale):
    rng = np.random.default_rng(0)
    x = UNIT + 0.1 * rng.standard_normal(UNIT.shape)
    assert np.allclose(scaled_jacobians(scale * x, HEX), scaled_jacobians(x, HEX), atol=1e-12)


# valid at its eight corners and its centre, inverted at a Gauss point: det J of a trilinear
# hexahedron is a polynomial in the natural coordinates, so positive corners do not bound it
WARPED_INSIDE = np.array([[0.593, -0.091, -0.084], [1.228, 0.843, 0.145], [1.052, 0.804, 0.126],
                          [0.553, 0.932, -0.069], [-0.236, -0.632, 1.685], [0.71, 0.58, 0.36],
                          [1.677, 0.458, 0.312], [-0.14, 0.01, 1.4]])


def test_an_element_inverted_only_at_a_gauss_point_is_inverted():
    from solver.errors import MeshError
    from solver.mesh import check_mesh

    sj = scaled_jacobians(WARPED_INSIDE, HEX)[0]
    assert sj[:9].min() > 0.05  # the corners and the centre alone would pass it
    assert min_scaled_jacobian(WARPED_INSIDE, HEX)[0] < 0
    assert quality_summary(WARPED_INSIDE, HEX)["n_inverted"] == 1
    with pytest.raises(MeshError):
        check_mesh(WARPED_INSIDE, HEX)


def test_gauss_point_rows_are_the_isoparametric_jacobian():
    # rows 9-16 are 2 dx/dxi at the 2x2x2 Gauss points: their determinants are 8 det J there,
    # det J computed independently by the solver's shape-function gradients
    from solver.mesh._hexmesh import det3, gauss_hex, hex8_gradients

    rng = np.random.default_rng(5)
    x = UNIT + 0.2 * rng.standard_normal(UNIT.shape)
    xg, _ = gauss_hex(2)
    jg = det3(np.einsum("ai,qaj->qij", x, hex8_gradients(xg)))
    ours = corner_jacobians(x, HEX)[0, 9:]
    # the same point set (order may differ): compare sorted values to round-off
    assert np.allclose(np.sort(ours), np.sort(8.0 * jg), rtol=1e-12, atol=1e-14)


def test_the_gate_agrees_with_the_solver_on_random_elements():
    # every element the quality measure calls valid, the solver accepts: the measure judges
    # the solver's points (corners, 2x2x2 Gauss points) and the centre besides. Draws strong
    # enough that a few hundred of 3000 are inverted somewhere.
    from solver.errors import MeshError
    from solver.mesh import check_mesh

    rng = np.random.default_rng(11)
    disagree = inverted = 0
    for _ in range(3000):
        x = UNIT + 0.4 * rng.standard_normal(UNIT.shape)
        ours = min_scaled_jacobian(x, HEX)[0] > 0
        try:
            check_mesh(x, HEX)
            theirs = True
        except MeshError:
            theirs = False
        disagree += ours and not theirs
        inverted += not theirs
    assert disagree == 0 and inverted > 100
