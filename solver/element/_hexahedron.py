"""Trilinear 8-node hexahedron (VTK node order) and 2x2x2 Gauss-Legendre quadrature.

N_a(xi) = 1/8 (1 + xi xi_a)(1 + eta eta_a)(1 + zeta zeta_a) on the reference cube [-1, 1]^3
(Hughes, *The Finite Element Method*, 1987, sec. 3.5). The 2x2x2 rule integrates the trilinear
mass-like terms exactly and is the usual full integration for Q1 solids.
"""
from __future__ import annotations

import numpy as np

__all__ = ["HEX8_CORNERS", "HEX8_FACES", "hex8_shape", "hex8_gradients", "gauss_hex", "gauss_quad",
           "quad4_shape", "quad4_gradients"]

# natural coordinates of the 8 nodes, VTK_HEXAHEDRON order
HEX8_CORNERS = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)

# the six faces, outward normal by the right-hand rule
HEX8_FACES = np.array([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4],
                       [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]], dtype=np.int64)

QUAD4_CORNERS = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)


def hex8_shape(xi: np.ndarray) -> np.ndarray:
    """Shape functions at points xi (q, 3) -> (q, 8)."""
    xi = np.atleast_2d(xi)
    return np.prod(1.0 + xi[:, None, :] * HEX8_CORNERS[None], axis=2) / 8.0


def hex8_gradients(xi: np.ndarray) -> np.ndarray:
    """Shape-function derivatives dN_a/dxi_j at points xi (q, 3) -> (q, 8, 3)."""
    xi = np.atleast_2d(xi)
    t = 1.0 + xi[:, None, :] * HEX8_CORNERS[None]          # (q, 8, 3)
    d = np.empty_like(t)
    for j in range(3):
        others = [k for k in range(3) if k != j]
        d[..., j] = HEX8_CORNERS[None, :, j] * t[..., others[0]] * t[..., others[1]] / 8.0
    return d


def gauss_hex(order: int = 2):
    """Tensor-product Gauss points (q, 3) and weights (q,) on [-1, 1]^3."""
    g, w = np.polynomial.legendre.leggauss(order)
    pts = np.array([[a, b, c] for c in g for b in g for a in g])
    wts = np.array([wa * wb * wc for wc in w for wb in w for wa in w])
    return pts, wts


def quad4_shape(xi: np.ndarray) -> np.ndarray:
    """Bilinear quad shape functions at points (q, 2) -> (q, 4)."""
    xi = np.atleast_2d(xi)
    return np.prod(1.0 + xi[:, None, :] * QUAD4_CORNERS[None], axis=2) / 4.0


def quad4_gradients(xi: np.ndarray) -> np.ndarray:
    """dN_a/dxi_j for the bilinear quad -> (q, 4, 2)."""
    xi = np.atleast_2d(xi)
    t = 1.0 + xi[:, None, :] * QUAD4_CORNERS[None]
    d = np.empty_like(t)
    d[..., 0] = QUAD4_CORNERS[None, :, 0] * t[..., 1] / 4.0
    d[..., 1] = QUAD4_CORNERS[None, :, 1] * t[..., 0] / 4.0
    return d


def gauss_quad(order: int = 2):
    """Gauss points (q, 2) and weights (q,) on [-1, 1]^2."""
    g, w = np.polynomial.legendre.leggauss(order)
    pts = np.array([[a, b] for b in g for a in g])
    wts = np.array([wa * wb for wb in w for wa in w])
    return pts, wts
