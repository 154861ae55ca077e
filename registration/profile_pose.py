"""Landmark-free pose of a face from its mid-sagittal profile: symmetry plane, then features.

The surface alignment (`registration.alignment.align_surfaces`: trimmed ICP of skin and bones)
fits the bulk of the face; on a face of other proportions than the generic one (a flatter or
blockier face, a longer lower face) the best bulk fit can be tilted by 10-15 degrees and put
the generic mouth 10 mm from the patient's, beyond what the elastic stage and the local
landmark search recover. This module corrects that pose from what the face shows whatever
its proportions, in the generic model's frame (x right, y anterior, z superior), starting
from the surface alignment:

1. the mid-sagittal plane: the plane about which the patient skin is most nearly its own
   mirror image, found by a rigid trimmed ICP of the mirrored skin onto the skin (the
   composition of the mirror and the rigid motion is the reflection about the symmetry
   plane: its normal is the eigenvector of eigenvalue -1, its offset half the translation's
   component along it; cf. Mitra, Guibas and Pauly, "Partial and approximate symmetry
   detection for 3D geometry", SIGGRAPH 2006, for symmetry by registration to the mirror);
   the pose is turned so that this plane is x = 0, which fixes yaw, roll and the lateral shift;
2. the profile: the skin cut by that plane (`landmark_search.sagittal_profile`), on which the
   anatomical features are found by their definitions (Farkas 1994) with measures that do not
   depend on the starting pose's pitch: pronasale (the most anterior point of the stretch of
   profile standing farthest in front of the face's surface continued from beside it, at
   x = +-20 mm extrapolated from +-35 mm, height for height; with the nasal dorsum above it,
   nothing above it standing farther forward, and standing NOSE_MIN_PROMINENCE_MM out on the
   tip or the dorsum above it), the oral fissure (a crease 12-60 mm below, where
   the lips meet at an angle: the point farthest behind the chord of the profile
   FISSURE_HALF_CHORD_MM either side beyond what the profile's curvature explains, which tells
   it from the smooth nasolabial and labiomental concavities, `crease_depth`), subnasale (the deepest concavity under the
   anterior hull between them) and soft pogonion (the anterior hull vertex below the
   labiomental fold, the deepest concavity below the mouth). Up to NOSE_CANDIDATES stretches
   are tried as the nose and MOUTH_CANDIDATES grooves as the fissure, most crease-like first;
3. the in-plane similarity (rotation about x, translation in y and z, one scale) taking the
   generic model's landmark nodes Prn, Sn, the stomion midpoint and Pog onto those features,
   in closed form (Umeyama 1991 in the plane, with complex numbers), for the first feature set
   in profile order (the generic proportions do not choose the fissure: on a face of other
   proportions a fold fits them better than the mouth does); steps 1-3 are repeated once from the corrected pose
   (a repetition that finds no feature set keeps the first pose).

The pose is accepted only when every feature is found, in profile order, the features fit a
similarity to FEATURE_RMS_MAX_MM RMS and the pose turns the face by at most MAX_PITCH_DEG from
the surface alignment; otherwise `profile_pose` returns None with the reason, and the caller
keeps the surface pose and says so (`registration.mesh_match`, `planner.registration_gate`).
A skin that does not show the nose tip (a CBCT cut through the nose) has no pronasale: nothing
on it fixes the face's height (the lips and chin are smooth along the profile).
"""
from __future__ import annotations

import numpy as np

from registration.alignment import Similarity, trimmed_icp
from registration.landmark_search import deepest_under_bitangent, most_anterior, plane_cut, sagittal_profile
from registration.surface import TargetSurface

