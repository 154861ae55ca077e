"""Smooth signed distance of rigid surfaces (`solver.contact._sdf`) and the contact terms built
on it: exact distances near the surface, consistent derivatives, and a faceted-edge tangent."""
import numpy as np
import pytest
from scipy import ndimage

from solver.contact import RigidSurfaceContact
from solver.contact._sdf import SignedDistanceGrid

from tests.solver.test_contact_terms import _fd_check, _sphere


def _box(lo, hi):
    """Closed axis-aligned box surface with outward normals (12 triangles)."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    V = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], float)
    quads = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [1, 2, 6, 5], [3, 0, 4, 7]]
    F = np.array([t for q in quads for t in ([q[0], q[1], q[2]], [q[0], q[2], q[3]])])
    return V, F


def _box_sdf(p, lo, hi):
    c, e = (np.asarray(lo) + hi) / 2, (np.asarray(hi) - lo) / 2
    q = np.abs(p - c) - e
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


@pytest.fixture(scope="module")
def sphere_grid():
    V, F = _sphere(10.0, 4)
    return V, F, SignedDistanceGrid(V, F, band=3.0, spacing=0.4)


def test_signed_distance_of_a_sphere_is_exact_near_the_surface(sphere_grid):
    V, F, grid = sphere_grid
    rng = np.random.default_rng(0)
    d = rng.standard_normal((500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(8.5, 11.5, 500)
    phi, grad, hess, ok = grid.evaluate(d * r[:, None])
    assert ok.all()
    # exact distance to the faceted sphere: the facets (4 subdivisions of an octahedron, edge
    # ~1 mm) sag below the r = 10 sphere by at most r (1 - cos(theta/2)) < 0.02 mm; the cubic
    # spline interpolation error of a field of curvature 1/r at step 0.4 is ~ h^2 / (8 r) ~
    # 0.002 mm: 0.05 mm covers both
    assert np.abs(phi - (r - 10.0)).max() < 0.05
    # |grad phi| = 1 (eikonal) within the facet/interpolation errors; the gradient points
    # away from the closest facet, edge or vertex, which for points up to 1.5 mm off a
    # polyhedron with ~1 mm facets is radial within ~20 degrees (cos > 0.9)
    assert np.allclose(np.linalg.norm(grad, axis=1), 1.0, atol=0.03)
    assert np.einsum("ij,ij->i", grad, d).min() > 0.9
    # far inside (beyond the band) is negative, far outside positive
    far, _, _, _ = grid.evaluate(np.array([[0.0, 0, 0], [0, 0, 2.0], [0, 13.5, 0]]))
    assert far[0] < 0 and far[1] < 0 and far[2] > 0


def test_spline_derivatives_match_finite_differences_and_scipy(sphere_grid):
    _, _, grid = sphere_grid
    rng = np.random.default_rng(1)
    p = rng.uniform(-11, 11, (200, 3))
    phi, grad, hess, ok = grid.evaluate(p)
    p, phi, grad, hess = p[ok], phi[ok], grad[ok], hess[ok]
    # the value is scipy's order-3 spline interpolation of the same coefficients (to round-off)
    u = ((p - grid.origin) / grid.spacing).T
    ref = ndimage.map_coordinates(grid.coefficients, u, order=3, prefilter=False, mode="mirror")
    assert np.allclose(phi, ref, atol=1e-12)
    # central differences, h = 1e-5 mm on a field with second derivatives ~1/h_grid: error
    # ~1e-9; tolerance 1e-6
    h = 1e-5
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fp, gp, _, _ = grid.evaluate(p + e)
        fm, gm, _, _ = grid.evaluate(p - e)
        assert np.allclose((fp - fm) / (2 * h), grad[:, k], atol=1e-6)
        assert np.allclose((gp - gm) / (2 * h), hess[:, :, k], atol=1e-6)
    assert np.allclose(hess, np.swapaxes(hess, 1, 2))


def test_box_corners_are_rounded_by_about_one_grid_step():
    lo, hi = np.array([0.0, 0, 0]), np.array([8.0, 6, 5])
    V, F = _box(lo, hi)
    grid = SignedDistanceGrid(V, F, band=2.0, spacing=0.25)
    rng = np.random.default_rng(2)
    p = rng.uniform(-1.5, 9.5, (4000, 3))
    phi, _, _, ok = grid.evaluate(p)
    exact = _box_sdf(p, lo, hi)
    sel = ok & (np.abs(exact) < 1.5)
    err = np.abs(phi[sel] - exact[sel])
    # the signed distance of a box is not smooth across its edges (inside: the medial
    # planes; outside it is C1): the C2 spline rounds those creases over ~2 steps, an error
    # below ~h/4 there; away from them the interpolating spline's prefilter spreads a crease's
    # error with a decay of |sqrt(3) - 2| ~ 0.27 per step, so the typical point (a few steps
    # from the nearest crease here) is within 1e-3 mm
    assert err.max() < 0.25 * grid.spacing + 1e-9
    assert np.median(err) < 1e-3


def test_faceted_contact_tangent_near_box_edges():
    """Nodes just off a box's edges and corners, held by multipliers (active contact) with the
    faceted gap: where the closest feature is an edge, the distance to the edge's line has
    no curvature along the edge (the tangent was 67 % off there before)."""
    from solver.contact._geometry import EDGE_AB, EDGE_BC, EDGE_CA, FACE

    V, F = _box((0.0, 0.0, 0.0), (4.0, 1.0, 2.0))
    pts = np.array([[4.05, 0.5, 2.04], [2.0, 1.03, 2.02], [4.03, 1.02, 2.05],
                    [0.5, -0.04, 1.0]])
    term = RigidSurfaceContact(pts, V, F, slave_nodes=np.arange(4),
                               slave_areas=np.ones(4), penalty=50.0, search_radius=1.0)
    term.multipliers[:] = 5.0                 # p = 5 - 50 g > 0: all four act
    g, n, reg, _ = term.gaps(pts, 1.0)
    assert np.all(g > 0)
    assert np.isin(reg[:2], [EDGE_AB, EDGE_BC, EDGE_CA]).all()   # two edge points
    assert reg[2] not in (FACE, EDGE_AB, EDGE_BC, EDGE_CA)       # a corner (vertex)
    assert reg[3] == FACE
    f, K = _fd_check(term, pts, 1.0)
    assert np.abs(f).max() > 0


def test_narrow_band_does_not_depend_on_the_thread_count():
    """The narrow-band distances are computed in slabs of grid planes, one per thread, each
    visiting the faces in the same order: 1, 2 or 3 slabs give bit-identical distances and
    closest faces (the culling by plane distance skips only nodes that could not improve)."""
    from solver.contact._sdf import _narrow_band

    V, F = _sphere(8.0, 2)
    h, band = 0.6, 2.0
    lo = V.min(axis=0) - band - 3 * h
    shape = np.ceil((V.max(axis=0) + band + 3 * h - lo) / h).astype(np.int64) + 1
    n = int(np.prod(shape))
    out = [_narrow_band(V, np.asarray(F, np.int64), lo, h, shape, band, np.full(n, np.inf),
                        np.full(n, -1, dtype=np.int64), k) for k in (1, 2, 3)]
    for d, b in out[1:]:
        assert np.array_equal(d, out[0][0]) and np.array_equal(b, out[0][1])
    near = np.isfinite(out[0][0])
    assert near.sum() > 1000


def test_shared_grids_are_built_once_per_surface_and_parameters():
    # the same surface and parameters give the same grid object (built once per process);
    # another band, or a moved vertex, gives another grid with its own distances
    from solver.contact._sdf import SignedDistanceGrid

    V, F = _box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    a = SignedDistanceGrid.shared(V, F, band=1.0, spacing=0.3)
    assert SignedDistanceGrid.shared(V.copy(), F.copy(), band=1.0, spacing=0.3) is a
    b = SignedDistanceGrid.shared(V, F, band=1.5, spacing=0.3)
    assert b is not a
    W = V.copy()
    W[0] += 0.1
    c = SignedDistanceGrid.shared(W, F, band=1.0, spacing=0.3)
    assert c is not a and not np.array_equal(c.coefficients, a.coefficients)
