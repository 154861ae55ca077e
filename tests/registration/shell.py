"""Analytic test geometry: a structured hexahedral shell between two ellipsoidal surfaces.

The shell spans azimuth theta (about +z, theta = 0 facing anterior +y) and elevation phi,
with radial layers from an inner "bone" surface to an outer "skin" surface, both given as
radius functions r(theta, phi) about a centre. It stands in for the generic face model in the
registration tests: the patient is another pair of radius functions, so true surfaces, true
correspondences and exact distances are all known.
"""
from __future__ import annotations

import numpy as np


def direction(theta, phi):
    return np.stack([np.sin(theta) * np.cos(phi), np.cos(theta) * np.cos(phi), np.sin(phi)], axis=-1)


def ellipsoid_radius(a, b, c):
    """Radius function of the ellipsoid x^2/a^2 + y^2/b^2 + z^2/c^2 = 1 along a direction."""
    def r(theta, phi):
        d = direction(theta, phi)
        return 1.0 / np.sqrt((d[..., 0] / a) ** 2 + (d[..., 1] / b) ** 2 + (d[..., 2] / c) ** 2)
    return r


def with_bump(radius, amplitude, theta0, phi0, width):
    def r(theta, phi):
        g = np.exp(-((theta - theta0) ** 2 + (phi - phi0) ** 2) / (2 * width**2))
        return radius(theta, phi) + amplitude * g
    return r


def shell_mesh(inner, outer, n_theta=16, n_phi=12, n_layers=3,
               theta_max=np.radians(70), phi_max=np.radians(50)):
    """Nodes, hexes (VTK order, positive), skin quads (outward), bone node ids, skin node ids."""
    th = np.linspace(-theta_max, theta_max, n_theta + 1)
    ph = np.linspace(-phi_max, phi_max, n_phi + 1)
    T, P = np.meshgrid(th, ph, indexing="ij")
    d = direction(T, P)
    ri, ro = inner(T, P), outer(T, P)
    s = np.linspace(0.0, 1.0, n_layers + 1)
    r = ri[..., None] + (ro - ri)[..., None] * s  # (i, j, k)
    nodes = (d[:, :, None, :] * r[..., None]).reshape(-1, 3)
    idx = np.arange(nodes.shape[0]).reshape(n_theta + 1, n_phi + 1, n_layers + 1)
    i, j, k = np.meshgrid(np.arange(n_theta), np.arange(n_phi), np.arange(n_layers), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    hexes = np.stack([idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
                      idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1]], 1)
    # orient: the corner Jacobian at node 0 must be positive
    x = nodes[hexes]
    det = np.einsum("md,md->m", x[:, 1] - x[:, 0], np.cross(x[:, 3] - x[:, 0], x[:, 4] - x[:, 0]))
    flip = det < 0
    hexes[flip] = hexes[flip][:, [0, 3, 2, 1, 4, 7, 6, 5]]
    top = k == n_layers - 1
    skin_quads = hexes[top][:, [4, 5, 6, 7]]
    skin_nodes = idx[:, :, -1].ravel()
    bone_nodes = idx[:, :, 0].ravel()
    return nodes, hexes, skin_quads, skin_nodes, bone_nodes, idx


def surface_grid(radius, n_theta=120, n_phi=90, theta_max=np.radians(85), phi_max=np.radians(65),
                 theta_min=None):
    """Triangulated surface r(theta, phi) over a parameter rectangle (vertices, faces)."""
    theta_min = -theta_max if theta_min is None else theta_min
    th = np.linspace(theta_min, theta_max, n_theta + 1)
    ph = np.linspace(-phi_max, phi_max, n_phi + 1)
    T, P = np.meshgrid(th, ph, indexing="ij")
    v = (direction(T, P) * radius(T, P)[..., None]).reshape(-1, 3)
    idx = np.arange(len(v)).reshape(T.shape)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, faces


def radial_distance(points, radius):
    """|r(p) - r_surface(direction of p)|: distance along the ray, an upper bound of the
    Euclidean distance to a star-shaped surface and equal to it to first order."""
    rho = np.linalg.norm(points, axis=1)
    theta = np.arctan2(points[:, 0], points[:, 1])
    phi = np.arcsin(np.clip(points[:, 2] / rho, -1, 1))
    return np.abs(rho - radius(theta, phi))


def quads_to_triangles(quads):
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
