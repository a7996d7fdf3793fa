"""Geometry as Warp functions, with pure NumPy references used by tests.

Conventions: boxes are (centre (x, y), heading h, length L, width W); the box frame has x
forward, y to the left. Corners are ordered front-left, front-right, rear-right, rear-left.

* Collisions: oriented boxes overlap by the separating-axis test on the four box axes
  (touching counts as overlap), after a distance pre-filter on the half-diagonals.
* Off-road: a road-edge segment intersects the agent's box at its current pose (box edges
  or inside, Liang-Barsky clipping) or crosses one of the four corner paths from the
  previous to the current pose (swept test, no tunnelling).
* Lanes: the nearest lane segment (point-to-segment distance) within ``lane_radius``;
  heading error = wrap(heading - lane direction); lateral offset signed, left positive.
* Lane distance (metrics): the true distance to the nearest lane centreline, by a ring
  search over the grid when no lane lies within ``lane_radius`` (:func:`lane_distance`).
* Collision cases and fault (BehaviorBench's classifier, nuPlan / PDM style), classified from
  the state one step before contact (pre-step poses and velocities of both agents), tested
  in order:

  5 VULNERABLE     the other is a pedestrian or cyclist             -> at fault
  0 STOPPED_EGO    the agent's speed <= 0.05 m/s                     -> not at fault
  1 STOPPED_TRACK  the other's speed <= 0.05 m/s                     -> at fault
  2 ACTIVE_REAR    the other's centre bears > 150 deg from the agent's heading
                   (it approached from behind)                       -> at fault only when straddling
  3 ACTIVE_FRONT   bearing < 60 deg and closing speed > 0.5 m/s      -> at fault
  4 ACTIVE_LATERAL otherwise                                         -> at fault only when straddling

  Bearing: the angle between the agent's heading and the direction from its centre to the
  other's centre. Closing speed: (v_agent - v_other) . that direction (the rate at which the
  centres approach). Straddling a lane divider: over the agent's last 4 positions (the
  pre-contact one and the three before it; fewer at the start of an episode, the first one
  repeated), its centre came within width/2 + 1.75 m of at least two distinct lane
  centrelines (lane polylines; the union over the four positions), and its lateral drift,
  the displacement from the oldest to the newest of those positions across its pre-contact
  heading, exceeds 0.3 m. The reach is capped at ``lane_radius`` (the grid's lane lists are
  exact up to it; 4 m covers boxes up to 4.5 m wide). The width is the collision box's
  (``box_scale`` applied).

  The kernel (:func:`collision_kind`, :func:`straddles_divider`, :func:`kind_at_fault`) is
  the only implementation used by the simulator and the evaluation; the NumPy functions at
  the end (:func:`classify_collision`, :func:`straddles_divider_np`, :func:`classify_fault`)
  are references for tests.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from cpsim.model_arrays import ModelArrays
from cpsim.scoring import NO_LANE_DISTANCE

PI = wp.constant(math.pi)
TWO_PI = wp.constant(2.0 * math.pi)
#: BehaviorBench's at-fault thresholds: stopped speed (m/s), "behind" and "front" bearings
#: (deg), closing speed of a front collision (m/s), lane-divider reach beyond half the
#: width (m), lateral drift of a straddling ego (m), positions looked back over.
STOPPED_SPEED = 0.05
BEHIND_DEG = 150.0
FRONT_DEG = 60.0
FRONT_CLOSING_SPEED = 0.5
DIVIDER_REACH = 1.75
DIVIDER_DRIFT = 0.3
DIVIDER_POSITIONS = 4
WP_STOPPED_SPEED = wp.constant(STOPPED_SPEED)
WP_COS_BEHIND = wp.constant(math.cos(math.radians(BEHIND_DEG)))
WP_COS_FRONT = wp.constant(math.cos(math.radians(FRONT_DEG)))
WP_FRONT_CLOSING = wp.constant(FRONT_CLOSING_SPEED)
WP_DIVIDER_REACH = wp.constant(DIVIDER_REACH)
WP_DIVIDER_DRIFT = wp.constant(DIVIDER_DRIFT)
#: :data:`cpsim.scoring.NO_LANE_DISTANCE` (m), what :func:`lane_distance` records when the grid holds no lane
WP_NO_LANE_DISTANCE = wp.constant(NO_LANE_DISTANCE)

#: Collision cases (the codes of the module docstring's table; ``collision_kind`` returns
#: them, ``kind_at_fault`` and the at-fault rule of ``agent_events`` test them).
STOPPED_EGO, STOPPED_TRACK, ACTIVE_REAR, ACTIVE_FRONT, ACTIVE_LATERAL, VULNERABLE = range(6)
COLLISION_KIND_NAMES = ("stopped_ego", "stopped_track", "active_rear", "active_front", "active_lateral",
                        "vulnerable")
KIND_STOPPED_EGO = wp.constant(STOPPED_EGO)         # the agent stood still: never at fault
KIND_STOPPED_TRACK = wp.constant(STOPPED_TRACK)     # the other stood still: at fault
KIND_ACTIVE_REAR = wp.constant(ACTIVE_REAR)         # the other came from behind: at fault if straddling
KIND_ACTIVE_FRONT = wp.constant(ACTIVE_FRONT)       # closing in on the other ahead: at fault
KIND_ACTIVE_LATERAL = wp.constant(ACTIVE_LATERAL)   # anything else, from the side: at fault if straddling
KIND_VULNERABLE = wp.constant(VULNERABLE)           # the other is a pedestrian / cyclist: at fault


# ============================================================================ Warp functions
@wp.func
def wrap_angle(a: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return a - TWO_PI * wp.floor((a + PI) / TWO_PI)


@wp.func
def cross2(a: wp.vec2f, b: wp.vec2f) -> float:
    return a[0] * b[1] - a[1] * b[0]


@wp.func
def to_local(v: wp.vec2f, c: float, s: float) -> wp.vec2f:
    """World-frame vector into a frame with heading (cos c, sin s)."""
    return wp.vec2f(c * v[0] + s * v[1], -s * v[0] + c * v[1])


@wp.func
def box_corner(centre: wp.vec2f, heading: float, half_len: float, half_wid: float, k: int) -> wp.vec2f:
    """Corner k of a box: 0 front-left, 1 front-right, 2 rear-right, 3 rear-left."""
    return box_corner_cs(centre, wp.cos(heading), wp.sin(heading), half_len, half_wid, k)


@wp.func
def box_corner_cs(centre: wp.vec2f, c: float, s: float, half_len: float, half_wid: float, k: int) -> wp.vec2f:
    """:func:`box_corner` with the heading given as (cos, sin)."""
    fx = half_len
    ly = half_wid
    if k == 1:
        ly = -half_wid
    elif k == 2:
        fx = -half_len
        ly = -half_wid
    elif k == 3:
        fx = -half_len
    return centre + wp.vec2f(c * fx - s * ly, s * fx + c * ly)


@wp.func
def boxes_overlap(ca: wp.vec2f, ha: float, la: float, wa: float,
                  cb: wp.vec2f, hb: float, lb: float, wb: float) -> bool:
    """Separating-axis test of two oriented boxes (full length/width); touching overlaps."""
    fa = wp.vec2f(wp.cos(ha), wp.sin(ha))
    na = wp.vec2f(-fa[1], fa[0])
    fb = wp.vec2f(wp.cos(hb), wp.sin(hb))
    nb = wp.vec2f(-fb[1], fb[0])
    d = cb - ca
    hla = 0.5 * la
    hwa = 0.5 * wa
    hlb = 0.5 * lb
    hwb = 0.5 * wb
    ff = wp.abs(wp.dot(fa, fb))
    fn = wp.abs(wp.dot(fa, nb))
    nf = wp.abs(wp.dot(na, fb))
    nn = wp.abs(wp.dot(na, nb))
    sep = bool(False)
    if wp.abs(wp.dot(d, fa)) > hla + hlb * ff + hwb * fn:
        sep = bool(True)
    if wp.abs(wp.dot(d, na)) > hwa + hlb * nf + hwb * nn:
        sep = bool(True)
    if wp.abs(wp.dot(d, fb)) > hlb + hla * ff + hwa * nf:
        sep = bool(True)
    if wp.abs(wp.dot(d, nb)) > hwb + hla * fn + hwa * nn:
        sep = bool(True)
    return not sep


@wp.func
def _on_segment(a: wp.vec2f, b: wp.vec2f, p: wp.vec2f) -> bool:
    return (wp.min(a[0], b[0]) <= p[0] and p[0] <= wp.max(a[0], b[0])
            and wp.min(a[1], b[1]) <= p[1] and p[1] <= wp.max(a[1], b[1]))


@wp.func
def segments_intersect(p1: wp.vec2f, p2: wp.vec2f, q1: wp.vec2f, q2: wp.vec2f) -> bool:
    """Closed segments p1-p2 and q1-q2 share a point (touching counts)."""
    d1 = cross2(q2 - q1, p1 - q1)
    d2 = cross2(q2 - q1, p2 - q1)
    d3 = cross2(p2 - p1, q1 - p1)
    d4 = cross2(p2 - p1, q2 - p1)
    hit = bool(False)
    if ((d1 > 0.0 and d2 < 0.0) or (d1 < 0.0 and d2 > 0.0)) and \
            ((d3 > 0.0 and d4 < 0.0) or (d3 < 0.0 and d4 > 0.0)):
        hit = bool(True)
    elif d1 == 0.0 and _on_segment(q1, q2, p1):
        hit = bool(True)
    elif d2 == 0.0 and _on_segment(q1, q2, p2):
        hit = bool(True)
    elif d3 == 0.0 and _on_segment(p1, p2, q1):
        hit = bool(True)
    elif d4 == 0.0 and _on_segment(p1, p2, q2):
        hit = bool(True)
    return hit


@wp.func
def segment_hits_box(p0: wp.vec2f, p1: wp.vec2f, centre: wp.vec2f, heading: float,
                     half_len: float, half_wid: float) -> bool:
    """Segment p0-p1 intersects the closed oriented box (Liang-Barsky in the box frame)."""
    return segment_hits_box_cs(p0, p1, centre, wp.cos(heading), wp.sin(heading), half_len, half_wid)


@wp.func
def segment_hits_box_cs(p0: wp.vec2f, p1: wp.vec2f, centre: wp.vec2f, c: float, s: float,
                        half_len: float, half_wid: float) -> bool:
    """:func:`segment_hits_box` with the box heading given as (cos, sin)."""
    a = to_local(p0 - centre, c, s)
    b = to_local(p1 - centre, c, s)
    t_lo = float(0.0)
    t_hi = float(1.0)
    hit = bool(True)
    for axis in range(2):
        start = a[axis]
        delta = b[axis] - a[axis]
        half = half_len
        if axis == 1:
            half = half_wid
        if wp.abs(delta) < 1.0e-12:
            if wp.abs(start) > half:
                hit = bool(False)
        else:
            ta = (-half - start) / delta
            tb = (half - start) / delta
            t_lo = wp.max(t_lo, wp.min(ta, tb))
            t_hi = wp.min(t_hi, wp.max(ta, tb))
    return hit and t_lo <= t_hi


@wp.func
def grid_cell(m: ModelArrays, g: int, p: wp.vec2f, clamp: bool) -> int:
    """Global cell index of point p in scenario g's grid; -1 outside unless ``clamp``."""
    o = m.grid_origin[g]
    cs = m.grid_cell[g]
    dims = m.grid_dims[g]
    fx = wp.clamp((p[0] - o[0]) / cs, -1.0, float(dims[0]))
    fy = wp.clamp((p[1] - o[1]) / cs, -1.0, float(dims[1]))
    ix = int(wp.floor(fx))
    iy = int(wp.floor(fy))
    inside = ix >= 0 and iy >= 0 and ix < dims[0] and iy < dims[1]
    result = int(-1)
    if inside or clamp:
        ix = wp.clamp(ix, 0, dims[0] - 1)
        iy = wp.clamp(iy, 0, dims[1] - 1)
        result = m.grid_first[g] + iy * dims[0] + ix
    return result


