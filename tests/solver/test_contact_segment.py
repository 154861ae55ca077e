"""Segment-to-segment contact (`SegmentContact`): quadrature, projection on bilinear facets,
and consistency of energy, force and tangent at states with many active Gauss points."""
import numpy as np
import pytest

from solver.contact import SegmentContact, facet_quadrature
from solver.contact.segment import _project, facet_gap

from test_contact_terms import _fd_check


@pytest.mark.parametrize("nv", [3, 4])
@pytest.mark.parametrize("subdivisions", [1, 3])
def test_facet_quadrature_is_exact_for_polynomials(nv, subdivisions):
    N, dN, w = facet_quadrature(3, nv, subdivisions)
    # partition of unity and its derivative
    assert np.allclose(N.sum(axis=1), 1.0) and np.allclose(dN.sum(axis=1), 0.0)
    if nv == 4:
        xi = N[:, 1] + N[:, 2] - N[:, 0] - N[:, 3]
        eta = N[:, 2] + N[:, 3] - N[:, 0] - N[:, 1]
        # 3-point Gauss is exact to degree 5 per direction: int xi^4 eta^2 = (2/5)(2/3)
        assert (w * xi ** 4 * eta ** 2).sum() == pytest.approx(4 / 15, rel=1e-13)
        assert w.sum() == pytest.approx(4.0, rel=1e-13)
    else:
        u, v = N[:, 1], N[:, 2]
        # collapsed 3x3 Gauss: exact to total degree 4; int u^2 v^2 = 2! 2! / 6!
        assert (w * u ** 2 * v ** 2).sum() == pytest.approx(4 / 720, rel=1e-12)
        assert w.sum() == pytest.approx(0.5, rel=1e-13)


def test_lobatto_quadrature_has_points_on_the_nodes():
    # trapezoid: exact for bilinear integrands; Simpson: to degree 3 per direction
    for n, f, exact in ((2, lambda u, v: (1 + u) * (2 - v), 8.0),
                        (3, lambda u, v: u ** 2 * v ** 2 + u ** 3 * v, 4.0 / 9.0)):
        N, dN, w = facet_quadrature(n, 4, 2, rule="lobatto")
        xi = N[:, 1] + N[:, 2] - N[:, 0] - N[:, 3]
        eta = N[:, 2] + N[:, 3] - N[:, 0] - N[:, 1]
        # composite trapezoid (n = 2) / Simpson (n = 3) on 2 x 2 sub-squares, shared points
        # merged: (2 (n - 1) + 1)^2 points, the facet's nodes among them
        assert len(w) == (2 * (n - 1) + 1) ** 2
        assert np.sum(np.isclose(N, 1.0)) == 4
        assert (w * f(xi, eta)).sum() == pytest.approx(exact, rel=1e-13)
    with pytest.raises(ValueError):
        facet_quadrature(4, 4, 1, rule="lobatto")
    with pytest.raises(ValueError):
        facet_quadrature(2, 3, 1, rule="lobatto")


@pytest.mark.parametrize("nv", [3, 4])
def test_projection_gap_normal_and_hessian_by_finite_differences(nv):
    """Closest point on warped bilinear quads (and triangles): gap, normal and Hessian."""
    rng = np.random.default_rng(4)
    k = 6
    ref = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)[:nv]
    xm0 = ref[None] + 0.15 * rng.standard_normal((k, nv, 3))
    xg0 = np.array([0.35, 0.3, 0.3]) + 0.1 * rng.standard_normal((k, 3))
    start = np.zeros(2) if nv == 4 else np.full(2, 1 / 3)

    def gap(y):
        xg, xm = y[:, :3], y[:, 3:].reshape(k, nv, 3)
        zeta = np.empty((k, 2))
        _project(np.ascontiguousarray(xg), np.arange(k * nv).reshape(k, nv),
                 np.ascontiguousarray(xm.reshape(-1, 3)), start, zeta)
        return facet_gap(xg, xm, zeta, True, True) + (zeta,)

    y = np.concatenate([xg0, xm0.reshape(k, -1)], axis=1)
    g, n, N, dg, dn, H, zeta = gap(y)
    # the projection is the closest point: r = x_g - x(zeta) is along the normal
    xp = np.einsum("ka,kai->ki", N, xm0)
    assert np.allclose(xg0 - xp, g[:, None] * n, atol=1e-12)
    h = 1e-6
    for i in range(y.shape[1]):
        e = np.zeros(y.shape[1])
        e[i] = h
        gp, np_, _, dgp, *_ = gap(y + e)
        gm, nm, _, dgm, *_ = gap(y - e)
        # central differences, h = 1e-6 on O(1) geometry: error ~1e-10; tolerance 1e-7
        assert np.allclose((gp - gm) / (2 * h), dg[:, i], atol=1e-7)
        assert np.allclose((np_ - nm) / (2 * h), dn[:, :, i], atol=1e-7)
        assert np.allclose((dgp - dgm) / (2 * h), H[:, :, i], atol=1e-7)
    assert np.allclose(H, np.swapaxes(H, 1, 2), atol=1e-12)


