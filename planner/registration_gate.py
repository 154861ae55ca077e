"""Quality gate of a registration: fit and repair figures far outside their normal range.

`registration_notes(report)` reads the report of `registration.mesh_match_and_repair` and
returns one sentence per figure far outside what a consistent case gives, naming the likely
cause, one when the landmarks were located on the skin without the head's frame (the skull
fit refused: `registration.mesh_match._head_frame`) and the face not placed by its profile's
features, and one when, without landmarks, the profile's features could not be found
(`registration.profile_pose`): the placement then rests on the surfaces' bulk fit alone, one
when, without landmarks, both stomia found on the skin were set aside (the lips then rest on
the profile's features alone), and one per pair of given landmarks that contradict each
other for the model (set aside or not), and one naming the given landmarks the mesh repair had
to move off their place. On consistent cases (the synthetic heads,
the demo head) the skin fit has a p95 below 1 mm and a maximum below 3 mm, the bone fit a mean
below 0.5 mm and a maximum below ~10 mm (the chin's edge), and the repair touches 1-2 % of the
elements; the limits below are two to three times those, so a note means that something in the
inputs disagrees (an LPS/RAS mix-up of one file, swapped or foreign bone surfaces, a partial or
noisy skin), not bad luck. A skin maximum out of range with a p95 within it is told apart: a
frame mix-up moves the whole skin, so one far part is a local shape the generic face did not
reach.
"""
from __future__ import annotations

SKIN_P95_MM = 2.5
SKIN_MAX_MM = 8.0
BONE_MEAN_MM = 1.5
BONE_MAX_MM = 20.0
REPAIRED_FRACTION = 0.08
# a given landmark the repair moved farther than this is named: the precision with which a
# landmark is placed on a CT-derived skin (about a voxel) and the skin fit's normal maximum
LANDMARK_MOVED_MM = 1.0
# how the note on lips that nothing on the skin confirmed begins (`bench/heads.py` counts it)
LIPS_UNCONFIRMED = "the mouth slit found on the skin lies"


def _get(d, *keys):
    for k in keys:
        if not isinstance(d, dict) or d.get(k) is None:
            return None
        d = d[k]
    return d


def registration_notes(report: dict) -> list[str]:
    """Sentences naming each fit or repair figure far outside its normal range and its likely
    cause; empty for a registration within range."""
    notes = []
    p95, mx = _get(report, "fit", "skin", "p95_mm"), _get(report, "fit", "skin", "max_mm")
    if p95 is not None and p95 > SKIN_P95_MM:
        top = f", max {mx:.1f} mm" if mx is not None else ""
        notes.append(f"the registered skin is far from the patient skin (p95 {p95:.1f} mm{top}; "
                     f"normal < {SKIN_P95_MM} / {SKIN_MAX_MM} mm): the skin, bones or landmarks are in "
                     "different frames (LPS vs RAS), or the skin is partial or noisy")
    elif mx is not None and mx > SKIN_MAX_MM:
        # the bulk fits: a frame mix-up moves the whole skin, so only a local cause is left
        notes.append(f"part of the registered skin is far from the patient skin (max {mx:.1f} mm, normal "
                     f"< {SKIN_MAX_MM} mm) while the rest fits{f' (p95 {p95:.1f} mm)' if p95 is not None else ''}: a local shape the "
                     "generic face does not reach (a receding forehead, a deep nasal root) or a spike "
                     "on the skin surface; check the images there")
    mean, bmax = _get(report, "fit", "bone", "mean_mm"), _get(report, "fit", "bone", "max_mm")
    if (mean is not None and mean > BONE_MEAN_MM) or (bmax is not None and bmax > BONE_MAX_MM):
        segs = _get(report, "fit", "bone_segments") or {}
        worst = max(segs, key=lambda s: segs[s].get("max_mm") or 0.0) if segs else None
        notes.append(f"the bone attachments are far from the bone surfaces (mean {mean:.1f} mm, max "
                     f"{bmax:.1f} mm{f' at {worst}' if worst else ''}; normal < {BONE_MEAN_MM} / "
                     f"{BONE_MAX_MM} mm): bone files swapped between segments, or bones from another "
                     "scan or frame")
    repaired = _get(report, "repair", "elements_needing_repair")
    n = report.get("n_elements")
    if repaired is not None and n and repaired > REPAIRED_FRACTION * n:
        notes.append(f"{repaired} of {n} elements needed repair (normal < {REPAIRED_FRACTION:.0%}): the "
                     "inputs pull the mesh in contradicting directions (skin, bones and landmarks "
                     "disagree)")
    refused = _get(report, "landmark_search", "head_frame_refused")
    by_profile = _get(report, "alignment", "pose") == "profile"
    if refused and not by_profile:
        notes.append(f"the landmarks were located on the skin without the head's own frame ({refused}): "
                     "on a face unlike the generic model they can be 10-20 mm off along the profile; "
                     "give at least four landmarks (landmarks.json)")
    for clash in report.get("landmarks_contradicting") or []:
        a, b = clash["pair"]
        done = (f"{clash['not_used']} was not used (the registration failed with both)"
                if clash.get("set_aside") else "both were followed")
        notes.append(f"landmarks {a} and {b} are given {clash['given_apart_mm']:.1f} mm apart where the face "
                     f"model holds them {clash['model_apart_mm']:.1f} mm apart: {done}; check them in "
                     "landmarks.json")
    # without landmarks, both stomia found on the skin set aside (found far from where the
    # registration guided by the profile's features carried them, or with their partner): the
    # slit the search took is another crease or the registration carried the mouth elsewhere;
    # either way nothing on the skin confirmed where the lips are
    search = report.get("landmark_search") or {}
    unused = set(search.get("not_used_far_from_profile_pose") or []) | \
        set(search.get("not_used_partner_set_aside") or [])
    if {"Stms", "Stmi"} <= unused:
        moved = [_get(search, "located", k, "moved_mm") for k in ("Stms", "Stmi")]
        moved = [m for m in moved if m is not None]
        apart = f" {max(moved):.0f} mm" if moved else ""
        notes.append(f"{LIPS_UNCONFIRMED}{apart} from where the registration put the "
                     "stomia and was not used: the lips are placed by the profile's features alone and "
                     "can be several mm off; check the lips in the images, or give at least four "
                     "landmarks (landmarks.json)")
    moved = {k: v for k, v in (_get(report, "repair", "landmarks_moved_mm") or {}).items()
             if v > LANDMARK_MOVED_MM}
    if moved:
        which = ", ".join(f"{k} {v:.1f} mm" for k, v in sorted(moved.items(), key=lambda kv: -kv[1]))
        notes.append(f"the mesh repair moved given landmark(s) off their place ({which}): held there, "
                     "the elements around them could not all be made valid (tissue thinner than the "
                     "model's layers there, or landmarks that pull the mesh against the skin); check "
                     "them in landmarks.json and the region in the images")
    why = _get(report, "alignment", "profile_pose", "refused")
    if why and _get(report, "alignment", "method") == "surfaces":
        notes.append(f"the face was placed on the skin by its surfaces alone, its profile's features not "
                     f"checked ({why}): on a face unlike the generic model the mouth and chin can be "
                     "10-20 mm off; give at least four landmarks (landmarks.json)")
    return notes
