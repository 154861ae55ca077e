"""The shared geometry kernels of `solver.geometry` against brute force and exact answers.

* point_triangle: on random triangles and points its distance equals the minimum over a dense
  barycentric grid up to the grid's resolution (|d - d_grid| <= h * longest edge, h = 1/400,
  and never larger: it is the minimum), and q = u a + v b + w c to round-off (1e-12).
* deepest_concavity: on a profile with a V-notch cut into a straight front the deepest point is
  the notch's tip and the spanning hull edge joins the notch's rims, exactly.
* TriangleTree: on a fine sphere beside a few huge triangles (nearest centroids alone miss the
  large ones), and on a surface whose triangle sizes span three orders of magnitude (grouped
  into pieces), its distances equal every-triangle brute force to rounding (1e-9 mm),
  and within `max_distance` where that is given.
"""
import numpy as np
import trimesh

from solver import geometry
from solver.geometry import FACE, deepest_concavity, point_triangle


def test_point_triangle_matches_brute_force():
    rng = np.random.default_rng(3)
    n = 400
    s, t = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    keep = s + t <= 1.0
    s, t = s[keep], t[keep]
    regions = set()
    for _ in range(40):
        a, b, c = rng.normal(size=(3, 3))
        p = 1.5 * rng.normal(size=3)
        qx, qy, qz, u, v, w, region = point_triangle(*p, *a, *b, *c)
        regions.add(region)
        q = np.array([qx, qy, qz])
        assert np.abs(q - (u * a + v * b + w * c)).max() < 1e-12
        assert min(u, v, w) >= -1e-12 and abs(u + v + w - 1.0) < 1e-12
        grid = a + s[:, None] * (b - a) + t[:, None] * (c - a)
        d_grid = np.linalg.norm(grid - p, axis=1).min()
        d = np.linalg.norm(q - p)
        edge = max(np.linalg.norm(b - a), np.linalg.norm(c - a), np.linalg.norm(c - b))
        assert d <= d_grid + 1e-12 and d_grid - d <= edge / n
    assert FACE in regions and len(regions) >= 4      # faces, edges and vertices exercised


def test_deepest_concavity_finds_a_notch():
    z = np.linspace(10.0, -10.0, 201)                  # ordered downwards
    y = np.zeros_like(z)
    notch = np.abs(z) < 3.0
    y[notch] = -(3.0 - np.abs(z[notch]))               # 3 mm deep V-notch behind the front
    k, i, j, inward = deepest_concavity(np.stack([y, z], axis=1), 0, 200)
    assert k == 100                                    # the tip, z = 0
    assert abs(z[i] - 3.0) < 0.11 and abs(z[j] + 3.0) < 0.11
    assert np.allclose(inward, [-1.0, 0.0])


def _brute_closest(v, f, p):
    """Every triangle a candidate: the exact answer by definition."""
    cand = np.tile(np.arange(len(f)), (len(p), 1))
    return geometry._closest_over_candidates(np.ascontiguousarray(p), v, f, cand)


def test_triangle_tree_is_exact_with_mixed_triangle_sizes():
    # a fine sphere patch next to a few huge triangles: nearest centroids alone miss the large
    # ones; the c - r bound must bring them in
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=20.0)
    big_v = np.array([[-200.0, -200.0, 30.0], [200.0, -200.0, 30.0], [0.0, 300.0, 30.0]])
    v = np.vstack([sphere.vertices, big_v])
    f = np.vstack([sphere.faces, [[len(sphere.vertices), len(sphere.vertices) + 1, len(sphere.vertices) + 2]]])
    rng = np.random.default_rng(3)
    p = rng.uniform(-40, 40, size=(400, 3))
    q, bary, face, d = geometry.TriangleTree(v, f).closest(p, k=4)
    q0, _, _, d0 = _brute_closest(np.ascontiguousarray(v, float), np.ascontiguousarray(f, np.int64), p)
    # the same distance to rounding (1e-9 mm at these sizes); the point on its triangle
    assert np.allclose(d, d0, atol=1e-9)
    assert np.allclose(np.einsum("nk,nkd->nd", bary, v[f[face]]), q, atol=1e-9)


def test_triangle_tree_levels_are_exact_over_many_sizes():
    # a wavy sheet whose cells grow geometrically from 0.05 mm to ~50 mm along x: several size
    # levels, each triangle's neighbours of another size
    edges = 0.05 * 1.35 ** np.arange(24)
    xs = np.concatenate([[0.0], np.cumsum(edges)])
    ys = np.linspace(0.0, 60.0, 13)
    gx, gy = np.meshgrid(xs, ys)
    v = np.column_stack([gx.ravel(), gy.ravel(), 2.0 * np.sin(gx.ravel() / 15.0)])
    nx = len(xs)
    i = (np.arange(len(ys) - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
    f = np.vstack([np.column_stack([i, i + 1, i + nx]), np.column_stack([i + 1, i + nx + 1, i + nx])])
    tree = geometry.TriangleTree(v, f)
    assert len(tree._owner) > len(f)             # the large cells are cut into pieces
    rng = np.random.default_rng(11)
    p = np.column_stack([rng.uniform(-5, xs[-1] + 5, 600), rng.uniform(-5, 65, 600), rng.uniform(-6, 6, 600)])
    p[:200, 0] = rng.uniform(0.0, 3.0, 200)          # crowd the smallest cells
    q, bary, face, d = tree.closest(p, k=4)
    q0, _, _, d0 = _brute_closest(np.ascontiguousarray(v, float), np.ascontiguousarray(f, np.int64), p)
    assert np.allclose(d, d0, atol=1e-9)
    assert np.allclose(np.einsum("nk,nkd->nd", bary, v[f[face]]), q, atol=1e-9)
    # exact within max_distance; beyond it an upper bound that is itself beyond it
    _, _, _, dm = tree.closest(p, k=4, max_distance=1.0)
    near = d0 <= 1.0
    assert near.sum() > 50 and np.allclose(dm[near], d0[near], atol=1e-9)
    assert np.all(dm[~near] > 1.0)