# mm: half-length of the chord the oral fissure's depth is measured under: a little more than
# the slit's own half-width, so that the chord rests on the lips either side, and well under
# the width of the nasolabial and labiomental concavities (10-20 mm), which are shallow under
# such a chord
FISSURE_HALF_CHORD_MM = 2.5
# mm: the skin the nose is compared with lies this far to either side of the midline: past
# the alae (the nose's half-width is 10-18 mm at its base), well within the mouth's and the
# chin's half-widths (20-28 mm, 15-25 mm), where those stand out nearly as much as on the midline
LATERAL_MM = 20.0
LATERAL_FAR_MM = 35.0
# mm: how far a profile point above pronasale may stand in front of it (the brow of a face
# tilted forward by the starting pose's error) before the nose is taken to be cut
PRN_ABOVE_TOL_MM = 2.0
# mm of profile the scan must show above pronasale (the nasal dorsum): where the scan is cut
# at or below the tip, the most prominent point is the cut edge itself
PRN_ARC_ABOVE_MM = 5.0
# mm of profile either side of the most prominent point searched for the nose's tip: about
# the nose's length along the profile
NOSE_ARC_MM = 15.0
# mm: the least a nose stands in front of the face's surface continued from beside it
# (`_side_height`), on its tip or the dorsum above it (`_nose_prominence`): noses stand
# 10-20 mm out by that measure, a lip or chin left below a nose cut
# off by the scan stands level with it or behind it
NOSE_MIN_PROMINENCE_MM = 5.0
# the most prominent stretches of profile tried as the nose (nose, chin, lips)
NOSE_CANDIDATES = 3
# the most crease-like grooves below the nose tried as the oral fissure
MOUTH_CANDIDATES = 3
# mm below pronasale where the fissure is sought: subnasale lies above the window's top on
# every face the generic model describes (nose tip to subnasale 10-20 mm along the profile),
# and the window reaches past the longest upper lip (nose tip to stomion ~45 mm at most)
MOUTH_BELOW_PRN_MM = (12.0, 60.0)
# mm below the stomion where the chin is sought (stomion to soft menton is 35-60 mm)
CHIN_BELOW_MOUTH_MM = 70.0
# mm: RMS of the four features about their similarity above which the pose is refused: faces
# of other proportions leave 2-6 mm (the similarity cannot stretch the lower face alone); a
# feature found on the wrong part of the profile leaves 10 mm or more
FEATURE_RMS_MAX_MM = 8.0
# deg: the largest rotation from the surface alignment believed; that pose is within ~15 deg
MAX_PITCH_DEG = 25.0
MIRROR = np.diag([-1.0, 1.0, 1.0])
FEATURES = ("Prn", "Sn", "mouth", "Pog")
# the refusal of a profile without a nose tip: the one that leaves the face's height unfixed
NO_NOSE_TIP = ("no point of the patient skin's profile stands out like a nose tip with the nasal "
               "dorsum above it: the scan does not show the nose tip")


def mirrored(skin: TargetSurface) -> TargetSurface:
    """The skin reflected about x = 0 (triangles re-wound so that normals stay outward)."""
    return TargetSurface(skin.vertices @ MIRROR, skin.faces[:, ::-1].copy(), skin.name + " (mirrored)")


def symmetry_frame(skin: TargetSurface, seed: int = 0) -> tuple[Similarity, dict]:
    """The rigid motion taking `skin` (roughly in the generic frame) to a frame in which its
    symmetry plane is x = 0, by the least rotation that turns the plane's normal onto x."""
    icp = trimmed_icp(mirrored(skin), skin, Similarity.identity(), n_points=1500, iterations=60,
                      seed=seed, fix_scale=True, tol=0.0, step_tol=0.01)
    a = icp.similarity.rotation @ MIRROR          # the reflection, linear part
    w, v = np.linalg.eigh(0.5 * (a + a.T))
    n = v[:, int(np.argmin(w))]
    if n[0] < 0:
        n = -n
    offset = 0.5 * float(n @ icp.similarity.translation)    # plane: n . p = offset
    # least rotation taking n onto the x axis (Rodrigues), then the plane shifted onto x = 0
    ex = np.array([1.0, 0.0, 0.0])
    axis = np.cross(n, ex)
    s, c = np.linalg.norm(axis), float(n @ ex)
    if s < 1e-12:
        rot = np.eye(3)
    else:
        k = axis / s
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        rot = np.eye(3) + s * kx + (1 - c) * kx @ kx
    frame = Similarity(1.0, rot, -offset * ex)
    return frame, {"symmetry_rms_mm": icp.rms_mm, "symmetry_tilt_deg": float(np.degrees(np.arctan2(s, c))),
                   "symmetry_offset_mm": offset}


