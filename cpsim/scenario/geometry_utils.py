"""Plain NumPy 2-D geometry helpers for building and checking scenarios.

Polylines are ``(n, 2)`` float64 arrays of vertices in metres. Headings are in
radians, counter-clockwise from +x. Nothing here touches Warp or torch; the helpers
are used by the procedural generator, the rule-based driver and the tests.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "cumulative_length", "resample", "bezier", "arc", "offset_polyline", "vertex_headings",
    "point_segment_distance", "min_distance_below", "point_polyline_distance", "segments_intersect",
    "first_intersection", "box_corners", "boxes_overlap", "boxes_cross_segments",
    "BatchedPolylines",
]


def cumulative_length(points: np.ndarray) -> np.ndarray:
    """(n,) arc length at each vertex of an ``(n, 2)`` polyline, starting at 0, m."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def resample(points: np.ndarray, spacing: float) -> np.ndarray:
    """Resample a polyline to vertices equally spaced by about ``spacing`` m.

    Both end points are kept; the spacing is adjusted so the last interval is not short.
    Duplicate consecutive vertices are tolerated.
    """
    points = np.asarray(points, dtype=np.float64)
    s = cumulative_length(points)
    total = s[-1]
    if total <= 0.0:
        raise ValueError("resample: polyline has zero length")
    count = max(int(np.ceil(total / spacing)), 1) + 1
    target = np.linspace(0.0, total, count)
    keep = np.concatenate([[True], np.diff(s) > 1e-12])
    s, points = s[keep], points[keep]
    return np.stack([np.interp(target, s, points[:, 0]), np.interp(target, s, points[:, 1])], axis=1)


