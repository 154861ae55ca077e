"""Release band of two-surface contact at the master surface's free edges (`edge_release`):
the force of a slave sliding off the edge of the master surface fades continuously to zero,
the force and tangent stay the exact derivatives of the energy, and the contact patch test
still holds."""
import numpy as np
import pytest

from solver.contact import SurfaceContact

from test_contact_terms import _fd_check


def _sheet_and_node(release, nx=3, blend=0.0, crease=0.0):
    """A flat master sheet z = 0 (nx x nx nodes over [0, 2]^2, normal +z, free edges at
    x = 0, 2 and y = 0, 2) and a slave triangle facing it (normal -z) whose first node is the
    probe; the slave facet sits 0.2 mm below the sheet (penetrating)."""
    s = np.linspace(0.0, 2.0, nx)
    gx, gy = np.meshgrid(s, s, indexing="ij")
    # a crease along x = 1 (slope `crease` on the x > 1 side)
    sheet = np.stack([gx.ravel(), gy.ravel(), crease * np.maximum(gx.ravel() - 1.0, 0.0)],
                     axis=1)
    quads = np.array([[i * nx + j, (i + 1) * nx + j, (i + 1) * nx + j + 1, i * nx + j + 1]
                      for i in range(nx - 1) for j in range(nx - 1)])
    probe = np.array([[1.0, 1.3, -0.2], [1.0, 0.3, -0.2], [0.0, 1.3, -0.2]])
    x = np.vstack([sheet, probe])
    n = len(sheet)
    slave = np.array([[n, n + 1, n + 2]])                  # normal -z
    term = SurfaceContact(x, slave, quads, two_pass=False, penalty=50.0, search_radius=1.0,
                          max_depth=1.0, ignore_initial_penetration=False,
                          edge_release=release, crease_blend=blend)
    return term, x, n


def _probe_force(release, xs, **kw):
    """Contact force (mN) on the probe node at each x-position (fresh search at each, as at
    the first Newton iterations of a load step), the node 0.2 mm deep."""
    term, x, n = _sheet_and_node(release, **kw)
    out = []
    for xp in xs:
        y = x.copy()
        y[n:, 0] += xp - 1.0          # the whole slave facet slides along x
        term._unfreeze()
        out.append(term.contact_forces(y)[n])
    return np.array(out)


def test_a_node_sliding_off_the_free_edge_is_released_continuously():
    """The probe slides along x across the sheet's free edge at x = 2 (edge length 1 mm,
    band 0.5 mm). Penalty 50 kPa/mm x tributary area 1/6 mm^2 x depth 0.2 mm: full force
    1.67 mN normal to the sheet."""
    xs = np.linspace(1.5, 2.7, 1201)                       # steps of 1 um
    full = 50.0 * (0.5 / 3.0) * 0.2
    f = _probe_force(0.5, xs)
    assert f[0, 2] == pytest.approx(full, rel=1e-9)        # on the sheet: unchanged
    inside = xs <= 2.0
    assert np.allclose(f[inside], f[0], rtol=0, atol=1e-9 * full)
    assert np.all(f[xs >= 2.5 + 1e-9] == 0.0)              # beyond the band: released
    # continuous: over a 1 um step the force changes by at most the largest slope of the
    # fade (quintic smoothstep: 15/8 per band width) times the step, plus the release push;
    # bound 1 % of the full force per um (a jump would be 100 %)
    jumps = np.linalg.norm(np.diff(f, axis=0), axis=1)
    assert jumps.max() < 1e-2 * full
    # the push off the edge (-psi dw/dx) points outward (+x) in the band
    band = (xs > 2.0 + 1e-3) & (xs < 2.5 - 1e-3)
    assert np.all(f[band, 0] > 0)
    # without the band the force drops from full to zero within one step at the edge
    f0 = _probe_force(0.0, xs)
    assert np.linalg.norm(np.diff(f0, axis=0), axis=1).max() > 0.9 * full


