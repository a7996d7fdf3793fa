"""Geometry as Warp functions, with pure NumPy references used by tests and evaluation.

Conventions: boxes are (centre (x, y), heading h, length L, width W); the box frame has x
forward, y to the left. Corners are ordered front-left, front-right, rear-right, rear-left.

* Collisions: oriented boxes overlap by the separating-axis test on the four box axes
  (touching counts as overlap), after a distance pre-filter on the half-diagonals.
* Off-road: a road-edge segment intersects the agent's box at its current pose (box edges
  or inside, Liang-Barsky clipping) or crosses one of the four corner paths from the
  previous to the current pose (swept test, no tunnelling).
* Lanes: the nearest lane segment (point-to-segment distance) within ``lane_radius``;
  heading error = wrap(heading - lane direction); lateral offset signed, left positive.
* Collision cases and fault (nuPlan, as in ``cpalgo.evaluate.metrics``), tested in order:

  0 STOPPED_EGO   the agent's |speed| <= 0.05 m/s            -> not at fault
  1 STOPPED_TRACK the other's |speed| <= 0.05 m/s             -> at fault
  2 ACTIVE_REAR   the other's centre bears > 150 deg from the agent's heading -> not at fault
  3 ACTIVE_FRONT  the agent's front edge touches the other box -> at fault
  4 ACTIVE_LATERAL otherwise -> at fault only when the agent spans two lanes (its corners'
                  nearest lane centrelines within ``lane_radius`` belong to different lane
                  polylines; corners with no lane near are ignored).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from cpsim.model import ModelArrays

PI = wp.constant(math.pi)
TWO_PI = wp.constant(2.0 * math.pi)
#: nuPlan's stopped-speed threshold (m/s) and "behind" bearing (deg).
STOPPED_SPEED = 0.05
BEHIND_DEG = 150.0
WP_STOPPED_SPEED = wp.constant(STOPPED_SPEED)
WP_COS_BEHIND = wp.constant(math.cos(math.radians(BEHIND_DEG)))

STOPPED_EGO, STOPPED_TRACK, ACTIVE_REAR, ACTIVE_FRONT, ACTIVE_LATERAL = range(5)
COLLISION_KIND_NAMES = ("stopped_ego", "stopped_track", "active_rear", "active_front", "active_lateral")


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
def point_segment(p: wp.vec2f, a: wp.vec2f, b: wp.vec2f):
    """Distance from p to segment a-b, and the signed side (cross of (b-a, p-a), left +)."""
    ab = b - a
    ab2 = wp.max(wp.dot(ab, ab), 1.0e-12)
    t = wp.clamp(wp.dot(p - a, ab) / ab2, 0.0, 1.0)
    d = p - (a + t * ab)
    return wp.length(d), cross2(ab, p - a)


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
            ap = p - m.seg_a[sid]
            u = m.seg_dir[sid]
            t = wp.clamp(wp.dot(ap, u), 0.0, m.seg_len[sid])
            dv = ap - t * u
            d2 = wp.dot(dv, dv)
            if d2 <= best_d2 and (best < 0 or d2 < best_d2 or sid < best):
                best = sid
                best_d2 = d2
                best_side = cross2(u, ap)
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
def spans_two_lanes(m: ModelArrays, g: int, centre: wp.vec2f, heading: float, half_len: float,
                    half_wid: float, radius: float) -> bool:
    """The box's corners' nearest lanes (within radius) belong to different lane polylines."""
    first = int(-1)
    spans = bool(False)
    for k in range(4):
        corner = box_corner(centre, heading, half_len, half_wid, k)
        sid, d, off, err = lane_query(m, g, corner, heading, radius)
        if sid >= 0:
            poly = m.seg_poly[sid]
            if first < 0:
                first = poly
            elif poly != first:
                spans = bool(True)
    return spans


@wp.func
def collision_kind(pa: wp.vec2f, ha: float, va: float, la: float, wa: float,
                   pb: wp.vec2f, hb: float, vb: float, lb: float, wb: float) -> int:
    """nuPlan collision case of agent a hitting b (codes in the module docstring)."""
    kind = int(4)
    if wp.abs(va) <= WP_STOPPED_SPEED:
        kind = 0
    elif wp.abs(vb) <= WP_STOPPED_SPEED:
        kind = 1
    else:
        rel = pb - pa
        n = wp.length(rel)
        cos_b = float(1.0)
        if n > 1.0e-9:
            cos_b = (rel[0] * wp.cos(ha) + rel[1] * wp.sin(ha)) / n
        if cos_b < WP_COS_BEHIND:
            kind = 2
        else:
            fl = box_corner(pa, ha, 0.5 * la, 0.5 * wa, 0)
            fr = box_corner(pa, ha, 0.5 * la, 0.5 * wa, 1)
            if segment_hits_box(fl, fr, pb, hb, 0.5 * lb, 0.5 * wb):
                kind = 3
    return kind


@wp.func
def kind_at_fault(kind: int, spans: bool) -> bool:
    return kind == 1 or kind == 3 or (kind == 4 and spans)


# ============================================================================ NumPy references
def wrap_angle_np(a: np.ndarray) -> np.ndarray:
    return a - 2.0 * np.pi * np.floor((a + np.pi) / (2.0 * np.pi))


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


def classify_collision(ego_xy, ego_heading, ego_speed, ego_size, other_xy, other_heading,
                       other_speed, other_size) -> int:
    """Reference of :func:`collision_kind` for one pair (codes in the module docstring)."""
    if abs(ego_speed) <= STOPPED_SPEED:
        return STOPPED_EGO
    if abs(other_speed) <= STOPPED_SPEED:
        return STOPPED_TRACK
    rel = np.asarray(other_xy, np.float64) - np.asarray(ego_xy, np.float64)
    n = np.linalg.norm(rel)
    cos_b = 1.0 if n <= 1e-9 else (rel[0] * np.cos(ego_heading) + rel[1] * np.sin(ego_heading)) / n
    if cos_b < math.cos(math.radians(BEHIND_DEG)):
        return ACTIVE_REAR
    corners = box_corners_np(ego_xy, ego_heading, ego_size)
    other = box_corners_np(other_xy, other_heading, other_size)
    # front edge touches the other box: it crosses one of the box's edges or lies inside it
    fl, fr = corners[0], corners[1]
    for k in range(4):
        if segments_intersect_np(fl, fr, other[k], other[(k + 1) % 4]):
            return ACTIVE_FRONT
    local = _to_local_np(fl, other_xy, other_heading)
    if abs(local[0]) <= other_size[0] / 2 and abs(local[1]) <= other_size[1] / 2:
        return ACTIVE_FRONT
    return ACTIVE_LATERAL


def classify_fault(kind: int, spans_two_lanes: bool) -> bool:
    """nuPlan fault rule: stopped other agent and front collisions are at fault; lateral
    collisions only while the agent spans two lanes; a stopped agent and being rear-ended
    are not."""
    return kind in (STOPPED_TRACK, ACTIVE_FRONT) or (kind == ACTIVE_LATERAL and bool(spans_two_lanes))


def _to_local_np(p, centre, heading) -> np.ndarray:
    d = np.asarray(p, np.float64) - np.asarray(centre, np.float64)
    c, s = math.cos(heading), math.sin(heading)
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])


__all__ = [
    "wrap_angle", "boxes_overlap", "segments_intersect", "segment_hits_box", "point_segment",
    "grid_cell", "lane_query", "spans_two_lanes", "collision_kind", "kind_at_fault", "box_corner",
    "boxes_overlap_np", "segments_intersect_np", "classify_collision", "classify_fault",
    "box_corners_np", "wrap_angle_np", "COLLISION_KIND_NAMES",
]
