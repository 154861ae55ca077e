"""The predicted whole face and the patient model in files other tools open.

* `blend_face`: the predicted *whole* face. The FE model covers only a patch of the face (nose
  to chin); the patient's own pre-op skin is kept everywhere and displaced by the model skin's
  displacement, interpolated at each patient vertex from the closest point of the model's skin
  patch (barycentric in the closest triangle: a displacement linear over a triangle is carried
  over exactly) and faded to zero across a band along the patch boundary with the C1
  smoothstep s(t) = 3t^2 - 2t^3 of t = (distance of that closest point to the patch boundary) /
  band, so the predicted face has no seam: the displacement and its first derivative are
  continuous where the modelled region meets the rest of the face. Patient vertices farther
  than `gap_mm` from the patch (inside the nostrils, behind the ears) keep their place, with the
  same smooth fade from `gap_mm` to twice it.
* `face_for_pictures`: the pre-op and predicted whole faces on one coarser triangulation for
  the pictures only (off-screen rendering time grows with the triangle count). The pre-op face
  is simplified by quadric edge collapse (Garland & Heckbert 1997, `fast_simplification`) and
  every simplified vertex takes the mean position, displacement and weight of the original
  vertices collapsed into it, so the predicted face is the pre-op one moved by the (locally
  averaged) displacement and both share the triangles. The exports keep the full surface.
* `write_mesh_glb` / `write_mesh_obj`: binary glTF 2.0 and Wavefront OBJ with per-vertex
  normals (trimesh's exporters), which any 3D viewer, a phone or a browser opens.
* `write_markups`: landmarks as a 3D Slicer markups file (`.mrk.json`, schema
  markups-schema-v1.0.3: one Fiducial markup, RAS, mm, one control point per landmark).
* `write_feb`: the patient model and the plan as an FEBio 4 input file (febio_spec 4.0): the
  hexahedral mesh (FEBio's hex8 node order, the same as VTK's), one element set (part) and one
  solid domain per tissue label, each tissue with FEBio's uncoupled "Yeoh" material (c1, c2, c3
  = C10, C20, C30 and bulk modulus k; FEBio's default uncoupled volumetric energy
  U = k/4 (J^2 - 1 - 2 ln J) is the one our solver uses), the skull-attached nodes fixed and
  every moved bone segment's attached nodes given the segment's rigid displacement
  u = R X + t - X as a nodal map of a "prescribed displacement" per axis, ramped by a linear
  load curve; the attachments are the ones faceplan's solve ties (osteotomy bridges released,
  a sagittal split's proximal segments fixed with the skull) and a held neck or floor of the
  mouth is a fixed node set ("held_neck", "held_floor"). Muscles are written with their
  passive Yeoh matrix only, and lip/teeth contact and tissue sliding on bone are not written
  (FEBio needs surfaces and rigid bodies for them): the file reproduces the tied, passive
  problem.
"""
from __future__ import annotations

import json
import os
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from facemodel.attachments import attachment_sets, segment_motion
from facemodel.simulation import held_boundaries

__all__ = ["BlendedFace", "blend_face", "write_mesh_glb", "write_mesh_obj", "write_markups",
           "write_feb", "SLICER_SCHEMA"]

SLICER_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
                 "Resources/Schema/markups-schema-v1.0.3.json#")


# Rounding of a projection onto a border edge at head size (mm): closer to the border is on it.
BORDER_TOL_MM = 1e-9


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


class BlendedFace:
    """The predicted whole face: `vertices` (patient vertices moved), `faces` (the patient's),
    `displacement` (n, 3) applied to each vertex and `weight` (n,) in [0, 1] of the model's
    displacement at each vertex (1 inside the patch, 0 away from it)."""

    def __init__(self, vertices, faces, displacement, weight):
        self.vertices = vertices
        self.faces = faces
        self.displacement = displacement
        self.weight = weight

    @property
    def magnitude(self) -> np.ndarray:
        return np.linalg.norm(self.displacement, axis=1)


