"""Mesh generators for verification problems and demos: block, Cook's membrane, sphere sector.

* `block` — a structured box of hexahedra.
* `cook_membrane` — the tapered panel of Cook (1974) with corners (0,0), (48,44), (48,60),
  (0,44) mm, one element thick, the classic bending-dominated locking benchmark.
* `sphere_sector` — a thick spherical shell sector a <= r <= b around +z bounded by the four
  planes x = +-t z, y = +-t z (a gnomonic "cube-sphere" patch); every node of a side plane has
  that plane's normal, so radial (spherically symmetric) deformation satisfies the symmetry
  conditions exactly with local-frame constraints.
All return node arrays, VTK-ordered hexes and named node sets.
"""
from __future__ import annotations

import numpy as np

__all__ = ["block", "cook_membrane", "sphere_sector", "structured_hexes"]


def structured_hexes(nx: int, ny: int, nz: int) -> np.ndarray:
    """VTK hexes of an (nx+1) x (ny+1) x (nz+1) lattice numbered i + (nx+1)(j + (ny+1) k)."""
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    i, j, k = i.ravel(order="F"), j.ravel(order="F"), k.ravel(order="F")

    def nid(a, b, c):
        return a + (nx + 1) * (b + (ny + 1) * c)

    return np.stack([nid(i, j, k), nid(i + 1, j, k), nid(i + 1, j + 1, k), nid(i, j + 1, k),
                     nid(i, j, k + 1), nid(i + 1, j, k + 1), nid(i + 1, j + 1, k + 1),
                     nid(i, j + 1, k + 1)], axis=1).astype(np.int64)


def _lattice(xs, ys, zs):
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    return np.stack([X.ravel(order="F"), Y.ravel(order="F"), Z.ravel(order="F")], axis=1)


def block(size=(1.0, 1.0, 1.0), divisions=(2, 2, 2), origin=(0.0, 0.0, 0.0)):
    """Box [origin, origin + size] with divisions elements per axis -> (nodes, hexes, sets).

    Node sets: 'xmin', 'xmax', 'ymin', 'ymax', 'zmin', 'zmax'.
    """
    nx, ny, nz = (int(d) for d in divisions)
    o = np.asarray(origin, dtype=float)
    L = np.asarray(size, dtype=float)
    nodes = _lattice(np.linspace(o[0], o[0] + L[0], nx + 1), np.linspace(o[1], o[1] + L[1], ny + 1),
                     np.linspace(o[2], o[2] + L[2], nz + 1))
    hexes = structured_hexes(nx, ny, nz)
    tol = 1e-9 * max(L)
    sets = {}
    for ax, name in enumerate("xyz"):
        sets[f"{name}min"] = np.nonzero(np.abs(nodes[:, ax] - o[ax]) < tol)[0]
        sets[f"{name}max"] = np.nonzero(np.abs(nodes[:, ax] - o[ax] - L[ax]) < tol)[0]
    return nodes, hexes, sets


def cook_membrane(n: int = 8, thickness: float = 1.0):
    """Cook's membrane with n x n elements in plane, one element through the thickness.

    Node sets: 'left' (x = 0, clamped), 'right' (x = 48, loaded), 'top_right' (the corner
    (48, 60), both thickness nodes); facet set 'right_facets' (outward quads of the right edge).
    """
    s, t = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    x = 48.0 * s
    ybot = 44.0 * s
    ytop = 44.0 + 16.0 * s
    y = ybot + t * (ytop - ybot)
    nodes2 = np.stack([x.ravel(order="F"), y.ravel(order="F")], axis=1)
    nodes = np.concatenate([np.c_[nodes2, np.zeros(len(nodes2))],
                            np.c_[nodes2, np.full(len(nodes2), thickness)]])
    hexes = structured_hexes(n, n, 1)
    left = np.nonzero(nodes[:, 0] < 1e-9)[0]
    right = np.nonzero(nodes[:, 0] > 48 - 1e-9)[0]
    top_right = np.nonzero((nodes[:, 0] > 48 - 1e-9) & (nodes[:, 1] > 60 - 1e-9))[0]
    from solver.mesh import boundary_facets

    fac = boundary_facets(hexes)
    rf = fac[np.all(nodes[fac][:, :, 0] > 48 - 1e-9, axis=1)]
    return nodes, hexes, {"left": left, "right": right, "top_right": top_right,
                          "right_facets": rf}


def sphere_sector(n_angle: int = 4, n_radial: int = 4, inner: float = 1.0, outer: float = 2.0,
                  half_angle_deg: float = 22.5, grading: float = 1.0):
    """Thick spherical shell sector around +z (see module docstring).

    grading > 1 concentrates radial layers near the inner surface (geometric ratio between
    consecutive layer thicknesses is 1/grading). Returns (nodes, hexes, sets) with node sets
    'inner', 'outer', 'plane_xm', 'plane_xp', 'plane_ym', 'plane_yp', the dict 'plane_normals'
    and facet set 'inner_facets' (outward normals of the body, pointing to the centre).
    """
    tmax = np.tan(np.radians(half_angle_deg))
    a = np.linspace(-tmax, tmax, n_angle + 1)
    if grading == 1.0:
        rr = np.linspace(inner, outer, n_radial + 1)
    else:
        w = grading ** (-np.arange(n_radial))
        rr = inner + (outer - inner) * np.concatenate([[0.0], np.cumsum(w) / w.sum()])
    A, B, R = np.meshgrid(a, a, rr, indexing="ij")
    A, B, R = A.ravel(order="F"), B.ravel(order="F"), R.ravel(order="F")
    d = np.stack([A, B, np.ones_like(A)], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    nodes = d * R[:, None]
    hexes = structured_hexes(n_angle, n_angle, n_radial)
    tol = 1e-9
    sets = {
        "inner": np.nonzero(np.abs(R - inner) < tol)[0],
        "outer": np.nonzero(np.abs(R - outer) < tol)[0],
        "plane_xm": np.nonzero(np.abs(A + tmax) < tol)[0],
        "plane_xp": np.nonzero(np.abs(A - tmax) < tol)[0],
        "plane_ym": np.nonzero(np.abs(B + tmax) < tol)[0],
        "plane_yp": np.nonzero(np.abs(B - tmax) < tol)[0],
    }
    c = np.sqrt(1 + tmax ** 2)
    sets["plane_normals"] = {"plane_xm": np.array([1.0, 0.0, tmax]) / c,
                             "plane_xp": np.array([1.0, 0.0, -tmax]) / c,
                             "plane_ym": np.array([0.0, 1.0, tmax]) / c,
                             "plane_yp": np.array([0.0, 1.0, -tmax]) / c}
    from solver.mesh import boundary_facets

    fac = boundary_facets(hexes)
    rad = np.linalg.norm(nodes[fac], axis=2)
    sets["inner_facets"] = fac[np.all(np.abs(rad - inner) < 1e-9, axis=1)]
    return nodes, hexes, sets
