"""Tests for cpsim.render: rasteriser, matplotlib figure, video writing."""

from __future__ import annotations

import os

import numpy as np
import pytest

from cpsim.render import (
    COLLIDED_COLOR,
    EGO_COLOR,
    OFFROAD_COLOR,
    TopDownRenderer,
    plot_scenario,
    record_episode,
    render_frame,
    write_video,
)
from cpsim.scenario.datatypes import NUM_STEPS, RoadType, Scenario


def cross_scenario() -> Scenario:
    """A small 4-way crossing (80 m arms, one lane each way), 3 vehicles; the ego drives east."""
    roads, types = [], []
    xs = np.linspace(-40, 40, 17)
    for y, d in ((-1.9, 1), (1.9, -1)):
        roads.append(np.stack([xs[::d], np.full_like(xs, y)], 1))
        types.append(RoadType.LANE)
        roads.append(np.stack([np.full_like(xs, -y), xs[::-d]], 1))
        types.append(RoadType.LANE)
    for s in (-3.8, 3.8):
        for a, b in ((-40, -3.8), (3.8, 40)):
            seg = np.array([[a, s], [b, s]])
            roads += [seg, seg[:, ::-1].copy()]
            types += [RoadType.ROAD_EDGE, RoadType.ROAD_EDGE]
    roads.append(np.array([[-40, 0.0], [-6, 0]]))
    types.append(RoadType.ROAD_LINE)
    roads.append(np.array([[-5.5, -3.8], [-4.5, -3.8], [-4.5, 3.8], [-5.5, 3.8]]))
    types.append(RoadType.CROSSWALK)
    pts = np.concatenate(roads).astype(np.float32)
    offs = np.concatenate([[0], np.cumsum([len(r) for r in roads])]).astype(np.int32)
    t = np.arange(NUM_STEPS) * 0.1
    xy = np.zeros((3, NUM_STEPS, 2), np.float32)
    hd = np.zeros((3, NUM_STEPS), np.float32)
    vel = np.zeros((3, NUM_STEPS, 2), np.float32)
    xy[0, :, 0], xy[0, :, 1], vel[0, :, 0] = -30 + 8 * t, -1.9, 8
    xy[1, :, 0], xy[1, :, 1], hd[1], vel[1, :, 1] = 1.9, 30 - 6 * t, -np.pi / 2, -6
    xy[2, :, 0], xy[2, :, 1], hd[2] = 20.0, 1.9, np.pi
    return Scenario(id="cross", log_xy=xy, log_heading=hd, log_velocity=vel,
                    log_valid=np.ones((3, NUM_STEPS), bool), goal_xy=xy[:, -1],
                    sizes=np.array([[4.5, 2.0]] * 3, np.float32), agent_types=np.zeros(3, np.int8),
                    road_points=pts, road_offsets=offs, road_types=np.array(types, np.int8),
                    ego_index=0)


@pytest.fixture(scope="module")
def scen() -> Scenario:
    return cross_scenario()


def _count(img: np.ndarray, color: np.ndarray) -> int:
    return int(np.all(img == color, axis=-1).sum())


@pytest.mark.parametrize("camera", ["ego", "scene"])
def test_frame_shape_not_blank_and_changes(scen, camera):
    r = TopDownRenderer(width=160, height=120, camera=camera)
    f0, f1 = r.render_log(scen, 0), r.render_log(scen, 30)
    assert f0.shape == (120, 160, 3) and f0.dtype == np.uint8
    assert len(np.unique(f0.reshape(-1, 3), axis=0)) > 5  # roads, agents, background
    assert _count(f0, EGO_COLOR) > 10  # the ego box is visible
    assert not np.array_equal(f0, f1)


def test_ego_camera_follows_ego(scen):
    r = TopDownRenderer(width=200, height=200, camera="ego", view_m=40.0)
    for t in (0, 40):
        f = r.render_log(scen, t)
        rows, cols = np.nonzero(np.all(f == EGO_COLOR, axis=-1))
        # ego box centred in the image (to a pixel or two; the front quarter is darker)
        assert abs(rows.mean() - 100) < 3 and abs(cols.mean() - 100) < 6