@wp.func
def segment_d2(m: ModelArrays, sid: int, p: wp.vec2f) -> float:
    """Squared distance (m^2) from point p to road segment ``sid``."""
    ap = p - m.seg_a[sid]
    u = m.seg_dir[sid]
    t = wp.clamp(wp.dot(ap, u), 0.0, m.seg_len[sid])
    dv = ap - t * u
    return wp.dot(dv, dv)


@wp.func
def lane_query(m: ModelArrays, g: int, p: wp.vec2f, heading: float, radius: float):
    """Nearest lane segment within ``radius`` of p (through the cell's lane candidates).

    Returns (segment id or -1, distance m, signed lateral offset m (left +),
    signed heading error rad).
    """
    best = int(-1)
    best_d2 = float(radius * radius)
    best_side = float(0.0)
    cell = grid_cell(m, g, p, False)
    if cell >= 0:
        for k in range(m.lane_start[cell], m.lane_start[cell + 1]):
            sid = m.lane_items[k]
            d2 = segment_d2(m, sid, p)
            if d2 <= best_d2 and (best < 0 or d2 < best_d2 or sid < best):
                best = sid
                best_d2 = d2
                best_side = cross2(m.seg_dir[sid], p - m.seg_a[sid])
    offset = float(0.0)
    err = float(0.0)
    best_d = wp.sqrt(best_d2)
    if best >= 0:
        offset = best_d
        if best_side < 0.0:
            offset = -best_d
        dirv = m.seg_dir[best]
        err = wrap_angle(heading - wp.atan2(dirv[1], dirv[0]))
    return best, best_d, offset, err


