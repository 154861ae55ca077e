"""Closed quad surfaces of structured boxes, mapped to anatomy (teeth arches, bone shells).

A box gridded n_u x n_v x n_w in parameter space is filled with hexahedra (VTK order) and
its boundary faces kept (faces that belong to one hexahedron only, outward by the
right-hand rule); mapping the parameters to space gives a closed, watertight surface by
construction, oriented outward when the map preserves orientation (checked by the caller).
"""
from __future__ import annotations

import numpy as np

HEX_FACES = np.array([
    [0, 3, 2, 1], [4, 5, 6, 7], [0, 4, 7, 3], [1, 2, 6, 5], [0, 1, 5, 4], [3, 7, 6, 2],
])


def boundary_quads(hexes: np.ndarray) -> np.ndarray:
    """Faces (k, 4) that belong to one hexahedron only, outward by the right-hand rule."""
    faces = np.asarray(hexes)[:, HEX_FACES].reshape(-1, 4)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.ravel()] == 1]


def box_surface(n_u: int, n_v: int, n_w: int):
    """(params (k, 3) in [0, 1]^3, triangles (t, 3)) of the closed surface of a gridded box."""
    u, v, w = np.meshgrid(np.linspace(0, 1, n_u + 1), np.linspace(0, 1, n_v + 1),
                          np.linspace(0, 1, n_w + 1), indexing="ij")
    idx = np.arange(u.size).reshape(u.shape)
    h = np.stack([idx[:-1, :-1, :-1], idx[1:, :-1, :-1], idx[1:, 1:, :-1], idx[:-1, 1:, :-1],
                  idx[:-1, :-1, 1:], idx[1:, :-1, 1:], idx[1:, 1:, 1:], idx[:-1, 1:, 1:]],
                 -1).reshape(-1, 8)
    quads = boundary_quads(h)
    used, inv = np.unique(quads, return_inverse=True)
    quads = inv.reshape(-1, 4)
    params = np.stack([u.ravel(), v.ravel(), w.ravel()], -1)[used]
    tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return params, tri


def orient_outward(vertices: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Flip the triangles if the enclosed signed volume is negative."""
    a, b, c = vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]]
    if np.einsum("ij,ij->i", a, np.cross(b, c)).sum() < 0:
        return tri[:, ::-1].copy()
    return tri
