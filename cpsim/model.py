"""The static model: everything about a scenario pool that never changes during a run.

Built once in NumPy from a list of :class:`~cpsim.scenario.Scenario` and uploaded to the
device as one :class:`ModelArrays` Warp struct (Newton / mujoco_warp style: static Model,
mutable State, Control). A world can be (re)assigned any scenario of the pool by index.

Contents (S road segments, L log rows = all agents of the pool, T = 91):

* road segments of every scenario in one array (after simplifying each polyline to
  ``road_simplify_tol`` and splitting pieces longer than ``road_max_segment``), with type,
  source polyline, midpoint, unit direction and length;
* a uniform grid per scenario (``grid_cell`` metres, enlarged on very large maps so a grid
  has at most :data:`MAX_CELLS_PER_SCENARIO` cells) with three candidate lists per cell
  (CSR, global segment ids):

  - ``obs``: the ``num_road`` segments whose midpoints are nearest to the cell centre and
    within ``road_radius`` + half the cell diagonal, sorted by that distance: an agent's M
    observed road segments are this list (the nearest ones up to the cell size);
  - ``lane``: every lane segment within ``lane_radius`` of the cell (exact square-to-segment
    distance), so the nearest lane within ``lane_radius`` of any point of the cell is exact;
  - ``edge``: every road-edge segment within reach of any box centred in the cell, including
    the corner paths of the last step (agent half-diagonal x ``box_scale`` + one step of
    motion, from the cell), so the swept off-road test is exact;

* all logged trajectories of the pool (replay) and each agent's compressed logged path
  (valid points only, cumulative arc length, logged heading; IDM drives along it and
  beyond its end along the final heading) and IDM desired speed (max logged speed, 0 for
  agents that move less than 1 m);
* ``log_offroad``: the events kernel's off-road test of every logged move (vehicles, step
  t-1 to t), computed once on the device; a replayed agent on its logged poses reads it
  instead of testing (exactly the same result), which matters on WOMD scenes where most
  agents are replayed scenery.

The lane and road-edge lists are computed for the cells near each segment only (its
bounding box grown by the radius), with the same distances as the full cell x segment
matrix: a WOMD scene builds in seconds.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import warp as wp

from cpsim.config import SimConfig
from cpsim.model_arrays import ModelArrays
from cpsim.scenario.datatypes import RoadType, Scenario, ScenarioError, validate_scenarios

#: Largest number of grid cells per scenario; larger maps get proportionally larger cells.
MAX_CELLS_PER_SCENARIO = 40_000
#: Agents' logged region is extended by this (m) beyond the observation radius before it
#: clips the grid: roads farther from every logged position cannot matter.
GRID_REGION_MARGIN = 50.0
#: Agents moving less than this along their whole log are parked for IDM (desired speed 0).
IDM_PARKED_PATH_LENGTH = 1.0


# ----------------------------------------------------------------------------- geometry helpers
def simplify_polyline(points: np.ndarray, tol: float, max_len: float) -> np.ndarray:
    """Indices of the vertices kept when simplifying a polyline.

    Greedy chord simplification: from each kept vertex, jump to the farthest later vertex
    such that every vertex in between lies within ``tol`` of the chord and the chord is at
    most ``max_len`` long (the next vertex is always accepted). First and last are kept.

    Args:
        points: (n, 2) vertices, m.
    Returns:
        (k,) int64 increasing indices, k >= min(n, 2).
    """
    n = points.shape[0]
    if n <= 2:
        return np.arange(n)
    pts = points.astype(np.float64)
    window = 64
    keep = [0]
    i = 0
    while i < n - 1:
        hi = min(n - 1, i + window)
        cand = pts[i + 1:hi + 1] - pts[i]                       # (k, 2) chords to candidate ends
        k = cand.shape[0]
        length = np.linalg.norm(cand, axis=1)
        inter = cand[:-1]                                        # intermediate points (k-1, 2)
        # dev[c, m] = distance of intermediate m from chord c (only m < c matters)
        cross = np.abs(cand[:, None, 0] * inter[None, :, 1] - cand[:, None, 1] * inter[None, :, 0])
        dev = cross / np.maximum(length, 1e-12)[:, None]
        mask = np.arange(k - 1)[None, :] < np.arange(k)[:, None]
        maxdev = np.where(mask, dev, 0.0).max(axis=1) if k > 1 else np.zeros(1)
        ok = (maxdev <= tol) & (length <= max_len)
        ok[0] = True
        bad = np.flatnonzero(~ok)
        c = (bad[0] - 1) if bad.size else k - 1
        i = i + 1 + int(c)
        keep.append(i)
    return np.asarray(keep)


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points (C, 2) to segments a-b (S, 2): (C, S) float64, m."""
    ab = (b - a).astype(np.float64)
    ab2 = np.maximum((ab * ab).sum(-1), 1e-12)
    ap = p[:, None, :].astype(np.float64) - a[None, :, :]
    t = np.clip((ap * ab[None]).sum(-1) / ab2[None], 0.0, 1.0)
    d = ap - t[..., None] * ab[None]
    return np.sqrt((d * d).sum(-1))


