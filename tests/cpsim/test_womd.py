"""WOMD JSON loading, the .npz cache and folder loading (cpsim.scenario.womd)."""

from __future__ import annotations

import dataclasses
import gzip
import json
import os
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

import cpsim
from cpsim.scenario import AgentType, RoadType, Scenario, ScenarioError, womd
from cpsim.scenario.womd import (
    CACHE_FORMAT_VERSION,
    LoadReport,
    ScenarioLoadWarning,
    convert_dir,
    load,
    load_cache,
    load_dir,
    save_cache,
)

T = 91


def _womd_dir() -> Path:
    env = os.environ.get("CPSIM_WOMD_DIR")
    return Path(env) if env else Path(__file__).resolve().parents[2].parent / "shared/data/womd"


WOMD_DIR = _womd_dir()
FILE_4 = WOMD_DIR / "tfrecord-00000-of-01000_4.json"
FILE_407 = WOMD_DIR / "tfrecord-00002-of-01000_407.json"
needs_womd = pytest.mark.skipif(
    not (FILE_4.is_file() and FILE_407.is_file()),
    reason=f"real WOMD files not found in {WOMD_DIR} (set CPSIM_WOMD_DIR)",
)
# The 140 gzip-compressed scenes of the shared data folder (40 train, 100 valid).
WOMD_TRAIN, WOMD_VALID = WOMD_DIR / "train", WOMD_DIR / "valid"
needs_womd_gz = pytest.mark.skipif(
    not (WOMD_TRAIN.is_dir() and WOMD_VALID.is_dir()),
    reason=f"real WOMD .json.gz folders train/ and valid/ not found in {WOMD_DIR} (set CPSIM_WOMD_DIR)",
)


# ----------------------------------------------------------------------------- helpers
def _pt(x: float, y: float, z: float = 0.0) -> dict[str, float]:
    return {"x": x, "y": y, "z": z}


def make_doc(scenario_id: str = "hand-json", n_objects: int = 6) -> dict[str, Any]:
    """A small valid scenario document in the GPUDrive / ScenarioMax schema."""
    kinds = ["vehicle", "vehicle", "pedestrian", "cyclist", "bus", "vehicle"]
    objects = []
    for i in range(n_objects):
        valid = [True] * T
        pos = [_pt(2.0 * t * 0.1 * (i + 1), 4.0 * i, 1.0) for t in range(T)]
        vel = [{"x": 2.0 * (i + 1), "y": 0.0} for _ in range(T)]
        head = [0.01 * i] * T
        if i == 5:  # appears late: WOMD fills invalid steps with -10000
            for t in range(40):
                valid[t] = False
                pos[t] = _pt(-10000.0, -10000.0, -10000.0)
                vel[t] = {"x": -10000.0, "y": -10000.0}
                head[t] = -10000.0
        objects.append({
            "position": pos, "velocity": vel, "heading": head, "valid": valid,
            "width": 2.0 + 0.1 * i, "length": 4.5 + 0.1 * i, "height": 1.5,
            "goalPosition": _pt(30.0 + i, 4.0 * i, 1.0),
            "type": kinds[i % len(kinds)], "id": 100 + i, "mark_as_expert": i % 2 == 1,
        })
    roads = [
        {"geometry": [_pt(0, -2), _pt(50, -2), _pt(100, -2)], "type": "lane", "map_element_id": 2, "id": 1},
        {"geometry": [_pt(0, -6), _pt(100, -6)], "type": "road_edge", "map_element_id": 15, "id": 2},
        {"geometry": [_pt(40, 3)], "type": "stop_sign", "map_element_id": 17, "id": 3},
        {"geometry": [_pt(0, 0), _pt(1, 0)], "type": "road_line", "map_element_id": 6, "id": 4},
        {"geometry": [_pt(5, 5), _pt(6, 5), _pt(6, 6), _pt(5, 6)], "type": "crosswalk", "map_element_id": 18, "id": 5},
        {"geometry": [_pt(7, 7), _pt(8, 8)], "type": "speed_bump", "map_element_id": 19, "id": 6},
        {"geometry": [_pt(9, 9), _pt(9, 12)], "type": "driveway", "map_element_id": 20, "id": 7},
        {"geometry": [_pt(1, 1), _pt(2, 2)], "type": "unknown", "map_element_id": 0, "id": 8},
    ]
    return {
        "name": f"{scenario_id}.json", "scenario_id": scenario_id, "objects": objects, "roads": roads,
        "tl_states": {},
        "metadata": {"sdc_track_index": 1, "objects_of_interest": [],
                     "tracks_to_predict": [{"track_index": 0, "difficulty": 0}, {"track_index": 3, "difficulty": 1}]},
    }


def write_doc(path: Path, doc: Any) -> Path:
    """Write ``doc`` as JSON; gzip-compressed when the name ends in ``.gz``."""
    text = json.dumps(doc)  # json.dumps writes NaN / Infinity tokens as Python's json does
    if path.name.endswith(".gz"):
        path.write_bytes(gzip.compress(text.encode()))
    else:
        path.write_text(text)
    return path