@wp.func
def lane_distance(m: ModelArrays, g: int, p: wp.vec2f) -> float:
    """True distance from p to the nearest lane centreline segment of scenario g's grid.

    Ring search over the grid cells around p: each cell's lane list holds every lane segment
    within ``lane_radius`` of the cell, so after the rings up to r (a square reaching at
    least r cells from p) every segment passing within r x cell of p has been seen; the
    search stops once the best distance is within that reach. Costs O(cells within the
    distance); :data:`NO_LANE_DISTANCE` when the grid holds no lane."""
    o = m.grid_origin[g]
    cs = m.grid_cell[g]
    dims = m.grid_dims[g]
    first = m.grid_first[g]
    cx = int(wp.floor(wp.clamp((p[0] - o[0]) / cs, -1.0e6, 1.0e6)))
    cy = int(wp.floor(wp.clamp((p[1] - o[1]) / cs, -1.0e6, 1.0e6)))
    # rings that can touch the grid: from the grid's Chebyshev distance to its farthest cell
    gx = wp.max(wp.max(-cx, cx - (dims[0] - 1)), 0)
    gy = wp.max(wp.max(-cy, cy - (dims[1] - 1)), 0)
    r_lo = wp.max(gx, gy)
    r_hi = wp.max(wp.max(wp.abs(cx), wp.abs(cx - (dims[0] - 1))), wp.max(wp.abs(cy), wp.abs(cy - (dims[1] - 1))))
    best_d2 = float(1.0e30)
    found = bool(False)
    for r in range(r_lo, r_hi + 1):
        if found:
            reach = float(r - 1) * cs
            if r > 0 and best_d2 <= reach * reach:
                break
        # the ring's cells: rows cy - r and cy + r in full, then columns cx - r and cx + r
        for side in range(4):
            fixed = cy - r
            if side == 1:
                fixed = cy + r
            elif side == 2:
                fixed = cx - r
            elif side == 3:
                fixed = cx + r
            if r == 0 and side > 0:
                continue
            lo = cx - r
            hi = cx + r
            n_fixed = dims[1]
            n_free = dims[0]
            if side >= 2:
                lo = cy - r + 1
                hi = cy + r - 1
                n_fixed = dims[0]
                n_free = dims[1]
            if fixed < 0 or fixed >= n_fixed:
                continue
            lo = wp.max(lo, 0)
            hi = wp.min(hi, n_free - 1)
            for k in range(lo, hi + 1):
                ix = k
                iy = fixed
                if side >= 2:
                    ix = fixed
                    iy = k
                cell = first + iy * dims[0] + ix
                for q in range(m.lane_start[cell], m.lane_start[cell + 1]):
                    d2 = segment_d2(m, m.lane_items[q], p)
                    if d2 < best_d2:
                        best_d2 = d2
                        found = bool(True)
    result = WP_NO_LANE_DISTANCE
    if found:
        result = wp.sqrt(best_d2)
    return result


