"""Mesh-Match-and-Repair on plain arrays: align, register elastically, snap, repair, measure.

The stages follow Bucki, Lobos and Payan (Med. Image Anal. 14, 2010): (1) a similarity from
landmarks (Umeyama) or from the surfaces (principal axes + trimmed ICP); where a
registration fails with two given landmarks that contradict each other for the model (given
on one point, their nodes well apart: `registration.landmark_fit.contradicting_landmarks`),
it is made again with the one farther from its node set aside (`match_and_repair_arrays`),
(2) the joint elastic
registration of skin and bone-attachment nodes by a composed multilevel B-spline FFD
(`registration.elastic`), (3) a snap of the surface nodes onto the patient surfaces with a
harmonic spread into the volume, (3b) with given landmarks, the landmark nodes moved onto them
by a geodesic correction of the skin that can separate the lips (`registration.landmark_fit`),
(4) the repair of every element whose minimum scaled Jacobian is below the threshold
(`registration.repair`; landmark nodes held), (4b) the least-squares facet fit that places the
skin nodes so that the bilinear facets, not only the nodes, lie on the patient skin
(`registration.surface_fit`; landmark nodes stay on it, no element goes below the threshold),
(5) the teeth placed with their bone segments
(or the patient's own) and the soft tissue cleared of them (`registration.teeth`), (6) the lips
kept at least `lip_gap_mm` apart across the mouth slit (`registration.lips`; the teeth cleared
again if that pushed a lip node towards them, alternating while each pass brings the deepest
node nearer the teeth clearance), then fit
errors (mean / 95th percentile / max of the distances from the registered skin -- its nodes and points inside its facets -- to the
patient skin where the patient surface covers the model, the reverse distances, and the
bone-attachment node distances) and quality figures.
Inputs that cannot give a trustworthy mesh (wrong units, a surface that covers too little of
the face, landmarks that contradict the surface) raise `RegistrationInputError`; a result that
misses the validity gates raises `RegistrationFailure` -- an inverted or badly fitting mesh is
never returned.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from registration.alignment import Similarity, align_surfaces, trimmed_icp, umeyama
from registration.elastic import (ElasticSchedule, SurfaceGroup, elastic_register, mesh_laplacian,
                                  snap_to_surfaces, vertex_normals)
from registration.errors import RegistrationFailure, RegistrationInputError
from registration.landmark_fit import contradicting_landmarks, landmark_correction
from registration.landmark_search import LOCATED, locate_landmarks, mirror_pairs
from registration.lips import lip_overlap, quad_vertex_normals, separate_lips
from registration.profile_pose import FEATURES, profile_pose
from registration.quality import min_scaled_jacobian, quality_summary
from registration.repair import SurfaceConstraint, repair_holding
from registration.surface import TargetSurface
from registration.surface_fit import facet_fit
from registration.teeth import Arch, union_distance, clear_teeth, place_teeth


@dataclass
class MatchOptions:
    threshold: float = 0.2  # minimum scaled Jacobian after repair
    schedule: ElasticSchedule = field(default_factory=ElasticSchedule)
    use_landmarks: bool = True
    max_snap_mm: float = 5.0
    coverage_min: float = 0.25  # fraction of generic skin nodes the patient skin must cover
    # Umeyama residual above which landmarks are refused: a swapped or misnamed landmark gives
    # tens of mm; faces of other proportions (long or short lower face, small nose) reach
    # 8-9 mm RMS over the ten landmarks against the generic face
    landmark_rms_max_mm: float = 12.0
    skin_mean_gate_mm: float = 1.0  # refuse to return a mesh fitting worse than this
    # a skin node of the model farther than this from the patient skin where the scan lies
    # under it (closest point inside the scan, normals agreeing) is misplaced along the scan:
    # the snap brings every covered node within max_snap_mm onto the skin and the repair and
    # facet fit move nodes by a fraction of an element, so a covered node twice the snap
    # distance away is one the elastic stage never brought near its skin (the face slid
    # along a scan that does not fix where it sits). None disables the gate
    skin_off_scan_gate_mm: float | None = 10.0
    # soft-tissue nodes end at least this far outside the teeth (the clearance that
    # facemodel.teeth.clear_teeth asks of a contact start, so that it has nothing to move)
    teeth_clearance_mm: float = 0.25
    # given landmarks: the landmark nodes brought onto them after the snap, the correction
    # spread over the skin with this geodesic radius (registration.landmark_fit)
    landmark_correction: bool = True
    landmark_sigma_mm: float = 8.0
    # landmarks the case does not give located by their anatomical definitions on the patient
    # skin near where the registration carried them, then corrected like given ones
    # (registration.landmark_search)
    locate_landmarks: bool = True
    # a landmark the registered skin misses by more than this contradicts the surfaces
    landmark_max_correction_mm: float = 10.0
    # the same for a located landmark: found by its definition on the scan near the carried
    # node, it may lie farther from it where the head's shape moves the feature along the
    # profile (menton on a short, retruded chin; pogonion on a chin without a summit of its
    # own). A located landmark on the wrong feature is caught by the profile order
    # (`landmark_search.out_of_profile_order`); this bound only keeps the correction within
    # the reach of the search itself along the profile (landmark_search.MENTON_REACH)
    located_max_correction_mm: float = 25.0
    # skin nodes placed so that the facets, not only the nodes, fit the skin (least squares)
    facet_fit: bool = True
    # lips kept at least this far apart across the mouth slit (registration.lips); 0 disables
    lip_gap_mm: float = 0.1
    # a lip's skin node at the slit's front edge may leave the patient skin by up to this much
    # where the skin takes its push back (lips touching or crossing as scanned); None: never
    lip_skin_release_mm: float | None = 1.0
    # without landmarks, the pose corrected by the skin's symmetry plane and profile features
    # (registration.profile_pose) where the surface alignment misplaces them
    profile_pose: bool = True
    # the profile pose wherever it was found, whatever the surface pose (set for the second
    # attempt of a registration whose surface pose left the model's nose off the patient's)
    prefer_profile_pose: bool = False
    # the profile's features guide the elastic stage whichever pose placed the face (set for
    # the second attempt of a registration whose located landmarks disagree with them)
    profile_guide: bool = False
    # given landmarks that contradict each other for the model set aside (the one farther
    # from its node of each pair: `registration.landmark_fit.contradicting_landmarks`); set
    # for the second attempt of a registration that failed with such a pair followed
    set_aside_contradicting: bool = False
    seed: int = 0


@dataclass
class MatchInput:
    """The generic mesh, as arrays."""

    nodes: np.ndarray
    hexes: np.ndarray
    skin_quads: np.ndarray  # (k, 4) node ids, outward
    bone_node_sets: dict  # segment name -> node ids attached to it
    landmark_nodes: dict = field(default_factory=dict)  # landmark name -> node id
    bone_quads: np.ndarray | None = None  # (k, 4) deep facets on bone, outward from the tissue
    teeth: dict = field(default_factory=dict)  # arch -> (vertices, faces, segment), generic frame
    lip_quads: tuple | None = None  # (upper, lower) contact facets across the mouth slit, outward
    regions: dict = field(default_factory=dict)  # skin region name -> node ids (the report's)
    edge_nodes: np.ndarray | None = None  # node ids on the mesh's cut edges (its border columns)


def _fit_stats(d: np.ndarray) -> dict:
    if len(d) == 0:
        return {"mean_mm": None, "p95_mm": None, "max_mm": None, "n_points": 0}
    return {"mean_mm": float(d.mean()), "p95_mm": float(np.percentile(d, 95)),
            "max_mm": float(d.max()), "n_points": int(len(d))}


def covered_skin(x: np.ndarray, skin_quads: np.ndarray, skin_tris: np.ndarray, skin) -> tuple[np.ndarray, np.ndarray]:
    """The skin nodes whose closest patient-skin point (on `skin`, anything with `closest`) is
    inside the surface (not on an open border) with a compatible normal, as a mask over the
    nodes of x, and the skin quads whose four nodes are such: the facets the patient skin covers."""
    skin_quads = np.asarray(skin_quads)
    ids = np.unique(skin_quads)
    normals = vertex_normals(x, skin_tris)
    cl = skin.closest(x[ids])
    ok = ~cl.on_boundary & (np.einsum("ij,ij->i", normals[ids], cl.normal) > 0.5)
    node_ok = np.zeros(len(x), bool)
    node_ok[ids[ok]] = True
    return node_ok, skin_quads[node_ok[skin_quads].all(axis=1)]


# Without landmarks, the nose is what fixes the face's height on a partial skin: the lips and
# the chin are smooth along the profile and a face-only scan gives the skull too little to
# place the face to a few mm, so the elastic stage can slide the generic face along the
# profile (lips onto the chin, the nose onto its cut stump) with a close skin fit. Without
# landmarks, a registration whose nose region is not fitted (a CBCT cut through the nose, or
# the model's nose left off the patient's) is refused.
NOSE_REGION = "nose"
REGION_FITTED_MIN = 0.5  # a region is fitted when the patient skin covers this share of its nodes


def region_coverage(regions: dict, skin_ids: np.ndarray, valid: np.ndarray, dist: np.ndarray,
                    fitted_min: float = REGION_FITTED_MIN) -> dict:
    """Per skin region: how many of its skin nodes the patient skin covers (`valid`, over
    `skin_ids`: the caller's test -- closest point inside the patient surface with an agreeing
    normal, within the snap distance) and their distance to it. A region covered on less than `fitted_min` of its nodes is "not fitted":
    its shape is the generic one carried by the covered skin and the bones (the elastic
    transform and the harmonic extension), not the patient's."""
    pos = np.full(int(max(skin_ids.max(initial=0), max((int(np.max(v)) for v in regions.values()
                                                          if len(v)), default=0))) + 1, -1)
    pos[skin_ids] = np.arange(len(skin_ids))
    out = {}
    for name in sorted(regions):
        ids = np.asarray(regions[name], np.int64)
        k = pos[ids]
        k = k[k >= 0]
        if len(k) == 0:
            continue
        cov = valid[k]
        out[name] = {"n_nodes": int(len(k)), "covered_fraction": float(cov.mean()),
                     "fitted": bool(cov.mean() >= fitted_min),
                     "mean_mm": float(dist[k][cov].mean()) if cov.any() else None}
    return out