def _wavy_patches(nx=4, shift=(0.37, 0.21), triangles=False):
    """Two facing wavy patches, overlapping by ~0.05-0.2 mm, off each other's grid."""
    s = np.linspace(0, 3, nx)
    gx, gy = np.meshgrid(s, s, indexing="ij")
    bottom = np.stack([gx.ravel(), gy.ravel(), 0.1 * np.sin(gx + gy).ravel()], axis=1)
    top = bottom.copy()
    top[:, :2] += shift
    top[:, 2] = -0.05 + 0.1 * np.cos(gx - gy).ravel()
    x = np.vstack([bottom, top])
    q = np.array([[i * nx + j, (i + 1) * nx + j, (i + 1) * nx + j + 1, i * nx + j + 1]
                  for i in range(nx - 1) for j in range(nx - 1)])
    if triangles:
        q = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    return x, q, q[:, ::-1] + nx * nx


@pytest.mark.parametrize("formulation, triangles, rule", [
    ("symmetric", False, "gauss"), ("symmetric", True, "gauss"), ("symmetric", False, "lobatto"),
    ("two_half_pass", False, "gauss"), ("two_half_pass", True, "gauss")])
def test_segment_contact_force_and_tangent_are_consistent(formulation, triangles, rule):
    x, a, b = _wavy_patches(triangles=triangles)
    # one sub-square per facet (the composite rule only repeats the same kernels): 2x2
    # Gauss points, or 3x3 Simpson points with the nodes among them
    quad = dict(quadrature=3 if rule == "lobatto" else 2, subdivisions=1, rule=rule)
    term = SegmentContact(x, a, b, penalty=50.0, search_radius=1.0, formulation=formulation,
                          ignore_initial_penetration=False, **quad)
    for ps in term.passes:
        ps.multipliers[:] = 0.3
    f, K = term.assemble(x, 1.0)
    # several active Gauss points on both sides
    assert all(ps.active.sum() >= 15 for ps in term.passes)
    if formulation == "symmetric":
        # a potential: force = dE/dx and tangent = df/dx (central differences, tolerances
        # in `_fd_check`), a symmetric tangent, and action = reaction
        f, K = _fd_check(term, x, 1.0)
        assert np.allclose(K, K.T, atol=1e-10 * np.abs(K).max())
        assert np.allclose(f.reshape(-1, 3).sum(axis=0), 0.0, atol=1e-12)
    else:
        # half passes derive from no potential: tangent = df/dx only (same tolerance)
        K = K.toarray()
        h = 1e-6
        for i in range(x.size):
            dx = np.zeros(x.size)
            dx[i] = h
            fp, _ = term.assemble(x + dx.reshape(x.shape), 1.0)
            fm, _ = term.assemble(x - dx.reshape(x.shape), 1.0)
            assert np.allclose((fp - fm) / (2 * h), K[:, i], atol=1e-5 * np.abs(K).max())
    # contact_forces is minus the residual term at the same state
    term2 = SegmentContact(x, a, b, penalty=50.0, search_radius=1.0, formulation=formulation,
                           ignore_initial_penetration=False, **quad)
    for ps in term2.passes:
        ps.multipliers[:] = 0.3
    f2, _ = term2.assemble(x, 1.0)
    assert np.allclose(term2.contact_forces(x).ravel(), -f2, atol=1e-12)


def test_initial_penetration_is_ignored_and_input_is_checked():
    x, a, b = _wavy_patches()
    term = SegmentContact(x, a, b, penalty=50.0, search_radius=1.0)
    assert term.initial_penetration > 0.05
    f, K = term.assemble(x, 1.0)
    assert np.abs(f).max() == 0.0 and term.penetration(x) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError):
        SegmentContact(x, a, b, formulation="mortar")
    with pytest.raises(ValueError):
        SegmentContact(x, a[:, :2], b)
    with pytest.raises(ValueError):
        SegmentContact(x, a, b, penalty=0.0)