@wp.func
def _lanes_near(m: ModelArrays, g: int, p: wp.vec2f, reach: float, first_in: int, two_in: bool):
    """Lane polylines with a segment within ``reach`` of p (reach <= lane_radius), folded into
    (first polyline seen, a second distinct one seen)."""
    first = first_in
    two = two_in
    cell = grid_cell(m, g, p, False)
    if cell >= 0:
        r2 = reach * reach
        for k in range(m.lane_start[cell], m.lane_start[cell + 1]):
            sid = m.lane_items[k]
            ap = p - m.seg_a[sid]
            u = m.seg_dir[sid]
            t = wp.clamp(wp.dot(ap, u), 0.0, m.seg_len[sid])
            dv = ap - t * u
            if wp.dot(dv, dv) <= r2:
                poly = m.seg_poly[sid]
                if first < 0:
                    first = poly
                elif poly != first:
                    two = bool(True)
    return first, two


@wp.func
def straddles_divider(m: ModelArrays, g: int, oldest: wp.vec2f, p1: wp.vec2f, p2: wp.vec2f,
                      newest: wp.vec2f, heading: float, width: float, lane_radius: float) -> bool:
    """The agent straddled a lane divider over its last 4 positions (module docstring):
    >= 2 distinct lane centrelines within width/2 + 1.75 m (capped at ``lane_radius``) of
    its centre, and a lateral drift (oldest -> newest, across ``heading``) above 0.3 m."""
    d = newest - oldest
    drift = wp.abs(-wp.sin(heading) * d[0] + wp.cos(heading) * d[1])
    result = bool(False)
    if drift > WP_DIVIDER_DRIFT:
        reach = wp.min(0.5 * width + WP_DIVIDER_REACH, lane_radius)
        first = int(-1)
        two = bool(False)
        first, two = _lanes_near(m, g, oldest, reach, first, two)
        first, two = _lanes_near(m, g, p1, reach, first, two)
        first, two = _lanes_near(m, g, p2, reach, first, two)
        first, two = _lanes_near(m, g, newest, reach, first, two)
        result = two
    return result


