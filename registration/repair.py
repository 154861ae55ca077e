"""Mesh repair: untangle inverted hexahedra and raise every scaled Jacobian above a threshold.

The Repair step of Mesh-Match-and-Repair (Bucki, Lobos and Payan, Med. Image Anal. 14, 2010)
relocates nodes around the bad elements. Here it is an optimisation-based untangling and
quality improvement (Knupp, "Hexahedral and tetrahedral mesh untangling", Eng. Comput. 17,
2001; Escobar et al., "Simultaneous untangling and smoothing of tetrahedral meshes", CMAME 192,
2003) over a patch: the nodes of the elements whose minimum scaled Jacobian is below the
threshold, grown by `rings` layers of neighbours. The patch objective is
  E(a) = sum over patch elements e and their 17 corners q (`registration.quality`) of max(0, tau - sj_eq)^2
         + sum over inverted corners of (det_eq / h^3)^2
         + mu * sum_nodes |x - x0|^2 / h^2
         [+ w * sum over corners of max(0, threshold + delta - sj_eq)^2, once a round fails],
with tau = threshold + margin, so that invalid corners (sj <= 0) are penalised hardest
(validity first) and corners already better than tau cost nothing (quality next, with minimal
motion). Node positions x = x0 + B a: interior nodes move freely (B = I), nodes on a patient
surface (skin, bone) move in its tangent plane and are projected back onto the surface after
each optimisation, nodes on two surfaces stay fixed. The exact gradient comes from
chain rule of `registration.quality` (evaluated node by node with numba, checked against
`scaled_jacobian_gradient` in the tests); L-BFGS-B minimises. Rounds repeat with a
larger patch until no element is below the threshold or the round budget is spent; a round
that does not lower the total shortfall below the threshold is undone and switches on (then
strengthens) the bound's penalty w (`repair_mesh`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
from scipy.optimize import minimize
from threadpoolctl import threadpool_limits

from registration.quality import (EDGE_OPERATOR, corner_edges, gather_element,
                                  min_scaled_jacobian, quality_summary)
from registration.surface import TargetSurface


# the bound the penalty enforces lies this far above the threshold, so that the projection of
# surface nodes back onto their surface after a round (a small move off the tangent plane)
# does not take a corner just at the bound below the threshold
BOUND_MARGIN = 0.01
# weight of the bound's penalty, once on (`repair_mesh`), against the quality target's (both
# squared shortfalls of a scaled Jacobian): a corner 0.1 short of the bound then weighs as
# much as a hundred corners 0.1 short of the target
BOUND_WEIGHT = 100.0


@dataclass
class SurfaceConstraint:
    """Nodes that must stay on a surface."""

    name: str
    node_ids: np.ndarray
    surface: TargetSurface


def node_element_incidence(n_nodes: int, hexes: np.ndarray) -> sp.csr_matrix:
    m = len(hexes)
    return sp.csr_matrix((np.ones(8 * m), (np.asarray(hexes).ravel(), np.repeat(np.arange(m), 8))),
                         shape=(n_nodes, m))


def _tangent_bases(x: np.ndarray, free: np.ndarray, constraints: list[SurfaceConstraint],
                   fixed: np.ndarray) -> np.ndarray:
    """(k, 3, 3) bases: identity, tangent plane (third column zero) or zero (fixed)."""
    basis = np.repeat(np.eye(3)[None], len(free), axis=0)
    count = np.zeros(len(free), int)
    pos = {int(n): i for i, n in enumerate(free)}
    for con in constraints:
        sel = np.array([pos[n] for n in con.node_ids if n in pos], dtype=int)
        if len(sel) == 0:
            continue
        cl = con.surface.closest(x[free[sel]])
        n = cl.normal
        helper = np.where(np.abs(n[:, [0]]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
        t1 = np.cross(n, helper)
        t1 /= np.linalg.norm(t1, axis=1)[:, None]
        t2 = np.cross(n, t1)
        basis[sel] = np.stack([t1, t2, np.zeros_like(t1)], axis=2)
        count[sel] += 1
    fixed_mask = (count > 1) | np.isin(free, fixed)
    basis[fixed_mask] = 0.0
    return basis


@numba.njit(cache=True)
def _penalty_and_gradient(x, hexes, local, n_free, edge_op, tau, eps2=0.0, h3=0.0, bound=-2.0,
                          weight=0.0):
    """sum over elements and their 17 corners of max(0, tau - sj)^2 and its gradient with
    respect to the free nodes (local[node] >= 0), accumulated node by node. Edge lengths are
    regularised, l = sqrt(|e|^2 + eps2): with eps2 > 0 a collapsed edge (two nodes on one
    point, as a projection onto a patient surface can leave) gives a finite objective and
    gradient instead of a division by zero; eps2 = (1e-6 h)^2 changes sj by ~1e-12 elsewhere.
    With h3 > 0 (a typical element volume, h^3) every inverted corner also costs (det / h3)^2,
    Knupp's untangling term on the unscaled Jacobian: the scaled Jacobian is stationary at -1
    (an element turned inside out as a whole has a zero sj gradient), its determinant is not.
    With weight > 0 every corner below `bound` (< tau) also costs weight * (bound - sj)^2: the
    quadratic penalty of the constraint sj >= bound (Nocedal and Wright, ch. 17), which makes
    the corners short of the threshold outweigh the many corners only short of the quality
    target tau."""
    f = 0.0
    g = np.zeros((n_free, 3))
    e = np.empty((3, 3))
    xe = np.empty((8, 3))
    for m in range(hexes.shape[0]):
        gather_element(x, hexes, m, xe)
        for q in range(edge_op.shape[0]):
            corner_edges(edge_op, q, xe, e)
            c23 = np.array([e[1, 1] * e[2, 2] - e[1, 2] * e[2, 1], e[1, 2] * e[2, 0] - e[1, 0] * e[2, 2],
                            e[1, 0] * e[2, 1] - e[1, 1] * e[2, 0]])
            c31 = np.array([e[2, 1] * e[0, 2] - e[2, 2] * e[0, 1], e[2, 2] * e[0, 0] - e[2, 0] * e[0, 2],
                            e[2, 0] * e[0, 1] - e[2, 1] * e[0, 0]])
            c12 = np.array([e[0, 1] * e[1, 2] - e[0, 2] * e[1, 1], e[0, 2] * e[1, 0] - e[0, 0] * e[1, 2],
                            e[0, 0] * e[1, 1] - e[0, 1] * e[1, 0]])
            det = e[0, 0] * c23[0] + e[0, 1] * c23[1] + e[0, 2] * c23[2]
            l0 = np.sqrt(e[0, 0] ** 2 + e[0, 1] ** 2 + e[0, 2] ** 2 + eps2)
            l1 = np.sqrt(e[1, 0] ** 2 + e[1, 1] ** 2 + e[1, 2] ** 2 + eps2)
            l2 = np.sqrt(e[2, 0] ** 2 + e[2, 1] ** 2 + e[2, 2] ** 2 + eps2)
            prod = l0 * l1 * l2
            if not prod > 0.0:
                continue  # a fully collapsed corner (eps2 = 0) or NaN: no direction to push it
            sj = det / prod
            short = tau - sj
            if short <= 0.0:
                continue
            f += short * short
            coef = -2.0 * short
            below = bound - sj
            if weight > 0.0 and below > 0.0:
                f += weight * below * below
                coef -= 2.0 * weight * below
            untangle = 0.0
            if h3 > 0.0 and det < 0.0:
                f += (det / h3) ** 2
                untangle = 2.0 * det / (h3 * h3)
            for k in range(3):
                lk = l0 if k == 0 else (l1 if k == 1 else l2)
                for d in range(3):
                    cd = c23[d] if k == 0 else (c31[d] if k == 1 else c12[d])
                    dsj = cd / prod - sj * e[k, d] / (lk * lk) + untangle * cd / coef
                    for n in range(8):
                        w = edge_op[q, k, n]
                        if w != 0.0:
                            ln = local[hexes[m, n]]
                            if ln >= 0:
                                g[ln, d] += coef * dsj * w
    return f, g


def _optimise_patch(x, hexes, patch_elems, free, basis, tau, mu, h, maxiter=50, bound=-2.0, weight=0.0):
    hx = np.ascontiguousarray(hexes[patch_elems], dtype=np.int64)
    x0 = x[free].copy()
    local = np.full(len(x), -1, dtype=np.int64)
    local[free] = np.arange(len(free))
    xw = x.copy()

    def fun(a):
        a = a.reshape(-1, 3)
        xw[free] = x0 + np.einsum("kij,kj->ki", basis, a)
        f, g = _penalty_and_gradient(xw, hx, local, len(free), EDGE_OPERATOR, tau, (1e-6 * h) ** 2, h**3,
                                     bound, weight)
        dx = xw[free] - x0
        f += mu * float(np.sum(dx**2)) / h**2
        g += 2.0 * mu * dx / h**2
        return f, np.einsum("kij,ki->kj", basis, g).ravel()

    # L-BFGS-B's vector updates through a single BLAS thread: with OpenBLAS threads on a
    # loaded 2-core machine each iteration waited ~10 ms on thread hand-offs (0.2-1.4 ms with
    # one; the standard strong class II: 13 s of 30 in these minimisations)
    with threadpool_limits(limits=1, user_api="blas"):
        res = minimize(fun, np.zeros(3 * len(free)), jac=True, method="L-BFGS-B",
                       options={"maxiter": maxiter, "gtol": 1e-7, "ftol": 1e-10})
    fun(res.x)
    return xw


def quality_shortfall(q: np.ndarray, threshold: float) -> float:
    """sum over elements of max(0, threshold - q_e), q the elements' minimum scaled Jacobians:
    how far a mesh is from the quality gate, the measure `repair_mesh` lowers round by round
    and by which two repaired meshes are compared."""
    return float(np.sum(np.maximum(threshold - np.asarray(q, float), 0.0)))


def mesh_shortfall(x: np.ndarray, hexes: np.ndarray, threshold: float) -> float:
    """`quality_shortfall` of the mesh (x, hexes)."""
    return quality_shortfall(min_scaled_jacobian(x, hexes), threshold)


def repair_mesh(nodes: np.ndarray, hexes: np.ndarray, *, threshold: float = 0.2,
                constraints: list[SurfaceConstraint] = (), fixed: np.ndarray | None = None,
                margin: float = 0.1, rings: int = 1, max_rounds: int = 8, mu: float = 1e-4,
                stall_rounds: int = 3, release: bool = True, release_rounds: int = 6,
                bound_margin: float = BOUND_MARGIN, bound_weight: float = BOUND_WEIGHT,
                bound_first: bool = False):
    """Relocate nodes until every element's minimum scaled Jacobian is >= threshold.

    Returns (new nodes, report dict). Nodes in a constraint stay on its surface (to the
    closest-point precision); `fixed` nodes never move.

    Each round optimises a patch: the elements below the threshold grown by `rings` layers
    (one more every second round). The objective's quality target is threshold + margin. A
    round is kept only when it lowers the total shortfall sum_e max(0, threshold - sj_e) (the
    mesh never leaves a round worse than it entered); a round that does not is undone, and
    the next one widens the patch by a ring and adds the bound threshold + bound_margin as a
    quadratic penalty of weight `bound_weight` (ten times heavier after each further undone
    round): penalty continuation (Nocedal and Wright, ch. 17). The target alone untangles best
    (the bound's heavy weight on a few scaled Jacobians drowns the determinant's untangling
    term), but it balances the squared shortfalls of all corners short of the target and can
    leave a few corners below the threshold for many that are only short of the target; the
    bound then makes those few outweigh the rest, and the wider patch reaches room the narrow
    one did not. `stall_rounds` undone rounds in a row end the search (fixed nodes that make
    the threshold unreachable: a caller then retries with fewer of them fixed).
    Each round allows the minimiser more iterations than the last (a tangled patch can need
    hundreds). With `release`, when the constrained rounds end with elements still below the
    threshold, the surface nodes of those elements and their neighbours leave their surfaces
    (they move in 3D, held near their place by the motion term only) for up to
    `release_rounds` more rounds: a surface that leaves no room for a valid element between it
    and the next (soft tissue thinner than the mesh's layers, two patient surfaces closer than
    the generic ones) then costs a local fit error, reported as `nodes_released_from_surfaces`,
    instead of an invalid mesh."""
    hexes = np.asarray(hexes)
    x = np.array(nodes, dtype=float)
    fixed = np.zeros(0, int) if fixed is None else np.asarray(fixed, int)
    q = min_scaled_jacobian(x, hexes)
    before = quality_summary(x, hexes, threshold, q=q)
    bad0 = np.flatnonzero(q < threshold)
    inc = node_element_incidence(len(x), hexes)
    h = float(np.median(np.linalg.norm(x[hexes[:, 1]] - x[hexes[:, 0]], axis=1))) or 1.0
    moved = np.zeros(len(x), bool)
    constraints = constraints0 = list(constraints)
    released = np.zeros(0, np.int64)
    rounds, total, undone = 0, 0, 0

    def shortfall(qq):
        return quality_shortfall(qq, threshold)

    def run(n_rounds, first_round):
        nonlocal x, q, total, undone
        stalled = 0
        best = shortfall(q)
        done = 0
        for r in range(first_round, first_round + n_rounds):
            bad = np.flatnonzero(q < threshold)
            if len(bad) == 0:
                break
            done += 1
            total += 1
            patch_nodes = np.unique(hexes[bad])
            for _ in range(rings + (r - 1) // 2 + stalled):
                elems = np.unique(inc[patch_nodes].indices)
                patch_nodes = np.unique(hexes[elems])
            free = np.setdiff1d(patch_nodes, fixed)
            patch_elems = np.unique(inc[free].indices)
            basis = _tangent_bases(x, free, constraints, fixed)
            x_prev, q_prev = x[free].copy(), q[patch_elems].copy()
            # the bound's penalty: on after an undone round (ten times heavier after each
            # further one), or from the first round with `bound_first`
            if stalled:
                weight = bound_weight * 10.0 ** (stalled - 1)
            else:
                weight = bound_weight if bound_first else 0.0
            x = _optimise_patch(x, hexes, patch_elems, free, basis, threshold + margin, mu, h,
                                maxiter=50 * min(r, 8), bound=threshold + bound_margin, weight=weight)
            for con in constraints:
                on = np.intersect1d(con.node_ids, free)
                if len(on):
                    x[on] = con.surface.closest(x[on]).points
            # only the elements around the free nodes changed
            q[patch_elems] = min_scaled_jacobian(x, hexes[patch_elems])
            now = shortfall(q)
            if now < best * (1.0 - 1e-3):
                best, stalled = now, 0
                moved[free] = True
            else:
                x[free], q[patch_elems] = x_prev, q_prev
                undone += 1
                stalled += 1
                if stalled >= stall_rounds:
                    break
        return done

    rounds = run(max_rounds, 1)
    bad = np.flatnonzero(q < threshold)
    if release and len(bad) and constraints:
        ring = np.unique(hexes[np.unique(inc[np.unique(hexes[bad])].indices)])
        on_any = np.unique(np.concatenate([c.node_ids for c in constraints]))
        released = np.setdiff1d(np.intersect1d(ring, on_any), fixed)
        constraints = [SurfaceConstraint(c.name, np.setdiff1d(c.node_ids, released), c.surface)
                       for c in constraints]
        rounds += run(release_rounds, 2)
    after = quality_summary(x, hexes, threshold, q=q)
    report = {
        "threshold": float(threshold),
        "elements_needing_repair": int(len(bad0)),
        "elements_inverted_before": int(before["n_inverted"]),
        "elements_still_below_threshold": int(after["n_below_threshold"]),
        "rounds": int(rounds),
        "rounds_undone": int(undone),
        "bound_first": bool(bound_first),
        "nodes_moved": int(moved.sum()),
        "nodes_released_from_surfaces": int(len(released)),
        "quality_before": before,
        "quality_after": after,
    }
    if after["n_below_threshold"] and not bound_first and bound_weight > 0:
        # the other order: the bound penalised from the first round (where the target alone
        # untangled into a state the bound cannot leave); the result nearer the threshold is kept
        y, other = repair_mesh(nodes, hexes, threshold=threshold, constraints=constraints0,
                               fixed=fixed, margin=margin, rings=rings, max_rounds=max_rounds,
                               mu=mu, stall_rounds=stall_rounds, release=release,
                               release_rounds=release_rounds, bound_margin=bound_margin,
                               bound_weight=bound_weight, bound_first=True)
        if mesh_shortfall(y, hexes, threshold) < shortfall(q):
            other["rounds"] += report["rounds"]
            return y, other
    return x, report


def repair_holding(nodes: np.ndarray, hexes: np.ndarray, held, *, threshold: float = 0.2,
                   constraints=()) -> tuple[np.ndarray, dict]:
    """`repair_mesh` with the `held` nodes fixed (landmark nodes placed on given landmarks: the
    repair moves their neighbours instead); when that leaves an element below the threshold
    (the held nodes leave no room for a valid element), the repair is made once more with
    them free, and the result nearer the threshold (`mesh_shortfall`) is kept: freeing them
    widens the search but does not always end nearer. The report's `landmark_nodes_held`
    says whether the held nodes stayed where they were."""
    x0 = np.asarray(nodes, float)
    held = np.asarray(held, np.int64)
    x, rep = repair_mesh(x0, hexes, threshold=threshold, constraints=constraints, fixed=held)
    if len(held) and rep["elements_still_below_threshold"]:
        y, free_rep = repair_mesh(x0, hexes, threshold=threshold, constraints=constraints)
        if mesh_shortfall(y, hexes, threshold) < mesh_shortfall(x, hexes, threshold):
            x, rep = y, free_rep
    rep["landmark_nodes_held"] = bool(len(held)) and bool(np.array_equal(x[held], x0[held]))
    return x, rep