# ----------------------------------------------------------------------------- hand-made JSON
def test_small_json_loads_every_field(tmp_path: Path) -> None:
    path = write_doc(tmp_path / "small.json", make_doc())
    s = load(path)
    assert s.id == "hand-json" and s.family == "womd" and s.source == str(path)
    assert s.num_agents == 6 and s.ego_index == 1
    assert s.agent_types.tolist() == [AgentType.VEHICLE, AgentType.VEHICLE, AgentType.PEDESTRIAN,
                                      AgentType.CYCLIST, AgentType.OTHER, AgentType.VEHICLE]
    assert s.road_types.tolist() == [RoadType.LANE, RoadType.ROAD_EDGE, RoadType.STOP_SIGN, RoadType.ROAD_LINE,
                                     RoadType.CROSSWALK, RoadType.SPEED_BUMP, RoadType.DRIVEWAY, RoadType.OTHER]
    assert np.diff(s.road_offsets).tolist() == [3, 2, 1, 2, 4, 2, 2, 2]
    np.testing.assert_array_equal(s.road(2), [[40, 3]])  # single-point stop sign kept
    np.testing.assert_array_equal(s.road(0), [[0, -2], [50, -2], [100, -2]])
    assert s.agent_ids.tolist() == [100, 101, 102, 103, 104, 105]
    assert s.mark_as_expert.tolist() == [False, True, False, True, False, True]
    assert s.tracks_to_predict.tolist() == [0, 3]
    assert s.log_valid[5, :40].sum() == 0 and s.log_valid[5, 40:].all()
    # Invalid steps keep WOMD's sentinel; valid steps hold the data, in float32.
    assert s.log_xy[5, 0, 0] == -10000.0 and s.log_heading[5, 0] == -10000.0
    assert s.log_xy[2, 10, 0] == np.float32(2.0 * 10 * 0.1 * 3) and s.log_xy[2, 10, 1] == 8.0
    np.testing.assert_allclose(s.log_velocity[3, 0], [8.0, 0.0])
    np.testing.assert_allclose(s.sizes[4], [4.9, 2.4], rtol=1e-6)  # (length, width)
    np.testing.assert_allclose(s.goal_xy[2], [32.0, 8.0])
    assert s.log_xy.dtype == np.float32 and s.road_offsets.dtype == np.int32


def test_name_is_the_id_when_scenario_id_is_absent_and_optional_fields_default(tmp_path: Path) -> None:
    doc = make_doc()
    del doc["scenario_id"]
    for obj in doc["objects"]:
        del obj["id"], obj["mark_as_expert"]
    del doc["metadata"]["tracks_to_predict"]
    s = load(write_doc(tmp_path / "a.json", doc))
    assert s.id == "hand-json.json"
    assert s.agent_ids.tolist() == list(range(6)) and not s.mark_as_expert.any()
    assert s.tracks_to_predict.shape == (0,)


def test_nan_at_invalid_steps_is_allowed(tmp_path: Path) -> None:
    doc = make_doc()
    doc["objects"][5]["heading"][3] = float("nan")
    doc["objects"][5]["position"][4] = _pt(float("inf"), float("nan"))
    s = load(write_doc(tmp_path / "nan_ok.json", doc))
    assert np.isnan(s.log_heading[5, 3]) and not s.log_valid[5, 3]


def test_round_trip_json_cache_exact(tmp_path: Path) -> None:
    src = write_doc(tmp_path / "rt.json", make_doc())
    s = load(src)
    cache = save_cache(s, tmp_path / "rt.npz", origin=src)
    back = load(cache)
    assert back == s and back.source == s.source and back.family == "womd"
    assert load(save_cache(s, tmp_path / "raw.npz", compress=False)) == s
    for name, arr in s.arrays().items():
        assert getattr(back, name).dtype == arr.dtype, name
    # A field that differs breaks equality (the round-trip assertion is not vacuous).
    moved = np.array(s.goal_xy)
    moved[0, 0] += 1e-3
    assert dataclasses.replace(s, goal_xy=moved) != back
    assert not [p for p in tmp_path.iterdir() if p.suffix == ".tmp"]


def test_cache_accepts_procedural_style_scenarios(tmp_path: Path) -> None:
    s = load(write_doc(tmp_path / "x.json", make_doc()))
    other = dataclasses.replace(s, family="four_way", source="procedural:four_way:3", id="p3")
    back = load_cache(save_cache(other, tmp_path / "p.npz"))
    assert back == other and back.source == "procedural:four_way:3"


# ----------------------------------------------------------------------------- bad JSON
Mutation = Callable[[dict], Any]


def _set(path: tuple, value: Any) -> Mutation:
    def f(doc: dict) -> None:
        target = doc
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value
    return f


def _delete(path: tuple) -> Mutation:
    def f(doc: dict) -> None:
        target = doc
        for key in path[:-1]:
            target = target[key]
        del target[path[-1]]
    return f


def _truncate_trajectory(i: int, key: str, n: int) -> Mutation:
    def f(doc: dict) -> None:
        traj = doc["objects"][i][key]
        doc["objects"][i][key] = traj[:n] if n <= len(traj) else traj + traj[: n - len(traj)]
    return f


def _all_invalid(doc: dict) -> None:
    for obj in doc["objects"]:
        obj["valid"] = [False] * T


