"""Newton converges when nothing (or almost nothing) is loaded.

At zero load the internal forces, and with them the relative residual scale, vanish, while the
assembled residual cannot fall below the round-off of forces computed from absolute coordinates
(~1e-10 mN here, above the default absolute tolerance). The solver must then accept the iterate
(its correction is at floating-point resolution) instead of cutting the step back to failure.
"""
import numpy as np
import pytest

import solver
from solver.examples import block


@pytest.mark.parametrize("pull", [0.0, 1e-9, 1e-6])
def test_zero_and_tiny_loads_converge_to_the_exact_state(pull):
    nodes, hexes, s = block((20.0, 20.0, 20.0), (3, 3, 3))
    nodes = nodes + np.array([50.0, 80.0, -40.0])       # face-like absolute coordinates (mm)
    body = solver.SolidBody(solver.HexMesh(nodes, hexes), solver.Yeoh(2.5, 1.175, 0.0, K=2500.0))
    bcs = [solver.fix(s["xmin"]), solver.Prescribed(s["xmax"], [pull, 0.0, 0.0], (0,))]
    res = solver.newton_solve(body, bcs, steps=2, rtol=1e-6, etol=1e-8)
    u = res.x - nodes
    # Exact answer: zero displacement at zero pull; for a tiny pull the linear response, bounded
    # by the pull itself (tolerance 1e-12 mm absolute: round-off on 100 mm coordinates).
    assert np.abs(u).max() <= pull + 1e-12
    assert np.allclose(u[s["xmax"], 0], pull, atol=1e-12)
    assert res.iterations <= 8          # no cut-back cascade (2 steps, a few iterations each)
