"""Forward models of the in-vivo tests: a layered slab under an aspiration aperture or a sphere.

The tissue at a measurement site is a slab of dermis (thickness `skin_mm`) over hypodermis
(`fat_mm`) tied to bone (bottom fixed). Both tests are axially symmetric, so the slab is a thin
wedge of a cylinder (angle `wedge_deg`, one element across) meshed with structured hexahedra
graded towards the axis and the top; the two cut planes carry symmetry conditions (no normal
displacement: Cartesian on the plane y = 0, a local frame on the other), and the axis is a thin
core of radius `axis_mm` whose nodes move along the axis only (u_r = 0 on the axis). Each layer
is a nearly incompressible Yeoh solid (faceplan's solver: Q1/P0 mean dilatation, K = 1000 mu as
the face model's table), the dermis `ratio` times stiffer than the hypodermis (both C10, C20).

* Aspiration (LASTIC device, Luboz et al. 2014; the inverse analysis of Avril & Evans 2017):
  the rim of the device (an annulus of inner radius aperture/2 and width `rim_mm`) holds the
  skin (its nodes fixed); the suction acts on the skin inside the aperture as a follower
  pressure pulling outwards; the measured quantity is the height of the tissue at the apex.
* Indentation: a rigid frictionless sphere of radius R pushed to a prescribed depth; contact by
  a penalty on the gap g = |x - c| - R of the top nodes (penalty per node eps A_i, A_i the
  tributary area, so eps g is a pressure; eps is set from the stiffness and the element size so
  that the penetration stays below 1e-3 of the element size); the force is the sum of the
  contact forces times the number of wedges in a full turn.

Each measured point is solved in turn from the previous state (the load fraction of one solve
ramps from the previous point's pressure or depth to the next one), so the outputs are exactly
at the measured pressures or depths.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from solver import (FollowerPressure, HexMesh, LocalFrame, Prescribed, SolidBody, SolveFailed,
                    Yeoh, newton_solve)
from solver.contact import nodal_areas
from solver.terms import Term

__all__ = ["Site", "MeshOptions", "SlabMesh", "slab_mesh", "forward_curve", "BULK_FACTOR",
           "ForwardError"]

BULK_FACTOR = 1000.0    # K / mu, the face model's near incompressibility (facemodel.materials)
HYPODERMIS, DERMIS = 0, 1


class ForwardError(RuntimeError):
    """A forward solve did not converge (names the site, the parameters and the point)."""


@dataclass(frozen=True)
class Site:
    """One measurement site's test and geometry (mm)."""

    test: str                       # "aspiration" or "indentation"
    skin_mm: float
    fat_mm: float
    aperture_mm: float = 10.0       # aspiration: inner diameter
    rim_mm: float = 3.0             # aspiration: rim width
    indenter_radius_mm: float = 2.0  # indentation: sphere radius
    max_depth_mm: float = 1.0       # indentation: largest depth of the curve (sizes the mesh)

    @property
    def thickness(self) -> float:
        return self.skin_mm + self.fat_mm


@dataclass(frozen=True)
class MeshOptions:
    """Resolution of the slab: `n_fine` radial elements over the zone of interest (the aperture
    and rim, or 1.5 contact radii), growing by `growth` beyond it to `lateral` slab thicknesses
    further out; `n_skin` elements across the dermis, the hypodermis graded from the dermis'
    element size by `growth` downwards."""

    n_fine: int = 16
    growth: float = 1.3
    lateral: float = 3.0
    n_skin: int = 2
    wedge_deg: float = 5.0
    axis_fraction: float = 1e-2     # axis core radius / first element size

    def refined(self, factor: float = 2.0) -> "MeshOptions":
        return replace(self, n_fine=int(round(self.n_fine * factor)),
                       growth=1.0 + (self.growth - 1.0) / factor,
                       n_skin=int(round(self.n_skin * factor)))


