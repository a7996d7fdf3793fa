"""Top-down rendering: fast NumPy rasteriser, static matplotlib figures, videos.

Three entry points:

* :func:`render_frame` / :class:`TopDownRenderer`: a (H, W, 3) uint8 top-down image of
  one world (roads, agents as oriented boxes coloured by controller and state, goals,
  the ego's trail), with the camera on the ego or on the whole scene. Rasterised with
  NumPy (no matplotlib): the static road layer of a scenario is drawn once and cached,
  each frame only crops it and draws the agents, so a frame costs about a millisecond.
* :func:`plot_scenario`: a static matplotlib figure of a :class:`~cpsim.scenario.Scenario`
  at one logged step (uses the Agg canvas directly, never switches a user's backend).
* :func:`write_video` / :func:`record_episode`: frames to a GIF or MP4 with imageio,
  written atomically (temp file + ``os.replace``).

Colours (RGB): controller POLICY blue, REPLAY grey, IDM green, STATIC dark slate; the
ego purple; collided agents red, off-road agents orange (drawn at the pose where they
were removed); agents removed at their goal are drawn faded. Goals are rings, the
ego's trail a thin line.

World coordinates are metres with y up; images have row 0 at the top (north up, the
camera never rotates, which is what lets the road layer be cached).
"""

from __future__ import annotations

import os
from collections import OrderedDict
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from cpsim.arrays import to_numpy as _np
from cpsim.atomic import atomic_path
from cpsim.scenario.datatypes import RoadType, Scenario

# Enum values of cpsim.config.Controller / Outcome (kept as ints so that rendering a
# Scenario never needs the simulator module).
POLICY, REPLAY, IDM, STATIC, NONE = 0, 1, 2, 3, 4
RUNNING, GOAL, COLLISION, OFFROAD, TIMEOUT = 0, 1, 2, 3, 4

CAMERAS = ("ego", "scene")
GOAL_MODES = ("none", "ego", "policy", "all")

BACKGROUND = np.array([226, 232, 220], np.uint8)      # off-road: pale green-grey
ROAD_SURFACE = np.array([150, 150, 155], np.uint8)    # asphalt around lane centrelines
LANE_CENTRE = np.array([172, 172, 178], np.uint8)     # faint centreline
ROAD_LINE = np.array([250, 250, 250], np.uint8)       # painted lines
ROAD_EDGE = np.array([40, 40, 45], np.uint8)          # kerbs
CROSSWALK = np.array([205, 205, 210], np.uint8)
STOP_SIGN = np.array([200, 30, 30], np.uint8)
SPEED_BUMP = np.array([230, 200, 40], np.uint8)

CONTROLLER_COLORS = np.array(
    [
        [40, 110, 230],    # POLICY
        [120, 120, 120],   # REPLAY
        [40, 160, 80],     # IDM
        [70, 80, 95],      # STATIC
        [120, 120, 120],   # NONE (not simulated; drawn like replay if ever present)
    ],
    np.uint8,
)
EGO_COLOR = np.array([140, 50, 200], np.uint8)
COLLIDED_COLOR = np.array([220, 30, 30], np.uint8)
OFFROAD_COLOR = np.array([245, 140, 0], np.uint8)
TRAIL_COLOR = np.array([180, 120, 230], np.uint8)

LANE_HALF_WIDTH_M = 1.9   # half of a 3.8 m lane: the asphalt strip drawn around centrelines


