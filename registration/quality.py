"""Hexahedron quality: corner and Gauss-point Jacobians and the scaled Jacobian, with exact gradients.

For a trilinear hexahedron (VTK node order) the Jacobian at corner c is the determinant of the
three edge vectors leaving c towards its neighbours, ordered so that a right-handed element
has positive determinants. The *scaled Jacobian* divides that determinant by the product of
the three edge lengths, so it lies in [-1, 1], is 1 for a rectangular box and <= 0 for an
inverted corner (Knupp, "Achieving finite element mesh quality via optimization of the
Jacobian matrix norm and associated quantities", IJNME 48, 2000; the Verdict library
definition, which adds the element centre evaluated with the principal axes).

Positive corner Jacobians do not make a trilinear hexahedron valid: det J is a polynomial in
the natural coordinates, and an element with warped faces can be inverted inside while every
corner is positive. The finite-element solver integrates at the 2 x 2 x 2 Gauss points and
refuses an element inverted at any of them (`solver.mesh.check_mesh`), so the quality measured
here also takes the isoparametric Jacobian columns 2 dx/dxi_k at those eight points (scaled
by their lengths in the same way): a mesh this module passes is one the solver accepts.

Each of the 17 "corners" q (8 corners, the centre, 8 Gauss points) is written as three edge
vectors E_q = M_q X that are linear in the eight nodal positions X, so the gradient of the
scaled Jacobian with respect to the nodes follows from the chain rule in closed form; this is
what the repair step optimises.
"""
from __future__ import annotations

import numba
import numpy as np

# neighbours of each corner, ordered so that det[e1, e2, e3] > 0 for a right-handed hexahedron
CORNER_NEIGHBOURS = np.array(
    [[1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7], [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]]
)


# natural coordinates of the eight nodes (VTK hexahedron)
NODE_XI = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                    [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)
# the 2 x 2 x 2 Gauss points the solver integrates at (`solver.mesh.check_mesh` checks them)
GAUSS_XI = NODE_XI / np.sqrt(3.0)
N_CORNERS = 17  # 8 corners, the centre, 8 Gauss points


def _edge_operator() -> np.ndarray:
    """M (17, 3, 8): edge k of "corner" q is sum_n M[q, k, n] x_n (8 corners, the centre,
    the 8 Gauss points). At the centre and the Gauss points the edges are the isoparametric
    Jacobian's columns times 2, 2 dx/dxi_k, which for a box are its edge vectors."""
    m = np.zeros((N_CORNERS, 3, 8))
    for c in range(8):
        for k in range(3):
            m[c, k, CORNER_NEIGHBOURS[c, k]] += 1.0
            m[c, k, c] -= 1.0
    # principal axes through the centre (Verdict): xi, eta, zeta directions
    m[8, 0] = np.array([-1, 1, 1, -1, -1, 1, 1, -1]) / 4.0
    m[8, 1] = np.array([-1, -1, 1, 1, -1, -1, 1, 1]) / 4.0
    m[8, 2] = np.array([-1, -1, -1, -1, 1, 1, 1, 1]) / 4.0
    # 2 dN_n/dxi_k = xi_nk prod_{j != k} (1 + xi_nj xi_j) / 4 at each Gauss point xi
    for g, xi in enumerate(GAUSS_XI):
        lin = 1.0 + NODE_XI * xi  # (8, 3)
        for k in range(3):
            others = [j for j in range(3) if j != k]
            m[9 + g, k] = NODE_XI[:, k] * lin[:, others[0]] * lin[:, others[1]] / 4.0
    return m


EDGE_OPERATOR = _edge_operator()


EDGE_MATRIX = EDGE_OPERATOR.reshape(3 * N_CORNERS, 8)
EDGE_TRANSPOSED = np.ascontiguousarray(EDGE_OPERATOR.transpose(0, 2, 1))  # (17, 8, 3)


