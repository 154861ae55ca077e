"""Repair is necessary and sufficient: a warp that inverts elements is undone, surfaces kept."""
import numpy as np
import pytest

from registration.quality import min_scaled_jacobian
from registration.repair import SurfaceConstraint, repair_mesh
from registration.surface import TargetSurface
from shell import ellipsoid_radius, radial_distance, shell_mesh, surface_grid, with_bump

INNER = ellipsoid_radius(70, 85, 95)
OUTER = with_bump(ellipsoid_radius(84, 100, 108), 10, 0.0, 0.0, 0.2)


@pytest.fixture(scope="module")
def warped():
    nodes, hexes, quads, skin_ids, bone_ids, idx = shell_mesh(INNER, OUTER, n_theta=16, n_phi=12, n_layers=3)
    skin = TargetSurface(*surface_grid(OUTER, n_theta=240, n_phi=180))
    bone = TargetSurface(*surface_grid(INNER, n_theta=240, n_phi=180))
    # a localised warp: a Gaussian push, tangential on the skin and through the thickness
    centre = nodes[idx[8, 6, 1]]
    g = np.exp(-np.sum((nodes - centre) ** 2, axis=1) / (2 * 12.0**2))[:, None]
    x = nodes + g * np.array([14.0, 0.0, 10.0])
    interior = np.setdiff1d(np.arange(len(nodes)), np.concatenate([skin_ids, bone_ids]))
    x[interior] += g[interior] * np.array([0.0, 16.0, 0.0])  # middle layers pushed through the skin
    x[skin_ids] = skin.closest(x[skin_ids]).points  # surface nodes stay on their surfaces
    x[bone_ids] = bone.closest(x[bone_ids]).points
    return x, hexes, skin, bone, skin_ids, bone_ids


def test_warp_inverts_elements(warped):
    x, hexes, *_ = warped
    q = min_scaled_jacobian(x, hexes)
    assert (q <= 0).sum() >= 3  # the repair below has real work to do


def test_repair_fixes_every_element_and_keeps_surfaces(warped):
    x, hexes, skin, bone, skin_ids, bone_ids = warped
    bad_before = min_scaled_jacobian(x, hexes) < 0.2
    cons = [SurfaceConstraint("skin", skin_ids, skin), SurfaceConstraint("bone", bone_ids, bone)]
    y, rep = repair_mesh(x, hexes, threshold=0.2, constraints=cons)
    q = min_scaled_jacobian(y, hexes)
    assert q.min() >= 0.2 and rep["quality_after"]["n_inverted"] == 0
    assert rep["elements_needing_repair"] == int(bad_before.sum()) > 0
    assert rep["quality_before"]["n_inverted"] > 0
    # skin and bone nodes are on the patient surfaces: exactly on the triangulation (projection,
    # round-off), and on the analytic surface within the chord error of a 240 x 180 grid
    assert skin.closest(y[skin_ids]).distance.max() < 1e-9
    assert bone.closest(y[bone_ids]).distance.max() < 1e-9
    assert radial_distance(y[skin_ids], OUTER).max() < 0.05
    assert radial_distance(y[bone_ids], INNER).max() < 0.05
    # only nodes near the damage move
    moved = np.linalg.norm(y - x, axis=1) > 1e-12
    assert moved.sum() < 0.5 * len(x)


def test_valid_mesh_is_left_untouched(warped):
    x, hexes, skin, bone, skin_ids, bone_ids = warped
    nodes, hexes0, *_ = shell_mesh(INNER, OUTER, n_theta=16, n_phi=12, n_layers=3)
    y, rep = repair_mesh(nodes, hexes0, threshold=0.2)
    assert rep["elements_needing_repair"] == 0 and np.array_equal(y, nodes)


