"""Closest points and signed point-to-surface distances on triangle meshes.

For every query point the exact closest point on a triangulated surface is found
(`solver.geometry.TriangleTree`: candidate triangles from a k-d tree of pieces that cover
them, each projected with the Voronoi-region case analysis of Ericson, *Real-Time Collision Detection*
(2005), sect. 5.1.5, the search widened until no other triangle can be nearer). The distance is
signed with the normal interpolated (barycentric) from area-weighted vertex normals at the
closest point: positive when the query point lies on the outer side of the surface. A closest
point that lies on a boundary edge or boundary vertex of the surface is flagged, and so is a
query point beyond that edge (its offset is not along the normal), so callers can drop points
where the two surfaces do not overlap (a point beyond the edge of a partial scan is not a
distance between two existing surfaces).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from solver.geometry import TriangleTree

__all__ = ["TriangleSurface", "ClosestPoints", "vertex_areas"]


@dataclass(frozen=True)
class ClosestPoints:
    """Result of a closest-point query (arrays over the query points)."""

    point: np.ndarray        # (p, 3) closest point on the surface
    face: np.ndarray         # (p,) triangle index
    bary: np.ndarray         # (p, 3) barycentric weights of `point` in that triangle
    distance: np.ndarray     # (p,) unsigned distance (mm)
    signed: np.ndarray       # (p,) signed distance, > 0 on the outer side (mm)
    normal: np.ndarray       # (p, 3) unit surface normal at `point`
    on_boundary: np.ndarray  # (p,) bool: `point` lies on the surface's boundary
    beyond_boundary: np.ndarray  # (p,) bool: on the boundary and the query point lies beyond
                                 # the edge (offset not along the normal), i.e. no overlap


class TriangleSurface:
    """A triangle mesh with what closest-point queries need, computed once.

    `vertices (n, 3)`, `faces (m, 3)` with consistent winding (outward normals by the
    right-hand rule).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise ValueError("a surface needs at least one triangle")

    @cached_property
    def _tree(self) -> TriangleTree:
        return TriangleTree(self.vertices, self.faces)

    @cached_property
    def face_normals(self) -> np.ndarray:
        """Area-weighted (un-normalised: twice the area times the unit normal) face normals."""
        v = self.vertices
        f = self.faces
        return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])

    @cached_property
    def face_areas(self) -> np.ndarray:
        return 0.5 * np.linalg.norm(self.face_normals, axis=1)

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """Unit vertex normals, area-weighted average of the incident face normals."""
        n = len(self.vertices)
        idx = self.faces.ravel()
        fn = np.repeat(self.face_normals, 3, axis=0)
        vn = np.column_stack([np.bincount(idx, weights=fn[:, c], minlength=n) for c in range(3)])
        norm = np.linalg.norm(vn, axis=1, keepdims=True)
        return vn / np.where(norm > 0, norm, 1.0)

    @cached_property
    def _edge_keys(self) -> np.ndarray:
        """(m, 3) int64 key a * n + b (a < b) of the edges (0,1), (1,2), (2,0) of each face."""
        n = len(self.vertices)
        e = self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 3, 2)
        return np.minimum(e[..., 0], e[..., 1]) * n + np.maximum(e[..., 0], e[..., 1])

    @cached_property
    def boundary_edges(self) -> np.ndarray:
        """(b, 2) vertex pairs of edges used by exactly one triangle."""
        n = len(self.vertices)
        uniq, counts = np.unique(self._edge_keys.ravel(), return_counts=True)
        key = uniq[counts == 1]
        return np.column_stack([key // n, key % n])

    @cached_property
    def _face_edge_on_boundary(self) -> np.ndarray:
        """(m, 3) bool: edge k of face (corners k, k+1) is a boundary edge."""
        n = len(self.vertices)
        key_b = self.boundary_edges[:, 0] * n + self.boundary_edges[:, 1]
        return np.isin(self._edge_keys, key_b)

    @cached_property
    def vertex_on_boundary(self) -> np.ndarray:
        flag = np.zeros(len(self.vertices), bool)
        flag[self.boundary_edges.ravel()] = True
        return flag

    @cached_property
    def mean_edge_length(self) -> float:
        v = self.vertices
        f = self.faces
        return float(np.mean(np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2)))

    def closest(self, points: np.ndarray, k: int = 16) -> ClosestPoints:
        """Exact closest points on the surface (`solver.geometry.TriangleTree`)."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        _, bary, face, distance = self._tree.closest(points, k=k)
        corners = self.vertices[self.faces[face]]                  # (p, 3, 3)
        point = np.einsum("pk,pki->pi", bary, corners)
        normal = np.einsum("pk,pki->pi", bary, self.vertex_normals[self.faces[face]])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        side = np.einsum("pi,pi->p", points - point, normal)
        signed = np.where(side < 0, -distance, distance)
        # on the boundary: on a boundary edge (the weight of the opposite corner is 0) or at a
        # boundary vertex (its weight is 1)
        zero = bary <= 1e-12
        edge_b = self._face_edge_on_boundary[face]                 # edges (0,1), (1,2), (2,0)
        on_edge = (zero[:, 2] & edge_b[:, 0]) | (zero[:, 0] & edge_b[:, 1]) | (zero[:, 1] & edge_b[:, 2])
        at_vertex = self.vertex_on_boundary[self.faces[face]] & (bary >= 1.0 - 1e-12)
        on_boundary = on_edge | np.any(at_vertex, axis=1)
        # beyond the edge: the offset has a tangential part (more than 0.05 mm, far above
        # round-off, far below any scan's resolution); a point right above an edge is not
        tangential = np.linalg.norm(points - point - side[:, None] * normal, axis=1)
        beyond = on_boundary & (tangential > 0.05)
        return ClosestPoints(point, face, bary, distance, signed, normal, on_boundary, beyond)


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Barycentric area of each vertex (a third of its incident triangles' areas), mm^2."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    a = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    return np.bincount(f.ravel(), weights=np.repeat(a / 3.0, 3), minlength=len(v))