def _lip_away(model: MatchInput, x: np.ndarray) -> np.ndarray | None:
    """(n, 3): for each lip-surface node the direction away from the other lip (against its own
    contact surface's outward normal); zero elsewhere and on the nodes the two lips share."""
    if model.lip_quads is None:
        return None
    up, low = (np.asarray(q) for q in model.lip_quads)
    away = -(quad_vertex_normals(x, up) + quad_vertex_normals(x, low))
    away[np.intersect1d(np.unique(up), np.unique(low))] = 0.0
    return away


def _extent(v: np.ndarray) -> float:
    return float(np.linalg.norm(np.ptp(v, axis=0)))


def check_units(name: str, vertices: np.ndarray, reference_extent: float, file: str | None = None):
    """Refuse surfaces whose size says they are not in mm (metres, centimetres, inches)."""
    ext = _extent(vertices)
    ratio = ext / reference_extent
    if 0.4 <= ratio <= 2.5:
        return
    for unit, factor in (("metres", 1000.0), ("centimetres", 10.0), ("inches", 25.4)):
        if 0.4 <= ratio * factor <= 2.5:
            raise RegistrationInputError(
                f"the {name} surface spans {ext:.4g} units where a face spans about "
                f"{reference_extent:.0f} mm: it looks like {unit}; export it in mm "
                f"(scale by {factor:g})", file=file, field="units")
    raise RegistrationInputError(
        f"the {name} surface spans {ext:.4g} units where a face spans about "
        f"{reference_extent:.0f} mm; faceplan expects surfaces in mm", file=file, field="units")


