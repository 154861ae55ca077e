"""Anatomical landmarks located on the patient skin, for those the case does not give.

The elastic registration carries the generic model's landmark nodes onto the patient skin but
lets them slide along it (closest-point correspondences fix the normal offset left by the
alignment, not the tangential one: several mm on the nose tip, the lips and the chin of a
strong class II / III). Each soft-tissue landmark the case does not give is therefore found by
its anatomical definition (Farkas, Anthropometry of the Head and Face, 1994; Swennen et al.,
Three-Dimensional Cephalometry, 2006) on the patient skin near where the registration carried
it, in the generic model's frame (x right, y anterior, z superior; the patient surface mapped
back by the alignment similarity):

* mid-sagittal plane near a landmark: x = the median of the midpoints of registered skin nodes
  that are mirror images of each other on the symmetric generic mesh, within `MIDLINE_RADIUS`
  of the carried landmark (a slide common to both sides cancels in the midpoint; the lower face
  of an asymmetric head shifts sideways, and so does this plane), then refined on the scan
  itself: the plane about which the skin within `SYMMETRY_RADIUS` of the landmark is most
  nearly its own mirror image (`symmetry_plane`; the registered pairs alone left subnasale and
  labrale superius up to 1.2 mm to the side on the bench heads, the scan's symmetry 0.3 mm);
* sagittal profile: the patient skin cut by that plane (exact triangle-plane intersection,
  chained along the cut edges into a polyline, oriented downwards);
* pronasale (Prn): the most anterior profile point of the nose; labrale superius (Ls) and
  inferius (Li): the most anterior points of the upper lip below subnasale and of the lower lip
  above the labiomental fold; soft pogonion (Pog): the most anterior point of the chin below
  the fold. Each maximum is refined by a parabola through the profile vertices within +-3 mm of
  arc length of the best vertex (the scan's facets cut convex tips) and Li and Pog are taken on
  their own local mid-sagittal plane. Pogonion is the chin's summit, past the bottom of the
  fold's valley (a chin receding down to the profile's end has none: pogonion is then the
  fold's lower edge), as `facemodel.head_geometry.anatomical_landmarks` defines it;
* subnasale (Sn) and the labiomental fold: the deepest points under the profile's anterior
  convex hull edges (bitangents) that span the nasolabial and labiomental concavities; the
  subnasale corner is sharper than the scan's facets, which bridge it by a chord: it is taken
  where the columella's and the upper lip's last chords, extended, meet behind that chord,
  projected onto the skin (`concave_corner`);
* stomion superius / inferius (Stms, Stmi): the ends of the lips at the mouth slit. A scan with
  facets of a few mm bridges the step between an overhanging lip and the receding one by one
  long facet (the profile's most horizontal segment near the mouth, |dy| > |dz|, at least
  `BRIDGE_MIN_MM` long): the receding lip ends at the bridge's concave end; the overhanging
  lip's end lies below the bridge's convex end, where that lip's profile, continued along its
  last chord, reaches the level of the concave end -- the bridge point closest to that
  continuation. Lips nearly flush show no bridge: the stomia then stay where the registration
  carried them.
* soft-tissue menton (Me): the lowest point of the chin, below pogonion. A submental contour
  that still descends backwards (no throat in view, or a head tilted chin-up) puts the profile's
  lowest point on the neck, so the chin's lowest point is taken against the chin's inferior
  border, a line descending MENTON_TILT deg backwards: the profile point farthest along the
  direction MENTON_TILT deg in front of straight down (refined like the maxima above, on the
  mid-sagittal plane at the point found).
A located landmark that ends above or below its neighbour on the profile (`PROFILE_ORDER`)
is on the wrong feature: it is not used. The cheilia are left where the registration carried
them (the mouth slit of these scans fades out towards its corners). The located landmarks are then handled as given ones
(`registration.landmark_fit` moves the landmark nodes onto them).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.ndimage import median_filter
from scipy.spatial import cKDTree

from registration.alignment import Similarity
from registration.surface import TargetSurface
from solver.geometry import deepest_concavity

MIDLINE_RADIUS = 15.0    # mm: mirror pairs around a landmark that place its mid-sagittal plane
SYMMETRY_RADIUS = 12.0   # mm: skin around a landmark whose mirror symmetry refines that plane
REFINE_HALF_WIDTH = 3.0  # mm of profile arc either side of a maximum fitted by a parabola
# mm: skin vertices around a maximum fitted by a surface, about the size of the feature
SUMMIT_RADIUS = {"Prn": 8.0, "Li": 8.0, "Pog": 10.0}
BRIDGE_MIN_MM = 2.0      # mm: the shortest facet step between the lips taken as the mouth slit
# A densely sampled scan (profile segments of at most DENSE_PROFILE_MM, as a CT-derived skin's
# 0.5-1 mm) samples the lips' ends themselves: the step between offset lips is one segment at
# least STEP_MIN_MM long and STEP_RATIO times any other near the mouth (the scan's own
# segments there are 0.2-1.2 mm, a 1 mm lip offset bridged by a 1.4 mm one); flush lips meet at
# the bottom of their groove, and each stomion is taken STOMION_INSET_MM inside its own lip,
# the convention of the synthetic truth (`facemodel.head_geometry.STOMION_INSET`, 0.3 deg at
# ~95 mm from the head's centre)
DENSE_PROFILE_MM = 1.5
STEP_MIN_MM = 1.0
STEP_RATIO = 1.5
STOMION_INSET_MM = 0.5
# Cheilion (`fissure_end`): cuts every FISSURE_STEP_MM from FISSURE_BEFORE_MM medial to
# FISSURE_AFTER_MM lateral of the carried cheilion (the registration carries it within ~4 mm);
# the groove's depth behind a chord of +-FISSURE_CHORD_MM (the groove is ~3 mm wide); its end
# where the depth has fallen to FISSURE_END_LEVEL of its drop above the background (a fissure
# ends where its depth vanishes; 10 % keeps the level above the background's scatter, ~0.05
# mm from cut to cut); a drop under FISSURE_MIN_DROP_MM is no fissure end
FISSURE_STEP_MM = 0.25
FISSURE_BEFORE_MM = 10.0
FISSURE_AFTER_MM = 8.0
FISSURE_CHORD_MM = 3.0
FISSURE_BAND_MM = 5.0    # mm: the groove sought within this height of the mouth's centre
FISSURE_END_LEVEL = 0.1
FISSURE_MIN_DROP_MM = 0.3
MENTON_REACH = 25.0      # mm of profile beyond the carried menton searched for it
# deg in front of straight down: menton is the chin's extreme along that direction (the chin's
# inferior border taken as a line descending this much backwards: module docstring); the same
# convention as the synthetic heads' truth (facemodel.head_geometry.MENTON_TILT)
MENTON_TILT = 35.0
# the profile landmarks from top to bottom, as neighbours whose heights cannot swap (the stomia
# are not compared with each other: lips that overhang can cross at the slit)
PROFILE_ORDER = (("Prn", "Sn"), ("Sn", "Ls"), ("Ls", "Stms"), ("Ls", "Stmi"), ("Stms", "Li"),
                 ("Stmi", "Li"), ("Li", "Pog"), ("Pog", "Me"))
ORDER_TOL_MM = 0.5       # mm: heights compared up to the located landmarks' own scatter
LOCATED = ("Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "ChL", "ChR", "Pog", "Me")


def mirror_pairs(nodes: np.ndarray, ids: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """(k, 2) node ids (i, j) of `ids` mirror images of each other about x = 0 (i == j on the
    plane), from the generic (symmetric) node positions."""
    ids = np.asarray(ids, dtype=np.int64)
    p = np.asarray(nodes, float)[ids]
    d, j = cKDTree(p).query(p * [-1.0, 1.0, 1.0])
    ok = (d < tol) & (np.arange(len(ids)) <= j)
    return np.stack([ids[ok], ids[j[ok]]], axis=1)


def local_midline(x: np.ndarray, pairs: np.ndarray, centre: np.ndarray,
                  radius: float = MIDLINE_RADIUS) -> float:
    """x of the mid-sagittal plane near `centre`: the median midpoint of the registered mirror
    pairs within `radius` (the centre's own x when there is none)."""
    if len(pairs) == 0:
        return float(centre[0])
    mid = 0.5 * (x[pairs[:, 0]] + x[pairs[:, 1]])
    near = np.linalg.norm(mid - centre, axis=1) < radius
    return float(np.median(mid[near, 0])) if near.any() else float(centre[0])


def symmetry_plane(skin: TargetSurface, centre: np.ndarray, x_guess: float,
                   radius: float = SYMMETRY_RADIUS, span: float = 3.0, step: float = 0.25) -> float:
    """x of the plane x = x0 about which the skin around `centre` is most nearly its own mirror
    image: the skin vertices within `radius` of the centre reflected about each candidate plane
    (x_guess +- span, every `step` mm), their mean squared distance to the skin (the lower 80 %,
    so that a scan's edge or a local asymmetry does not dominate), minimised by a parabola
    through the best candidate and its neighbours. `x_guess` when fewer than 10 vertices."""
    v = skin.vertices
    near = v[np.linalg.norm(v - centre, axis=1) < radius]
    if len(near) < 10:
        return float(x_guess)
    xs = x_guess + np.arange(-span, span + step / 2, step)
    cost = np.empty(len(xs))
    for n, x0 in enumerate(xs):
        m = near.copy()
        m[:, 0] = 2.0 * x0 - m[:, 0]
        d = np.sort(skin.closest(m).distance)
        cost[n] = float(np.mean(d[:max(1, int(0.8 * len(d)))] ** 2))
    k = int(np.argmin(cost))
    if 0 < k < len(xs) - 1:
        c0, c1, c2 = cost[k - 1], cost[k], cost[k + 1]
        den = c0 - 2.0 * c1 + c2
        if den > 0:
            return float(xs[k] + 0.5 * step * (c0 - c2) / den)
    return float(xs[k])


def plane_cut(vertices: np.ndarray, faces: np.ndarray, x0: float) -> list[np.ndarray]:
    """The surface cut by the plane x = x0: polylines (k, 3), each chained along the cut edges
    (a closed loop repeats its first point at the end)."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    d = v[:, 0] - x0
    if np.any(np.abs(d) < 1e-9):  # no vertex exactly on the plane: every cut point is on an edge
        x0 += 1e-6
        d = v[:, 0] - x0
    s = d[f] > 0
    cut = s.any(axis=1) & ~s.all(axis=1)
    fc = f[cut]
    sc = s[cut]
    # the two edges of each cut face whose ends lie on either side of the plane
    edges = np.stack([fc[:, [0, 1]], fc[:, [1, 2]], fc[:, [2, 0]]], axis=1)      # (m, 3, 2)
    crosses = np.stack([sc[:, 0] != sc[:, 1], sc[:, 1] != sc[:, 2], sc[:, 2] != sc[:, 0]], axis=1)
    pair = edges[crosses].reshape(-1, 2, 2)                                       # (m, 2 edges, 2)
    keys = np.sort(pair.reshape(-1, 2), axis=1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    a, b = v[uniq[:, 0]], v[uniq[:, 1]]
    t = d[uniq[:, 0]] / (d[uniq[:, 0]] - d[uniq[:, 1]])
    pts = a + t[:, None] * (b - a)
    seg = inv.reshape(-1, 2)
    n = len(uniq)
    adj = sp.coo_matrix((np.ones(2 * len(seg)), (np.r_[seg[:, 0], seg[:, 1]], np.r_[seg[:, 1], seg[:, 0]])),
                        shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    deg = np.diff(adj.indptr)
    visited = np.zeros(n, bool)
    out = []
    # open chains first (from one end), then the closed loops
    for start in list(np.flatnonzero(deg == 1)) + list(range(n)):
        if visited[start]:
            continue
        chain = [start]
        visited[start] = True
        cur = start
        while True:
            nxt = [k for k in adj.indices[adj.indptr[cur]:adj.indptr[cur + 1]] if not visited[k]]
            if not nxt:
                break
            cur = nxt[0]
            visited[cur] = True
            chain.append(cur)
        if deg[start] == 2 and len(chain) > 2 and start in adj.indices[adj.indptr[cur]:adj.indptr[cur + 1]]:
            chain.append(start)
        out.append(pts[chain])
    return out


def sagittal_profile(skin: TargetSurface, x0: float, centre: np.ndarray, radius: float) -> np.ndarray:
    """The piece of the profile x = x0 through the point nearest `centre`, within `radius` of
    it along the chain, ordered downwards (k, 3); empty when the plane misses the skin there."""
    best, best_d = None, np.inf
    for chain in plane_cut(skin.vertices, skin.faces, x0):
        dist = np.linalg.norm(chain - centre, axis=1)
        i = int(np.argmin(dist))
        if dist[i] < best_d:
            best, best_d, i0 = chain, dist[i], i
    if best is None or best_d > radius:
        return np.zeros((0, 3))
    closed = len(best) > 2 and np.allclose(best[0], best[-1])
    if closed:  # start the loop opposite the centre, so that the arc around it is contiguous
        best = np.roll(best[:-1], len(best[:-1]) // 2 - i0, axis=0)
        i0 = len(best) // 2
    inside = np.linalg.norm(best - centre, axis=1) < radius
    lo = i0
    while lo > 0 and inside[lo - 1]:
        lo -= 1
    hi = i0
    while hi < len(best) - 1 and inside[hi + 1]:
        hi += 1
    arc = best[lo:hi + 1]
    if len(arc) > 1 and arc[0, 2] < arc[-1, 2]:
        arc = arc[::-1]
    return arc


def _arc_length(p: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def _at(p: np.ndarray, s: np.ndarray, t: float) -> np.ndarray:
    """The polyline point at arc length t."""
    return np.array([np.interp(t, s, p[:, k]) for k in range(3)])


def most_anterior(p: np.ndarray, lo: int = 0, hi: int | None = None,
                  direction: np.ndarray | None = None) -> np.ndarray:
    """The most anterior (max y) point of the profile between vertices lo and hi, refined by a
    least-squares parabola y(s) of arc length s through the vertices within REFINE_HALF_WIDTH
    of the best one, the window widened to reach at least one vertex 1 mm or more away on
    either side (a scan's facets can leave a flat tip between two far vertices). `direction`
    (anterior y, superior z), unit: the extreme along it instead of along y."""
    hi = len(p) - 1 if hi is None else hi
    h = p[:, 1] if direction is None else p[:, 1:] @ np.asarray(direction, float)
    i = lo + int(np.argmax(h[lo:hi + 1]))
    s = _arc_length(p)
    idx = np.arange(lo, hi + 1)
    before, after = idx[s[idx] < s[i] - 1.0], idx[s[idx] > s[i] + 1.0]
    left = min(s[i] - REFINE_HALF_WIDTH, s[before[-1]]) if len(before) else s[i]
    right = max(s[i] + REFINE_HALF_WIDTH, s[after[0]]) if len(after) else s[i]
    near = idx[(s[idx] >= left - 1e-9) & (s[idx] <= right + 1e-9)]
    if len(before) and len(after) and len(near) >= 3:
        a, b, _ = np.polyfit(s[near] - s[i], h[near], 2)
        if a < 0:
            t = s[i] - b / (2.0 * a)
            if s[near].min() <= t <= s[near].max():
                return _at(p, s, t)
    return p[i].copy()


def anterior_summit(skin: TargetSurface, q: np.ndarray, z_range: tuple[float, float],
                    radius: float) -> np.ndarray:
    """The most anterior point of the skin around the profile maximum q: a least-squares
    surface y = f(x, z), quadratic in x and cubic in z (a chin or nose tip bulges unevenly
    above and below its summit), through the skin's vertices within `radius` of q and z in
    `z_range` (the scan's vertices lie on the skin, its facets cut under a convex summit), its
    maximum (Newton from q) taken onto the skin along y, the fit's own height direction
    (`skin_along_y`); q itself where the fit has no maximum in the fitted region."""
    v = skin.vertices
    sel = (np.linalg.norm(v - q, axis=1) < radius) & (v[:, 2] >= z_range[0]) & (v[:, 2] <= z_range[1])
    if sel.sum() < 10:
        return q
    dx, dz, y = v[sel, 0] - q[0], v[sel, 2] - q[2], v[sel, 1]
    a = np.column_stack([np.ones_like(dx), dx, dz, dx * dx, dx * dz, dz * dz, dz**3])
    c = np.linalg.lstsq(a, y, rcond=None)[0]
    o = np.zeros(2)
    for _ in range(20):
        g = np.array([c[1] + 2 * c[3] * o[0] + c[4] * o[1],
                      c[2] + c[4] * o[0] + 2 * c[5] * o[1] + 3 * c[6] * o[1] ** 2])
        h = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5] + 6 * c[6] * o[1]]])
        if np.any(np.linalg.eigvalsh(h) >= 0):
            return q
        step = np.linalg.solve(h, -g)
        o = o + step
        if np.linalg.norm(step) < 1e-6:
            break
    ox, oz = o
    if not (dx.min() <= ox <= dx.max() and dz.min() <= oz <= dz.max()):
        return q
    y0 = c[0] + c[1] * ox + c[2] * oz + c[3] * ox**2 + c[4] * ox * oz + c[5] * oz**2 + c[6] * oz**3
    return skin_along_y(skin, q[0] + ox, q[2] + oz, y0)


def skin_along_y(skin: TargetSurface, x: float, z: float, y_near: float) -> np.ndarray:
    """The skin point at (x, z) nearest `y_near` along y: where the line {(x, t, z)} crosses
    the skin's facets (of several crossings, the one nearest y_near), the closest skin point
    when the line misses the skin. Unlike the closest point, this is continuous in (x, z) on
    either side of a crease: a summit on a symmetric head lies on its mid-sagittal plane,
    where the facets of both sides meet at a ridge, and a point just inside the skin there
    has two nearest facets, the closest point jumping between them with the last bit of x."""
    v, f = skin.vertices, skin.faces
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    # barycentric coordinates of (x, z) in each facet projected onto the (x, z) plane
    e1, e2 = (b - a)[:, [0, 2]], (c - a)[:, [0, 2]]
    r = np.array([x, z]) - a[:, [0, 2]]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > 1e-12 * (np.einsum("ij,ij->i", e1, e1) + np.einsum("ij,ij->i", e2, e2))
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (r[:, 0] * e2[:, 1] - r[:, 1] * e2[:, 0]) / det
        w = (e1[:, 0] * r[:, 1] - e1[:, 1] * r[:, 0]) / det
    # a point on a shared edge lies in both facets, at the same height: either will do
    eps = 1e-9
    hit = np.flatnonzero(ok & (u >= -eps) & (w >= -eps) & (u + w <= 1.0 + eps))
    if len(hit) == 0:
        return skin.closest(np.array([[x, y_near, z]])).points[0]
    y = a[hit, 1] + u[hit] * (b - a)[hit, 1] + w[hit] * (c - a)[hit, 1]
    return np.array([x, y[int(np.argmin(np.abs(y - y_near)))], z])


def deepest_under_bitangent(p: np.ndarray, lo: int, hi: int, with_span: bool = False):
    """On the profile arc p[lo..hi] (ordered downwards): the index of the point deepest behind
    the anterior convex hull edge that spans the arc's deepest concavity; `with_span`: also
    that edge's ends (i, j) and its inward (posterior) unit normal in (y, z)."""
    k, i, j, inward = deepest_concavity(p[:, 1:], lo, hi)
    return (k, (i, j, inward)) if with_span else k


def _thin(p: np.ndarray, min_step: float = 0.25) -> np.ndarray:
    """The polyline's points at least `min_step` mm from the previous one kept (a skin vertex
    close to the cutting plane is cut by each of its edges: a cluster of points carries no
    direction for the tangents of `concave_corner`)."""
    keep = [0]
    for i in range(1, len(p)):
        if np.linalg.norm(p[i] - p[keep[-1]]) >= min_step:
            keep.append(i)
    return p[keep]


def _line_meet(a0, a1, b0, b1):
    """Intersection of the lines a0-a1 and b0-b1 in a plane ((2,) points), None if parallel."""
    da, db = a1 - a0, b1 - b0
    det = da[0] * -db[1] - da[1] * -db[0]
    if abs(det) < 1e-9 * np.linalg.norm(da) * np.linalg.norm(db):
        return None
    r = b0 - a0
    u = (r[0] * -db[1] - r[1] * -db[0]) / det
    return a0 + u * da


def concave_corner(skin: TargetSurface, p: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """The deepest point of a concave corner of the profile arc p[lo..hi] (ordered downwards)
    on a scan whose facets bridge it: the profile's cut points lie on the skin, the corner
    itself lies between the deepest of them and a neighbour, where the chord hides it. Each
    side's last chord is extended into the corner (the columella's and the upper lip's
    tangents for subnasale); of the two chords next to the deepest point, the one behind whose
    middle these tangents meet deepest holds the corner, and the corner is the skin point
    closest to where they meet. The deepest profile point when no tangents meet behind a chord
    (a rounded corner sampled densely)."""
    k, (i, j, inward) = deepest_under_bitangent(p, lo, hi, with_span=True)
    q = _thin(p[i:j + 1])
    if len(q) < 4:
        return p[k].copy()
    yz = q[:, 1:]
    m = int(np.argmax(yz @ inward))
    best, best_depth = None, -np.inf
    for c0, c1 in ((m - 1, m), (m, m + 1)):
        if c0 - 1 < 0 or c1 + 1 >= len(q):
            continue
        x = _line_meet(yz[c0 - 1], yz[c0], yz[c1 + 1], yz[c1])
        if x is None:
            continue
        chord = yz[c1] - yz[c0]
        t = (x - yz[c0]) @ chord / (chord @ chord)
        depth = (x - yz[c0]) @ inward
        if 0.0 < t < 1.0 and depth > 0.0 and depth > best_depth:
            best, best_depth = x, depth
    if best is None:
        return q[m].copy()
    x0 = float(np.median(q[:, 0]))
    return skin.closest(np.array([[x0, best[0], best[1]]])).points[0]


def _valley_end(p: np.ndarray, k: int, hi: int) -> int:
    """From vertex k, the index where the profile stops receding (y stops decreasing) going
    down: the search for the next most anterior point starts beyond the concavity's bottom
    (a shallow fold found one vertex early would otherwise be its own maximum)."""
    while k < hi and p[k + 1, 1] <= p[k, 1]:
        k += 1
    return k


def _nearest_index(p: np.ndarray, q: np.ndarray) -> int:
    return int(np.argmin(np.linalg.norm(p - q, axis=1)))


def _closest_on_segment(a: np.ndarray, b: np.ndarray, q: np.ndarray) -> np.ndarray:
    ab = b - a
    t = float(np.clip(np.dot(q - a, ab) / max(np.dot(ab, ab), 1e-300), 0.0, 1.0))
    return a + t * ab


def _runs(flag: np.ndarray, sign: np.ndarray):
    """(start, end) point indices of the maximal runs of consecutive flagged profile segments
    whose y steps all have the same sign (segments start..end-1)."""
    k = 0
    while k < len(flag):
        if not flag[k]:
            k += 1
            continue
        j = k
        while j + 1 < len(flag) and flag[j + 1] and sign[j + 1] == sign[k]:
            j += 1
        yield k, j + 1
        k = j + 1


def mouth_slit(p: np.ndarray, centre: np.ndarray, reach: float = 7.0):
    """(Stms, Stmi) on the profile near `centre` from the facets bridging the lips' step (module
    docstring), or None when the profile shows no such step. The bridge is the run of
    consecutive profile segments steeper in y than in z (|dy| >= 0.8 |dz|: the lips themselves
    run mostly vertically) with the largest total |dy|, at least BRIDGE_MIN_MM, one of them
    within `reach` of `centre`."""
    if len(p) < 3:
        return None
    d = np.diff(p, axis=0)
    mid = 0.5 * (p[1:] + p[:-1])
    flat = np.abs(d[:, 1]) >= 0.8 * np.abs(d[:, 2])
    sign = np.sign(d[:, 1])
    best, best_dy = None, BRIDGE_MIN_MM
    for k, e in _runs(flat, sign):
        dy = abs(p[e, 1] - p[k, 1])
        if dy >= best_dy and np.min(np.linalg.norm(mid[k:e] - centre, axis=1)) < reach:
            best, best_dy = (k, e), dy
    if best is None:
        return None
    ia, ib = best
    a, b = p[ia], p[ib]
    if b[1] < a[1] and ia > 0:
        # the upper lip overhangs: the lower lip ends at the concave end b; the upper lip
        # continues, hidden under the bridge, down to the level of b: its lowest point is where
        # its last chord reaches that level, on the scan the bridge point closest to it
        u = a - p[ia - 1]
        if u[2] < -1e-9:
            return _closest_on_segment(a, b, a + u * (b[2] - a[2]) / u[2]), b.copy()
    # the lower lip protrudes: the upper lip ends at the concave end a, the lower lip's
    # highest scanned point is the bridge's lower end b
    return a.copy(), b.copy()


def lips_meeting(p: np.ndarray, centre: np.ndarray, reach: float = 7.0):
    """(Stms, Stmi) on a densely sampled profile (segments of ~1 mm or less; module
    docstring) near `centre`, or None when the profile has too few points there. Where the
    lips' ends are offset from each other, the scan bridges the step with a strip of long
    facets, which the profile crosses as one to three consecutive segments each at least twice
    the profile's median segment near the mouth and, as the lips themselves run mostly
    vertically, steeper in y than in z (|dy| >= 0.8 |dz|, all the same way); the run of them
    that spans the most (at least
    STEP_MIN_MM, and STEP_RATIO times any other segment within `reach`) is the step: its upper
    end is the upper lip's lowest point, its lower end the lower lip's highest (whichever lip
    overhangs). Where the lips meet flush, the contact line
    is the bottom of the groove between them, the deepest point under the profile's anterior
    bitangent within `reach`; each stomion is then STOMION_INSET_MM of profile inside its own
    lip from that bottom."""
    q = _thin(p, 0.2)
    if len(q) < 4:
        return None
    seg = np.linalg.norm(np.diff(q, axis=0), axis=1)
    mid = 0.5 * (q[1:] + q[:-1])
    win = np.flatnonzero(np.linalg.norm(mid - centre, axis=1) < reach)
    if len(win) < 3:
        return None
    d = np.diff(q, axis=0)
    long_ = np.zeros(len(seg), bool)
    long_[win] = (seg[win] >= 2.0 * np.median(seg[win])) & (np.abs(d[win, 1]) >= 0.8 * np.abs(d[win, 2]))
    sign = np.sign(d[:, 1])
    best, best_len = None, 0.0
    for k, e in _runs(long_, sign):
        span = float(np.linalg.norm(q[e] - q[k]))
        if span > best_len:
            best, best_len = (k, e), span
    if best is not None:
        i0, i1 = best
        rest = seg[win[(win < i0) | (win >= i1)]]
        if best_len >= STEP_MIN_MM and (len(rest) == 0 or best_len >= STEP_RATIO * rest.max()):
            return q[i0].copy(), q[i1].copy()
    lo, hi = int(win[0]), int(win[-1]) + 1
    k = deepest_under_bitangent(q, lo, hi)
    s = _arc_length(q)
    return _at(q, s, s[k] - STOMION_INSET_MM), _at(q, s, s[k] + STOMION_INSET_MM)


def _dense(p: np.ndarray, centre: np.ndarray, reach: float = 7.0) -> bool:
    """Whether the profile is sampled densely near `centre` (median segment at most
    DENSE_PROFILE_MM once near-coincident cut points are merged), as a CT-derived skin is."""
    q = _thin(p, 0.2)
    if len(q) < 4:
        return False
    seg = np.linalg.norm(np.diff(q, axis=0), axis=1)
    near = np.linalg.norm(0.5 * (q[1:] + q[:-1]) - centre, axis=1) < reach
    return bool(near.sum() >= 3 and np.median(seg[near]) <= DENSE_PROFILE_MM)


def _chord_depth(q: np.ndarray, idx: np.ndarray, half: float = FISSURE_CHORD_MM) -> np.ndarray:
    """Depth (mm) of the profile vertices q[idx] ((k, 3) in a frame where the profile lies in
    the (y, z) plane, y outward) behind the chord joining the profile points `half` mm of arc
    before and after each; -inf where the profile does not reach that far."""
    s = _arc_length(q)
    out = np.full(len(idx), -np.inf)
    ok = (s[idx] - half >= 0.0) & (s[idx] + half <= s[-1])
    if not ok.any():
        return out
    i = idx[ok]
    a = np.column_stack([np.interp(s[i] - half, s, q[:, k]) for k in (1, 2)])
    b = np.column_stack([np.interp(s[i] + half, s, q[:, k]) for k in (1, 2)])
    ch = b - a
    n = np.column_stack([-ch[:, 1], ch[:, 0]]) / np.linalg.norm(ch, axis=1, keepdims=True)
    n = np.where(n[:, :1] > 0, -n, n)          # inward: away from the outward y
    out[ok] = np.einsum("ij,ij->i", q[i, 1:] - a, n)
    return out


def fissure_end(skin: TargetSurface, carried: np.ndarray, mouth: np.ndarray,
                step: float = FISSURE_STEP_MM):
    """Cheilion: the lateral end of the oral fissure (the groove along the lips' contact line)
    on a densely sampled scan, near the `carried` cheilion, `mouth` the stomia's midpoint.

    The skin is cut by vertical planes across the mouth line (normal t: the horizontal
    direction from the mouth's centre to the carried cheilion) every `step` mm from
    FISSURE_BEFORE_MM medial to FISSURE_AFTER_MM lateral of the carried point. In each cut the
    groove is the profile point deepest behind the chord of +-FISSURE_CHORD_MM of arc (a
    feature ~3 mm wide; the lips' own curvature leaves a shallow background depth) on the
    profile within 12 mm of arc and FISSURE_BAND_MM in height of the mouth's centre (the
    carried cheilion can be 5 mm too high or low in a strong class II). The
    groove's depth d(s) (median of 5 cuts: a cut that misses the groove is a lone outlier)
    runs at its full value along the fissure and falls to the background
    of the lips' junction over its last 1-2 mm: the fall is the steepest drop of d over 1.5 mm;
    D the largest depth in the 1-2.5 mm before it and b the depth 1.5 mm after it. The fissure
    ends where d has fallen to b + FISSURE_END_LEVEL (D - b) (of several falls at least half as
    steep as the steepest, the lateral-most); the cheilion is the groove point
    there, projected onto the skin. Returns (point, report) or (None, reason) when the cuts
    show no fissure ending (a drop of less than FISSURE_MIN_DROP_MM) or miss the skin."""
    t = np.asarray(carried, float) - np.asarray(mouth, float)
    t[2] = 0.0
    if np.linalg.norm(t) < 1e-6:
        return None, "cheilion on the mid-sagittal plane"
    t /= np.linalg.norm(t)
    n = np.cross([0.0, 0.0, 1.0], t)
    n = n if n[1] > 0 else -n
    rot = np.stack([t, n, [0.0, 0.0, 1.0]], axis=1)    # columns: across-plane, outward, up
    v, f = skin.vertices, skin.faces
    reach = max(FISSURE_BEFORE_MM, FISSURE_AFTER_MM) + 12.0
    near_f = f[np.all(np.linalg.norm(v[f] - carried, axis=2) < reach, axis=1)]
    used = np.unique(near_f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    v, f = v[used], remap[near_f]
    offsets = np.arange(-FISSURE_BEFORE_MM, FISSURE_AFTER_MM + step / 2, step)
    depth = np.full(len(offsets), -np.inf)
    groove = np.zeros((len(offsets), 3))
    guess = carried - FISSURE_BEFORE_MM * t
    guess[2] = mouth[2]
    for k, o in enumerate(offsets):
        origin = carried + o * t
        local = (v - origin) @ rot
        g = (guess - origin) @ rot
        best, best_d, i0 = None, np.inf, 0
        for chain in plane_cut(local, f, 0.0):
            dist = np.linalg.norm(chain - g, axis=1)
            i = int(np.argmin(dist))
            if dist[i] < best_d:
                best, best_d, i0 = chain, dist[i], i
        if best is None or best_d > 5.0:
            return None, "the cuts across the mouth line miss the skin"
        # the profile within 12 mm of arc (a scan's bridge over offset lips can be ~10 mm)
        arc = _arc_length(best)
        q = best[np.abs(arc - arc[i0]) < 12.0]
        win = np.flatnonzero(np.abs(q[:, 2] - g[2]) < FISSURE_BAND_MM)
        if len(win) == 0:
            return None, "the cuts across the mouth line miss the skin"
        d = _chord_depth(q, win)
        j = int(np.argmax(d))
        depth[k] = d[j]
        groove[k] = origin + rot @ q[win[j]]
        guess = guess + step * t
    if not np.all(np.isfinite(depth)):
        return None, "the cuts across the mouth line are too short"
    # a cut that misses the groove (a facet's corner on the plane) is a lone outlier
    depth = median_filter(depth, size=5, mode="nearest")
    h = int(round(0.75 / step))
    drop = np.full(len(offsets), -np.inf)
    drop[h:-h] = depth[:-2 * h] - depth[2 * h:]
    drop[:int(round(2.5 / step))] = -np.inf     # a plateau before it is needed
    # the fissure's end is its lateral-most steep fall (medially, where the lips' offset is
    # large, a cut can lose the groove for a few mm)
    strong = np.flatnonzero(drop >= 0.5 * drop.max())
    j = int(strong[-1])
    while j > 0 and drop[j - 1] > drop[j]:     # the peak of that fall
        j -= 1
    before = depth[max(0, j - int(round(2.5 / step))):max(1, j - int(round(1.0 / step)) + 1)]
    full = float(before.max())
    base = float(depth[min(len(depth) - 1, j + int(round(1.5 / step)))])
    if full - base < FISSURE_MIN_DROP_MM:
        return None, "no end of the oral fissure near the carried cheilion"
    level = base + FISSURE_END_LEVEL * (full - base)
    k = j
    while k < len(depth) - 1 and depth[k + 1] > level:
        k += 1
    if k == len(depth) - 1:
        return None, "no end of the oral fissure near the carried cheilion"
    frac = float(np.clip((depth[k] - level) / max(depth[k] - depth[k + 1], 1e-12), 0.0, 1.0))
    end = groove[k] + frac * (groove[k + 1] - groove[k])
    point = skin.closest(end[None]).points[0]
    return point, {"fissure_depth_mm": full, "background_mm": base,
                   "offset_mm": float(offsets[k] + frac * step)}


def _menton(p: np.ndarray, i_pog: int) -> np.ndarray | None:
    """Menton on the profile p (ordered downwards) below pogonion (vertex i_pog): the extreme
    along the direction MENTON_TILT deg in front of straight down (module docstring); None
    when that extreme is the profile's end (the profile does not reach round the chin)."""
    a = np.radians(MENTON_TILT)
    d = np.array([np.sin(a), -np.cos(a)])
    h = p[i_pog:, 1:] @ d
    k = int(np.argmax(h))
    if k == len(h) - 1:
        return None
    return most_anterior(p, i_pog, len(p) - 1, direction=d)


def locate_landmarks(skin: TargetSurface, x: np.ndarray, pairs: np.ndarray, carried: dict,
                     wanted, frame: Similarity | None = None) -> tuple[dict, dict]:
    """Landmarks of `wanted` (names) located on `skin` near their `carried` positions (name ->
    (3,), the registered landmark nodes), x the registered nodes and `pairs` the mirror pairs
    of skin nodes (`mirror_pairs`). `frame`: the similarity from the head's anatomical frame
    (x right, y anterior, z superior) to the frame of the inputs, when they differ (the
    directions "anterior" and "superior" of the definitions are the head's). Returns ({name:
    (3,) point on the skin, in the inputs' frame}, report: per landmark the distance moved
    from the carried position, and the ones not found)."""
    if frame is not None:
        inv = frame.inverse()
        found, report = locate_landmarks(skin.transformed(inv.scale, inv.rotation, inv.translation),
                                         inv.apply(x), pairs,
                                         {k: inv.apply(np.asarray(v, float)) for k, v in carried.items()},
                                         wanted)
        for k in found:
            found[k] = frame.apply(found[k])
            report["located"][k]["moved_mm"] = float(np.linalg.norm(found[k] - carried[k]))
        return found, report
    wanted = [k for k in LOCATED if k in set(wanted) and k in carried]
    c = {k: np.asarray(v, float) for k, v in carried.items()}
    found: dict[str, np.ndarray] = {}
    missing: list[str] = []

    def profile(centre, radius):
        x0 = symmetry_plane(skin, centre, local_midline(x, pairs, centre))
        return sagittal_profile(skin, x0, centre, radius)

    if not wanted:
        return {}, {"located": {}, "not_found": []}
    # pronasale and the mouth slit anchor the rest
    prn, stms, stmi = c.get("Prn"), c.get("Stms"), c.get("Stmi")
    dense = False
    if prn is not None:
        p = profile(prn, 12.0)
        if len(p) >= 3:
            prn = most_anterior(p)
            prn = anterior_summit(skin, prn, (-np.inf, np.inf), SUMMIT_RADIUS["Prn"])
            found["Prn"] = prn
    if stms is not None and stmi is not None:
        mouth = 0.5 * (stms + stmi)
        p = profile(mouth, 16.0)
        dense = _dense(p, mouth)
        slit = lips_meeting(p, mouth) if dense else mouth_slit(p, mouth)
        if slit is not None:
            stms, stmi = slit
            found["Stms"], found["Stmi"] = stms, stmi
        elif len(p) >= 2:  # lips nearly flush: the carried stomia, on this profile
            stms, stmi = p[_nearest_index(p, stms)], p[_nearest_index(p, stmi)]
    # nasolabial concavity and upper lip: the profile arc from pronasale to stomion superius
    if prn is not None and stms is not None and ("Sn" in wanted or "Ls" in wanted):
        centre = 0.5 * (prn + stms)
        p = profile(c.get("Ls", centre), 0.5 * np.linalg.norm(prn - stms) + 12.0)
        if len(p) >= 4:
            i0, i1 = _nearest_index(p, prn), _nearest_index(p, stms)
            if i1 - i0 >= 3:
                i_sn = deepest_under_bitangent(p, i0, i1)
                found["Sn"] = concave_corner(skin, p, i0, i1)
                ls_ = most_anterior(p, _valley_end(p, i_sn, i1), i1)
                found["Ls"] = ls_
    # lower lip, labiomental fold, chin: from stomion inferius down past the carried menton
    if stmi is not None and ("Li" in wanted or "Pog" in wanted or "Me" in wanted) and "Pog" in c:
        low_end = c.get("Me", c["Pog"] + [0.0, -10.0, -10.0])
        p = profile(c["Pog"], np.linalg.norm(stmi - low_end) + MENTON_REACH)
        if len(p) >= 4:
            i0, i1 = _nearest_index(p, stmi), _nearest_index(p, low_end)
            if i1 - i0 >= 3:
                i_fold = deepest_under_bitangent(p, i0, i1)
                # pogonion: the chin's summit, the most anterior point past the bottom of the
                # fold's valley; a chin whose profile recedes down to the profile's end has no
                # summit, and pogonion is the fold's lower edge (the definition in
                # facemodel.head_geometry.anatomical_landmarks)
                k_valley = _valley_end(p, i_fold, len(p) - 1)
                flat_chin = k_valley >= len(p) - 1
                li = most_anterior(p, i0, i_fold)
                pog = p[i_fold] if flat_chin else most_anterior(p, k_valley, max(i1, k_valley))
                z_fold = p[i_fold, 2]
                if dense:
                    # the scan samples the lip: its summit on the lip's own mid-sagittal plane
                    q = profile(li, SUMMIT_RADIUS["Li"])
                    found["Li"] = li
                    if len(q) >= 3:  # the arc around li between the fold and the stomion
                        a = b = _nearest_index(q, li)
                        while a > 0 and q[a - 1, 2] < p[i0, 2] - 0.5:
                            a -= 1
                        while b < len(q) - 1 and q[b + 1, 2] > z_fold:
                            b += 1
                        if b - a >= 2:
                            found["Li"] = most_anterior(q, a, b)
                else:
                    found["Li"] = anterior_summit(skin, li, (z_fold, p[i0, 2] - 0.5), SUMMIT_RADIUS["Li"])
                if flat_chin:
                    found["Pog"] = p[i_fold].copy()
                else:
                    found["Pog"] = anterior_summit(skin, pog, (p[i1, 2], z_fold), SUMMIT_RADIUS["Pog"])
                if "Me" in wanted:
                    me = _menton(p, _nearest_index(p, pog))
                    if me is not None:  # again on the mid-sagittal plane at that point
                        q = profile(me, MENTON_REACH)
                        me2 = _menton(q, _nearest_index(q, found["Pog"])) if len(q) >= 4 else None
                        found["Me"] = me if me2 is None else me2
    # the cheilia: the lateral ends of the oral fissure, on a scan that samples it densely
    if dense and stms is not None and stmi is not None:
        mouth = 0.5 * (stms + stmi)
        for k in ("ChL", "ChR"):
            if k in wanted:
                point, info = fissure_end(skin, c[k], mouth)
                if point is not None:
                    found[k] = point
    disordered = out_of_profile_order(found, c)
    out = {}
    for k in wanted:
        if k in found and k not in disordered:
            out[k] = found[k]
        else:
            missing.append(k)
    report = {"located": {k: {"moved_mm": float(np.linalg.norm(out[k] - c[k]))} for k in out},
              "not_found": missing, "out_of_order": disordered}
    return out, report


def out_of_profile_order(found: dict, carried: dict, tol: float = ORDER_TOL_MM) -> list[str]:
    """Located landmarks that break the top-to-bottom order of the profile landmarks
    (PROFILE_ORDER; each pair of neighbours compared by height, z superior, found positions
    where located and carried ones elsewhere): a landmark placed on the wrong feature (the
    upper lip's summit taken for subnasale, the fold for the chin) lands above or below its
    neighbour. Of a disordered pair, the located landmark(s) are returned (they stay where the
    registration carried them)."""
    pos = {k: np.asarray(found.get(k, carried.get(k)), float) for k in {*found, *carried}
           if found.get(k, carried.get(k)) is not None}
    bad: set[str] = set()
    for upper, lower in PROFILE_ORDER:
        if upper in pos and lower in pos and pos[upper][2] < pos[lower][2] - tol:
            bad.update(k for k in (upper, lower) if k in found)
    return sorted(bad)
