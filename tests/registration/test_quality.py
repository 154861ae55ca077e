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