BAD_DOCS: dict[str, tuple[Mutation, str]] = {
    "missing objects": (_delete(("objects",)), "'objects'"),
    "missing roads": (_delete(("roads",)), "'roads'"),
    "missing metadata": (_delete(("metadata",)), "'metadata'"),
    "missing scenario id": (lambda d: (d.pop("scenario_id"), d.pop("name")), "'scenario_id'"),
    "missing sdc index": (_delete(("metadata", "sdc_track_index")), "'metadata.sdc_track_index'"),
    "missing heading": (_delete(("objects", 3, "heading")), "'objects[3].heading'"),
    "missing position": (_delete(("objects", 0, "position")), "'objects[0].position'"),
    "missing velocity": (_delete(("objects", 4, "velocity")), "'objects[4].velocity'"),
    "missing valid": (_delete(("objects", 2, "valid")), "'objects[2].valid'"),
    "missing width": (_delete(("objects", 1, "width")), "'objects[1].width'"),
    "missing goal": (_delete(("objects", 1, "goalPosition")), "'objects[1].goalPosition'"),
    "missing goal y": (_delete(("objects", 1, "goalPosition", "y")), "'objects[1].goalPosition.y'"),
    "missing type": (_delete(("objects", 5, "type")), "'objects[5].type'"),
    "missing point x": (_delete(("objects", 2, "position", 7, "x")), "'objects[2].position[7].x'"),
    "missing road geometry": (_delete(("roads", 1, "geometry")), "'roads[1].geometry'"),
    "missing road type": (_delete(("roads", 4, "type")), "'roads[4].type'"),
    "missing road point y": (_delete(("roads", 0, "geometry", 1, "y")), "'roads[0].geometry[1].y'"),
    "short position": (_truncate_trajectory(1, "position", 90), "'objects[1].position'"),
    "long heading": (_truncate_trajectory(2, "heading", 92), "'objects[2].heading'"),
    "short valid": (_truncate_trajectory(0, "valid", 50), "'objects[0].valid'"),
    "short velocity": (_truncate_trajectory(3, "velocity", 10), "'objects[3].velocity'"),
    "nan heading": (_set(("objects", 1, "heading", 10), float("nan")), "'objects[1].heading[10]'"),
    "inf position": (_set(("objects", 2, "position", 3, "y"), float("inf")), "'objects[2].position[3]'"),
    "float32 overflow": (_set(("objects", 0, "position", 8, "x"), 1e300), "'objects[0].position[8]'"),
    "nan velocity": (_set(("objects", 5, "velocity", 60, "x"), float("nan")), "'objects[5].velocity[60]'"),
    "nan goal": (_set(("objects", 4, "goalPosition", "x"), float("nan")), "'objects[4].goalPosition.x'"),
    "nan road point": (_set(("roads", 3, "geometry", 1, "x"), float("-inf")), "'roads[3].geometry[1]'"),
    "string coordinate": (_set(("objects", 2, "position", 5, "x"), "abc"), "'objects[2].position[5].x'"),
    "null heading": (_set(("objects", 3, "heading", 0), None), "'objects[3].heading[0]'"),
    "string road point": (_set(("roads", 4, "geometry", 2, "y"), "1.0"), "'roads[4].geometry[2].y'"),
    "non-bool valid": (_set(("objects", 1, "valid", 4), "yes"), "'objects[1].valid[4]'"),
    "negative width": (_set(("objects", 0, "width"), -1.0), "'objects[0].width'"),
    "zero length": (_set(("objects", 3, "length"), 0.0), "'objects[3].length'"),
    "no roads": (_set(("roads",), []), "'roads'"),
    "empty road geometry": (_set(("roads", 2, "geometry"), []), "'roads[2].geometry'"),
    "no objects": (_set(("objects",), []), "'objects'"),
    "no valid agent": (_all_invalid, "'objects[*].valid'"),
    "sdc out of range": (_set(("metadata", "sdc_track_index"), 6), "'metadata.sdc_track_index'"),
    "sdc negative": (_set(("metadata", "sdc_track_index"), -1), "'metadata.sdc_track_index'"),
    "sdc not an int": (_set(("metadata", "sdc_track_index"), "1"), "'metadata.sdc_track_index'"),
    "bad track to predict": (_set(("metadata", "tracks_to_predict", 1, "track_index"), 17),
                             "'metadata.tracks_to_predict[1].track_index'"),
    "object not a dict": (_set(("objects", 2), [1, 2]), "'objects[2]'"),
    "position not a list": (_set(("objects", 2, "position"), 5), "'objects[2].position'"),
    "id not an int": (_set(("objects", 2, "id"), "car"), "'objects[2].id'"),
    "top level list": (lambda d: [d], "'<document>'"),
}


@pytest.mark.parametrize("case", sorted(BAD_DOCS))
def test_bad_document_raises_scenario_error_naming_file_and_field(tmp_path: Path, case: str) -> None:
    mutate, field = BAD_DOCS[case]
    doc = make_doc()
    replaced = mutate(doc)
    doc = replaced if isinstance(replaced, list) else doc
    path = write_doc(tmp_path / f"bad_{case.replace(' ', '_')}.json", doc)
    with pytest.raises(ScenarioError) as info:
        load(path)
    message = str(info.value)
    assert path.name in message and field in message, message
    assert isinstance(info.value, ValueError) and info.value.source == str(path)


@pytest.mark.parametrize("content, needle", [
    (b"this is not json", "not valid JSON"),
    (b"", "truncated"),
    (b"\xff\xfe\x00garbage", "not valid JSON"),
])
def test_not_json_raises(tmp_path: Path, content: bytes, needle: str) -> None:
    path = tmp_path / "garbage.json"
    path.write_bytes(content)
    with pytest.raises(ScenarioError, match=needle) as info:
        load(path)
    assert "garbage.json" in str(info.value) and "'<document>'" in str(info.value)


