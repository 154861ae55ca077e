"""Teeth on the registered face: each arch with its bone segment, and the lips cleared of them.

Placement: the teeth are rigid parts of their bone segment ("upper" -> maxilla, "lower" ->
mandible), so each arch is moved by the least-squares similarity (Umeyama, IEEE PAMI 13, 1991)
that maps its segment's attachment nodes from their generic to their registered positions --
not by the global alignment, which ignores how each jaw of the patient sits (class II / III).
A jaw whose shape differs from the generic one (another anatomy: a wider ramus, a longer
body) maps by no single similarity: the segment's fit, dominated by its far parts, can then
put the arch through the face. The skin bounds the mouth, and no stage after this one may
move it, so an arch reaching within the teeth clearance of a registered skin node is placed
instead by the similarity of the attachment nodes near it (Gaussian weights exp(-(d/LOCAL_MM)^2),
d the generic node's distance to the generic arch: the alveolar bone that carries the teeth),
the placement that keeps it farther inside the skin kept (`info[arch]["placement"]`).
When the patient's own teeth surfaces are given (e.g. from an intra-oral or CT scan) they are
used as they are.

Clearance: the soft tissue registered onto skin and bone knows nothing of the teeth, so after
Mesh-Match-and-Repair some deep lip nodes can lie inside an arch, and a contact solve cannot
start from there. Every movable node (not on the skin, not attached to a bone) whose signed
distance to the arches (positive outside: exact closest point on the triangles, the sign from
the angle-weighted pseudonormal of the face, edge or vertex holding it, Baerentzen and Aanaes,
IEEE TVCG 11, 2005) is below the clearance is moved to the nearest point `clearance` outside
them in the half-space facing away from the dental arch: for a node in a lip, whose tissue lies
labial / buccal to the teeth, that is the push along the outward normal of the labial face, and
a node caught where the crowns of the two arches meet (occlusion: opposed normals, a gap
thinner than twice the clearance) leaves the gap labially instead of bouncing between them
(rays over a hemisphere, sampled then bisected); the displacement of these held nodes is spread into the surrounding
tissue by harmonic extension over the mesh graph with skin and attached nodes fixed (the snap
of `registration.elastic`), and the elements this leaves below the scaled-Jacobian threshold
are repaired by `registration.repair` with skin and attached nodes fixed. Rounds repeat until
no movable node is closer than the clearance (a node the repair takes back towards a tooth is
pushed again), or until rounds stop bringing the deepest node nearer it (tissue between the
fixed skin and an arch too thin for the clearance).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from registration.alignment import Similarity, umeyama
from registration.elastic import harmonic_extension, mesh_laplacian
from registration.errors import RegistrationInputError
from registration.quality import min_scaled_jacobian
from registration.repair import repair_mesh
from registration.surface import TargetSurface

ARCH_SEGMENT = {"upper": "maxilla", "lower": "mandible"}
# length scale (mm) of the local placement's weights: about an incisor's root plus the
# alveolar bone around it, so that the jaw's far parts (ramus, angle) do not steer the arch
LOCAL_MM = 10.0


@dataclass
class Arch:
    """One set of teeth: its surface (patient frame) and its bone segment."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    segment: str

    def __post_init__(self):
        import trimesh

        self.vertices = np.asarray(self.vertices, dtype=float)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        self.surface = TargetSurface(self.vertices, self.faces, f"teeth.{self.name}")
        self.closed = bool(trimesh.Trimesh(self.vertices, self.faces, process=False).is_watertight)
        self.bounds = np.array([self.vertices.min(0), self.vertices.max(0)])
        # angle-weighted pseudonormals of faces, edges and vertices (Baerentzen and Aanaes,
        # IEEE TVCG 11, 2005): the sign of (p - q) . n at the closest point q is exact for a
        # closed manifold surface whichever feature (face, edge, vertex) q lies on
        fn = self.surface.face_normals
        tri = self.vertices[self.faces]
        angles = np.empty((len(self.faces), 3))
        for c in range(3):
            u = tri[:, (c + 1) % 3] - tri[:, c]
            w = tri[:, (c + 2) % 3] - tri[:, c]
            cosang = np.einsum("ij,ij->i", u, w) / np.maximum(
                np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300)
            angles[:, c] = np.arccos(np.clip(cosang, -1.0, 1.0))
        vn = np.zeros_like(self.vertices)
        np.add.at(vn, self.faces, angles[:, :, None] * fn[:, None, :])
        self._vertex_normals = vn
        # edge c of a face is the one opposite its corner c
        ends = np.stack([self.faces[:, [1, 2]], self.faces[:, [2, 0]], self.faces[:, [0, 1]]], axis=1)
        keys = np.sort(ends, axis=2).reshape(-1, 2)
        _, inverse = np.unique(keys, axis=0, return_inverse=True)
        inverse = inverse.ravel()
        en = np.zeros((inverse.max() + 1, 3))
        np.add.at(en, inverse, np.repeat(fn, 3, axis=0))
        self._edge_normals = en[inverse].reshape(len(self.faces), 3, 3)

    def signed_distance(self, points: np.ndarray):
        """(signed distance (n,) positive outside, closest points (n, 3), outward unit
        directions (n, 3) from the closest point towards the outside)."""
        p = np.asarray(points, float).reshape(-1, 3)
        cl = self.surface.closest(p)
        zero = cl.bary <= 1e-12
        nz = zero.sum(axis=1)
        n = self.surface.face_normals[cl.face].copy()
        on_edge = np.flatnonzero(nz == 1)
        if len(on_edge):
            c = np.argmax(zero[on_edge], axis=1)
            n[on_edge] = self._edge_normals[cl.face[on_edge], c]
        on_vertex = np.flatnonzero(nz == 2)
        if len(on_vertex):
            c = np.argmax(~zero[on_vertex], axis=1)
            n[on_vertex] = self._vertex_normals[self.faces[cl.face[on_vertex], c]]
        d = p - cl.points
        inside = np.einsum("ij,ij->i", d, n) < 0.0
        sd = np.where(inside, -cl.distance, cl.distance)
        norm = np.linalg.norm(d, axis=1)
        direction = np.where(norm[:, None] > 1e-9, d / np.maximum(norm, 1e-300)[:, None], cl.normal)
        direction[inside & (norm > 1e-9)] *= -1.0
        return sd, cl.points, direction

    def near(self, points: np.ndarray, margin: float) -> np.ndarray:
        return np.all((points > self.bounds[0] - margin) & (points < self.bounds[1] + margin), axis=1)


