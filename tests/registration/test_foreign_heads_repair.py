"""The repair on degenerate input: a collapsed edge (two nodes on one point) neither crashes
the objective nor survives the repair."""
import numpy as np

from registration.quality import EDGE_OPERATOR, min_scaled_jacobian
from registration.repair import _penalty_and_gradient, repair_mesh
from shell import ellipsoid_radius, shell_mesh

INNER = ellipsoid_radius(70, 85, 95)
OUTER = ellipsoid_radius(84, 100, 108)


def _collapsed():
    nodes, hexes, *_ = shell_mesh(INNER, OUTER, n_theta=10, n_phi=8, n_layers=3)
    x = np.array(nodes, float)
    h = hexes[len(hexes) // 2]
    x[h[1]] = x[h[0]]          # edge 0-1 of one element collapsed to a point
    return x, np.asarray(hexes)


def test_objective_finite_on_a_collapsed_edge():
    x, hexes = _collapsed()
    local = np.arange(len(x), dtype=np.int64)
    h = 5.0
    f, g = _penalty_and_gradient(x, hexes.astype(np.int64), local, len(x), EDGE_OPERATOR, 0.3, (1e-6 * h) ** 2)
    assert np.isfinite(f) and np.isfinite(g).all() and f > 0


def test_repair_untangles_a_collapsed_edge():
    x, hexes = _collapsed()
    assert min_scaled_jacobian(x, hexes).min() < 1e-6
    y, rep = repair_mesh(x, hexes, threshold=0.2)
    # the repair's own gate, checked independently
    assert min_scaled_jacobian(y, hexes).min() >= 0.2
    assert rep["elements_still_below_threshold"] == 0


def test_regularised_penalty_matches_the_exact_one_on_a_sound_mesh():
    """eps2 = (1e-6 h)^2 changes the penalty by a relative ~1e-12 where no edge is short:
    1e-9 leaves room for round-off over the sum."""
    nodes, hexes, *_ = shell_mesh(INNER, OUTER, n_theta=6, n_phi=5, n_layers=2)
    rng = np.random.default_rng(3)
    x = nodes + rng.normal(0, 2.0, nodes.shape)
    local = np.arange(len(x), dtype=np.int64)
    f0, g0 = _penalty_and_gradient(x, hexes.astype(np.int64), local, len(x), EDGE_OPERATOR, 0.5)
    f1, g1 = _penalty_and_gradient(x, hexes.astype(np.int64), local, len(x), EDGE_OPERATOR, 0.5, 25e-12)
    assert abs(f1 - f0) <= 1e-9 * f0
    assert np.abs(g1 - g0).max() <= 1e-9 * np.abs(g0).max()



def _plane(z: float, half: float = 20.0):
    from registration.surface import TargetSurface

    g = np.linspace(-half, half, 9)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    v = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], 1)
    idx = np.arange(len(v)).reshape(xx.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return TargetSurface(v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))


def test_release_when_the_surfaces_leave_no_room():
    """A box whose top face is held on a "skin" plane that lies 2 mm *below* its bottom face,
    fixed on the bone (a patient skin crossing the bone, as a surface mismatch can give):
    the bottom corners' Jacobians stay negative wherever the top nodes slide on their plane,
    so the constrained rounds fail; the release stage frees the top face's nodes (the fixed
    ones never move), and the element ends valid, the released nodes reported."""
    from registration.repair import SurfaceConstraint

    base = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]], float)
    x = np.vstack([base, base + [0.0, 0.0, -2.0]])       # top face below the bottom one
    hexes = np.arange(8)[None]
    assert min_scaled_jacobian(x, hexes).min() < 0
    cons = [SurfaceConstraint("skin", np.arange(4, 8), _plane(-2.0)),
            SurfaceConstraint("bone", np.arange(4), _plane(0.0))]
    bottom = np.arange(4)
    _, held = repair_mesh(x, hexes, threshold=0.2, constraints=cons, fixed=bottom, release=False)
    assert held["elements_still_below_threshold"] == 1
    y, rep = repair_mesh(x, hexes, threshold=0.2, constraints=cons, fixed=bottom)
    assert min_scaled_jacobian(y, hexes).min() >= 0.2
    assert rep["nodes_released_from_surfaces"] == 4 and np.array_equal(y[bottom], x[bottom])


def test_penalty_gradient_with_untangling_matches_finite_differences():
    """The objective with regularised lengths and the untangling term: central differences
    (step 1e-5 mm on ~10 mm elements) agree with the analytic gradient to 1e-5 relative --
    the truncation error of the difference, O(step^2) times third derivatives, is far below."""
    nodes, hexes, *_ = shell_mesh(INNER, OUTER, n_theta=3, n_phi=2, n_layers=1)
    rng = np.random.default_rng(11)
    x = nodes + rng.normal(0, 6.0, nodes.shape)
    assert (min_scaled_jacobian(x, hexes) < 0).any()          # inverted corners present
    hx = hexes.astype(np.int64)
    local = np.arange(len(x), dtype=np.int64)
    args = (EDGE_OPERATOR, 0.3, 1e-10, 1000.0)
    f, g = _penalty_and_gradient(x, hx, local, len(x), *args)
    step = 1e-5
    fd = np.zeros_like(x)
    for i in range(len(x)):
        for d in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, d] += step
            xm[i, d] -= step
            fd[i, d] = (_penalty_and_gradient(xp, hx, local, len(x), *args)[0]
                        - _penalty_and_gradient(xm, hx, local, len(x), *args)[0]) / (2 * step)
    assert np.abs(fd - g).max() <= 1e-5 * np.abs(g).max()
