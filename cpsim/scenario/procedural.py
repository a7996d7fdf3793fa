"""Procedural scenario families: the built-in, download-free training and evaluation data.

``generate(family, seed)`` builds one :class:`~cpsim.scenario.Scenario` in plain NumPy:
a randomised road network, agents with routes, sizes, start times and goals, and a
91-step log for every agent produced by the rule-based driver
(:mod:`cpsim.scenario.driver`: IDM along the route + gap acceptance at conflict zones).
Same ``(family, seed)``, same scenario, bit for bit, in any process.

Families (right-hand traffic; every scene is rotated by a random angle about the origin):

``intersection``
    Four-way unsigned junction. Four arms at 90 deg +- 11 deg, 1 or 2 lanes per
    direction (lane width 3.2-3.8 m), arms 40-55 m long, rounded corners (radius 5-10 m),
    a crosswalk across every arm. Connector lanes for every movement (straight from each
    lane, left turns from the inner lane, right turns from the outer lane). Left turns
    give way to oncoming straight and right-turning traffic; otherwise first come, first
    served. Ego: an unprotected left turner.
``t_junction``
    A main road (1-2 lanes per direction) and a one-lane side road meeting at 90 deg
    +- 17 deg. Main-road through and right-turn traffic has priority, main-road left turns
    yield to oncoming traffic, the side road yields to everyone. Ego: usually a side-road
    left turner, else a main-road left turner.
``roundabout``
    A single-lane ring (centre-line radius 14-20 m, lane width 3.4-4.0 m) around a
    round island, 3 or 4 one-lane arms at jittered angles, counter-clockwise circulation.
    Entering traffic yields to the ring (merge at the entry point). Ego: an entering car.
``merge``
    Highway on-ramp: 1-2 main lanes on a gently curved carriageway (radius >= 300 m),
    an on-ramp approaching at 12-22 deg, a 40-70 m acceleration lane and a 30-45 m taper
    into the rightmost main lane. Main-lane traffic has priority. Ego: a ramp car.
``lane_drop``
    2-3 lanes in one direction; the rightmost lane ends with a 40-60 m taper into its
    neighbour (zipper merge: equal priority, first come first served). Ego: a car in the
    ending lane.
``parked``
    Two-way road, one lane per direction (curvature radius >= 150 m), 1-4 parked cars or
    trucks partly blocking the right lane; a bypass lane swings into the opposite lane
    around them (as far as they need). Oncoming traffic has priority. Ego: the first car
    behind the parked vehicles; its oncoming rivals are timed to leave the bypass shortly
    before it gets there (it waits briefly, then passes), and its task ends once it is past
    the last parked vehicle (or where its log ends, if further). Parked vehicles are agents
    with goal == start (not controllable).

Traffic around the ego: 1-3 agents on routes that cross or join the ego's, present from
step 0 and timed to reach the conflict at about the ego's time (parked: to leave the bypass
a little before the ego reaches it); the other agents use the other routes (some entering
later at the map border). The ego's task runs through its conflict zones (at most 25 m past
the first one; 12 m in roundabouts; parked: past the last parked vehicle), and a scene whose
logged ego gets that far is preferred. Its goal is then where that log was
:data:`EGO_GOAL_SLACK` s before the log ends, but at least 5 m past its first conflict zone
(parked: past the last parked vehicle); when the log falls short, the goal lies further along
the route. It is not the log's end because the log drives at the rule driver's pace, and
a task that demands exactly that pace leaves an ego that yields to its conflict partner no
time to finish, so every wait would end in a timeout.

Road polylines are ordered lanes first, so lane ``k`` of a route is road polyline ``k``
(:attr:`ProceduralScene.routes`). ``ROAD_EDGE`` polylines bound the drivable area and
never come closer than :data:`EDGE_CLEARANCE` to a lane centreline (checked on every
generated network). Between 2 and 32 agents; controllable agents are valid at step 0;
some traffic enters later (``log_valid`` False before its first step).

Pools: ``train_pool(n, seed)`` draws scenario seeds from ``[0, 2**30)`` and
``eval_pool(n, seed)`` from ``[2**30, 2**31)``, so a training pool and an evaluation
pool never share a scenario, whatever their pool seeds.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from cpsim.scenario.datatypes import DT, AgentType, RoadType, Scenario
from cpsim.scenario.driver import (
    AgentPlan,
    DriveResult,
    LaneConflicts,
    drive,
    lane_conflicts,
    right_of_way,
    route_polyline,
)
from cpsim.scenario.geometry_utils import (
    arc,
    bezier,
    boxes_overlap,
    cumulative_length,
    first_intersection,
    min_distance_below,
    offset_polyline,
    point_segment_distance,
    resample,
    vertex_headings,
)

__all__ = [
    "FAMILIES", "TRAIN_SEED_RANGE", "EVAL_SEED_RANGE", "EDGE_CLEARANCE", "ProceduralScene",
    "generate", "build", "pool", "train_pool", "eval_pool", "log_collisions", "ego_log_reaches_goal",
    "EGO_GOAL_SLACK",
]

FAMILIES: tuple[str, ...] = ("intersection", "t_junction", "roundabout", "merge", "lane_drop", "parked")
TRAIN_SEED_RANGE = (0, 2 ** 30)
EVAL_SEED_RANGE = (2 ** 30, 2 ** 31)
#: Every lane centreline vertex is at least this far from every road edge, m.
EDGE_CLEARANCE = 1.9
MAX_AGENTS = 32
LANE_SPACING = 1.5   # vertex spacing of lanes, m
EDGE_SPACING = 2.0   # road edges, m
LINE_SPACING = 3.0   # painted lines, m
INVALID_XY = -10000.0  # WOMD's filler for invalid steps
_MAX_ATTEMPTS = 12
#: Time, s, by which the ego's logged drive reaches its goal before the log ends: about what
#: yielding to a conflict partner costs (the partner's passage, then pulling away again).
EGO_GOAL_SLACK = 3.0


@dataclasses.dataclass(frozen=True)
class ProceduralScene:
    """A generated scenario plus what built it (for tests, rendering and debugging).

    ``routes[i]``: road-polyline (lane) indices agent ``i`` drives along, in order (parked
    agents: the lane they stand in); ``route_polylines[i]``: those lanes concatenated,
    ``(n_i, 2)`` float64, m; ``static (N,)``: parked agents; ``seed``: the scenario seed.
    """

    scenario: Scenario
    routes: tuple[tuple[int, ...], ...]
    route_polylines: tuple[np.ndarray, ...]
    static: np.ndarray
    seed: int


# =========================================================================== road network builder
@dataclasses.dataclass
class _Net:
    """Mutable road network under construction (local frame, float64)."""

    lanes: list[np.ndarray] = dataclasses.field(default_factory=list)
    levels: list[int] = dataclasses.field(default_factory=list)
    edges: list[np.ndarray] = dataclasses.field(default_factory=list)
    lines: list[np.ndarray] = dataclasses.field(default_factory=list)
    crosswalks: list[np.ndarray] = dataclasses.field(default_factory=list)
    routes: list[tuple[int, ...]] = dataclasses.field(default_factory=list)
    border: list[bool] = dataclasses.field(default_factory=list)
    ego_routes: list[int] = dataclasses.field(default_factory=list)
    parked: list[tuple[np.ndarray, float, float, float, int]] = dataclasses.field(default_factory=list)
    give_way: list[tuple[int, int]] = dataclasses.field(default_factory=list)   # (lane a yields to lane b)
    ego_reach: float = 25.0    # the ego's goal lies at most this far past its first conflict zone, m
    # where the ego's task ends when that is not past its conflict zones (a point near its
    # route, snapped to the route's nearest vertex): the parked family's bypass is one long
    # zone, and passing it and swinging back does not fit in an episode after a wait
    ego_goal_xy: np.ndarray | None = None

    def lane(self, polyline: np.ndarray, level: int = 1) -> int:
        self.lanes.append(np.asarray(polyline, dtype=np.float64))
        self.levels.append(int(level))
        return len(self.lanes) - 1

    def route(self, lanes: tuple[int, ...], ego: bool = False, border: bool = True) -> int:
        """Add a route; ``border``: it starts at the map border (late agents may enter there)."""
        self.routes.append(tuple(int(x) for x in lanes))
        self.border.append(bool(border))
        if ego:
            self.ego_routes.append(len(self.routes) - 1)
        return len(self.routes) - 1

    def rotate(self, angle: float) -> None:
        """Turn every polyline by ``angle`` (rad, counter-clockwise) about the origin."""
        rot = np.array([[np.cos(angle), np.sin(angle)], [-np.sin(angle), np.cos(angle)]])  # row-vector form
        for group in (self.lanes, self.edges, self.lines, self.crosswalks):
            group[:] = [p @ rot for p in group]
        self.parked = [(xy @ rot, h + angle, length, width, lane) for xy, h, length, width, lane in self.parked]

    def check(self) -> bool:
        """Road edges keep :data:`EDGE_CLEARANCE` from every lane vertex and lanes join exactly."""
        lanes = np.concatenate(self.lanes)
        seg_a = np.concatenate([e[:-1] for e in self.edges])
        seg_b = np.concatenate([e[1:] for e in self.edges])
        if min_distance_below(lanes, seg_a, seg_b, EDGE_CLEARANCE):
            return False
        for r in self.routes:
            for a, b in zip(r[:-1], r[1:]):
                if np.linalg.norm(self.lanes[a][-1] - self.lanes[b][0]) > 1e-6:
                    return False
        return True


def _unit(angle: float) -> np.ndarray:
    return np.array([np.cos(angle), np.sin(angle)])


def _segment(p0: np.ndarray, p1: np.ndarray, spacing: float) -> np.ndarray:
    return resample(np.stack([p0, p1]), spacing)


def _wrap(angle: float) -> float:
    return float((angle + np.pi) % (2.0 * np.pi) - np.pi)


def _smooth(s: np.ndarray, s_a: float, s_b: float, d0: float, d1: float) -> np.ndarray:
    """Smoothstep from ``d0`` (at ``s <= s_a``) to ``d1`` (at ``s >= s_b``)."""
    t = np.clip((s - s_a) / max(s_b - s_a, 1e-9), 0.0, 1.0)
    return d0 + (d1 - d0) * t * t * (3.0 - 2.0 * t)


class _Frame:
    """Reference curve for straight-ish roads: arc length ``s`` -> point, heading, and
    lateral offset ``d`` (m, positive to the left). Curvature is piecewise constant."""

    def __init__(self, length: float, pieces: list[tuple[float, float]]):
        s = np.linspace(0.0, length, int(np.ceil(length / 0.25)) + 1)
        kappa = np.zeros_like(s)
        start = 0.0
        for end, k in pieces:
            kappa[(s >= start) & (s <= end)] = k
            start = end
        heading = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * np.diff(s))])
        mid = 0.5 * (heading[1:] + heading[:-1])
        steps = np.stack([np.cos(mid), np.sin(mid)], axis=1) * np.diff(s)[:, None]
        self.s, self.heading = s, heading
        self.xy = np.concatenate([[[0.0, 0.0]], np.cumsum(steps, axis=0)]) - np.array([length / 2, 0.0])
        self.length = length

    def at(self, s: np.ndarray, d: np.ndarray | float) -> np.ndarray:
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        h = np.interp(s, self.s, self.heading)
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        d = np.broadcast_to(np.asarray(d, dtype=np.float64), s.shape)
        return np.stack([x - d * np.sin(h), y + d * np.cos(h)], axis=1)

    def heading_at(self, s: float) -> float:
        return float(np.interp(s, self.s, self.heading))

    def line(self, s0: float, s1: float, d: Callable[[np.ndarray], np.ndarray] | float,
             spacing: float = LANE_SPACING) -> np.ndarray:
        """Polyline from ``s0`` to ``s1`` (reversed when ``s1 < s0``) at offset ``d(s)``."""
        s = np.linspace(s0, s1, max(int(np.ceil(abs(s1 - s0) / spacing)), 1) + 1)
        return self.at(s, d(s) if callable(d) else d)


# =========================================================================== families
def _junction(rng: np.random.Generator, net: _Net, angles: list[float], lane_counts: list[int],
              width: float, shoulder: float, arm_length: float, corner_radius: float,
              level_of: Callable[[int, int, str], int], crosswalks: bool) -> list[tuple[int, int, str, int]]:
    """Build arms, connector lanes, rounded corners, lines and crosswalks of a junction.

    ``angles`` are the outward arm directions (rad, sorted counter-clockwise). Returns the
    movements ``(arm_in, arm_out, turn, route index)``.
    """
    num = len(angles)
    u = [_unit(a) for a in angles]
    nrm = [_unit(a + np.pi / 2) for a in angles]
    half = [c * width + shoulder for c in lane_counts]          # arm half width to the edge
    mouth = [0.0] * num
    flat_side = [False] * num                                     # side between arm k and k+1 is straight
    for k in range(num):
        m = (k + 1) % num
        gap = (angles[m] - angles[k]) % (2 * np.pi)
        if gap > np.radians(150):
            flat_side[k] = True
            continue
        mat = np.stack([u[k], -u[m]], axis=1)
        t = np.linalg.solve(mat, -half[m] * nrm[m] - half[k] * nrm[k])
        mouth[k] = max(mouth[k], t[0] + corner_radius)
        mouth[m] = max(mouth[m], t[1] + corner_radius)
    mouth = [max(r, max(half) + 3.0) for r in mouth]
    incoming: list[list[int]] = []
    outgoing: list[list[int]] = []
    for k in range(num):
        ins, outs = [], []
        for j in range(lane_counts[k]):
            off = (j + 0.5) * width
            far, near = (mouth[k] + arm_length) * u[k], mouth[k] * u[k]
            ins.append(net.lane(_segment(far + off * nrm[k], near + off * nrm[k], LANE_SPACING)))
            outs.append(net.lane(_segment(near - off * nrm[k], far - off * nrm[k], LANE_SPACING)))
        incoming.append(ins)
        outgoing.append(outs)
        near, far = mouth[k] * u[k], (mouth[k] + arm_length) * u[k]
        net.lines.append(_segment(near, far, LINE_SPACING))
        for j in range(1, lane_counts[k]):
            for side in (1.0, -1.0):
                net.lines.append(_segment(near + side * j * width * nrm[k], far + side * j * width * nrm[k],
                                          LINE_SPACING))
        if crosswalks:
            lat = lane_counts[k] * width
            a0, a1 = (mouth[k] + 0.5) * u[k], (mouth[k] + 3.5) * u[k]
            net.crosswalks.append(np.stack([a0 + lat * nrm[k], a1 + lat * nrm[k], a1 - lat * nrm[k],
                                            a0 - lat * nrm[k], a0 + lat * nrm[k]]))
    # road edges: arm k's left side, the rounded corner, arm k+1's right side, as one polyline
    for k in range(num):
        m = (k + 1) % num
        far_k = (mouth[k] + arm_length) * u[k] + half[k] * nrm[k]
        p0 = mouth[k] * u[k] + half[k] * nrm[k]
        p3 = mouth[m] * u[m] - half[m] * nrm[m]
        far_m = (mouth[m] + arm_length) * u[m] - half[m] * nrm[m]
        corner = bezier(p0, angles[k] + np.pi, p3, angles[m], EDGE_SPACING)
        net.edges.append(np.concatenate([_segment(far_k, p0, EDGE_SPACING)[:-1], corner,
                                         _segment(p3, far_m, EDGE_SPACING)[1:]]))
    movements = []
    for k in range(num):
        for m in range(num):
            if m == k:
                continue
            turn = _wrap(angles[m] - angles[k] - np.pi)
            kind = "straight" if abs(turn) < np.radians(35) else "left" if turn > 0 else "right"
            if kind == "straight":
                pairs = [(j, j) for j in range(min(lane_counts[k], lane_counts[m]))]
            elif kind == "left":
                pairs = [(0, 0)]
            else:
                pairs = [(lane_counts[k] - 1, lane_counts[m] - 1)]
            for j_in, j_out in pairs:
                a, b = incoming[k][j_in], outgoing[m][j_out]
                conn = bezier(net.lanes[a][-1], angles[k] + np.pi, net.lanes[b][0], angles[m], LANE_SPACING)
                conn[0], conn[-1] = net.lanes[a][-1], net.lanes[b][0]
                c = net.lane(conn, level_of(k, m, kind))
                movements.append((k, m, kind, net.route((a, c, b))))
    return movements


def _family_intersection(rng: np.random.Generator, net: _Net) -> None:
    jitter = rng.uniform(-0.2, 0.2, 4)
    angles = [k * np.pi / 2 + jitter[k] for k in range(4)]
    count = int(rng.choice([1, 2], p=[0.6, 0.4]))
    moves = _junction(rng, net, angles, [count] * 4, width=rng.uniform(3.2, 3.8),
                      shoulder=rng.uniform(0.6, 1.2), arm_length=rng.uniform(40.0, 55.0),
                      corner_radius=rng.uniform(5.0, 10.0),
                      level_of=lambda k, m, kind: 1, crosswalks=True)
    # unsigned: first come, first served, except that a left turn gives way to the oncoming
    # straight and right-turning traffic (from the arm it would reach by going straight)
    straight_to = {k: m for k, m, kind, _ in moves if kind == "straight"}
    for k, _, kind, r in moves:
        if kind != "left" or k not in straight_to:
            continue
        for k2, _, kind2, r2 in moves:
            if k2 == straight_to[k] and kind2 in ("straight", "right"):
                net.give_way.append((net.routes[r][1], net.routes[r2][1]))
    net.ego_routes.extend(r for _, _, kind, r in moves if kind == "left")


def _family_t_junction(rng: np.random.Generator, net: _Net) -> None:
    side = -np.pi / 2 + rng.uniform(-0.3, 0.3)
    angles = [0.0, np.pi + rng.uniform(-0.12, 0.12), side % (2 * np.pi)]
    order = np.argsort([a % (2 * np.pi) for a in angles])
    angles = [angles[i] % (2 * np.pi) for i in order]
    side_arm = int(np.nonzero(order == 2)[0][0])
    main = int(rng.choice([1, 2], p=[0.6, 0.4]))
    counts = [1 if k == side_arm else main for k in range(3)]

    def level(k: int, m: int, kind: str) -> int:
        if k == side_arm:
            return 0
        return 1 if (m == side_arm and kind == "left") else 2

    moves = _junction(rng, net, angles, counts, width=rng.uniform(3.2, 3.8), shoulder=rng.uniform(0.6, 1.2),
                      arm_length=rng.uniform(40.0, 55.0), corner_radius=rng.uniform(5.0, 10.0),
                      level_of=level, crosswalks=bool(rng.random() < 0.5))
    side_left = [r for k, _, kind, r in moves if k == side_arm and kind == "left"]
    main_left = [r for k, m, kind, r in moves if k != side_arm and m == side_arm and kind == "left"]
    net.ego_routes.extend(side_left if (rng.random() < 0.7 or not main_left) else main_left)


def _family_roundabout(rng: np.random.Generator, net: _Net) -> None:
    arms = int(rng.choice([3, 4]))
    jit = 0.15 if arms == 4 else 0.25
    angles = [k * 2 * np.pi / arms + rng.uniform(-jit, jit) for k in range(arms)]
    width, shoulder = rng.uniform(3.4, 4.0), rng.uniform(0.8, 1.2)
    r_ring = rng.uniform(14.0, 20.0)
    r_outer = r_ring + width / 2 + shoulder
    r_island = r_ring - width / 2 - rng.uniform(2.0, 2.6)
    delta, gamma = rng.uniform(0.35, 0.45), rng.uniform(0.08, 0.14)
    r_arm, arm_length = r_ring + rng.uniform(11.0, 15.0), rng.uniform(35.0, 50.0)
    net.ego_reach = 12.0       # into the ring and round to about the next entry
    centre = np.zeros(2)
    u = [_unit(a) for a in angles]
    nrm = [_unit(a + np.pi / 2) for a in angles]
    ins, outs, entries, exits, ring_at, ring_between = [], [], [], [], [], []
    for k in range(arms):
        far, near = (r_arm + arm_length) * u[k], r_arm * u[k]
        off = 0.5 * width
        ins.append(net.lane(_segment(far + off * nrm[k], near + off * nrm[k], LANE_SPACING)))
        outs.append(net.lane(_segment(near - off * nrm[k], far - off * nrm[k], LANE_SPACING)))
        net.lines.append(_segment(near, far, LINE_SPACING))
    for k in range(arms):
        m = (k + 1) % arms
        x_k, e_k = angles[k] - delta, angles[k] + delta
        x_m = angles[m] - delta
        while x_m <= e_k:
            x_m += 2 * np.pi
        ring_at.append(net.lane(arc(centre, r_ring, x_k, e_k, LANE_SPACING), 1))
        ring_between.append(net.lane(arc(centre, r_ring, e_k, x_m, LANE_SPACING), 1))
    for k in range(arms):
        e_pt = net.lanes[ring_between[k]][0]
        conn = bezier(net.lanes[ins[k]][-1], angles[k] + np.pi, e_pt, angles[k] + delta + np.pi / 2, LANE_SPACING)
        conn[0], conn[-1] = net.lanes[ins[k]][-1], e_pt
        entries.append(net.lane(conn, 0))
        x_pt = net.lanes[ring_at[k]][0]
        conn = bezier(x_pt, angles[k] - delta + np.pi / 2, net.lanes[outs[k]][0], angles[k], LANE_SPACING)
        conn[0], conn[-1] = x_pt, net.lanes[outs[k]][0]
        exits.append(net.lane(conn, 1))
    for k in range(arms):
        # snap the ring joints so consecutive ring arcs share their end points exactly
        net.lanes[ring_at[k]][-1] = net.lanes[ring_between[k]][0]
        net.lanes[ring_between[k]][-1] = net.lanes[ring_at[(k + 1) % arms]][0]
    for k in range(arms):
        for hops in range(1, arms):
            m = (k + hops) % arms
            ring = [ring_between[k]]
            for step in range(1, hops):
                q = (k + step) % arms
                ring += [ring_at[q], ring_between[q]]
            full = (ins[k], entries[k], *ring, exits[m], outs[m])
            net.route(full, ego=hops <= 2)      # the ego leaves at the first or second exit
            net.route((*ring, exits[m], outs[m]), border=False)   # traffic already on the ring
    # edges: island, and the outer boundary between consecutive arms
    net.edges.append(arc(centre, r_island, 0.0, 2 * np.pi, EDGE_SPACING))
    half = width + shoulder
    for k in range(arms):
        m = (k + 1) % arms
        a0 = angles[k] + delta + gamma
        a1 = angles[m] - delta - gamma
        while a1 <= a0:
            a1 += 2 * np.pi
        p0, far_k = r_arm * u[k] + half * nrm[k], (r_arm + arm_length) * u[k] + half * nrm[k]
        p3, far_m = r_arm * u[m] - half * nrm[m], (r_arm + arm_length) * u[m] - half * nrm[m]
        outer = arc(centre, r_outer, a0, a1, EDGE_SPACING)
        fillet_in = bezier(p0, angles[k] + np.pi, outer[0], a0 + np.pi / 2, EDGE_SPACING)
        fillet_out = bezier(outer[-1], a1 + np.pi / 2, p3, angles[m], EDGE_SPACING)
        net.edges.append(np.concatenate([_segment(far_k, p0, EDGE_SPACING)[:-1], fillet_in[:-1], outer,
                                         fillet_out[1:], _segment(p3, far_m, EDGE_SPACING)[1:]]))


def _taper_road(rng: np.random.Generator, net: _Net, frame: _Frame, count: int, width: float,
                shoulder: float, s_taper: float, s_join: float, with_ramp: bool,
                ramp_levels: tuple[int, int]) -> None:
    """One-way road with ``count`` lanes (lane 0 leftmost at offset 0) plus a lane that
    tapers into the rightmost one between ``s_taper`` and ``s_join``.

    ``with_ramp``: the tapering lane is an on-ramp's acceleration lane (fed by a ramp
    approaching from the right); otherwise it is the road's own rightmost lane that ends.
    """
    length = frame.length
    d_target = -(count - 1) * width          # the lane it merges into
    d_extra = d_target - width                # the lane that ends
    for j in range(count - 1):
        net.route((net.lane(frame.line(0.0, length, -j * width)),))
    main_a = net.lane(frame.line(0.0, s_join, d_target))
    main_b = net.lane(frame.line(s_join, length, d_target))
    net.route((main_a, main_b))
    s_start = 0.0
    approach = None
    if with_ramp:
        s_start = float(rng.uniform(50.0, 70.0))
        phi = np.radians(rng.uniform(12.0, 22.0))
        h_a = frame.heading_at(s_start)
        p_a = frame.at(s_start, d_extra)[0]
        far = p_a - rng.uniform(45.0, 65.0) * _unit(h_a + phi)
        approach = bezier(far, h_a + phi, p_a, h_a, LANE_SPACING)
        approach[-1] = p_a
    ending_d = lambda s: _smooth(s, s_taper, s_join, d_extra, d_target)  # noqa: E731
    ending = frame.line(s_start, s_join, ending_d)
    ending[-1] = net.lanes[main_b][0]
    low, high = ramp_levels
    if approach is not None:
        ending[0] = approach[-1]
        ramp = net.lane(approach, low)
        net.route((ramp, net.lane(ending, low), main_b), ego=True)
    else:
        net.route((net.lane(ending, low), main_b), ego=True)
    net.levels[main_a] = high
    # edges and lines
    edge_off = 0.5 * width + shoulder
    net.edges.append(frame.line(0.0, length, edge_off, EDGE_SPACING))
    right_d = lambda s: np.where(s <= s_join, ending_d(s), d_target) - edge_off  # noqa: E731
    right = frame.line(s_start, length, right_d, EDGE_SPACING)
    if approach is not None:
        ramp_right = offset_polyline(approach, -edge_off)
        ramp_left = offset_polyline(approach, edge_off)
        main_right = frame.line(0.0, s_start + 10.0, d_target - edge_off, EDGE_SPACING)
        hit = first_intersection(main_right, ramp_left)
        if hit is None:
            raise _Reject("ramp edge does not meet the main road edge")
        ia, ib, point = hit
        net.edges.append(np.concatenate([main_right[:ia + 1], point[None]]))
        net.edges.append(np.concatenate([ramp_left[:ib + 1], point[None]]))
        net.edges.append(np.concatenate([ramp_right, right[1:]]))
        net.lines.append(frame.line(s_start, s_taper, d_target - 0.5 * width, LINE_SPACING))
    else:
        net.edges.append(right)
        net.lines.append(frame.line(0.0, s_taper, d_target - 0.5 * width, LINE_SPACING))
    for j in range(count - 1):
        net.lines.append(frame.line(0.0, length, -(j + 0.5) * width, LINE_SPACING))


def _curved_frame(rng: np.random.Generator, length: float, max_curvature: float) -> _Frame:
    split = rng.uniform(0.3, 0.7) * length
    k1, k2 = rng.uniform(-max_curvature, max_curvature, 2)
    return _Frame(length, [(split, k1), (length, k2)])


def _family_merge(rng: np.random.Generator, net: _Net) -> None:
    count = int(rng.choice([1, 2]))
    length = rng.uniform(250.0, 300.0)
    frame = _curved_frame(rng, length, 1.0 / 300.0)
    s_taper = rng.uniform(50.0, 70.0) + rng.uniform(40.0, 70.0)
    _taper_road(rng, net, frame, count, width=rng.uniform(3.4, 3.9), shoulder=rng.uniform(0.9, 1.4),
                s_taper=s_taper, s_join=s_taper + rng.uniform(30.0, 45.0), with_ramp=True, ramp_levels=(0, 1))


def _family_lane_drop(rng: np.random.Generator, net: _Net) -> None:
    count = int(rng.choice([1, 2]))          # lanes that continue; one more ends
    length = rng.uniform(200.0, 240.0)
    frame = _curved_frame(rng, length, 1.0 / 200.0)
    s_taper = rng.uniform(90.0, 120.0)
    _taper_road(rng, net, frame, count, width=rng.uniform(3.3, 3.8), shoulder=rng.uniform(0.8, 1.4),
                s_taper=s_taper, s_join=s_taper + rng.uniform(40.0, 60.0), with_ramp=False, ramp_levels=(1, 1))


def _family_parked(rng: np.random.Generator, net: _Net) -> None:
    width, shoulder = rng.uniform(3.2, 3.8), rng.uniform(0.8, 1.3)
    length = rng.uniform(150.0, 190.0)
    frame = _curved_frame(rng, length, 1.0 / 150.0)
    taper, margin = rng.uniform(16.0, 24.0), rng.uniform(5.0, 8.0)
    # parked vehicles, rear of the first at s_first
    s = rng.uniform(75.0, 95.0)
    boxes = []
    for _ in range(int(rng.integers(1, 5))):
        truck = rng.random() < 0.2
        lng = rng.uniform(6.5, 9.0) if truck else rng.uniform(4.0, 5.2)
        wid = rng.uniform(2.3, 2.5) if truck else rng.uniform(1.8, 2.1)
        shift = rng.uniform(0.1, max(0.1, 0.5 * width + shoulder - 0.5 * wid - 0.35))
        boxes.append((s + 0.5 * lng, lng, wid, shift))
        s += lng + rng.uniform(1.0, 5.0)
    s_first, s_last = boxes[0][0] - 0.5 * boxes[0][1], boxes[-1][0] + 0.5 * boxes[-1][1]
    s_b0, s_b1 = s_first - margin - taper, s_last + margin + taper
    right, left = -0.5 * width, 0.5 * width
    right_a = net.lane(frame.line(0.0, s_b0, right))
    right_mid = net.lane(frame.line(s_b0, s_b1, right))
    right_b = net.lane(frame.line(s_b1, length, right))
    # the bypass swings out only as far as the widest parked vehicle needs (0.6 m beside a
    # 2.1 m car): a bypass on the oncoming lane's centreline would make the two lanes
    # equally near, and the nearest-lane metrics (lane_align, lane_center) a coin flip
    # between them for a car that drives it exactly
    inner = max(right - shift + 0.5 * wid for _, _, wid, shift in boxes)
    out = float(np.clip(inner + 0.5 * 2.1 + 0.6, right + 1.0, left))
    swing = lambda s: np.where(s < 0.5 * (s_b0 + s_b1),  # noqa: E731
                               _smooth(s, s_b0, s_b0 + taper, right, out),
                               _smooth(s, s_b1 - taper, s_b1, out, right))
    bypass = frame.line(s_b0, s_b1, swing)
    bypass[0], bypass[-1] = net.lanes[right_a][-1], net.lanes[right_b][0]
    net.lanes[right_mid][0], net.lanes[right_mid][-1] = net.lanes[right_a][-1], net.lanes[right_b][0]
    by = net.lane(bypass, 0)
    oncoming = net.lane(frame.line(length, 0.0, left))
    net.route((right_a, by, right_b), ego=True)
    net.route((oncoming,))
    for centre_s, lng, wid, shift in boxes:
        xy = frame.at(centre_s, right - shift)[0]
        net.parked.append((xy, frame.heading_at(centre_s), lng, wid, right_mid))
    # the ego's task ends once it is past the last parked vehicle, before it swings back
    net.ego_goal_xy = frame.at(s_last + margin, out)[0]
    edge = width + shoulder
    net.edges.append(frame.line(0.0, length, edge, EDGE_SPACING))
    net.edges.append(frame.line(0.0, length, -edge, EDGE_SPACING))
    net.lines.append(frame.line(0.0, length, 0.0, LINE_SPACING))


_BUILDERS: dict[str, Callable[[np.random.Generator, _Net], None]] = {
    "intersection": _family_intersection,
    "t_junction": _family_t_junction,
    "roundabout": _family_roundabout,
    "merge": _family_merge,
    "lane_drop": _family_lane_drop,
    "parked": _family_parked,
}


@dataclasses.dataclass(frozen=True)
class _FamilySpec:
    agents: tuple[int, int]          # target number of agents (inclusive range)
    speed: tuple[float, float]       # desired speeds, m/s
    late_fraction: float             # share of traffic that enters after step 0
    moving_trucks: bool
    # rivals are timed to leave the shared zone (not to enter it) when the ego reaches it, and
    # no rival is placed untimed (neither by the traffic loop nor by the fallback draw: a draw
    # where no timed rival fits is rejected): for a long shared zone (the parked family's
    # bypass, 50-90 m of the oncoming lane) an oncoming car that enters it with the ego holds
    # the ego back for the 6-8 s it takes to pass, and the ego's log then ends short of its goal
    rivals_leave_first: bool = False
    rival_eta_scale: float = 1.0     # rivals are timed to reach their meeting point at this x the ego's ETA


_SPECS = {
    "intersection": _FamilySpec((4, 22), (8.0, 12.0), 0.15, True),
    "t_junction": _FamilySpec((4, 16), (8.0, 12.5), 0.15, True),
    "roundabout": _FamilySpec((4, 16), (6.5, 10.0), 0.2, False),
    "merge": _FamilySpec((4, 22), (14.0, 19.5), 0.3, True),
    "lane_drop": _FamilySpec((4, 22), (10.0, 15.0), 0.3, True),
    "parked": _FamilySpec((3, 12), (8.0, 12.0), 0.15, False, rivals_leave_first=True, rival_eta_scale=0.6),
}


class _Reject(Exception):
    """A random draw produced an unusable scene; the generator draws again."""


# =========================================================================== agents
def _route_conflict(lane_offsets: dict[int, float], other: tuple[int, ...], conflicts: LaneConflicts,
                    own: tuple[int, ...]) -> tuple[float, float] | None:
    """First conflict zone of a route with another: (entry, exit) on the own route, m."""
    own_set, other_set = set(own), set(other)
    best = None
    for c in range(conflicts.count):
        a, b = int(conflicts.a[c]), int(conflicts.b[c])
        if a in own_set and b in other_set and b not in own_set and a not in other_set:
            enter = lane_offsets[a] + conflicts.enter_a[c]
            if best is None or enter < best[0]:
                best = (float(enter), float(lane_offsets[a] + conflicts.exit_a[c]))
    return best


class _Placer:
    """Chooses agents (routes, sizes, start states, driver parameters) for a network."""

    def __init__(self, rng: np.random.Generator, net: _Net, spec: _FamilySpec, conflicts: LaneConflicts):
        self.rng, self.net, self.spec, self.conflicts = rng, net, spec, conflicts
        self.lane_len = np.array([cumulative_length(p)[-1] for p in net.lanes])
        self.polys = [route_polyline(net.lanes, r) for r in net.routes]
        self.cum = [cumulative_length(p) for p in self.polys]
        self.heads = [vertex_headings(p) for p in self.polys]
        self.offsets = []
        for r in net.routes:
            starts = np.concatenate([[0.0], np.cumsum(self.lane_len[list(r)])[:-1]])
            self.offsets.append(dict(zip(r, starts)))
        self.curvy = [float(np.max(np.abs(np.diff(h)) / np.maximum(np.diff(c), 1e-6)))
                      for h, c in zip(self.heads, self.cum)]
        self.agents: list[dict] = []

    # -- helpers
    def pose(self, route: int, s: float) -> tuple[np.ndarray, float]:
        c = self.cum[route]
        xy = np.array([np.interp(s, c, self.polys[route][:, 0]), np.interp(s, c, self.polys[route][:, 1])])
        return xy, float(np.interp(s, c, self.heads[route]))

    def conflict_zone(self, route: int, other: int) -> tuple[float, float] | None:
        return _route_conflict(self.offsets[route], self.net.routes[other], self.conflicts, self.net.routes[route])

    def conflict_entry(self, route: int, other: int) -> float | None:
        hit = self.conflict_zone(route, other)
        return None if hit is None else hit[0]

    def meeting_point(self, route: int, ego_route: int) -> float:
        """Arc length on ``route`` that a rival is timed to reach with the ego: the start of
        its conflict zone with the ego's route, or its end for ``rivals_leave_first``."""
        zone = self.conflict_zone(route, ego_route)
        return zone[1] if self.spec.rivals_leave_first else zone[0]

    def draw_size(self, route: int, allow_truck: bool) -> tuple[float, float]:
        if allow_truck and self.spec.moving_trucks and self.curvy[route] < 1.0 / 40.0 and self.rng.random() < 0.15:
            return float(self.rng.uniform(7.0, 10.0)), float(self.rng.uniform(2.3, 2.5))
        return float(self.rng.uniform(4.0, 5.2)), float(self.rng.uniform(1.8, 2.1))

    def fits(self, xy: np.ndarray, heading: float, length: float, width: float, speed: float) -> bool:
        """No overlap at step 0 with already placed agents, boxes inflated by a following gap."""
        placed = [a for a in self.agents if a["start_step"] == 0
                  and np.hypot(*(a["xy"] - xy)) < a["length"] + length + 4.0 + 1.2 * (a["speed"] + speed)]
        if not placed:
            return True
        c2 = np.array([a["xy"] for a in placed])
        h2 = np.array([a["heading"] for a in placed])
        s2 = np.array([[a["length"] + 2.0 * (1.0 + 0.6 * a["speed"]), a["width"] + 0.4] for a in placed])
        s1 = np.array([length + 2.0 * (1.0 + 0.6 * speed), width + 0.4])
        return not bool(boxes_overlap(xy[None], np.array([heading]), s1[None], c2, h2, s2).any())

    def add(self, route: int, s: float, speed: float, start_step: int, length: float, width: float,
            static: bool = False, lane_route: tuple[int, ...] | None = None,
            xy: np.ndarray | None = None, heading: float | None = None) -> None:
        rng = self.rng
        if xy is None:
            xy, heading = self.pose(route, s)
        desired = rng.uniform(*self.spec.speed)
        self.agents.append(dict(
            route=lane_route if lane_route is not None else self.net.routes[route], route_id=route,
            s=float(s), speed=float(speed), start_step=int(start_step), length=length, width=width,
            static=static, xy=xy, heading=heading, desired=desired,
            headway=rng.uniform(1.2, 1.8), accel=rng.uniform(1.2, 2.0), decel=rng.uniform(1.8, 2.5),
            gap=rng.uniform(2.0, 3.0)))

    def speed_at(self, route: int, s: float, desired: float) -> float:
        """A start speed that the curve ahead allows (lateral acceleration <= 2.5 m/s^2)."""
        c, h = self.cum[route], self.heads[route]
        ahead = (c >= s) & (c <= s + 25.0)
        if ahead.sum() >= 2:
            kappa = np.max(np.abs(np.diff(h[ahead])) / np.maximum(np.diff(c[ahead]), 1e-6))
            desired = min(desired, float(np.sqrt(2.5 / max(kappa, 1e-6))))
        return desired

    # -- placement
    def place(self, target: int) -> int:
        rng, net = self.rng, self.net
        for xy, heading, lng, wid, lane in net.parked:
            poly = net.lanes[lane]
            seg = int(np.argmin(point_segment_distance(xy[None], poly[:-1], poly[1:])[0]))
            along = float(np.dot(xy - poly[seg], poly[seg + 1] - poly[seg]) / np.linalg.norm(poly[seg + 1] - poly[seg]))
            s_lane = float(cumulative_length(poly)[seg]) + along
            self.add(-1, s_lane, 0.0, 0, lng, wid, static=True, lane_route=(lane,), xy=xy, heading=heading)
        # ego: on an ego route, 6-30 m before its first conflict with any other route
        ego_route = int(net.ego_routes[int(rng.integers(len(net.ego_routes)))])
        others = [r for r in range(len(net.routes)) if r != ego_route]
        zones = [z for z in (self.conflict_zone(ego_route, r) for r in others) if z is not None]
        entry, first_exit = min(zones) if zones else (0.5 * self.cum[ego_route][-1],) * 2
        # the ego's task runs through its conflict zones (out of the junction), but not
        # more than net.ego_reach m past its first one (a roundabout ring passes many entries)
        own = net.routes[ego_route]
        exits = [self.offsets[ego_route][a] + x for a, b, x in
                 zip(self.conflicts.a, self.conflicts.b, self.conflicts.exit_a) if a in own and b not in own]
        self.ego_zone_exit = min(float(max(exits)), first_exit + net.ego_reach) if exits else entry
        # the goal lies at least 5 m past the first conflict zone, the one its partners are
        # timed for (_assemble)
        self.ego_first_exit = min(float(first_exit), self.ego_zone_exit)
        if net.ego_goal_xy is not None:     # the goal test is "5 m past ego_zone_exit"
            poly = self.polys[ego_route]
            self.ego_zone_exit = float(self.cum[ego_route][np.argmin(np.hypot(*(poly - net.ego_goal_xy).T))]) - 5.0
            self.ego_first_exit = self.ego_zone_exit
        length, width = self.draw_size(ego_route, allow_truck=False)
        s0 = max(entry - rng.uniform(3.0, 18.0) - 0.5 * length, 0.5 * length + 0.5)
        desired = rng.uniform(*self.spec.speed)
        speed = rng.uniform(0.3, 0.9) * self.speed_at(ego_route, s0, desired)
        xy, heading = self.pose(ego_route, s0)
        if not self.fits(xy, heading, length, width, speed):
            raise _Reject("ego does not fit")
        self.add(ego_route, s0, speed, 0, length, width)
        ego = len(self.agents) - 1
        ego_eta = max(entry - s0 - 0.5 * length, 0.0) / max(speed, 3.0)
        # rivals: routes that conflict with the ego's, timed to reach their meeting point
        # (the zone's start, or its end for rivals_leave_first) at about the ego's time
        rivals = [r for r in others if self.conflict_entry(r, ego_route) is not None]
        rival_set = set(rivals)
        # at most 1-3 agents on routes that cross or join the ego's, all present from the
        # start: the ego meets real interaction but its task stays feasible (the rest of the
        # traffic uses the other routes)
        max_rivals = int(rng.integers(1, 4))
        tries = 0
        while rivals and tries < 6 and len(self.agents) < min(target, len(net.parked) + 1 + max_rivals):
            tries += 1
            r = int(rivals[int(rng.integers(len(rivals)))])
            e_r = self.meeting_point(r, ego_route)
            length, width = self.draw_size(r, allow_truck=True)
            desired = rng.uniform(*self.spec.speed)
            dist = ego_eta * self.spec.rival_eta_scale * desired * rng.uniform(0.6, 1.3) + rng.uniform(-5.0, 5.0)
            s_r = min(e_r - max(dist, 3.0) - 0.5 * length, e_r - 3.0 - 0.5 * length)
            if s_r < 0.5 * length + 0.5:
                continue
            speed = rng.uniform(0.5, 1.0) * self.speed_at(r, s_r, desired)
            xy, heading = self.pose(r, s_r)
            if self.fits(xy, heading, length, width, speed):
                self.add(r, s_r, speed, 0, length, width)
        count_rivals = sum(1 for a in self.agents if a["route_id"] in rival_set)
        for _ in range(0 if count_rivals else 10):     # the timed draw failed: anywhere before the zone
            r = int(rivals[int(rng.integers(len(rivals)))]) if rivals else -1
            if r < 0:
                break
            length, width = self.draw_size(r, allow_truck=True)
            hi = self.meeting_point(r, ego_route) - 3.0 - 0.5 * length
            if hi <= 0.5 * length + 0.5:
                continue
            s_r = rng.uniform(0.5 * length + 0.5, hi)
            speed = rng.uniform(0.5, 1.0) * self.speed_at(r, s_r, rng.uniform(*self.spec.speed))
            xy, heading = self.pose(r, s_r)
            if self.fits(xy, heading, length, width, speed):
                if self.spec.rivals_leave_first:
                    # this rival would be untimed: it may enter the long shared zone with the
                    # ego and hold it back. Rejected where it would have been added, so the
                    # random draws (and the scenes) of every other seed stay as they were
                    raise _Reject("no timed rival fits")
                self.add(r, s_r, speed, 0, length, width)
                count_rivals = 1
                break
        if not count_rivals:
            raise _Reject("no agent crosses or joins the ego's route")
        # traffic: anywhere on the first lane of a random route, or entering later at its start
        tries = 0
        while len(self.agents) < target and tries < 6 * target:
            tries += 1
            r = int(rng.integers(len(net.routes)))
            length, width = self.draw_size(r, allow_truck=True)
            desired = rng.uniform(*self.spec.speed)
            late = rng.random() < self.spec.late_fraction
            if r in rival_set:
                if late or count_rivals >= max_rivals or self.spec.rivals_leave_first:
                    continue
            if late and net.border[r]:
                s_r = 0.5 * length + 0.5
                self.add(r, s_r, rng.uniform(0.6, 1.0) * self.speed_at(r, s_r, desired),
                         int(rng.integers(3, 70)), length, width)
                continue
            first = self.lane_len[net.routes[r][0]]
            hi = first - 0.5 * length - 1.0
            lo = 0.5 * length + 0.5
            if hi <= lo:
                continue
            s_r = rng.uniform(lo, hi)
            speed = rng.uniform(0.4, 1.0) * self.speed_at(r, s_r, desired)
            xy, heading = self.pose(r, s_r)
            if self.fits(xy, heading, length, width, speed):
                self.add(r, s_r, speed, 0, length, width)
                count_rivals += int(r in rival_set)
        return ego

    def plan(self) -> AgentPlan:
        a = self.agents
        col = lambda key, dtype=np.float64: np.array([x[key] for x in a], dtype=dtype)  # noqa: E731
        return AgentPlan(
            routes=tuple(x["route"] for x in a), start_s=col("s"), start_speed=col("speed"),
            start_step=col("start_step", np.int64), static=col("static", bool), length=col("length"),
            width=col("width"), desired_speed=col("desired"), headway=col("headway"), accel=col("accel"),
            decel=col("decel"), gap=col("gap"))


