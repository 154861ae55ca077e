"""Export of results to VTU (meshio): displacement, Cauchy stress, volume ratio J, labels.

Point data: `displacement` (n, 3) mm; cell data: `cauchy_stress` (m, 9 -> 3x3 row-major) kPa,
`von_mises` kPa, `J` (element volume ratio v/V), `label`. Extra point/cell arrays may be added.
"""
from __future__ import annotations

import numpy as np

from solver.mechanics import von_mises

__all__ = ["write_vtu", "read_vtu"]


def write_vtu(path, nodes, hexes, displacement=None, cauchy=None, J=None, labels=None,
              point_data=None, cell_data=None, deformed: bool = False) -> None:
    """Write a hexahedral mesh and results to `path` (.vtu). With `deformed`, the points are the
    current coordinates (nodes + displacement); otherwise the reference ones."""
    import meshio

    nodes = np.asarray(nodes, dtype=float)
    pdata = {}
    cdata = {}
    if displacement is not None:
        u = np.asarray(displacement, dtype=float).reshape(-1, 3)
        pdata["displacement"] = u
        if deformed:
            nodes = nodes + u
    if cauchy is not None:
        s = np.asarray(cauchy, dtype=float)
        cdata["cauchy_stress"] = [s.reshape(len(s), 9)]
        cdata["von_mises"] = [von_mises(s)]
    if J is not None:
        cdata["J"] = [np.asarray(J, dtype=float)]
    if labels is not None:
        cdata["label"] = [np.asarray(labels, dtype=np.int32)]
    for k, v in (point_data or {}).items():
        pdata[k] = np.asarray(v)
    for k, v in (cell_data or {}).items():
        cdata[k] = [np.asarray(v)]
    mesh = meshio.Mesh(nodes, [("hexahedron", np.asarray(hexes, dtype=np.int64))],
                       point_data=pdata, cell_data=cdata)
    mesh.write(str(path))


def read_vtu(path):
    """Read a VTU written by `write_vtu` -> (nodes, hexes, point_data, cell_data)."""
    import meshio

    m = meshio.read(str(path))
    hexes = m.get_cells_type("hexahedron")
    cdata = {k: v[0] for k, v in m.cell_data.items()}
    return m.points, hexes, dict(m.point_data), cdata
