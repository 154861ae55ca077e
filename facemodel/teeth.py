"""Rigid teeth against the lips: start contact without penetration.

Contact (lip/teeth) is solved from a state where no soft-tissue node lies inside a tooth;
after a registration moves the lips elastically and the teeth rigidly, some lip nodes can end
up inside the arches. `clear_teeth` translates each arch backwards (posterior, -y: the lips rest on the
incisors from the front) by the smallest amount that
leaves every node at least `clearance` mm outside, found by bisection on the signed distance
(trimesh; the arches are closed surfaces). The teeth stay rigid and on their bone segment's
side: only the contact start is changed, by the measured penetration (reported).

The largest depth of many nodes needs the exact signed distance of few of them: a node's
distance to the surface lies between its nearest centroid's distance minus the largest
centroid-to-corner distance of a triangle (a lower bound) and its nearest vertex's distance (an
upper bound), so an outside node whose lower bound exceeds the smallest upper bound cannot be
the nearest; such nodes are only tested for being inside (ray parity, `trimesh`), and the
signed distance is computed for the others and for any inside.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np


class _Solid:
    """A closed surface's largest depth of points, exact, with the signed distance computed
    only where it can decide it (module docstring)."""

    def __init__(self, mesh):
        from scipy.spatial import cKDTree

        self.mesh = mesh
        tri = np.asarray(mesh.triangles, float)
        c = tri.mean(axis=1)
        self.r_max = float(np.linalg.norm(tri - c[:, None], axis=2).max())
        self.centroids, self.vertices = cKDTree(c), cKDTree(np.asarray(mesh.vertices, float))

    def depth(self, points, offset=None) -> float:
        """Largest depth (mm) of points inside the surface moved by `offset` (3,) (<= 0 when
        all are outside; -inf for no points)."""
        import trimesh

        p = np.asarray(points, float).reshape(-1, 3)
        if len(p) == 0:
            return -np.inf
        if offset is not None:
            p = p - np.asarray(offset, float)        # the points in the surface's frame
        lower = self.centroids.query(p)[0] - self.r_max
        upper = self.vertices.query(p)[0]
        near = lower <= upper.min()
        far = np.flatnonzero(~near)
        if len(far):
            near[far[self.mesh.contains(p[far])]] = True
        return float(trimesh.proximity.signed_distance(self.mesh, p[near]).max())


def _depth(mesh, points) -> float:
    """Largest depth (mm) of points inside a closed surface (<= 0 when all outside)."""
    return _Solid(mesh).depth(points)


def teeth_penetration(model, nodes=None) -> dict:
    """Largest depth (mm) of model nodes inside each arch (<= 0: none inside)."""
    x = np.asarray(model.nodes if nodes is None else nodes, dtype=float)
    out = {}
    for name in model.teeth:
        t = model.teeth_mesh(name)
        lo, hi = t.bounds
        near = np.all((x > lo - 2.0) & (x < hi + 2.0), axis=1)
        out[name] = _depth(t, x[near])
    return out


def clear_teeth(model, clearance: float = 0.25, max_shift: float = 6.0):
    """A model whose arches are moved back just enough that every node is `clearance` mm
    outside them; returns (model, {arch: shift_mm}). Arches already clear are untouched.
    Raises ValueError if an arch would have to move more than `max_shift` mm."""
    import trimesh

    x = np.asarray(model.nodes, dtype=float)
    teeth = dict(model.teeth)
    shifts = {}
    for name, (v, f, seg) in model.teeth.items():
        v = np.asarray(v, dtype=float)
        mesh = trimesh.Trimesh(v, f, process=False)
        lo, hi = mesh.bounds
        near = np.all((x > lo - max_shift - 2.0) & (x < hi + max_shift + 2.0), axis=1)
        pts = x[near]
        solid = _Solid(mesh)
        if solid.depth(pts) <= -clearance:
            shifts[name] = 0.0
            continue
        back = np.array([0.0, -1.0, 0.0])      # posterior (RAS): away from the lips

        def depth(s):
            return solid.depth(pts, offset=s * back)

        if depth(max_shift) > -clearance:
            raise ValueError(f"teeth {name!r}: nodes stay inside the arch even after "
                             f"{max_shift} mm; the registered lips and teeth disagree")
        a, b = 0.0, max_shift
        for _ in range(30):           # bisection to ~1e-8 mm
            m = 0.5 * (a + b)
            if depth(m) > -clearance:
                a = m
            else:
                b = m
        shifts[name] = b
        teeth[name] = (v + b * back, np.asarray(f), seg)
    return replace(model, teeth=teeth), shifts
