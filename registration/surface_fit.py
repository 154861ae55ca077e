"""Least-squares facet fit: skin nodes placed so that the bilinear skin facets, not only their
corners, lie on the patient skin.

After the snap every skin node lies on the patient surface, but a bilinear quad between four
nodes on a curved surface sags below it on convex parts (and bulges above it in concave ones)
by about h^2 kappa / 8 at its centre (h the facet size, kappa the normal curvature): ~0.3-0.5
mm on the lips and nose of the coarse mesh. The best the facets can do is to straddle the
surface: each node i moves by o_i along its vertex normal n_i so that the squared signed
distance integrated over the facets is least (a Gauss-Newton iteration on the linearised
distance, as in the surface-fitting stage of subdivision / spline surface fitting, e.g. Hoppe
et al., "Piecewise smooth surface reconstruction", SIGGRAPH 1994, and the L2 facet criterion
of Bucki et al.'s surface-matching energy):
    min_o  sum_quads sum_gauss  A_q w_g (s_qg + sum_c N_c(xi_g) (n_c . m_qg) o_c)^2
           + alpha sum_i A_i o_i^2 + beta sum_edges (o_i - o_j)^2,
s_qg the signed distance (outward positive) of the Gauss point from the patient skin, m_qg
the patient normal at its closest point, N_c the bilinear shape functions, A_q the facet
area and w_g the 3 x 3 Gauss-Legendre weights (so the sum is the facet integral of s^2).
The small ridge (alpha) keeps nodes outside the fitted facets where they are (a large
one pins the landmark nodes on the surface); the edge term
(beta) keeps neighbouring offsets alike. Offsets are capped at `max_offset_mm`, and any
element whose minimum scaled Jacobian would fall below the quality threshold gives its skin
nodes back their previous offset, so that the fit never costs the repair's quality.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from registration.elastic import vertex_normals
from registration.quality import min_scaled_jacobian
from registration.surface import TargetSurface

_G = 0.5 * (1.0 + np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)]))  # Gauss-Legendre on [0, 1]
_W = np.array([5.0, 8.0, 5.0]) / 18.0
GAUSS_UV = np.array([[u, v] for v in _G for u in _G])
GAUSS_W = np.array([wu * wv for wv in _W for wu in _W])


def bilinear_shape(uv: np.ndarray) -> np.ndarray:
    """(s, 4) bilinear shape functions of quad corners 0-1-2-3 at (u, v) points."""
    u, v = uv[:, 0], uv[:, 1]
    return np.stack([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], axis=1)


def _signed(surface: TargetSurface, p: np.ndarray):
    cl = surface.closest(p)
    s = np.einsum("ij,ij->i", p - cl.points, cl.normal)
    return s, cl.normal, cl.on_boundary


def facet_fit(x: np.ndarray, hexes: np.ndarray, quads: np.ndarray, skin_tris: np.ndarray,
              surface: TargetSurface, *, threshold: float = 0.2, iterations: int = 3,
              alpha: float = 1e-3, beta: float = 1e-2, max_offset_mm: float = 1.0,
              pinned: np.ndarray | None = None):
    """Offsets of the nodes of `quads` (skin facets fitted, all nodes on `surface`) along
    their normals minimising the facet-to-surface L2 distance; returns (new nodes, report).

    pinned: node ids that stay where they are (on the surface), e.g. the landmark nodes,
    which must remain skin points; the facets around them fit with the other nodes."""
    x = np.array(x, dtype=float)
    quads = np.asarray(quads, dtype=np.int64)
    report = {"facets": int(len(quads)), "iterations": 0}
    if len(quads) == 0:
        return x, {**report, "nodes_moved": 0, "rms_before_mm": None, "rms_after_mm": None}
    ids = np.unique(quads)
    loc = np.searchsorted(ids, quads)
    n = len(ids)
    normals = vertex_normals(x, np.asarray(skin_tris))[ids]
    shape = bilinear_shape(GAUSS_UV)  # (g, 4)
    x0 = x[ids].copy()
    offset = np.zeros(n)
    edges = np.unique(np.sort(np.concatenate([loc[:, [0, 1]], loc[:, [1, 2]], loc[:, [2, 3]],
                                              loc[:, [3, 0]]]), axis=1), axis=0)
    lap = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    lap = lap + lap.T
    lap = (sp.diags(np.asarray(lap.sum(axis=1)).ravel()) - lap).tocsr()

    def gauss_points(pos):
        corners = pos[loc]  # (q, 4, 3)
        pts = np.einsum("gc,qcd->qgd", shape, corners)
        # facet area element at the Gauss points (|x_u x x_v|), bilinear derivatives
        du = np.einsum("gc,qcd->qgd", _shape_du(GAUSS_UV), corners)
        dv = np.einsum("gc,qcd->qgd", _shape_dv(GAUSS_UV), corners)
        jac = np.linalg.norm(np.cross(du, dv), axis=-1)
        return pts.reshape(-1, 3), (jac * GAUSS_W[None]).ravel()

    def rms(pos):
        p, w = gauss_points(pos)
        s, _, _ = _signed(surface, p)
        return float(np.sqrt(np.sum(w * s**2) / np.sum(w)))

    pos = x0.copy()
    report["rms_before_mm"] = rms(pos)
    area_node = np.zeros(n)
    _, w0 = gauss_points(pos)
    np.add.at(area_node, np.repeat(loc, len(GAUSS_W), axis=0).ravel(),
              np.repeat(w0, 4) / 4.0)
    ridge = alpha * area_node
    if pinned is not None:
        ridge = np.where(np.isin(ids, pinned), 1e6 * area_node, ridge)
    rows = np.repeat(np.arange(len(quads) * len(GAUSS_W)), 4)
    cols = np.repeat(loc, len(GAUSS_W), axis=0).ravel()
    for it in range(iterations):
        p, w = gauss_points(pos)
        s, m, bnd = _signed(surface, p)
        w = np.where(bnd, 0.0, w)
        # d s_qg / d o_c = N_c(xi_g) (n_c . m_qg)
        nc = normals[cols]
        vals = np.tile(shape, (len(quads), 1)).ravel() * np.einsum("ij,ij->i", nc, np.repeat(m, 4, axis=0))
        jmat = sp.csr_matrix((vals, (rows, cols)), shape=(len(p), n))
        wd = sp.diags(w)
        scale = float(np.mean(area_node))
        lhs = (jmat.T @ wd @ jmat + sp.diags(ridge) + beta * scale * lap).tocsc()
        rhs = -(jmat.T @ (w * s)) - ridge * offset - beta * scale * (lap @ offset)
        step = spsolve(lhs, rhs)
        offset = np.clip(offset + step, -max_offset_mm, max_offset_mm)
        pos = x0 + offset[:, None] * normals
        report["iterations"] = it + 1

    # quality guard: elements that would fall below the threshold keep their old skin nodes
    q_old = min_scaled_jacobian(x, hexes)
    node_elem = sp.csr_matrix((np.ones(hexes.size), (np.asarray(hexes).ravel(),
                                                     np.repeat(np.arange(len(hexes)), 8))),
                              shape=(len(x), len(hexes)))
    touched = np.unique(node_elem[ids].indices)
    reverted = np.zeros(n, bool)
    for _ in range(10):
        xn = x.copy()
        xn[ids] = x0 + np.where(reverted, 0.0, offset)[:, None] * normals
        q = min_scaled_jacobian(xn, hexes[touched])
        bad = touched[(q < threshold) & (q < q_old[touched])]
        if len(bad) == 0:
            break
        hit = np.isin(ids, np.asarray(hexes)[bad].ravel())
        if not (hit & ~reverted).any():
            break
        reverted |= hit
    x = xn
    report.update(rms_after_mm=rms(x[ids]), nodes_moved=int((~reverted & (np.abs(offset) > 0)).sum()),
                  nodes_reverted=int(reverted.sum()),
                  offset_mean_abs_mm=float(np.abs(np.where(reverted, 0, offset)).mean()),
                  offset_max_abs_mm=float(np.abs(np.where(reverted, 0, offset)).max()))
    return x, report


def _shape_du(uv):
    v = uv[:, 1]
    return np.stack([-(1 - v), (1 - v), v, -v], axis=1)


def _shape_dv(uv):
    u = uv[:, 0]
    return np.stack([-(1 - u), -u, u, (1 - u)], axis=1)