def _chord_depth(p: np.ndarray, half: float) -> np.ndarray:
    """Per profile point: how far it lies behind (posterior to) the chord joining the profile
    points `half` mm of arc before and after it; -inf where the arc does not reach."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p[:, 1:], axis=0), axis=1))])
    out = np.full(len(p), -np.inf)
    ok = (s - half >= 0) & (s + half <= s[-1])
    for i in np.flatnonzero(ok):
        a = np.array([np.interp(s[i] - half, s, p[:, k]) for k in (1, 2)])
        b = np.array([np.interp(s[i] + half, s, p[:, k]) for k in (1, 2)])
        t = b - a
        nrm = np.array([-t[1], t[0]]) / max(np.linalg.norm(t), 1e-12)
        if nrm[0] > 0:        # pointing posterior (-y)
            nrm = -nrm
        out[i] = float((p[i, 1:] - a) @ nrm)
    return out


def crease_depth(p: np.ndarray, half: float) -> np.ndarray:
    """Per profile point: the depth under the chord of half-length `half` beyond what the
    profile's curvature there explains. A smooth concavity of curvature k lies k h^2 / 2 behind
    a chord of half-length h, so its depth under 2h is four times that under h and
    d(h) - d(2h) / 4 vanishes; a crease (two surfaces meeting at an angle, the lips at the
    oral fissure) lies a h behind, linear in h, and keeps d(h) / 2. Where the arc does not
    reach 2h either side the plain depth d(h) is used; -inf where it does not reach h."""
    near, broad = _chord_depth(p, half), _chord_depth(p, 2.0 * half)
    both = np.isfinite(broad)
    near[both] -= 0.25 * broad[both]
    return near


def _front_height(skin: TargetSurface, x0: float, z: np.ndarray) -> np.ndarray:
    """Per height z: the skin's most anterior y on the plane x = x0 (NaN where its cut does
    not reach that height)."""
    best = np.full(len(z), -np.inf)
    for chain in plane_cut(skin.vertices, skin.faces, x0):
        a, b = chain[:-1], chain[1:]
        lo, hi = np.minimum(a[:, 2], b[:, 2]), np.maximum(a[:, 2], b[:, 2])
        inside = (z[:, None] >= lo[None]) & (z[:, None] <= hi[None]) & (hi - lo > 1e-9)[None]
        t = (z[:, None] - a[None, :, 2]) / np.where(hi - lo > 1e-9, b[:, 2] - a[:, 2], 1.0)[None]
        y = np.where(inside, a[None, :, 1] + t * (b[None, :, 1] - a[None, :, 1]), -np.inf)
        best = np.maximum(best, y.max(axis=1, initial=-np.inf))
    return np.where(np.isfinite(best), best, np.nan)


def _side_height(skin: TargetSurface, z: np.ndarray) -> np.ndarray:
    """Per height z: the face's own surface continued to the midline from beside it: the
    anterior y at x = +-LATERAL_MM extrapolated linearly from x = +-LATERAL_FAR_MM, averaged
    over both sides (the face's round shape and a jaw tapering towards the chin removed;
    NaN where a plane's cut does not reach that height)."""
    near = 0.5 * (_front_height(skin, -LATERAL_MM, z) + _front_height(skin, LATERAL_MM, z))
    far = 0.5 * (_front_height(skin, -LATERAL_FAR_MM, z) + _front_height(skin, LATERAL_FAR_MM, z))
    return near + (near - far) * LATERAL_MM / (LATERAL_FAR_MM - LATERAL_MM)


def profile_features(skin: TargetSurface, generic: dict) -> tuple[dict | None, str]:
    """The features on the profile x = 0 of `skin` (in a frame where its symmetry plane is
    x = 0 and the face roughly in the generic place); `generic`: the generic model's feature
    positions (FEATURES). Returns ({name: (3,)}, "") or (None, reason)."""
    p = sagittal_profile(skin, 0.0, generic["Prn"], 250.0)
    if len(p) < 10:
        return None, "the patient skin does not cross its own symmetry plane near the nose"
    z = p[:, 2]
    # pronasale: the profile point standing farthest in front of the face's surface continued
    # from beside it (`_side_height`): the nose is narrow and stands 15-25 mm out of the face,
    # lips and chin are broad and stand out less; a height-for-height comparison, so the pitch
    # of the starting pose does not enter. Where the scan is cut through the nose, the stump
    # at the cut edge is that point, or stands in front of what is found lower down: refused
    side = _side_height(skin, p[:, 2])
    # only where the profile faces forward (steeper than 45 deg): under the chin or the nose
    # the skin beside it at the same height lies far behind along a nearly level surface
    t = np.gradient(p[:, 1:], axis=0)
    prom = np.where(np.abs(t[:, 1]) > np.abs(t[:, 0]), p[:, 1] - side, np.nan)
    if not np.isfinite(prom).any():
        return None, "the patient skin's profile has no skin beside it: it does not look like a face"
    # the tip: the most anterior point of the nose's stretch of profile (the prominence is
    # largest where the skin beside the nose recedes most, which can be above the tip). The
    # candidates are tried from the most prominent down (a broad chin can stand out of a
    # tapering jaw as much as a small nose): a chin or lip is refused by the nose above it
    s_arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p[:, 1:], axis=0), axis=1))])
    order = np.argsort(-np.where(np.isfinite(prom), prom, -np.inf))
    tried: list[float] = []
    i_prn = None
    for i_nose in order[:len(order) - int(np.isnan(prom).sum())]:
        if any(abs(s_arc[i_nose] - t) <= NOSE_ARC_MM for t in tried):
            continue
        if len(tried) == NOSE_CANDIDATES:
            break
        tried.append(float(s_arc[i_nose]))
        near = np.flatnonzero(np.abs(s_arc - s_arc[i_nose]) <= NOSE_ARC_MM)
        i_tip = int(near[np.argmax(p[near, 1])])
        nose_prom = _nose_prominence(prom, s_arc, i_tip)
        if (s_arc[i_tip] >= PRN_ARC_ABOVE_MM and p[:i_tip + 1, 1].max() <= p[i_tip, 1] + PRN_ABOVE_TOL_MM
                and nose_prom >= NOSE_MIN_PROMINENCE_MM):
            i_prn = i_tip
            break
    if i_prn is None:
        return None, NO_NOSE_TIP
    prn = most_anterior(p, max(0, i_prn - 20), min(len(p) - 1, i_prn + 20))
    lo, hi = prn[2] - MOUTH_BELOW_PRN_MM[0], prn[2] - MOUTH_BELOW_PRN_MM[1]
    band = np.flatnonzero((z < lo) & (z > hi) & (np.arange(len(p)) > i_prn))
    depth = crease_depth(p, FISSURE_HALF_CHORD_MM)
    if len(band) < 3 or not np.isfinite(depth[band]).any():
        return None, "the patient skin's profile does not reach the mouth below the nose"
    # the fissure: the grooves of the band ranked by their crease depth (the nasolabial or
    # labiomental concavity can be as deep under the short chord on a blocky face, but it is a
    # smooth concavity: its crease depth is near zero); each gives a feature set, in that
    # order, and the caller keeps the first whose features lie in profile order
    d = np.where(np.isfinite(depth[band]), depth[band], -np.inf)
    peaks = [k for k in range(len(band)) if d[k] > 0 and d[k] >= d[max(k - 1, 0)] and d[k] >= d[min(k + 1, len(band) - 1)]]
    peaks.sort(key=lambda k: -d[k])
    chosen: list[int] = []
    for k in peaks:
        if all(abs(s_arc[band[k]] - s_arc[band[j]]) > 2 * FISSURE_HALF_CHORD_MM for j in chosen):
            chosen.append(k)
        if len(chosen) == MOUTH_CANDIDATES:
            break
    if not chosen:
        return None, "no oral fissure (a groove between the lips) on the patient skin's profile"
    out, why = [], ""
    for k in chosen:
        f, why = _below_mouth(p, z, i_prn, int(band[k]), prn)
        if f is not None:
            f["nose_prominence_mm"] = nose_prom
            out.append(f)
    return (out or None), why


