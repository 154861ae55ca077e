"""Smooth signed distance to a rigid surface: a narrow-band grid with cubic B-spline interpolation.

Node-to-surface contact against a faceted rigid surface has a gap whose gradient jumps across
facet edges (the closest feature switches between the two faces' planes): a node pressed
onto a convex edge, where the penalty solution sits (a few micrometres inside), chatters
between the faces and Newton cycles. Rigid obstacles do not deform, so their signed distance
phi can be sampled once, in the surface's own frame, and replaced by the C2 tricubic B-spline
that interpolates the samples (the implicit rigid-obstacle treatment of e.g. Sifakis & Barbic's
course notes and FEBio's rigid "signed distance" walls): gap g = phi(y), gradient and Hessian
follow analytically, so the contact linearisation is consistent and Newton converges
quadratically, while the facets' corners are rounded over about one grid spacing.

Construction: every grid node within `band` of a triangle gets the exact distance to the
surface (closest point by Ericson's Voronoi-region tests, one numba pass over the triangles and
the grid nodes of their inflated bounding boxes, the grid split in slabs between threads and
nodes culled by their distance to the face's plane), signed with the angle-weighted pseudo-normal
of its closest feature (Baerentzen & Aanaes 2005); nodes farther away take +-band, the sign of
each connected far region taken from the band nodes around it. The interpolating spline's
coefficients come from `scipy.ndimage.spline_filter` (order 3, Unser 1999); evaluation sums the
4 x 4 x 4 coefficients around a point with the cubic B-spline weights and their first and second
derivatives.

A grid depends only on the surface and its parameters, and the same rigid surface is often met
by several solves in one process (repeated solves of one model): `SignedDistanceGrid.shared`
keeps the last few grids built in this process (keyed by a hash of the vertices, faces and
parameters; nothing modifies a grid once built) and returns a stored one instead of building
it again.
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict

import numba as nb
import numpy as np
from scipy import ndimage

from solver.contact._geometry import TriangleSurface, closest_on_triangle, closest_point_on_triangles

__all__ = ["SignedDistanceGrid"]


@nb.njit(cache=True, parallel=True)
def _narrow_band(vertices, faces, origin, h, shape, band, dist2, best, n_slabs):
    """Smallest squared distance (and its face) of every grid node within `band` of a face.

    Each thread owns a slab of grid planes i and visits every face's inflated bounding box
    within it, in face order, so the result does not depend on the number of threads. A node
    whose distance to the face's plane already exceeds the band or its best distance so far
    is skipped before the closest-point test (the plane distance bounds the face distance
    from below)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    b2 = band * band
    nf = faces.shape[0]
    lo = np.empty((nf, 3), dtype=np.int64)
    hi = np.empty((nf, 3), dtype=np.int64)
    normal = np.zeros((nf, 3))
    for f in range(nf):
        a = vertices[faces[f, 0]]
        b = vertices[faces[f, 1]]
        c = vertices[faces[f, 2]]
        for k in range(3):
            mn = min(a[k], min(b[k], c[k])) - band
            mx = max(a[k], max(b[k], c[k])) + band
            lo[f, k] = max(0, int(np.floor((mn - origin[k]) / h)))
            hi[f, k] = min(shape[k] - 1, int(np.ceil((mx - origin[k]) / h)))
        n0 = (b[1] - a[1]) * (c[2] - a[2]) - (b[2] - a[2]) * (c[1] - a[1])
        n1 = (b[2] - a[2]) * (c[0] - a[0]) - (b[0] - a[0]) * (c[2] - a[2])
        n2 = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        length = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if length > 0.0:                    # a degenerate face gets no plane test
            normal[f, 0], normal[f, 1], normal[f, 2] = n0 / length, n1 / length, n2 / length
    for t in nb.prange(n_slabs):
        i0 = t * nx // n_slabs
        i1 = (t + 1) * nx // n_slabs
        p = np.empty(3)
        for f in range(nf):
            ilo = max(lo[f, 0], i0)
            ihi = min(hi[f, 0], i1 - 1)
            if ilo > ihi:
                continue
            a = vertices[faces[f, 0]]
            b = vertices[faces[f, 1]]
            c = vertices[faces[f, 2]]
            for i in range(ilo, ihi + 1):
                p[0] = origin[0] + i * h
                for j in range(lo[f, 1], hi[f, 1] + 1):
                    p[1] = origin[1] + j * h
                    for k in range(lo[f, 2], hi[f, 2] + 1):
                        p[2] = origin[2] + k * h
                        idx = (i * ny + j) * nz + k
                        dp = ((p[0] - a[0]) * normal[f, 0] + (p[1] - a[1]) * normal[f, 1]
                              + (p[2] - a[2]) * normal[f, 2])
                        if dp * dp > b2 or dp * dp > dist2[idx]:
                            continue
                        qx, qy, qz, _ = closest_on_triangle(p, a, b, c)
                        d2 = (p[0] - qx) ** 2 + (p[1] - qy) ** 2 + (p[2] - qz) ** 2
                        if d2 < dist2[idx] and d2 <= b2:
                            dist2[idx] = d2
                            best[idx] = f
    return dist2, best


