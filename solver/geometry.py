"""Geometry kernels any package may use: the closest point of a point on a triangle.

`point_triangle` (numba, scalar arguments) is the Voronoi-region test of Ericson
(*Real-Time Collision Detection*, 2005, sec. 5.1.5): it returns the closest point, its
barycentric coordinates and its region (the face, an edge or a vertex), so that a caller may
sign a distance with pseudo-normals (contact) or tell boundary points (registration).
`closest_on_triangle` is its form on (3,) arrays, `closest_point_on_triangles` its row-by-row
form on (k, 3) arrays; `TriangleTree` answers exact closest points on a whole triangle mesh
(candidate triangles from a k-d tree of pieces of bounded size that cover them, widened
until the answer is provably the nearest); `triangulate` splits quads into triangles;
`deepest_concavity` finds, on a planar polyline, the point deepest behind the convex-hull edge
(bitangent) that spans a concavity.
"""
from __future__ import annotations

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

__all__ = ["FACE", "VERT_A", "VERT_B", "VERT_C", "EDGE_AB", "EDGE_BC", "EDGE_CA",
           "point_triangle", "closest_on_triangle", "closest_point_on_triangles", "triangulate",
           "deepest_concavity", "TriangleTree", "TIE_REL"]

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


# Two triangles whose closest points lie within this of each other (squared distances, relative
# to 1 + d^2 in mm^2) are a tie: a point whose closest point is on an edge or vertex they share
# is as close to both, up to the rounding of the projections (~1e-13 mm^2 at head size). A tie
# goes to the lower triangle index, so that the triangle (and its normal, which the registration
# tests against thresholds, for example) does not depend on the order of the candidates or on the last bits
# of the sums, which differ between BLAS kernels and processors.
TIE_REL = 1e-12