def test_box_orientation_and_size(scen):
    """A 4.5 x 2 m box heading north at 0.25 m/px spans about 18 px rows x 8 px cols."""
    r = TopDownRenderer(width=200, height=200, camera="ego", view_m=50.0, goals="none")
    f = r.render(scen, np.array([[0.0, 20.0]]), np.array([np.pi / 2]), np.array([[4.5, 2.0]]),
                 controllers=np.array([0]), ego=0)
    box = np.all(f == EGO_COLOR, axis=-1) | np.all(f == (EGO_COLOR * 0.7).astype(np.uint8), axis=-1) \
        | np.all(f == (EGO_COLOR * 0.45).astype(np.uint8), axis=-1)
    rows, cols = np.nonzero(box)
    assert 15 <= rows.max() - rows.min() + 1 <= 20
    assert 6 <= cols.max() - cols.min() + 1 <= 10
    # the darker front quarter is at the top (north)
    front = np.all(f == (EGO_COLOR * 0.7).astype(np.uint8), axis=-1)
    assert np.nonzero(front)[0].mean() < rows.mean()


def test_state_colours(scen):
    xy = np.array([[-10.0, -1.9], [0.0, -1.9], [10.0, -1.9]])
    f = render_frame(scen, xy, np.zeros(3), np.full((3, 2), [4.5, 2.0]), width=200, height=200,
                     camera="scene", controllers=np.array([0, 0, 1]), outcome=np.array([0, 2, 3]),
                     alive=np.array([True, False, False]), ego=0)
    assert _count(f, COLLIDED_COLOR) > 5 and _count(f, OFFROAD_COLOR) > 5
    # an absent slot is not drawn
    g = render_frame(scen, xy, np.zeros(3), np.full((3, 2), [4.5, 2.0]), width=200, height=200,
                     camera="scene", controllers=np.array([0, 0, 1]), outcome=np.array([0, 2, 3]),
                     alive=np.array([True, False, False]), present=np.array([True, False, True]), ego=0)
    assert _count(g, COLLIDED_COLOR) == 0 and _count(g, OFFROAD_COLOR) > 5


def test_bad_arguments(scen):
    with pytest.raises(ValueError, match="camera"):
        TopDownRenderer(camera="drone")
    with pytest.raises(ValueError, match="goals"):
        TopDownRenderer(goals="some")
    with pytest.raises(ValueError, match="ego"):
        TopDownRenderer().render(scen, np.zeros((2, 2)), np.zeros(2), np.ones((2, 2)), ego=5)
    with pytest.raises(ValueError, match="t"):
        TopDownRenderer().render_log(scen, 91)


def test_plot_scenario_draws(scen, tmp_path):
    ax = plot_scenario(scen, t=10)
    assert len(ax.patches) >= 3 + 1  # three agent boxes + the crosswalk (+ goals)
    out = tmp_path / "scene.png"
    ax.figure.savefig(out)
    assert out.stat().st_size > 1000


@pytest.mark.parametrize("ext", [".gif", ".mp4"])
def test_write_video_roundtrip(scen, tmp_path, ext):
    import imageio.v2 as imageio

    if ext == ".mp4":
        pytest.importorskip("imageio_ffmpeg")
    r = TopDownRenderer(width=97, height=65, camera="ego")
    frames = [r.render_log(scen, t) for t in range(0, 30, 3)]
    path = write_video(frames, tmp_path / f"ep{ext}", fps=5)
    back = imageio.mimread(path, memtest=False)
    assert len(back) == len(frames)
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp_video_")]


def test_write_video_bad_input(tmp_path):
    with pytest.raises(ValueError, match="extension"):
        write_video([np.zeros((8, 8, 3), np.uint8)], tmp_path / "a.avi")
    with pytest.raises(ValueError, match="no frames"):
        write_video([], tmp_path / "a.gif")
    with pytest.raises(ValueError, match=r"frames\[1\]"):
        write_video([np.zeros((8, 8, 3), np.uint8), np.zeros((9, 8, 3), np.uint8)], tmp_path / "a.gif")
    assert not (tmp_path / "a.gif").exists()


def test_record_episode_records_a_selfplay_vec_env(tmp_path):
    import cpsim

    env = cpsim.SelfPlayVecEnv(num_worlds=1, max_agents=2, num_scenarios=1, render_mode="rgb_array",
                               episode_steps=3)
    frames = record_episode(env, tmp_path / "e.gif", seed=0)
    assert len(frames) == 4 and frames[0].ndim == 3 and frames[0].dtype == np.uint8  # reset + 3 decisions
    assert (tmp_path / "e.gif").stat().st_size > 0


def test_record_episode_needs_rgb_array():
    class _Env:
        render_mode = None

    with pytest.raises(ValueError, match="rgb_array"):
        record_episode(_Env())