@dataclass(frozen=True)
class SlabMesh:
    mesh: HexMesh
    radii: np.ndarray               # (nr,) node radii
    z: np.ndarray                   # (nz,) node heights, bottom 0, top = thickness
    wedge: float                    # radians

    def node(self, plane, i, k):
        """Node index of (cut plane 0/1, radial index, height index)."""
        return _node_index(len(self.radii), len(self.z), plane, i, k)


def _node_index(nr, nz, plane, i, k):
    return np.asarray(plane) * nr * nz + np.asarray(i) * nz + np.asarray(k)


def _graded(h: float, length: float, growth: float) -> np.ndarray:
    """Increasing sizes from h by the factor `growth` summing exactly to `length`."""
    if length <= 0:
        return np.zeros(0)
    sizes = []
    s, total = h, 0.0
    while total + s < length:
        sizes.append(s)
        total += s
        s *= growth
    if not sizes:
        return np.array([length])
    rest = length - total
    if rest < 0.5 * sizes[-1]:
        sizes[-1] += rest
    else:
        sizes.append(rest)
    return np.asarray(sizes)


def _radii(site: Site, opt: MeshOptions) -> tuple[np.ndarray, float]:
    if site.test == "aspiration":
        ra = 0.5 * site.aperture_mm
        h = ra / opt.n_fine
        n_rim = max(1, int(np.ceil(site.rim_mm / h)))
        fine = np.concatenate([np.linspace(0.0, ra, opt.n_fine + 1),
                               np.linspace(ra, ra + site.rim_mm, n_rim + 1)[1:]])
    else:
        R = site.indenter_radius_mm
        a = min(R, np.sqrt(2.0 * R * max(site.max_depth_mm, 1e-3)))
        zone = 1.5 * a
        # twice the aspiration's count: the first, shallow points have a contact patch of a
        # fraction of the largest one, which must still span several elements
        n = 2 * opt.n_fine
        h = zone / n
        fine = np.linspace(0.0, zone, n + 1)
    outer = _graded(fine[-1] - fine[-2], opt.lateral * site.thickness, opt.growth)
    r = np.concatenate([fine, fine[-1] + np.cumsum(outer)])
    r[0] = opt.axis_fraction * h
    return r, h


def _heights(site: Site, opt: MeshOptions, h_r: float) -> np.ndarray:
    # at least `n_skin` elements across the dermis, and no taller than 1.5 radial elements of
    # the fine zone (the contact patch or the aperture must be resolved in depth too); the
    # hypodermis starts at that size and grows towards the bone
    n_skin = max(opt.n_skin, int(np.ceil(site.skin_mm / (1.5 * h_r))))
    hs = site.skin_mm / n_skin
    fat = _graded(hs, site.fat_mm, opt.growth)[::-1]
    z_fat = np.concatenate([[0.0], np.cumsum(fat)])
    z_fat[-1] = site.fat_mm
    z_skin = site.fat_mm + np.linspace(0.0, site.skin_mm, n_skin + 1)[1:]
    return np.concatenate([z_fat, z_skin])


def slab_mesh(site: Site, opt: MeshOptions = MeshOptions()) -> SlabMesh:
    """Structured wedge mesh of the slab: labels HYPODERMIS (0) and DERMIS (1)."""
    r, h_r = _radii(site, opt)
    z = _heights(site, opt, h_r)
    w = np.radians(opt.wedge_deg)
    nr, nz = len(r), len(z)
    P, I, K = np.meshgrid(np.arange(2), np.arange(nr), np.arange(nz), indexing="ij")
    th = P * w
    nodes = np.stack([r[I] * np.cos(th), r[I] * np.sin(th), z[K]], -1).reshape(-1, 3)
    i, k = np.meshgrid(np.arange(nr - 1), np.arange(nz - 1), indexing="ij")
    i, k = i.ravel(), k.ravel()
    def n(plane, i, k):
        return _node_index(nr, nz, plane, i, k)

    hexes = np.stack([n(0, i, k), n(0, i + 1, k), n(1, i + 1, k), n(1, i, k),
                      n(0, i, k + 1), n(0, i + 1, k + 1), n(1, i + 1, k + 1), n(1, i, k + 1)], 1)
    zc = 0.5 * (z[k] + z[k + 1])
    labels = np.where(zc > site.fat_mm, DERMIS, HYPODERMIS)
    return SlabMesh(HexMesh(nodes, hexes, labels), r, z, w)