# =========================================================================== checks
def log_collisions(xy: np.ndarray, heading: np.ndarray, valid: np.ndarray, sizes: np.ndarray,
                   margin: float = 0.0) -> np.ndarray:
    """(K, 3) int array of ``(step, i, j)`` (i < j) where the oriented boxes of agents i and j
    overlap while both are valid. ``xy (N, T, 2)``, ``heading (N, T)``, ``valid (N, T)``,
    ``sizes (N, 2)`` (length, width, m); ``margin`` inflates every box side, m."""
    n = xy.shape[0]
    i, j = np.triu_indices(n, k=1)
    size = np.asarray(sizes, dtype=np.float64) + 2.0 * margin
    reach = 0.5 * np.linalg.norm(size, axis=1)
    both = valid[i] & valid[j]                                            # (P, T)
    close = np.linalg.norm(xy[i] - xy[j], axis=-1) < (reach[i] + reach[j])[:, None]
    p, t = np.nonzero(both & close)
    if p.size == 0:
        return np.zeros((0, 3), np.int64)
    hit = boxes_overlap(xy[i[p], t].astype(np.float64), heading[i[p], t].astype(np.float64), size[i[p]],
                        xy[j[p], t].astype(np.float64), heading[j[p], t].astype(np.float64), size[j[p]])
    return np.stack([t[hit], i[p][hit], j[p][hit]], axis=1).astype(np.int64)


