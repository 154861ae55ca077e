"""Post-op scans with a known withheld effect, made on a model that is not the diagnosed one.

For checking the diagnosis where `faceplan synth` cannot write post-op scans: the prepared case
is perturbed the way issue 19 prescribes for synthetic truths (every tissue's moduli scaled by
an independent factor within +-`modulus_pct`, the bulk-to-shear ratio redrawn, and the soft
tissue's thickness changed by moving every node that is neither on the skin nor on a bone by a
smooth random field of amplitude `thickness_mm`), the effect is added, and the predicted skin
is made to look like a scan: subdivided to ~`edge_mm` triangles, only the front of the face
kept, Gaussian noise along the normals (sigma `noise_mm`) and a random rigid offset (at most
`offset_mm` and `offset_deg`) that the diagnosis's superimposition must undo.
"""
from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["perturbed_case", "scan_like"]


def perturbed_case(case, seed: int, modulus_pct: float = 15.0, thickness_pct: float = 20.0):
    """A copy of a `forward.CaseModel` with perturbed moduli and tissue thickness."""
    from facemodel import materials as fm

    rng = np.random.default_rng(seed)
    model = case.model
    overrides = {}
    for label in model.label_names:
        p = fm.parameters(label)
        f = 1.0 + rng.uniform(-modulus_pct, modulus_pct) / 100.0
        o = {k: float(p[k] * f) for k in ("C10", "C20") if k in p}
        if "K" in p and "C10" in p:
            o["K"] = float(2.0 * o["C10"] * rng.uniform(500.0, 2000.0))   # K / mu, mu = 2 C10
        overrides[label] = o
    x = np.asarray(model.nodes, float).copy()
    fixed = np.zeros(len(x), bool)
    fixed[np.asarray(case.skin_ids)] = True
    for name, ids in model.node_sets.items():
        if name.startswith("attach_") or name in ("deep_free", "border"):
            fixed[np.asarray(ids, int)] = True
    for quads in model.facet_sets.values():          # skin, lip and mucosa contact surfaces
        fixed[np.asarray(quads, int).ravel()] = True
    # layer thickness: every inner node's depth below its nearest skin node scaled by a smooth
    # random factor 1 + a(x), |a| <= thickness_pct (the deep surfaces stay on the bone)
    from scipy.spatial import cKDTree

    skin = x[np.asarray(case.skin_ids)]
    _, near = cKDTree(skin).query(x)
    k = rng.normal(size=(2, 3)) / 30.0              # wavelengths ~ 50-200 mm
    phase = rng.uniform(0, 2 * np.pi, 2)
    a = np.sin(x @ k[0] + phase[0]) + 0.5 * np.sin(x @ k[1] + phase[1])
    a *= thickness_pct / 100.0 / max(np.abs(a).max(), 1e-12)
    depth = x - skin[near]
    x0 = x.copy()
    x[~fixed] = skin[near][~fixed] + depth[~fixed] * (1.0 + a[~fixed, None])
    # thin elements (lips, nostrils) whose nodes see different nearest skin nodes may fold:
    # those nodes keep their place
    from planner.report import corner_jacobians, gauss_jacobians

    hexes = np.asarray(model.hexes)
    gauss_floor = 0.3 * gauss_jacobians(x0, hexes).min(axis=1)
    corner_floor = 0.3 * np.maximum(corner_jacobians(x0, hexes).min(axis=1), 0.0)
    for _ in range(20):
        bad = ((gauss_jacobians(x, hexes).min(axis=1) <= gauss_floor)
               | (corner_jacobians(x, hexes).min(axis=1) <= corner_floor))
        if not bad.any():
            break
        nodes = np.unique(hexes[bad])
        x[nodes] = x0[nodes]
    plan = case.plan
    plan = dataclasses.replace(plan, model=dataclasses.replace(plan.model, materials=overrides))
    return dataclasses.replace(case, model=dataclasses.replace(model, nodes=x), plan=plan)


def scan_like(skin: np.ndarray, faces: np.ndarray, seed: int, edge_mm: float = 2.0, noise_mm: float = 0.2,
              offset_mm: float = 2.0, offset_deg: float = 2.0, front_only: bool = True):
    """(vertices, faces) of a scan-like copy of the surface (see the module text)."""
    import trimesh
    import trimesh.remesh

    from planner.compare.alignment import rotation_matrix

    rng = np.random.default_rng(seed)
    v, f = trimesh.remesh.subdivide_to_size(np.asarray(skin, float), np.asarray(faces), max_edge=edge_mm,
                                            max_iter=10)
    mesh = trimesh.Trimesh(v, f, process=True)
    if front_only:            # a frontal scanner sees what faces forwards
        keep = mesh.face_normals[:, 1] > 0.05
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=True)
        mesh.remove_unreferenced_vertices()
    v = np.asarray(mesh.vertices, float) + rng.normal(0.0, noise_mm, len(mesh.vertices))[:, None] * mesh.vertex_normals
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R = rotation_matrix(axis * np.radians(rng.uniform(0, offset_deg)))
    t = rng.normal(size=3)
    t *= rng.uniform(0, offset_mm) / np.linalg.norm(t)
    c = v.mean(axis=0)
    v = (v - c) @ R.T + c + t
    return v, np.asarray(mesh.faces)