def bezier(p0, heading0: float, p3, heading3: float, spacing: float = 1.5) -> np.ndarray:
    """Cubic Bezier from ``p0`` (leaving along ``heading0``) to ``p3`` (arriving along ``heading3``).

    The control-arm length is the one that makes a circular arc of the same turn angle
    exact (``2/3 tan(phi/4) / sin(phi/2)`` of the chord; 1/3 for a straight line), so
    junction connectors and rounded road corners built the same way stay nested.
    Returns an ``(n, 2)`` polyline resampled to ``spacing`` m.
    """
    p0 = np.asarray(p0, dtype=np.float64)
    p3 = np.asarray(p3, dtype=np.float64)
    chord = float(np.linalg.norm(p3 - p0))
    turn = abs((heading3 - heading0 + np.pi) % (2 * np.pi) - np.pi)
    if turn < 1e-3:
        ratio = 1.0 / 3.0
    else:
        ratio = (2.0 / 3.0) * np.tan(turn / 4.0) / max(np.sin(turn / 2.0), 1e-6)
    arm = ratio * chord
    d0 = np.array([np.cos(heading0), np.sin(heading0)])
    d3 = np.array([np.cos(heading3), np.sin(heading3)])
    p1, p2 = p0 + arm * d0, p3 - arm * d3
    t = np.linspace(0.0, 1.0, max(int(np.ceil(chord * 1.6 / spacing)), 2) * 4 + 1)[:, None]
    dense = (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t ** 2 * p2 + t ** 3 * p3
    return resample(dense, spacing)


def arc(center, radius: float, angle0: float, angle1: float, spacing: float = 1.5) -> np.ndarray:
    """Circular arc from polar angle ``angle0`` to ``angle1`` (counter-clockwise when
    ``angle1 > angle0``), ``(n, 2)`` with about ``spacing`` m between vertices."""
    count = max(int(np.ceil(abs(angle1 - angle0) * radius / spacing)), 1) + 1
    a = np.linspace(angle0, angle1, count)
    c = np.asarray(center, dtype=np.float64)
    return np.stack([c[0] + radius * np.cos(a), c[1] + radius * np.sin(a)], axis=1)


def vertex_headings(points: np.ndarray) -> np.ndarray:
    """(n,) unwrapped tangent heading at each vertex (mean of the adjacent segment directions), rad."""
    d = np.diff(points, axis=0)
    seg = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    if seg.shape[0] == 1:
        return np.array([seg[0], seg[0]])
    mid = 0.5 * (seg[:-1] + seg[1:])
    return np.concatenate([[seg[0]], mid, [seg[-1]]])


def offset_polyline(points: np.ndarray, distance: float) -> np.ndarray:
    """The polyline shifted by ``distance`` m to its left (negative: right), along vertex normals."""
    h = vertex_headings(points)
    return points + distance * np.stack([-np.sin(h), np.cos(h)], axis=1)


def point_segment_distance(points: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray) -> np.ndarray:
    """(M, S) distance from each of ``points (M, 2)`` to each segment ``seg_a[s] -> seg_b[s]``, m."""
    ab = seg_b - seg_a                                       # (S, 2)
    ap = points[:, None, :] - seg_a[None, :, :]              # (M, S, 2)
    denom = np.maximum(np.einsum("sk,sk->s", ab, ab), 1e-12)
    t = np.clip(np.einsum("msk,sk->ms", ap, ab) / denom, 0.0, 1.0)
    closest = ap - t[..., None] * ab[None]
    return np.sqrt(np.einsum("msk,msk->ms", closest, closest))


def min_distance_below(points: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray, threshold: float,
                       chunk: int = 16) -> bool:
    """Whether any of ``points (M, 2)`` is closer than ``threshold`` (m) to any segment
    ``seg_a[s] -> seg_b[s]``. Segments are tested in chunks, each only against the points
    inside its bounding box grown by ``threshold``, which keeps the cost near linear."""
    for lo in range(0, seg_a.shape[0], chunk):
        a, b = seg_a[lo:lo + chunk], seg_b[lo:lo + chunk]
        box_lo = np.minimum(a.min(0), b.min(0)) - threshold
        box_hi = np.maximum(a.max(0), b.max(0)) + threshold
        inside = np.all((points > box_lo) & (points < box_hi), axis=1)
        if inside.any() and point_segment_distance(points[inside], a, b).min() < threshold:
            return True
    return False


def point_polyline_distance(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """(M,) distance from each point to the nearest segment of ``polyline``, m."""
    return point_segment_distance(points, polyline[:-1], polyline[1:]).min(axis=1)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def segments_intersect(p1, p2, q1, q2) -> np.ndarray:
    """Whether segments ``p1->p2`` and ``q1->q2`` properly intersect (broadcasting over
    leading dims of the ``(..., 2)`` inputs). Touching end points count as intersecting."""
    d1, d2 = p2 - p1, q2 - q1
    o1 = _cross(d1, q1 - p1)
    o2 = _cross(d1, q2 - p1)
    o3 = _cross(d2, p1 - q1)
    o4 = _cross(d2, p2 - q1)
    return (o1 * o2 <= 0) & (o3 * o4 <= 0) & ~((o1 == 0) & (o2 == 0))


def first_intersection(poly_a: np.ndarray, poly_b: np.ndarray) -> tuple[int, int, np.ndarray] | None:
    """First crossing of ``poly_a`` with ``poly_b`` walking along ``poly_a``.

    Returns ``(segment index in a, segment index in b, point)`` or ``None``.
    """
    a1, a2 = poly_a[:-1, None, :], poly_a[1:, None, :]
    b1, b2 = poly_b[None, :-1, :], poly_b[None, 1:, :]
    hit = segments_intersect(a1, a2, b1, b2)
    if not hit.any():
        return None
    ia, ib = np.argwhere(hit)[0]
    p, r = poly_a[ia], poly_a[ia + 1] - poly_a[ia]
    q, s = poly_b[ib], poly_b[ib + 1] - poly_b[ib]
    denom = _cross(r, s)
    t = 0.0 if abs(denom) < 1e-12 else float(_cross(q - p, s) / denom)
    return int(ia), int(ib), p + t * r


def box_corners(center: np.ndarray, heading: np.ndarray, size: np.ndarray) -> np.ndarray:
    """(..., 4, 2) corners of oriented boxes; ``center (..., 2)``, ``heading (...)``,
    ``size (..., 2)`` as (length, width), counter-clockwise from front-left."""
    c, s = np.cos(heading), np.sin(heading)
    fwd = np.stack([c, s], axis=-1) * (0.5 * size[..., 0:1])
    left = np.stack([-s, c], axis=-1) * (0.5 * size[..., 1:2])
    return np.stack([center + fwd + left, center - fwd + left, center - fwd - left,
                     center + fwd - left], axis=-2)


def boxes_overlap(c1, h1, s1, c2, h2, s2) -> np.ndarray:
    """Separating-axis overlap test of oriented boxes (broadcasting over leading dims).

    ``c (..., 2)`` centres, ``h (...)`` headings, ``s (..., 2)`` (length, width). Boxes
    that only touch do not overlap.
    """
    c1, c2 = np.asarray(c1, np.float64), np.asarray(c2, np.float64)
    lead = np.broadcast_shapes(c1.shape[:-1], c2.shape[:-1], np.shape(h1), np.shape(h2),
                               np.shape(s1)[:-1], np.shape(s2)[:-1])
    c1, c2 = np.broadcast_to(c1, lead + (2,)), np.broadcast_to(c2, lead + (2,))
    h1, h2 = np.broadcast_to(np.asarray(h1, np.float64), lead), np.broadcast_to(np.asarray(h2, np.float64), lead)
    s1 = np.broadcast_to(np.asarray(s1, np.float64), lead + (2,))
    s2 = np.broadcast_to(np.asarray(s2, np.float64), lead + (2,))
    k1, k2 = box_corners(c1, h1, s1), box_corners(c2, h2, s2)
    axes = np.stack([np.stack([np.cos(h1), np.sin(h1)], -1), np.stack([-np.sin(h1), np.cos(h1)], -1),
                     np.stack([np.cos(h2), np.sin(h2)], -1), np.stack([-np.sin(h2), np.cos(h2)], -1)],
                    axis=-2)                                              # (..., 4 axes, 2)
    p1 = np.einsum("...ck,...ak->...ac", k1, axes)                       # (..., 4 axes, 4 corners)
    p2 = np.einsum("...ck,...ak->...ac", k2, axes)
    separated = (p1.max(-1) <= p2.min(-1)) | (p2.max(-1) <= p1.min(-1))
    return ~separated.any(-1)


def boxes_cross_segments(center, heading, size, seg_a, seg_b, tolerance: float = 0.0) -> np.ndarray:
    """(B,) whether any edge of each box crosses any of the segments ``seg_a[s] -> seg_b[s]``.

    This is the simulator's off-road rule (a box edge crossing a road edge). Boxes are
    ``center (B, 2)``, ``heading (B,)``, ``size (B, 2)``; ``tolerance`` shrinks the boxes
    by that many metres on every side. Only segments near a box are tested.
    """
    size = np.maximum(np.asarray(size, dtype=np.float64) - 2.0 * tolerance, 1e-3)
    corners = box_corners(np.asarray(center, np.float64), np.asarray(heading, np.float64), size)
    radius = 0.5 * np.linalg.norm(size, axis=-1)
    out = np.zeros(corners.shape[0], dtype=bool)
    mid = 0.5 * (seg_a + seg_b)
    half = 0.5 * np.linalg.norm(seg_b - seg_a, axis=-1)
    step = 4096
    for lo in range(0, corners.shape[0], step):                  # bounded memory, not per box
        cc = np.asarray(center[lo:lo + step], np.float64)
        near = np.linalg.norm(cc[:, None] - mid[None], axis=-1) <= radius[lo:lo + step, None] + half[None]
        bi, si = np.nonzero(near)
        if bi.size == 0:
            continue
        k = corners[lo + bi]                                     # (P, 4, 2)
        e1, e2 = k, np.roll(k, -1, axis=1)
        hit = segments_intersect(e1, e2, seg_a[si, None], seg_b[si, None]).any(axis=1)
        np.logical_or.at(out, lo + bi, hit)
    return out


class BatchedPolylines:
    """Several polylines padded into one array so that points at given arc lengths can be
    looked up for all of them at once (one ``searchsorted``, no loop over polylines).

    Attributes: ``xy (N, K, 2)``, ``s (N, K)`` cumulative arc length (padded by repeating the
    last vertex), ``heading (N, K)`` unwrapped vertex tangents, ``length (N,)``, ``count (N,)``.
    """

    _ROW_STRIDE = 1.0e7  # larger than any polyline length, keeps the flattened arc lengths sorted

    def __init__(self, polylines: list[np.ndarray]):
        if not polylines:
            raise ValueError("BatchedPolylines: no polylines")
        n = len(polylines)
        k = max(p.shape[0] for p in polylines)
        self.count = np.array([p.shape[0] for p in polylines], dtype=np.int64)
        if np.any(self.count < 2):
            raise ValueError("BatchedPolylines: every polyline needs at least 2 vertices")
        self.xy = np.empty((n, k, 2))
        self.s = np.empty((n, k))
        self.heading = np.empty((n, k))
        for i, p in enumerate(polylines):                       # build time only
            m = p.shape[0]
            self.xy[i, :m], self.xy[i, m:] = p, p[-1]
            cs = cumulative_length(p)
            self.s[i, :m], self.s[i, m:] = cs, cs[-1]
            hd = vertex_headings(p)
            self.heading[i, :m], self.heading[i, m:] = hd, hd[-1]
        self.length = self.s[np.arange(n), self.count - 1].copy()
        self._flat_s = (self.s + self._ROW_STRIDE * np.arange(n)[:, None]).ravel()

    def _locate(self, s: np.ndarray, rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flat vertex index of the segment holding each arc length, the fraction along it,
        and the clipped arc lengths."""
        s = np.asarray(s, dtype=np.float64)
        if rows is None:
            rows = np.arange(self.xy.shape[0]).reshape((-1,) + (1,) * (s.ndim - 1))
            rows = np.broadcast_to(rows, s.shape)
        rows = np.asarray(rows)
        k = self.xy.shape[1]
        sc = np.clip(s, 0.0, self.length[rows])
        idx = np.searchsorted(self._flat_s, sc + self._ROW_STRIDE * rows, side="right") - 1
        local = np.clip(idx - rows * k, 0, self.count[rows] - 2)
        flat = rows * k + local
        s_flat = self.s.reshape(-1)
        s0, s1 = s_flat[flat], s_flat[flat + 1]
        t = np.clip((sc - s0) / np.maximum(s1 - s0, 1e-9), 0.0, 1.0)
        return flat, t, sc

    def at(self, s: np.ndarray, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``(..., 2)`` and headings ``(...)`` at arc lengths ``s``.

        ``s`` has shape ``(N,)`` or ``(N, M)`` (one row per polyline) unless ``rows`` gives the
        polyline of each entry (same shape as ``s``). Arc lengths are clipped to each polyline.
        """
        flat, t, _ = self._locate(s, rows)
        xy_flat, h_flat = self.xy.reshape(-1, 2), self.heading.reshape(-1)
        xy = xy_flat[flat] + t[..., None] * (xy_flat[flat + 1] - xy_flat[flat])
        heading = h_flat[flat] + t * (h_flat[flat + 1] - h_flat[flat])
        return xy, heading

    def interp(self, values: np.ndarray, s: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Linear interpolation of per-vertex ``values (N, K)`` at arc lengths ``s`` (see :meth:`at`)."""
        flat, t, _ = self._locate(s, rows)
        v = values.reshape(-1)
        return v[flat] + t * (v[flat + 1] - v[flat])
