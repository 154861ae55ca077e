"""Attachments that depend on the operation: the tissue a genioplasty degloves slides on bone,
the tissue over every osteotomy the plan opens bridges it, tied to neither segment
(`osteotomy_bridges`, `attachment_sets`), and a sagittal split leaves the tissue on the
mandible's proximal segments (ramus, angle) with the skull (`attachment_sets`' `proximal`).

An intra-oral sliding genioplasty is reached through a vestibular incision in the lower labial
sulcus; the periosteum and the mentalis are stripped (subperiosteal degloving) from the
anterior mandible between the vestibule fornix and the osteotomy, between the mental nerves,
along the cut out to the lower border, and over the anterior face of the chin segment, while
the chin segment keeps its soft-tissue pedicle on its inferior border and lingual side
(mentalis re-suspended, digastric and geniohyoid left on the segment) (Trauner R., Obwegeser
H., Oral Surg Oral Med Oral Pathol 10:677-689, 1957; Hoenig J.F., Aesthetic Plast Surg
31:384-391, 2007; Reyneke J.P., Essentials of Orthognathic Surgery, 2nd ed., 2010; Posnick
J.C., Orthognathic Surgery: Principles and Practice, 2014).
At closure the degloved tissue lies on the bone again: it is neither tied to it nor free in
space, it stays on the bone surface and slides on it. `genioplasty_sliding` lists, for a plan
that moves the chin on the mandible, the deep nodes that slide on each bone:

- mandible: the generic face's node set "release_genioplasty" (anterior mandible between the
  fornix and the cut, and the tunnel along the cut; `generic_mesh.builder._genioplasty_release`);
- chin: the chin segment's attached nodes where the bone faces more forward than downward,
  n . anterior > n . inferior with n the bone's outward normal (the anterior face of the
  symphysis); where the surface has turned downward (inferior border, underside) the pedicle
  stays tied.

A sliding node keeps the bone's normal displacement and is free in the bone's tangent plane:
a `solver.bc.LocalFrame` constraint in the frame `bone_frames` gives (normal first), i.e.
frictionless sliding linearised about the pre-operative bone surface (exact for a translated
segment; a rotation by theta tilts the tangent plane by theta, an error of about theta times
the slide). `facemodel.simulation.simulate`'s own `sliding=` (bilateral node-to-surface contact
of a whole segment's deep nodes against their own facets) cannot do this: it cannot slide part
of a segment, and on the generic face it does not converge (`sliding=("chin",)`: the slaves are
the surface's own vertices, whose normal is undefined at zero gap; Newton converges at load
0.5, the augmented-Lagrangian re-solve then cycles, and every cut-back down to load 1e-4 fails).

Diagnosis on the coarse generic face, 5 mm chin advancement, no contact (soft-tissue pogonion
/ chin ratio; published 0.8-1.0, San Miguel Moragas et al., Int J Oral Maxillofac Surg
44:1009, 2015): everything tied 1.035 (the bony step and the chin's tangential drag are imposed
on the tissue); the mandible's degloved tissue freed 1.014 (and in a setback the lower lip no
longer follows the mandible) or sliding 1.037; the anterior chin face sliding as well 0.980
(standard 0.969, fine 0.962). The tie of the chin's anterior face is what pushes pogonion ahead
of the bone.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from facemodel.errors import ModelInputError
from facemodel.model import PROXIMAL_CONDITIONS, PROXIMAL_SET

__all__ = ["RELEASE_SET", "BRIDGE_WIDTH_MM", "PROXIMAL", "has_genioplasty", "release_for_plan",
           "genioplasty_sliding", "attachment_sets", "osteotomy_bridges", "bone_normals",
           "bone_frames", "segment_motion", "has_split"]

RELEASE_SET = "release_genioplasty"
ANTERIOR = np.array([0.0, 1.0, 0.0])      # patient RAS
INFERIOR = np.array([0.0, 0.0, -1.0])


# half-width of the tissue that bridges an osteotomy, tied to neither segment (mm); see
# `osteotomy_bridges`
BRIDGE_WIDTH_MM = 2.5


# the owner of the tissue on the mandible's proximal segments when a sagittal split leaves
# them seated (`attachment_sets`); it follows the skull
PROXIMAL = "proximal"


def segment_motion(motions: dict, seg: str) -> np.ndarray:
    """The 4x4 motion of segment `seg` in `motions` (identity when not given); the proximal
    segments of a sagittal split follow the skull, whose condylar fossae seat them."""
    T = motions.get("skull" if seg == PROXIMAL else seg)
    return np.eye(4) if T is None else np.asarray(T, dtype=float)


def _moves_apart(motions: dict, a: str, b: str, tol: float = 1e-9) -> bool:
    """True if segments a and b move relative to each other in `motions` (an identity is
    assumed for a segment not given)."""
    return bool(np.abs(segment_motion(motions, a) - segment_motion(motions, b)).max() > tol)


def has_split(motions: dict, tol: float = 1e-9) -> bool:
    """True if `motions` move the mandible relative to the skull: a sagittal split (BSSO)
    unless the plan says the whole mandible moves (`model.proximal: moved`)."""
    return _moves_apart(motions, "mandible", "skull", tol)


def osteotomy_bridges(model, owners: dict, motions: dict,
                      width: float | None = None) -> np.ndarray:
    """Attached node ids of the tissue that bridges the plan's osteotomies.

    An osteotomy of the plan is where the attachments of two segments that the plan moves
    relative to each other meet: the Le Fort I line between the maxilla and the skull, the
    genioplasty's between the chin and the mandible. The approach to each degloves the bone on
    both sides of the cut (the Le Fort I's circumvestibular incision and subperiosteal
    dissection up to the infraorbital foramina: Bell W.H., J Oral Surg 33:412-426, 1975;
    Reyneke 2010; the genioplasty's, module docstring), so the tissue over the cut lies on
    neither segment: it bridges the step the move opens. A node of `owners` {segment: ids}
    within `width` (None: `BRIDGE_WIDTH_MM`) of a node of another segment moved relative to its
    own is such a bridge node and is tied to no bone.

    The rule makes the tissue's shear across the cut a property of the anatomy, not of the
    mesh. Tied on both sides, the relative move d of the two segments shears the one element
    row between them by d / h, h the mesh spacing on the bone: it grows as 1 / h under
    refinement, and on a fine mesh the Newton updates of the load steps fold those elements.
    Released within `width` on either side, d is spread over a bridge about 2 `width` wide on
    every mesh whose spacing is below `width`; what remains is the weak singularity at the
    bridge's ends, where tied tissue meets free tissue (strain ~ r^(-1/2), Williams M.L.,
    J Appl Mech 19:526-528, 1952). A mesh whose spacing across the cut is above `width` keeps
    its one element row: on every mesh the shear across the cut stays below about d / `width`.
    """
    width = BRIDGE_WIDTH_MM if width is None else float(width)
    X = np.asarray(model.nodes, dtype=float)
    segs = [s for s in owners if len(owners[s])]
    out = []
    trees = {s: cKDTree(X[owners[s]]) for s in segs}
    for i, a in enumerate(segs):
        for b in segs[i + 1:]:
            if not _moves_apart(motions, a, b):
                continue
            for own, other in ((a, b), (b, a)):
                ids = np.asarray(owners[own], dtype=np.int64)
                d, _ = trees[other].query(X[ids], distance_upper_bound=width)
                out.append(ids[d < width])
    if not out:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.concatenate(out))


def attachment_sets(model, motions: dict, bridge_width: float | None = None,
                    proximal: str = "seated") -> dict:
    """{segment: node ids} of the tissue tied to each bone segment for the plan's `motions`:
    the "attach_<segment>" node sets with one owner per node (a node listed by two segments
    goes to the later of `model.segments`), less the nodes that bridge an osteotomy
    (`osteotomy_bridges` of `bridge_width`, None: `BRIDGE_WIDTH_MM` as it is at the call;
    0: none released).

    proximal: "seated" (default) or "moved" (`facemodel.model.PROXIMAL_CONDITIONS`). When the
    mandible moves relative to the skull, "seated" reads the move as a sagittal split: its
    attached nodes in node set "mandible_proximal" (ramus and angle) get their own owner,
    `PROXIMAL`, which follows the skull (`segment_motion`). In a bilateral sagittal split the
    buccal cut runs down the body at the second molar and the lingual cut above the lingula;
    the proximal segments keep the condyles, which the surgeon seats back in the fossae before
    fixation, and with them the masseter and medial pterygoid insertions, while the distal
    segment carries the teeth (Trauner R., Obwegeser H., Oral Surg Oral Med Oral Pathol
    10:677-689, 1957; Dal Pont G., J Oral Surg 19:42-47, 1961; Reyneke 2010).
    The cut itself then opens between the two owners, and `osteotomy_bridges` releases the
    tissue over it. "moved": the whole mandible moves as one body (a mandible that only
    autorotates about its condyles, no split)."""
    if proximal not in PROXIMAL_CONDITIONS:
        raise ModelInputError(f"proximal must be one of {', '.join(PROXIMAL_CONDITIONS)}, got {proximal!r}")
    if bridge_width is None:
        bridge_width = BRIDGE_WIDTH_MM
    owner = {}
    for seg in model.segments:
        for i in np.asarray(model.node_sets.get("attach_" + seg, ()), dtype=np.int64).tolist():
            owner[i] = seg
    sets = {}
    for seg in model.segments:
        ids = np.array(sorted(i for i, s in owner.items() if s == seg), dtype=np.int64)
        if len(ids):
            sets[seg] = ids
    if proximal == "seated" and "mandible" in sets and has_split(motions):
        behind = np.asarray(model.node_sets.get(PROXIMAL_SET, ()), dtype=np.int64)
        ids = np.intersect1d(sets["mandible"], behind)
        if len(ids):
            sets[PROXIMAL] = ids
            sets["mandible"] = np.setdiff1d(sets["mandible"], ids)
    if bridge_width > 0.0:
        bridge = osteotomy_bridges(model, sets, motions, bridge_width)
        if len(bridge):
            sets = {s: np.setdiff1d(ids, bridge) for s, ids in sets.items()}
            sets = {s: ids for s, ids in sets.items() if len(ids)}
    return sets


def has_genioplasty(motions: dict, tol: float = 1e-9) -> bool:
    """True if the chin segment moves relative to the mandible in `motions` {segment: 4x4}
    (an identity is assumed for a segment not given)."""
    return _moves_apart(motions, "chin", "mandible", tol)


def release_for_plan(model, motions: dict):
    """The model with the genioplasty's degloved mandible nodes moved from "attach_mandible" to
    "deep_free" when `motions` hold a genioplasty; the model itself otherwise (or when it has
    no such node set). Freed, the tissue leaves the bone (up to ~6 mm behind it in a 5 mm
    setback) and the lower lip stops following a mandibular setback: the degloved tissue
    slides instead (`genioplasty_sliding`); this is the comparison case."""
    ids = np.asarray(model.node_sets.get(RELEASE_SET, ()), dtype=np.int64)
    if not len(ids) or not has_genioplasty(motions):
        return model
    sets = dict(model.node_sets)
    sets["attach_mandible"] = np.setdiff1d(np.asarray(sets.get("attach_mandible", ()), np.int64), ids)
    sets["deep_free"] = np.union1d(np.asarray(sets.get("deep_free", ()), np.int64), ids)
    return replace(model, node_sets=sets)


def bone_normals(model) -> np.ndarray:
    """(n, 3) unit outward bone normals at the nodes of the "deep_bone" facets (area-weighted
    mean of the facets' normals, zero at other nodes). The deep facets' right-hand normal
    points out of the soft tissue, i.e. into the bone; the bone's outward normal is its
    opposite."""
    X = np.asarray(model.nodes, float)
    F = np.asarray(model.facet_sets.get("deep_bone", np.zeros((0, 4))), dtype=np.int64)
    acc = np.zeros_like(X)
    if len(F):
        p = X[F]
        # quad normal times area: half the cross product of the diagonals
        area_n = -0.5 * np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
        np.add.at(acc, F.ravel(), np.repeat(area_n, F.shape[1], axis=0))
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.divide(acc, norm, out=np.zeros_like(acc), where=norm > 0)


def bone_frames(model, nodes) -> np.ndarray:
    """(k, 3, 3) right-handed orthonormal frames at `nodes`, rows (normal, t1, t2) with the
    bone's outward normal first (ValueError where a node lies on no deep bone facet)."""
    nodes = np.asarray(nodes, dtype=np.int64)
    n = bone_normals(model)[nodes]
    if len(n) and not np.all(np.linalg.norm(n, axis=1) > 0.5):
        raise ValueError("some sliding nodes lie on no deep bone facet")
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return np.stack([n, t1, np.cross(n, t1)], axis=1)


def genioplasty_sliding(model, motions: dict) -> dict[str, np.ndarray]:
    """{segment: deep node ids} of the tissue a genioplasty degloves, which slides on that
    segment's bone: the mandible's "release_genioplasty" nodes and the chin segment's nodes
    on its anterior face (bone facing more forward than downward); {} when `motions` move no
    chin on the mandible or the model has no chin attachments."""
    if not has_genioplasty(motions):
        return {}
    sets = model.node_sets
    normals = bone_normals(model)
    onbone = np.linalg.norm(normals, axis=1) > 0.5
    out = {}
    mandible = np.asarray(sets.get("attach_mandible", ()), dtype=np.int64)
    released = np.intersect1d(np.asarray(sets.get(RELEASE_SET, ()), dtype=np.int64), mandible)
    released = released[onbone[released]]
    chin = np.asarray(sets.get("attach_chin", ()), dtype=np.int64)
    chin = chin[onbone[chin]]
    front = chin[normals[chin] @ ANTERIOR > normals[chin] @ INFERIOR]
    if len(front):
        out["chin"] = front
        if len(released):
            out["mandible"] = released
    return out
