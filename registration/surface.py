"""Triangulated target surfaces: cleaning, orientation and exact closest-point queries.

A `TargetSurface` wraps a patient surface (skin or a bone segment) as vertex / triangle arrays.
Closest points are exact point-triangle projections (Ericson, "Real-Time Collision Detection",
2005, sec. 5.1.5) evaluated with numba over candidate triangles found with a k-d tree of
triangle centroids (widened where the triangles are large compared with the distance). Each answer
also says whether the closest point lies on the open boundary of the surface (a hole or the edge
of a partial scan); registration rejects such correspondences, which is what makes it robust to
partial and holed surfaces. Normals are oriented outward (away from the bulk of the head)
whatever the winding of the input, so flipped-normal files behave like correct ones.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from solver.geometry import TIE_REL, _closest_over_candidates




def _mix64(x: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser: a bijection of uint64 that spreads every input bit over the word."""
    x = x ^ (x >> np.uint64(30))
    x = x * np.uint64(0xBF58476D1CE4E5B9)
    x = x ^ (x >> np.uint64(27))
    x = x * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, inverse) of the distinct rows of a 2-D float or integer array: a[first] holds each
    distinct row once, in the order of first appearance, and a[first][inverse] == a.

    The rows are hashed to one uint64 (their bit patterns through splitmix64), so only one
    integer column is sorted (np.unique(axis=0) sorts whole rows: ~10x slower on 10^6 rows); a
    hash collision is detected (a row differing from its representative) and answered by the
    exact row sort, so the result never depends on the hash."""
    a = np.ascontiguousarray(a)
    if a.ndim != 2:
        raise ValueError("unique_rows expects a 2-D array")
    if len(a) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    bits = a.view(np.uint64) if a.dtype.itemsize == 8 else a.astype(np.int64).view(np.uint64)
    with np.errstate(over="ignore"):
        h = np.zeros(len(a), np.uint64)
        for c in range(bits.shape[1]):
            h = _mix64(h ^ bits[:, c])
    _, first, inverse = np.unique(h, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    if not np.array_equal(a[first][inverse], a):
        _, first, inverse = np.unique(a, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.reshape(-1)
    # numbered in the order of first appearance (independent of the hash)
    order = np.argsort(first)
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    return first[order].astype(np.int64), rank[inverse]


@numba.njit(cache=True)
def _propagate_flips(flip, child, parent, inconsistent):
    for i in range(child.shape[0]):
        flip[child[i]] = flip[parent[i]] ^ inconsistent[i]


@dataclass(frozen=True)
class Closest:
    """Answer of a closest-point query, one row per query point."""

    points: np.ndarray  # (n, 3) closest points on the surface
    distance: np.ndarray  # (n,)
    face: np.ndarray  # (n,) triangle index
    bary: np.ndarray  # (n, 3) barycentric coordinates in that triangle
    normal: np.ndarray  # (n, 3) outward unit normal of that triangle
    on_boundary: np.ndarray  # (n,) bool: closest point on an open edge (hole / scan border)


@dataclass
class TargetSurface:
    """A triangulated surface with outward normals, boundary edges and a closest-point query."""

    vertices: np.ndarray
    faces: np.ndarray
    name: str = "surface"
    _tree: cKDTree = field(init=False, repr=False)

    def __post_init__(self):
        v = np.ascontiguousarray(self.vertices, dtype=np.float64)
        f = np.ascontiguousarray(self.faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"{self.name}: expected vertices (n, 3) and triangles (m, 3)")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{self.name}: vertices contain NaN or infinite values")
        v, f = merge_coincident(v, f)
        tri = v[f]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area2 = np.linalg.norm(cross, axis=1)
        keep = area2 > 1e-12 * max(area2.max(), 1e-300)
        f = f[keep]
        self.vertices, self.faces = v, f
        tri = v[f]
        cross = cross[keep]
        self.face_areas = 0.5 * np.linalg.norm(cross, axis=1)
        self.face_normals = cross / np.maximum(2.0 * self.face_areas, 1e-300)[:, None]
        self.centroids = tri.mean(axis=1)
        self._tree = cKDTree(self.centroids)
        self.face_edge_boundary = self._boundary_edges(f, len(v))
        # vertices on an open edge: a closest point at such a vertex is on the border whichever
        # of the triangles around it the query returns
        self.vertex_on_boundary = np.zeros(len(v), bool)
        for k, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
            self.vertex_on_boundary[f[self.face_edge_boundary[:, k]][:, [a, b]].ravel()] = True
        self._orient_outward()

    @staticmethod
    def _boundary_edges(faces: np.ndarray, n_vertices: int) -> np.ndarray:
        """(m, 3) bool: edge opposite vertex i of each triangle is used by one triangle only."""
        opp = [(1, 2), (2, 0), (0, 1)]
        e = np.concatenate([np.sort(faces[:, list(o)], axis=1) for o in opp])
        key = e[:, 0] * np.int64(n_vertices) + e[:, 1]
        _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
        return (counts[inv] == 1).reshape(3, -1).T

    def _orient_outward(self):
        """Make the winding consistent over each connected patch, then point it outward.

        Consistency: a breadth-first walk over edge-adjacent triangles flips a triangle whose
        shared edge runs the same way as in its predecessor. Outward: per patch, the sign for
        which the area-weighted normals point away from the patch's area centroid (a face, a
        skull or a bone fragment is seen from inside its own bulk)."""
        f = self.faces
        n = len(f)
        directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        owner = np.tile(np.arange(n), 3)
        und = np.sort(directed, axis=1)
        key = und[:, 0] * np.int64(len(self.vertices)) + und[:, 1]
        order = np.argsort(key, kind="stable")
        k_sorted = key[order]
        pair = np.flatnonzero(k_sorted[1:] == k_sorted[:-1])
        # only manifold pairs (exactly two triangles on the edge)
        if len(pair):
            manifold = np.ones(len(pair), bool)
            manifold[1:] &= pair[1:] != pair[:-1] + 1
            manifold[:-1] &= pair[:-1] + 1 != pair[1:]
            pair = pair[manifold]
        e1, e2 = order[pair], order[pair + 1]
        f1, f2 = owner[e1], owner[e2]
        same_direction = directed[e1, 0] == directed[e2, 0]
        flip = np.zeros(n, bool)
        adj = sp.coo_matrix((np.ones(len(pair)), (f1, f2)), shape=(n, n)).tocsr()
        ncomp, comp = csgraph.connected_components(adj, directed=False)
        if len(pair):
            pkey = np.minimum(f1, f2) * np.int64(n) + np.maximum(f1, f2)
            srt = np.argsort(pkey)
            pkey, same_sorted = pkey[srt], same_direction[srt]
            sizes = np.bincount(comp, minlength=ncomp)
            first = np.full(ncomp, -1)
            first[comp[::-1]] = np.arange(n)[::-1]
            for c in np.flatnonzero(sizes > 1):
                visit, pred = csgraph.breadth_first_order(adj, int(first[c]), directed=False)
                child = visit[1:]
                parent = pred[child]
                q = np.minimum(child, parent) * np.int64(n) + np.maximum(child, parent)
                inconsistent = same_sorted[np.searchsorted(pkey, q)]
                _propagate_flips(flip, child, parent, inconsistent)
        normals = np.where(flip[:, None], -self.face_normals, self.face_normals)
        a = self.face_areas
        area_c = np.bincount(comp, a, minlength=ncomp)
        centre = np.stack([np.bincount(comp, a * self.centroids[:, d], minlength=ncomp)
                           for d in range(3)], axis=1) / np.maximum(area_c, 1e-300)[:, None]
        out = np.einsum("ij,ij->i", normals, self.centroids - centre[comp]) * a
        turn = np.bincount(comp, out, minlength=ncomp) < 0.0
        normals[turn[comp]] *= -1.0
        flip ^= turn[comp]
        self.face_normals = normals
        # share of the area whose winding was turned on reading (1.0: all normals were flipped)
        self.flipped_fraction = float(self.face_areas[flip].sum() / self.face_areas.sum())

    @property
    def bounds(self) -> np.ndarray:
        return np.array([self.vertices.min(0), self.vertices.max(0)])

    @property
    def area(self) -> float:
        return float(self.face_areas.sum())

    @property
    def mean_edge_length(self) -> float:
        tri = self.vertices[self.faces]
        return float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).mean())

    def closest(self, points: np.ndarray, k: int = 24) -> Closest:
        """Closest points on the surface for points (n, 3).

        Candidates are the triangles of the k nearest centroids; where the k-th centroid is
        nearer than the best distance found (large triangles next to small ones) the search is
        widened eight-fold. The result is the exact closest point whenever the closest triangle
        is among the candidates."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        k = int(min(k, len(self.faces)))
        d_c, cand = self._tree.query(p, k=k)
        cand = np.asarray(cand, dtype=np.int64).reshape(len(p), k)
        d_k = np.asarray(d_c, dtype=float).reshape(len(p), k)[:, -1]
        q, bary, face, dist = _closest_over_candidates(p, self.vertices, self.faces, cand)
        unsure = np.flatnonzero(d_k < dist) if k < len(self.faces) else []
        if len(unsure):
            kk = int(min(len(self.faces), 8 * k))
            _, cand2 = self._tree.query(p[unsure], k=kk)
            cand2 = np.asarray(cand2, dtype=np.int64).reshape(len(unsure), kk)
            q2, b2, f2, d2 = _closest_over_candidates(p[unsure], self.vertices, self.faces, cand2)
            # the wider search holds the first candidates: the same triangle, or a closer one,
            # or a tie with a lower index (the same rule as within one search)
            s0, s2 = dist[unsure] ** 2, d2 ** 2
            tie = TIE_REL * (1.0 + s0)
            better = (s2 < s0 - tie) | ((s2 <= s0 + tie) & (f2 < face[unsure]))
            idx = unsure[better]
            q[idx], bary[idx], face[idx], dist[idx] = q2[better], b2[better], f2[better], d2[better]
        tol = 1e-6
        # closest point on the edge opposite vertex i <=> bary[i] ~ 0
        on_edge = bary < tol
        on_boundary = np.any(on_edge & self.face_edge_boundary[face], axis=1)
        at_vertex = bary > 1.0 - tol
        on_boundary |= np.any(at_vertex & self.vertex_on_boundary[self.faces[face]], axis=1)
        return Closest(q, dist, face, bary, self.face_normals[face], on_boundary)

    def sample(self, n: int, seed: int = 0) -> np.ndarray:
        """n points spread over the surface by area (deterministic for a seed)."""
        rng = np.random.default_rng(seed)
        f = rng.choice(len(self.faces), size=n, p=self.face_areas / self.face_areas.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
        return np.einsum("ni,nid->nd", w, self.vertices[self.faces[f]])

    def transformed(self, scale: float, rotation: np.ndarray, translation: np.ndarray) -> "TargetSurface":
        """The surface moved by x -> scale R x + t. A similarity (scale > 0, R proper) keeps
        which vertices coincide, which triangles are valid, the open edges and the outward
        orientation: only the geometry is mapped and the centroid tree rebuilt (cleaning and
        orienting anew cost seconds on a 10^6-triangle scan)."""
        r = np.asarray(rotation, float)
        t = np.asarray(translation, float)
        v = scale * self.vertices @ r.T + t
        if not (scale > 0 and np.linalg.det(r) > 0):
            return TargetSurface(v, self.faces, self.name)
        out = copy.copy(self)
        out.vertices = v
        out.centroids = scale * self.centroids @ r.T + t
        out.face_normals = self.face_normals @ r.T
        out.face_areas = scale * scale * self.face_areas
        out._tree = cKDTree(out.centroids)
        return out


def merge_coincident(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices that coincide to 1e-9 of the surface's extent merged (STL stores every
    triangle's corners separately) and the triangles left with a repeated corner dropped."""
    v, f = np.asarray(vertices, float), np.asarray(faces, np.int64)
    extent = float(np.ptp(v, axis=0).max()) or 1.0
    first, inverse = unique_rows(np.round(v / (1e-9 * extent)) + 0.0)   # + 0.0: -0.0 is 0.0
    v, f = v[first], inverse[f]
    return v, f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]


# Triangle budget of the surfaces registration works on: a CT-derived skin or bone has 10^5-10^6
# triangles, the face model's skin ~10^4 facets (edges of 2-4 mm); 200,000 triangles keep edges
# near 1 mm on a head (the CT reader's own budget, `planner.case.CT_MAX_FACES`), where a chord
# departs from a curved surface by e^2 / 8R (~0.03 mm at R = 5 mm, the nose tip).
WORKING_MAX_FACES = 200_000


def simplifies(n_faces: int, max_faces: int | None) -> bool:
    """Whether `working_surface` simplifies a surface of n_faces triangles."""
    return max_faces is not None and n_faces > 2 * max_faces


def working_surface(vertices: np.ndarray, faces: np.ndarray, max_faces: int = WORKING_MAX_FACES
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The surface registration works on: unchanged up to twice `max_faces` triangles (there a
    simplification would cost about what it saves downstream), else its coincident vertices
    merged and the mesh simplified to `max_faces` triangles by quadric edge collapse (Garland and
    Heckbert, SIGGRAPH 1997; the `fast_simplification` implementation of Fast Quadric Mesh
    Simplification), which keeps each new vertex where the squared distances to the planes of
    the original triangles around it are least, so that the coarse surface stays on the fine
    one (`surface_deviation` measures by how much)."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    if not simplifies(len(f), max_faces):
        return v, f
    import fast_simplification

    v, f = merge_coincident(v, f)
    out_v, out_f = fast_simplification.simplify(v, f, target_count=int(max_faces))
    return np.asarray(out_v, float), np.asarray(out_f, np.int64)


def surface_deviation(full_vertices: np.ndarray, working: TargetSurface, n_max: int = 50_000) -> dict:
    """How far the vertices of the full surface (up to n_max of them, evenly strided) lie from
    a working surface made from it: mean, 99th percentile and maximum, mm."""
    v = np.asarray(full_vertices, float)
    d = working.closest(v[:: max(1, len(v) // n_max)]).distance
    return {"mean_mm": float(d.mean()), "p99_mm": float(np.percentile(d, 99)), "max_mm": float(d.max())}
