"""Hexahedral meshes: the mesh record, validation, quality and boundary facets.

A mesh is `nodes (n, 3)` float64 and `hexes (m, 8)` int in VTK hexahedron order, with an
integer material label per element. Validation refuses indices out of range, repeated nodes in
an element and inverted or degenerate elements (non-positive Jacobian determinant at a corner
or Gauss point), naming the elements. The scaled Jacobian is the minimum over the eight
corners of the determinant of the three unit edge vectors meeting there (Knupp 2000, the
Verdict library's `hex_scaled_jacobian`): 1 for a cube, <= 0 for an inverted corner.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from solver.element import HEX8_CORNERS, HEX8_FACES, gauss_hex, hex8_gradients
from solver.errors import MeshError

__all__ = ["HexMesh", "corner_jacobians", "scaled_jacobian", "boundary_facets", "check_mesh"]

# for corner c, the three neighbouring corners along +xi, +eta, +zeta (or their opposites),
# ordered so that a right-handed undistorted element has positive determinants
_CORNER_NEIGHBOURS = np.array([[1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7],
                               [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]])


@dataclass(frozen=True, eq=False)
class HexMesh:
    """A hexahedral mesh. `labels` default to zeros; `check` validates on construction."""

    nodes: np.ndarray
    hexes: np.ndarray
    labels: np.ndarray = None
    check: bool = field(default=True, repr=False)

    def __post_init__(self):
        nodes = np.ascontiguousarray(self.nodes, dtype=float)
        hexes = np.ascontiguousarray(self.hexes, dtype=np.int64)
        labels = (np.zeros(len(hexes), dtype=np.int64) if self.labels is None
                  else np.ascontiguousarray(self.labels, dtype=np.int64))
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "hexes", hexes)
        object.__setattr__(self, "labels", labels)
        if self.check:
            check_mesh(nodes, hexes, labels)

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_cells(self) -> int:
        return len(self.hexes)

    def boundary_facets(self) -> np.ndarray:
        return boundary_facets(self.hexes)

    def scaled_jacobian(self) -> np.ndarray:
        return scaled_jacobian(self.nodes, self.hexes)


def check_mesh(nodes: np.ndarray, hexes: np.ndarray, labels: np.ndarray | None = None) -> None:
    """Raise MeshError if the arrays do not form a valid, non-inverted hexahedral mesh."""
    if nodes.ndim != 2 or nodes.shape[1] != 3:
        raise MeshError(f"nodes must have shape (n, 3), got {nodes.shape}")
    if hexes.ndim != 2 or hexes.shape[1] != 8:
        raise MeshError(f"hexes must have shape (m, 8), got {hexes.shape}")
    if len(hexes) == 0:
        raise MeshError("the mesh has no elements")
    if not np.all(np.isfinite(nodes)):
        bad = np.unique(np.nonzero(~np.isfinite(nodes))[0])
        raise MeshError(f"node coordinates are not finite at nodes {bad[:10].tolist()}")
    if hexes.min() < 0 or hexes.max() >= len(nodes):
        bad = np.nonzero((hexes < 0).any(1) | (hexes >= len(nodes)).any(1))[0]
        raise MeshError(f"elements {bad[:10].tolist()} refer to nodes outside 0..{len(nodes) - 1}",
                        elements=bad)
    if labels is not None and labels.shape != (len(hexes),):
        raise MeshError(f"labels must have shape ({len(hexes)},), got {labels.shape}")
    s = np.sort(hexes, axis=1)
    rep = np.nonzero((s[:, 1:] == s[:, :-1]).any(1))[0]
    if len(rep):
        raise MeshError(f"elements {rep[:10].tolist()} repeat a node (degenerate hexahedra)",
                        elements=rep)
    detj = corner_jacobians(nodes, hexes)
    xg, _ = gauss_hex(2)
    dN = hex8_gradients(xg)
    Jg = det3(np.einsum("mai,qaj->mqij", nodes[hexes], dN))
    worst = np.minimum(detj.min(1), Jg.min(1))
    bad = np.nonzero(~(worst > 0))[0]
    if len(bad):
        raise MeshError(
            f"{len(bad)} inverted or degenerate element(s) (Jacobian determinant <= 0), "
            f"first: {bad[:10].tolist()}; worst element {int(np.argmin(worst))} "
            f"(det J = {worst.min():.3g}). Check the node order (VTK hexahedron) and the geometry.",
            elements=bad)


def det3(J: np.ndarray) -> np.ndarray:
    """Determinants of 3 x 3 matrices (..., 3, 3) by the triple product (cofactor expansion
    along the first row): the same value as `np.linalg.det` up to round-off, without an LU
    factorisation per matrix."""
    return (J[..., 0, 0] * (J[..., 1, 1] * J[..., 2, 2] - J[..., 1, 2] * J[..., 2, 1])
            - J[..., 0, 1] * (J[..., 1, 0] * J[..., 2, 2] - J[..., 1, 2] * J[..., 2, 0])
            + J[..., 0, 2] * (J[..., 1, 0] * J[..., 2, 1] - J[..., 1, 1] * J[..., 2, 0]))


def corner_jacobians(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """Jacobian determinant of the isoparametric map at the 8 corners -> (m, 8)."""
    dN = hex8_gradients(HEX8_CORNERS)                          # (8 corners, 8 nodes, 3)
    Jc = np.einsum("mai,caj->mcij", nodes[hexes], dN)
    return det3(Jc)


def scaled_jacobian(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """Minimum corner scaled Jacobian of each hexahedron -> (m,), in [-1, 1]."""
    x = nodes[hexes]                                           # (m, 8, 3)
    e = x[:, _CORNER_NEIGHBOURS, :] - x[:, :, None, :]         # (m, 8, 3, 3) edges from corner
    n = np.linalg.norm(e, axis=-1, keepdims=True)
    e = e / np.where(n > 0, n, 1.0)
    d = det3(e)
    return d.min(axis=1)


def boundary_facets(hexes: np.ndarray, return_cells: bool = False):
    """Quads that belong to exactly one hexahedron, outward by the right-hand rule -> (k, 4).

    With `return_cells`, also the owning element of each facet and the local face index.
    """
    hexes = np.asarray(hexes)
    faces = hexes[:, HEX8_FACES].reshape(-1, 4)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    once = counts[inv] == 1
    if return_cells:
        idx = np.nonzero(once)[0]
        return faces[idx], idx // 6, idx % 6
    return faces[once]