def test_truncated_json_raises(tmp_path: Path) -> None:
    text = json.dumps(make_doc())
    path = tmp_path / "cut.json"
    path.write_text(text[: len(text) // 2])
    with pytest.raises(ScenarioError, match="truncated") as info:
        load(path)
    assert "cut.json" in str(info.value)


def test_missing_file_and_unknown_suffix(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match="file not found"):
        load(tmp_path / "nope.json")
    with pytest.raises(ScenarioError, match="file not found"):
        load(tmp_path / "nope.npz")
    (tmp_path / "a.txt").write_text("{}")
    with pytest.raises(ScenarioError, match="unknown suffix"):
        load(tmp_path / "a.txt")


# ----------------------------------------------------------------------------- bad caches
def test_bad_caches_raise(tmp_path: Path) -> None:
    src = write_doc(tmp_path / "ok.json", make_doc())
    good = save_cache(load(src), tmp_path / "ok.npz", origin=src)
    payload = dict(np.load(good))

    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[:200])
    with pytest.raises(ScenarioError, match="truncated.npz.*not a readable"):
        load(truncated)

    meta = json.loads(str(payload["meta"]))
    old = tmp_path / "old.npz"
    np.savez(old, **{**payload, "meta": np.array(json.dumps({**meta, "format_version": CACHE_FORMAT_VERSION + 1}))})
    with pytest.raises(ScenarioError, match="old.npz: field 'format_version'"):
        load(old)

    missing = tmp_path / "missing.npz"
    np.savez(missing, **{k: v for k, v in payload.items() if k != "log_heading"})
    with pytest.raises(ScenarioError, match="missing.npz: field 'log_heading'"):
        load(missing)

    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, a=np.zeros(3))
    with pytest.raises(ScenarioError, match="foreign.npz: field 'meta'"):
        load(foreign)

    no_id = tmp_path / "no_id.npz"
    np.savez(no_id, **{**payload, "meta": np.array(json.dumps({k: v for k, v in meta.items() if k != "id"}))})
    with pytest.raises(ScenarioError, match="no_id.npz: field 'meta.id'"):
        load(no_id)

    corrupt = tmp_path / "corrupt.npz"
    bad = dict(payload)
    bad["sizes"] = -bad["sizes"]
    np.savez(corrupt, **bad)
    with pytest.raises(ScenarioError, match="field 'sizes'"):
        load(corrupt)


def test_failed_cache_write_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    s = load(write_doc(tmp_path / "w.json", make_doc()))
    target = tmp_path / "out" / "w.npz"

    def broken_savez(fh: Any, **arrays: Any) -> None:
        fh.write(b"PK partial")
        raise OSError("disk full")

    monkeypatch.setattr(womd.np, "savez", broken_savez)
    monkeypatch.setattr(womd.np, "savez_compressed", broken_savez)
    for compress in (True, False):
        with pytest.raises(OSError, match="disk full"):
            save_cache(s, target, compress=compress)
        assert list(target.parent.iterdir()) == []


# ----------------------------------------------------------------------------- folders
def _folder(tmp_path: Path) -> tuple[Path, dict[str, Scenario]]:
    """Folder with b.json, a.json (good), c.json (bad: no roads) and an unrelated notes.txt."""
    folder = tmp_path / "src"
    folder.mkdir()
    write_doc(folder / "b.json", make_doc("scen-b"))
    doc_a = make_doc("scen-a", n_objects=4)
    doc_a["metadata"]["tracks_to_predict"] = []
    write_doc(folder / "a.json", doc_a)
    bad = make_doc("scen-c")
    bad["roads"] = []
    write_doc(folder / "c.json", bad)
    (folder / "notes.txt").write_text("not a scenario")
    return folder, {"a": load(folder / "a.json"), "b": load(folder / "b.json")}


def test_load_dir_sorts_and_reports_skipped(tmp_path: Path) -> None:
    folder, expected = _folder(tmp_path)
    with pytest.warns(ScenarioLoadWarning, match="c.json"):
        scenarios, report = load_dir(folder)
    assert [s.id for s in scenarios] == ["scen-a", "scen-b"]
    assert scenarios == [expected["a"], expected["b"]]
    assert report.loaded == [str(folder / "a.json"), str(folder / "b.json")]
    assert len(report.skipped) == 1
    path, reason = report.skipped[0]
    assert path == str(folder / "c.json") and "'roads'" in reason
    assert not report.ok and "c.json" in report.summary() and report.written == []


def test_load_dir_with_cache_dir_converts_once_and_detects_stale(tmp_path: Path) -> None:
    folder, expected = _folder(tmp_path)
    cache = tmp_path / "cache"
    with pytest.warns(ScenarioLoadWarning):
        first, rep1 = load_dir(folder, cache_dir=cache)
    assert sorted(Path(p).name for p in rep1.written) == ["a.npz", "b.npz"]
    with pytest.warns(ScenarioLoadWarning):
        second, rep2 = load_dir(folder, cache_dir=cache)
    assert rep2.written == [] and rep2.loaded == [str(cache / "a.npz"), str(cache / "b.npz")]
    assert second == first == [expected["a"], expected["b"]]
    assert second[0].source == str(folder / "a.json")  # the cache keeps the original source
    # Edit a.json: its cache is stale and gets rebuilt from the new content.
    doc = make_doc("scen-a2", n_objects=5)
    write_doc(folder / "a.json", doc)
    with pytest.warns(ScenarioLoadWarning):
        third, rep3 = load_dir(folder, cache_dir=cache)
    assert rep3.written == [str(cache / "a.npz")]
    assert third[0].id == "scen-a2" and third[0].num_agents == 5
    assert load(cache / "a.npz") == third[0]


