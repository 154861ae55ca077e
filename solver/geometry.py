"""Geometry kernels any package may use: the closest point of a point on a triangle.

`point_triangle` (numba, scalar arguments) is the Voronoi-region test of Ericson
(*Real-Time Collision Detection*, 2005, sec. 5.1.5): it returns the closest point, its
barycentric coordinates and its region (the face, an edge or a vertex), so that a caller may
sign a distance with pseudo-normals (contact) or tell boundary points (registration).
`closest_on_triangle` is its form on (3,) arrays, `closest_point_on_triangles` its row-by-row
form on (k, 3) arrays; `triangulate` splits quads into triangles. `deepest_concavity` finds,
on a planar polyline, the point deepest behind the convex-hull edge (bitangent) that spans a
concavity.
"""
from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["FACE", "VERT_A", "VERT_B", "VERT_C", "EDGE_AB", "EDGE_BC", "EDGE_CA",
           "point_triangle", "closest_on_triangle", "closest_point_on_triangles", "triangulate",
           "deepest_concavity"]

FACE, VERT_A, VERT_B, VERT_C, EDGE_AB, EDGE_BC, EDGE_CA = range(7)


@nb.njit(cache=True)
def point_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point q of triangle abc to p: (qx, qy, qz, u, v, w, region) with q = u a + v b
    + w c up to round-off and region one of FACE, VERT_A/B/C, EDGE_AB/BC/CA. A degenerate
    triangle gives its vertex a."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, 1.0, 0.0, 0.0, VERT_A
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, 0.0, 1.0, 0.0, VERT_B
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        return ax + t * abx, ay + t * aby, az + t * abz, 1.0 - t, t, 0.0, EDGE_AB
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, 0.0, 0.0, 1.0, VERT_C
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        return ax + t * acx, ay + t * acy, az + t * acz, 1.0 - t, 0.0, t, EDGE_CA
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return (bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz), 0.0, 1.0 - t, t,
                EDGE_BC)
    denom = va + vb + vc
    if denom == 0.0:
        return ax, ay, az, 1.0, 0.0, 0.0, FACE
    v = vb / denom
    w = vc / denom
    inv = 1.0 / denom
    bv, bw = vb * inv, vc * inv
    return (ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w,
            1.0 - bv - bw, bv, bw, FACE)


@nb.njit(cache=True)
def closest_on_triangle(p, a, b, c):
    """Closest point (qx, qy, qz) on triangle (a, b, c) to point p and its region; p, a, b, c
    are (3,) arrays."""
    qx, qy, qz, _, _, _, region = point_triangle(p[0], p[1], p[2], a[0], a[1], a[2],
                                                 b[0], b[1], b[2], c[0], c[1], c[2])
    return qx, qy, qz, region


@nb.njit(cache=True)
def _closest_rows(p, a, b, c, q, region):
    for i in range(p.shape[0]):
        q[i, 0], q[i, 1], q[i, 2], region[i] = closest_on_triangle(p[i], a[i], b[i], c[i])


def closest_point_on_triangles(p, a, b, c):
    """Closest points on triangles (a, b, c) to points p, all (k, 3), paired row by row.

    Returns (q (k, 3), region (k,) int: FACE, VERT_A/B/C, EDGE_AB/BC/CA).
    """
    p, a, b, c = (np.ascontiguousarray(v, dtype=float).reshape(-1, 3) for v in (p, a, b, c))
    q = np.empty_like(p)
    region = np.empty(len(p), dtype=np.int64)
    _closest_rows(p, a, b, c, q, region)
    return q, region


def triangulate(facets: np.ndarray) -> np.ndarray:
    """Triangles (k, 3) from triangles or quads (split along the 0-2 diagonal), same winding."""
    facets = np.asarray(facets, dtype=np.int64)
    if facets.ndim != 2 or facets.shape[1] not in (3, 4):
        raise ValueError(f"facets must be (k, 3) triangles or (k, 4) quads, got {facets.shape}")
    if facets.shape[1] == 3:
        return facets
    return np.concatenate([facets[:, [0, 1, 2]], facets[:, [0, 2, 3]]])


def deepest_concavity(p, lo: int, hi: int):
    """On the planar polyline p[lo..hi] ((k, 2), ordered by decreasing second coordinate):
    walk its convex hull on the side of the largest first coordinate (each hull vertex the
    next point whose chord leans farthest that way) and return (k, i, j, inward): k the point
    deepest behind a hull edge (i, j), i.e. the deepest concavity, and that edge's unit normal
    pointing into the concavity. Without a concavity: (lo, lo, hi, (-1, 0))."""
    p = np.asarray(p, dtype=float)
    best, best_k, span = -1.0, lo, (lo, hi, np.array([-1.0, 0.0]))
    i = lo
    while i < hi:
        d = p[i + 1:hi + 1] - p[i]
        j = i + 1 + int(np.argmax(np.arctan2(d[:, 0], -d[:, 1])))   # next hull vertex
        if j > i + 1:
            chord = p[j] - p[i]
            inward = np.array([-chord[1], chord[0]]) / np.linalg.norm(chord)
            if inward[0] > 0:
                inward = -inward
            depth = (p[i + 1:j] - p[i]) @ inward
            k = int(np.argmax(depth))
            if depth[k] > best:
                best, best_k, span = float(depth[k]), i + 1 + k, (i, j, inward)
        i = j
    return (best_k,) + span