# ---------------------------------------------------------------------------- rasterising
def _disc_offsets(radius_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel offsets (dy, dx) of a filled disc of ``radius_px`` pixels."""
    r = max(radius_px, 0.0)
    ri = int(np.ceil(r))
    dy, dx = np.mgrid[-ri:ri + 1, -ri:ri + 1]
    keep = dy * dy + dx * dx <= r * r + 0.25
    return dy[keep].astype(np.int64), dx[keep].astype(np.int64)


def _ring_offsets(radius_px: float, thickness_px: float = 1.2) -> tuple[np.ndarray, np.ndarray]:
    ri = int(np.ceil(radius_px + thickness_px))
    dy, dx = np.mgrid[-ri:ri + 1, -ri:ri + 1]
    d = np.sqrt(dy * dy + dx * dx)
    keep = (d <= radius_px + 0.5) & (d >= radius_px - thickness_px)
    return dy[keep].astype(np.int64), dx[keep].astype(np.int64)


def _stamp(img: np.ndarray, cols: np.ndarray, rows: np.ndarray,
           offsets: tuple[np.ndarray, np.ndarray], color: np.ndarray,
           max_writes: int = 4_000_000) -> None:
    """Write ``color`` at every (row + dy, col + dx) inside ``img`` (chunked to bound memory).

    ``cols``, ``rows``: (P,) integer pixel centres; ``img`` (H, W, 3) uint8, modified in place.
    """
    if cols.size == 0:
        return
    h, w = img.shape[:2]
    oy, ox = offsets
    chunk = max(1, max_writes // max(1, oy.size))
    for s in range(0, cols.size, chunk):
        r = rows[s:s + chunk, None] + oy[None, :]
        c = cols[s:s + chunk, None] + ox[None, :]
        ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        img[r[ok], c[ok]] = color


def _sample_segments(p0: np.ndarray, p1: np.ndarray, spacing_px: float) -> np.ndarray:
    """Points every ``spacing_px`` pixels along segments p0 -> p1 ((S, 2) pixel coords)."""
    if p0.shape[0] == 0:
        return np.zeros((0, 2))
    length = np.linalg.norm(p1 - p0, axis=1)
    n = np.maximum(np.ceil(length / spacing_px).astype(np.int64), 1) + 1
    seg = np.repeat(np.arange(p0.shape[0]), n)
    start = np.cumsum(n) - n
    t = (np.arange(seg.size) - np.repeat(start, n)) / np.repeat(n - 1, n)
    return p0[seg] + (p1[seg] - p0[seg]) * t[:, None]


class _View:
    """Maps world metres to pixel coordinates of a canvas.

    ``x0``: world x of the left image border; ``y1``: world y of the top border;
    ``mpp``: metres per pixel.
    """

    def __init__(self, x0: float, y1: float, mpp: float, width: int, height: int):
        self.x0, self.y1, self.mpp, self.width, self.height = x0, y1, mpp, width, height

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) world metres -> (..., 2) float pixel (col, row) of pixel centres."""
        xy = np.asarray(xy, np.float64)
        col = (xy[..., 0] - self.x0) / self.mpp - 0.5
        row = (self.y1 - xy[..., 1]) / self.mpp - 0.5
        return np.stack([col, row], axis=-1)


def _segments_of(scenario: Scenario, types: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """All polyline segments (p0, p1), each (S, 2) world metres, of the given road types."""
    offs = scenario.road_offsets
    mask_roads = np.isin(scenario.road_types, np.asarray(types, np.int8))
    if not np.any(mask_roads):
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    # a point i starts a segment when i + 1 belongs to the same polyline
    road_of_point = np.repeat(np.arange(scenario.num_roads), np.diff(offs))
    starts = np.arange(scenario.road_points.shape[0] - 1)
    same = road_of_point[starts] == road_of_point[starts + 1]
    keep = same & mask_roads[road_of_point[starts]]
    idx = starts[keep]
    return scenario.road_points[idx], scenario.road_points[idx + 1]


def _draw_polylines(img: np.ndarray, view: _View, p0: np.ndarray, p1: np.ndarray,
                    half_width_m: float, color: np.ndarray, min_radius_px: float = 0.0) -> None:
    if p0.shape[0] == 0:
        return
    a, b = view.to_px(p0), view.to_px(p1)
    radius = max(half_width_m / view.mpp, min_radius_px)
    # cull segments entirely outside the canvas (plus the stroke radius)
    lo = np.minimum(a, b) - radius - 1
    hi = np.maximum(a, b) + radius + 1
    vis = (hi[:, 0] >= 0) & (lo[:, 0] < img.shape[1]) & (hi[:, 1] >= 0) & (lo[:, 1] < img.shape[0])
    if not np.any(vis):
        return
    pts = _sample_segments(a[vis], b[vis], spacing_px=max(0.5, 0.7 * radius))
    cols = np.rint(pts[:, 0]).astype(np.int64)
    rows = np.rint(pts[:, 1]).astype(np.int64)
    _stamp(img, cols, rows, _disc_offsets(radius), color)


def _fill_polygon(img: np.ndarray, view: _View, poly: np.ndarray, color: np.ndarray) -> None:
    """Even-odd fill of one polygon ((n, 2) world metres) over its pixel bounding box."""
    if poly.shape[0] < 3:
        return
    px = view.to_px(poly)
    c0 = max(int(np.floor(px[:, 0].min())), 0)
    c1 = min(int(np.ceil(px[:, 0].max())), img.shape[1] - 1)
    r0 = max(int(np.floor(px[:, 1].min())), 0)
    r1 = min(int(np.ceil(px[:, 1].max())), img.shape[0] - 1)
    if c1 < c0 or r1 < r0:
        return
    rr, cc = np.mgrid[r0:r1 + 1, c0:c1 + 1]
    x, y = cc.astype(np.float64), rr.astype(np.float64)
    inside = np.zeros(x.shape, bool)
    xj, yj = px[-1]
    for xi, yi in px:  # polygon vertices (few), not pixels
        crosses = (yi > y) != (yj > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_at = (xj - xi) * (y - yi) / (yj - yi) + xi
        inside ^= crosses & (x < x_at)
        xj, yj = xi, yi
    img[rr[inside], cc[inside]] = color


def _draw_roads(img: np.ndarray, view: _View, scenario: Scenario) -> None:
    """Draw the static road layer of ``scenario`` into ``img`` (in place)."""
    img[...] = BACKGROUND
    lanes = _segments_of(scenario, [RoadType.LANE])
    _draw_polylines(img, view, *lanes, LANE_HALF_WIDTH_M, ROAD_SURFACE)
    for r in np.flatnonzero(scenario.road_types == RoadType.CROSSWALK):
        _fill_polygon(img, view, scenario.road(int(r)), CROSSWALK)
    _draw_polylines(img, view, *lanes, 0.0, LANE_CENTRE, min_radius_px=0.0)
    _draw_polylines(img, view, *_segments_of(scenario, [RoadType.ROAD_LINE]), 0.08, ROAD_LINE,
                    min_radius_px=0.5)
    _draw_polylines(img, view, *_segments_of(scenario, [RoadType.SPEED_BUMP]), 0.3, SPEED_BUMP,
                    min_radius_px=1.0)
    _draw_polylines(img, view, *_segments_of(scenario, [RoadType.ROAD_EDGE]), 0.12, ROAD_EDGE,
                    min_radius_px=1.0)
    stops = np.flatnonzero(scenario.road_types == RoadType.STOP_SIGN)
    if stops.size:
        pts = np.stack([scenario.road(int(r)).mean(axis=0) for r in stops])
        px = np.rint(view.to_px(pts)).astype(np.int64)
        _stamp(img, px[:, 0], px[:, 1], _disc_offsets(max(0.8 / view.mpp, 2.0)), STOP_SIGN)


def _draw_boxes(img: np.ndarray, view: _View, xy: np.ndarray, heading: np.ndarray,
                sizes: np.ndarray, colors: np.ndarray) -> None:
    """Fill oriented boxes, batched over agents; later agents are drawn on top.

    ``xy`` (N, 2) m, ``heading`` (N,) rad, ``sizes`` (N, 2) (length, width) m,
    ``colors`` (N, 3) uint8. Each box gets a darker outline and a darker front quarter
    so that its heading is visible.
    """
    n = xy.shape[0]
    if n == 0:
        return
    centre = view.to_px(xy)
    half_diag = 0.5 * np.hypot(sizes[:, 0], sizes[:, 1]) / view.mpp
    s = int(np.ceil(half_diag.max())) + 1
    grid = np.arange(-s, s + 1)
    shape = (n, grid.size, grid.size)
    rows = np.broadcast_to(np.rint(centre[:, 1]).astype(np.int64)[:, None, None] + grid[None, :, None], shape)
    cols = np.broadcast_to(np.rint(centre[:, 0]).astype(np.int64)[:, None, None] + grid[None, None, :], shape)
    # pixel centres back in metres relative to the box centre, then into the box frame
    dx = (cols - centre[:, 0, None, None]) * view.mpp
    dy = -(rows - centre[:, 1, None, None]) * view.mpp
    c, sn = np.cos(heading)[:, None, None], np.sin(heading)[:, None, None]
    lon = c * dx + sn * dy
    lat = -sn * dx + c * dy
    half_l = 0.5 * sizes[:, 0, None, None]
    half_w = 0.5 * sizes[:, 1, None, None]
    inside = (np.abs(lon) <= half_l) & (np.abs(lat) <= half_w)
    edge = inside & ((np.abs(lon) > half_l - view.mpp) | (np.abs(lat) > half_w - view.mpp))
    front = inside & (lon > 0.5 * half_l)
    shade = np.where(edge, 0.45, np.where(front, 0.7, 1.0))
    col = (colors[:, None, None, :].astype(np.float32) * shade[..., None]).astype(np.uint8)
    ok = inside & (rows >= 0) & (rows < img.shape[0]) & (cols >= 0) & (cols < img.shape[1])
    # boolean indexing walks agents in order, so later agents (the ego last) win overlaps
    img[rows[ok], cols[ok]] = col[ok]


def _fade(color: np.ndarray, amount: float = 0.6) -> np.ndarray:
    return (color.astype(np.float32) * (1 - amount) + BACKGROUND.astype(np.float32) * amount).astype(np.uint8)


def agent_colors(controllers: np.ndarray, outcome: np.ndarray, alive: np.ndarray,
                 ego: int | None) -> np.ndarray:
    """(N, 3) uint8 colours by controller and state (see the module docstring)."""
    ctrl = np.clip(np.asarray(controllers, np.int64), 0, CONTROLLER_COLORS.shape[0] - 1)
    colors = CONTROLLER_COLORS[ctrl].copy()
    if ego is not None and 0 <= ego < colors.shape[0]:
        colors[ego] = EGO_COLOR
    outcome = np.asarray(outcome)
    alive = np.asarray(alive, bool)
    removed_goal = ~alive & (outcome == GOAL)
    colors[removed_goal] = _fade(colors[removed_goal])
    colors[outcome == COLLISION] = COLLIDED_COLOR
    colors[outcome == OFFROAD] = OFFROAD_COLOR
    return colors


# ---------------------------------------------------------------------------- renderer
class TopDownRenderer:
    """Rasterises top-down frames; caches the road layer of the last few scenarios.

    Args:
        width, height: image size in pixels.
        camera: ``"ego"`` (centred on the ego, ``view_m`` metres wide) or ``"scene"``
            (the whole road network fits the image).
        view_m: width of the ego camera's field of view, metres.
        goals: which goals to draw: ``"none"``, ``"ego"``, ``"policy"`` (policy-driven
            agents still alive, and the ego) or ``"all"`` (every agent still alive, and the ego).
        cache_size: number of scenarios whose road layer is kept.
    """

    #: the cached road layer is drawn at full resolution up to this many pixels
    MAX_LAYER_PIXELS = 16_000_000

    def __init__(self, width: int = 480, height: int = 480, camera: str = "ego",
                 view_m: float = 70.0, goals: str = "policy", cache_size: int = 8):
        if int(width) < 16 or int(height) < 16:
            raise ValueError(f"width and height must be >= 16 pixels, got {width}x{height}")
        if camera not in CAMERAS:
            raise ValueError(f"camera: unknown value {camera!r}; accepted: {list(CAMERAS)}")
        if goals not in GOAL_MODES:
            raise ValueError(f"goals: unknown value {goals!r}; accepted: {list(GOAL_MODES)}")
        if not np.isfinite(view_m) or view_m <= 0:
            raise ValueError(f"view_m must be a positive number of metres, got {view_m!r}")
        self.width, self.height = int(width), int(height)
        self.camera = camera
        self.view_m = float(view_m)
        self.goals = goals
        self._cache: OrderedDict[tuple, tuple[np.ndarray, _View]] = OrderedDict()
        self._cache_size = int(cache_size)

    # -- views
    def _scene_bounds(self, scenario: Scenario) -> tuple[float, float, float, float]:
        pts = scenario.road_points
        return float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), float(pts[:, 1].max())

    def _scene_view(self, scenario: Scenario) -> _View:
        xmin, ymin, xmax, ymax = self._scene_bounds(scenario)
        margin = 3.0
        span_x, span_y = xmax - xmin + 2 * margin, ymax - ymin + 2 * margin
        mpp = max(span_x / self.width, span_y / self.height, 1e-3)
        cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
        return _View(cx - 0.5 * self.width * mpp, cy + 0.5 * self.height * mpp, mpp, self.width, self.height)

    def _road_layer(self, scenario: Scenario, mpp: float) -> tuple[np.ndarray, _View] | None:
        """The scenario's road layer over its whole extent at ``mpp`` (cached), or None if too big."""
        key = (id(scenario), scenario.id, round(mpp, 9))
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        xmin, ymin, xmax, ymax = self._scene_bounds(scenario)
        pad = 10.0
        w = int(np.ceil((xmax - xmin + 2 * pad) / mpp))
        h = int(np.ceil((ymax - ymin + 2 * pad) / mpp))
        if w * h > self.MAX_LAYER_PIXELS:
            return None
        view = _View(xmin - pad, ymax + pad, mpp, w, h)
        layer = np.empty((h, w, 3), np.uint8)
        _draw_roads(layer, view, scenario)
        self._cache[key] = (layer, view)
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return layer, view

    def _background(self, scenario: Scenario, view: _View) -> np.ndarray:
        """Road layer cropped to ``view`` (pixel-snapped), drawn directly when not cacheable."""
        cached = self._road_layer(scenario, view.mpp)
        img = np.empty((view.height, view.width, 3), np.uint8)
        if cached is None:
            _draw_roads(img, view, scenario)
            return img
        layer, lv = cached
        # snap the view's origin to the layer's pixel grid
        c0 = int(round((view.x0 - lv.x0) / lv.mpp))
        r0 = int(round((lv.y1 - view.y1) / lv.mpp))
        view.x0 = lv.x0 + c0 * lv.mpp
        view.y1 = lv.y1 - r0 * lv.mpp
        img[...] = BACKGROUND
        sr0, sc0 = max(r0, 0), max(c0, 0)
        sr1, sc1 = min(r0 + view.height, layer.shape[0]), min(c0 + view.width, layer.shape[1])
        if sr1 > sr0 and sc1 > sc0:
            img[sr0 - r0:sr1 - r0, sc0 - c0:sc1 - c0] = layer[sr0:sr1, sc0:sc1]
        return img

    # -- frames
    def render(
        self,
        scenario: Scenario,
        xy: np.ndarray,
        heading: np.ndarray,
        sizes: np.ndarray,
        *,
        controllers: np.ndarray | None = None,
        outcome: np.ndarray | None = None,
        alive: np.ndarray | None = None,
        present: np.ndarray | None = None,
        goal_xy: np.ndarray | None = None,
        ego: int | None = 0,
        trail: np.ndarray | None = None,
    ) -> np.ndarray:
        """Render one world.

        Args (N agent slots):
            scenario: the world's scenario (its roads are drawn).
            xy: (N, 2) agent centres, m. heading: (N,) rad. sizes: (N, 2) (length, width), m.
            controllers: (N,) ``Controller`` values (default all REPLAY).
            outcome: (N,) ``Outcome`` values (default all RUNNING).
            alive: (N,) bool, agent present and not removed (default all True).
            present: (N,) bool, slot holds an agent at all (default all True); absent
                slots are not drawn. Removed agents are drawn faded / red / orange.
            goal_xy: (N, 2) goals, m (optional).
            ego: slot of the ego (camera target, purple), or None.
            trail: (T, 2) past ego positions, m (optional).

        Returns: (height, width, 3) uint8.
        """
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        n = xy.shape[0]
        heading = np.asarray(heading, np.float64).reshape(n)
        sizes = np.asarray(sizes, np.float64).reshape(n, 2)
        controllers = np.full(n, REPLAY) if controllers is None else np.asarray(controllers).reshape(n)
        outcome = np.zeros(n, np.int64) if outcome is None else np.asarray(outcome).reshape(n)
        alive = np.ones(n, bool) if alive is None else np.asarray(alive, bool).reshape(n)
        present = np.ones(n, bool) if present is None else np.asarray(present, bool).reshape(n)
        if ego is not None and not 0 <= int(ego) < n:
            raise ValueError(f"ego: slot {ego} outside [0, {n})")
        # removed agents keep their last pose; agents removed at their goal fade out,
        # collided / off-road ones stay visible in their warning colour
        present = present & np.all(np.isfinite(xy), axis=1)

        if self.camera == "scene" or ego is None:
            view = self._scene_view(scenario)
        else:
            mpp = self.view_m / self.width
            cx, cy = xy[int(ego)]
            view = _View(cx - 0.5 * self.width * mpp, cy + 0.5 * self.height * mpp, mpp,
                         self.width, self.height)
        img = self._background(scenario, view)

        colors = agent_colors(controllers, outcome, alive, ego)
        if trail is not None and len(trail) > 1:
            t = np.asarray(trail, np.float64).reshape(-1, 2)
            t = t[np.all(np.isfinite(t), axis=1)]
            if t.shape[0] > 1:
                _draw_polylines(img, view, t[:-1], t[1:], 0.25, TRAIL_COLOR, min_radius_px=0.5)

        if goal_xy is not None and self.goals != "none":
            goal_xy = np.asarray(goal_xy, np.float64).reshape(n, 2)
            show = np.zeros(n, bool)
            if self.goals == "all":
                show = present & alive
            elif self.goals == "policy":
                show = present & alive & (controllers == POLICY)
            if ego is not None:
                show[int(ego)] = present[int(ego)]
            idx = np.flatnonzero(show & np.all(np.isfinite(goal_xy), axis=1))
            if idx.size:
                gp = np.rint(view.to_px(goal_xy[idx])).astype(np.int64)
                ring = _ring_offsets(max(1.5 / view.mpp, 3.0), max(0.3 / view.mpp, 1.2))
                dot = _disc_offsets(max(0.3 / view.mpp, 1.0))
                for k, i in enumerate(idx):  # few goals; each ring is one vectorised stamp
                    _stamp(img, gp[k:k + 1, 0], gp[k:k + 1, 1], ring, colors[i])
                    _stamp(img, gp[k:k + 1, 0], gp[k:k + 1, 1], dot, colors[i])

        # draw order: faded (goal-reached) first, then others, warning colours, ego last
        order_key = np.where(~alive & (outcome == GOAL), 0, 1) + np.where(outcome >= COLLISION, 1, 0)
        order_key = order_key + np.where(outcome == TIMEOUT, -1, 0)
        if ego is not None:
            order_key[int(ego)] = 10
        draw = np.flatnonzero(present)
        draw = draw[np.argsort(order_key[draw], kind="stable")]
        _draw_boxes(img, view, xy[draw], heading[draw], sizes[draw], colors[draw])
        return img

    def render_log(self, scenario: Scenario, t: int = 0, trail: bool = True) -> np.ndarray:
        """Render the logged (expert) state of ``scenario`` at step ``t`` (all agents REPLAY)."""
        if not 0 <= int(t) < scenario.num_steps:
            raise ValueError(f"t: step {t} outside [0, {scenario.num_steps})")
        t = int(t)
        valid = scenario.log_valid[:, t]
        ego = scenario.ego_index
        ctrl = np.full(scenario.num_agents, REPLAY)
        ctrl[scenario.controllable] = POLICY
        tr = scenario.log_xy[ego, : t + 1][scenario.log_valid[ego, : t + 1]] if trail else None
        return self.render(
            scenario, scenario.log_xy[:, t], scenario.log_heading[:, t], scenario.sizes,
            controllers=ctrl, present=valid, goal_xy=scenario.goal_xy,
            ego=ego if valid[ego] else None, trail=tr,
        )

    def render_sim(self, sim: Any, world: int = 0, ego_slot: int = 0,
                   trail: np.ndarray | None = None) -> np.ndarray:
        """Render world ``world`` of a :class:`cpsim.Simulator` (reads its public outputs)."""
        if not 0 <= int(world) < sim.num_worlds:
            raise ValueError(f"world: {world} outside [0, {sim.num_worlds})")
        w = int(world)
        scenario = sim.scenarios[int(_np(sim.world_scenario)[w])]
        agent_index = _np(sim.agent_index)[w]
        present = agent_index >= 0
        safe = np.where(present, agent_index, 0)
        # per-slot box sizes and goals as the simulator holds them (logged sizes otherwise)
        sizes = _np(sim.size)[w] if hasattr(sim, "size") else scenario.sizes[safe]
        goals = _np(sim.goal)[w] if hasattr(sim, "goal") else scenario.goal_xy[safe]
        return self.render(
            scenario, _np(sim.xy)[w], _np(sim.heading)[w], sizes,
            controllers=_np(sim.controllers)[w], outcome=_np(sim.outcome)[w], alive=_np(sim.alive)[w],
            present=present, goal_xy=goals,
            ego=ego_slot if present[ego_slot] else None, trail=trail,
        )


_DEFAULT_RENDERERS: dict[tuple, TopDownRenderer] = {}


def render_frame(scenario: Scenario, xy: np.ndarray, heading: np.ndarray, sizes: np.ndarray,
                 *, width: int = 480, height: int = 480, camera: str = "ego",
                 view_m: float = 70.0, goals: str = "policy", **kwargs: Any) -> np.ndarray:
    """One top-down frame, (height, width, 3) uint8; see :meth:`TopDownRenderer.render`.

    Reuses a module-level renderer per (size, camera, view, goals) so the road layer is cached.
    """
    key = (int(width), int(height), camera, float(view_m), goals)
    renderer = _DEFAULT_RENDERERS.get(key)
    if renderer is None:
        renderer = _DEFAULT_RENDERERS[key] = TopDownRenderer(width, height, camera, view_m, goals)
    return renderer.render(scenario, xy, heading, sizes, **kwargs)


# ---------------------------------------------------------------------------- matplotlib
_MPL_ROAD_STYLE = {
    RoadType.LANE: dict(color="#9a9aa0", lw=0.6, ls=(0, (4, 3)), zorder=1),
    RoadType.ROAD_LINE: dict(color="#d8b400", lw=1.0, zorder=2),
    RoadType.ROAD_EDGE: dict(color="#202025", lw=1.6, zorder=3),
    RoadType.SPEED_BUMP: dict(color="#e6c828", lw=2.0, zorder=2),
    RoadType.DRIVEWAY: dict(color="#b0b0b0", lw=0.8, zorder=1),
    RoadType.OTHER: dict(color="#c0c0c0", lw=0.5, zorder=1),
}


def plot_roads(ax: Any, road_points: np.ndarray, road_offsets: np.ndarray, road_types: np.ndarray) -> None:
    """Draw a road network (a Scenario's ``road_points`` / ``road_offsets`` / ``road_types``)
    on a matplotlib Axes, in :func:`plot_scenario`'s style: background, lanes (dashed
    centrelines), road lines, road edges, crosswalks (filled), stop signs."""
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Circle, Polygon

    points = np.asarray(road_points)
    offsets = np.asarray(road_offsets)
    types = np.asarray(road_types)

    def road(r: int) -> np.ndarray:
        return points[int(offsets[r]):int(offsets[r + 1])]

    ax.set_facecolor("#e2e8dc")
    for rtype, style in _MPL_ROAD_STYLE.items():
        lines = [road(r) for r in np.flatnonzero(types == rtype) if road(r).shape[0] > 1]
        if lines:
            ax.add_collection(LineCollection(lines, **style))
    for r in np.flatnonzero(types == RoadType.CROSSWALK):
        ax.add_patch(Polygon(road(r), closed=True, fc="#cfcfd4", ec="#a0a0a8", lw=0.5, zorder=1.5))
    for r in np.flatnonzero(types == RoadType.STOP_SIGN):
        ax.add_patch(Circle(road(r).mean(axis=0), 0.8, color="#c81e1e", zorder=4))


def plot_scenario(scenario: Scenario, ax: Any = None, t: int = 0, *, show_logs: bool = True,
                  show_goals: bool = True, figsize: tuple[float, float] = (7.0, 7.0)) -> Any:
    """Static matplotlib drawing of ``scenario`` at logged step ``t``; returns the Axes.

    Lanes (dashed centrelines), road lines, road edges, crosswalks (filled), stop signs,
    every agent valid at ``t`` as an oriented box (ego purple, controllable blue, others
    grey), goals of controllable agents (rings) and, with ``show_logs``, faint logged
    trajectories. When ``ax`` is None a new ``Figure`` on an Agg canvas is created (no
    pyplot, so a user's interactive backend is never switched); save it with
    ``ax.figure.savefig(path)``.
    """
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Circle, Polygon

    if not 0 <= int(t) < scenario.num_steps:
        raise ValueError(f"t: step {t} outside [0, {scenario.num_steps})")
    t = int(t)
    if ax is None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(figsize=figsize, dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
    plot_roads(ax, scenario.road_points, scenario.road_offsets, scenario.road_types)

    ctrl = scenario.controllable
    ego = scenario.ego_index
    if show_logs:
        segs = [scenario.log_xy[i][scenario.log_valid[i]] for i in range(scenario.num_agents)
                if scenario.log_valid[i].sum() > 1]
        if segs:
            ax.add_collection(LineCollection(segs, color="#6a7fb0", lw=0.5, alpha=0.35, zorder=4))
    for i in np.flatnonzero(scenario.log_valid[:, t]):  # drawing artists, not simulation
        color = "#" + "".join(f"{v:02x}" for v in (EGO_COLOR if i == ego else
                                                    CONTROLLER_COLORS[POLICY if ctrl[i] else REPLAY]))
        length, width = scenario.sizes[i]
        c, s = np.cos(scenario.log_heading[i, t]), np.sin(scenario.log_heading[i, t])
        corners = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]]) * [length, width]
        rot = corners @ np.array([[c, s], [-s, c]]) + scenario.log_xy[i, t]
        ax.add_patch(Polygon(rot, closed=True, fc=color, ec="black", lw=0.6,
                             zorder=6 if i == ego else 5))
        nose = scenario.log_xy[i, t] + 0.5 * length * np.array([c, s])
        ax.plot([scenario.log_xy[i, t, 0], nose[0]], [scenario.log_xy[i, t, 1], nose[1]],
                color="white", lw=0.8, zorder=7)
        if show_goals and (ctrl[i] or i == ego):
            ax.add_patch(Circle(scenario.goal_xy[i], 1.5, fill=False, ec=color, lw=1.2, zorder=5))
    xmin, ymin = scenario.road_points.min(axis=0)
    xmax, ymax = scenario.road_points.max(axis=0)
    ax.set_xlim(xmin - 3, xmax + 3)
    ax.set_ylim(ymin - 3, ymax + 3)
    ax.set_aspect("equal")
    ax.set_title(f"{scenario.id} ({scenario.family}), t={t}", fontsize=9)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return ax