@wp.func
def collision_kind(pa: wp.vec2f, ha: float, va: wp.vec2f, pb: wp.vec2f, vb: wp.vec2f,
                   other_vulnerable: bool) -> int:
    """BehaviorBench collision case of agent a hitting b from their pre-contact states
    (centres, a's heading, velocities; codes in the module docstring)."""
    kind = int(KIND_ACTIVE_LATERAL)
    fwd = wp.vec2f(wp.cos(ha), wp.sin(ha))
    rel = pb - pa
    n = wp.length(rel)
    u = fwd
    if n > 1.0e-9:
        u = rel / n
    cos_b = wp.dot(u, fwd)
    closing = wp.dot(va - vb, u)
    if other_vulnerable:
        kind = KIND_VULNERABLE
    elif wp.length(va) <= WP_STOPPED_SPEED:
        kind = KIND_STOPPED_EGO
    elif wp.length(vb) <= WP_STOPPED_SPEED:
        kind = KIND_STOPPED_TRACK
    elif cos_b < WP_COS_BEHIND:
        kind = KIND_ACTIVE_REAR
    elif cos_b > WP_COS_FRONT and closing > WP_FRONT_CLOSING:
        kind = KIND_ACTIVE_FRONT
    return kind


@wp.func
def kind_needs_straddle(kind: int) -> bool:
    """Rear and lateral collisions: their fault depends on straddling a lane divider."""
    return kind == KIND_ACTIVE_REAR or kind == KIND_ACTIVE_LATERAL


