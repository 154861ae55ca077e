"""Contact terms on their own: geometry kernels and consistency of energy, force and tangent."""
import numpy as np
import pytest

from solver.contact import (RigidSurfaceContact, SurfaceContact, TriangleSurface,
                            closest_point_on_triangles, plane_gap)


def test_closest_point_on_triangles_matches_dense_sampling():
    rng = np.random.default_rng(0)
    k = 200
    a, b, c = (rng.standard_normal((k, 3)) for _ in range(3))
    p = 2.0 * rng.standard_normal((k, 3))
    q, region = closest_point_on_triangles(p, a, b, c)
    d = np.linalg.norm(p - q, axis=1)
    # dense barycentric sampling (step 1/200): sampled distance >= exact, within a step's size
    s = np.linspace(0, 1, 201)
    u, v = np.meshgrid(s, s)
    m = u + v <= 1
    u, v = u[m], v[m]
    pts = (a[:, None] + (b - a)[:, None] * u[None, :, None] + (c - a)[:, None] * v[None, :, None])
    dmin = np.linalg.norm(pts - p[:, None], axis=2).min(axis=1)
    h = 1.0 / 200 * np.maximum(np.linalg.norm(b - a, axis=1), np.linalg.norm(c - a, axis=1))
    assert np.all(d <= dmin + 1e-12)
    assert np.all(dmin - d <= 2 * h)
    assert set(np.unique(region)) >= {0}


def test_plane_gap_gradient_and_hessian_by_finite_differences():
    rng = np.random.default_rng(1)
    X = rng.standard_normal((8, 12))

    def f(X):
        return plane_gap(X[:, 0:3], X[:, 3:6], X[:, 6:9], X[:, 9:12])

    g, G, H, n, bc = f(X)
    h = 1e-6
    for i in range(12):
        E = np.zeros(12)
        E[i] = h
        gp, Gp, *_ = f(X + E)
        gm, Gm, *_ = f(X - E)
        # central differences, h = 1e-6 on O(1) geometry: error ~1e-10; tolerance 1e-7
        assert np.allclose((gp - gm) / (2 * h), G[:, i], atol=1e-7)
        assert np.allclose((Gp - Gm) / (2 * h), H[:, :, i], atol=1e-7)
    # the projection point reconstructs the node: x_s - g n = x_1 + xi a + eta b
    proj = X[:, 3:6] + bc[:, :1] * (X[:, 6:9] - X[:, 3:6]) + bc[:, 1:] * (X[:, 9:12] - X[:, 3:6])
    assert np.allclose(X[:, 0:3] - g[:, None] * n, proj, atol=1e-12)


def _sphere(r=1.0, n=3):
    """Icosphere-like closed surface (outward normals) by subdividing an octahedron."""
    V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                  [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    for _ in range(n):
        verts = list(V)
        cache = {}

        def mid(i, j):
            key = (min(i, j), max(i, j))
            if key not in cache:
                m = (verts[i] + verts[j]) / 2
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]
        newF = []
        for a, b, c in F:
            ab, bc_, ca = mid(a, b), mid(b, c), mid(c, a)
            newF += [[a, ab, ca], [ab, b, bc_], [ca, bc_, c], [ab, bc_, ca]]
        V, F = np.array(verts), np.array(newF)
    return r * V, F


