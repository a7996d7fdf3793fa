"""The model's lane / road-edge candidate lists (built near each segment) equal the lists of
the full cell x segment distance matrix."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cpsim.config import SimConfig
from cpsim.model import Model, near_segment_rows, rect_segment_distance, scenario_segments
from cpsim.scenario import pool
from cpsim.scenario.datatypes import RoadType

WOMD_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "womd"


def dense_rows(centres, cell, a, b, ids, radius):
    if ids.size == 0:
        return [np.zeros(0, np.int64) for _ in range(centres.shape[0])]
    d = rect_segment_distance(centres, 0.5 * cell, a[ids], b[ids]) <= radius
    return [ids[np.flatnonzero(row)] for row in d]


def scenes():
    out = list(pool(4, 0))
    if any(WOMD_DIR.glob("*.json")):
        from cpsim.scenario import load

        out += [load(p) for p in sorted(WOMD_DIR.glob("*.json"))]
    return out


@pytest.mark.parametrize("dynamics", ["jerk", "classic"])
def test_near_segment_rows_equal_dense_lists(dynamics):
    cfg = SimConfig(dynamics=dynamics)
    scs = scenes()
    model = Model(scs[:1], cfg)
    for sc in scs:
        a, b, t, _ = scenario_segments(sc, cfg.road_simplify_tol, cfg.road_max_segment)
        info = model._grid_info(sc, a, b)
        nx, ny = info.dims
        ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="xy")
        centres = info.origin + (np.stack([ix.ravel(), iy.ravel()], 1) + 0.5) * info.cell
        for kind, radius in ((RoadType.LANE, cfg.lane_radius), (RoadType.ROAD_EDGE, model.edge_margin)):
            ids = np.flatnonzero(t == kind)
            fast = near_segment_rows(centres, info.dims, info.cell, a, b, ids, radius)
            slow = dense_rows(centres, info.cell, a, b, ids, radius)
            assert len(fast) == len(slow) == centres.shape[0]
            assert all(np.array_equal(f, s) for f, s in zip(fast, slow)), (sc.id, kind)
            assert sum(f.size for f in fast) > 0


def test_observed_lists_are_the_nearest_midpoints_nearest_first():
    cfg = SimConfig(dynamics="classic")
    scs = scenes()
    model = Model(scs, cfg)
    h = model.host
    mids = h["seg_mid"].astype(np.float64)
    seg_first = np.concatenate([[0], np.cumsum([scenario_segments(sc, cfg.road_simplify_tol, cfg.road_max_segment)[0]
                                                .shape[0] for sc in scs])])
    checked = 0
    for g in range(len(scs)):
        first = int(h["grid_first"][g])
        nx, ny = (int(v) for v in h["grid_dims"][g])
        cell = float(h["grid_cell"][g])
        own = np.arange(seg_first[g], seg_first[g + 1])
        reach = cfg.road_radius + cell * np.sqrt(0.5)
        for c in np.random.default_rng(g).choice(nx * ny, size=min(40, nx * ny), replace=False):
            centre = h["grid_origin"][g].astype(np.float64) + (np.array([c % nx, c // nx]) + 0.5) * cell
            items = h["obs_items"][h["obs_start"][first + c]:h["obs_start"][first + c + 1]]
            d_all = np.sort(np.linalg.norm(mids[own] - centre, axis=1))
            expected = d_all[:cfg.num_road]
            expected = expected[expected <= reach]
            got = np.linalg.norm(mids[items] - centre, axis=1)
            assert np.all(np.isin(items, own))  # the scenario's own segments only
            np.testing.assert_allclose(got, expected, atol=1e-4)  # the nearest, nearest first
            checked += items.size
    assert checked > 0


def test_an_offered_host_build_is_adopted_once_by_its_pool_and_config():
    import pickle

    from cpsim.model import build_model_host, offer_model_host

    scs = list(pool(3, 1))
    cfg = SimConfig(dynamics="classic")
    prebuilt = pickle.loads(pickle.dumps(build_model_host(scs, cfg)))  # as a worker process returns it
    offer_model_host(prebuilt)
    other = Model(scs, SimConfig(dynamics="jerk"))  # another config: ignores the offer
    assert not other.prebuilt
    adopted = Model(list(scs), cfg)
    assert adopted.prebuilt
    built = Model(scs, cfg)  # used once: the next Model builds its own
    assert not built.prebuilt
    assert adopted.host.keys() == built.host.keys()
    assert all(np.array_equal(adopted.host[k], built.host[k]) for k in built.host)
    assert adopted.edge_margin == built.edge_margin and all(
        np.array_equal(a, b) for a, b in zip(adopted.slot_order, built.slot_order))
    with pytest.raises(ValueError, match="prebuilt: expected a ModelHost"):
        offer_model_host(built.host)