def _bone_pairs(model: MatchInput, bones: dict | None, n_max: int = 200) -> list:
    """For the surface alignment (`align_surfaces`' extra pairs): per segment the patient gives
    a bone surface for, up to n_max of the model's attachment nodes of that segment and that
    surface."""
    out = []
    for seg, ids in model.bone_node_sets.items():
        ids = np.asarray(ids, dtype=np.int64)
        if bones and seg in bones and len(ids):
            step = max(1, len(ids) // n_max)
            out.append((np.asarray(model.nodes, float)[ids[::step]], bones[seg]))
    return out


def initial_alignment(model: MatchInput, skin: TargetSurface, landmarks: dict | None,
                      options: MatchOptions, bones: dict | None = None) -> tuple[Similarity, dict]:
    """Similarity generic -> patient, and how it was found (`bones`: the patient's bone
    surfaces by segment, which disambiguate a pose found from the surfaces)."""
    info: dict = {}
    if landmarks and options.use_landmarks:
        common = [k for k in model.landmark_nodes if k in landmarks]
        if len(common) >= 4:
            src = model.nodes[[model.landmark_nodes[k] for k in common]]
            dst = np.array([landmarks[k] for k in common], dtype=float)
            sim = umeyama(src, dst)
            rms = float(np.sqrt(np.mean(np.sum((sim.apply(src) - dst) ** 2, axis=1))))
            info.update(method="landmarks", landmarks_used=common, landmark_rms_mm=rms)
            if rms > options.landmark_rms_max_mm:
                raise RegistrationInputError(
                    f"the landmarks cannot be matched to the face model by a similarity "
                    f"(residual {rms:.1f} mm over {', '.join(common)}): check their names, frame "
                    f"(RAS vs LPS) and units", field="landmarks")
            if not 0.6 <= sim.scale <= 1.6:
                raise RegistrationInputError(
                    f"the landmarks imply a head {sim.scale:.3g} times the generic size: check "
                    f"their units (mm expected)", field="landmarks")
            info.update(scale=sim.scale, rotation_deg=sim.rotation_deg)
            return sim, info
        info["landmarks_ignored"] = f"only {len(common)} landmark(s) in common with the model (4 needed)"
    q = np.asarray(model.skin_quads)
    generic_skin = TargetSurface(model.nodes, np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]), "generic skin")
    icp = align_surfaces(generic_skin, skin, seed=options.seed, extra=_bone_pairs(model, bones))
    sim = icp.similarity
    info.update(method="surfaces", trimmed_rms_mm=icp.rms_mm, inlier_fraction=icp.inliers,
                scale=sim.scale, rotation_deg=sim.rotation_deg)
    # the face's own features correct a bulk fit that puts them elsewhere (a face of other
    # proportions than the generic one): the profile pose is used where it moves the generic
    # nose, mouth or chin by more than PROFILE_POSE_AGREE_MM from where the surfaces put them
    feats = profile_feature_nodes(model)
    if feats is not None and options.profile_pose:
        pose, pinfo = profile_pose(skin, sim, feats, seed=options.seed)
        info["profile_pose"] = pinfo
        if pose is not None:
            src = np.array([feats[k] for k in FEATURES])
            moved = float(np.linalg.norm(pose.apply(src) - sim.apply(src), axis=1).max())
            pinfo["features_moved_mm"] = moved
            if options.prefer_profile_pose or \
                    moved > PROFILE_POSE_AGREE_MM + 2.0 * float(pinfo.get("features_rms_mm", 0.0)):
                sim = pose
                info.update(method="surfaces", pose="profile", scale=sim.scale, rotation_deg=sim.rotation_deg)
    if not 0.65 <= sim.scale <= 1.5:
        raise RegistrationInputError(
            f"the patient skin matches the face model only at scale {sim.scale:.3g}: it does not "
            f"look like a face in mm", field="skin")
    return sim, info


# mm: the surface pose is kept where the profile pose places the generic features within this
# of it, plus twice the features' own RMS misfit to the generic profile (their scatter: a
# mouth slit found at the lower lip's edge under an overhanging upper lip is 4 mm from the
# generic stomion midpoint): the elastic stage and the local landmark search (its reach about
# the mouth is 7 mm) recover such a difference; beyond it the features decide
PROFILE_POSE_AGREE_MM = 5.0


# mm: how far a located landmark may lie from where the elastic stage, guided by the profile's
# features, carried it, and, unguided, from its feature itself: the profile pose places the
# features to 1-3 mm and the stomia lie within 1-3 mm of the fissure point, while the nearest
# other feature a definition can latch onto (the labiomental fold below the lips, the
# columella above) lies 10 mm or more away
PROFILE_LOCATED_MAX_MOVE_MM = 8.0


def profile_feature_nodes(model: MatchInput) -> dict | None:
    """The generic model's positions of the profile features (`registration.profile_pose`):
    its pronasale, subnasale, stomion midpoint and pogonion nodes; None without them."""
    lm = model.landmark_nodes
    if not all(k in lm for k in ("Prn", "Sn", "Stms", "Stmi", "Pog")):
        return None
    x = np.asarray(model.nodes, float)
    return {"Prn": x[lm["Prn"]], "Sn": x[lm["Sn"]], "mouth": 0.5 * (x[lm["Stms"]] + x[lm["Stmi"]]),
            "Pog": x[lm["Pog"]]}


# deg: the largest tilt the skull may correct in the alignment of skin and bones (module
# docstring of `_head_frame`); a larger rotation is an ICP slide along a smooth skull
HEAD_FRAME_MAX_DEG = 15.0


def _head_frame(model: MatchInput, bones: dict, seed: int = 0,
                info: dict | None = None) -> Similarity | None:
    """The head's anatomical frame in the working frame: the similarity that takes the generic
    skull attachment surface (deep facets on the skull, generic frame) onto the patient skull
    by trimmed ICP. The skull is what the face's shape differences leave in place: the
    alignment of the whole skin tilts by several degrees on a strong class II / III (the lower
    face differs most), and the elastic stage keeps that tilt (the surfaces slide freely along
    each other). None without a skull surface or attachment.

    The working frame is already the joint alignment of skin and bones, so the skull only
    corrects a tilt of a few degrees. A skull cap is nearly a piece of a sphere: its rotation
    about its own centre is weakly determined, and where the patient's skull surface covers
    another part of the cranium than the generic attachment (a CBCT's field of view, another
    anatomy) the trimmed ICP slides the cap round by tens of degrees to overlap them. A frame
    rotated by more than HEAD_FRAME_MAX_DEG from the alignment is such a slide: it is not
    used (None; `info` records the rotation found and why it was refused), and the
    definitions' directions are those of the alignment."""
    skull = bones.get("skull")
    if skull is None or model.bone_quads is None or "skull" not in model.bone_node_sets:
        return None
    q = np.asarray(model.bone_quads)
    on = np.zeros(len(model.nodes), bool)
    on[np.asarray(model.bone_node_sets["skull"], np.int64)] = True
    q = q[on[q].all(axis=1)]
    if len(q) < 20:
        return None
    ids = np.unique(q)
    tris = np.searchsorted(ids, np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]))
    source = TargetSurface(np.asarray(model.nodes, float)[ids], tris, "generic skull attachment")
    frame = trimmed_icp(source, skull, Similarity.identity(), n_points=800, iterations=30, seed=seed).similarity
    if info is not None:
        info["head_frame_rotation_deg"] = frame.rotation_deg
    if frame.rotation_deg > HEAD_FRAME_MAX_DEG:
        if info is not None:
            info["head_frame_refused"] = (f"the skull fit turns the head by {frame.rotation_deg:.1f} deg "
                                          f"(more than {HEAD_FRAME_MAX_DEG:g}): a slide along the skull, "
                                          "not a tilt; the alignment's axes are used")
        return None
    return frame


def _bone_groups(model: MatchInput, bones: dict) -> list[SurfaceGroup]:
    """One group per attachment set: its segment's surface, or the union of the bones."""
    bone_tris = None
    if model.bone_quads is not None and len(model.bone_quads):
        bq = np.asarray(model.bone_quads)
        bone_tris = np.concatenate([bq[:, [0, 1, 2]], bq[:, [0, 2, 3]]])
    union, groups = None, []
    for seg, ids in model.bone_node_sets.items():
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0 or not bones:
            continue
        if seg in bones:
            target = bones[seg]
        else:
            if union is None:
                vs, fs, off = [], [], 0
                for b in bones.values():
                    vs.append(b.vertices)
                    fs.append(b.faces + off)
                    off += len(b.vertices)
                union = TargetSurface(np.vstack(vs), np.vstack(fs), "bones")
            target = union
        groups.append(SurfaceGroup(seg, ids, target, weight=1.0 / max(len(model.bone_node_sets), 1),
                                   tris=bone_tris, facing=-1.0))
    return groups