# ---------------------------------------------------------------------------- video
VIDEO_FORMATS = (".gif", ".mp4")


def write_video(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float = 10.0) -> str:
    """Write frames ((H, W, 3) uint8, all the same size) to ``path`` (.gif or .mp4).

    MP4 needs the ``imageio-ffmpeg`` package; frames are padded to even sizes for H.264.
    The file is written to a temporary name in the same folder and moved into place, so
    ``path`` is never half-written. Returns the path as a string.
    """
    import imageio.v2 as imageio

    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in VIDEO_FORMATS:
        raise ValueError(f"path: unsupported video extension {ext!r}; accepted: {list(VIDEO_FORMATS)}")
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be positive, got {fps!r}")
    frames = [np.asarray(f) for f in frames]
    if not frames:
        raise ValueError("frames: no frames to write")
    shape = frames[0].shape
    for k, f in enumerate(frames):
        if f.shape != shape or f.ndim != 3 or f.shape[2] != 3:
            raise ValueError(f"frames[{k}]: expected shape {shape} with 3 channels, got {f.shape}")
        if f.dtype != np.uint8:
            raise ValueError(f"frames[{k}]: expected dtype uint8, got {f.dtype}")
    with atomic_path(path, suffix=ext) as tmp:
        if ext == ".gif":
            imageio.mimsave(tmp, frames, format="GIF", duration=1000.0 / fps, loop=0)
        else:
            h, w = shape[0] + shape[0] % 2, shape[1] + shape[1] % 2
            writer = imageio.get_writer(tmp, format="FFMPEG", fps=fps, codec="libx264",
                                        macro_block_size=1, quality=7, pixelformat="yuv420p")
            try:
                for f in frames:
                    if f.shape[:2] != (h, w):
                        f = np.pad(f, ((0, h - f.shape[0]), (0, w - f.shape[1]), (0, 0)), mode="edge")
                    writer.append_data(f)
            finally:
                writer.close()
    return path