@wp.func
def kind_at_fault(kind: int, straddled: bool) -> bool:
    """Fault of a collision case: stopped other, front and vulnerable always; rear and
    lateral only while straddling a lane divider; a stopped agent never."""
    return (kind == KIND_STOPPED_TRACK or kind == KIND_ACTIVE_FRONT or kind == KIND_VULNERABLE
            or (kind_needs_straddle(kind) and straddled))



# ============================================================================ NumPy references
def box_corners_np(xy: np.ndarray, heading: np.ndarray, size: np.ndarray) -> np.ndarray:
    """(..., 4, 2) corners FL, FR, RR, RL of boxes (..., 2) xy, (...,) heading, (..., 2) (L, W)."""
    xy = np.asarray(xy, np.float64)
    h = np.asarray(heading, np.float64)
    size = np.asarray(size, np.float64)
    f = np.stack([np.cos(h), np.sin(h)], -1)
    n = np.stack([-np.sin(h), np.cos(h)], -1)
    signs = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], np.float64)
    hl, hw = 0.5 * size[..., 0:1], 0.5 * size[..., 1:2]
    return (xy[..., None, :] + signs[:, 0, None] * (hl * f)[..., None, :]
            + signs[:, 1, None] * (hw * n)[..., None, :])


def boxes_overlap_np(xa, ha, sa, xb, hb, sb) -> np.ndarray:
    """Reference SAT: boxes (..., 2) centre, (...,) heading, (..., 2) (length, width)."""
    ca, cb = box_corners_np(xa, ha, sa), box_corners_np(xb, hb, sb)
    ha, hb = np.asarray(ha, np.float64), np.asarray(hb, np.float64)
    axes = [np.stack([np.cos(h), np.sin(h)], -1) for h in (ha, hb)]
    axes += [np.stack([-np.sin(h), np.cos(h)], -1) for h in (ha, hb)]
    sep = np.zeros(np.broadcast(ha, hb).shape, bool)
    for u in axes:
        pa = (ca * u[..., None, :]).sum(-1)
        pb = (cb * u[..., None, :]).sum(-1)
        sep |= (pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1))
    return ~sep