def test_load_dir_reports_stale_and_unreadable_npz_next_to_json(tmp_path: Path) -> None:
    folder, expected = _folder(tmp_path)
    (folder / "c.json").unlink()
    # A stale cache of b (made from different content) and a garbage a.npz.
    other = tmp_path / "other.json"
    write_doc(other, make_doc("scen-old"))
    save_cache(load(other), folder / "b.npz", origin=other)
    (folder / "a.npz").write_bytes(b"garbage")
    with pytest.warns(ScenarioLoadWarning):
        scenarios, report = load_dir(folder)
    assert [s.id for s in scenarios] == ["scen-a", "scen-b"]
    reasons = dict(report.skipped)
    assert "unreadable cache" in reasons[str(folder / "a.npz")]
    assert "stale cache" in reasons[str(folder / "b.npz")]
    # A fresh cache next to its JSON is preferred over the JSON.
    save_cache(expected["b"], folder / "b.npz", origin=folder / "b.json")
    with pytest.warns(ScenarioLoadWarning):
        _, report = load_dir(folder)
    assert str(folder / "b.npz") in report.loaded


def test_load_dir_skips_duplicate_ids_and_loads_bare_npz(tmp_path: Path) -> None:
    folder = tmp_path / "f"
    folder.mkdir()
    write_doc(folder / "x.json", make_doc("same"))
    write_doc(folder / "y.json", make_doc("same"))
    save_cache(load(write_doc(tmp_path / "z.json", make_doc("zed"))), folder / "z.npz")
    with pytest.warns(ScenarioLoadWarning, match="duplicate scenario id"):
        scenarios, report = load_dir(folder)
    assert [s.id for s in scenarios] == ["same", "zed"]
    assert report.skipped[0][0] == str(folder / "y.json")
    assert report.loaded == [str(folder / "x.json"), str(folder / "z.npz")]


def test_load_dir_errors(tmp_path: Path, capsys) -> None:
    with pytest.raises(ScenarioError, match="folder does not exist"):
        load_dir(tmp_path / "missing")
    from cpsim.scenario.womd import main

    with pytest.raises(SystemExit) as exit_info:  # the command: one error line, exit status 2
        main(["convert", str(tmp_path / "missing"), str(tmp_path / "out")])
    assert exit_info.value.code == 2 and "src: no such folder" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.md").write_text("x")
    with pytest.raises(ScenarioError, match=r"no .json, .json.gz or .npz files"):
        load_dir(empty)
    allbad = tmp_path / "allbad"
    allbad.mkdir()
    (allbad / "one.json").write_text("{")
    with pytest.raises(ScenarioError, match="one.json"):
        load_dir(allbad)


def test_convert_dir_writes_caches_once_and_reports(tmp_path: Path) -> None:
    folder, expected = _folder(tmp_path)
    dst = tmp_path / "dst"
    with pytest.warns(ScenarioLoadWarning, match="c.json"):
        report = convert_dir(folder, dst)
    assert isinstance(report, LoadReport)
    assert sorted(p.name for p in dst.iterdir()) == ["a.npz", "b.npz"]  # no temp files left
    assert [Path(p).name for p in report.skipped[0][:1]] == ["c.json"]
    assert len(report.written) == 2 and len(report.loaded) == 2
    with pytest.warns(ScenarioLoadWarning):
        again = convert_dir(folder, dst)
    assert again.written == [] and len(again.loaded) == 2
    with pytest.warns(ScenarioLoadWarning):
        forced = convert_dir(folder, dst, overwrite=True)
    assert len(forced.written) == 2
    scenarios, rep = load_dir(dst)  # a folder of caches alone
    assert rep.ok and scenarios == [expected["a"], expected["b"]]
    with pytest.raises(ScenarioError, match="src_dir"):
        convert_dir(tmp_path / "missing", dst)
    with pytest.raises(ScenarioError, match=r"no .json or .json.gz files"):
        convert_dir(dst, tmp_path / "dst2")


def test_public_names_are_exported() -> None:
    assert cpsim.scenario.load is load and cpsim.scenario.load_dir is load_dir
    assert cpsim.scenario.convert_dir is convert_dir and cpsim.scenario.LoadReport is LoadReport


