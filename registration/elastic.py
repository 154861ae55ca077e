"""Joint elastic registration of the generic skin and bone-attachment surfaces onto the patient.

Coarse-to-fine non-rigid ICP driving a multilevel B-spline FFD (see `registration.ffd`): at each
level (lattice spacing h) and iteration, correspondences are formed
  * skin, forward: every generic skin node -> its closest point on the patient skin;
  * skin, reverse: samples of the patient skin -> their closest point on the current generic
    skin surface (this pulls the mesh into features the forward pairs would skip);
  * bone: every node attached to a bone segment -> its closest point on that segment's surface;
  * landmarks (optional): landmark nodes -> the patient's landmarks, with a small weight;
and pairs are rejected when the closest point lies on an open border of the other surface (a
hole, the edge of a partial scan, the border of the generic face mask), when the normals
disagree by more than 60 degrees, or when the distance is an outlier: beyond the median by
four robust standard deviations, more than 1 mm and, with landmarks given, more than half the
level's lattice spacing h (a mismatch the level's lattice can follow is then shape, not an
outlier). The FFD fitted to the surviving pairs
moves every node of the volume mesh; composing the per-iteration diffeomorphic FFDs gives the
smooth, fold-free volumetric transform of the Mesh-Match step (Couteau et al., "Finite element
mesh generation by a mesh-matching method", Comput. Methods Programs Biomed. 63, 2000; Bucki,
Lobos and Payan, "A fast and robust patient specific finite element mesh registration
technique", Med. Image Anal. 14, 2010). A final *snap* projects the skin and attached nodes
exactly onto their surfaces and spreads that small correction into the volume by harmonic
extension over the mesh graph.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from registration.ffd import BSplineLattice, FFDFit
from registration.surface import TargetSurface

COS_NORMAL = np.cos(np.radians(60.0))


@dataclass
class SurfaceGroup:
    """Mesh nodes to bring onto a patient surface."""

    name: str
    node_ids: np.ndarray
    target: TargetSurface
    weight: float = 1.0
    tris: np.ndarray | None = None  # mesh triangles (node ids) giving the nodes' normals
    facing: float = 1.0  # +1: mesh normal along the target's outward normal, -1: against it

    def accept(self, x: np.ndarray, cl) -> np.ndarray:
        """Pairs kept: closest point not on an open border, normals compatible (if known)."""
        ok = ~cl.on_boundary
        if self.tris is not None and len(self.tris):
            n = vertex_normals(x, self.tris)[self.node_ids]
            has = np.linalg.norm(n, axis=1) > 0.5
            agree = self.facing * np.einsum("ij,ij->i", n, cl.normal) > COS_NORMAL
            ok &= agree | ~has
        return ok


@dataclass
class ElasticSchedule:
    spacings: tuple[float, ...] = (40.0, 20.0, 10.0, 5.0)  # lattice spacing per level, mm
    iterations: tuple[int, ...] = (4, 4, 4, 2)  # correspondence updates per level
    smoothness: tuple[float, ...] = (5.0, 2.0, 1.0, 0.5)  # bending weight per level
    reverse_samples: int = 6000
    landmark_weight: float = 0.5
    # no pair closer than this fraction of the level's lattice spacing is an outlier
    # (`_outlier_gate`); 0: the robust statistics alone. Meant for landmarks given with the
    # case: they hold the features, so a pair left far off is a difference of shape. Without
    # them a far pair may as well be a feature slid onto another along a smooth profile (the
    # lips onto the labiomental fold), and following it misplaces the face.
    shape_floor: float = 0.5


@dataclass
class ElasticLog:
    levels: list = field(default_factory=list)


def vertex_normals(x: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (n, 3) of a triangulation given by node ids (zeros off it)."""
    t = x[tris]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    vn = np.zeros_like(x)
    for k in range(3):
        np.add.at(vn, tris[:, k], fn)
    norm = np.linalg.norm(vn, axis=1)
    return vn / np.maximum(norm, 1e-300)[:, None]


