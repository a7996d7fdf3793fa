"""Rule-based driver that produces the logged trajectories of procedural scenarios.

Every agent follows a *route*: a sequence of lane centrelines (indices into a lane
list) concatenated into one polyline. Its state is the arc length ``s`` of its box
centre along that polyline and its speed ``v``; pose = point and tangent of the route at
``s``; velocity = ``v`` times the tangent. All agents step together, vectorised with
NumPy over agents and agent pairs (one Python iteration per time step, none per agent).

Longitudinal control is the Intelligent Driver Model (IDM) against the most
constraining of:

* the leader on the same path: any agent whose current lane is also on my route and
  lies ahead of me (lane offsets make this one gather per step);
* virtual leaders at merges: an agent on another lane that joins my route at the same
  point and is closer to that point than I am;
* stop lines in front of conflict zones while I yield (gap acceptance, below);
* a comfortable speed envelope for curves (lateral acceleration limit) that also brings
  me to a stop at the end of my route (agents stay on the map, valid to the last step).

Conflict zones come from pairs of lanes whose centrelines pass closer than
:data:`CONFLICT_DISTANCE` (crossing, merging or diverging lanes). At a crossing I wait
while another agent occupies the zone, or while an agent that has the right of way
(by the lane rule, :func:`right_of_way`; else first come: who first got near the zone,
else who arrives sooner, else the lower index) would be in the zone while I am, padded by
my accepted time gap, unless that agent is itself standing and waiting for someone
else. I wait at the first of my zones still ahead (not inside the junction) and go on
once I could no longer stop comfortably. The generator still checks the logs for
collisions and drops offending traffic.

Public helpers :func:`poses_along` and :func:`follow_speed_profile` turn an arc-length
or speed profile on any polyline into poses; the simulator's IDM and replay code and
the tests may reuse them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cpsim.scenario.datatypes import DT, NUM_STEPS
from cpsim.scenario.geometry_utils import BatchedPolylines, cumulative_length

__all__ = [
    "CONFLICT_DISTANCE", "CROSS", "MERGE", "DIVERGE", "LaneConflicts", "lane_conflicts", "right_of_way",
    "AgentPlan", "DriveResult", "drive", "poses_along", "follow_speed_profile",
]

#: Two lanes interact where their centrelines come closer than this (m): about two
#: half car widths plus a margin. Parallel lanes (>= 3.2 m apart) never do.
CONFLICT_DISTANCE = 2.6
CROSS, MERGE, DIVERGE = 1, 2, 3

MIN_GAP = 2.0             # IDM jam distance s0, m
EMERGENCY_DECEL = 9.0     # hardest braking, m/s^2
STOP_LINE_MARGIN = 1.0    # my front stops this far before a conflict zone, m
COMMIT_DECEL = 3.5        # past the point where stopping needs more than this, I go on, m/s^2
LATERAL_ACCEL = 2.5       # comfortable lateral acceleration in curves, m/s^2
ENVELOPE_DECEL = 1.5      # deceleration used to anticipate curves and route ends, m/s^2
CRUISE_FRACTION = 0.75    # zone crossing times assume at most this share of the desired speed
END_MARGIN = 1.0          # agents stop with their front this far before the end of their route, m
_FAR = 1.0e9
_GRID = 0.5               # arc-length step of the tabulated speed envelope, m


# --------------------------------------------------------------------------- reusable pieces
def poses_along(polyline: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``(T, 2)`` and headings ``(T,)`` (rad, wrapped to (-pi, pi]) at arc lengths
    ``s (T,)`` (m, clipped to the polyline) along ``polyline (n, 2)``."""
    route = BatchedPolylines([np.asarray(polyline, dtype=np.float64)])
    s = np.asarray(s, dtype=np.float64)
    xy, heading = route.at(s[None, :])
    return xy[0], _wrap(heading[0])