def _place_parked(result: DriveResult, plan: AgentPlan, parked: list) -> DriveResult:
    """Parked agents stand where they were placed (beside the lane centre), speed 0."""
    static = plan.static.astype(bool)
    if not static.any():
        return result
    xy, heading, velocity = result.xy.copy(), result.heading.copy(), result.velocity.copy()
    xy[static] = np.array([p[0] for p in parked])[:, None, :]
    heading[static] = ((np.array([p[1] for p in parked]) + np.pi) % (2 * np.pi) - np.pi)[:, None]
    velocity[static] = 0.0
    return dataclasses.replace(result, xy=xy, heading=heading, velocity=velocity)


def _drive_clean(net: _Net, conflicts: LaneConflicts, plan: AgentPlan, ego: int) -> tuple[AgentPlan, DriveResult, int]:
    """Drive, then drop traffic involved in log collisions (never the ego) until the logs
    are collision-free; agents whose entry never came are dropped too. Parked agents come
    first in the plan and are never dropped."""
    levels = right_of_way(np.array(net.levels), net.give_way)
    for _ in range(MAX_AGENTS + 1):
        result = _place_parked(drive(net.lanes, levels, conflicts, plan), plan, net.parked)
        drop = result.entered < 0
        hits = log_collisions(result.xy, result.heading, result.valid,
                              np.stack([plan.length, plan.width], axis=1), margin=0.05)
        if hits.shape[0]:
            # the first collision only: dropping one agent changes what the others do
            _, i, j = hits[np.argmin(hits[:, 0])]
            victim = j if j != ego and not plan.static[j] else i
            if victim == ego or plan.static[victim]:
                raise _Reject("the ego or a parked vehicle is in a log collision")
            drop[victim] = True
        if not drop.any():
            return plan, result, ego
        if drop[ego]:
            raise _Reject("ego dropped")
        keep = ~drop
        ego = int(np.sum(keep[:ego]))
        plan = plan.subset(keep)
        if hits.shape[0] == 0:            # only agents that never appeared: no need to drive again
            return plan, result.without_absent(keep), ego
    raise _Reject("could not clean the logs")