def test_signed_distance_to_closed_surface_has_the_right_sign():
    V, F = _sphere(2.0, 3)
    surf = TriangleSurface(V, F)
    rng = np.random.default_rng(2)
    d = rng.standard_normal((300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0.5, 3.5, 300)
    pts = d * r[:, None]
    term = RigidSurfaceContact(np.vstack([pts]), V, F, slave_nodes=np.arange(300),
                               search_radius=10.0)
    g, n, reg, _ = term.gaps(pts, 1.0)
    # the polyhedron lies inside the sphere of radius 2 and outside the one of radius
    # 2 cos(angle of the finest facet) ~ 1.98: the sign is exact away from that thin shell
    far = np.abs(r - 2.0) > 0.05
    assert np.all(np.sign(g[far]) == np.sign(r[far] - 2.0))
    assert np.allclose(np.abs(g[far]), np.abs(r[far] - 2.0), atol=0.05)


def _fd_check(term, x, load, h=1e-6):
    """Force = dE/dx and tangent = df/dx by central differences on every dof."""
    f, K = term.assemble(x, load)
    K = K.toarray()
    n = x.size
    for i in range(n):
        dx = np.zeros(n)
        dx[i] = h
        xp, xm = x + dx.reshape(x.shape), x - dx.reshape(x.shape)
        fe = (term.energy(xp, load) - term.energy(xm, load)) / (2 * h)
        fp, _ = term.assemble(xp, load)
        fm, _ = term.assemble(xm, load)
        # h = 1e-6 on forces of order 1-100 mN: FD error ~1e-8; tolerance 1e-5 (relative)
        scale = max(1.0, np.abs(f).max())
        assert fe == pytest.approx(f[i], abs=1e-5 * scale)
        assert np.allclose((fp - fm) / (2 * h), K[:, i], atol=1e-5 * max(1.0, np.abs(K).max()))
    return f, K


@pytest.mark.parametrize("smooth", [False, True])
@pytest.mark.parametrize("bilateral", [False, True])
def test_rigid_contact_force_and_tangent_are_consistent(bilateral, smooth):
    """Faceted gap, or the spline signed distance (`smooth`) under a 90 deg rotation."""
    V, F = _sphere(2.0, 3 if smooth else 2)
    rng = np.random.default_rng(3)
    d = rng.standard_normal((6, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = d * rng.uniform(1.8 if smooth else 1.7, 2.1, 6)[:, None]
    motion = np.eye(4)
    if smooth:
        motion[:3, :3] = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    motion[:3, 3] = [0.1, -0.05, 0.02]
    grid = dict(smooth=True, grid_spacing=0.2, search_radius=1.0, max_depth=1.0) if smooth else {}
    term = RigidSurfaceContact(x, V, F, slave_nodes=np.arange(6),
                               slave_areas=rng.uniform(0.5, 1.5, 6), motion=motion,
                               penalty=30.0, bilateral=bilateral, **grid)
    term.multipliers[:] = rng.uniform(0, 3, 6)
    f, K = _fd_check(term, x, 0.7)
    assert np.abs(f).max() > 0
    assert np.allclose(K, K.T)


def test_deformable_contact_force_and_tangent_are_consistent():
    """Two facing wavy patches: slaves of each against the other's triangles."""
    nx = 4
    s = np.linspace(0, 3, nx)
    gx, gy = np.meshgrid(s, s, indexing="ij")
    bottom = np.stack([gx.ravel(), gy.ravel(), 0.1 * np.sin(gx + gy).ravel()], axis=1)
    top = bottom.copy()
    top[:, :2] += [0.37, 0.21]  # off the quads diagonals
    top[:, 2] = -0.05 + 0.1 * np.cos(gx - gy).ravel()
    x = np.vstack([bottom, top])
    q = np.array([[i * nx + j, (i + 1) * nx + j, (i + 1) * nx + j + 1, i * nx + j + 1]
                  for i in range(nx - 1) for j in range(nx - 1)])
    quads_bottom = q                                   # normal +z
    quads_top = q[:, ::-1] + nx * nx                   # normal -z
    term = SurfaceContact(x, quads_bottom, quads_top, penalty=50.0, search_radius=1.0)
    for ps in term.passes:
        ps.multipliers[:] = 0.3
    f, K = _fd_check(term, x, 1.0)
    assert np.abs(f).max() > 0
    # action and reaction: contact forces sum to zero
    assert np.allclose(f.reshape(-1, 3).sum(axis=0), 0.0, atol=1e-10)


def test_projected_rigid_tangent_is_positive_semidefinite_with_the_same_forces():
    """Nodes pressed onto a convex obstacle (a sphere, spline distance): the exact tangent has
    the negative curvature stiffness -p d2g/dx2; the projected one clips it to >= 0 per node and
    keeps the forces."""
    V, F = _sphere(2.0, 3)
    rng = np.random.default_rng(5)
    d = rng.standard_normal((6, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = d * rng.uniform(1.9, 2.05, 6)[:, None]
    kw = dict(slave_nodes=np.arange(6), slave_areas=np.ones(6), penalty=30.0, smooth=True,
              grid_spacing=0.2, search_radius=1.0, max_depth=1.0)
    exact = RigidSurfaceContact(x, V, F, **kw)
    proj = RigidSurfaceContact(x, V, F, tangent="projected", **kw)
    for t in (exact, proj):
        t.multipliers[:] = 3.0
    f0, K0 = exact.assemble(x, 1.0)
    f1, K1 = proj.assemble(x, 1.0)
    assert np.array_equal(f0, f1)
    K0, K1 = K0.toarray(), K1.toarray()
    # convex obstacle, pressing nodes: the exact tangent has the tangential stiffness
    # -p/R ~ -3/2 (no other stiffness acts tangentially), so it is indefinite; the projected
    # one is not (round-off 1e-9)
    assert np.linalg.eigvalsh(K0).min() < -0.1
    assert np.linalg.eigvalsh(K1).min() > -1e-9
    # the projection only removes the negative part of the curvature stiffness: K1 - K0 is
    # positive semi-definite, and zero where the exact one already was (round-off 1e-9)
    assert np.linalg.eigvalsh(K1 - K0).min() > -1e-9
    assert np.abs(K1 - K0).max() > 0.1
    # once the contact status is frozen (after `freeze_after` evaluations at one load) the
    # projected term gives back the exact tangent (quadratic convergence near the solution)
    for _ in range(proj.freeze_after):
        exact.assemble(x, 1.0)
        _, Kf = proj.assemble(x, 1.0)
    assert np.allclose(Kf.toarray(), exact.assemble(x, 1.0)[1].toarray(), rtol=0, atol=1e-12)


def _ridge_pairing(hysteresis, shifts):
    """Triangle of the ridge (convex crease along y between two master triangles, T0 on the
    x < 0 side, T1 on x > 0) that a slave node slightly inside it is paired with, after each
    lateral shift of the slave facet (one search per position, as at Newton iterations)."""
    master = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.5, -0.3], [1.0, 0.5, -0.3]])
    tris = np.array([[0, 1, 2], [0, 3, 1]])                 # normals (-0.3, 0, 1), (0.3, 0, 1)
    slave = np.array([[-0.02, 0.5, -0.02], [-0.02, 0.8, -0.02], [0.28, 0.5, -0.02]])
    x = np.vstack([master, slave])
    term = SurfaceContact(x, np.array([[4, 5, 6]]), tris, two_pass=False, penalty=10.0,
                          search_radius=0.5, ignore_initial_penetration=False,
                          pair_hysteresis=hysteresis)
    ps = term.passes[0]
    out = []
    for dx in shifts:
        y = x.copy()
        y[4:, 0] += dx
        ps.pairs(y, term.search_radius, term.max_depth, hessian=False)
        out.append(int(ps.previous[ps.slave_pos[4]]))
    return out


def test_pairing_hysteresis_keeps_the_triangle_across_a_crease_within_the_band():
    """A node just across the ridge (barycentric 0.01 outside its triangle) keeps it with the
    0.05 band, switches at once without it, and switches with the band too once it is well
    over the other side (0.28 outside): the band only stops the flip-flop of a node on the
    crease, it does not pin a node to a triangle it has left."""
    assert _ridge_pairing(0.05, [0.0, 0.03, 0.3]) == [0, 0, 1]
    assert _ridge_pairing(0.0, [0.0, 0.03, 0.3]) == [0, 1, 1]
    with pytest.raises(ValueError, match="pair_hysteresis"):
        _ridge_pairing(0.7, [0.0])