# ----------------------------------------------------------------------------- real files
@needs_womd
def test_real_file_4_counts() -> None:
    s = load(FILE_4)
    assert s.id == "db4edc9bd0c9d18c" and s.family == "womd" and s.source == str(FILE_4)
    assert s.num_agents == 81 and s.ego_index == 80
    counts = np.bincount(s.agent_types, minlength=4)
    assert counts.tolist() == [68, 12, 1, 0]  # vehicles, pedestrians, cyclists, other
    assert s.num_roads == 102
    roads = np.bincount(s.road_types, minlength=len(RoadType))
    assert roads[RoadType.LANE] == 37 and roads[RoadType.ROAD_EDGE] == 18
    assert roads[RoadType.DRIVEWAY] == 30 and roads[RoadType.ROAD_LINE] == 7
    assert roads[RoadType.CROSSWALK] == 5 and roads[RoadType.STOP_SIGN] == 5
    assert np.all(np.diff(s.road_offsets)[s.road_types == RoadType.STOP_SIGN] == 1)
    assert int(s.log_valid[:, 0].sum()) == 52 and int(s.mark_as_expert.sum()) == 41
    assert int((s.log_valid[:, 0] & (s.agent_types == AgentType.VEHICLE)).sum()) == 47
    assert s.tracks_to_predict.tolist() == [16, 79, 68, 71, 47, 40, 36]
    assert s.log_valid[80].all()
    assert np.all(s.log_xy[~s.log_valid] == -10000.0)


@needs_womd
def test_real_file_407_counts() -> None:
    s = load(FILE_407)
    assert s.id == "bada21415c031740" and s.num_agents == 15 and s.ego_index == 14
    assert np.bincount(s.agent_types, minlength=4).tolist() == [15, 0, 0, 0]
    assert s.num_roads == 177 and s.road_points.shape == (11155, 2)
    roads = np.bincount(s.road_types, minlength=len(RoadType))
    assert roads[RoadType.LANE] == 76 and roads[RoadType.ROAD_EDGE] == 28
    assert roads[RoadType.ROAD_LINE] == 17 and roads[RoadType.DRIVEWAY] == 47
    assert roads[RoadType.STOP_SIGN] == 6 and roads[RoadType.CROSSWALK] == 2 and roads[RoadType.SPEED_BUMP] == 1
    assert int(s.log_valid[:, 0].sum()) == 8 and int(s.mark_as_expert.sum()) == 0
    assert s.agent_ids[:3].tolist() == [1728, 1729, 1733]
    assert s.tracks_to_predict.tolist() == [1, 5]


@needs_womd
def test_real_files_round_trip_through_convert_dir(tmp_path: Path) -> None:
    report = convert_dir(WOMD_DIR, tmp_path)
    assert report.ok and len(report.written) == 2
    cached, rep = load_dir(WOMD_DIR, cache_dir=tmp_path)
    assert rep.written == [] and all(p.endswith(".npz") for p in rep.loaded)
    assert cached == [load(FILE_4), load(FILE_407)]