def _outlier_gate(dist: np.ndarray, spacing: float, floor: float = 0.0) -> float:
    """Distances above median + 4 robust sigmas (1.4826 MAD) are outliers, but never those
    below 1 mm nor below `floor` times the lattice spacing.

    The statistical gate alone tightens to about 1 mm once most of the face fits, and would
    leave a larger local difference of shape (a deeper nasion, a longer ramus: anatomy other
    than the generic face's) out of every later level. The snap reaches only a few mm, so such
    nodes would stay far off the surface, or be snapped piecewise and invert the elements
    between. A mismatch of up to half the spacing is one the level's B-spline lattice can
    follow smoothly (a control point moves a region of about the spacing); a larger one is left
    to the coarser levels, whose floor is larger. `floor` is ElasticSchedule.shape_floor."""
    if len(dist) == 0:
        return np.inf
    med = float(np.median(dist))
    mad = float(np.median(np.abs(dist - med)))
    return max(med + 4.0 * 1.4826 * mad, 1.0, floor * spacing)


def _correspondences(x, skin: SurfaceGroup, skin_tris, bones, landmarks, samples, spacing, sched):
    pts, res, wts, stats = [], [], [], {}
    normals = vertex_normals(x, skin_tris)
    # skin forward
    ids = skin.node_ids
    cl = skin.target.closest(x[ids])
    ok = ~cl.on_boundary & (np.einsum("ij,ij->i", normals[ids], cl.normal) > COS_NORMAL)
    ok &= cl.distance <= _outlier_gate(cl.distance[ok], spacing, sched.shape_floor)
    n_f = max(int(ok.sum()), 1)
    pts.append(x[ids][ok]); res.append(cl.points[ok] - x[ids][ok]); wts.append(np.full(ok.sum(), skin.weight / n_f))
    stats["skin_forward_mean_mm"] = float(cl.distance[ok].mean()) if ok.any() else np.nan
    stats["skin_forward_used"] = int(ok.sum())
    # skin reverse: patient samples -> current generic skin
    mesh_surface = TargetSurface(x[np.unique(skin_tris)], _reindex(skin_tris), "generic skin")
    rc = mesh_surface.closest(samples.points)
    ok_r = ~rc.on_boundary & (np.einsum("ij,ij->i", rc.normal, samples.normal) > COS_NORMAL)
    ok_r &= rc.distance <= _outlier_gate(rc.distance[ok_r], spacing, sched.shape_floor)
    n_r = max(int(ok_r.sum()), 1)
    pts.append(rc.points[ok_r]); res.append(samples.points[ok_r] - rc.points[ok_r])
    wts.append(np.full(ok_r.sum(), skin.weight / n_r))
    stats["skin_reverse_mean_mm"] = float(rc.distance[ok_r].mean()) if ok_r.any() else np.nan
    # bones
    for g in bones:
        cb = g.target.closest(x[g.node_ids])
        okb = g.accept(x, cb)
        okb &= cb.distance <= _outlier_gate(cb.distance[okb], spacing, sched.shape_floor)
        n_b = max(int(okb.sum()), 1)
        pts.append(x[g.node_ids][okb]); res.append(cb.points[okb] - x[g.node_ids][okb])
        wts.append(np.full(okb.sum(), g.weight / n_b))
        stats[f"bone_{g.name}_mean_mm"] = float(cb.distance[okb].mean()) if okb.any() else np.nan
    if landmarks is not None:
        lid, lpos = landmarks
        pts.append(x[lid]); res.append(lpos - x[lid])
        wts.append(np.full(len(lid), sched.landmark_weight / max(len(lid), 1)))
    return np.concatenate(pts), np.concatenate(res), np.concatenate(wts), stats


def _reindex(tris: np.ndarray) -> np.ndarray:
    used, inv = np.unique(tris, return_inverse=True)
    return inv.reshape(tris.shape)


@dataclass(frozen=True)
class _Samples:
    points: np.ndarray
    normal: np.ndarray


def elastic_register(nodes: np.ndarray, skin: SurfaceGroup, skin_tris: np.ndarray,
                     bones: list[SurfaceGroup], landmarks=None,
                     schedule: ElasticSchedule | None = None, seed: int = 0):
    """Move all nodes by a composed multilevel FFD; returns (new nodes, per-level log)."""
    sched = schedule or ElasticSchedule()
    x = np.array(nodes, dtype=float)
    n_s = min(sched.reverse_samples, max(len(skin.node_ids) * 2, 500))
    rng = np.random.default_rng(seed)
    face = rng.choice(len(skin.target.faces), size=n_s, p=skin.target.face_areas / skin.target.area)
    r1, r2 = rng.random(n_s), rng.random(n_s)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    samples = _Samples(np.einsum("ni,nid->nd", w, skin.target.vertices[skin.target.faces[face]]),
                       skin.target.face_normals[face])
    log = ElasticLog()
    for level, h in enumerate(sched.spacings):
        lam = sched.smoothness[min(level, len(sched.smoothness) - 1)]
        ffd = FFDFit(BSplineLattice.covering(x, h), x, lam)
        for it in range(sched.iterations[min(level, len(sched.iterations) - 1)]):
            p, r, wt, stats = _correspondences(x, skin, skin_tris, bones, landmarks, samples, h, sched)
            c = ffd.fit(p, r, wt)
            x = x + ffd.evaluate(c, x)
            stats.update(level=level, spacing_mm=h, iteration=it)
            log.levels.append(stats)
    return x, log