def segments_intersect_np(p1, p2, q1, q2) -> bool:
    """Reference closed-segment intersection for single segments (2,) arrays."""
    p1, p2, q1, q2 = (np.asarray(v, np.float64) for v in (p1, p2, q1, q2))

    def cross(a, b):
        return a[0] * b[1] - a[1] * b[0]

    def on(a, b, p):
        return min(a[0], b[0]) <= p[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= p[1] <= max(a[1], b[1])

    d1, d2 = cross(q2 - q1, p1 - q1), cross(q2 - q1, p2 - q1)
    d3, d4 = cross(p2 - p1, q1 - p1), cross(p2 - p1, q2 - p1)
    if d1 * d2 < 0 and d3 * d4 < 0:
        return True
    return bool((d1 == 0 and on(q1, q2, p1)) or (d2 == 0 and on(q1, q2, p2))
                or (d3 == 0 and on(p1, p2, q1)) or (d4 == 0 and on(p1, p2, q2)))


def classify_collision(ego_xy, ego_heading, ego_vel, other_xy, other_vel, other_vulnerable=False) -> int:
    """Reference of :func:`collision_kind` for one pair, from the pre-contact state:
    centres (2,), the ego's heading (rad) and both velocities (2,) m/s."""
    ego_xy, other_xy = np.asarray(ego_xy, np.float64), np.asarray(other_xy, np.float64)
    va, vb = np.asarray(ego_vel, np.float64), np.asarray(other_vel, np.float64)
    fwd = np.array([math.cos(ego_heading), math.sin(ego_heading)])
    rel = other_xy - ego_xy
    n = float(np.linalg.norm(rel))
    u = rel / n if n > 1e-9 else fwd
    bearing = math.degrees(math.acos(float(np.clip(u @ fwd, -1.0, 1.0))))
    closing = float((va - vb) @ u)
    if other_vulnerable:
        return VULNERABLE
    if np.linalg.norm(va) <= STOPPED_SPEED:
        return STOPPED_EGO
    if np.linalg.norm(vb) <= STOPPED_SPEED:
        return STOPPED_TRACK
    if bearing > BEHIND_DEG:
        return ACTIVE_REAR
    if bearing < FRONT_DEG and closing > FRONT_CLOSING_SPEED:
        return ACTIVE_FRONT
    return ACTIVE_LATERAL


def straddles_divider_np(positions, heading: float, width: float, segments, poly_ids,
                         lane_radius: float = 4.0) -> bool:
    """Reference of :func:`straddles_divider`.

    Args:
        positions: (4, 2) the agent's last positions, oldest first (the last one is the
            pre-contact position).
        heading: the pre-contact heading, rad. width: the collision box's width, m.
        segments: (S, 4) lane-centreline segments (x0, y0, x1, y1); poly_ids: (S,) their
            polyline ids (distinct centrelines).
    """
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    d = pos[-1] - pos[0]
    drift = abs(-math.sin(heading) * d[0] + math.cos(heading) * d[1])
    if drift <= DIVIDER_DRIFT:
        return False
    seg = np.asarray(segments, np.float64).reshape(-1, 4)
    if seg.shape[0] == 0:
        return False
    a, b = seg[:, :2], seg[:, 2:]
    ab = b - a
    t = np.clip((((pos[:, None] - a) * ab).sum(-1)) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
    dist = np.linalg.norm(pos[:, None] - (a + t[..., None] * ab), axis=-1)  # (4, S)
    reach = min(0.5 * width + DIVIDER_REACH, lane_radius)
    near = np.asarray(poly_ids)[(dist <= reach).any(0)]
    return len(set(near.tolist())) >= 2


def classify_fault(kind: int, straddled: bool) -> bool:
    """Reference of :func:`kind_at_fault`: a stopped other agent, front collisions and
    vulnerable road users are at fault; rear and lateral collisions only while the agent
    straddled a lane divider; a stopped agent never."""
    return kind in (STOPPED_TRACK, ACTIVE_FRONT, VULNERABLE) or (
        kind in (ACTIVE_REAR, ACTIVE_LATERAL) and bool(straddled))


def lane_distance_np(xy, segments) -> np.ndarray:
    """Reference of :func:`lane_distance`: (...,) true distance from (..., 2) points to the
    nearest of (S, 4) lane segments (:data:`NO_LANE_DISTANCE` when there is none)."""
    p = np.asarray(xy, np.float64)[..., None, :]
    seg = np.asarray(segments, np.float64).reshape(-1, 4)
    if seg.shape[0] == 0:
        return np.full(p.shape[:-2], NO_LANE_DISTANCE)
    a, b = seg[:, :2], seg[:, 2:]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1).min(-1)


__all__ = [
    "wrap_angle", "boxes_overlap", "segments_intersect", "segment_hits_box",
    "grid_cell", "lane_query", "lane_distance", "straddles_divider", "collision_kind", "kind_at_fault", "kind_needs_straddle",
    "box_corner", "boxes_overlap_np", "segments_intersect_np", "classify_collision",
    "straddles_divider_np", "classify_fault", "lane_distance_np", "box_corners_np",
    "COLLISION_KIND_NAMES", "NO_LANE_DISTANCE",
]