def _nose_prominence(prom: np.ndarray, s_arc: np.ndarray, i_tip: int) -> float:
    """How far the nose whose tip is profile vertex `i_tip` stands out of the face: the largest
    prominence (`prom`, NaN where the profile does not face forward) on the tip and the
    NOSE_ARC_MM of profile above it (the lower nasal dorsum); -inf where none is defined.
    Measured at the tip alone it depends on the pose: the planes beside the nose can cross a
    broad nose's alae just below the tip, which stand nearly as far forward as the tip, and a
    few degrees of pitch bring the tip to their height; along the dorsum the cheeks recede."""
    above = np.flatnonzero((s_arc >= s_arc[i_tip] - NOSE_ARC_MM) & (s_arc <= s_arc[i_tip]))
    vals = prom[above]
    vals = vals[np.isfinite(vals)]
    return float(vals.max()) if len(vals) else -np.inf


def _below_mouth(p, z, i_prn, i_mouth, prn):
    """Subnasale, pogonion for the fissure at profile vertex i_mouth: the feature set, or
    (None, reason)."""
    i_sn = deepest_under_bitangent(p, i_prn, i_mouth) if i_mouth - i_prn >= 3 else None
    below = np.flatnonzero((z < p[i_mouth, 2] - 3.0) & (z > p[i_mouth, 2] - CHIN_BELOW_MOUTH_MM)
                           & (np.arange(len(p)) > i_mouth))
    if i_sn is None or len(below) < 6:
        return None, "the patient skin's profile does not reach the chin"
    # the labiomental fold: the deepest concavity under the anterior hull from below the
    # fissure (past the lower lip's roll) down to the profile's lowest point (the chin's
    # underside: beyond it the submental contour runs back); pogonion the chin's summit below
    start = int(below[0])
    end = int(below[np.argmin(z[below])])
    if end - start < 4:
        return None, "the patient skin's profile does not reach the chin"
    i_fold, (_, i_pog, _) = deepest_under_bitangent(p, start, end, with_span=True)
    if i_pog >= end:   # no summit in front of the chin's underside: the chin below the fold
        i_pog = i_fold + int(np.argmax(p[i_fold:end + 1, 1]))
    pog = most_anterior(p, max(i_fold, i_pog - 10), min(end, i_pog + 10))
    return {"Prn": prn, "Sn": p[i_sn].copy(), "mouth": p[i_mouth].copy(), "Pog": pog}, ""