def _boundary_samples(vertices: np.ndarray, faces: np.ndarray, spacing: float) -> np.ndarray:
    """Points every <= `spacing` mm along the edges used by one triangle only."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = uniq[counts == 1]
    if not len(boundary):
        return np.zeros((0, 3))
    a, b = vertices[boundary[:, 0]], vertices[boundary[:, 1]]
    n = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / spacing).astype(int))
    t = np.concatenate([np.arange(k + 1) / k for k in n])
    which = np.repeat(np.arange(len(boundary)), n + 1)
    return a[which] + t[:, None] * (b[which] - a[which])


def blend_face(patient_vertices: np.ndarray, patient_faces: np.ndarray, patch_vertices: np.ndarray,
               patch_faces: np.ndarray, patch_displacement: np.ndarray, band_mm: float = 15.0,
               gap_mm: float = 4.0) -> BlendedFace:
    """The patient's skin with the model patch's displacement carried over (see the module
    text). `patch_vertices` are the model skin's pre-op positions, `patch_displacement` (k, 3)
    its displacement; `band_mm`: width of the fade along the patch boundary."""
    from scipy.spatial import cKDTree

    from solver.geometry import TriangleTree

    pv_ = np.asarray(patient_vertices, float)
    pf = np.asarray(patient_faces, np.int64)
    xv = np.asarray(patch_vertices, float)
    xf = np.asarray(patch_faces, np.int64)
    ud = np.asarray(patch_displacement, float)
    if ud.shape != xv.shape:
        raise ValueError(f"patch displacement {ud.shape} does not match its vertices {xv.shape}")
    # only vertices within 2 gap_mm of the patch's box can move: the others are not queried
    near = np.all((pv_ >= xv.min(axis=0) - 2 * gap_mm) & (pv_ <= xv.max(axis=0) + 2 * gap_mm), axis=1)
    d = np.zeros_like(pv_)
    weight = np.zeros(len(pv_))
    if near.any():
        q = pv_[near]
        # exact closest points wherever the weight can be non-zero (nearer than 2 gap_mm); the
        # others get a distance that is itself beyond 2 gap_mm, hence weight 0 all the same
        closest, bary, tri, distance = TriangleTree(xv, xf).closest(q, k=32, max_distance=2.0 * gap_mm)
        bary = np.clip(bary, 0.0, None)
        bary /= bary.sum(axis=1, keepdims=True)
        u = np.einsum("nk,nkj->nj", bary, ud[xf[tri]])
        border = _boundary_samples(xv, xf, spacing=min(0.5, band_mm / 10.0))
        if len(border):
            to_border, _ = cKDTree(border).query(closest)
            # a closest point within rounding of the border is on it (weight exactly 0 there)
            to_border[to_border < BORDER_TOL_MM] = 0.0
        else:                      # a closed patch has no boundary to fade at
            to_border = np.full(len(q), np.inf)
        w = _smoothstep(to_border / band_mm) * (1.0 - _smoothstep((distance - gap_mm) / gap_mm))
        weight[near] = w
        d[near] = w[:, None] * u
    return BlendedFace(pv_ + d, pf, d, weight)


# Triangles above which the pictures use a simplified face: a head scan at the scanner's
# resolution (~0.8 mm, ~2e5 triangles) renders as given, a 10^6-triangle CT skin is reduced.
PICTURE_TRIANGLES = 250_000


def face_for_pictures(pre_face, post_face: BlendedFace, max_triangles: int = PICTURE_TRIANGLES):
    """(pre_face, post_face) on at most about `max_triangles` shared triangles (module text);
    returned unchanged when the face already has no more."""
    pre_v, faces = np.asarray(pre_face[0], float), np.asarray(pre_face[1], np.int64)
    if len(faces) <= max_triangles:
        return pre_face, post_face
    import fast_simplification

    _, _, collapses = fast_simplification.simplify(pre_v, faces, target_reduction=1.0 - max_triangles / len(faces),
                                                   return_collapses=True)
    _, faces_s, owner = fast_simplification.replay_simplification(pre_v, faces, collapses)
    n = int(owner.max()) + 1
    count = np.bincount(owner, minlength=n).astype(float)

    def mean(values):
        values = np.asarray(values, float)
        if values.ndim == 1:
            return np.bincount(owner, values, minlength=n) / count
        return np.stack([np.bincount(owner, values[:, j], minlength=n) for j in range(values.shape[1])], 1) / count[:, None]

    pre_s, disp_s = mean(pre_v), mean(post_face.displacement)
    faces_s = np.asarray(faces_s, np.int64)
    return (pre_s, faces_s), BlendedFace(pre_s + disp_s, faces_s, disp_s, mean(post_face.weight))


def _normals_mesh(vertices, faces):
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=False)
    mesh.vertex_normals   # computed (area-weighted) and cached so the exporters write them
    return mesh


def write_mesh_glb(vertices, faces, path: os.PathLike | str) -> Path:
    """Binary glTF 2.0 with per-vertex normals (mm, RAS as given; glTF has no unit field, viewers
    take the numbers as they are)."""
    from trimesh.exchange.gltf import export_glb

    path = Path(path)
    path.write_bytes(export_glb(_normals_mesh(vertices, faces).scene(), include_normals=True))
    return path


def write_mesh_obj(vertices, faces, path: os.PathLike | str) -> Path:
    """Wavefront OBJ with `vn` per-vertex normals (`f a//a b//b c//c`: vertex i has normal i),
    the text formatted in one pass per block (a 10^6-triangle face in about a second)."""
    mesh = _normals_mesh(vertices, faces)
    v = np.asarray(mesh.vertices, float)
    n = np.asarray(mesh.vertex_normals, float)
    f = np.asarray(mesh.faces, np.int64) + 1
    path = Path(path)
    with open(path, "w") as fh:
        fh.write(f"# faceplan: {len(v)} vertices, {len(f)} triangles; mm, RAS\n")
        fh.write(("v %.6f %.6f %.6f\n" * len(v)) % tuple(v.ravel()))
        fh.write(("vn %.6f %.6f %.6f\n" * len(n)) % tuple(n.ravel()))
        fh.write(("f %d//%d %d//%d %d//%d\n" * len(f)) % tuple(np.repeat(f, 2, axis=1).ravel()))
    return path


def write_markups(landmarks: Mapping[str, Sequence[float]], path: os.PathLike | str,
                  name: str = "predicted landmarks", descriptions: Mapping[str, str] | None = None) -> Path:
    """A 3D Slicer markups file (`.mrk.json`): one Fiducial markup in RAS mm."""
    descriptions = descriptions or {}
    points = []
    for i, (label, p) in enumerate(landmarks.items()):
        p = [float(c) for c in p]
        if len(p) != 3 or not all(np.isfinite(p)):
            raise ValueError(f"landmark {label}: not a finite 3D point")
        points.append({"id": str(i + 1), "label": str(label), "description": descriptions.get(label, ""),
                       "associatedNodeID": "", "position": p,
                       "orientation": [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0],
                       "selected": True, "locked": True, "visibility": True, "positionStatus": "defined"})
    doc = {"@schema": SLICER_SCHEMA,
           "markups": [{"type": "Fiducial", "coordinateSystem": "RAS", "coordinateUnits": "mm",
                        "locked": True, "fixedNumberOfControlPoints": False, "labelFormat": "%N-%d",
                        "lastUsedControlPointNumber": len(points), "name": name,
                        "controlPoints": points, "measurements": [],
                        "display": {"visibility": True, "opacity": 1.0, "color": [0.4, 1.0, 1.0],
                                    "selectedColor": [1.0, 0.5, 0.5], "propertiesLabelVisibility": True,
                                    "pointLabelsVisibility": True, "textScale": 3.0, "glyphType": "Sphere3D",
                                    "glyphScale": 3.0, "glyphSize": 5.0, "useGlyphScale": True}}]}
    path = Path(path)
    path.write_text(json.dumps(doc, indent=2))
    return path


def _sub(parent, tag, text=None, **attrib):
    e = ET.SubElement(parent, tag, {k: str(v) for k, v in attrib.items()})
    if text is not None:
        e.text = str(text)
    return e


def _g(v: float) -> str:
    return f"{float(v):.9g}"


def write_feb(model, motions: Mapping[str, np.ndarray], materials: Mapping[str, Mapping[str, float]],
              path: os.PathLike | str, steps: int = 10, title: str = "faceplan prediction", *,
              proximal: str = "seated", neck: str = "free", floor: str = "free") -> Path:
    """FEBio 4 input file of `model` (nodes, hexes, labels, label_names, node_sets with
    `attach_<segment>`) under the rigid segment `motions` ({segment: 4x4}); `materials`:
    {label: {"C10", "C20", "C30" (optional), "K"}} in kPa (see the module text). The
    attachments and held boundaries are faceplan's own: `proximal`, `neck` and `floor` as in
    `facemodel.simulation.simulate` (every segment's tied nodes, a seated BSSO's proximal
    segments fixed with the skull, a held neck or floor fixed)."""
    x = np.asarray(model.nodes, float)
    hexes = np.asarray(model.hexes, np.int64)
    labels = np.asarray(model.labels, np.int64)
    names = [str(n) for n in model.label_names]
    root = ET.Element("febio_spec", version="4.0")
    root.append(ET.Comment(f" {title}: written by faceplan; units mm, kPa (mN/mm^2), RAS frame. "
                           "Tied passive problem (attachments, osteotomy bridges and held boundaries as "
                           "faceplan solves them): muscle activation, lip contact and sliding are not "
                           "included. "))
    _sub(root, "Module", type="solid")
    control = _sub(root, "Control")
    _sub(control, "analysis", "STATIC")
    _sub(control, "time_steps", int(steps))
    _sub(control, "step_size", _g(1.0 / steps))
    _sub(control, "plot_level", "PLOT_MAJOR_ITRS")
    stepper = _sub(control, "time_stepper", type="default")
    _sub(stepper, "max_retries", 5)
    _sub(stepper, "opt_iter", 10)
    _sub(stepper, "dtmin", _g(0.01 / steps))
    _sub(stepper, "dtmax", _g(1.0 / steps))
    solver = _sub(control, "solver", type="solid")
    _sub(solver, "symmetric_stiffness", "symmetric")
    _sub(solver, "max_refs", 25)
    _sub(solver, "dtol", "0.001")
    _sub(solver, "etol", "0.01")
    _sub(solver, "rtol", "0")
    used = [i for i in range(len(names)) if np.any(labels == i)]
    mat = _sub(root, "Material")
    for k, i in enumerate(used):
        p = materials[names[i]]
        m = _sub(mat, "material", id=k + 1, name=names[i], type="Yeoh")
        _sub(m, "density", "1")
        _sub(m, "c1", _g(p["C10"]))
        _sub(m, "c2", _g(p.get("C20", 0.0)))
        _sub(m, "c3", _g(p.get("C30", 0.0)))
        _sub(m, "k", _g(p["K"]))
    mesh = _sub(root, "Mesh")
    nodes = _sub(mesh, "Nodes", name="face")
    for n, p in enumerate(x):
        _sub(nodes, "node", ",".join(_g(c) for c in p), id=n + 1)
    eid = 0
    for i in used:
        block = _sub(mesh, "Elements", type="hex8", name=names[i])
        for e in np.flatnonzero(labels == i):
            eid += 1
            _sub(block, "elem", ",".join(str(int(v) + 1) for v in hexes[e]), id=eid)
    sets = {}
    # the nodes faceplan's own solve ties to each segment (the osteotomy bridges released)
    tied = attachment_sets(model, motions, proximal=proximal)
    named = {seg: "attach_" + seg for seg in tied}
    for seg, ids in tied.items():
        sets[seg] = (ids, segment_motion(motions, seg))
    for owner, ids in held_boundaries(model, tied, neck=neck, floor=floor):
        sets[owner] = (ids, np.eye(4))
        named[owner] = "held_" + owner
    for seg, (ids, _) in sets.items():
        _sub(mesh, "NodeSet", ",".join(str(int(v) + 1) for v in ids), name=named[seg])
    domains = _sub(root, "MeshDomains")
    for i in used:
        _sub(domains, "SolidDomain", name=names[i], mat=names[i])
    moving = {s: v for s, v in sets.items() if not np.allclose(v[1], np.eye(4), atol=1e-12)}
    if moving:
        data = _sub(root, "MeshData")
        for seg, (ids, m4) in moving.items():
            u = x[ids] @ m4[:3, :3].T + m4[:3, 3] - x[ids]
            for axis, comp in zip("xyz", u.T):
                nd = _sub(data, "NodeData", name=f"{seg}_u{axis}", node_set=named[seg], data_type="scalar")
                for lid, value in enumerate(comp):
                    _sub(nd, "node", _g(value), lid=lid + 1)
    boundary = _sub(root, "Boundary")
    for seg, (ids, m4) in sets.items():
        if seg not in moving:
            bc = _sub(boundary, "bc", name=f"{seg}_fixed", node_set=named[seg], type="zero displacement")
            for axis in "xyz":
                _sub(bc, f"{axis}_dof", 1)
            continue
        for axis in "xyz":
            bc = _sub(boundary, "bc", name=f"{seg}_u{axis}", node_set=named[seg],
                      type="prescribed displacement")
            _sub(bc, "dof", axis)
            _sub(bc, "value", f"{seg}_u{axis}", lc=1, type="map")
            _sub(bc, "relative", 0)
    load = _sub(root, "LoadData")
    lc = _sub(load, "load_controller", id=1, name="plan", type="loadcurve")
    _sub(lc, "interpolate", "LINEAR")
    pts = _sub(lc, "points")
    _sub(pts, "pt", "0,0")
    _sub(pts, "pt", "1,1")
    out = _sub(root, "Output")
    plot = _sub(out, "plotfile", type="febio")
    for var in ("displacement", "stress", "relative volume"):
        _sub(plot, "var", type=var)
    ET.indent(root, space="  ")
    path = Path(path)
    ET.ElementTree(root).write(path, encoding="ISO-8859-1", xml_declaration=True)
    return path