def mesh_laplacian(n_nodes: int, hexes: np.ndarray, x: np.ndarray | None = None) -> sp.csr_matrix:
    """Graph Laplacian over the 12 edges of every hexahedron: unit weights, or 1/|edge|^2 for
    node positions `x` (the finite-difference weights: a thin layer then follows its faces)."""
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                      [0, 4], [1, 5], [2, 6], [3, 7]])
    e = np.asarray(hexes)[:, edges].reshape(-1, 2)
    e = np.unique(np.sort(e, axis=1), axis=0)
    w = np.ones(len(e))
    if x is not None:
        w = 1.0 / np.maximum(np.sum((x[e[:, 0]] - x[e[:, 1]]) ** 2, axis=1), 1e-12)
    a = sp.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(n_nodes, n_nodes))
    a = (a + a.T).tocsr()
    return (sp.diags(np.asarray(a.sum(axis=1)).ravel()) - a).tocsr()


def harmonic_extension(n_nodes: int, hexes: np.ndarray, fixed: np.ndarray,
                       fixed_values: np.ndarray, laplacian: sp.csr_matrix | None = None) -> np.ndarray:
    """Displacement (n, 3) equal to fixed_values on `fixed` nodes and harmonic elsewhere."""
    lap = mesh_laplacian(n_nodes, hexes) if laplacian is None else laplacian
    u = np.zeros((n_nodes, 3))
    u[fixed] = fixed_values
    free = np.setdiff1d(np.arange(n_nodes), fixed)
    if len(free) == 0:
        return u
    lff = lap[free][:, free].tocsc()
    lfc = lap[free][:, fixed]
    # nodes in components with no fixed node keep the Laplacian singular; a tiny ridge pins them
    lff = lff + 1e-9 * sp.identity(len(free), format="csc")
    u[free] = splu(lff).solve(-(lfc @ u[fixed]))
    return u


def snap_to_surfaces(x: np.ndarray, hexes: np.ndarray, skin: SurfaceGroup, skin_tris: np.ndarray,
                     bones: list[SurfaceGroup], max_snap: float = 3.0,
                     laplacian: sp.csr_matrix | None = None):
    """Project skin and attached nodes onto their surfaces; harmonic spread into the volume.

    Returns (new nodes, ids of snapped nodes per group as dict). Nodes whose projection is on an
    open border of the patient surface, disagrees in normal, or is farther than `max_snap` are
    left to the harmonic extension."""
    fixed_ids, fixed_vals, snapped = [], [], {}
    normals = vertex_normals(x, skin_tris)
    cl = skin.target.closest(x[skin.node_ids])
    ok = (~cl.on_boundary & (cl.distance <= max_snap)
          & (np.einsum("ij,ij->i", normals[skin.node_ids], cl.normal) > COS_NORMAL))
    fixed_ids.append(skin.node_ids[ok]); fixed_vals.append(cl.points[ok] - x[skin.node_ids[ok]])
    snapped["skin"] = skin.node_ids[ok]
    for g in bones:
        cb = g.target.closest(x[g.node_ids])
        okb = g.accept(x, cb) & (cb.distance <= max_snap)
        fixed_ids.append(g.node_ids[okb]); fixed_vals.append(cb.points[okb] - x[g.node_ids[okb]])
        snapped[g.name] = g.node_ids[okb]
    ids = np.concatenate(fixed_ids)
    vals = np.concatenate(fixed_vals)
    ids, first = np.unique(ids, return_index=True)  # a node on skin and bone keeps the skin value
    u = harmonic_extension(len(x), hexes, ids, vals[first], laplacian)
    return x + u, snapped
