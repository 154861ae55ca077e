"""Umeyama recovers a known similarity; surface alignment recovers a far, rotated, partial pose."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from registration.alignment import Similarity, align_surfaces, umeyama
from registration.surface import TargetSurface
from shell import ellipsoid_radius, surface_grid, with_bump


def test_umeyama_recovers_similarity_exactly():
    rng = np.random.default_rng(0)
    src = rng.normal(0, 50, (10, 3))
    r = Rotation.from_rotvec([0.3, -0.5, 1.1]).as_matrix()
    dst = 1.12 * src @ r.T + [10, -40, 5]
    tf = umeyama(src, dst)
    # noise-free data: the closed form is exact up to round-off
    assert abs(tf.scale - 1.12) < 1e-12 and np.allclose(tf.rotation, r, atol=1e-12)
    assert np.allclose(tf.apply(src), dst, atol=1e-9)


def _face():
    # an anterior shell with a "nose" so that no rotation about the y axis is a symmetry
    return with_bump(with_bump(ellipsoid_radius(75, 95, 105), 18, 0.0, 0.1, 0.15), 8, 0.0, -0.6, 0.2)


@pytest.mark.parametrize("angle_deg,shift,extent_deg", [(0, 0, 85), (90, 250, 70), (35, -120, 40)])
def test_surface_alignment_recovers_pose(angle_deg, shift, extent_deg):
    """Near pose with a wider patient surface; far pose (90 deg, 250 mm) with the same
    extent, where the principal axes disambiguate; 35 deg with only the front of the face."""
    radius = _face()
    gv, gf = surface_grid(radius, n_theta=40, n_phi=30, theta_max=np.radians(70), phi_max=np.radians(50))
    generic = TargetSurface(gv, gf)
    truth = Similarity(0.93, Rotation.from_rotvec(np.radians(angle_deg) * np.array([0.2, 0.3, 0.93])
                                                  / np.linalg.norm([0.2, 0.3, 0.93])).as_matrix(),
                       np.array([shift, 0.3 * shift, -0.2 * shift]))
    # the patient surface, triangulated twice as finely as the generic one
    tmax = np.radians(extent_deg)
    pv, pf = surface_grid(radius, n_theta=80, n_phi=60, theta_max=tmax, phi_max=np.radians(65))
    patient = TargetSurface(truth.apply(pv), pf)
    res = align_surfaces(generic, patient)
    x = res.similarity.apply(gv)
    err = np.linalg.norm(x - truth.apply(gv), axis=1)
    # tolerance: sampling of 1500 points on ~4 mm triangles leaves sub-mm registration error
    assert err.max() < 1.5, (err.max(), res)