# =========================================================================== public API
def _family_index(family: str) -> int:
    if family not in FAMILIES:
        raise ValueError(f"unknown procedural family {family!r}; expected one of {FAMILIES}")
    return FAMILIES.index(family)


def build(family: str, seed: int) -> ProceduralScene:
    """Generate the scenario ``(family, seed)`` and keep the routes that produced it."""
    index = _family_index(family)
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2 ** 63:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    seed = int(seed)
    rng = np.random.default_rng([index, seed])
    spec = _SPECS[family]
    fallback: ProceduralScene | None = None
    valid_draws = 0
    for _ in range(_MAX_ATTEMPTS + _CLEARING_ATTEMPTS):
        try:
            scene = _build_once(family, seed, rng, spec)
        except _Reject:
            continue
        # Prefer scenes whose expert ego clears its conflict and reaches its goal, so that
        # log replay (the "expert" regime) completes the task; a scene where it does not is
        # kept only when no such draw comes up within _CLEARING_ATTEMPTS valid scenes.
        if ego_log_reaches_goal(scene.scenario):
            return scene
        fallback = fallback or scene
        valid_draws += 1
        if valid_draws >= _CLEARING_ATTEMPTS:
            break
    if fallback is not None:
        return fallback
    raise RuntimeError(f"procedural family {family!r} seed {seed}: no valid scene in {_MAX_ATTEMPTS} draws")


