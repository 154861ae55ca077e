"""The elastic stage follows a local difference of shape larger than its outlier floor.

A block's top face is registered onto a plane with a smooth dent (Gaussian, 12 mm deep, 8 mm
wide), as the generic face's nasal root onto a patient's deeper one. Once the flat part fits,
the robust statistics of the distances alone would call the dent's pairs outliers (about 1 mm)
and leave the dent out of every finer level; a mismatch the level's lattice can follow is
kept (`ElasticSchedule.shape_floor`, with landmarks given), so the top face reaches the
dent's bottom.
"""
import numpy as np

from registration.elastic import ElasticSchedule, SurfaceGroup, elastic_register
from registration.surface import TargetSurface

DEPTH, WIDTH = 12.0, 8.0


def _dent(x, y):
    return -DEPTH * np.exp(-((x - 50.0) ** 2 + (y - 50.0) ** 2) / (2.0 * WIDTH ** 2))


def _block(h=5.0):
    xs = np.arange(0.0, 100.0 + h / 2, h)
    zs = np.arange(-20.0, 0.0 + h / 2, h)
    n = len(xs)
    X, Y, Z = np.meshgrid(xs, xs, zs, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange(len(nodes)).reshape(n, n, len(zs))
    hexes = [[idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
              idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1]]
             for i in range(n - 1) for j in range(n - 1) for k in range(len(zs) - 1)]
    top = idx[:, :, -1]
    tris = np.concatenate([np.stack([top[:-1, :-1].ravel(), top[1:, :-1].ravel(), top[1:, 1:].ravel()], 1),
                           np.stack([top[:-1, :-1].ravel(), top[1:, 1:].ravel(), top[:-1, 1:].ravel()], 1)])
    return nodes, np.asarray(hexes), top.ravel(), tris


def _target():
    g = np.arange(-20.0, 120.5, 1.0)
    X, Y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([X.ravel(), Y.ravel(), _dent(X, Y).ravel()], axis=1)
    n = len(g)
    i = np.arange(n * n).reshape(n, n)
    f = np.concatenate([np.stack([i[:-1, :-1].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()], 1),
                        np.stack([i[:-1, :-1].ravel(), i[1:, 1:].ravel(), i[:-1, 1:].ravel()], 1)])
    return TargetSurface(v, f, "dented plane")


def test_a_dent_beyond_the_statistical_outlier_gate_is_followed():
    nodes, hexes, top, tris = _block()
    target = _target()
    # the mesh triangles wound as the target's (whichever way it called outward): normals agree
    mesh_up = np.cross(nodes[tris[0, 1]] - nodes[tris[0, 0]], nodes[tris[0, 2]] - nodes[tris[0, 0]])[2] > 0
    target_up = np.median(target.face_normals[:, 2]) > 0
    if mesh_up != target_up:
        tris = tris[:, ::-1]
    skin = SurfaceGroup("skin", top, target, weight=1.0, tris=tris, facing=1.0)
    x, log = elastic_register(nodes, skin, tris, [], None, ElasticSchedule(), seed=0)
    d = target.closest(x[top]).distance
    # before: the top node over the dent's bottom is DEPTH below it, nearer to its walls
    assert target.closest(nodes[top]).distance.max() > 0.8 * DEPTH
    # after: every top node within 1 mm of the dented plane, well inside the snap's reach
    # (max_snap_mm 5); the lattice's smoothness leaves a few tenths of a mm at the dent's
    # sharpest curvature. With the statistical gate alone the dent's bottom stays about 5 mm
    # off: the coarse levels (40 and 20 mm lattices) cannot follow an 8 mm wide dent, and the
    # finer ones dropped its pairs as outliers
    assert d.max() < 1.0, d.max()
    assert np.median(d) < 0.2
    # the dent's pairs took part in the last level: no node of the dent was left out as an
    # outlier while the rest fitted
    assert log.levels[-1]["skin_forward_used"] == len(top)
    # the robust statistics alone (`shape_floor=0`, a registration without landmarks, where
    # a far pair may be a feature slid onto another): the dent's pairs are dropped and its
    # bottom stays beyond 4 mm
    x0, _ = elastic_register(nodes, skin, tris, [], None, ElasticSchedule(shape_floor=0.0), seed=0)
    assert target.closest(x0[top]).distance.max() > 4.0