def follow_speed_profile(polyline: np.ndarray, speeds: np.ndarray, dt: float = DT,
                         s0: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drive along ``polyline`` with the speed profile ``speeds (T,)`` (m/s, one per step).

    Step ``t`` is at arc length ``s0 + dt * sum(speeds[:t])``. Returns positions ``(T, 2)``,
    headings ``(T,)`` and world-frame velocities ``(T, 2)``; a profile that runs past the
    end of the polyline stops there (speed set to 0).
    """
    speeds = np.asarray(speeds, dtype=np.float64)
    s = s0 + dt * np.concatenate([[0.0], np.cumsum(speeds[:-1])])
    length = cumulative_length(np.asarray(polyline, dtype=np.float64))[-1]
    xy, heading = poses_along(polyline, s)
    v = np.where(s >= length, 0.0, speeds)
    return xy, heading, v[:, None] * np.stack([np.cos(heading), np.sin(heading)], axis=1)


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


# --------------------------------------------------------------------------- lane conflicts
@dataclasses.dataclass(frozen=True)
class LaneConflicts:
    """Directed conflict zones between lanes, one row per (lane a, lane b) ordered pair.

    ``a, b (C,)`` lane indices; ``kind (C,)`` CROSS / MERGE / DIVERGE; ``enter_a, exit_a``
    the arc-length interval (m) on lane ``a`` where it is within CONFLICT_DISTANCE of lane
    ``b``; ``enter_b, exit_b`` the same on ``b``.
    """

    a: np.ndarray
    b: np.ndarray
    kind: np.ndarray
    enter_a: np.ndarray
    exit_a: np.ndarray
    enter_b: np.ndarray
    exit_b: np.ndarray

    @property
    def count(self) -> int:
        return int(self.a.shape[0])


def lane_conflicts(lanes: list[np.ndarray], lane_mask: np.ndarray | None = None,
                   distance: float = CONFLICT_DISTANCE) -> LaneConflicts:
    """Find the conflict zones between every pair of (masked) lanes.

    Consecutive lanes (one ends where the other starts) do not conflict: the agents on
    them are handled by car following. Lanes that share both their start and their end
    (alternative paths such as a bypass around a blocked lane) are skipped as well.
    """
    num = len(lanes)
    mask = np.ones(num, bool) if lane_mask is None else np.asarray(lane_mask, bool)
    boxes = np.array([[p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()] for p in lanes])
    cum = [cumulative_length(p) for p in lanes]
    near = np.all(boxes[:, None, :2] - distance <= boxes[None, :, 2:], axis=-1)
    near &= np.all(boxes[None, :, :2] - distance <= boxes[:, None, 2:], axis=-1)
    rows: list[tuple] = []
    ends = np.array([[p[0, 0], p[0, 1], p[-1, 0], p[-1, 1]] for p in lanes])
    for a, b in zip(*np.nonzero(np.triu(near & mask[:, None] & mask[None, :], k=1))):
        pa, pb = lanes[a], lanes[b]
        same_start = np.linalg.norm(ends[a, :2] - ends[b, :2]) < 0.1
        same_end = np.linalg.norm(ends[a, 2:] - ends[b, 2:]) < 0.1
        consecutive = (np.linalg.norm(ends[a, 2:] - ends[b, :2]) < 0.1
                       or np.linalg.norm(ends[b, 2:] - ends[a, :2]) < 0.1)
        if consecutive or (same_start and same_end):
            continue
        # vertex-to-vertex distances (one matrix serves both lanes); the zone is then widened
        # by one vertex on each side, which covers what a point-to-segment test would add
        d2 = ((pa[:, None, :] - pb[None, :, :]) ** 2).sum(axis=-1) < distance ** 2
        close_a = d2.any(axis=1)
        if not close_a.any():
            continue
        close_b = d2.any(axis=0)
        ia, ib = np.nonzero(close_a)[0], np.nonzero(close_b)[0]
        # widen by one vertex on each side so the zone covers the true crossing extent
        ea, xa = cum[a][max(ia[0] - 1, 0)], cum[a][min(ia[-1] + 1, len(pa) - 1)]
        eb, xb = cum[b][max(ib[0] - 1, 0)], cum[b][min(ib[-1] + 1, len(pb) - 1)]
        kind = MERGE if same_end else DIVERGE if same_start else CROSS
        rows.append((a, b, kind, ea, xa, eb, xb))
        rows.append((b, a, kind, eb, xb, ea, xa))
    if not rows:
        z = np.zeros(0)
        return LaneConflicts(z.astype(np.int64), z.astype(np.int64), z.astype(np.int64), z, z, z, z)
    arr = np.array(rows, dtype=np.float64)
    return LaneConflicts(arr[:, 0].astype(np.int64), arr[:, 1].astype(np.int64),
                         arr[:, 2].astype(np.int64), arr[:, 3], arr[:, 4], arr[:, 5], arr[:, 6])


# --------------------------------------------------------------------------- agents and driving
@dataclasses.dataclass(frozen=True)
class AgentPlan:
    """What the driver needs per agent (N agents; arrays are (N,)).

    routes: lane-index sequences (each a tuple of ints into the lane list).
    start_s: arc length (m) of the box centre along the route when the agent appears.
    start_speed: speed (m/s) when it appears.
    start_step: first step at which it may appear (it waits while an agent on its route is
        too close to its start point, so late agents should start at the map border).
    static: parked agents: never move, speed 0, valid at every step.
    length, width: box size (m).
    desired_speed: IDM free-road speed (m/s). headway: IDM time headway (s).
    accel: IDM maximum acceleration (m/s^2). decel: IDM comfortable deceleration (m/s^2).
    gap: accepted time gap at conflict zones (s).
    """

    routes: tuple[tuple[int, ...], ...]
    start_s: np.ndarray
    start_speed: np.ndarray
    start_step: np.ndarray
    static: np.ndarray
    length: np.ndarray
    width: np.ndarray
    desired_speed: np.ndarray
    headway: np.ndarray
    accel: np.ndarray
    decel: np.ndarray
    gap: np.ndarray

    @property
    def num_agents(self) -> int:
        return len(self.routes)

    def subset(self, keep: np.ndarray) -> AgentPlan:
        """The plan restricted to the agents where ``keep`` is True (or listed indices)."""
        idx = np.nonzero(keep)[0] if np.asarray(keep).dtype == bool else np.asarray(keep)
        values = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            values[f.name] = tuple(v[i] for i in idx) if f.name == "routes" else np.asarray(v)[idx]
        return AgentPlan(**values)


@dataclasses.dataclass(frozen=True)
class DriveResult:
    """Logged trajectories (N agents, T steps): ``s, speed (N, T)`` route arc length (m) and
    speed (m/s); ``valid (N, T)``; ``xy (N, T, 2)``; ``heading (N, T)`` (rad, wrapped);
    ``velocity (N, T, 2)`` (m/s); ``routes``: the route polylines; ``entered (N,)`` the step
    each agent appeared (-1: never)."""

    s: np.ndarray
    speed: np.ndarray
    valid: np.ndarray
    xy: np.ndarray
    heading: np.ndarray
    velocity: np.ndarray
    routes: BatchedPolylines
    entered: np.ndarray

    def without_absent(self, keep: np.ndarray) -> DriveResult:
        """The logs of the agents where ``keep`` is True, valid only when every dropped agent
        never entered (an agent that never appeared influenced nobody, so nothing else changes)."""
        if np.any(self.entered[~keep] >= 0):
            raise ValueError("without_absent: a dropped agent entered the scene; drive again instead")
        idx = np.nonzero(keep)[0]
        polylines = [self.routes.xy[i, :self.routes.count[i]] for i in idx]
        return DriveResult(s=self.s[idx], speed=self.speed[idx], valid=self.valid[idx], xy=self.xy[idx],
                           heading=self.heading[idx], velocity=self.velocity[idx],
                           routes=BatchedPolylines(polylines), entered=self.entered[idx])


def route_polyline(lanes: list[np.ndarray], route: tuple[int, ...]) -> np.ndarray:
    """The lanes of ``route`` concatenated (shared joint vertices kept once), ``(n, 2)``."""
    parts = [lanes[route[0]]] + [lanes[r][1:] for r in route[1:]]
    return np.concatenate(parts, axis=0)


def _speed_envelope(routes: BatchedPolylines, desired: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """(N, K) highest speed at each route vertex from which the agent can still slow down
    (at ENVELOPE_DECEL) to the comfortable curve speed of every later vertex and to a stop
    at the end of its route. ``lengths (N,)`` box lengths, m."""
    ds = np.maximum(np.diff(routes.s, axis=1), 1e-6)
    curvature = np.abs(np.diff(routes.heading, axis=1)) / ds
    curvature = np.concatenate([curvature[:, :1], np.maximum(curvature[:, 1:], curvature[:, :-1]),
                                curvature[:, -1:]], axis=1)
    limit2 = np.minimum(LATERAL_ACCEL / np.maximum(curvature, 1e-9), desired[:, None] ** 2)
    reach = limit2 + 2.0 * ENVELOPE_DECEL * routes.s
    envelope2 = np.minimum.accumulate(reach[:, ::-1], axis=1)[:, ::-1] - 2.0 * ENVELOPE_DECEL * routes.s
    # agents stop at the end of their route (front END_MARGIN before it) instead of leaving the map
    stop_at = (routes.length - 0.5 * lengths - END_MARGIN)[:, None]
    envelope2 = np.minimum(envelope2, 2.0 * ENVELOPE_DECEL * (stop_at - routes.s))
    return np.sqrt(np.maximum(envelope2, 0.0))


def right_of_way(levels: np.ndarray, give_way: list[tuple[int, int]] = ()) -> np.ndarray:
    """(L, L) int8 right-of-way matrix from lane priority ``levels (L,)`` (higher goes first)
    and explicit ``give_way`` pairs ``(a, b)``: lane ``a`` gives way to lane ``b``.

    Entry ``[a, b]``: 1 when an agent on ``a`` gives way to one on ``b``, -1 for the
    reverse, 0 for first come, first served.
    """
    levels = np.asarray(levels, np.float64)
    matrix = np.sign(levels[None, :] - levels[:, None]).astype(np.int8)
    for a, b in give_way:
        matrix[a, b], matrix[b, a] = 1, -1
    return matrix


def drive(lanes: list[np.ndarray], priority: np.ndarray, conflicts: LaneConflicts,
          plan: AgentPlan, num_steps: int = NUM_STEPS, dt: float = DT,
          trace: list | None = None) -> DriveResult:
    """Simulate all agents of ``plan`` for ``num_steps`` steps and return their logs.

    ``priority``: who has the right of way at conflict zones, either lane levels ``(L,)``
    (higher goes first) or a :func:`right_of_way` matrix ``(L, L)``; ties are first come,
    first served. ``trace``: when a list, one
    dict per step is appended with the constraint matrices ``gap (N, N)`` (m, the binding
    distance to each other agent: leader, virtual leader or stop line), ``stop (N, N)``
    (I wait for that agent at a conflict zone) and ``accel (N,)``, for debugging.
    """
    n, num_lanes = plan.num_agents, len(lanes)
    polylines = [route_polyline(lanes, r) for r in plan.routes]
    routes = BatchedPolylines(polylines)
    lane_len = np.array([cumulative_length(p)[-1] for p in lanes])
    width_r = max(len(r) for r in plan.routes)
    route_lanes = np.full((n, width_r), -1, np.int64)
    lane_start = np.full((n, width_r), np.inf)
    offset = np.full((n, num_lanes), np.nan)           # arc length where lane l starts on route i
    for i, r in enumerate(plan.routes):                # build time only (N <= 32)
        starts = np.concatenate([[0.0], np.cumsum(lane_len[list(r)])[:-1]])
        route_lanes[i, :len(r)] = r
        lane_start[i, :len(r)] = starts
        offset[i, list(r)] = starts
    length = plan.length.astype(np.float64)
    half = 0.5 * length
    static = plan.static.astype(bool)
    moving = ~static
    envelope = _speed_envelope(routes, plan.desired_speed.astype(np.float64), length)
    # the envelope on a uniform arc-length grid: one gather per step instead of a search
    grid = np.arange(0.0, float(routes.length.max()) + 2.0 * _GRID, _GRID)
    envelope_grid = routes.interp(envelope, np.broadcast_to(grid, (n, grid.shape[0])))
    grid_last = grid.shape[0] - 1
    priority = np.asarray(priority)
    rule = right_of_way(priority) if priority.ndim == 1 else priority.astype(np.int8)
    zones = _pair_zones(offset, moving, conflicts, rule)
    zi, zj = zones["i"], zones["j"]
    z_in, z_out, o_in, o_out = zones["in"], zones["out"], zones["other_in"], zones["other_out"]
    is_cross, is_merge, is_diverge = zones["kind"] == CROSS, zones["kind"] == MERGE, zones["kind"] == DIVERGE
    higher, same = zones["higher"], zones["same"]
    reverse = zones["reverse"]
    lower_index = zj < zi
    half_i, half_j = half[zi], half[zj]
    half_sum = half_i + half_j
    gap_i = plan.gap.astype(np.float64)[zi]
    accel_i, accel_j = plan.accel.astype(np.float64)[zi], plan.accel.astype(np.float64)[zj]
    # speed assumed when estimating how long crossing a zone takes (curves slow agents down)
    cruise = np.maximum(CRUISE_FRACTION * plan.desired_speed.astype(np.float64), 1.0)
    cruise_i, cruise_j = cruise[zi], cruise[zj]
    half_sum_nn = half[:, None] + half[None, :]

    # ---- state
    s = plan.start_s.astype(np.float64).copy()
    v = np.where(static, 0.0, plan.start_speed.astype(np.float64))
    started = static | (plan.start_step <= 0)
    entered = np.where(started, 0, -1)
    claim = np.full(zi.shape[0], float(num_steps + 1))
    v0 = plan.desired_speed.astype(np.float64)
    a_max, b_comf = plan.accel.astype(np.float64), plan.decel.astype(np.float64)
    headway = plan.headway.astype(np.float64)[:, None]
    sqrt_ab = (2.0 * np.sqrt(a_max * b_comf))[:, None]
    # nobody starts faster than it could still slow down for the curves and the route end
    v = np.minimum(v, routes.interp(envelope, s))
    route_end = routes.length
    rows = np.arange(n)
    lower_nn = rows[None, :] < rows[:, None]
    not_self = ~np.eye(n, dtype=bool)
    pair_gap = np.full((n, n), _FAR)
    pair_lead = np.zeros((n, n))
    ahead_nn = np.full((n, n), _FAR)
    waiting = np.zeros(n, bool)           # agents that stood at a stop line on the last step

    log_s = np.zeros((n, num_steps))
    log_v = np.zeros((n, num_steps))
    log_valid = np.zeros((n, num_steps), bool)
    for t in range(num_steps):
        # -- where is agent j in my route's arc length? (NaN: not on my route)
        k = (s[:, None] >= lane_start).sum(axis=1) - 1
        local = s - lane_start[rows, k]
        proj = offset[:, route_lanes[rows, k]] + local[None, :]

        # -- late agents appear at the start of their route (the map border, where only
        #    agents of the same entry lane can be) once it is clear
        pending = ~started & (plan.start_step <= t)
        if pending.any():
            need = half_sum_nn + MIN_GAP + np.maximum(v, v[:, None]) * 1.0
            blocked = (np.abs(proj - s[:, None]) < need) & started[None, :]
            cand = pending & ~blocked.any(axis=1)
            clash = (np.abs(proj - s[:, None]) < need) & cand[None, :] & lower_nn
            cand &= ~clash.any(axis=1)
            started = started | cand
            entered = np.where(cand, t, entered)
        log_s[:, t], log_v[:, t], log_valid[:, t] = s, v, started
        active = started & moving
        follow = (proj > s[:, None]) & (active[:, None] & started[None, :] & not_self)
        gap_follow = np.where(follow, proj - s[:, None] - half_sum_nn, _FAR)

        # -- conflict zones, one entry per ordered agent pair that has one (flat arrays)
        s_i, s_j, v_i, v_j = s[zi], s[zj], v[zi], v[zj]
        front_i, rear_i, front_j, rear_j = s_i + half_i, s_i - half_i, s_j + half_j, s_j - half_j
        live = active[zi] & active[zj]
        occupied = (front_j >= o_in) & (rear_j <= o_out)          # the other is inside its zone
        dist_me = z_in - front_i
        inside_me = (dist_me <= 0.0) & (rear_i <= z_out)
        cleared_me, cleared_other = rear_i > z_out, rear_j > o_out
        floor_i, floor_j = np.maximum(v_i, 2.0), np.maximum(v_j, 2.0)
        tta_other = np.maximum(o_in - front_j, 0.0) / floor_j     # 0 once its front is in
        tta_me = np.maximum(dist_me, 0.0) / floor_i
        t_exit = _travel_time(np.maximum(z_out - rear_i, 0.0), v_i, accel_i, cruise_i)
        t_exit_other = _travel_time(np.maximum(o_out - rear_j, 0.0), v_j, accel_j, cruise_j)
        near = live & ~cleared_me & (dist_me < np.maximum(8.0, 4.0 * v_i))
        claim = np.where(near, np.minimum(claim, t), claim)
        claim_other = claim[reverse]
        other_first = (claim_other < claim) | ((claim_other == claim) & (
            (tta_other < tta_me) | ((tta_other == tta_me) & lower_index)))
        # the other has the right of way, unless it is itself standing and waiting for someone
        # else (a waiting car does not hold up the cars it would go before)
        priority = (higher | (same & other_first)) & ~(waiting[zj] & (v_j < 1.0))
        # I wait at the first of my zones still ahead of me, not inside the junction, so that
        # a waiting car never blocks a zone another car waits for (no "blocking the box")
        ahead_nn[zi, zj] = np.where(dist_me > 0.0, z_in, _FAR)
        first_ahead = ahead_nn.min(axis=1)[zi]
        stop_gap = np.where(first_ahead < _FAR, np.minimum(first_ahead, z_in), z_in) - front_i - STOP_LINE_MARGIN
        committed = stop_gap < v_i * v_i / (2.0 * COMMIT_DECEL)
        relevant = live & ~cleared_me & ~inside_me & ~cleared_other
        # I give way when our occupation times, padded by my accepted gap, overlap
        overlap = (tta_other < t_exit + gap_i) & (t_exit_other + gap_i > tta_me)
        yield_zone = relevant & ((is_cross & (occupied | (priority & ~committed & overlap)))
                                 | (is_diverge & occupied))
        # merges: the agent nearer the joining point leads (virtual leader); I yield to an
        # agent with priority that would reach the joining point within my accepted gap
        to_join_me, to_join_other = z_out - s_i, o_out - s_j
        merging = is_merge & live & (to_join_me > 0.0) & (to_join_other > 0.0)
        virtual = merging & (to_join_other < to_join_me) & (dist_me < np.maximum(15.0, 3.0 * v_i))
        yield_merge = (merging & ~virtual & ~inside_me & priority & ~committed
                       & (to_join_other / floor_j < to_join_me / floor_i + gap_i))
        stop = yield_zone | yield_merge
        waiting = np.zeros(n, bool)
        waiting[zi[stop]] = True
        pair_gap[zi, zj] = np.where(stop, stop_gap, np.where(virtual, to_join_me - to_join_other - half_sum, _FAR))
        pair_lead[zi, zj] = np.where(stop, 0.0, v_j)

        # -- IDM against every constraint; the most constraining one wins
        # per pair, the nearer of the two constraints (leader on my route, zone/merge) counts
        vv = v[:, None]
        nearer_follow = gap_follow < pair_gap
        gap = np.where(nearer_follow, gap_follow, pair_gap)
        lead = np.where(nearer_follow, v[None, :], pair_lead)
        need = MIN_GAP + np.maximum(0.0, vv * headway + vv * (vv - lead) / sqrt_ab)
        interaction = ((need / np.maximum(gap, 1e-2)) ** 2).max(axis=1)
        min_gap = gap.min(axis=1)
        v_free = np.minimum(envelope_grid[rows, np.minimum((s * (1.0 / _GRID)).astype(np.int64), grid_last)], v0)
        accel = a_max * (1.0 - (v / np.maximum(v_free, 0.1)) ** 4 - interaction)
        accel = np.maximum(np.minimum(np.where(min_gap < 0.05, -EMERGENCY_DECEL, accel), a_max), -EMERGENCY_DECEL)
        if trace is not None:
            stop_nn = np.zeros((n, n), bool)
            stop_nn[zi, zj] = stop
            trace.append({"gap": gap.copy(), "stop": stop_nn, "accel": accel.copy()})
        v_new = np.maximum(v + accel * dt, 0.0)
        s_new = s + 0.5 * (v + v_new) * dt
        # at the very end of the route: stop there, with the speed that covers the distance left
        at_end = s_new >= route_end - half
        v_new = np.where(at_end, np.maximum(2.0 * (route_end - half - s) / dt - v, 0.0), v_new)
        s = np.where(active, np.minimum(s_new, route_end - half), s)
        v = np.where(active, v_new, v)

    xy, heading = routes.at(log_s)
    heading = _wrap(heading)
    velocity = log_v[..., None] * np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    return DriveResult(s=log_s, speed=log_v, valid=log_valid, xy=xy, heading=heading,
                       velocity=velocity, routes=routes, entered=entered)


def _travel_time(distance: np.ndarray, speed: np.ndarray, accel: np.ndarray, cruise: np.ndarray) -> np.ndarray:
    """Time (s) to cover ``distance`` (m) from ``speed`` accelerating at ``accel`` up to ``cruise``
    (then constant; an agent already faster than ``cruise`` keeps its speed)."""
    cruise = np.maximum(cruise, speed)
    ramp = (cruise * cruise - speed * speed) / (2.0 * accel)
    accelerating = (np.sqrt(speed * speed + 2.0 * accel * distance) - speed) / accel
    return np.where(distance <= ramp, accelerating,
                    (cruise - speed) / accel + (distance - ramp) / np.maximum(cruise, 0.1))


def _pair_zones(offset: np.ndarray, moving: np.ndarray, conflicts: LaneConflicts,
                rule: np.ndarray) -> dict[str, np.ndarray]:
    """Conflict zone of every ordered pair of moving agents whose routes conflict (the first
    zone along my route), as flat arrays over those pairs.

    ``offset (N, L)``: arc length where lane l starts on route i (NaN: not on it). Returns
    ``i, j`` agent indices, ``in, out`` my zone on my route, ``other_in, other_out`` the
    other's zone on its route (m), ``kind``, ``higher`` (I give way to the other by rule),
    ``same`` (first come, first served), ``reverse`` (index of the pair (j, i)).
    """
    n = offset.shape[0]
    best = np.full((n, n), np.inf)
    pick = np.full((n, n), -1)
    present = ~np.isnan(offset)
    for c in range(conflicts.count):      # per lane pair, vectorised over agent pairs
        a, b = conflicts.a[c], conflicts.b[c]
        # both lanes on one route means the pair is handled by following on that route
        ok = (present[:, a] & ~present[:, b])[:, None] & (present[:, b] & ~present[:, a])[None, :]
        ok &= moving[:, None] & moving[None, :]
        cand = np.where(ok, offset[:, a][:, None] + conflicts.enter_a[c], np.inf)
        better = cand < best
        best = np.where(better, cand, best)
        pick = np.where(better, c, pick)
    np.fill_diagonal(pick, -1)
    # keep a pair only when its reverse has a zone too (always true for symmetric conflicts)
    has = (pick >= 0) & (pick.T >= 0)
    zi, zj = np.nonzero(has)
    c = pick[zi, zj]
    index = np.full((n, n), -1)
    index[zi, zj] = np.arange(zi.shape[0])
    a, b = conflicts.a[c], conflicts.b[c]
    order = rule[a, b]
    return {
        "i": zi, "j": zj,
        "in": offset[zi, a] + conflicts.enter_a[c], "out": offset[zi, a] + conflicts.exit_a[c],
        "other_in": offset[zj, b] + conflicts.enter_b[c], "other_out": offset[zj, b] + conflicts.exit_b[c],
        "kind": conflicts.kind[c], "higher": order > 0, "same": order == 0,
        "reverse": index[zj, zi],
    }