#: Valid scenes drawn per seed while looking for one whose expert ego reaches its goal.
_CLEARING_ATTEMPTS = 12


def ego_log_reaches_goal(scenario: Scenario, radius: float = 2.0) -> bool:
    """Whether the ego's log passes within ``radius`` m of its goal: log replay completes the
    task. BehaviorBench's goals are the logs' final positions, so this holds for every one of
    its tasks; the evaluator keeps only such procedural scenes as tasks
    (:func:`cpalgo.evaluate.runner.make_tasks`)."""
    e = scenario.ego_index
    xy = scenario.log_xy[e][scenario.log_valid[e]]
    return bool(np.min(np.linalg.norm(xy - scenario.goal_xy[e], axis=1)) <= radius)


def _build_once(family: str, seed: int, rng: np.random.Generator, spec: _FamilySpec) -> ProceduralScene:
    net = _Net()
    _BUILDERS[family](rng, net)
    # built, checked and driven in the family's own frame (axis-aligned bounding boxes stay
    # tight there); the finished scene is rotated by this angle
    angle = float(rng.uniform(0.0, 2.0 * np.pi))
    if not net.check():
        raise _Reject("road edge too close to a lane")
    used = np.zeros(len(net.lanes), bool)
    for r in net.routes:
        used[list(r)] = True
    conflicts = lane_conflicts(net.lanes, used)
    placer = _Placer(rng, net, spec, conflicts)
    target = int(rng.integers(spec.agents[0], spec.agents[1] + 1)) + len(net.parked)
    ego = placer.place(min(target, MAX_AGENTS))
    plan, result, ego = _drive_clean(net, conflicts, placer.plan(), ego)
    n = plan.num_agents
    if n < 2:
        raise _Reject("fewer than two agents")
    ego_lanes = set(plan.routes[ego])
    partner_lanes = {lane for i, r in enumerate(plan.routes) if i != ego and not plan.static[i] for lane in r}
    if not any(a in ego_lanes and b in partner_lanes - ego_lanes for a, b in zip(conflicts.a, conflicts.b)):
        raise _Reject("no remaining agent crosses or joins the ego's route")
    return _assemble(family, seed, rng, net, plan, result, ego, placer.ego_zone_exit, placer.ego_first_exit, angle)