def _edges(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    x = np.asarray(nodes, dtype=float)[np.asarray(hexes)]  # (m, 8, 3)
    return (EDGE_MATRIX @ x).reshape(-1, N_CORNERS, 3, 3)  # (m, 17, 3, 3): edge k of corner q


def corner_jacobians(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """Determinants (m, 17) of the edge matrices at the 8 corners, the centre and the 8 Gauss
    points (mm^3)."""
    e = _edges(nodes, hexes)
    return np.einsum("...d,...d->...", e[..., 0, :], np.cross(e[..., 1, :], e[..., 2, :]))


def scaled_jacobians(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """Scaled Jacobian (m, 17) at the 8 corners, the centre and the 8 Gauss points of every
    hexahedron."""
    e = _edges(nodes, hexes)
    det = np.einsum("...d,...d->...", e[..., 0, :], np.cross(e[..., 1, :], e[..., 2, :]))
    lengths = np.linalg.norm(e, axis=-1).prod(axis=-1)
    return det / np.maximum(lengths, 1e-300)


@numba.njit(cache=True)
def gather_element(x, hexes, i, xe):
    """The eight node coordinates of hexahedron i into xe (8, 3)."""
    for n in range(8):
        for d in range(3):
            xe[n, d] = x[hexes[i, n], d]


@numba.njit(cache=True)
def corner_edges(edge_op, q, xe, e):
    """The three edge vectors e (3, 3) of corner q (0-7, 8 the centre, 9-16 the Gauss points)
    of element xe (8, 3):
    e[k] = sum_n edge_op[q, k, n] xe[n]."""
    for k in range(3):
        for d in range(3):
            acc = 0.0
            for n in range(8):
                acc += edge_op[q, k, n] * xe[n, d]
            e[k, d] = acc


@numba.njit(cache=True)
def _min_scaled_jacobian_kernel(x, hexes, edge_op):
    """The minimum over the 17 corners of `scaled_jacobians`, element by element (one
    pass, no (m, 17, 3, 3) temporaries: the repair and lip stages call it every round)."""
    m = hexes.shape[0]
    out = np.empty(m)
    e = np.empty((3, 3))
    xe = np.empty((8, 3))
    for i in range(m):
        gather_element(x, hexes, i, xe)
        best = np.inf
        for q in range(edge_op.shape[0]):
            corner_edges(edge_op, q, xe, e)
            det = (e[0, 0] * (e[1, 1] * e[2, 2] - e[1, 2] * e[2, 1])
                   + e[0, 1] * (e[1, 2] * e[2, 0] - e[1, 0] * e[2, 2])
                   + e[0, 2] * (e[1, 0] * e[2, 1] - e[1, 1] * e[2, 0]))
            prod = 1.0
            for k in range(3):
                prod *= np.sqrt(e[k, 0] ** 2 + e[k, 1] ** 2 + e[k, 2] ** 2)
            sj = det / max(prod, 1e-300)
            if sj < best:
                best = sj
        out[i] = best
    return out


def min_scaled_jacobian(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """Per-element minimum scaled Jacobian (m,): the minimum over the rows of
    `scaled_jacobians` (numba kernel)."""
    if len(hexes) == 0:
        return np.zeros(0)
    return _min_scaled_jacobian_kernel(np.ascontiguousarray(nodes, dtype=np.float64),
                                       np.ascontiguousarray(hexes, dtype=np.int64), EDGE_OPERATOR)


def scaled_jacobian_gradient(nodes: np.ndarray, hexes: np.ndarray):
    """Scaled Jacobians sj (m, 17) and their gradients d sj / d x (m, 17, 8, 3)."""
    e = _edges(nodes, hexes)  # (m, 17, 3, 3)
    e1, e2, e3 = e[..., 0, :], e[..., 1, :], e[..., 2, :]
    c23, c31, c12 = np.cross(e2, e3), np.cross(e3, e1), np.cross(e1, e2)
    det = np.einsum("...d,...d->...", e1, c23)
    lens = np.maximum(np.linalg.norm(e, axis=-1), 1e-300)  # (m, 17, 3)
    prod = lens.prod(axis=-1)
    sj = det / prod
    ddet = np.stack([c23, c31, c12], axis=-2)  # d det / d e_k  (m, 17, 3, 3)
    dsj_de = ddet / prod[..., None, None] - sj[..., None, None] * e / lens[..., None] ** 2
    grad = EDGE_TRANSPOSED @ dsj_de  # (m, 17, 8, 3)
    return sj, grad


def quality_histogram(min_sj: np.ndarray, bins=(-1.0, 0.0, 0.2, 0.3, 0.5, 0.7, 0.9, 1.0)) -> dict:
    """Counts of elements per scaled-Jacobian bin, as a json-friendly dict."""
    edges = np.asarray(bins, dtype=float)
    counts, _ = np.histogram(np.clip(min_sj, -1.0, 1.0), bins=edges)
    return {"bin_edges": edges.tolist(), "counts": counts.astype(int).tolist()}


def quality_summary(nodes: np.ndarray, hexes: np.ndarray, threshold: float = 0.2,
                    q: np.ndarray | None = None) -> dict:
    """Inverted count, count below threshold, min / mean / 1st percentile and histogram
    (`q`: the per-element minimum scaled Jacobians when already computed)."""
    q = min_scaled_jacobian(nodes, hexes) if q is None else np.asarray(q)
    return {
        "n_elements": int(len(q)),
        "n_inverted": int(np.sum(q <= 0.0)),
        "n_below_threshold": int(np.sum(q < threshold)),
        "threshold": float(threshold),
        "min_scaled_jacobian": float(q.min()) if len(q) else 1.0,
        "p01_scaled_jacobian": float(np.percentile(q, 1)) if len(q) else 1.0,
        "mean_scaled_jacobian": float(q.mean()) if len(q) else 1.0,
        "histogram": quality_histogram(q),
    }
