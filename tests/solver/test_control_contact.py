"""The contact terms' shared settings and results interface (`ContactTerm`).

* `settings=AugmentedLagrangian(...)` and the same fields as keywords build the same term (the
  same force, compared exactly: the same arithmetic); a class keeps its own defaults
  (`RigidSurfaceContact.DEFAULTS`); a bad penalty or an unknown field is refused.
* `SurfaceContact.contact_forces(x)` is minus the term's residual contribution at the same state
  (to round-off, 1e-12), as `SegmentContact`'s is (tests/solver/test_contact_segment.py).
"""
import numpy as np
import pytest

from solver.contact import (AugmentedLagrangian, ContactTerm, RigidSurfaceContact,
                            SegmentContact, SurfaceContact)
from solver.terms import Term


def _patches():
    """Two facing wavy patches (as in test_contact_terms)."""
    nx = 4
    s = np.linspace(0, 3, nx)
    gx, gy = np.meshgrid(s, s, indexing="ij")
    bottom = np.stack([gx.ravel(), gy.ravel(), 0.1 * np.sin(gx + gy).ravel()], axis=1)
    top = bottom.copy()
    top[:, :2] += [0.37, 0.21]
    top[:, 2] = -0.05 + 0.1 * np.cos(gx - gy).ravel()
    q = np.array([[i * nx + j, (i + 1) * nx + j, (i + 1) * nx + j + 1, i * nx + j + 1]
                  for i in range(nx - 1) for j in range(nx - 1)])
    return np.vstack([bottom, top]), q, q[:, ::-1] + nx * nx


def _pressed(term):
    for ps in term.passes:
        ps.multipliers[:] = 0.3
    return term


def test_settings_object_and_keywords_agree():
    x, a, b = _patches()
    t1 = _pressed(SurfaceContact(x, a, b, penalty=50.0, search_radius=1.0))
    t2 = _pressed(SurfaceContact(x, a, b, settings=AugmentedLagrangian(penalty=50.0,
                                                                        search_radius=1.0)))
    f1, _ = t1.assemble(x, 1.0)
    f2, _ = t2.assemble(x, 1.0)
    assert np.abs(f1).max() > 0 and np.array_equal(f1, f2)
    t3 = SurfaceContact(x, a, b, settings=AugmentedLagrangian(penalty=50.0), tolerance=0.01)
    assert t3.penalty == 50.0 and t3.tolerance == 0.01       # a keyword overrides a field
    rigid = RigidSurfaceContact(x, x[:3], np.array([[0, 1, 2]]), slave_nodes=np.arange(3))
    assert rigid.search_radius == 5.0 and np.isinf(rigid.max_depth)
    with pytest.raises(ValueError, match="penalty"):
        SurfaceContact(x, a, b, penalty=0.0)
    with pytest.raises(TypeError):
        SurfaceContact(x, a, b, no_such_setting=1.0)
    for cls in (SurfaceContact, RigidSurfaceContact, SegmentContact):
        assert issubclass(cls, ContactTerm) and issubclass(cls, Term)


def test_surface_contact_forces_are_minus_the_residual_term():
    x, a, b = _patches()
    term = _pressed(SurfaceContact(x, a, b, penalty=50.0, search_radius=1.0))
    f, _ = term.assemble(x, 1.0)
    fc = term.contact_forces(x)
    assert np.abs(f).max() > 0
    assert np.allclose(fc.ravel(), -f, atol=1e-12)
    assert term.penetration(x) >= 0.0