@nb.njit(cache=True)
def _weights(t, w, dw, d2w):
    """Uniform cubic B-spline weights at local coordinate t in [0, 1) and derivatives."""
    s = 1.0 - t
    w[0] = s * s * s / 6.0
    w[1] = (3.0 * t ** 3 - 6.0 * t * t + 4.0) / 6.0
    w[2] = (-3.0 * t ** 3 + 3.0 * t * t + 3.0 * t + 1.0) / 6.0
    w[3] = t ** 3 / 6.0
    dw[0] = -0.5 * s * s
    dw[1] = 1.5 * t * t - 2.0 * t
    dw[2] = -1.5 * t * t + t + 0.5
    dw[3] = 0.5 * t * t
    d2w[0] = s
    d2w[1] = 3.0 * t - 2.0
    d2w[2] = 1.0 - 3.0 * t
    d2w[3] = t


@nb.njit(cache=True)
def _evaluate(coef, origin, h, pts, val, grad, hess, ok):
    nx, ny, nz = coef.shape
    w = np.empty((3, 4))
    dw = np.empty((3, 4))
    d2w = np.empty((3, 4))
    base = np.empty(3, dtype=np.int64)
    for q in range(pts.shape[0]):
        inside = True
        for k in range(3):
            u = (pts[q, k] - origin[k]) / h
            i = int(np.floor(u))
            if i < 1 or i > coef.shape[k] - 3:
                inside = False
                break
            base[k] = i - 1
            _weights(u - i, w[k], dw[k], d2w[k])
        ok[q] = inside
        if not inside:
            continue
        v = 0.0
        g0 = g1 = g2 = 0.0
        h00 = h11 = h22 = h01 = h02 = h12 = 0.0
        for a in range(4):
            for b in range(4):
                for c in range(4):
                    cf = coef[base[0] + a, base[1] + b, base[2] + c]
                    v += cf * w[0, a] * w[1, b] * w[2, c]
                    g0 += cf * dw[0, a] * w[1, b] * w[2, c]
                    g1 += cf * w[0, a] * dw[1, b] * w[2, c]
                    g2 += cf * w[0, a] * w[1, b] * dw[2, c]
                    h00 += cf * d2w[0, a] * w[1, b] * w[2, c]
                    h11 += cf * w[0, a] * d2w[1, b] * w[2, c]
                    h22 += cf * w[0, a] * w[1, b] * d2w[2, c]
                    h01 += cf * dw[0, a] * dw[1, b] * w[2, c]
                    h02 += cf * dw[0, a] * w[1, b] * dw[2, c]
                    h12 += cf * w[0, a] * dw[1, b] * dw[2, c]
        val[q] = v
        grad[q, 0], grad[q, 1], grad[q, 2] = g0 / h, g1 / h, g2 / h
        h2 = h * h
        hess[q, 0, 0], hess[q, 1, 1], hess[q, 2, 2] = h00 / h2, h11 / h2, h22 / h2
        hess[q, 0, 1] = hess[q, 1, 0] = h01 / h2
        hess[q, 0, 2] = hess[q, 2, 0] = h02 / h2
        hess[q, 1, 2] = hess[q, 2, 1] = h12 / h2


