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