def record_episode(env: Any, path: str | os.PathLike | None = None,
                   policy: Callable[[Any], Any] | None = None, *, seed: int | None = None,
                   max_steps: int = 1000, fps: float = 10.0) -> list[np.ndarray]:
    """Run one episode of an env with ``render_mode="rgb_array"`` and keep its frames.

    ``env`` is a Gymnasium env (``cpsim/Drive-v0``) or a Stable-Baselines3 VecEnv such as
    :class:`cpsim.SelfPlayVecEnv` (its frame tiles its first ``render_worlds`` worlds; the
    episode is the simulator's ``episode_steps`` decisions, as its worlds reset on their own).
    ``policy(obs) -> action`` (default: random actions from the action space, seeded by
    ``seed``; for a VecEnv one action per env index). Writes the frames with
    :func:`write_video` when ``path`` is given.
    Returns the list of frames ((H, W, 3) uint8), the reset frame included.
    """
    if getattr(env, "render_mode", None) != "rgb_array":
        raise ValueError("env: record_episode needs an env made with render_mode='rgb_array'")
    from stable_baselines3.common.vec_env import VecEnv

    if isinstance(env, VecEnv):
        return _record_vec_episode(env, path, policy, seed=seed, max_steps=max_steps, fps=fps)
    obs, _ = env.reset(seed=seed)
    if policy is None:
        env.action_space.seed(seed)
        policy = lambda _obs: env.action_space.sample()  # noqa: E731
    frames = [env.render()]
    for _ in range(int(max_steps)):
        obs, _, terminated, truncated, _ = env.step(policy(obs))
        frames.append(env.render())
        if terminated or truncated:
            break
    if path is not None:
        write_video(frames, path, fps=fps)
    return frames


