"""The scenario model: plain NumPy data describing one driving task.

A :class:`Scenario` holds the logged (expert) trajectories of every agent, their
goals, sizes and types, and the road network as polylines. It is validated on
construction, so every consumer (simulator, renderer, metrics) can rely on shapes,
dtypes and finiteness.

Conventions (WOMD / GPUDrive):

* ``T = 91`` logged steps at ``dt = 0.1 s`` (:data:`NUM_STEPS`).
* Positions in metres, headings in radians, velocities in m/s, world frame.
* Invalid steps have ``log_valid == False``; their coordinates are meaningless
  (WOMD stores -10000 there) and must not be read.
"""

from __future__ import annotations

import dataclasses
from enum import IntEnum
from typing import Any

import numpy as np

NUM_STEPS = 91
DT = 0.1
#: Minimum start-to-goal distance (m) for an agent to be a controllable task agent.
MIN_GOAL_DISTANCE = 2.0


class ScenarioError(ValueError):
    """A scenario (file, folder or in-memory data) is malformed.

    The message names the source (file path or scenario id) and the offending field.
    """

    def __init__(self, source: str, field: str, reason: str):
        self.source = source
        self.field = field
        self.reason = reason
        super().__init__(f"{source}: field '{field}': {reason}")


class AgentType(IntEnum):
    VEHICLE = 0
    PEDESTRIAN = 1
    CYCLIST = 2
    OTHER = 3


class RoadType(IntEnum):
    LANE = 0
    ROAD_LINE = 1
    ROAD_EDGE = 2
    CROSSWALK = 3
    STOP_SIGN = 4
    SPEED_BUMP = 5
    DRIVEWAY = 6
    OTHER = 7


AGENT_TYPE_NAMES = {t.name.lower(): t for t in AgentType}
ROAD_TYPE_NAMES = {t.name.lower(): t for t in RoadType}