def test_penalty_gradient_matches_vectorised_chain_rule():
    from registration.quality import EDGE_OPERATOR, scaled_jacobian_gradient
    from registration.repair import _penalty_and_gradient

    nodes, hexes, *_ = shell_mesh(INNER, OUTER, n_theta=4, n_phi=3, n_layers=2)
    rng = np.random.default_rng(5)
    x = nodes + rng.normal(0, 3.0, nodes.shape)  # some corners below tau, some inverted
    tau = 0.5
    local = np.arange(len(x), dtype=np.int64)
    f, g = _penalty_and_gradient(x, hexes.astype(np.int64), local, len(x), EDGE_OPERATOR, tau)
    sj, grad = scaled_jacobian_gradient(x, hexes)
    short = np.maximum(tau - sj, 0.0)
    want = np.zeros_like(x)
    np.add.at(want, hexes, (-2.0 * short[:, :, None, None] * grad).sum(axis=1))
    # the same closed-form derivative evaluated two ways: equal to round-off
    assert abs(f - np.sum(short**2)) < 1e-10 * max(f, 1.0)
    assert np.allclose(g, want, rtol=1e-9, atol=1e-12)


def test_held_nodes_that_block_the_repair_are_freed_on_a_second_attempt(warped):
    from registration.repair import mesh_shortfall, repair_holding

    x, hexes, skin, bone, skin_ids, bone_ids = warped
    cons = [SurfaceConstraint("skin", skin_ids, skin), SurfaceConstraint("bone", bone_ids, bone)]
    q = min_scaled_jacobian(x, hexes)
    # every node of the worst element held: no move of the others can lift that element
    held = np.unique(hexes[np.argmin(q)])
    y, rep = repair_holding(x, hexes, held, threshold=0.2, constraints=cons)
    assert min_scaled_jacobian(y, hexes).min() >= 0.2
    assert rep["landmark_nodes_held"] is False
    assert mesh_shortfall(y, hexes, 0.2) == 0.0


def test_held_nodes_away_from_the_damage_stay_put(warped):
    from registration.repair import repair_holding

    x, hexes, skin, bone, skin_ids, bone_ids = warped
    cons = [SurfaceConstraint("skin", skin_ids, skin), SurfaceConstraint("bone", bone_ids, bone)]
    q = min_scaled_jacobian(x, hexes)
    near = np.unique(hexes[q < 0.5])
    held = np.setdiff1d(skin_ids, near)[:10]
    y, rep = repair_holding(x, hexes, held, threshold=0.2, constraints=cons)
    assert min_scaled_jacobian(y, hexes).min() >= 0.2
    assert rep["landmark_nodes_held"] is True and np.array_equal(y[held], x[held])


def test_the_attempt_nearer_the_threshold_is_kept(warped, monkeypatch):
    import registration.repair as rp

    x, hexes, skin, bone, skin_ids, bone_ids = warped
    cons = [SurfaceConstraint("skin", skin_ids, skin), SurfaceConstraint("bone", bone_ids, bone)]
    q = min_scaled_jacobian(x, hexes)
    held = np.unique(hexes[np.argmin(q)])   # that element cannot be lifted while held
    real = rp.repair_mesh
    calls = []

    def free_attempt_does_nothing(nodes, hexes_, *, fixed=None, **kw):
        calls.append(fixed is not None)
        if fixed is None:   # the second attempt, made worse than the first: the mesh as given
            return np.array(nodes, float), {"elements_still_below_threshold": int((q < 0.2).sum())}
        return real(nodes, hexes_, fixed=fixed, **kw)

    monkeypatch.setattr(rp, "repair_mesh", free_attempt_does_nothing)
    y, rep = rp.repair_holding(x, hexes, held, threshold=0.2, constraints=cons)
    # (the held attempt's own second order of penalties calls repair_mesh again, held)
    assert calls[0] and calls.count(False) == 1
    # the held attempt lifted every element it could: it is kept, the held nodes unmoved
    assert rp.mesh_shortfall(y, hexes, 0.2) < rp.mesh_shortfall(x, hexes, 0.2)
    assert rep["landmark_nodes_held"] is True and np.array_equal(y[held], x[held])
    assert rp.quality_shortfall(min_scaled_jacobian(y, hexes), 0.2) == rp.mesh_shortfall(y, hexes, 0.2)