def rect_segment_distance(centres: np.ndarray, half: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance between axis-aligned squares (centres (C, 2), half side ``half``) and
    segments a-b (S, 2): (C, S) float64, m (0 where they intersect)."""
    c = centres.astype(np.float64)[:, None, :]
    a = a.astype(np.float64)[None]
    b = b.astype(np.float64)[None]
    # segment vs square: clip the segment to the square (Liang-Barsky); hit -> distance 0
    d = b - a
    lo_t = np.zeros(np.broadcast_shapes(c.shape[:2], a.shape[:2]))
    hi_t = np.ones_like(lo_t)
    hit = np.ones_like(lo_t, bool)
    for k in range(2):
        p0 = a[..., k] - c[..., k]
        dk = np.broadcast_to(d[..., k], lo_t.shape)
        par = np.abs(dk) < 1e-12
        hit &= ~(par & (np.abs(p0) > half))
        safe = np.where(par, 1.0, dk)
        t1, t2 = (-half - p0) / safe, (half - p0) / safe
        lo_t = np.where(par, lo_t, np.maximum(lo_t, np.minimum(t1, t2)))
        hi_t = np.where(par, hi_t, np.minimum(hi_t, np.maximum(t1, t2)))
    hit &= lo_t <= hi_t
    # otherwise the closest pair involves an endpoint or a square corner
    def point_square(p):
        q = np.maximum(np.abs(p - c) - half, 0.0)
        return np.sqrt((q * q).sum(-1))
    dist = np.minimum(point_square(a), point_square(b))
    for sx in (-half, half):
        for sy in (-half, half):
            corner = centres.astype(np.float64) + np.array([sx, sy])
            dist = np.minimum(dist, point_segment_distance(corner, a[0], b[0]))
    return np.where(hit, 0.0, dist)


def rect_segment_distance_pairs(centres: np.ndarray, half: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`rect_segment_distance` for N (square, segment) pairs: centres, a, b (N, 2) ->
    (N,) float64, the same operations element by element (so the same values)."""
    c = centres.astype(np.float64)
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    d = b - a
    lo_t = np.zeros(c.shape[0])
    hi_t = np.ones_like(lo_t)
    hit = np.ones_like(lo_t, bool)
    for k in range(2):
        p0 = a[:, k] - c[:, k]
        dk = d[:, k]
        par = np.abs(dk) < 1e-12
        hit &= ~(par & (np.abs(p0) > half))
        safe = np.where(par, 1.0, dk)
        t1, t2 = (-half - p0) / safe, (half - p0) / safe
        lo_t = np.where(par, lo_t, np.maximum(lo_t, np.minimum(t1, t2)))
        hi_t = np.where(par, hi_t, np.minimum(hi_t, np.maximum(t1, t2)))
    hit &= lo_t <= hi_t

    def point_square(p):
        q = np.maximum(np.abs(p - c) - half, 0.0)
        return np.sqrt((q * q).sum(-1))

    def point_segment(p):
        ab = b - a
        ab2 = np.maximum((ab * ab).sum(-1), 1e-12)
        ap = p - a
        t = np.clip((ap * ab).sum(-1) / ab2, 0.0, 1.0)
        e = ap - t[:, None] * ab
        return np.sqrt((e * e).sum(-1))

    dist = np.minimum(point_square(a), point_square(b))
    for sx in (-half, half):
        for sy in (-half, half):
            dist = np.minimum(dist, point_segment(c + np.array([sx, sy])))
    return np.where(hit, 0.0, dist)


def near_segment_csr(centres: np.ndarray, dims: tuple[int, int], cell: float, a: np.ndarray, b: np.ndarray,
                     ids: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Per grid cell (``centres`` (C, 2), cell id = iy * nx + ix), the segments of ``ids``
    (ascending) whose distance to the cell's square is <= ``radius``, ascending: the lists
    ``rect_segment_distance(centres, cell / 2, a[ids], b[ids]) <= radius`` gives, computed
    only for the cells near each segment (its bounding box grown by radius + a cell).

    Returns ``counts`` (C,) int64 and ``items`` (sum(counts),) int64, cell after cell."""
    nx, ny = dims
    C = centres.shape[0]
    if ids.size == 0:
        return np.zeros(C, np.int64), np.zeros(0, np.int64)
    half = 0.5 * cell
    sa, sb = a[ids].astype(np.float64), b[ids].astype(np.float64)
    lo = np.minimum(sa, sb) - (radius + half)
    hi = np.maximum(sa, sb) + (radius + half)
    c0 = centres[0]  # centre of cell (0, 0); centres step by ``cell``
    ix0 = np.clip(np.floor((lo[:, 0] - c0[0]) / cell).astype(np.int64) - 1, 0, nx - 1)
    ix1 = np.clip(np.ceil((hi[:, 0] - c0[0]) / cell).astype(np.int64) + 1, 0, nx - 1)
    iy0 = np.clip(np.floor((lo[:, 1] - c0[1]) / cell).astype(np.int64) - 1, 0, ny - 1)
    iy1 = np.clip(np.ceil((hi[:, 1] - c0[1]) / cell).astype(np.int64) + 1, 0, ny - 1)
    wx, wy = ix1 - ix0 + 1, iy1 - iy0 + 1
    count = wx * wy
    seg = np.repeat(np.arange(ids.size), count)
    k = np.arange(seg.size) - np.repeat(np.cumsum(count) - count, count)
    cells = (iy0[seg] + k // wx[seg]) * nx + ix0[seg] + k % wx[seg]
    keep = rect_segment_distance_pairs(centres[cells], half, a[ids][seg], b[ids][seg]) <= radius
    cells, seg = cells[keep], seg[keep]
    order = np.lexsort((seg, cells))
    cells, seg = cells[order], ids[seg[order]]
    return np.bincount(cells, minlength=C).astype(np.int64), seg.astype(np.int64)


def near_segment_rows(centres: np.ndarray, dims: tuple[int, int], cell: float, a: np.ndarray, b: np.ndarray,
                      ids: np.ndarray, radius: float) -> list[np.ndarray]:
    """:func:`near_segment_csr` as one array per cell (C arrays of segment ids, int64)."""
    counts, items = near_segment_csr(centres, dims, cell, a, b, ids, radius)
    return np.split(items, np.cumsum(counts)[:-1])


def scenario_segments(sc: Scenario, tol: float, max_len: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Simplified road segments of one scenario.

    Returns:
        a (S, 2), b (S, 2) float32 endpoints; types (S,) int32; poly (S,) int32 local polyline ids.
    """
    a_list, b_list, t_list, p_list = [], [], [], []
    for r in range(sc.num_roads):
        pts = sc.road(r).astype(np.float64)
        if pts.shape[0] == 1:
            continue  # isolated points (stop signs) carry no segment
        keep = simplify_polyline(pts, tol, max_len)
        v = pts[keep]
        a, b = v[:-1], v[1:]
        length = np.linalg.norm(b - a, axis=1)
        nonzero = length > 1e-6
        a, b, length = a[nonzero], b[nonzero], length[nonzero]
        if a.shape[0] == 0:
            continue
        pieces = np.maximum(1, np.ceil(length / max_len - 1e-9)).astype(np.int64)
        if np.any(pieces > 1):  # split pieces longer than max_len into equal parts
            rep = np.repeat(np.arange(a.shape[0]), pieces)
            start = np.concatenate([[0], np.cumsum(pieces)[:-1]])
            k = np.arange(rep.size) - np.repeat(start, pieces)
            f0 = (k / pieces[rep])[:, None]
            f1 = ((k + 1) / pieces[rep])[:, None]
            d = (b - a)[rep]
            a, b = a[rep] + f0 * d, a[rep] + f1 * d
        a_list.append(a)
        b_list.append(b)
        t_list.append(np.full(a.shape[0], int(sc.road_types[r]), np.int32))
        p_list.append(np.full(a.shape[0], r, np.int32))
    if not a_list:
        raise ScenarioError(sc.source, "roads", "no road polyline with two distinct points")
    return (np.concatenate(a_list).astype(np.float32), np.concatenate(b_list).astype(np.float32),
            np.concatenate(t_list), np.concatenate(p_list))


def _join_csr(counts: list[np.ndarray], items: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per-scenario CSR parts (cell counts, global item ids) -> one ``start`` (cells + 1,)
    and ``items`` array, int32."""
    all_counts = np.concatenate(counts) if counts else np.zeros(0, np.int64)
    start = np.concatenate([[0], np.cumsum(all_counts)]).astype(np.int32)
    joined = np.concatenate(items).astype(np.int32) if items else np.zeros(0, np.int32)
    return start, joined


# ----------------------------------------------------------------------------- the model
#: the host fields :meth:`Model._build_host` computes, in :class:`ModelHost`
HOST_FIELDS: tuple[str, ...] = ("host", "slot_order", "slot_controllable", "max_half_diagonal", "max_log_speed",
                                "edge_margin")


@dataclass(frozen=True)
class ModelHost:
    """What building a :class:`Model` computes in NumPy (everything but the device upload),
    for one pool and one :class:`SimConfig`: picklable, so another process can build it
    while this one works (:func:`build_model_host`, :func:`offer_model_host`).

    Attributes:
        fingerprint: the pool's :attr:`Model.fingerprint`.
        config: the SimConfig it was built for.
        fields: :data:`HOST_FIELDS` -> value (``host`` arrays, slot orders, pool-wide bounds).
    """

    fingerprint: str
    config: SimConfig
    fields: dict


#: host builds offered to the next Model of the same pool and config (each is used once)
_OFFERED: dict[tuple[str, SimConfig], ModelHost] = {}


def build_model_host(scenarios: Sequence[Scenario], config: SimConfig | None = None) -> ModelHost:
    """Build a pool's :class:`ModelHost` without a device (NumPy only; safe in a worker
    process). ``Model(scenarios, config)`` after :func:`offer_model_host` of it uses these
    arrays instead of building its own (they are the same arrays)."""
    model = Model.__new__(Model)
    model.config = config or SimConfig()
    model.scenarios = validate_scenarios(scenarios, needs="the pool")
    model.fingerprint = Model._fingerprint(model.scenarios)
    model._build_host()
    return ModelHost(model.fingerprint, model.config, {k: getattr(model, k) for k in HOST_FIELDS})


def offer_model_host(prebuilt: ModelHost) -> None:
    """Let the next :class:`Model` of ``prebuilt``'s pool (same content, same order) and
    config adopt it instead of building (once; a Model of any other pool or config ignores
    it). Only the most recent offer per pool and config is kept."""
    if not isinstance(prebuilt, ModelHost):
        raise ValueError(f"prebuilt: expected a ModelHost, got {type(prebuilt).__name__}")
    _OFFERED[(prebuilt.fingerprint, prebuilt.config)] = prebuilt


@dataclass
class GridInfo:
    origin: np.ndarray  # (2,)
    dims: tuple[int, int]
    cell: float


class Model:
    """Static model of a scenario pool for one configuration (see module docstring).

    Attributes:
        scenarios: the pool (list of Scenario).
        config: the SimConfig it was built for (grid lists depend on radii, M, box_scale).
        fingerprint: hex digest identifying the pool's content (snapshot compatibility).
        host: dict of the NumPy arrays uploaded to the device.
        arrays: the :class:`ModelArrays` Warp struct on ``device``.
        slot_order: per scenario, agent indices in slot order (ego, other controllable by
            distance to the ego, remaining agents valid at t0 by distance), untruncated.
        slot_controllable: per scenario, bool flags aligned with ``slot_order``.
        max_idm_speed, max_half_diagonal: pool-wide bounds used for grid margins.
    """

    def __init__(self, scenarios: Sequence[Scenario], config: SimConfig | None = None, device: str = "cpu"):
        config = config or SimConfig()
        scenarios = validate_scenarios(scenarios, needs="the pool")
        self.scenarios = scenarios
        self.config = config
        self.device = str(device)
        self.fingerprint = self._fingerprint(scenarios)
        prebuilt = _OFFERED.pop((self.fingerprint, config), None)
        #: whether the host arrays came from an offered :class:`ModelHost`
        self.prebuilt = prebuilt is not None
        if prebuilt is not None:
            for key, value in prebuilt.fields.items():
                setattr(self, key, value)
        else:
            self._build_host()
        self.arrays = self._upload()
        self._replay_offroad()

    # ------------------------------------------------------------------ build
    @staticmethod
    def _fingerprint(scenarios: Sequence[Scenario]) -> str:
        h = hashlib.sha1()
        for sc in scenarios:
            h.update(sc.id.encode())
            h.update(str(sc.ego_index).encode())
            for name, arr in sc.arrays().items():
                h.update(name.encode())
                h.update(str(arr.shape).encode())
                h.update(np.ascontiguousarray(arr).tobytes())
        return h.hexdigest()

    def _build_host(self) -> None:
        """Build :attr:`host` (the NumPy arrays :meth:`_upload` sends to the device: agents and
        logs, road segments, grids and candidate lists), :attr:`slot_order` /
        :attr:`slot_controllable` and the pool-wide bounds ``max_half_diagonal``,
        ``max_log_speed`` and ``edge_margin``."""
        self.slot_order: list[np.ndarray] = []
        self.slot_controllable: list[np.ndarray] = []
        for sc in self.scenarios:
            order, ctrl = self._slot_order(sc)
            self.slot_order.append(order)
            self.slot_controllable.append(ctrl)
        agents = self._agent_arrays()
        cfg = self.config
        # reach of a box from its cell within one step: half-diagonal x box_scale + one step of motion
        max_step = cfg.dt * max(self.max_log_speed, 100.0 if cfg.dynamics == "classic" else 20.0) + 0.5
        self.edge_margin = self.max_half_diagonal * cfg.box_scale + max_step
        self.host: dict[str, np.ndarray] = {**self._road_arrays(), **agents}

    def _agent_arrays(self) -> dict[str, np.ndarray]:
        """The agent rows of the pool (L = all agents of all scenarios, T steps), as host
        arrays: ``agent_first`` (G + 1,) first row of each scenario, ``agent_scenario`` (L,),
        ``slot_count`` (G,) slots of each scenario (:attr:`slot_order`, built before),
        the logs ``log_xy`` (L, T, 2) m, ``log_heading`` (L, T) rad, ``log_vel`` (L, T, 2) m/s
        (0 at invalid steps), ``log_valid`` (L, T), ``size`` (L, 2) m, ``agent_type`` (L,),
        ``goal`` (L, 2) m, and the compressed paths of :meth:`_paths` (``path_*``,
        ``idm_v0`` m/s). Sets ``max_half_diagonal`` (m) and ``max_log_speed`` (m/s)."""
        scs = self.scenarios
        n_agents = np.array([sc.num_agents for sc in scs], np.int64)
        agent_first = np.concatenate([[0], np.cumsum(n_agents)]).astype(np.int32)
        log_xy = np.concatenate([sc.log_xy for sc in scs]).astype(np.float32)
        log_heading = np.concatenate([sc.log_heading for sc in scs]).astype(np.float32)
        log_vel = np.concatenate([sc.log_velocity for sc in scs]).astype(np.float32)
        log_valid = np.concatenate([sc.log_valid for sc in scs]).astype(bool)
        # invalid steps may hold -10000 sentinels; keep them finite and harmless
        log_xy = np.where(log_valid[..., None], log_xy, 0.0).astype(np.float32)
        log_heading = np.where(log_valid, log_heading, 0.0).astype(np.float32)
        log_vel = np.where(log_valid[..., None], log_vel, 0.0).astype(np.float32)
        sizes = np.concatenate([sc.sizes for sc in scs]).astype(np.float32)
        types = np.concatenate([sc.agent_types for sc in scs]).astype(np.int32)
        goals = np.concatenate([sc.goal_xy for sc in scs]).astype(np.float32)
        path_xy, path_s, path_h, path_n, v0 = self._paths(log_xy, log_heading, log_vel, log_valid)
        self.max_half_diagonal = float(0.5 * np.sqrt((sizes ** 2).sum(1)).max())
        speeds = np.linalg.norm(log_vel, axis=-1)
        self.max_log_speed = float(speeds[log_valid].max()) if log_valid.any() else 0.0
        return {
            "agent_first": agent_first,
            "agent_scenario": np.repeat(np.arange(len(scs), dtype=np.int32), n_agents).astype(np.int32),
            "slot_count": np.array([o.size for o in self.slot_order], np.int32),
            "log_xy": log_xy, "log_heading": log_heading, "log_vel": log_vel, "log_valid": log_valid,
            "size": sizes, "agent_type": types, "goal": goals, "idm_v0": v0,
            "path_xy": path_xy, "path_s": path_s, "path_h": path_h, "path_n": path_n,
        }

    def _road_arrays(self) -> dict[str, np.ndarray]:
        """The road segments of the pool (S, all scenarios, global ids) and every scenario's
        grid, as host arrays: ``seg_a`` / ``seg_b`` / ``seg_mid`` (S, 2) m, ``seg_dir`` (S, 2)
        unit, ``seg_len`` (S,) m, ``seg_type`` / ``seg_poly`` (S,); ``grid_origin`` (G, 2) m,
        ``grid_dims`` (G, 2) cells, ``grid_cell`` (G,) m, ``grid_first`` (G,) first global
        cell; and the three candidate lists per cell in CSR form (``obs_*``, ``lane_*``,
        ``edge_*``: ``*_start`` (cells + 1,), ``*_items`` global segment ids)."""
        cfg = self.config
        G = len(self.scenarios)
        seg_a, seg_b, seg_t, seg_p = [], [], [], []
        grid_origin, grid_dims, grid_cell, grid_first = [], [], [], []
        # candidate lists as CSR parts per scenario: (cell counts, global segment ids)
        lists: dict[str, tuple[list[np.ndarray], list[np.ndarray]]] = {k: ([], []) for k in ("obs", "lane", "edge")}
        seg_offset = 0
        poly_offset = 0
        cell_offset = 0
        for sc in self.scenarios:
            a, b, t, p = scenario_segments(sc, cfg.road_simplify_tol, cfg.road_max_segment)
            info = self._grid_info(sc, a, b)
            nx, ny = info.dims
            ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="xy")
            # cell id = iy * nx + ix  (row-major over y)
            centres = info.origin + (np.stack([ix.ravel(), iy.ravel()], 1) + 0.5) * info.cell
            parts = {"obs": self._observed_csr(centres, info.cell, a, b)}
            # lane / road-edge candidates: near each segment only (same lists as the full
            # cell x segment distance matrix, a fraction of its cost on large maps)
            for name, kind, radius in (("lane", RoadType.LANE, cfg.lane_radius),
                                       ("edge", RoadType.ROAD_EDGE, self.edge_margin)):
                ids = np.flatnonzero(t == kind)
                parts[name] = near_segment_csr(centres, info.dims, info.cell, a, b, ids, radius)
            for name, (counts, items) in parts.items():
                lists[name][0].append(counts)
                lists[name][1].append(items + seg_offset)
            seg_a.append(a)
            seg_b.append(b)
            seg_t.append(t)
            seg_p.append(p + poly_offset)
            grid_origin.append(info.origin)
            grid_dims.append(info.dims)
            grid_cell.append(info.cell)
            grid_first.append(cell_offset)
            seg_offset += a.shape[0]
            poly_offset += sc.num_roads
            cell_offset += centres.shape[0]

        a = np.concatenate(seg_a)
        b = np.concatenate(seg_b)
        d = (b - a).astype(np.float64)
        length = np.linalg.norm(d, axis=1)
        obs_start, obs_items = _join_csr(*lists["obs"])
        lane_start, lane_items = _join_csr(*lists["lane"])
        edge_start, edge_items = _join_csr(*lists["edge"])
        return {
            "seg_a": a.astype(np.float32),
            "seg_b": b.astype(np.float32),
            "seg_mid": (0.5 * (a + b)).astype(np.float32),
            "seg_dir": (d / np.maximum(length, 1e-12)[:, None]).astype(np.float32),
            "seg_len": length.astype(np.float32),
            "seg_type": np.concatenate(seg_t).astype(np.int32),
            "seg_poly": np.concatenate(seg_p).astype(np.int32),
            "grid_origin": np.asarray(grid_origin, np.float32).reshape(G, 2),
            "grid_dims": np.asarray(grid_dims, np.int32).reshape(G, 2),
            "grid_cell": np.asarray(grid_cell, np.float32),
            "grid_first": np.asarray(grid_first, np.int32),
            "obs_start": obs_start, "obs_items": obs_items,
            "lane_start": lane_start, "lane_items": lane_items,
            "edge_start": edge_start, "edge_items": edge_items,
        }

    def _observed_csr(self, centres: np.ndarray, cell: float, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Observation candidates of every cell of one scenario's grid: per cell centre
        (C, 2) m, the ids (local to the scenario's (S, 2) segments ``a`` -> ``b``, m) of the
        ``num_road`` segments whose midpoints are nearest to it, within road_radius + half
        the cell diagonal (``cell`` m), nearest first. Returns ``counts`` (C,) and ``items``
        (int64, cell after cell; empty when ``num_road`` is 0)."""
        cfg = self.config
        M = cfg.num_road
        C = centres.shape[0]
        if M <= 0:
            return np.zeros(C, np.int64), np.zeros(0, np.int64)
        half_diag = cell * np.sqrt(0.5)
        mids = 0.5 * (a + b)
        counts: list[np.ndarray] = []
        items: list[np.ndarray] = []
        chunk = max(1, 2_000_000 // max(a.shape[0], 1))  # bounds the (chunk, S) distance matrix
        for c0 in range(0, C, chunk):
            cc = centres[c0:c0 + chunk]
            # the same values as the norm over the last axis, without its slow axis-2 reduction
            dx = cc[:, None, 0] - mids[None, :, 0]
            dy = cc[:, None, 1] - mids[None, :, 1]
            dm = np.sqrt(dx * dx + dy * dy)
            if dm.shape[1] > M:
                part = np.argpartition(dm, M - 1, axis=1)[:, :M]
            else:
                part = np.broadcast_to(np.arange(dm.shape[1]), dm.shape).copy()
            dpart = np.take_along_axis(dm, part, axis=1)
            order = np.argsort(dpart, axis=1, kind="stable")
            part = np.take_along_axis(part, order, axis=1)
            dpart = np.take_along_axis(dpart, order, axis=1)
            inside = dpart <= cfg.road_radius + half_diag
            counts.append(inside.sum(axis=1).astype(np.int64))
            items.append(part[inside].astype(np.int64))  # row-major: cell after cell, nearest first
        return np.concatenate(counts), np.concatenate(items)

    def _grid_info(self, sc: Scenario, a: np.ndarray, b: np.ndarray) -> GridInfo:
        cfg = self.config
        pts = np.concatenate([a, b])
        lo, hi = pts.min(0).astype(np.float64), pts.max(0).astype(np.float64)
        valid = sc.log_valid
        if valid.any():
            ext = max(cfg.road_radius, cfg.partner_radius) + GRID_REGION_MARGIN
            apts = np.concatenate([sc.log_xy[valid], sc.goal_xy])
            alo, ahi = apts.min(0) - ext, apts.max(0) + ext
            ilo, ihi = np.maximum(lo, alo), np.minimum(hi, ahi)
            if np.all(ihi > ilo):
                lo, hi = ilo, ihi
        # every point within edge/lane reach of a road lies inside the grid
        pad = max(cfg.lane_radius, self.edge_margin) + cfg.grid_cell
        lo, hi = lo - pad, hi + pad
        ext = hi - lo
        cell = float(cfg.grid_cell)
        if np.prod(np.ceil(ext / cell)) > MAX_CELLS_PER_SCENARIO:
            cell = float(np.sqrt(ext[0] * ext[1] / MAX_CELLS_PER_SCENARIO)) * 1.01
        dims = tuple(int(v) for v in np.maximum(1, np.ceil(ext / cell)))
        return GridInfo(origin=lo.astype(np.float32), dims=dims, cell=cell)

    @staticmethod
    def _paths(log_xy: np.ndarray, log_heading: np.ndarray, log_vel: np.ndarray, log_valid: np.ndarray):
        """Compressed logged paths (valid points first), arc lengths and IDM desired speeds."""
        L, T = log_valid.shape
        order = np.argsort(~log_valid, axis=1, kind="stable")  # valid steps first, in time order
        pxy = np.take_along_axis(log_xy, order[..., None], axis=1)
        ph = np.take_along_axis(log_heading, order, axis=1)
        n = log_valid.sum(1).astype(np.int32)
        k = np.arange(T)[None, :]
        inside = k < n[:, None]
        step = np.linalg.norm(np.diff(pxy, axis=1), axis=-1)
        step = np.where(inside[:, 1:], step, 0.0)
        s = np.concatenate([np.zeros((L, 1)), np.cumsum(step, axis=1)], axis=1)
        # pad beyond n with the last point so reads past the end stay finite
        last = np.maximum(n - 1, 0)
        pxy = np.where(inside[..., None], pxy, pxy[np.arange(L), last][:, None, :])
        ph = np.where(inside, ph, ph[np.arange(L), last][:, None])
        total = s[np.arange(L), last]
        speed = np.where(log_valid, np.linalg.norm(log_vel, axis=-1), 0.0)
        v0 = np.where(total >= IDM_PARKED_PATH_LENGTH, speed.max(1), 0.0)
        return (pxy.astype(np.float32), s.astype(np.float32), ph.astype(np.float32), n,
                v0.astype(np.float32))

    @staticmethod
    def _slot_order(sc: Scenario) -> tuple[np.ndarray, np.ndarray]:
        """Agents in slot order: ego, other controllable by distance to the ego, then the
        remaining agents valid at t0 by distance (an ego invalid at t0 is left out)."""
        valid0 = sc.log_valid[:, 0]
        ctrl = sc.controllable
        ego = sc.ego_index
        ref = sc.log_xy[ego, 0] if valid0[ego] else sc.log_xy[np.argmax(valid0), 0]
        dist = np.linalg.norm(sc.log_xy[:, 0] - ref, axis=1)
        idx = np.arange(sc.num_agents)
        others = idx[valid0 & (idx != ego)]
        key_ctrl = ~ctrl[others]  # controllable first
        others = others[np.lexsort((others, dist[others], key_ctrl))]
        order = np.concatenate([[ego] if valid0[ego] else [], others]).astype(np.int32)
        return order, ctrl[order]

    def _upload(self) -> ModelArrays:
        h = self.host
        dev = self.device
        m = ModelArrays()
        vec2 = {"seg_a", "seg_b", "seg_mid", "seg_dir", "grid_origin", "log_xy", "log_vel", "size",
                "goal", "path_xy"}
        for name, arr in h.items():
            if name in vec2:
                value = wp.array(arr, dtype=wp.vec2f, device=dev)
            elif name == "grid_dims":
                value = wp.array(arr, dtype=wp.vec2i, device=dev)
            elif arr.dtype == np.bool_:
                value = wp.array(arr, dtype=wp.bool, device=dev)
            elif arr.dtype == np.int32:
                value = wp.array(arr, dtype=wp.int32, device=dev)
            else:
                value = wp.array(arr.astype(np.float32), dtype=wp.float32, device=dev)
            setattr(m, name, value)
        return m

    def _replay_offroad(self) -> None:
        """``log_offroad`` (L, T): the events kernel's off-road test for every logged move of
        every vehicle (from step t-1 to t), computed once on the device with the same Warp
        function; replayed agents read it instead of testing (see ``agent_events``)."""
        from cpsim import kernels as K

        K.load(self.device)
        L, T = self.host["log_valid"].shape
        out = wp.zeros((L, T), dtype=wp.bool, device=self.device)
        self.arrays.log_offroad = out
        K.metrics.launch_replay_offroad(self.arrays, float(self.config.box_scale), out, dim=(L, T), device=self.device)

    # ------------------------------------------------------------------ info
    @property
    def num_scenarios(self) -> int:
        return len(self.scenarios)

    @property
    def num_segments(self) -> int:
        return int(self.host["seg_a"].shape[0])

    def summary(self) -> dict[str, float]:
        h = self.host
        cells = int(h["obs_start"].size - 1)
        return {
            "scenarios": self.num_scenarios,
            "segments": self.num_segments,
            "cells": cells,
            "obs_items_per_cell": float(h["obs_items"].size / max(cells, 1)),
            "lane_items_per_cell": float(h["lane_items"].size / max(cells, 1)),
            "edge_items_per_cell": float(h["edge_items"].size / max(cells, 1)),
            "log_rows": int(h["size"].shape[0]),
        }


__all__ = ["Model", "ModelArrays", "ModelHost", "build_model_host", "offer_model_host", "simplify_polyline", "point_segment_distance", "rect_segment_distance",
           "rect_segment_distance_pairs", "near_segment_csr", "near_segment_rows",
           "scenario_segments",
           "MAX_CELLS_PER_SCENARIO"]
