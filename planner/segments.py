"""Assignment of the face model's bone-attachment nodes to the patient's bone segments.

The generic model marks the soft-tissue nodes tied to bone (`attach_*` node sets). After
registration these nodes lie on the patient's bone, and which segment they follow during surgery
is decided by the patient's anatomy and the plan, not by the generic labels: each attachment node
goes to the bone surface closest to it (exact point-to-triangle distance, `nearest_surface`: a
k-d tree of triangle centroids and compiled projections, so that a CT-derived bone of 10^5-10^6
triangles costs little more than a synthetic one), and a
segment defined by cut planes (plan `cut_planes`, `from`) takes over the nodes of its source
surface that lie on the kept side of all its planes (Payan et al.: nodes attached to the
osteotomised segment follow its rigid movement, the others stay fixed with the skull).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import trimesh

from planner.errors import InputError
from planner.plan import FIXED_SEGMENT, Plan

ATTACH_PREFIX = "attach_"


def as_trimesh(surface) -> trimesh.Trimesh:
    """A bone surface given as trimesh.Trimesh, (vertices, faces) or an object with both."""
    if isinstance(surface, trimesh.Trimesh):
        return surface
    if isinstance(surface, (tuple, list)) and len(surface) >= 2:
        return trimesh.Trimesh(np.asarray(surface[0], float), np.asarray(surface[1], int), process=False)
    if hasattr(surface, "vertices") and hasattr(surface, "faces"):
        return trimesh.Trimesh(np.asarray(surface.vertices, float), np.asarray(surface.faces, int),
                               process=False)
    raise TypeError(f"not a surface: {type(surface).__name__}")


def nearest_surface(surfaces: list, points: np.ndarray, k: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """For each point (n, 3): the index of the closest of `surfaces` (any form `as_trimesh`
    takes) and the exact distance to it.

    Per surface, the triangles of the k nearest centroids (a k-d tree) are projected exactly
    (Ericson's point-triangle routine, compiled: `registration.surface`). That distance d is
    exact unless an unseen triangle could be closer: a triangle whose centroid lies c from
    the point is at least c - r away (r: the largest centroid-to-corner distance of the
    surface), so d is exact when the k-th centroid lies beyond d + r. Otherwise, and only
    where that surface could be the nearest one (its lower bound, the nearest centroid's
    distance minus r, not above the best distance found over all surfaces), every triangle
    whose centroid lies within d + r is projected. Ties between surfaces go to the first."""
    from scipy.spatial import cKDTree

    from solver.geometry import _closest_over_candidates

    x = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    n = len(x)
    found = []
    for surface in surfaces:
        mesh = as_trimesh(surface)
        v = np.ascontiguousarray(mesh.vertices, dtype=float)
        f = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        tri = v[f]
        # zero-area triangles project nowhere (their edges belong to their neighbours)
        area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        keep = area2 > 1e-12 * max(float(area2.max()), 1e-300)
        f, tri = f[keep], tri[keep]
        centroids = tri.mean(axis=1)
        tree = cKDTree(centroids)
        r = float(np.linalg.norm(tri - centroids[:, None, :], axis=2).max())
        kk = int(min(k, len(f)))
        dc, cand = tree.query(x, k=kk)
        dc, cand = dc.reshape(n, kk), np.asarray(cand, np.int64).reshape(n, kk)
        d = _closest_over_candidates(x, v, f, cand)[3]
        sure = (dc[:, -1] - r >= d) | (kk == len(f))
        found.append((v, f, tree, r, np.maximum(dc[:, 0] - r, 0.0), d, sure))
    best = np.min([item[5] for item in found], axis=0)
    dist = np.empty((len(found), n))
    for i, (v, f, tree, r, lower, d, sure) in enumerate(found):
        need = np.flatnonzero(~sure & (lower <= best))
        if len(need):
            balls = tree.query_ball_point(x[need], d[need] + r)
            width = max(len(b) for b in balls)
            cand = np.full((len(need), max(width, 1)), -1, np.int64)   # -1: no candidate
            for row, b in enumerate(balls):
                cand[row, :len(b)] = b
            d[need] = np.minimum(d[need], _closest_over_candidates(x[need], v, f, cand)[3])
        dist[i] = d
    nearest = np.argmin(dist, axis=0)
    return nearest, dist[nearest, np.arange(n)]


@dataclass(frozen=True)
class SegmentAssignment:
    node_sets: dict[str, np.ndarray]       # "attach_<segment>" -> node ids
    distance_mm: np.ndarray                # per attachment node: distance to its bone surface
    nodes: np.ndarray                      # the attachment node ids (union of the generic sets)
    segment_of_node: np.ndarray            # per attachment node: segment name

    def summary(self) -> dict:
        out = {}
        for seg in sorted(set(self.segment_of_node)):
            sel = self.segment_of_node == seg
            d = self.distance_mm[sel]
            out[seg] = {"nodes": int(sel.sum()), "median_distance_mm": round(float(np.median(d)), 3),
                        "max_distance_mm": round(float(d.max()), 3)}
        return out


def _cut_order(plan: Plan) -> list[str]:
    """Segments with cut planes, each after the segment it is cut from."""
    cut = {n: sp.source or n for n, sp in plan.segments.items() if sp.cut_planes}
    order: list[str] = []
    visiting: set[str] = set()

    def visit(n):
        if n in order:
            return
        if n in visiting:
            raise InputError(f"cut planes form a cycle through segment {n!r}", file=plan.path,
                             field=f"segments.{n}.from")
        visiting.add(n)
        if cut[n] in cut and cut[n] != n:
            visit(cut[n])
        visiting.discard(n)
        order.append(n)

    for n in cut:
        visit(n)
    return order


def assign_segments(model, bones: dict, plan: Plan, segments: tuple[str, ...] | None = None
                    ) -> SegmentAssignment:
    """Assign every attachment node of `model` to a bone segment of the patient.

    `bones` maps surface names (preop/bone/<name>) to surfaces; `segments` defaults to
    `model.segments`. A generic attachment set of a segment without any patient surface keeps
    the label of the nearest surface found.
    """
    segments = tuple(segments or model.segments)
    generic = {k[len(ATTACH_PREFIX):]: np.asarray(v, int) for k, v in model.node_sets.items()
               if k.startswith(ATTACH_PREFIX)}
    nodes = np.unique(np.concatenate([v for v in generic.values()] or [np.zeros(0, int)]))
    if nodes.size == 0:
        raise InputError("the face model has no bone-attachment nodes (attach_* node sets)")
    if not bones:
        raise InputError("the case has no bone surfaces (preop/bone/<segment>.stl)")
    x = np.asarray(model.nodes, float)[nodes]

    names = sorted(bones)
    nearest, distance = nearest_surface([bones[n] for n in names], x)
    label = np.array(names, dtype=object)[nearest]

    for seg in _cut_order(plan):
        sp = plan.segments[seg]
        source = sp.source or seg
        keep = label == source
        for cp in sp.cut_planes:
            keep &= cp.keeps(x)
        label[keep] = seg

    # Surfaces that are not segments (e.g. a whole-skull CT surface only used as a cut source)
    # give their remaining nodes to the generic segment of the node, else to the fixed skull.
    generic_of = {}
    for seg, ids in generic.items():
        for i in ids:
            generic_of.setdefault(int(i), seg)
    for k in np.flatnonzero(~np.isin(label, segments)):
        g = generic_of.get(int(nodes[k]), FIXED_SEGMENT)
        label[k] = g if g in segments else FIXED_SEGMENT

    for seg in plan.motions():
        if not np.any(label == seg):
            raise InputError(f"no soft-tissue attachment node lies on the bone of segment {seg!r}: "
                             "check its bone surface and cut planes", file=plan.path,
                             field=f"segments.{seg}")
    node_sets = {ATTACH_PREFIX + seg: np.sort(nodes[label == seg]) for seg in segments}
    return SegmentAssignment(node_sets, distance, nodes, label.astype(str))


def with_segments(model, assignment: SegmentAssignment):
    """A copy of the (frozen) face model with the attachment sets replaced."""
    node_sets = dict(model.node_sets)
    node_sets.update(assignment.node_sets)
    return dataclasses.replace(model, node_sets=node_sets)