def _assemble(family: str, seed: int, rng: np.random.Generator, net: _Net, plan: AgentPlan,
              result: DriveResult, ego: int, ego_zone_exit: float, ego_first_exit: float,
              angle: float) -> ProceduralScene:
    n = plan.num_agents
    static = plan.static.astype(bool)
    valid, xy, heading, velocity = result.valid, result.xy, result.heading, result.velocity
    # goals: where the log ends if the agent moved far enough (10 m; for the ego: past its
    # first conflict zone), else further along the route (15-35 m from its start)
    first = np.argmax(valid, axis=1)
    s_first = result.s[np.arange(n), first]
    s_last = result.s[:, -1]
    far_enough = s_first + 10.0
    far_enough[ego] = max(far_enough[ego], ego_zone_exit + 5.0)
    stop_limit = np.maximum(result.routes.length - 0.5 * plan.length - 1.0, s_last)
    further = np.maximum(s_first + rng.uniform(15.0, 35.0, n), far_enough)
    goal_s = np.where(s_last >= far_enough, s_last, np.minimum(further, stop_limit))
    if s_last[ego] >= far_enough[ego]:
        # a log that clears every conflict zone (a scene build() prefers): the ego's goal is
        # where the log was EGO_GOAL_SLACK s before its end, at least 5 m past its first zone
        slack_steps = int(round(EGO_GOAL_SLACK / DT))
        goal_s[ego] = max(min(ego_first_exit + 5.0, s_last[ego]), result.s[ego, -1 - slack_steps])
    goal_xy, _ = result.routes.at(goal_s)
    goal_xy = np.where(static[:, None], xy[:, 0], goal_xy)
    # rotate the whole scene (row vectors: p @ rot turns p by +angle)
    rot = np.array([[np.cos(angle), np.sin(angle)], [-np.sin(angle), np.cos(angle)]])
    xy, velocity, goal_xy = xy @ rot, velocity @ rot, goal_xy @ rot
    heading = (heading + angle + np.pi) % (2.0 * np.pi) - np.pi
    net.rotate(angle)
    xy = np.where(valid[..., None], xy, INVALID_XY)
    heading = np.where(valid, heading, 0.0)
    velocity = np.where(valid[..., None], velocity, 0.0)
    # roads: lanes first so that lane k is road polyline k
    polylines = list(net.lanes) + net.lines + net.edges + net.crosswalks
    types = ([RoadType.LANE] * len(net.lanes) + [RoadType.ROAD_LINE] * len(net.lines)
             + [RoadType.ROAD_EDGE] * len(net.edges) + [RoadType.CROSSWALK] * len(net.crosswalks))
    offsets = np.concatenate([[0], np.cumsum([p.shape[0] for p in polylines])]).astype(np.int32)
    scenario = Scenario(
        id=f"{family}-{seed}",
        log_xy=xy.astype(np.float32),
        log_heading=heading.astype(np.float32),
        log_velocity=velocity.astype(np.float32),
        log_valid=valid,
        goal_xy=goal_xy.astype(np.float32),
        sizes=np.stack([plan.length, plan.width], axis=1).astype(np.float32),
        agent_types=np.full(n, AgentType.VEHICLE, np.int8),
        road_points=np.concatenate(polylines).astype(np.float32),
        road_offsets=offsets,
        road_types=np.array(types, np.int8),
        ego_index=ego,
        mark_as_expert=np.zeros(n, bool),
        agent_ids=np.arange(n, dtype=np.int64),
        tracks_to_predict=None,
        source=f"procedural:{family}:{seed}",
        family=family,
    )
    ctrl = np.nonzero(scenario.controllable)[0].astype(np.int32)
    scenario = dataclasses.replace(scenario, tracks_to_predict=ctrl)
    polys = tuple(route_polyline(net.lanes, r) for r in plan.routes)
    return ProceduralScene(scenario=scenario, routes=tuple(tuple(r) for r in plan.routes),
                           route_polylines=polys, static=static, seed=seed)