def test_command_line_convert(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder, expected = _folder(tmp_path)
    with pytest.warns(ScenarioLoadWarning):
        code = womd.main(["convert", str(folder), str(tmp_path / "out")])
    assert code == 1  # c.json was skipped
    out = capsys.readouterr().out
    assert "1 skipped" in out and "c.json" in out
    assert load(tmp_path / "out" / "b.npz") == expected["b"]


def test_load_dir_with_cache_dir_equal_to_the_folder(tmp_path: Path) -> None:
    folder, expected = _folder(tmp_path)
    (folder / "c.json").unlink()
    (folder / "orphan.npz").write_bytes(b"not a zip")  # a bare, unreadable cache is reported
    with pytest.warns(ScenarioLoadWarning, match="orphan.npz"):
        first, rep1 = load_dir(folder, cache_dir=folder)
    assert [Path(p).name for p in rep1.written] == ["a.npz", "b.npz"]
    assert [Path(p).name for p, _ in rep1.skipped] == ["orphan.npz"]
    (folder / "orphan.npz").unlink()
    second, rep2 = load_dir(folder, cache_dir=folder)
    assert rep2.ok and rep2.written == [] and second == first == [expected["a"], expected["b"]]
    assert [Path(p).name for p in rep2.loaded] == ["a.npz", "b.npz"]


# ----------------------------------------------------------------------------- .json.gz
def test_json_gz_loads_exactly_like_json(tmp_path: Path) -> None:
    plain = load(write_doc(tmp_path / "s.json", make_doc()))
    gz_path = write_doc(tmp_path / "s.json.gz", make_doc())
    assert gz_path.read_bytes()[:2] == b"\x1f\x8b"
    for loader in (load, womd.load_json):
        s = loader(gz_path)
        assert s == plain and s.source == str(gz_path) and s.family == "womd"
    upper = write_doc(tmp_path / "UP.JSON.GZ", make_doc("up"))
    assert load(upper).id == "up"
    assert womd.is_json_file(gz_path) and womd.is_json_file(upper) and not womd.is_json_file(tmp_path / "x.gz")
    # compression is recognised by content: a gzip stream named .json loads too
    (tmp_path / "zipped.json").write_bytes(gz_path.read_bytes())
    assert load(tmp_path / "zipped.json") == plain


@pytest.mark.parametrize("damage, needle", [
    ("truncate", "truncated gzip data"),
    ("corrupt", "not valid gzip data"),
])
def test_bad_gzip_raises_scenario_error_naming_the_file(tmp_path: Path, damage: str, needle: str) -> None:
    data = gzip.compress(json.dumps(make_doc()).encode())
    if damage == "truncate":
        data = data[: len(data) // 2]
    else:  # keep the magic bytes, break the header's compression method
        data = data[:2] + b"\x00" + data[3:]
    path = tmp_path / f"{damage}.json.gz"
    path.write_bytes(data)
    with pytest.raises(ScenarioError, match=needle) as info:
        load(path)
    assert info.value.source == str(path) and info.value.field == "<document>"
    # a gzip stream holding bad JSON is a JSON error, still naming the .gz file
    bad = tmp_path / "bad_json.json.gz"
    bad.write_bytes(gzip.compress(b'{"objects": ['))
    with pytest.raises(ScenarioError, match="truncated JSON") as info:
        load(bad)
    assert "bad_json.json.gz" in str(info.value)


def _gz_folder(tmp_path: Path) -> tuple[Path, dict[str, Scenario]]:
    """Folder with a.json.gz, b.json (plain) and c.json.gz (bad: no roads)."""
    folder = tmp_path / "gz"
    folder.mkdir()
    write_doc(folder / "a.json.gz", make_doc("scen-a", n_objects=5))
    write_doc(folder / "b.json", make_doc("scen-b"))
    bad = make_doc("scen-c")
    bad["roads"] = []
    write_doc(folder / "c.json.gz", bad)
    return folder, {"a": load(folder / "a.json.gz"), "b": load(folder / "b.json")}


def test_load_dir_reads_json_gz_and_caches_it(tmp_path: Path) -> None:
    folder, expected = _gz_folder(tmp_path)
    with pytest.warns(ScenarioLoadWarning, match="c.json.gz"):
        scenarios, report = load_dir(folder)
    assert scenarios == [expected["a"], expected["b"]]
    assert report.loaded == [str(folder / "a.json.gz"), str(folder / "b.json")]
    assert [p for p, _ in report.skipped] == [str(folder / "c.json.gz")]
    # cache: <stem>.npz (not <stem>.json.npz), fresh against the .gz file
    cache = tmp_path / "cache"
    with pytest.warns(ScenarioLoadWarning):
        _, rep1 = load_dir(folder, cache_dir=cache)
    assert sorted(Path(p).name for p in rep1.written) == ["a.npz", "b.npz"]
    with pytest.warns(ScenarioLoadWarning):
        again, rep2 = load_dir(folder, cache_dir=cache)
    assert rep2.written == [] and rep2.loaded == [str(cache / "a.npz"), str(cache / "b.npz")]
    assert again == scenarios and again[0].source == str(folder / "a.json.gz")
    write_doc(folder / "a.json.gz", make_doc("scen-a2", n_objects=4))  # edited: stale cache rebuilt
    with pytest.warns(ScenarioLoadWarning):
        third, rep3 = load_dir(folder, cache_dir=cache)
    assert rep3.written == [str(cache / "a.npz")] and third[0].id == "scen-a2"
    assert womd.scenario_files(folder) == [folder / "a.json.gz", folder / "b.json", folder / "c.json.gz"]


def test_plain_json_wins_over_json_gz_of_the_same_stem(tmp_path: Path) -> None:
    folder = tmp_path / "both"
    folder.mkdir()
    write_doc(folder / "x.json", make_doc("plain"))
    write_doc(folder / "x.json.gz", make_doc("zipped"))
    with pytest.warns(ScenarioLoadWarning, match="x.json.gz"):
        scenarios, report = load_dir(folder)
    assert [s.id for s in scenarios] == ["plain"] and report.loaded == [str(folder / "x.json")]
    assert report.skipped == [(str(folder / "x.json.gz"), "x.json holds the same stem and is loaded instead")]


def test_convert_dir_and_command_line_read_json_gz(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder, expected = _gz_folder(tmp_path)
    with pytest.warns(ScenarioLoadWarning, match="c.json.gz"):
        report = convert_dir(folder, tmp_path / "dst")
    assert sorted(p.name for p in (tmp_path / "dst").iterdir()) == ["a.npz", "b.npz"]
    assert report.loaded == [str(folder / "a.json.gz"), str(folder / "b.json")]
    assert load(tmp_path / "dst" / "a.npz") == expected["a"]
    with pytest.warns(ScenarioLoadWarning):
        again = convert_dir(folder, tmp_path / "dst")
    assert again.written == []  # fresh against the .gz
    with pytest.warns(ScenarioLoadWarning):
        code = womd.main(["convert", str(folder), str(tmp_path / "cli")])
    assert code == 1 and "c.json.gz" in capsys.readouterr().out
    assert load(tmp_path / "cli" / "a.npz") == expected["a"]
    only_gz = tmp_path / "only_gz"
    only_gz.mkdir()
    write_doc(only_gz / "z.json.gz", make_doc("zed"))
    assert womd.main(["convert", str(only_gz), str(tmp_path / "cli2")]) == 0
    rows = womd.bench_load(only_gz, repeat=1)
    assert [r["file"] for r in rows] == ["z.json.gz"] and rows[0]["json_ms"] > 0


# ----------------------------------------------------------------------------- duplicate object ids
def test_duplicate_object_id_raises_naming_file_and_id(tmp_path: Path) -> None:
    doc = make_doc()
    doc["objects"][4]["id"] = 102  # objects[2] has id 102
    for name in ("dup.json", "dup.json.gz"):
        path = write_doc(tmp_path / name, doc)
        with pytest.raises(ScenarioError) as info:
            load(path)
        assert info.value.source == str(path) and info.value.field == "objects[4].id"
        assert str(info.value) == (f"{path}: field 'objects[4].id': duplicate object id 102 "
                                   "(objects[2] has the same id)")


def test_duplicate_with_a_default_id_says_so(tmp_path: Path) -> None:
    doc = make_doc()
    doc["objects"][0]["id"] = 3  # collides with objects[3], which has no id (default: its index)
    del doc["objects"][3]["id"]
    with pytest.raises(ScenarioError, match=r"duplicate object id 3 \(objects\[0\] has the same id; "
                                            r"objects\[3\] has no 'id'") as info:
        load(write_doc(tmp_path / "default.json", doc))
    assert "default.json" in str(info.value)


def test_load_dir_reports_a_duplicate_id_file_and_loads_the_rest(tmp_path: Path) -> None:
    folder = tmp_path / "dups"
    folder.mkdir()
    doc = make_doc("has-dups")
    doc["objects"][1]["id"] = doc["objects"][0]["id"]
    write_doc(folder / "a.json.gz", doc)
    write_doc(folder / "b.json", make_doc("fine"))
    with pytest.warns(ScenarioLoadWarning, match="duplicate object id 100"):
        scenarios, report = load_dir(folder)
    assert [s.id for s in scenarios] == ["fine"]
    assert report.skipped[0][0] == str(folder / "a.json.gz") and "objects[1].id" in report.skipped[0][1]


def test_cache_with_duplicate_ids_is_rejected(tmp_path: Path) -> None:
    s = load(write_doc(tmp_path / "ok.json", make_doc()))
    ids = np.array(s.agent_ids)
    ids[5] = ids[0]
    path = save_cache(dataclasses.replace(s, agent_ids=ids), tmp_path / "dup.npz")
    with pytest.raises(ScenarioError, match="dup.npz: field 'agent_ids': duplicate object id 100"):
        load(path)


# ----------------------------------------------------------------------------- envs on a WOMD folder
def _env_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "envs"
    folder.mkdir()
    write_doc(folder / "one.json.gz", make_doc("one"))
    write_doc(folder / "two.json", make_doc("two", n_objects=5))
    return folder


def _step_selfplay(folder: Path, **kwargs: Any) -> cpsim.SelfPlayVecEnv:
    env = cpsim.SelfPlayVecEnv(womd_dir=str(folder), num_worlds=2, max_agents=8, seed=0, **kwargs)
    obs = env.reset()
    assert obs.shape == (env.num_envs, env.observation_space.shape[0]) and env.active_mask().any()
    rng = np.random.default_rng(0)
    for _ in range(3):
        obs, reward, done, infos = env.step(rng.integers(0, env.action_space.n, env.num_envs))
        assert np.isfinite(obs).all() and np.isfinite(reward).all() and len(infos) == env.num_envs
    return env


def _step_drive(folder: Path, **kwargs: Any) -> tuple[Any, dict]:
    from cpsim.envs.drive import DriveEnv

    env = DriveEnv(womd_dir=str(folder), regime="replay", seed=0, **kwargs)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    for _ in range(3):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert np.isfinite(obs).all() and np.isfinite(reward)
    return env, info


def test_selfplay_and_drive_env_on_a_womd_folder(tmp_path: Path) -> None:
    folder = _env_folder(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ScenarioLoadWarning)  # nothing is skipped
        env = _step_selfplay(folder)
        assert [s.id for s in env.scenarios] == ["one", "two"]
        assert [s.id for s in _step_selfplay(folder, num_scenarios=1).scenarios] == ["one"]
        drive, info = _step_drive(folder)
    assert info["scenario_id"] in {"one", "two"} and info["step"] == 3
    assert [s.id for s in drive.core.scenarios] == ["one", "two"]
    with pytest.raises(ScenarioError, match="folder does not exist"):
        cpsim.SelfPlayVecEnv(womd_dir=str(tmp_path / "missing"))


@needs_womd_gz
def test_selfplay_and_drive_env_on_real_json_gz_scenes(tmp_path: Path) -> None:
    folder = tmp_path / "real"
    folder.mkdir()
    # the two smallest files (model build time grows with the road network); symlinks, so
    # the data stays in the shared folder
    for p in sorted(WOMD_TRAIN.glob("*.json.gz"), key=lambda q: (q.stat().st_size, q.name))[:2]:
        (folder / p.name).symlink_to(p)
    env = _step_selfplay(folder)
    assert len(env.scenarios) == 2 and all(s.family == "womd" for s in env.scenarios)
    _step_drive(folder, max_agents=16)


# ----------------------------------------------------------------------------- real .json.gz folders
@needs_womd_gz
def test_real_json_gz_folders_load_and_convert(tmp_path: Path) -> None:
    counts = {}
    for folder in (WOMD_TRAIN, WOMD_VALID):
        scenarios, report = load_dir(folder)
        assert report.ok and all(p.endswith(".json.gz") for p in report.loaded)
        assert len({s.id for s in scenarios}) == len(scenarios)
        assert all(len(set(s.agent_ids.tolist())) == s.num_agents for s in scenarios)
        assert all(s.tracks_to_predict.size > 0 for s in scenarios)
        counts[folder.name] = len(scenarios)
    assert counts == {"train": 40, "valid": 100}
    # the .npz cache of a .json.gz: same scenario, source kept, fresh on the second call
    first, rep = load_dir(WOMD_TRAIN, cache_dir=tmp_path)
    assert len(rep.written) == 40 and sorted(p.name for p in tmp_path.iterdir())[0].endswith(".npz")
    cached, rep2 = load_dir(WOMD_TRAIN, cache_dir=tmp_path)
    assert rep2.written == [] and cached == first and cached[0].source.endswith(".json.gz")