class _NoseNotPlaced(RegistrationFailure):
    """A registration without landmarks whose surface pose left the model's nose off the
    patient's (`match_and_repair_arrays` tries the profile pose then)."""


# Per landmark found on an arc of the sagittal profile, the landmarks the search found first and
# bounds that arc with (`landmark_search`), the nearest first: subnasale and labrale superius lie
# on the arc from pronasale to stomion superius, labrale inferius below stomion inferius; the two
# stomia are the mouth slit's two ends.
PROFILE_ANCHORS = {"Sn": ("Prn", "Stms"), "Ls": ("Stms", "Stmi"), "Li": ("Stmi", "Stms")}


def far_from_profile_pose(found: dict, carried: dict,
                          limit: float = PROFILE_LOCATED_MAX_MOVE_MM) -> list[str]:
    """Located landmarks (name -> (3,)) that moved more than `limit` from where the elastic
    stage, guided by the profile's features, `carried` them: another feature of the profile
    than the one sought (the labiomental fold taken for the mouth slit).

    A landmark found on the arc between two anchors of the profile (`PROFILE_ANCHORS`) is
    measured against the move of an anchor that passed the test: the elastic stage's error is
    smooth along the profile, so where it carried a whole upper lip several mm too low, its
    stomion and labrale superius both move by about that much, and what tells another feature
    is the landmark's move relative to its anchor's (a stomion is no anchor when its partner
    is far: the slit found is another crease). Menton is not tested (the chin's lowest
    point is sought along the submental contour, no feature guides it)."""
    move = {k: np.asarray(found[k], float) - np.asarray(carried[k], float) for k in found}
    far = {k for k, m in move.items() if k != "Me" and np.linalg.norm(m) > limit}
    # the two stomia are one detection (`stomia_as_one`): one far makes neither an anchor
    trusted = set(move) - far - ({"Stms", "Stmi"} if far & {"Stms", "Stmi"} else set())
    for k in sorted(far & set(PROFILE_ANCHORS)):
        anchors = [a for a in PROFILE_ANCHORS[k] if a in trusted]
        if any(np.linalg.norm(move[k] - move[a]) <= limit for a in anchors):
            far.discard(k)
    return sorted(far)


def stomia_as_one(found: dict, wanted, report: dict) -> None:
    """Set aside a located stomion whose partner was set aside. The two stomia are one
    detection, the mouth slit's two ends (`landmark_search`): where one of them was not used
    (another crease taken for the slit, found far from where the registration carried it, or
    out of the profile's order), the slit found is not the mouth's, and the other is not used
    either (the registration carries it). Only when both were sought (`wanted`); `found` and
    `report` (the search's: `not_found`, `not_used_partner_set_aside`) are updated in place."""
    pair = [k for k in ("Stms", "Stmi") if k in wanted]
    lone = [k for k in pair if k in found] if len(pair) == 2 else []
    if len(lone) == 1:
        del found[lone[0]]
        report["not_used_partner_set_aside"] = lone
        report["not_found"] = sorted(set(report.get("not_found", [])) | set(lone))


def _far_from_features(before: str, far: dict, after: str, report: dict) -> RegistrationFailure:
    """The refusal of a registration without landmarks whose located landmarks lie `far`
    (name -> mm) from the features found on the skin's profile."""
    return RegistrationFailure(
        f"without landmarks {before + ' ' if before else ''}the landmarks located on the "
        f"registered face lie " + ", ".join(f"{k} {v:.1f} mm" for k, v in far.items())
        + f" from the features found on the skin's profile{after}: the placement cannot be "
        "trusted; give at least four landmarks (landmarks.json)", report)


def match_and_repair_arrays(model: MatchInput, skin: TargetSurface, bones: dict,
                            landmarks: dict | None = None, options: MatchOptions | None = None,
                            files: dict | None = None, teeth: dict | None = None):
    """Register the generic mesh onto the patient surfaces (`_match_and_repair_arrays`).

    A registration that fails with two given landmarks that contradict each other for the
    model (given on one point, their nodes well apart: pulling both there can fold the
    tissue between them beyond repair) is made once more with the one farther from its node
    set aside (`landmarks_contradicting[*].set_aside` in the report, which lists such pairs
    whether set aside or not); if that fails too, the first failure stands."""
    opt = options or MatchOptions()
    try:
        return _match_and_repair_arrays(model, skin, bones, landmarks, opt, files, teeth)
    except RegistrationFailure as exc:
        if opt.set_aside_contradicting or not (exc.report or {}).get("landmarks_contradicting"):
            raise
        first = exc
    try:
        return _match_and_repair_arrays(model, skin, bones, landmarks,
                                        dataclasses.replace(opt, set_aside_contradicting=True),
                                        files, teeth)
    except RegistrationFailure:
        raise first from None


def _match_and_repair_arrays(model: MatchInput, skin: TargetSurface, bones: dict,
                             landmarks: dict | None = None, options: MatchOptions | None = None,
                             files: dict | None = None, teeth: dict | None = None):
    """Register the generic mesh onto the patient surfaces.

    Returns (nodes, similarity, report, teeth): `teeth` maps each arch to (vertices, faces,
    segment) in the patient frame -- the patient's own surface where `teeth` gives one (arch
    name -> surface), else the generic arch moved with its bone segment -- and no node that
    is neither on the skin nor attached to a bone lies closer than the clearance to them
    (`registration.teeth`). `bones` maps segment names to TargetSurface; a segment of the
    model without a patient bone surface is fitted to the union of the given bones.

    Without landmarks the face is placed by the surfaces, or by the skin's profile features
    where the two disagree by more than the features' own misfit allows (`initial_alignment`).
    A face of other proportions than the generic one can fit the features poorly enough that
    the surface pose is kept, and yet the surfaces slide it along its profile:
    - when that leaves the model's nose off the patient's skin or off the scan (the refusal's
      cause), the registration is made once more from the profile pose, which places the nose
      by construction, and returned if it passes every gate (the nose's included); the report's
      `alignment.surface_pose_refused` says so; otherwise the first refusal stands;
    - when the landmarks located on the skin lie farther from the profile's features than the
      features' own error allows (the search took another crease for the mouth), the
      registration is made once more with the features guiding the elastic stage, and that
      one is returned if it passes every gate (`alignment.guided_after` gives the distances
      that asked for it); if it fails, the registration is refused: the first is known to be
      misplaced. Where the profile pose was refused (features that fit the generic profile
      too poorly to place the face) such a disagreement is a refusal at once: the surfaces
      alone placed a face whose own features are elsewhere."""
    opt = options or MatchOptions()
    try:
        out = _match_and_repair_once(model, skin, bones, landmarks, opt, files, teeth)
    except _NoseNotPlaced as exc:
        align = exc.report.get("alignment") or {}
        pinfo = align.get("profile_pose") or {}
        # nothing to retry: the profile pose placed this face already, or there is none
        if opt.prefer_profile_pose or align.get("pose") == "profile" or not pinfo.get("features") \
                or "refused" in pinfo:
            raise RegistrationFailure(str(exc), exc.report) from None
        first = exc
    else:
        align = out[2].get("alignment", {})
        far = align.get("located_far_from_features_mm")
        if not far or opt.profile_guide:
            return out
        refused = (align.get("profile_pose") or {}).get("refused")
        if refused:
            # the features were found but fit the generic profile too poorly to place the
            # face, and the surfaces placed it elsewhere: nothing left to trust
            raise _far_from_features(f"the surfaces alone placed the face (the skin profile's "
                                     f"pose was refused: {refused}), and", far, "", out[2])
        try:
            guided = _match_and_repair_once(model, skin, bones, landmarks,
                                            dataclasses.replace(opt, profile_guide=True), files, teeth)
        except RegistrationFailure as exc:
            # the first registration is known to disagree with the skin's own features, and
            # the one they guide did not pass its gates: neither placement can be trusted
            raise _far_from_features("", far, f", and the registration guided by those features "
                                     f"failed ({exc})", out[2]) from None
        guided[2]["alignment"]["guided_after"] = far
        return guided
    retry = dataclasses.replace(opt, prefer_profile_pose=True)
    try:
        out = _match_and_repair_once(model, skin, bones, landmarks, retry, files, teeth)
    except RegistrationFailure as exc:
        raise RegistrationFailure(f"{first} (from the skin profile's pose as well: {exc})",
                                  first.report) from None
    out[2]["alignment"]["surface_pose_refused"] = str(first)
    return out


