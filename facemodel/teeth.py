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


# mm: the step of the search for the smallest shift that clears an arch (`clear_teeth`), a
# fraction of the smallest teeth's thickness (a few mm) so that no clear interval is stepped over
SCAN_MM = 0.25
# degrees: the directions in the mid-sagittal plane `clear_teeth` tries after straight back,
# tilted up or down from it (the arch sits in a slot of tissue: moved straight back far enough
# it meets the tissue behind it, and a tilted move can clear both sides sooner)
TILTS_DEG = (15, -15, 30, -30, 45, -45, 60, -60, 75, -75, 90, -90)


def _smallest_shift(depth, clearance: float, max_shift: float):
    """The smallest s in (0, max_shift] with depth(s) <= -clearance, or None: scanned upwards
    in SCAN_MM steps, then bisected (to ~1e-8 mm) in the step where it first clears. A larger
    shift is not always clear too (moved far enough, the arch reaches the tissue behind it),
    so the search cannot bisect over the whole range."""
    b = next((s for s in np.arange(1, int(np.ceil(max_shift / SCAN_MM)) + 1) * SCAN_MM
              if depth(min(s, max_shift)) <= -clearance), None)
    if b is None:
        return None
    b = min(b, max_shift)
    a = max(b - SCAN_MM, 0.0)
    for _ in range(30):
        m = 0.5 * (a + b)
        if depth(m) > -clearance:
            a = m
        else:
            b = m
    return b


def clear_teeth(model, clearance: float = 0.25, max_shift: float = 6.0):
    """A model whose arches are moved just enough that every node is `clearance` mm outside
    them; returns (model, {arch: shift_mm}). Arches already clear are untouched. Each arch is
    moved straight back (posterior: away from the lips) by the smallest shift that clears it;
    where none up to `max_shift` does, along the direction of the mid-sagittal plane tilted
    up or down from it (`TILTS_DEG`) that clears with the smallest shift. Raises ValueError if
    no direction clears within `max_shift` mm."""
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
        best = None
        for tilt in (0,) + TILTS_DEG:
            t = np.radians(tilt)
            d = np.array([0.0, -np.cos(t), np.sin(t)])      # RAS: back, tilted up (+) or down

            def depth(s, d=d):
                return solid.depth(pts, offset=s * d)

            shift = _smallest_shift(depth, clearance, max_shift if best is None else best[0])
            if shift is not None and (best is None or shift < best[0]):
                best = (shift, d)
            if tilt == 0 and best is not None:
                break       # straight back clears: the other directions are not tried
        if best is None:
            raise ValueError(f"teeth {name!r}: nodes stay inside the arch for every shift up to "
                             f"{max_shift} mm, straight back or tilted up or down from it; the "
                             "registered lips and teeth disagree")
        shifts[name] = best[0]
        teeth[name] = (v + best[0] * best[1], np.asarray(f), seg)
    return replace(model, teeth=teeth), shifts
