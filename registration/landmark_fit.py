"""Landmark correction: the model's landmark nodes brought onto the patient's given landmarks.

The elastic stage (`registration.elastic`) is a smooth transform of the whole volume, so it
cannot tear the mesh along the mouth slit: where the patient's lips are offset from each other
in the other sense than the generic lips (a strong class III: the lower lip 8-9 mm in front
of the upper, the generic upper lip 2.5 mm in front of the lower), the upper and lower lip
ends move together and the snap projects both onto the skin between the lips, several mm from
the stomia (on the strong class III head of bench/registration.py, Stms 4 mm forward onto
the triangles that join the upper lip to the lower, the 3 mm triangulation of the 8.5 mm
step between the lips). The mesh graph itself is torn along the slit (the lips' nodes are
doubled through the thickness), so a correction carried along the graph can separate them.

Given landmarks (a case's `preop/landmarks.json`) are first moved onto the patient skin
(closest point). The correction c_k = target_k - x_k of each landmark node is spread over
the skin by Gaussian radial basis functions of the *geodesic* distance along the skin mesh
(Dijkstra over the skin quads' edges, which do not cross the slit):
    u(i) = sum_k w_k exp(-(d_g(i, k) / sigma)^2),  with u(k) = c_k at every landmark node,
the moved skin nodes are projected back onto the patient skin and the skin change is carried
into the volume by harmonic extension over the hexahedral mesh graph (bone-attached nodes
held; edge weights 1/|e|^2, so that the thin layers under the skin move with it). Landmarks
farther than `max_distance_mm` from the patient skin are not skin landmarks, and landmarks
the registered skin misses by more than `max_correction_mm` contradict the surfaces: both are
left out (and reported). The repair stage then restores element quality.

`contradicting_landmarks` (on the model as the similarity placed it): two landmarks given on
nearly one point whose nodes the model holds well apart (given closer than CLASH_RATIO of the
nodes' distance, and by more than CLASH_MM) contradict each other for the model -- a labrale
inferius taken at the stomion of a lower lip without a prominence. Pulling both nodes there
compresses the tissue between them; most registrations still repair it, but where one fails,
it is made again with the one farther from its node set aside
(`registration.mesh_match.match_and_repair_arrays`).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from registration.elastic import harmonic_extension, mesh_laplacian
from registration.surface import TargetSurface

# a pair of given landmarks contradicts the model when their points are closer than this
# fraction of their nodes' distance on the registered skin: the face's own proportions vary
# by about a factor of two around the generic face's (a lower lip's vermilion 5-13 mm high
# against 8 mm), a fourfold compression is two landmarks put on one point
CLASH_RATIO = 0.25
# ... and closer by more than this (mm): twice the 1.5 mm with which a soft-tissue landmark
# is placed by hand, so that a pair the model holds a few mm apart (the two stomia, across
# the mouth slit) may close freely
CLASH_MM = 3.0


def skin_edge_graph(x: np.ndarray, skin_quads: np.ndarray, skin_ids: np.ndarray) -> sp.csr_matrix:
    """Symmetric graph (local skin indices) of the skin quads' edges weighted by their length."""
    loc = np.searchsorted(skin_ids, np.asarray(skin_quads))
    e = np.concatenate([loc[:, [0, 1]], loc[:, [1, 2]], loc[:, [2, 3]], loc[:, [3, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    w = np.linalg.norm(x[skin_ids[e[:, 0]]] - x[skin_ids[e[:, 1]]], axis=1)
    n = len(skin_ids)
    g = sp.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(n, n))
    return (g + g.T).tocsr()


def landmark_correction(x: np.ndarray, hexes: np.ndarray, skin_quads: np.ndarray,
                        landmark_nodes: np.ndarray, landmarks: np.ndarray, skin: TargetSurface,
                        movable_skin: np.ndarray, held: np.ndarray, *, sigma_mm: float = 8.0,
                        max_distance_mm: float = 5.0, max_correction_mm: float | np.ndarray = 6.0):
    """Move the landmark nodes onto the given landmarks (projected on the skin) with a smooth
    geodesic correction of the skin around them; returns (new nodes, report).

    movable_skin: skin node ids on the patient skin (projected back onto it after the
    correction); held: node ids that keep their position (bone-attached nodes). A landmark
    node is placed on its landmark whether it was on the patient skin before or not.
    max_correction_mm: one limit, or one per landmark."""
    skin_quads = np.asarray(skin_quads)
    skin_ids = np.unique(skin_quads)
    landmark_nodes = np.asarray(landmark_nodes, dtype=np.int64)
    cl = skin.closest(np.asarray(landmarks, dtype=float).reshape(-1, 3))
    use = (~cl.on_boundary) & (cl.distance <= max_distance_mm)
    report = {"landmarks_used": int(use.sum()), "sigma_mm": float(sigma_mm), "nodes": []}
    # a landmark the registered surface misses by more than max_correction_mm contradicts the
    # surfaces (a mislabelled or misplaced point): reported, not followed
    far = np.linalg.norm(cl.points - x[landmark_nodes], axis=1) > np.asarray(max_correction_mm, float)
    report["landmarks_not_followed"] = [int(i) for i in np.flatnonzero(use & far)]
    use &= ~far
    report["landmarks_used"] = int(use.sum())
    if not use.any():
        report["max_correction_mm"] = 0.0
        return np.array(x, dtype=float), report
    nodes, targets = landmark_nodes[use], cl.points[use]
    nodes, first = np.unique(nodes, return_index=True)
    targets = targets[first]
    corr = targets - x[nodes]
    report["max_correction_mm"] = float(np.linalg.norm(corr, axis=1).max())
    report["nodes"] = [int(i) for i in nodes]  # the landmark nodes now on their landmarks

    graph = skin_edge_graph(x, skin_quads, skin_ids)
    src = np.searchsorted(skin_ids, nodes)
    dist = csgraph.dijkstra(graph, indices=src, limit=4.0 * sigma_mm)  # (k, n_skin), inf beyond
    phi = np.exp(-(np.minimum(dist, 1e6) / sigma_mm) ** 2)
    a = phi[:, src]  # (k, k), symmetric, unit diagonal; Gaussian kernels are positive definite
    w = np.linalg.solve(a + 1e-9 * np.eye(len(src)), corr)
    u_skin = phi.T @ w  # (n_skin, 3)

    # skin nodes on the patient skin move with the correction and back onto it; the others
    # (not snapped: off the scan, or facing away) move with the smooth correction alone
    movable = np.isin(skin_ids, movable_skin)
    moving = np.linalg.norm(u_skin, axis=1) > 1e-6
    new_skin = x[skin_ids] + np.where(moving[:, None], u_skin, 0.0)
    proj = moving & movable
    new_skin[proj] = skin.closest(new_skin[proj]).points
    new_skin[np.searchsorted(skin_ids, nodes)] = targets  # exactly on the projected landmarks
    delta_skin = new_skin - x[skin_ids]

    held = np.setdiff1d(np.asarray(held, dtype=np.int64), skin_ids)
    fixed = np.concatenate([skin_ids, held])
    vals = np.concatenate([delta_skin, np.zeros((len(held), 3))])
    # edge weights 1/|e|^2: the thin dermis and the layers under a moved skin node follow it
    # (unit weights would leave them behind and invert the dermis under a large correction)
    u = harmonic_extension(len(x), hexes, fixed, vals, mesh_laplacian(len(x), hexes, x))
    report["skin_nodes_moved"] = int(moving.sum())
    return x + u, report


def contradicting_landmarks(node_points: np.ndarray, given: np.ndarray) -> tuple[np.ndarray, list]:
    """Which given landmarks to use: the pairs given on nearly one point whose model nodes lie
    well apart (module docstring) lose the one farther from its node.

    node_points (k, 3): the landmark nodes of the model as placed; given (k, 3): the given
    landmarks in the same frame. Returns (use (k,) bool, clashes: one dict per pair set aside,
    indices into the k landmarks)."""
    node_points = np.asarray(node_points, float).reshape(-1, 3)
    given = np.asarray(given, float).reshape(-1, 3)
    k = len(given)
    use = np.ones(k, bool)
    off = np.linalg.norm(given - node_points, axis=1)
    pairs = sorted((float(np.linalg.norm(given[a] - given[b])), a, b)
                   for a in range(k) for b in range(a + 1, k))
    clashes = []
    for apart, a, b in pairs:           # the closest pair first
        model_apart = float(np.linalg.norm(node_points[a] - node_points[b]))
        if use[a] and use[b] and apart < CLASH_RATIO * model_apart and model_apart - apart > CLASH_MM:
            drop = a if off[a] >= off[b] else b
            use[drop] = False
            clashes.append({"pair": [a, b], "given_apart_mm": round(apart, 3),
                            "model_apart_mm": round(model_apart, 3), "not_used": drop})
    return use, clashes
