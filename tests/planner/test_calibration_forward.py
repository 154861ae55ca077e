"""Forward models of `faceplan calibrate`: Hertz limit, mesh convergence, lateral extent."""
import numpy as np
import pytest

from planner.calibration.slab import MeshOptions, Site, forward_curve, slab_mesh


def test_hertz_homogeneous_half_space():
    # a homogeneous slab (dermis ratio 1, no C20) 15 contact radii thick and wide under a small
    # spherical indentation: F = 16/9 E sqrt(R) d^1.5 (incompressible Hertz). 3 %: Hertz is the
    # small-strain limit (a/R = 0.16 here: the finite-strain correction is ~1 %), the wedge
    # mesh's discretisation error ~1 % at this resolution.
    site = Site("indentation", skin_mm=2.0, fat_mm=28.0, indenter_radius_mm=2.0)
    C10 = 2.5
    E = 6.0 * C10
    d = np.array([0.02, 0.05])
    F = forward_curve(site, C10, 0.0, 1.0, d, MeshOptions(n_fine=6, lateral=1.5))
    hertz = 16.0 / 9.0 * E * np.sqrt(2.0) * d ** 1.5
    assert np.all(np.abs(F / hertz - 1.0) < 0.03), F / hertz


def _rel_change(a, b):
    return float(np.max(np.abs(a / b - 1.0)))


@pytest.mark.parametrize("test", ["aspiration", "indentation"])
def test_mesh_convergence_and_lateral_extent(test):
    # the curve changes by < 1 % when the mesh is refined twice (radial and across the dermis,
    # growth halved) and when the slab's lateral extent is doubled
    if test == "aspiration":
        site = Site("aspiration", skin_mm=1.8, fat_mm=8.0, aperture_mm=10.0, rim_mm=3.0)
        x = np.array([4.0, 12.0])
        n_fine = 8
    else:
        site = Site("indentation", skin_mm=1.5, fat_mm=5.0, indenter_radius_mm=3.0)
        x = np.array([0.3, 1.0])
        n_fine = 6
    params = (5.0, 2.0, 3.0)
    base = MeshOptions(n_fine=n_fine)
    y0 = forward_curve(site, *params, x, base)
    y_fine = forward_curve(site, *params, x, base.refined(2.0))
    y_wide = forward_curve(site, *params, x, MeshOptions(n_fine=n_fine, lateral=2 * base.lateral))
    assert _rel_change(y0, y_fine) < 0.01, (y0, y_fine)
    assert _rel_change(y0, y_wide) < 0.01, (y0, y_wide)
    assert np.all(np.diff(y0) > 0) and np.all(y0 > 0)


def test_slab_mesh_layers_and_wedge():
    site = Site("aspiration", skin_mm=2.0, fat_mm=6.0)
    sm = slab_mesh(site, MeshOptions(n_fine=4))
    m = sm.mesh
    zc = m.nodes[m.hexes, 2].mean(1)
    assert np.all((zc > 6.0) == (m.labels == 1))
    # the slab's volume is the wedge's: (angle / 2) (R^2 - r0^2) thickness
    from solver.element import gauss_hex, hex8_gradients
    xg, wg = gauss_hex(2)
    J = np.einsum("mai,qaj->mqij", m.nodes[m.hexes], hex8_gradients(xg))
    vol = np.sum(np.linalg.det(J) * wg)
    R, r0 = sm.radii[-1], sm.radii[0]
    exact = 0.5 * sm.wedge * (R ** 2 - r0 ** 2) * 8.0
    # chords instead of arcs: the area of the polygonal wedge is sin(w)/w of the sector's
    assert vol == pytest.approx(exact * np.sin(sm.wedge) / sm.wedge, rel=1e-9)