def teeth_arrays(surface, name: str):
    """(vertices, faces, segment or None) from a trimesh, a (v, f[, segment]) tuple or a
    TargetSurface."""
    seg = None
    if isinstance(surface, TargetSurface):
        v, f = surface.vertices, surface.faces
    elif isinstance(surface, (tuple, list)) and len(surface) in (2, 3):
        v, f = surface[0], surface[1]
        seg = surface[2] if len(surface) == 3 else None
    elif hasattr(surface, "vertices") and hasattr(surface, "faces"):
        v, f = surface.vertices, surface.faces
    else:
        raise RegistrationInputError(f"teeth {name}: expected a triangle surface, got "
                                     f"{type(surface).__name__}", field=f"teeth.{name}")
    v = np.asarray(v, dtype=float)
    f = np.asarray(f, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 \
            or not np.all(np.isfinite(v)) or f.min() < 0 or f.max() >= len(v):
        raise RegistrationInputError(f"teeth {name}: not a valid triangle surface", field=f"teeth.{name}")
    return v, f, seg


def _skin_margin(v, f, skin) -> float:
    """Smallest signed distance (mm, positive outside the arch) of the skin nodes to the arch
    (v, f); inf without skin near it."""
    return float(union_distance([Arch("arch", v, f, "")], skin, 5.0)[0].min())


def _alveolar_similarity(v, ids, generic_nodes, registered_nodes):
    """The similarity of the attachment nodes `ids` weighted by their nearness to the generic
    arch v (exp(-(d/LOCAL_MM)^2)); None when none of them is near it."""
    from scipy.spatial import cKDTree

    w = np.exp(-(cKDTree(v).query(generic_nodes[ids])[0] / LOCAL_MM) ** 2)
    if w.sum() <= 1e-6 * len(w):
        return None
    return umeyama(generic_nodes[ids], registered_nodes[ids], weights=w)


def place_teeth(generic_teeth: dict, attach: dict, generic_nodes: np.ndarray,
                registered_nodes: np.ndarray, fallback: Similarity,
                patient_teeth: dict | None = None, skin_ids=None,
                clearance: float = 0.25) -> tuple[dict, dict]:
    """Arches in the patient frame and how each was placed.

    generic_teeth: name -> (vertices, faces, segment) in the generic frame; attach: segment ->
    attached node ids; patient_teeth: name -> the patient's own surface (used as given);
    skin_ids: the registered skin's node ids: an arch placed by its segment's similarity that
    reaches within `clearance` of them is placed by the local similarity instead where that
    keeps it farther from the skin (module docstring). Returns ({name: (vertices, faces,
    segment)}, {name: info})."""
    patient_teeth = patient_teeth or {}
    unknown = sorted(set(patient_teeth) - set(generic_teeth) - set(ARCH_SEGMENT))
    if unknown:
        raise RegistrationInputError(
            f"teeth: unknown arch name(s) {', '.join(unknown)}; expected "
            f"{', '.join(sorted(set(generic_teeth) | set(ARCH_SEGMENT)))}", field="teeth")
    out, info = {}, {}
    for name in sorted(set(generic_teeth) | set(patient_teeth)):
        gen = generic_teeth.get(name)
        seg = (gen[2] if gen is not None else None) or ARCH_SEGMENT.get(name)
        if name in patient_teeth:
            v, f, pseg = teeth_arrays(patient_teeth[name], name)
            seg = pseg or seg
            out[name] = (v, f, seg)
            info[name] = {"source": "patient", "segment": seg}
            continue
        v, f = np.asarray(gen[0], float), np.asarray(gen[1], np.int64)
        ids = np.asarray(attach.get(seg, []), dtype=np.int64)
        if len(ids) >= 4:
            tf = umeyama(generic_nodes[ids], registered_nodes[ids])
            res = tf.apply(generic_nodes[ids]) - registered_nodes[ids]
            info[name] = {"source": "segment", "segment": seg, "attachment_nodes": int(len(ids)),
                          "fit_rms_mm": float(np.sqrt(np.mean(np.sum(res**2, axis=1))))}
        else:
            tf = fallback
            info[name] = {"source": "global alignment", "segment": seg,
                          "attachment_nodes": int(len(ids))}
        placed = tf.apply(v)
        if len(ids) >= 4 and skin_ids is not None and len(skin_ids):
            skin = registered_nodes[np.asarray(skin_ids, np.int64)]
            margin = _skin_margin(placed, f, skin)
            info[name].update(placement="segment", skin_margin_mm=round(margin, 4))
            local = _alveolar_similarity(v, ids, generic_nodes, registered_nodes) if margin < clearance else None
            m_local = -np.inf if local is None else _skin_margin(local.apply(v), f, skin)
            if m_local > margin:
                tf, placed = local, local.apply(v)
                info[name].update(placement="local", skin_margin_mm=round(m_local, 4),
                                  segment_skin_margin_mm=round(margin, 4))
        info[name].update(scale=float(tf.scale), matrix=tf.matrix.tolist())
        out[name] = (placed, f, seg)
    return out, info


def union_distance(arches: list[Arch], points: np.ndarray, margin: float):
    """The smallest signed distance (n,) over all arches (inf for points farther than
    `margin` from every arch's bounding box) and the index (n,) of the arch giving it."""
    p = np.asarray(points, float).reshape(-1, 3)
    sd = np.full((max(len(arches), 1), len(p)), np.inf)
    for a, arch in enumerate(arches):
        sel = np.flatnonzero(arch.near(p, margin))
        if len(sel):
            sd[a, sel] = arch.signed_distance(p[sel])[0]
    best = np.argmin(sd, axis=0)
    return sd[best, np.arange(len(p))], best


def _sphere_directions(n: int) -> np.ndarray:
    """n nearly uniform unit vectors (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z**2)
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def escape_outward(arches: list[Arch], points: np.ndarray, clearance: float, centre: np.ndarray,
                   reach: float = 8.0, step: float = 0.25, n_dirs: int = 64,
                   away: np.ndarray | None = None) -> np.ndarray:
    """For points the normal projection cannot clear (caught between two arches in occlusion,
    where the outward normals of the upper and lower crowns oppose each other): the nearest
    clear point along rays of the half-space that faces away from the dental arch (labial /
    buccal: the lips and cheeks lie outside the arch, away from its centre in the horizontal
    plane), sampled every `step` mm up to `reach` mm. Points with no clear sample are kept.
    `away` (n, 3): optional directions each point must not move against (a lip node held
    clear of the other lip by `registration.lips`: only rays with a non-negative component
    along its lip normal, or any ray where none of those clears within reach)."""
    p = np.array(points, dtype=float).reshape(-1, 3)
    if len(p) == 0:
        return p
    dirs = _sphere_directions(n_dirs)
    t = np.arange(1, int(reach / step) + 1) * step
    radial = p - centre
    radial[:, 2] = 0.0
    radial /= np.maximum(np.linalg.norm(radial, axis=1), 1e-12)[:, None]
    facing = radial @ dirs.T > 0.0                                       # (points, dirs)
    if away is not None:
        facing &= np.asarray(away, float).reshape(-1, 3) @ dirs.T >= 0.0
    # march all facing rays of the unresolved points outwards together: a point is resolved
    # at the first sample distance where one of its rays is clear (the lowest-numbered such
    # ray is taken); most points clear within a few samples, so few are ever evaluated
    idx = np.full(len(p), len(t) - 1)
    k = np.zeros(len(p), dtype=np.int64)
    found = np.zeros(len(p), bool)
    for j, tj in enumerate(t):
        pi, di = np.nonzero(facing & ~found[:, None])
        if len(pi) == 0:
            break
        clear = union_distance(arches, p[pi] + tj * dirs[di], clearance + 2.0)[0] >= clearance
        pi, di = pi[clear], di[clear]
        first_ray = np.unique(pi, return_index=True)[1]  # pairs are ordered by point, then ray
        hit = pi[first_ray]
        k[hit], idx[hit], found[hit] = di[first_ray], j, True
    direction = dirs[k]
    # bisection between the last blocked and the first clear sample of the chosen ray
    hi = t[idx]
    lo = np.where(idx > 0, t[np.maximum(idx - 1, 0)], 0.0)
    for _ in range(10):
        mid = 0.5 * (lo + hi)
        clear = union_distance(arches, p + mid[:, None] * direction, clearance + 2.0)[0] >= clearance
        hi = np.where(clear, mid, hi)
        lo = np.where(clear, lo, mid)
    out = np.where(found[:, None], p + hi[:, None] * direction, p)
    if away is not None and not found.all():
        # no clear ray away from the other lip within reach: the nearest clear point of any ray
        lost = ~found
        out[lost] = escape_outward(arches, p[lost], clearance, centre, reach, step, n_dirs)
    return out


def clear_teeth(x: np.ndarray, hexes: np.ndarray, arches: list[Arch], fixed: np.ndarray, *,
                clearance: float = 0.2, threshold: float = 0.2, max_rounds: int = 8,
                tol: float = 0.01, away: np.ndarray | None = None, reach: float = 20.0,
                stall_rounds: int = 2):
    """Move movable nodes to at least `clearance` mm outside every arch (module docstring).

    `fixed`: nodes that never move (skin, attached); `away` (n, 3): optional per-node
    directions a push must not go against (zero rows: any; the lip-surface nodes, kept from
    moving into the other lip); nodes farther than `reach` mm from the arches' bounding boxes
    are held. The search ends early after `stall_rounds` rounds in a row that do not bring
    the deepest node at least `tol` nearer the clearance: the repair then keeps taking the
    pushes back (tissue between a fixed skin and an arch thinner than the clearance allows),
    and more rounds only spend time; the node's depth left is reported, and the contact start
    of the prediction moves the arch back from it (`facemodel.teeth.clear_teeth`).
    Returns (new nodes, report)."""
    hexes = np.asarray(hexes)
    x = np.array(x, dtype=float)
    n = len(x)
    fixed = np.unique(np.asarray(fixed, dtype=np.int64))
    movable = np.ones(n, bool)
    movable[fixed] = False
    x_start = x.copy()
    lap = mesh_laplacian(n, hexes)
    centre = np.concatenate([a.vertices for a in arches]).mean(axis=0)

    def measure(points_ids):
        return union_distance(arches, x[points_ids], clearance + 1.0)[0]

    # the tissue that follows the pushes: nodes within `reach` mm of an arch's bounding box
    # (the rest is held, so that each round solves a small system)
    far = ~np.any([a.near(x, reach) for a in arches], axis=0)
    all_ids = np.arange(n)
    sd0 = measure(all_ids)
    inside0 = sd0 < 0.0
    held = np.zeros(n, bool)
    rounds, repaired = 0, 0
    best, stalled, shortfalls = np.inf, 0, []
    for rounds in range(1, max_rounds + 1):
        ids = np.flatnonzero(movable)
        sd = measure(ids)
        bad = sd < clearance
        if not bad.any():
            rounds -= 1
            break
        short = float(clearance - sd[bad].min())
        shortfalls.append(short)
        if short < best - tol:
            best, stalled = short, 0
        else:
            stalled += 1
            if stalled >= stall_rounds:
                rounds -= 1
                break
        push_ids = ids[bad]
        # a margin `tol` beyond the clearance, so that the small moves of the repair that
        # follows do not bring a node back below it
        target = escape_outward(arches, x[push_ids], clearance + tol, centre,
                                away=None if away is None else away[push_ids])
        held[push_ids] = True
        # held nodes keep their place (zero displacement) unless pushed again in this round
        dirichlet = np.flatnonzero(held | ~movable | far)
        values = np.zeros((len(dirichlet), 3))
        pos = np.searchsorted(dirichlet, push_ids)
        values[pos] = target - x[push_ids]
        x = x + harmonic_extension(n, hexes, dirichlet, values, lap)
        if min_scaled_jacobian(x, hexes).min() < threshold:
            # held nodes may move in the repair: one it takes back towards a tooth is pushed
            # again in the next round
            x, rep = repair_mesh(x, hexes, threshold=threshold, fixed=fixed)
            repaired += rep["elements_needing_repair"]
    if rounds and min_scaled_jacobian(x, hexes).min() < threshold:
        # the last round's repair fell short (the next round's would have had another go): a
        # wider patch around the elements left, more rounds
        x, rep = repair_mesh(x, hexes, threshold=threshold, fixed=fixed, rings=3, max_rounds=12)
        repaired += rep["elements_needing_repair"]
    sd_end = measure(all_ids)
    moved = np.linalg.norm(x - x_start, axis=1)
    finite = np.isfinite(sd_end)
    report = {
        "clearance_mm": float(clearance),
        "nodes_inside_before": int(inside0.sum()),
        "max_depth_before_mm": float(max(0.0, -sd0[np.isfinite(sd0)].min())) if np.isfinite(sd0).any() else 0.0,
        "nodes_pushed": int(held.sum()),
        "nodes_moved": int((moved > 1e-3).sum()),  # by more than 1 micrometre
        "max_push_mm": float(moved.max()) if n else 0.0,
        "rounds": int(rounds),
        # the deepest node's shortfall from the clearance at the start of each round
        "shortfall_per_round_mm": [round(v, 4) for v in shortfalls],
        "stalled": bool(stalled >= stall_rounds),
        "elements_repaired": int(repaired),
        "min_signed_distance_after_mm": float(sd_end[movable & finite].min()) if (movable & finite).any() else None,
        "min_signed_distance_fixed_nodes_mm": float(sd_end[~movable & finite].min()) if (~movable & finite).any() else None,
        "nodes_inside_after": int((sd_end < 0.0).sum()),
        "arches": {a.name: {"closed": a.closed, "segment": a.segment} for a in arches},
    }
    return x, report