def plane_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[Similarity, float]:
    """The similarity about the x axis (rotation about x, scale, translation in y, z) taking
    the (y, z) of src onto those of dst in least squares (Umeyama in the plane: the complex
    ratio of the centred point sets), and its RMS residual (mm, in the plane)."""
    a = src[:, 1] + 1j * src[:, 2]
    b = dst[:, 1] + 1j * dst[:, 2]
    am, bm = a.mean(), b.mean()
    k = np.sum((b - bm) * np.conj(a - am)) / np.sum(np.abs(a - am) ** 2)
    scale, theta = float(abs(k)), float(np.angle(k))
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    t = bm - k * am
    sim = Similarity(scale, rot, np.array([0.0, t.real, t.imag]))
    rms = float(np.sqrt(np.mean(np.abs(k * a + t - b) ** 2)))
    return sim, rms


def _one_pass(skin: TargetSurface, start: Similarity, generic: dict, seed: int):
    inv = start.inverse()
    skin_g = skin.transformed(inv.scale, inv.rotation, inv.translation)
    frame, info = symmetry_frame(skin_g, seed)
    skin_s = skin_g.transformed(frame.scale, frame.rotation, frame.translation)
    sets, why = profile_features(skin_s, generic)
    if sets is None:
        info["refused"] = why
        info["nose_tip_found"] = why != NO_NOSE_TIP
        return None, info
    src = np.array([generic[k] for k in FEATURES])
    best = None
    for found in sets:      # the most crease-like fissure first
        dst = np.array([found[k] for k in FEATURES])
        if np.any(np.diff(dst[:, 2]) >= 0):
            continue
        plane, rms = plane_similarity(src, dst)
        best = (plane, rms, found)
        break
    if best is None:
        info["refused"] = "the features found on the profile are not in their top-to-bottom order"
        return None, info
    plane, rms, found = best
    info["nose_prominence_mm"] = found.pop("nose_prominence_mm", None)
    info["candidates"] = len(sets)
    pitch = float(np.degrees(np.arctan2(plane.rotation[2, 1], plane.rotation[1, 1])))
    back = start.compose(frame.inverse())
    info.update(features_rms_mm=rms, pitch_correction_deg=pitch, plane_scale=plane.scale,
                features={k: [float(c) for c in back.apply(v)] for k, v in found.items()})
    return back.compose(plane), info


