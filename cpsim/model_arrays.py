"""The device view of the static model: the :class:`ModelArrays` Warp struct.

:class:`cpsim.model.Model` fills it (and re-exports it); the kernels of :mod:`cpsim.kernels`
read it. It lives in its own module so the kernels do not import :mod:`cpsim.model`, which
imports the kernels to compute ``log_offroad``. Warp names the struct by its class name
(``ModelArrays``) and hashes its fields only, so the kernels' module hash does not depend on
which Python module defines it.
"""

from __future__ import annotations

import warp as wp


@wp.struct
class ModelArrays:
    """Device view of the static model (see :mod:`cpsim.model`). Shapes: S segments,
    C cells (all scenarios), G scenarios, L log rows (agents of the pool), T = 91."""

    seg_a: wp.array(dtype=wp.vec2f)        # (S,) start point, m
    seg_b: wp.array(dtype=wp.vec2f)        # (S,) end point, m
    seg_mid: wp.array(dtype=wp.vec2f)      # (S,) midpoint, m
    seg_dir: wp.array(dtype=wp.vec2f)      # (S,) unit direction a->b
    seg_len: wp.array(dtype=wp.float32)    # (S,) length, m
    seg_type: wp.array(dtype=wp.int32)     # (S,) RoadType
    seg_poly: wp.array(dtype=wp.int32)     # (S,) global polyline id (lane identity)
    grid_origin: wp.array(dtype=wp.vec2f)  # (G,) lower-left corner of the grid, m
    grid_dims: wp.array(dtype=wp.vec2i)    # (G,) cells along x and y
    grid_cell: wp.array(dtype=wp.float32)  # (G,) cell side, m
    grid_first: wp.array(dtype=wp.int32)   # (G,) global index of the scenario's first cell
    obs_start: wp.array(dtype=wp.int32)    # (C+1,) CSR offsets into obs_items
    obs_items: wp.array(dtype=wp.int32)
    lane_start: wp.array(dtype=wp.int32)   # (C+1,)
    lane_items: wp.array(dtype=wp.int32)
    edge_start: wp.array(dtype=wp.int32)   # (C+1,)
    edge_items: wp.array(dtype=wp.int32)
    agent_first: wp.array(dtype=wp.int32)  # (G+1,) log rows of scenario g: agent_first[g] ...
    agent_scenario: wp.array(dtype=wp.int32)  # (L,) scenario of each log row
    slot_count: wp.array(dtype=wp.int32)   # (G,) agents given a slot at reset (slots 0.. hold them)
    log_xy: wp.array2d(dtype=wp.vec2f)     # (L, T) m
    log_heading: wp.array2d(dtype=wp.float32)  # (L, T) rad
    log_vel: wp.array2d(dtype=wp.vec2f)    # (L, T) m/s
    log_valid: wp.array2d(dtype=wp.bool)   # (L, T)
    log_offroad: wp.array2d(dtype=wp.bool)  # (L, T) off-road test of the logged move t-1 -> t (vehicles)
    size: wp.array(dtype=wp.vec2f)         # (L,) logged (length, width), m
    agent_type: wp.array(dtype=wp.int32)   # (L,) AgentType
    goal: wp.array(dtype=wp.vec2f)         # (L,) m
    idm_v0: wp.array(dtype=wp.float32)     # (L,) IDM desired speed, m/s
    path_xy: wp.array2d(dtype=wp.vec2f)    # (L, T) valid logged points, compressed to the front
    path_s: wp.array2d(dtype=wp.float32)   # (L, T) cumulative arc length, m
    path_h: wp.array2d(dtype=wp.float32)   # (L, T) logged heading at the path point, rad
    path_n: wp.array(dtype=wp.int32)       # (L,) number of path points


__all__ = ["ModelArrays"]