def _materials(C10: float, C20: float, ratio: float) -> dict:
    def yeoh(f):
        return Yeoh(C10=f * C10, C20=f * C20, C30=0.0, K=BULK_FACTOR * 2.0 * f * C10)
    return {HYPODERMIS: yeoh(1.0), DERMIS: yeoh(ratio)}


def _symmetry(sm: SlabMesh, held: np.ndarray) -> list:
    """Bone (bottom) fixed, the nodes `held` fixed, symmetry on the cut planes, u_r = 0 on the
    axis core; each node under one condition only."""
    nr, nz = len(sm.radii), len(sm.z)
    n_nodes = 2 * nr * nz
    fixed = np.zeros(n_nodes, dtype=bool)
    fixed[sm.node(np.arange(2)[:, None], np.arange(nr)[None, :], 0).ravel()] = True
    fixed[held] = True
    axis = np.zeros(n_nodes, dtype=bool)
    axis[sm.node(np.arange(2)[:, None], 0, np.arange(nz)[None, :]).ravel()] = True
    axis &= ~fixed
    plane1 = np.zeros(n_nodes, dtype=bool)
    plane1[nr * nz:] = True
    cons = [Prescribed(np.nonzero(fixed)[0])]
    a0 = np.nonzero(axis & ~plane1)[0]
    a1 = np.nonzero(axis & plane1)[0]
    s0 = np.nonzero(~plane1 & ~axis & ~fixed)[0]
    s1 = np.nonzero(plane1 & ~axis & ~fixed)[0]
    c, s = np.cos(sm.wedge), np.sin(sm.wedge)
    frame = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])    # rows e_r, e_theta, e_z
    cons += [Prescribed(a0, 0.0, (0, 1)), Prescribed(s0, 0.0, (1,)),
             LocalFrame(a1, frame, (0, 1)), LocalFrame(s1, frame, (1,))]
    return [cn for cn in cons if len(cn.nodes)]


class SphereContact(Term):
    """Frictionless penalty contact of nodes against a rigid sphere whose centre moves along z.

    Gap g_i = |x_i - c| - R, pressure force p_i = eps A_i <-g_i>, residual -p_i n_i with
    n_i = (x_i - c)/|x_i - c|, tangent eps A_i n n^T (active nodes) - p_i (I - n n^T)/|x_i - c|
    (the sphere's curvature); the potential sum eps A_i <-g_i>^2 / 2.
    """

    def __init__(self, nodes, facets, radius: float, centre, penalty: float):
        n_nodes = len(nodes)
        areas = nodal_areas(nodes, facets, n_nodes)
        self.slaves = np.unique(facets)
        self.eps = penalty * areas[self.slaves]
        self.R = float(radius)
        self.centre = centre
        self.n = n_nodes
        d = (3 * self.slaves[:, None] + np.arange(3)).ravel()
        blocks = d.reshape(-1, 3)
        self._rows = np.repeat(blocks, 3, axis=1).ravel()
        self._cols = np.tile(blocks, (1, 3)).ravel()
        self._dofs = d

    def _state(self, x, load):
        d = x[self.slaves] - self.centre(load)
        dist = np.linalg.norm(d, axis=1)
        nrm = d / dist[:, None]
        p = self.eps * np.maximum(self.R - dist, 0.0)
        return nrm, dist, p

    def assemble(self, x, load):
        nrm, dist, p = self._state(x, load)
        f = np.zeros(3 * self.n)
        f[self._dofs] = (-p[:, None] * nrm).ravel()
        act = (p > 0)[:, None, None]
        nn = nrm[:, :, None] * nrm[:, None, :]
        Ke = act * (self.eps[:, None, None] * nn
                    - (p / dist)[:, None, None] * (np.eye(3) - nn))
        K = sp.coo_matrix((Ke.ravel(), (self._rows, self._cols)), shape=(3 * self.n, 3 * self.n))
        return f, K

    def energy(self, x, load):
        _, dist, p = self._state(x, load)
        return float(0.5 * np.sum(p * np.maximum(self.R - dist, 0.0)))

    def force_z(self, x, load) -> float:
        """Force on the sphere along +z (mN), this wedge only."""
        nrm, _, p = self._state(x, load)
        return float(-np.sum(p * nrm[:, 2]))