class SignedDistanceGrid:
    """C2 signed distance (outward positive) to a triangulated surface, near the surface.

    vertices (p, 3), faces (q, 3) (or a `TriangleSurface` as `vertices`): the surface, outward
    normals by the right-hand rule (closed
    surfaces are signed everywhere; open ones by the side of their closest feature). band (mm):
    distances are exact up to `band` from the surface (clamped beyond). spacing (mm): grid step,
    by default a third of the median edge length clipped to [0.2, 0.5] mm, enlarged if the grid
    would exceed `max_nodes`.
    """

    _shared: OrderedDict = OrderedDict()     # key -> grid, least recently used first
    shared_size = 8                          # grids kept (a few MB each)

    @classmethod
    def shared(cls, vertices, faces=None, band: float = 3.0, spacing: float | None = None,
               max_nodes: int = 6_000_000) -> "SignedDistanceGrid":
        """The grid of these arguments, built once per process (least recently used grids
        beyond `shared_size` are dropped)."""
        surf = vertices if isinstance(vertices, TriangleSurface) else \
            TriangleSurface(vertices, faces)
        h = hashlib.blake2b(digest_size=16)
        for a in (surf.vertices, surf.faces):
            a = np.ascontiguousarray(a)
            h.update(str((a.dtype, a.shape)).encode())
            h.update(a.tobytes())
        key = (h.hexdigest(), float(band), None if spacing is None else float(spacing),
               int(max_nodes))
        grid = cls._shared.get(key)
        if grid is None:
            grid = cls(surf, band=band, spacing=spacing, max_nodes=max_nodes)
            cls._shared[key] = grid
            while len(cls._shared) > cls.shared_size:
                cls._shared.popitem(last=False)
        cls._shared.move_to_end(key)
        return grid

    def __init__(self, vertices, faces=None, band: float = 3.0, spacing: float | None = None,
                 max_nodes: int = 6_000_000):
        surf = vertices if isinstance(vertices, TriangleSurface) else \
            TriangleSurface(vertices, faces)
        V, F = surf.vertices, surf.faces
        if not band > 0:
            raise ValueError(f"band must be > 0, got {band}")
        if spacing is None:
            e = np.linalg.norm(V[F] - V[np.roll(F, 1, axis=1)], axis=2)
            spacing = float(np.clip(np.median(e) / 3.0, 0.2, 0.5))
        h = float(spacing)
        margin = band + 3.0 * h
        lo, hi = V.min(axis=0) - margin, V.max(axis=0) + margin
        while True:
            shape = np.ceil((hi - lo) / h).astype(np.int64) + 1
            if np.prod(shape) <= max_nodes:
                break
            h *= 1.25
        # grid centred on the surface's box, so that a surface symmetric about a coordinate
        # plane through that centre gets symmetric samples (mirror-symmetric predictions)
        lo = 0.5 * (lo + hi) - 0.5 * (shape - 1) * h
        self.spacing, self.origin, self.shape, self.band = h, lo, tuple(int(s) for s in shape), band
        n = int(np.prod(shape))
        dist2, best = _narrow_band(V, F, lo, h, shape, band, np.full(n, np.inf),
                                   np.full(n, -1, dtype=np.int64), nb.get_num_threads())
        phi = np.full(n, band)
        near = np.nonzero(best >= 0)[0]
        ijk = np.stack(np.unravel_index(near, shape), axis=1)
        p = lo + ijk * h
        face = best[near]
        tri = V[F[face]]
        q, region = closest_point_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
        sign = np.where(np.einsum("ij,ij->i", p - q, surf.pseudo_normal(face, region)) >= 0,
                        1.0, -1.0)
        phi[near] = sign * np.sqrt(dist2[near])
        phi = phi.reshape(shape)
        self._sign_far_regions(phi, best.reshape(shape) >= 0)
        self.coefficients = ndimage.spline_filter(phi, order=3, mode="mirror")

    def _sign_far_regions(self, phi, in_band):
        """Far nodes take -band inside the surface: each connected far region gets the
        majority sign of the band nodes next to it."""
        far = ~in_band
        labels, count = ndimage.label(far)
        if count == 0:
            return
        neg = ndimage.binary_dilation(in_band & (phi < 0)) & far
        pos = ndimage.binary_dilation(in_band & (phi >= 0)) & far
        n_neg = np.bincount(labels[neg], minlength=count + 1)
        n_pos = np.bincount(labels[pos], minlength=count + 1)
        inside = n_neg > n_pos
        inside[0] = False
        phi[inside[labels]] = -self.band

    def evaluate(self, points):
        """phi, gradient (k, 3), Hessian (k, 3, 3) and a mask of the points on the grid."""
        pts = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
        k = len(pts)
        val = np.full(k, np.nan)
        grad = np.zeros((k, 3))
        hess = np.zeros((k, 3, 3))
        ok = np.zeros(k, dtype=np.bool_)
        _evaluate(self.coefficients, self.origin, self.spacing, pts, val, grad, hess, ok)
        return val, grad, hess, ok