def _record_vec_episode(env: Any, path: str | os.PathLike | None, policy: Callable[[Any], Any] | None, *,
                        seed: int | None, max_steps: int, fps: float) -> list[np.ndarray]:
    """:func:`record_episode` for a VecEnv (4-tuple ``step``, ``seed`` before ``reset``)."""
    if seed is not None:
        env.seed(seed)
    obs = env.reset()
    if policy is None:
        from gymnasium import spaces

        if not isinstance(env.action_space, spaces.Discrete):
            raise ValueError(f"policy: needed for a VecEnv whose action space is not Discrete ({env.action_space})")
        rng = np.random.default_rng(seed)
        policy = lambda _obs: rng.integers(0, int(env.action_space.n), env.num_envs)  # noqa: E731
    sim = getattr(env, "sim", None)
    steps = min(int(max_steps), int(sim.config.episode_steps)) if sim is not None else int(max_steps)
    frames = [env.render()]
    for _ in range(steps):
        obs, _, dones, _ = env.step(policy(obs))
        frames.append(env.render())
        if sim is None and bool(np.all(dones)):
            break
    if path is not None:
        write_video(frames, path, fps=fps)
    return frames


__all__ = [
    "TopDownRenderer", "render_frame", "plot_roads", "plot_scenario", "write_video", "record_episode",
    "agent_colors", "CAMERAS", "GOAL_MODES", "VIDEO_FORMATS",
]
