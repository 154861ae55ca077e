"""Attachments that depend on the operation: the tissue a genioplasty degloves.

An intra-oral sliding genioplasty is reached through a vestibular incision: the periosteum
and the mentalis are stripped from the anterior mandible between the vestibule fornix and the
osteotomy (between the mental nerves), and along the cut to the lower border, while the chin
segment keeps its soft-tissue pedicle (Trauner R., Obwegeser H., Oral Surg Oral Med Oral
Pathol 10:677-689, 1957; Hoenig J.F., Aesthetic Plast Surg 31:384-391, 2007). The generic
face lists these mandible-tied deep nodes as node set "release_genioplasty"
(`generic_mesh.builder._genioplasty_release`). They stay tied for plans without a
genioplasty; with one, tying them to the mandible while the chin moves would impose the bony
step at the cut on the tissue as a displacement jump between neighbouring nodes: on a 5 mm
advancement the soft-tissue pogonion then follows the chin by 1.035 (coarse) / 0.966
(standard), and the fine mesh inverts elements; with the nodes released, by 1.014 / 0.978 /
0.975 (coarse / standard / fine; published 0.8-1.0).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

__all__ = ["RELEASE_SET", "has_genioplasty", "release_for_plan"]

RELEASE_SET = "release_genioplasty"


def has_genioplasty(motions: dict, tol: float = 1e-9) -> bool:
    """True if the chin segment moves relative to the mandible in `motions` {segment: 4x4}
    (an identity is assumed for a segment not given)."""
    eye = np.eye(4)
    chin = np.asarray(motions.get("chin", eye), float)
    mandible = np.asarray(motions.get("mandible", eye), float)
    return bool(np.abs(chin - mandible).max() > tol)


def release_for_plan(model, motions: dict):
    """The model with the genioplasty's degloved nodes moved from "attach_mandible" to
    "deep_free" when `motions` hold a genioplasty; the model itself otherwise (or when it
    has no such node set)."""
    ids = np.asarray(model.node_sets.get(RELEASE_SET, ()), dtype=np.int64)
    if not len(ids) or not has_genioplasty(motions):
        return model
    sets = dict(model.node_sets)
    sets["attach_mandible"] = np.setdiff1d(np.asarray(sets.get("attach_mandible", ()), np.int64), ids)
    sets["deep_free"] = np.union1d(np.asarray(sets.get("deep_free", ()), np.int64), ids)
    return replace(model, node_sets=sets)