def _match_and_repair_once(model: MatchInput, skin: TargetSurface, bones: dict, landmarks,
                           opt: MatchOptions, files: dict | None, teeth: dict | None):
    """One registration from one initial pose (`match_and_repair_arrays`)."""
    files = files or {}
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    hexes = np.asarray(model.hexes)
    skin_tris = np.concatenate([model.skin_quads[:, [0, 1, 2]], model.skin_quads[:, [0, 2, 3]]])
    skin_ids = np.unique(model.skin_quads)
    ref_extent = _extent(model.nodes[skin_ids])
    check_units("skin", skin.vertices, ref_extent, files.get("skin"))
    for name, b in bones.items():
        ext = _extent(b.vertices)
        if not 0.05 * ref_extent <= ext <= 2.5 * ref_extent:
            hint = " it looks like metres;" if 0.05 * ref_extent <= 1000 * ext <= 2.5 * ref_extent else ""
            raise RegistrationInputError(
                f"the bone surface '{name}' spans {ext:.4g} units, not a bone segment in mm;{hint} "
                f"export it in mm", file=files.get(name), field="units")
    if landmarks:
        for name, p in landmarks.items():
            if not np.all(np.isfinite(np.asarray(p, float))):
                raise RegistrationInputError(f"landmark {name} is not a finite point", field=name)

    sim, align_info = initial_alignment(model, skin, landmarks, opt, bones)
    # bones in the same units as the skin (checked after alignment: bones must sit under the skin)
    skin_box = np.array([skin.vertices.min(0), skin.vertices.max(0)])
    for name, b in bones.items():
        c = b.vertices.mean(0)
        margin = 0.5 * (skin_box[1] - skin_box[0])
        if np.any(c < skin_box[0] - margin) or np.any(c > skin_box[1] + margin):
            raise RegistrationInputError(
                f"the bone surface '{name}' lies outside the skin surface (centre "
                f"{np.round(c, 1).tolist()} mm): bones and skin must share one frame and unit",
                file=files.get(name), field="bone")
    # the elastic stage works in the generic model's frame (the patient data mapped back by the
    # inverse similarity), so that the FFD lattice is aligned with the face whatever the pose
    inv = sim.inverse()
    skin_g = skin.transformed(inv.scale, inv.rotation, inv.translation)
    bones_g = {k: b.transformed(inv.scale, inv.rotation, inv.translation) for k, b in bones.items()}
    x = np.array(model.nodes, dtype=float)
    times["align_s"] = time.perf_counter() - t0

    # coverage: how much of the face the patient skin covers once aligned
    normals = vertex_normals(x, skin_tris)
    cl = skin_g.closest(x[skin_ids])
    covered = (~cl.on_boundary & (cl.distance < 10.0)
               & (np.einsum("ij,ij->i", normals[skin_ids], cl.normal) > 0.5))
    coverage = float(covered.mean())
    if coverage < opt.coverage_min:
        raise RegistrationInputError(
            f"after alignment the patient skin covers only {100 * coverage:.0f}% of the face "
            f"model (at least {100 * opt.coverage_min:.0f}% needed): is it a face, in mm, "
            f"with the face itself scanned?", file=files.get("skin"), field="skin")

    t1 = time.perf_counter()
    groups = _bone_groups(model, bones_g)
    skin_group = SurfaceGroup("skin", skin_ids, skin_g, weight=1.0, tris=skin_tris, facing=1.0)
    lm = None
    clashes = []
    if landmarks and opt.use_landmarks:
        common = [k for k in model.landmark_nodes if k in landmarks]
        if common:
            lm = (np.array([model.landmark_nodes[k] for k in common]),
                  inv.apply(np.array([landmarks[k] for k in common], dtype=float)))
            # landmarks given on one point that the model holds apart: found always, the one
            # farther from its node set aside only on the second attempt
            # (`registration.landmark_fit.contradicting_landmarks`)
            keep, clashes = contradicting_landmarks(x[lm[0]], lm[1])
            clashes = [{**c, "pair": [common[i] for i in c["pair"]], "not_used": common[c["not_used"]],
                        "set_aside": bool(opt.set_aside_contradicting)} for c in clashes]
            if opt.set_aside_contradicting:
                lm = (lm[0][keep], lm[1][keep])
                common = [k for k, u in zip(common, keep) if u]
            used_names = common
    # without landmarks, where the profile pose replaced the surface pose (the bulk fit put the
    # features elsewhere), or where a first registration located landmarks that disagree with
    # the features (`profile_guide`), the features the profile pose found on the skin guide the
    # elastic stage as landmarks do (the stomion nodes both towards the fissure point, which
    # lies between them): the bulk of such a face otherwise slides its mouth and chin along the
    # smooth profile by up to 10-15 mm, beyond the reach of the landmark search that follows.
    # Where the surfaces and the profile agree, the elastic stage and the landmark search need
    # no guide, and a feature found to a few mm must not pull the lips off landmarks the search
    # finds exactly (a lower lip well in front of the upper one: the fissure point lies between).
    guide = lm
    pinfo = align_info.get("profile_pose") or {}
    feats = pinfo.get("features")
    features_ok = lm is None and bool(feats) and "refused" not in pinfo
    if features_ok and (align_info.get("pose") == "profile" or opt.profile_guide):
        pairs = [(k, f) for k, f in (("Prn", "Prn"), ("Sn", "Sn"), ("Stms", "mouth"), ("Stmi", "mouth"),
                                     ("Pog", "Pog")) if k in model.landmark_nodes]
        guide = (np.array([model.landmark_nodes[k] for k, _ in pairs], np.int64),
                 inv.apply(np.array([feats[f] for _, f in pairs], float)))
    # the shape floor of the outlier gate only where given landmarks hold the features
    schedule = opt.schedule if lm is not None else dataclasses.replace(opt.schedule, shape_floor=0.0)
    x, elog = elastic_register(x, skin_group, skin_tris, groups, guide, schedule, seed=opt.seed)
    times["elastic_s"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    lap = mesh_laplacian(len(x), hexes)
    x, snapped = snap_to_surfaces(x, hexes, skin_group, skin_tris, groups, opt.max_snap_mm, lap)
    times["snap_s"] = time.perf_counter() - t2

    # the landmarks the case does not give, located on the patient skin by their definitions
    lm_given = lm
    lm_names = list(used_names) if lm is not None else []
    search_report = None
    located: list[str] = []
    # (a given landmark set aside as contradicting another is not sought either)
    missing = [k for k in model.landmark_nodes if k not in lm_names and k in LOCATED
               and not (landmarks and k in landmarks and opt.use_landmarks)]
    if opt.locate_landmarks and opt.landmark_correction and missing:
        t_s = time.perf_counter()
        carried = {k: x[i] for k, i in model.landmark_nodes.items()}
        frame_info: dict = {}
        head_frame = _head_frame(model, bones_g, opt.seed, frame_info)
        found, search_report = locate_landmarks(skin_g, x, mirror_pairs(model.nodes, skin_ids), carried,
                                                missing, frame=head_frame)
        search_report.update(frame_info)
        if guide is not lm:
            # the elastic stage followed the profile's features: the carried landmarks are within
            # a few mm of their features (the profile pose's own error); one found farther from
            # where it was carried is another feature of the profile (the labiomental fold taken
            # for the mouth slit on a foreign face): it is not used (`far_from_profile_pose`)
            far = far_from_profile_pose(found, carried)
            for k in far:
                del found[k]
            if far:
                search_report["not_used_far_from_profile_pose"] = far
                search_report["not_found"] = sorted(set(search_report["not_found"]) | set(far))
        if guide is lm and lm is None and feats:
            # unguided, the search is checked against the profile's features: a landmark found
            # farther than PROFILE_LOCATED_MAX_MOVE_MM from its feature took another crease of
            # a face the surfaces placed along its profile, and the registration is made again
            # with the features guiding (`match_and_repair_arrays`); the chin's feature, the
            # least sharp (5-9 mm off on some faces), is not used
            mine = {k: found[k] for k in ("Prn", "Sn") if k in found}
            if "Stms" in found and "Stmi" in found:     # the feature is the stomia's midpoint
                mine["mouth"] = 0.5 * (found["Stms"] + found["Stmi"])
            apart = {k: round(float(np.linalg.norm(p - inv.apply(np.asarray(feats[k], float)[None])[0])), 2)
                     for k, p in mine.items()}
            far = {k: v for k, v in apart.items() if v > PROFILE_LOCATED_MAX_MOVE_MM}
            if far:
                align_info["located_far_from_features_mm"] = far
        stomia_as_one(found, missing, search_report)
        if found:
            add = list(found)
            located = add
            nodes_add = np.array([model.landmark_nodes[k] for k in add], dtype=np.int64)
            pts_add = np.array([found[k] for k in add])
            lm = (nodes_add, pts_add) if lm is None else (np.r_[lm[0], nodes_add], np.vstack([lm[1], pts_add]))
            lm_names = lm_names + add
            # where they are in the patient frame, for the report
            for k, v in zip(add, sim.apply(pts_add)):
                search_report["located"][k]["point"] = [float(c) for c in v]
        times["landmark_search_s"] = time.perf_counter() - t_s

    landmark_report = None
    if lm is not None and opt.landmark_correction:
        t_l = time.perf_counter()
        held = np.concatenate([snapped[g.name] for g in groups]) if groups else np.zeros(0, np.int64)
        x, landmark_report = landmark_correction(x, hexes, model.skin_quads, lm[0], lm[1], skin_g,
                                                 snapped["skin"], held, sigma_mm=opt.landmark_sigma_mm,
                                                 max_distance_mm=opt.max_snap_mm,
                                                 max_correction_mm=np.array(
                                                     [opt.located_max_correction_mm if k in located
                                                      else opt.landmark_max_correction_mm for k in lm_names]))
        landmark_report["landmarks_not_followed"] = [lm_names[i] for i in landmark_report["landmarks_not_followed"]]
        times["landmarks_s"] = time.perf_counter() - t_l

    t3 = time.perf_counter()
    on_skin = snapped["skin"]
    if landmark_report and landmark_report["nodes"]:  # now on the patient skin too
        on_skin = np.union1d(on_skin, np.asarray(landmark_report["nodes"], np.int64))
    constraints = [SurfaceConstraint("skin", on_skin, skin_g)]
    constraints += [SurfaceConstraint(g.name, snapped[g.name], g.target) for g in groups]
    # landmark nodes placed on given landmarks stay there (the repair moves their neighbours);
    # should that leave an element below the threshold, the repair runs again with them free
    # (the stages below repair what is left)
    pin = np.asarray(landmark_report["nodes"] if landmark_report else [], np.int64)
    x_held = x[pin].copy()
    x, rep = repair_holding(x, hexes, pin, threshold=opt.threshold, constraints=constraints)
    # the landmarks the repair had to move off their given place, and how far: in the patient
    # frame (mm), the model frame's lengths times the alignment's scale
    moved = dict(zip(pin.tolist(), (sim.scale * np.linalg.norm(x[pin] - x_held, axis=1)).tolist()))
    rep["landmarks_moved_mm"] = {k: round(moved[i], 3) for k, i in model.landmark_nodes.items()
                                 if moved.get(i, 0.0) > 1e-3}
    times["repair_s"] = time.perf_counter() - t3

    x = sim.apply(x)  # back to the patient frame; measured against the patient's own surfaces

    # the facets onto the skin: nodes of the skin quads lying on the patient skin straddle it
    facet_report = None
    if opt.facet_fit:
        t6 = time.perf_counter()
        x, facet_report = facet_fit(x, hexes, covered_skin(x, model.skin_quads, skin_tris, skin)[1],
                                    skin_tris, skin, threshold=opt.threshold,
                                    pinned=np.fromiter(model.landmark_nodes.values(), np.int64,
                                                       len(model.landmark_nodes)))
        times["facet_fit_s"] = time.perf_counter() - t6

    # teeth with their segments (or the patient's own), then the lips cleared of them; skin
    # and attached nodes stay where they are, so the fits below are those of the repair
    t5 = time.perf_counter()
    placed, teeth_info = place_teeth(model.teeth, model.bone_node_sets, np.asarray(model.nodes, float),
                                     x, sim, teeth, skin_ids=skin_ids, clearance=opt.teeth_clearance_mm)
    clearance_report = None
    if placed:
        arches = [Arch(k, v, f, seg) for k, (v, f, seg) in placed.items()]
        keep = np.concatenate([skin_ids] + [np.asarray(i, np.int64) for i in model.bone_node_sets.values()])
        x, clearance_report = clear_teeth(x, hexes, arches, keep, clearance=opt.teeth_clearance_mm,
                                          threshold=opt.threshold)
    times["teeth_clearance_s"] = time.perf_counter() - t5

    # the lips apart across the mouth slit (the stages above move its two sides independently);
    # the teeth cleared again while a movable node is short of their clearance
    lip_report = None
    if model.lip_quads is not None and opt.lip_gap_mm > 0:
        t7 = time.perf_counter()
        attached = np.concatenate([np.asarray(i, np.int64) for i in model.bone_node_sets.values()]
                                  or [np.zeros(0, np.int64)])
        # landmark nodes placed on given landmarks stay there (the other lip moves instead)
        up, low = model.lip_quads
        held_lm = np.asarray(landmark_report["nodes"] if landmark_report else [], np.int64)
        # (the nodes of one lip's contact surface only: the slit's closed ends stay)
        lip_nodes = np.setxor1d(np.unique(up), np.unique(low))
        lip_before = lip_overlap(x, up, low)
        passes = []
        movable = np.setdiff1d(np.arange(len(x)), keep) if placed else None
        released = []
        # the stomia of a lip overhanging the other can cross each other's lip as given (the
        # upper lip's lowest point below the lower lip's highest, hidden behind it): where the
        # lips still cross with them held, both lips make room, those landmark nodes released
        for held in (held_lm, np.setdiff1d(held_lm, lip_nodes)):
            if passes and (lip_overlap(x, up, low)["min_gap_mm"] >= opt.lip_gap_mm - 1e-3
                           or len(held) == len(held_lm)):
                break
            if passes:
                released = [int(i) for i in np.intersect1d(held_lm, lip_nodes)]
            fixed = np.union1d(attached, held)
            best_short = np.inf
            for _ in range(6):
                x, rep_l = separate_lips(x, hexes, up, low, fixed, skin_nodes=skin_ids, skin=skin,
                                         gap=opt.lip_gap_mm, threshold=opt.threshold,
                                         arches=arches if placed else None,
                                         teeth_clearance=opt.teeth_clearance_mm,
                                         skin_release_mm=opt.lip_skin_release_mm)
                passes.append(rep_l)
                if not placed:
                    break
                short = opt.teeth_clearance_mm - \
                    union_distance(arches, x[movable], opt.teeth_clearance_mm + 1.0)[0].min()
                if short <= 1e-6:
                    break  # lips apart and every movable node clear of the teeth
                # a pass that leaves the deepest node no nearer the clearance ends the
                # alternation: the lips and the teeth then take each other's room (tissue
                # thinner than the clearances allow), and each further pass only deforms the
                # mesh more; the depth left is reported, and the prediction's contact start
                # moves the arch back from it (`facemodel.teeth.clear_teeth`)
                if short > best_short - 0.01:
                    break
                best_short = short
                # lip nodes pushed out of the teeth preferably not back into the other lip
                x, again = clear_teeth(x, hexes, arches, keep, clearance=opt.teeth_clearance_mm,
                                       threshold=opt.threshold, away=_lip_away(model, x))
                clearance_report.setdefault("after_lip_separation", []).append(again)
        if placed:
            # where the movable tissue ends against the teeth (negative: inside an arch by so
            # much, which the prediction's contact start resolves by moving the arch)
            clearance_report["min_signed_distance_final_mm"] = float(
                union_distance(arches, x[movable], opt.teeth_clearance_mm + 1.0)[0].min())
        lip_report = {"gap_mm": opt.lip_gap_mm, "before": lip_before, "after": lip_overlap(x, up, low),
                      "landmark_nodes_released": released,
                      "nodes_pushed": int(sum(p["nodes_pushed"] for p in passes)),
                      "elements_repaired": int(sum(p["elements_repaired"] for p in passes)),
                      "passes": passes}
        times["lip_separation_s"] = time.perf_counter() - t7

    t4 = time.perf_counter()
    groups = _bone_groups(model, bones)
    normals = vertex_normals(x, skin_tris)
    cl = skin.closest(x[skin_ids])
    valid = ~cl.on_boundary & (np.einsum("ij,ij->i", normals[skin_ids], cl.normal) > 0.5)
    samples = skin.sample(20000, seed=opt.seed + 1)
    mesh_skin = TargetSurface(x[skin_ids], np.searchsorted(skin_ids, skin_tris), "registered skin")
    back = mesh_skin.closest(samples)
    bone_fit, bone_all = {}, []
    for g in groups:
        cb = g.target.closest(x[g.node_ids])
        d = cb.distance[g.accept(x, cb)]
        bone_fit[g.name] = {**_fit_stats(d), "n_outside_patient_surface": int(len(cb.distance) - len(d))}
        bone_all.append(d)
    # the skin surface itself (bilinear quads sampled at 5 points each, corners excluded)
    # against the patient skin, over quads whose four nodes lie on the patient surface
    node_ok = np.zeros(len(x), bool)
    node_ok[skin_ids[valid]] = True
    quads = np.asarray(model.skin_quads)[node_ok[np.asarray(model.skin_quads)].all(axis=1)]
    uv = np.array([[0.5, 0.5], [0.25, 0.25], [0.75, 0.25], [0.75, 0.75], [0.25, 0.75]])
    shape_fn = np.stack([(1 - uv[:, 0]) * (1 - uv[:, 1]), uv[:, 0] * (1 - uv[:, 1]),
                         uv[:, 0] * uv[:, 1], (1 - uv[:, 0]) * uv[:, 1]], axis=1)
    facet_pts = np.einsum("sc,qcd->qsd", shape_fn, x[quads]).reshape(-1, 3)
    facet_d = skin.closest(facet_pts).distance if len(facet_pts) else np.zeros(0)
    def describe(t: TargetSurface) -> dict:
        return {"triangles": int(len(t.faces)), "area_mm2": t.area,
                "mean_edge_mm": t.mean_edge_length,
                "open_edges": int(t.face_edge_boundary.sum()),
                "reoriented_fraction": t.flipped_fraction}

    report = {
        "input_surfaces": {"skin": describe(skin), **{f"bone.{k}": describe(b) for k, b in bones.items()}},
        "alignment": {**align_info, "matrix": sim.matrix.tolist()},
        "coverage": coverage,
        "fit": {
            "skin": {**_fit_stats(np.concatenate([facet_d, cl.distance[valid]])),
                     "n_outside_patient_surface": int((~valid).sum())},
            "skin_nodes": _fit_stats(cl.distance[valid]),
            "skin_patient_to_mesh": _fit_stats(back.distance[~back.on_boundary]),
            "bone": _fit_stats(np.concatenate(bone_all) if bone_all else np.zeros(0)),
            "bone_segments": bone_fit,
            # the smooth transform alone (last elastic iteration, generic frame), before the
            # projection of the surface nodes: how much the snap had to correct
            "before_snap": {k: v for k, v in (elog.levels[-1] if elog.levels else {}).items()
                            if k.endswith("_mean_mm")},
        },
        "quality": quality_summary(x, hexes, opt.threshold),
        # the skin regions the patient skin covers, and those it does not (carried, not fitted)
        "regions": region_coverage(model.regions, skin_ids, valid & (cl.distance <= opt.max_snap_mm),
                                   cl.distance),
        "repair": rep,
        "landmark_correction": landmark_report,
        "landmark_search": search_report,
        "facet_fit": facet_report,
        "teeth": teeth_info,
        "teeth_clearance": clearance_report,
        "lip_separation": lip_report,
        "elastic": elog.levels,
    }
    report["regions_not_fitted"] = sorted(k for k, v in report["regions"].items() if not v["fitted"])
    # covered skin nodes left far off the scan (MatchOptions.skin_off_scan_gate_mm), by region
    # The model's border columns (its cut edges: the top row over the forehead, the sides, the
    # neck) are not gated: the elastic stage has no support beyond them, so where the scan
    # curves away past the model's edge (a forehead receding behind the generic one) the edge
    # row lags while the rows inside fit. A face misplaced along the scan moves the nodes
    # inside the edge too, and those are gated; a lagging edge is reported here and named by
    # the quality gate's skin maximum (planner.registration_gate).
    off = edge_off = np.zeros(0, np.int64)
    if opt.skin_off_scan_gate_mm is not None:
        far = skin_ids[valid & (cl.distance > opt.skin_off_scan_gate_mm)]
        edge = np.isin(far, np.asarray(model.edge_nodes if model.edge_nodes is not None else [], np.int64))
        off, edge_off = far[~edge], far[edge]
    off_regions = sorted(k for k, v in model.regions.items() if len(np.intersect1d(off, np.asarray(v))))
    report["fit"]["skin_off_scan"] = {"gate_mm": opt.skin_off_scan_gate_mm, "n_nodes": int(len(off)),
                                      "max_mm": float(cl.distance[valid].max()) if valid.any() else None,
                                      "regions": off_regions, "border_nodes_over_gate": int(len(edge_off))}
    if lm_given is not None:
        # distance from each carried landmark node to the given landmark, in the patient frame
        # (those set aside as contradicting another included)
        names = [k for k in model.landmark_nodes if k in landmarks]
        err = np.linalg.norm(x[[model.landmark_nodes[k] for k in names]]
                             - np.array([landmarks[k] for k in names], dtype=float), axis=1)
        report["landmarks"] = {n: {"error_mm": float(e)} for n, e in zip(names, err)}
        if clashes:
            report["landmarks_contradicting"] = clashes
    times["measure_s"] = time.perf_counter() - t4
    times["total_s"] = time.perf_counter() - t0
    report["time"] = times

    # the misplaced face first: it is the cause a failed repair or a poor fit would follow from
    nose = report["regions"].get(NOSE_REGION)
    if align_info.get("method") == "surfaces" and nose is not None and not nose["fitted"]:
        # the scan ends before the nose (the closest patient point of most of the model's nose
        # nodes on the scan's border), or the model's nose was not brought onto the patient's
        ids = np.intersect1d(np.asarray(model.regions[NOSE_REGION], np.int64), skin_ids)
        beyond = float(cl.on_boundary[np.searchsorted(skin_ids, ids)].mean()) if len(ids) else 1.0
        why = (f"the patient skin does not show the nose (the scan ends before "
               f"{100 * beyond:.0f}% of the model's nose region)" if beyond >= 0.5 else
               f"the face model's nose was not brought onto the patient's (only "
               f"{100 * nose['covered_fraction']:.0f}% of the model's nose region fits the skin)")
        kind = RegistrationFailure if beyond >= 0.5 else _NoseNotPlaced
        raise kind(
            f"{why} and the case gives fewer than four landmarks: without the nose nothing on "
            f"the skin fixes where the face sits on it, so the registration and the landmarks "
            f"located on the skin cannot be trusted; give at least four landmarks "
            f"(landmarks.json)", report)
    # the same cause seen on the profile: a skin cut at or just above the nose tip covers the
    # model's nose region, but no point of its profile is a tip with the dorsum above it, so
    # neither the profile pose nor anything else fixes the face's height on the lips and chin
    pinfo = align_info.get("profile_pose") or {}
    if align_info.get("method") == "surfaces" and pinfo.get("nose_tip_found") is False:
        raise RegistrationFailure(
            f"the patient skin's profile shows no nose tip ({pinfo.get('refused')}) and the case "
            f"gives fewer than four landmarks: without the nose tip nothing on the skin fixes how "
            f"high the face sits on it, so the registration and the landmarks located on the skin "
            f"cannot be trusted; give at least four landmarks (landmarks.json)", report)
    if len(off):
        where = f" ({', '.join(off_regions)})" if off_regions else ""
        # the nose off the scan is the same misplacement as the nose not brought onto it
        kind = (_NoseNotPlaced if align_info.get("method") == "surfaces"
                and {NOSE_REGION, "nasal_root"} & set(off_regions) else RegistrationFailure)
        # placed by the surfaces, the face slid along the scan; placed by landmarks, either a
        # landmark is wrong or the skin there has a shape the elastic stage did not reach
        why = ("the model is misplaced along the scan; the skin and bones alone did not place "
               "the face on the scan: give at least four landmarks (landmarks.json)"
               if align_info.get("method") == "surfaces" else
               "the model does not follow the patient skin there, though it is placed by the "
               "landmarks: check those landmarks and that the skin is the patient's face")
        raise kind(
            f"{len(off)} skin node(s) of the face model{where} lie up to "
            f"{report['fit']['skin_off_scan']['max_mm']:.1f} mm off the patient skin where the scan "
            f"covers them (gate {opt.skin_off_scan_gate_mm:g} mm): {why}", report)
    q = min_scaled_jacobian(x, hexes)
    if q.min() < opt.threshold:
        raise RegistrationFailure(
            f"repair left {int((q < opt.threshold).sum())} element(s) below scaled Jacobian "
            f"{opt.threshold} (min {q.min():.3f}, {int((q <= 0).sum())} inverted)", report)
    skin_mean = report["fit"]["skin"]["mean_mm"]
    if skin_mean is None or skin_mean > opt.skin_mean_gate_mm:
        raise RegistrationFailure(f"the registered skin misses the patient skin by {skin_mean} mm "
                                  f"on average (gate {opt.skin_mean_gate_mm} mm)", report)
    return x, sim, report, placed
