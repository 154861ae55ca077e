"""A body with Yeoh and non-Yeoh labels (a face: tissue and muscles) evaluates the Yeoh
elements with the fused kernel and the others through the Material protocol ("hybrid").

Its forces, tangent and energy equal those of the all-generic evaluation of the same body to
round-off (1e-10 relative: the two paths sum the same terms in a different order), in the
displacement-based and the three-field (stored theta, p) states, and an inverted element of
either kind is reported with its global index.
"""
import numpy as np
import pytest

import solver
from solver.constitution.muscle import Muscle
from solver.examples import block


def _body():
    nodes, hexes, _ = block((3.0, 2.0, 2.0), (3, 2, 2))
    centres = nodes[hexes].mean(axis=1)
    labels = (centres[:, 0] > 1.5).astype(int)             # label 1: a muscle slab
    fibres = np.zeros((len(hexes), 3))
    fibres[labels == 1] = [0.6, 0.8, 0.0]
    mats = {0: solver.Yeoh(2.5, 1.175, 0.1, K=500.0),
            1: Muscle(C10=3.0, C20=0.5, K=400.0, activation=0.3)}
    body = solver.SolidBody(solver.HexMesh(nodes, hexes, labels), mats, fibres=fibres)
    rng = np.random.default_rng(0)
    x = nodes * [1.1, 0.95, 0.97] + 0.03 * rng.standard_normal(nodes.shape)
    return body, x


def _both(body, x, load=1.0):
    assert body.hybrid and not body.fused
    a = body.evaluate(x, load)
    body.hybrid = False
    b = body.evaluate(x, load)
    body.hybrid = True
    return a, b


@pytest.mark.parametrize("mixed", [False, True])
def test_hybrid_equals_generic(mixed):
    body, x = _body()
    if mixed:
        body.begin_mixed(body.mesh.nodes)                   # stored state differs from x's
    a, b = _both(body, x, load=0.7)
    assert a.valid and b.valid
    scale = np.abs(b.force).max()
    assert np.abs(a.force - b.force).max() <= 1e-10 * scale
    assert np.abs(a.data - b.data).max() <= 1e-10 * np.abs(b.data).max()
    assert abs(a.energy - b.energy) <= 1e-10 * abs(b.energy)
    assert a.worst_element == b.worst_element and np.isclose(a.min_J, b.min_J, rtol=1e-12)


@pytest.mark.parametrize("label", [0, 1])
def test_inverted_element_reported_globally(label):
    body, x = _body()
    e = int(np.nonzero(body.mesh.labels == label)[0][-1])
    hexes = body.mesh.hexes
    x = body.mesh.nodes.copy()
    x[hexes[e, 6]] = x[hexes[e, 0]] - 0.5 * (x[hexes[e, 6]] - x[hexes[e, 0]])  # fold it over
    a, b = _both(body, x)
    assert not a.valid and not b.valid
    assert a.worst_element == b.worst_element == e or a.min_J <= 0.0 and b.min_J <= 0.0