@pytest.mark.parametrize("blend", [0.0, 0.25])
@pytest.mark.parametrize("position", [(2.2, 1.3), (2.3, 2.15), (1.0, 1.3), (1.1, 0.93)])
def test_release_band_force_and_tangent_are_the_derivatives_of_the_energy(position, blend):
    """Finite differences on every coordinate (slave and master nodes) in the band past one
    free edge, past a corner (two free edges: the product of two fades) and on the sheet,
    with the master sheet bent and multipliers set, with and without crease blending (near
    an interior edge and a vertex: the blended gap of up to three neighbouring planes); the
    status frozen (the pairing and the bands' edge normals are kept, as in a Newton solve
    after `freeze_after` evaluations)."""
    term, x, n = _sheet_and_node(0.5, blend=blend)
    y = x.copy()
    y[n:, 0] += position[0] - 1.0
    y[n:, 1] += position[1] - 1.3
    y[:n, 2] += 0.05 * np.sin(y[:n, 0] + 2.0 * y[:n, 1])           # bent master sheet
    ps = term.passes[0]
    ps.multipliers[:] = 0.4
    for _ in range(term.freeze_after + 1):
        term.assemble(y, 1.0)
    f, K = _fd_check(term, y, 1.0)
    assert np.abs(f).max() > 0
    assert np.allclose(K, K.T)
    # action and reaction: the contact forces sum to zero
    assert np.allclose(f.reshape(-1, 3).sum(axis=0), 0.0, atol=1e-10)


def test_edge_release_is_checked():
    with pytest.raises(ValueError, match="edge_release"):
        _sheet_and_node(-0.1)


def test_patch_test_holds_with_the_release_band():
    """The two-block patch test (`test_contact_patch`) with the band on both passes: the
    interface's boundary nodes lie on the master's free edges (d = 0, weight 1), so the
    contact still transmits the uniform confined-compression stress (1 %, as the test without
    the band) at the analytic value (0.1 %)."""
    from test_contact_patch import _confined_blocks

    szz, contact, res = _confined_blocks(
        4, 4, lambda nodes, low, up: SurfaceContact(nodes, low, up, penalty=100.0,
                                                    tolerance=1e-6, search_radius=0.5,
                                                    edge_release=0.5),
        steps=2)
    assert szz.max() < 0
    assert (szz.max() - szz.min()) / abs(szz.mean()) < 1e-2
    assert contact.penetration(res.x) < 1e-5
    lam, mu, K = 0.95, 5.0, 50.0
    I1 = 2 + lam ** 2
    expected = mu / lam * lam ** (-2 / 3) * (lam ** 2 - I1 / 3) + 0.5 * K * (lam - 1 / lam)
    assert szz.mean() == pytest.approx(expected, rel=1e-3)


def test_crease_blending_makes_the_force_continuous_across_a_crease():
    """The probe, 0.2 mm below the sheet, slides along x across the crease at x = 1 (the
    sheet rises with slope 0.5 beyond it, 26.6 deg). Without blending the gap jumps from one
    plane to the other where the pairing switches (here by about 0.03 mm of the 0.2 mm
    depth, with the pairing hysteresis 0.05 even more); with blending (band 0.25 of the edge
    each side) the force changes by at most 2 % of its value per um step (the largest slope
    of the blend, 15/8 per band width 0.5 mm, times the planes' gap difference, at most the
    slope x 0.25 mm: about 0.1 mN/mm here), and it is the plane's force well inside each
    triangle."""
    xs = np.linspace(0.6, 1.4, 801)                         # steps of 1 um
    kw = dict(crease=0.5)
    f = _probe_force(0.0, xs, blend=0.25, **kw)
    fn = np.linalg.norm(f, axis=1)
    jumps = np.linalg.norm(np.diff(f, axis=0), axis=1)
    assert jumps.max() < 2e-2 * fn.max()
    f0 = _probe_force(0.0, xs, **kw)
    assert np.allclose(f[0], f0[0], rtol=1e-9)               # outside the band: unchanged
    assert np.allclose(f[-1], f0[-1], rtol=1e-9)
    assert np.linalg.norm(np.diff(f0, axis=0), axis=1).max() > 10 * jumps.max()