def _arr(source: str, name: str, value: Any, dtype: Any, shape: tuple) -> np.ndarray:
    """Convert ``value`` to a C-contiguous array of ``dtype`` and check its shape.

    ``shape`` entries of ``None`` match any size.
    """
    try:
        a = np.ascontiguousarray(np.asarray(value), dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ScenarioError(source, name, f"cannot convert to {np.dtype(dtype).name}: {exc}") from None
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ScenarioError(source, name, f"expected shape {want}, got {a.shape}")
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class Scenario:
    """One driving scenario. All arrays are NumPy, validated in ``__post_init__``.

    Attributes (N agents, T = 91 steps, P road points, R road polylines):
        id: unique scenario id (str).
        log_xy: (N, T, 2) float32, logged centre positions, m.
        log_heading: (N, T) float32, logged headings, rad.
        log_velocity: (N, T, 2) float32, logged world-frame velocities, m/s.
        log_valid: (N, T) bool, whether the logged step exists.
        goal_xy: (N, 2) float32, goal positions, m.
        sizes: (N, 2) float32, box (length, width), m, > 0.
        agent_types: (N,) int8, :class:`AgentType` values.
        road_points: (P, 2) float32, concatenated polyline vertices, m.
        road_offsets: (R + 1,) int32, polyline r is ``road_points[road_offsets[r]:road_offsets[r+1]]``.
        road_types: (R,) int8, :class:`RoadType` values.
        ego_index: index of the task's designated ego (WOMD: ``sdc_track_index``).
        mark_as_expert: (N,) bool, WOMD's flag (agents that should be log-replayed);
            all False for procedural scenarios.
        agent_ids: (N,) int64, original object ids.
        tracks_to_predict: (K,) int32, indices of WOMD's tracks to predict (may be empty).
        source: where the scenario came from (file path, or ``procedural:<family>:<seed>``).
        family: procedural family name, or ``"womd"``.
    """

    id: str
    log_xy: np.ndarray
    log_heading: np.ndarray
    log_velocity: np.ndarray
    log_valid: np.ndarray
    goal_xy: np.ndarray
    sizes: np.ndarray
    agent_types: np.ndarray
    road_points: np.ndarray
    road_offsets: np.ndarray
    road_types: np.ndarray
    ego_index: int
    mark_as_expert: np.ndarray | None = None
    agent_ids: np.ndarray | None = None
    tracks_to_predict: np.ndarray | None = None
    source: str = ""
    family: str = "unknown"

    # ------------------------------------------------------------------ validation
    def __post_init__(self) -> None:
        src = self.source or str(self.id)
        if not isinstance(self.id, str) or not self.id:
            raise ScenarioError(src, "id", "must be a non-empty string")
        xy = _arr(src, "log_xy", self.log_xy, np.float32, (None, None, 2))
        n, t = xy.shape[0], xy.shape[1]
        if n == 0:
            raise ScenarioError(src, "objects", "scenario has no agents")
        if t != NUM_STEPS:
            raise ScenarioError(src, "log_xy", f"trajectory length {t}, expected {NUM_STEPS}")
        fields = {
            "log_xy": xy,
            "log_heading": _arr(src, "log_heading", self.log_heading, np.float32, (n, t)),
            "log_velocity": _arr(src, "log_velocity", self.log_velocity, np.float32, (n, t, 2)),
            "log_valid": _arr(src, "log_valid", self.log_valid, bool, (n, t)),
            "goal_xy": _arr(src, "goal_xy", self.goal_xy, np.float32, (n, 2)),
            "sizes": _arr(src, "sizes", self.sizes, np.float32, (n, 2)),
            "agent_types": _arr(src, "agent_types", self.agent_types, np.int8, (n,)),
            "road_points": _arr(src, "road_points", self.road_points, np.float32, (None, 2)),
            "road_offsets": _arr(src, "road_offsets", self.road_offsets, np.int32, (None,)),
        }
        r = fields["road_offsets"].shape[0] - 1
        fields["road_types"] = _arr(src, "road_types", self.road_types, np.int8, (max(r, 0),))
        fields["mark_as_expert"] = (
            np.zeros(n, bool) if self.mark_as_expert is None
            else _arr(src, "mark_as_expert", self.mark_as_expert, bool, (n,))
        )
        fields["agent_ids"] = (
            np.arange(n, dtype=np.int64) if self.agent_ids is None
            else _arr(src, "agent_ids", self.agent_ids, np.int64, (n,))
        )
        fields["tracks_to_predict"] = (
            np.zeros(0, np.int32) if self.tracks_to_predict is None
            else _arr(src, "tracks_to_predict", self.tracks_to_predict, np.int32, (None,))
        )
        valid = fields["log_valid"]
        for name in ("log_xy", "log_heading", "log_velocity"):
            vals = fields[name][valid]
            if not np.all(np.isfinite(vals)):
                raise ScenarioError(src, name, "NaN or infinite value at a valid step")
        for name in ("goal_xy", "sizes", "road_points"):
            if not np.all(np.isfinite(fields[name])):
                raise ScenarioError(src, name, "NaN or infinite value")
        if np.any(fields["sizes"] <= 0):
            bad = int(np.argwhere(np.any(fields["sizes"] <= 0, axis=1))[0, 0])
            raise ScenarioError(src, "sizes", f"agent {bad} has a non-positive length or width")
        if r < 1 or fields["road_points"].shape[0] == 0:
            raise ScenarioError(src, "roads", "scenario has no roads")
        offs = fields["road_offsets"]
        if offs[0] != 0 or offs[-1] != fields["road_points"].shape[0] or np.any(np.diff(offs) < 1):
            raise ScenarioError(src, "road_offsets", "must start at 0, end at len(road_points) and increase")
        if np.any((fields["road_types"] < 0) | (fields["road_types"] > max(RoadType))):
            raise ScenarioError(src, "road_types", "unknown road type code")
        if np.any((fields["agent_types"] < 0) | (fields["agent_types"] > max(AgentType))):
            raise ScenarioError(src, "agent_types", "unknown agent type code")
        if not np.any(valid):
            raise ScenarioError(src, "valid", "no agent has a valid step")
        ego = int(self.ego_index)
        if not 0 <= ego < n:
            raise ScenarioError(src, "ego_index", f"{ego} is outside [0, {n})")
        if np.any((fields["tracks_to_predict"] < 0) | (fields["tracks_to_predict"] >= n)):
            raise ScenarioError(src, "tracks_to_predict", "index outside the agent range")
        for name, value in fields.items():
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "ego_index", ego)
        object.__setattr__(self, "source", self.source or f"memory:{self.id}")

    # ------------------------------------------------------------------ derived
    @property
    def num_agents(self) -> int:
        return int(self.log_xy.shape[0])

    @property
    def num_roads(self) -> int:
        return int(self.road_types.shape[0])

    @property
    def num_steps(self) -> int:
        return int(self.log_xy.shape[1])

    @property
    def log_speed(self) -> np.ndarray:
        """(N, T) float32 logged speed, m/s (norm of ``log_velocity``)."""
        return np.linalg.norm(self.log_velocity, axis=-1).astype(np.float32)

    def road(self, r: int) -> np.ndarray:
        """(n_r, 2) vertices of polyline ``r``."""
        return self.road_points[self.road_offsets[r]:self.road_offsets[r + 1]]

    @property
    def goal_distance(self) -> np.ndarray:
        """(N,) float32 distance from the t0 position to the goal, m (inf where invalid at t0)."""
        d = np.linalg.norm(self.goal_xy - self.log_xy[:, 0], axis=-1)
        return np.where(self.log_valid[:, 0], d, np.inf).astype(np.float32)

    @property
    def controllable(self) -> np.ndarray:
        """(N,) bool: vehicle, valid at t0 and goal at least :data:`MIN_GOAL_DISTANCE` away."""
        return (
            (self.agent_types == AgentType.VEHICLE)
            & self.log_valid[:, 0]
            & (self.goal_distance >= MIN_GOAL_DISTANCE)
        )

    def arrays(self) -> dict[str, np.ndarray]:
        """All array fields by name (used by the cache writer and equality)."""
        return {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), np.ndarray)
        }

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Scenario):
            return NotImplemented
        if (self.id, self.ego_index, self.family) != (other.id, other.ego_index, other.family):
            return False
        a, b = self.arrays(), other.arrays()
        return a.keys() == b.keys() and all(
            a[k].dtype == b[k].dtype and a[k].shape == b[k].shape
            and np.array_equal(a[k], b[k], equal_nan=True) for k in a
        )

    __hash__ = object.__hash__

    def summary(self) -> dict[str, Any]:
        """Small human-readable description (counts), used by the CLI and logs."""
        return {
            "id": self.id,
            "family": self.family,
            "agents": self.num_agents,
            "controllable": int(self.controllable.sum()),
            "vehicles": int((self.agent_types == AgentType.VEHICLE).sum()),
            "roads": self.num_roads,
            "road_points": int(self.road_points.shape[0]),
            "ego_goal_distance_m": float(self.goal_distance[self.ego_index]),
        }


def validate_scenarios(scenarios: Any, argument: str = "scenarios", *, needs: str | None = None,
                       single: bool = True) -> list[Scenario]:
    """``scenarios`` as a new list, every item checked to be a :class:`Scenario`.

    The one check of every API that takes a list of scenarios (the simulator's pool, the
    self-play env, the splits). With ``single`` one Scenario stands for a list of one.
    ``needs`` names what cannot work without a scenario ("a pool", "a split"): an empty
    list then raises; ``None`` lets it through.

    Raises:
        ValueError: ``"<argument>: empty; <needs> needs at least one scenario"``, or
            ``"<argument>[i]: expected a Scenario (cpsim.Scenario), got <type>"``.
    """
    if single and isinstance(scenarios, Scenario):
        return [scenarios]
    out = list(scenarios)
    if not out and needs is not None:
        raise ValueError(f"{argument}: empty; {needs} needs at least one scenario")
    for i, s in enumerate(out):
        if not isinstance(s, Scenario):
            raise ValueError(f"{argument}[{i}]: expected a Scenario (cpsim.Scenario), got {type(s).__name__}")
    return out
