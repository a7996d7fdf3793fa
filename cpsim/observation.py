"""Observation layout: named slices of the per-agent observation vector.

The observation of an agent is in its own frame (x forward, y left), normalised to about
[-1, 1], and laid out as ``[ego | condition | partners | road]``:

ego (:data:`EGO_FEATURES`, 17 values)
    0 signed speed / 20 m/s, 1 a_long / 5 m/s^2, 2 a_lat / 4 m/s^2, 3 steering / 0.55 rad,
    4 length / 10 m, 5 width / 5 m, 6-7 goal position (x, y) / 100 m clipped to [-1, 1],
    8-9 unit direction to the goal (0, 0 at the goal), 10 goal distance / 100 m clipped to 1,
    11 heading error to the nearest lane / pi (0 without lane), 12 signed lateral offset /
    lane_radius (left +, 0 without lane), 13 lane within lane_radius (0/1), 14 has collided
    (0/1), 15 has gone off-road (0/1), 16 fraction of the episode left (1 at reset).
condition (10 values)
    ``cpsim.conditions.normalize_condition`` of the agent's raw condition.
partners (K x :data:`PARTNER_FEATURES` = 10)
    the K nearest live agents within ``partner_radius``, nearest first, zero-padded:
    0-1 relative position / partner_radius, 2-3 cos / sin of the relative heading,
    4-5 relative velocity (partner - ego, ego frame) / 20 m/s, 6 length / 10 m,
    7 width / 5 m, 8 pedestrian or cyclist (0/1), 9 present (1).
road (M x :data:`ROAD_FEATURES` = 8)
    the agent's grid cell's candidate list: up to M road segments whose midpoints are
    nearest to the cell centre, within ``road_radius`` + half the cell diagonal of it
    (nearest first; see :mod:`cpsim.model`), zero-padded:
    0-1 midpoint / road_radius, 2-3 direction cos / sin in the ego frame,
    4 length / road_max_segment, 5 lane centreline (0/1), 6 road edge (0/1), 7 present (1).

Empty slots and removed agents observe all zeros; so do scenery agents (neither driven by
the policy nor controllable at reset: parked cars, pedestrians, agents without a task)
unless ``SimConfig.observe_all`` is set.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cpsim.conditions import NUM_CONDITION_FIELDS, normalize_condition

EGO_FEATURES = 17
PARTNER_FEATURES = 10
ROAD_FEATURES = 8
EGO_FEATURE_NAMES: tuple[str, ...] = (
    "speed", "accel", "lat_accel", "steer", "length", "width", "goal_x", "goal_y", "goal_dir_x",
    "goal_dir_y", "goal_distance", "lane_heading_error", "lane_offset", "has_lane", "collided",
    "offroad", "time_left",
)
PARTNER_FEATURE_NAMES: tuple[str, ...] = (
    "x", "y", "cos_heading", "sin_heading", "vx", "vy", "length", "width", "vulnerable", "present",
)
ROAD_FEATURE_NAMES: tuple[str, ...] = ("x", "y", "cos", "sin", "length", "lane", "edge", "present")
assert len(EGO_FEATURE_NAMES) == EGO_FEATURES
assert len(PARTNER_FEATURE_NAMES) == PARTNER_FEATURES
assert len(ROAD_FEATURE_NAMES) == ROAD_FEATURES


@dataclass(frozen=True)
class ObsLayout:
    """Slices of the observation vector for K partners and M road segments."""

    num_partners: int = 16
    num_road: int = 64
    ego_features: int = EGO_FEATURES
    partner_features: int = PARTNER_FEATURES
    road_features: int = ROAD_FEATURES
    condition_features: int = NUM_CONDITION_FIELDS

    @property
    def ego(self) -> slice:
        return slice(0, self.ego_features)

    @property
    def condition(self) -> slice:
        return slice(self.ego_features, self.ego_features + self.condition_features)

    @property
    def partners(self) -> slice:
        start = self.condition.stop
        return slice(start, start + self.num_partners * self.partner_features)

    @property
    def road(self) -> slice:
        start = self.partners.stop
        return slice(start, start + self.num_road * self.road_features)

    @property
    def size(self) -> int:
        return self.road.stop

    def ego_index(self, name: str) -> int:
        """Index of a named ego feature in the observation vector."""
        return self.ego.start + EGO_FEATURE_NAMES.index(name)

    def split(self, obs: Any) -> dict[str, Any]:
        """Views of obs (..., D): ego (..., E), condition (..., 10), partners (..., K, PF),
        road (..., M, RF) (NumPy or torch)."""
        lead = tuple(obs.shape[:-1])
        return {
            "ego": obs[..., self.ego],
            "condition": obs[..., self.condition],
            "partners": obs[..., self.partners].reshape(*lead, self.num_partners, self.partner_features),
            "road": obs[..., self.road].reshape(*lead, self.num_road, self.road_features),
        }

    def replace_condition(self, obs: Any, conditions_raw: Any) -> Any:
        """A copy of obs (..., D) whose condition slice holds ``conditions_raw`` (..., 10) raw,
        normalised like the simulator does; broadcasts over leading dims (NumPy or torch)."""
        if obs.shape[-1] != self.size:
            raise ValueError(f"obs: last dimension must be {self.size}, got {tuple(obs.shape)}")
        if hasattr(obs, "clone"):  # torch
            import torch

            cond = torch.as_tensor(conditions_raw, dtype=obs.dtype, device=obs.device)
            if cond.shape[-1] != self.condition_features:
                raise ValueError(f"conditions_raw: last dimension must be {self.condition_features}, "
                                 f"got {tuple(cond.shape)}")
            out = obs.clone()
            out[..., self.condition] = normalize_condition(cond).to(obs.dtype)
            return out
        obs = np.asarray(obs)
        cond = np.asarray(conditions_raw, dtype=np.float32)
        if cond.shape[-1] != self.condition_features:
            raise ValueError(f"conditions_raw: last dimension must be {self.condition_features}, "
                             f"got {cond.shape}")
        out = np.array(obs, copy=True)
        out[..., self.condition] = normalize_condition(cond).astype(out.dtype)
        return out


__all__ = ["ObsLayout", "EGO_FEATURES", "PARTNER_FEATURES", "ROAD_FEATURES", "EGO_FEATURE_NAMES",
           "PARTNER_FEATURE_NAMES", "ROAD_FEATURE_NAMES"]