def generate(family: str, seed: int) -> Scenario:
    """The procedural scenario ``(family, seed)``; see the module docstring for the families.

    Raises ``ValueError`` for an unknown family (the message lists :data:`FAMILIES`) or a
    negative / non-integer seed.
    """
    return build(family, seed).scenario


def _pool_seeds(n: int, seed: int, seed_range: tuple[int, int], salt: int) -> np.ndarray:
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
    lo, hi = seed_range
    span = hi - lo
    if n > span:
        raise ValueError(f"n={n} exceeds the seed range size {span}")
    start = int(np.random.default_rng([int(seed), salt]).integers(0, span))
    return lo + (start + np.arange(n, dtype=np.int64)) % span


def _check_pool_args(n: int, families: tuple[str, ...] | list[str] | None) -> tuple[str, ...]:
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n must be a non-negative integer, got {n!r}")
    fams = FAMILIES if families is None else (families,) if isinstance(families, str) else tuple(families)
    if not fams:
        raise ValueError("families must not be empty")
    for f in fams:
        _family_index(f)
    return fams


def pool(n: int, seed: int = 0, families: tuple[str, ...] | list[str] | None = None,
         split: str = "train") -> list[Scenario]:
    """A mixed pool of ``n`` scenarios cycling through ``families`` (default: all).

    Scenario ``i`` is ``generate(families[i % F], seeds[i])`` where ``seeds`` are ``n``
    consecutive (wrapping) seeds of the split's range starting at a point drawn from
    ``seed``: ``split="train"`` uses :data:`TRAIN_SEED_RANGE`, ``"eval"``
    :data:`EVAL_SEED_RANGE`, so train and eval pools never share a scenario. All
    scenarios in one pool are distinct.
    """
    fams = _check_pool_args(n, families)
    ranges = {"train": (TRAIN_SEED_RANGE, 0), "eval": (EVAL_SEED_RANGE, 1)}
    if split not in ranges:
        raise ValueError(f"split must be 'train' or 'eval', got {split!r}")
    seed_range, salt = ranges[split]
    seeds = _pool_seeds(n, seed, seed_range, salt)
    return [generate(fams[i % len(fams)], int(s)) for i, s in enumerate(seeds)]


def train_pool(n: int, seed: int = 0, families: tuple[str, ...] | list[str] | None = None) -> list[Scenario]:
    """``pool(n, seed, families, split="train")``: scenario seeds in ``[0, 2**30)``."""
    return pool(n, seed, families, split="train")


def eval_pool(n: int, seed: int = 0, families: tuple[str, ...] | list[str] | None = None) -> list[Scenario]:
    """``pool(n, seed, families, split="eval")``: scenario seeds in ``[2**30, 2**31)``."""
    return pool(n, seed, families, split="eval")