@nb.njit(cache=True)
def _closest_over_candidates(points, vertices, faces, candidates):
    n = points.shape[0]
    out = np.empty((n, 3))
    bary = np.empty((n, 3))
    best_face = np.empty(n, dtype=np.int64)
    dist = np.empty(n)
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        best = np.inf
        best_face[i] = faces.shape[0]
        for j in range(candidates.shape[1]):
            f = candidates[i, j]
            if f < 0:
                continue
            ia, ib, ic = faces[f, 0], faces[f, 1], faces[f, 2]
            _, _, _, u, v, w, _ = point_triangle(
                px, py, pz, vertices[ia, 0], vertices[ia, 1], vertices[ia, 2],
                vertices[ib, 0], vertices[ib, 1], vertices[ib, 2],
                vertices[ic, 0], vertices[ic, 1], vertices[ic, 2])
            qx = u * vertices[ia, 0] + v * vertices[ib, 0] + w * vertices[ic, 0]
            qy = u * vertices[ia, 1] + v * vertices[ib, 1] + w * vertices[ic, 1]
            qz = u * vertices[ia, 2] + v * vertices[ib, 2] + w * vertices[ic, 2]
            d = (qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2
            tie = TIE_REL * (1.0 + best)
            if d < best - tie or (d <= best + tie and f < best_face[i]):
                best = d
                out[i, 0], out[i, 1], out[i, 2] = qx, qy, qz
                bary[i, 0], bary[i, 1], bary[i, 2] = u, v, w
                best_face[i] = f
        dist[i] = np.sqrt(best)
    return out, bary, best_face, dist



class TriangleTree:
    """Exact closest points on a triangle mesh taken as it is (no merging, no orientation): the
    light structure for many queries on a large surface or a one-off measure against one.

    Every triangle is covered by pieces of radius (largest centroid-to-corner distance) at most
    r0: a triangle up to r0 is its own piece, a larger one is cut at the midpoint of its
    longest edge until its pieces are small enough (a sliver into a row of pieces, a broad
    facet into a patch). A k-d tree holds the pieces' centroids. Candidates of a point are the
    triangles of its k nearest pieces, projected exactly (`_closest_over_candidates`). The
    answer d is exact when the k-th piece lies beyond d + r0: any triangle nearer than d has
    its closest point in one of its pieces, whose centroid then lies within d + r0. Otherwise
    the candidates are doubled until that holds. With r0 from the typical triangle, a surface
    where large triangles lie beside small ones (a decimated CT skin: broad flat facets on the
    cheek, fine ones round the nose) costs about what a uniform one does, and a large triangle
    whose centroid is far from a point above its edge is still found.

    Zero-area triangles are left out (their edges belong to their neighbours); `face` indices
    refer to the triangles as given, and of triangles equally near (`TIE_REL`) the lowest
    index wins."""

    # r0 in median triangle radii: larger, fewer pieces but a looser bound (more doubling)
    PIECE_RADIUS = 1.25

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        f = np.ascontiguousarray(faces, dtype=np.int64)
        tri = self.vertices[f]
        area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        self.kept = np.flatnonzero(area2 > 1e-12 * max(float(area2.max(initial=0.0)), 1e-300))
        if not len(self.kept):
            raise ValueError("the mesh has no triangle of non-zero area")
        self.faces = np.ascontiguousarray(f[self.kept])
        corners = tri[self.kept]
        self.radius = self.PIECE_RADIUS * float(np.median(_triangle_radii(corners)))
        owner, centroids = _pieces(corners, self.radius)
        self._owner = owner
        self._tree = cKDTree(centroids)

    def closest(self, points: np.ndarray, k: int = 16, max_distance: float = np.inf):
        """(closest points, barycentric coordinates, face index, distance) for points (n, 3);
        exact for every point nearer than `max_distance` (the others get an upper bound that
        is itself beyond it)."""
        x = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        n = len(x)
        m = len(self._owner)
        kk = int(min(k, m))
        dc, piece = self._tree.query(x, k=kk)
        dc, piece = np.reshape(dc, (n, kk)), np.reshape(piece, (n, kk))
        q, bary, face, d = _closest_over_candidates(x, self.vertices, self.faces, self._owner[piece])
        need = np.flatnonzero(dc[:, -1] - self.radius < np.minimum(d, max_distance))
        # widen: twice the candidates, and twice again, for the points still unsure (vectorised
        # queries in chunks of bounded memory). A wider set holds the first candidates: the same
        # answer or a better one. It ends when every point is certain or every piece is seen.
        while len(need) and kk < m:
            kk = int(min(2 * kk, m))
            still = []
            for chunk in np.array_split(need, -(-len(need) * kk // 2_000_000)):
                dc, piece = self._tree.query(x[chunk], k=kk)
                dc, piece = np.reshape(dc, (len(chunk), kk)), np.reshape(piece, (len(chunk), kk))
                q[chunk], bary[chunk], face[chunk], d[chunk] = _closest_over_candidates(
                    x[chunk], self.vertices, self.faces, self._owner[piece])
                still.append(chunk[dc[:, -1] - self.radius < np.minimum(d[chunk], max_distance)])
            need = np.concatenate(still)
        return q, bary, self.kept[face], d


def _triangle_radii(corners: np.ndarray) -> np.ndarray:
    """Largest centroid-to-corner distance of each triangle (m, 3, 3)."""
    return np.linalg.norm(corners - corners.mean(axis=1)[:, None, :], axis=2).max(axis=1)


def _pieces(corners: np.ndarray, r0: float):
    """(owner, centroid) of pieces of radius <= r0 covering the triangles (m, 3, 3): each
    triangle over r0 is cut at the midpoint of its longest edge, and its halves likewise."""
    owner = np.arange(len(corners))
    done_owner, done_centroid = [], []
    tri = corners
    while len(tri):
        small = _triangle_radii(tri) <= r0
        done_owner.append(owner[small])
        done_centroid.append(tri[small].mean(axis=1))
        tri, owner = tri[~small], owner[~small]
        if not len(tri):
            break
        # longest edge (i, i+1), opposite corner i+2: two halves sharing its midpoint
        edge = np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=2)
        i = np.argmax(edge, axis=1)
        rows = np.arange(len(tri))
        a, b, c = tri[rows, i], tri[rows, (i + 1) % 3], tri[rows, (i + 2) % 3]
        mid = 0.5 * (a + b)
        tri = np.concatenate([np.stack([a, mid, c], axis=1), np.stack([mid, b, c], axis=1)])
        owner = np.concatenate([owner, owner])
    return np.concatenate(done_owner), np.concatenate(done_centroid)


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