def forward_curve(site: Site, C10: float, C20: float, ratio: float, values,
                  opt: MeshOptions = MeshOptions()) -> np.ndarray:
    """The model's curve at the measured abscissae `values` (increasing, > 0): apex height (mm)
    at suctions (kPa) for aspiration, force (mN) at depths (mm) for indentation."""
    values = np.asarray(values, dtype=float)
    if site.test == "indentation":
        site = replace(site, max_depth_mm=float(values.max()))
    sm = slab_mesh(site, opt)
    mesh = sm.mesh
    nr, nz = len(sm.radii), len(sm.z)
    body = SolidBody(mesh, _materials(C10, C20, ratio))
    i_all = np.arange(nr)
    top_cells = np.nonzero(np.isin(mesh.hexes[:, 4], sm.node(0, i_all, nz - 1)))[0]
    apex = int(sm.node(0, 0, nz - 1))
    ra = 0.5 * site.aperture_mm
    if site.test == "aspiration":
        rc = sm.radii[1:][:len(top_cells)]                  # outer radius of each top cell
        rim = np.nonzero((sm.radii >= ra - 1e-9) & (sm.radii <= ra + site.rim_mm + 1e-9))[0]
        held = sm.node(np.arange(2)[:, None], rim[None, :], nz - 1).ravel()
        inside = top_cells[np.nonzero(rc <= ra + 1e-9)[0]]
        facets = mesh.hexes[inside][:, [4, 5, 6, 7]]
        cons = _symmetry(sm, held)
    else:
        cons = _symmetry(sm, np.zeros(0, dtype=np.int64))
        facets = mesh.hexes[top_cells][:, [4, 5, 6, 7]]
    out = np.empty(len(values))
    x = None
    prev = 0.0
    top = sm.z[-1]
    h_axis = sm.radii[1]
    for j, v in enumerate(values):
        lo, hi = prev, float(v)
        if site.test == "aspiration":
            # suction pulls the skin outwards: a negative pressure in the solver's convention
            terms = [FollowerPressure(facets, lambda t, lo=lo, hi=hi: -(lo + t * (hi - lo)),
                                      mesh.n_nodes)]
        else:
            R = site.indenter_radius_mm
            stiff = 6.0 * C10 * max(ratio, 1.0)
            centre = (lambda t, lo=lo, hi=hi:
                      np.array([0.0, 0.0, top + R - (lo + t * (hi - lo))]))
            contact = SphereContact(mesh.nodes, facets, R, centre, penalty=50.0 * stiff / h_axis)
            terms = [contact]
        try:
            res = newton_solve(body, cons, terms, steps=1 if j else 2, x0=x, max_iterations=20, stall_iterations=8,
                               rtol=1e-7, max_increment=0.25 * site.thickness)
        except SolveFailed as exc:
            raise ForwardError(f"{site.test} at {v:g}: {exc}") from None
        x = res.x
        if site.test == "aspiration":
            out[j] = x[apex, 2] - top
        else:
            out[j] = contact.force_z(x, 1.0) * (2.0 * np.pi / sm.wedge)
        prev = hi
    return out