def profile_pose(skin: TargetSurface, start: Similarity, generic: dict, seed: int = 0, passes: int = 2):
    """The pose generic -> patient from the patient skin's symmetry plane and profile features,
    starting from `start` (the surface alignment). `generic`: the generic model's positions of
    FEATURES (its landmark nodes; "mouth" the stomia's midpoint). The features are found again
    from the corrected pose (`passes` in all: a large pitch of the start shifts the windows);
    a later pass that finds no features keeps the last accepted pose (`info["passes"]` the
    passes used, `info["later_pass_refused"]` why the next one found none).
    Returns (Similarity or None, info) -- None with info["refused"] naming why."""
    pose, info = start, {}
    for k in range(passes):
        new, info_k = _one_pass(skin, pose, generic, seed)
        if new is None:
            if k == 0:
                return None, info_k
            # a later pass that finds no feature set keeps the pose of the last one that did:
            # those features passed every test (order, fit, turn), and what the later pass
            # misses is a test at its limit under the shifted sampling of the profile (a scan
            # cut about PRN_ARC_ABOVE_MM above the nose tip, a prominence near its threshold)
            info["passes"] = k
            info["later_pass_refused"] = info_k.get("refused")
            return pose, info
        info = info_k
        total = float(np.degrees(np.arccos(np.clip((np.trace(new.rotation @ start.rotation.T) - 1) / 2, -1, 1))))
        info["rotation_from_surface_pose_deg"] = total
        if info["features_rms_mm"] > FEATURE_RMS_MAX_MM:
            info["refused"] = (f"the nose, mouth and chin found on the profile fit the face model's only "
                               f"to {info['features_rms_mm']:.1f} mm RMS (at most {FEATURE_RMS_MAX_MM:g})")
            return None, info
        if total > MAX_PITCH_DEG:
            info["refused"] = (f"the profile's features turn the face by {total:.0f} deg from the surface "
                               f"alignment (at most {MAX_PITCH_DEG:g})")
            return None, info
        pose = new
    info["passes"] = passes
    return pose, info
