"""Lip separation: the registered lips kept apart across the mouth slit.

The generic mesh has an open mouth: the lower lip's contact surface (facet set
"lip_lower_contact", outward normal towards the upper lip) lies a small gap below the upper
lip's ("lip_upper_contact"). The smooth transform of the elastic stage, the snap of the skin
nodes, the landmark correction and the facet fit all move the two sides of this thin slit
independently of each other, and can push one lip through the other (an FE contact start
from an overlapping state). This stage restores the gap:

  signed gap  g(p) = (p - q) . n(q)  of every node p of one lip surface (nodes shared by the two
  surfaces, the closed ends of the slit, excluded) to the other lip surface, q the closest
  point on its triangulated facets, n(q) the facet-orientation vertex normals interpolated
  with the barycentric coordinates of q (positive outside the other lip); points whose
  closest point is on the open border of the other surface, or deeper than `band`, are beside
  it, not inside (the convention of the independent check `facemodel.simulation
  .lip_penetrations`).

A node with g < gap is moved by (gap + tol - g) / 2 along n(q) -- each side of an overlap moves
half the way, as in a symmetric node-to-surface contact correction (Wriggers, "Computational
Contact Mechanics", 2006, ch. 5: the gap function and its normal). Pushed skin nodes (the
front edge of the slit) are projected back onto the patient skin (where the scan shows the lips
crossing, a lip's edge hidden behind the other, the nodes whose pushes the skin keeps taking
back may leave it by up to `skin_release_mm` once the search has stalled); a target that comes within
the teeth clearance of an arch is moved to the nearest clear point along a ray that does not
go back towards the other lip (at the deep end of the slit, where the lips meet over the
incisal edges, the lip and teeth constraints would otherwise undo each other). The displacement of the
pushed nodes is carried into the tissue within `reach_mm` of the lips by harmonic extension
over the mesh graph (edge weights 1/|e|^2, `registration.elastic`) with the other skin nodes, the bone-attached nodes, nodes
within 0.5 mm of the teeth clearance and nodes pushed in earlier rounds held, then `registration.repair` restores every element above the
scaled-Jacobian threshold (skin nodes on the patient skin, pushed nodes fixed). Rounds repeat
until no lip node lies closer than the gap to the other lip (up to `max_rounds`: where the other
side is held -- a bone-attached or landmark node -- or the repair takes part of a push back, a
round closes only part of the deficit, and a node may need 15-20 rounds).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from registration.elastic import harmonic_extension, mesh_laplacian
from registration.quality import min_scaled_jacobian
from registration.repair import SurfaceConstraint, repair_mesh
from registration.surface import TargetSurface
from registration.teeth import escape_outward, union_distance


def quad_vertex_normals(x: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """(n, 3) unit normals at the nodes of `quads` (area-weighted, right-hand orientation of
    the quads; zero rows for nodes not in them)."""
    q = np.asarray(quads)
    p = x[q]
    # the quad normal from its diagonals: (x2 - x0) x (x3 - x1) = 2 * vector area
    nq = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
    vn = np.zeros((len(x), 3))
    np.add.at(vn, q.ravel(), np.repeat(nq, 4, axis=0))
    norm = np.linalg.norm(vn, axis=1)
    return np.where(norm[:, None] > 0, vn / np.maximum(norm, 1e-300)[:, None], 0.0)


def signed_gaps(x: np.ndarray, nodes: np.ndarray, quads: np.ndarray, band: float = 3.0):
    """Signed gap of `nodes` to the surface of `quads` (module docstring).

    Returns (gap (k,), normal at the closest point (k, 3), counted (k,) bool): `counted` is
    False for nodes beside the surface (closest point on its open border) or farther than
    `band` behind it."""
    q = np.asarray(quads)
    ids = np.unique(q)
    tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    surf = TargetSurface(x[ids], np.searchsorted(ids, tris), "lip")
    cl = surf.closest(x[nodes])
    # TargetSurface merges and re-indexes vertices: map its vertices back to the mesh nodes
    _, back = cKDTree(x[ids]).query(surf.vertices)
    vn = quad_vertex_normals(x, q)[ids[back]]
    n = np.einsum("kc,kcd->kd", cl.bary, vn[surf.faces[cl.face]])
    n /= np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
    g = np.einsum("kd,kd->k", x[nodes] - cl.points, n)
    counted = ~cl.on_boundary & (g > -band)
    return g, n, counted


def lip_overlap(x: np.ndarray, upper_quads: np.ndarray, lower_quads: np.ndarray,
                band: float = 3.0) -> dict:
    """Deepest crossing (mm, >= 0) of each lip into the other and the smallest signed gap
    (mm; negative: crossed) over both lips."""
    out, smallest = {}, np.inf
    shared = np.intersect1d(np.unique(upper_quads), np.unique(lower_quads))
    for key, slave, master in (("lower_in_upper_mm", lower_quads, upper_quads),
                               ("upper_in_lower_mm", upper_quads, lower_quads)):
        nodes = np.setdiff1d(np.unique(slave), shared)
        g, _, ok = signed_gaps(x, nodes, master, band)
        out[key] = float(max(0.0, -g[ok].min())) if ok.any() else 0.0
        if ok.any():
            smallest = min(smallest, float(g[ok].min()))
    out["min_gap_mm"] = None if not np.isfinite(smallest) else smallest
    return out


def separate_lips(x: np.ndarray, hexes: np.ndarray, upper_quads: np.ndarray,
                  lower_quads: np.ndarray, fixed: np.ndarray, *, skin_nodes: np.ndarray = (),
                  skin: TargetSurface | None = None, gap: float = 0.1, tol: float = 0.05,
                  threshold: float = 0.2, band: float = 3.0, max_rounds: int = 30,
                  arches: list | None = None, teeth_clearance: float = 0.25, reach_mm: float = 15.0,
                  stall_rounds: int = 4, skin_release_mm: float | None = None):
    """Move lip-surface nodes apart until each lip is at least `gap` mm from the other.

    fixed: nodes that never move (bone-attached); skin_nodes: the skin nodes (held where not
    pushed; pushed ones lying on the patient `skin` slide on it); arches: the teeth
    (`registration.teeth.Arch`), kept `teeth_clearance` away from the pushed nodes: a target
    that comes closer is moved to the nearest clear point along a ray that does not go back
    towards the other lip (`registration.teeth.escape_outward`). The search ends early after
    `stall_rounds` rounds in a row that do not reduce the largest push still needed.
    skin_release_mm: when the search ends (stalled, or out of rounds) with the lips still
    crossing, the pushed skin nodes whose push the patient skin took back (their target
    projected onto the skin kept less than half of the push) in `stall_rounds` rounds or more
    leave the skin, by at most this distance in all, and the search goes on for up to
    max_rounds / 3 more rounds: where the scan shows the lips touching or crossing (a lip
    overhanging the other, its edge hidden behind it) the slit's front edge cannot lie on the
    skin with the lips apart. None: skin nodes always stay on the skin.
    Returns (new nodes, report)."""
    hexes = np.asarray(hexes)
    x = np.array(x, dtype=float)
    n = len(x)
    upper_quads, lower_quads = np.asarray(upper_quads), np.asarray(lower_quads)
    shared = np.intersect1d(np.unique(upper_quads), np.unique(lower_quads))
    sides = [(np.setdiff1d(np.unique(lower_quads), shared), upper_quads),
             (np.setdiff1d(np.unique(upper_quads), shared), lower_quads)]
    fixed = np.unique(np.asarray(fixed, dtype=np.int64))
    skin_nodes = np.unique(np.asarray(skin_nodes, dtype=np.int64))
    on_skin = np.zeros(n, bool)
    if skin is not None and len(skin_nodes):  # the skin nodes lying on the patient skin
        on_skin[skin_nodes[skin.closest(x[skin_nodes]).distance < 1e-2]] = True
    before = lip_overlap(x, upper_quads, lower_quads, band)
    x_start = x.copy()
    held = np.zeros(n, bool)
    lap = None
    # the tissue that follows the lips: nodes within `reach_mm` of a lip-surface node (the rest
    # is held, so that each round solves a small system)
    lip_nodes = np.union1d(np.unique(upper_quads), np.unique(lower_quads))
    far = ~np.isfinite(cKDTree(x[lip_nodes]).query(x, distance_upper_bound=reach_mm)[0])
    centre = np.concatenate([a.vertices for a in arches]).mean(axis=0) if arches else None
    # nodes near the teeth clearance (where the clearance stage left them) are held unless
    # pushed, in the spread and in the repair: the lip pushes do not carry them back
    by_teeth = np.zeros(n, bool)
    if arches:
        by_teeth = union_distance(arches, x, teeth_clearance + 1.0)[0] < teeth_clearance + 0.5
    released = np.zeros(n, bool)           # skin nodes let off the skin (skin_release_mm)
    taken_back = np.zeros(n, np.int64)     # rounds in which the skin took a node's push back
    rounds, repaired, unrepairable = 0, 0, False
    best_short, stalled = np.inf, 0
    limit, rounds = max_rounds, 0
    while rounds < limit:
        rounds += 1
        push = np.zeros((n, 3))
        normal = np.zeros((n, 3))
        hit = np.zeros(n, bool)
        for nodes, master in sides:
            g, nrm, ok = signed_gaps(x, nodes, master, band)
            bad = ok & (g < gap)
            push[nodes[bad]] += 0.5 * (gap + tol - g[bad])[:, None] * nrm[bad]
            normal[nodes[bad]] += nrm[bad]
            hit[nodes[bad]] = True
        hit &= ~np.isin(np.arange(n), fixed)
        if not hit.any():
            rounds -= 1
            break
        # the deepest shortfall left: rounds that stop reducing it (a pushed skin node that the
        # patient skin takes back, a repair undoing a push) end the search
        short = float(np.max(np.linalg.norm(push[hit], axis=1)))
        if short < best_short - 1e-3:
            best_short, stalled = short, 0
        else:
            stalled += 1
        if stalled >= stall_rounds or rounds == limit:
            # the search ends with lips crossing: the skin nodes whose pushes the skin keeps
            # taking back leave it (once), and the search goes on
            free = hit & on_skin & (taken_back >= stall_rounds) \
                if skin_release_mm is not None and not released.any() else np.zeros(n, bool)
            if free.any():
                released |= free
                on_skin &= ~free
                best_short, stalled = np.inf, 0
                limit = rounds + max(max_rounds // 3, 1)
            elif stalled >= stall_rounds:
                break
        ids = np.flatnonzero(hit)
        target = x[ids] + push[ids]
        slide = on_skin[ids] | released[ids]
        if skin is not None and slide.any():
            cl = skin.closest(target[slide])
            # a released node keeps its target while within skin_release_mm of the skin
            off = released[ids[slide]] & (cl.distance <= (skin_release_mm or 0.0))
            d = push[ids[slide]]
            kept = np.einsum("kc,kc->k", cl.points - x[ids[slide]], d) / \
                np.maximum(np.einsum("kc,kc->k", d, d), 1e-300)
            taken_back[ids[slide][(kept < 0.5) & ~off]] += 1
            target[slide] = np.where(off[:, None], target[slide], cl.points)
            slide[np.flatnonzero(slide)[off]] = False
        if arches:
            sd = union_distance(arches, target, teeth_clearance + 1.0)[0]
            near = ~slide & (sd < teeth_clearance)
            if near.any():
                target[near] = escape_outward(arches, target[near], teeth_clearance + 0.01, centre,
                                              away=normal[ids[near]])
        held[ids] = True
        if lap is None:
            lap = mesh_laplacian(n, hexes, x)
        dirichlet = np.union1d(np.flatnonzero(held | far | by_teeth), np.union1d(fixed, skin_nodes))
        values = np.zeros((len(dirichlet), 3))
        values[np.searchsorted(dirichlet, ids)] = target - x[ids]
        x = x + harmonic_extension(n, hexes, dirichlet, values, lap)
        if min_scaled_jacobian(x, hexes).min() < threshold:
            cons = [SurfaceConstraint("skin", np.flatnonzero(on_skin), skin)] if on_skin.any() else []
            x_in = x
            x, rep = repair_mesh(x_in, hexes, threshold=threshold, constraints=cons,
                                 fixed=np.union1d(np.union1d(fixed, ids), np.flatnonzero(by_teeth)))
            if rep["elements_still_below_threshold"]:
                # the pushed nodes free too: one the repair takes back is pushed again next round
                x, rep = repair_mesh(x_in, hexes, threshold=threshold, constraints=cons, fixed=fixed)
            repaired += rep["elements_needing_repair"]
    if min_scaled_jacobian(x, hexes).min() < threshold:
        # the last round's repair fell short: a wider patch around the elements left, more
        # rounds; failing that, the separation is undone (a valid mesh, the lips as they came)
        cons = [SurfaceConstraint("skin", np.flatnonzero(on_skin), skin)] if on_skin.any() else []
        x, rep = repair_mesh(x, hexes, threshold=threshold, constraints=cons, fixed=fixed, rings=3, max_rounds=12)
        repaired += rep["elements_needing_repair"]
        if rep["elements_still_below_threshold"] and min_scaled_jacobian(x_start, hexes).min() >= threshold:
            x, unrepairable = x_start.copy(), True
    after = lip_overlap(x, upper_quads, lower_quads, band)
    moved = np.linalg.norm(x - x_start, axis=1)
    report = {
        "gap_mm": float(gap),
        "before": before,
        "after": after,
        "nodes_pushed": int(held.sum()),
        "skin_nodes_pushed": int((held & (on_skin | released)).sum()),
        "skin_nodes_released": int(released.sum()),
        "nodes_moved": int((moved > 1e-3).sum()),
        "max_move_mm": float(moved.max()) if n else 0.0,
        "rounds": int(rounds),
        "elements_repaired": int(repaired),
        "undone": unrepairable,
    }
    return x, report
