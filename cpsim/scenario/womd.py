"""WOMD scenario JSON (GPUDrive / PufferDrive / ScenarioMax schema) and the ``.npz`` cache.

Public API:

* :func:`load` ``(path) -> Scenario``: a ``.json`` or ``.json.gz`` file or a ``.npz`` cache,
  by suffix.
* :func:`load_json`, :func:`load_cache`, :func:`save_cache`: the two formats explicitly
  (:func:`load_json` reads plain and gzip-compressed JSON alike).
* :func:`load_dir` ``(path, cache_dir=None) -> (list[Scenario], LoadReport)``: a folder of
  ``.json`` / ``.json.gz`` and/or ``.npz`` files, preferring a fresh cache over its JSON.
* :func:`convert_dir` ``(src_dir, dst_dir) -> LoadReport``: JSON folder -> one ``.npz`` per file.
* :func:`scenario_files` ``(folder)``: the scenario files of a folder that the above read.

A gzip-compressed file (``<stem>.json.gz``, as in GPUDrive / PufferDrive releases) is the
JSON file ``<stem>.json`` in every respect: same stem, same cache name ``<stem>.npz``, same
messages. When a folder holds both ``x.json`` and ``x.json.gz``, ``x.json`` is used and the
``.gz`` is reported as skipped.

JSON schema read here (fields not listed are ignored, e.g. ``tl_states``, ``height``, ``z``):

* top level: ``scenario_id`` (or ``name``; the scenario id), ``objects``, ``roads``,
  ``metadata`` with ``sdc_track_index`` (-> ``ego_index``) and optionally
  ``tracks_to_predict`` (list of ``{track_index, difficulty}`` or plain indices).
* object: ``position`` (91 x {x, y, z}), ``velocity`` (91 x {x, y}), ``heading`` (91),
  ``valid`` (91), ``width``, ``length``, ``goalPosition`` {x, y}, ``type``; optional
  ``id`` (default: the object's index) and ``mark_as_expert`` (default False).
  Unknown object types map to :attr:`AgentType.OTHER`. Object ids must be unique within a
  file: a repeated id raises :class:`ScenarioError` naming the file and the id (no silent
  de-duplication: which copy is right cannot be told).
* road: ``geometry`` (list of >= 1 {x, y, z}), ``type``; unknown road types (including
  ``"unknown"``) map to :attr:`RoadType.OTHER`. Single-point roads (stop signs) are kept
  as one-vertex polylines.

Values at invalid steps are kept as stored (WOMD writes -10000 there); only valid steps
are checked for finiteness. Every malformed input raises :class:`ScenarioError` naming the
file and the field (``objects[3].heading``, ``roads[7].geometry[2].x``, ...); nothing
half-built is ever returned and cache files are written atomically.

The cache (format :data:`CACHE_FORMAT_VERSION`) is a compressed ``.npz`` holding every
array of the :class:`Scenario` plus a ``meta`` JSON entry with ``id``, ``ego_index``,
``family``, ``source`` and the name, size and modification time of the JSON it was made
from (used to decide freshness). It loads 4-6x faster than the JSON (see BENCHMARKS.md).
"""

from __future__ import annotations

import dataclasses
import gzip
import json
import logging
import os
import tempfile
import warnings
import zipfile
import zlib
from operator import itemgetter
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from cpsim.atomic import atomic_path
from cpsim.scenario.datatypes import NUM_STEPS, AgentType, RoadType, Scenario, ScenarioError

try:  # optional: about 4x faster parsing; stdlib json is the fallback and handles NaN
    import orjson as _orjson
except ImportError:  # pragma: no cover - depends on the environment
    _orjson = None

__all__ = [
    "CACHE_FORMAT_VERSION",
    "CACHE_SUFFIX",
    "LoadReport",
    "ScenarioLoadWarning",
    "convert_dir",
    "is_json_file",
    "load",
    "load_cache",
    "load_dir",
    "load_json",
    "save_cache",
    "scenario_files",
]

logger = logging.getLogger(__name__)

#: Version of the ``.npz`` cache layout; caches of another version are rejected (and rebuilt
#: by :func:`load_dir` / :func:`convert_dir` when the JSON is at hand).
CACHE_FORMAT_VERSION = 1
CACHE_SUFFIX = ".npz"
JSON_SUFFIX = ".json"
#: gzip-compressed JSON (GPUDrive / PufferDrive releases); read like ``.json``.
GZ_JSON_SUFFIX = ".json.gz"
_GZIP_MAGIC = b"\x1f\x8b"
FAMILY = "womd"

_GET_X = itemgetter("x")
_GET_Y = itemgetter("y")

_OBJECT_TYPES: dict[str, AgentType] = {
    "vehicle": AgentType.VEHICLE,
    "pedestrian": AgentType.PEDESTRIAN,
    "cyclist": AgentType.CYCLIST,
}
_ROAD_TYPES: dict[str, RoadType] = {
    "lane": RoadType.LANE,
    "road_line": RoadType.ROAD_LINE,
    "road_edge": RoadType.ROAD_EDGE,
    "crosswalk": RoadType.CROSSWALK,
    "stop_sign": RoadType.STOP_SIGN,
    "speed_bump": RoadType.SPEED_BUMP,
    "driveway": RoadType.DRIVEWAY,
}

# Scenario fields stored as arrays in the cache (all of them, see Scenario.arrays()).
_ARRAY_FIELDS: tuple[str, ...] = tuple(
    f.name for f in dataclasses.fields(Scenario)
    if f.name not in ("id", "ego_index", "source", "family")
)
_META = "meta"  # cache entry holding the scalar fields as a JSON string


class ScenarioLoadWarning(UserWarning):
    """Issued when a folder load or conversion skipped files (the report says which and why)."""


@dataclasses.dataclass
class LoadReport:
    """What a folder load or conversion did.

    Attributes:
        loaded: paths (str) whose scenario was loaded or converted, in file-name order.
        skipped: ``(path, reason)`` for every file that was not used: malformed files,
            stale or unreadable caches superseded by their JSON, duplicate scenario ids.
        written: cache files written by this call.
    """

    loaded: list[str] = dataclasses.field(default_factory=list)
    skipped: list[tuple[str, str]] = dataclasses.field(default_factory=list)
    written: list[str] = dataclasses.field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when nothing was skipped."""
        return not self.skipped

    def summary(self) -> str:
        """Multi-line human-readable summary naming every skipped file and its reason."""
        lines = [f"{len(self.loaded)} loaded, {len(self.skipped)} skipped, {len(self.written)} cache(s) written"]
        lines += [f"  skipped {path}: {reason}" for path, reason in self.skipped]
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()

    def _warn_if_skipped(self, what: str) -> None:
        if self.skipped:
            message = f"{what}: {self.summary()}"
            logger.warning(message)
            warnings.warn(message, ScenarioLoadWarning, stacklevel=3)


# ---------------------------------------------------------------------------- JSON parsing
def _parse_json_bytes(data: bytes, source: str) -> Any:
    """Parse JSON bytes; raise ScenarioError(field '<document>') when not valid JSON."""
    if _orjson is not None:
        try:
            return _orjson.loads(data)
        except _orjson.JSONDecodeError:
            pass  # re-parse with the stdlib: it accepts NaN/Infinity and gives line/column
    try:
        return json.loads(data)
    except json.JSONDecodeError as exc:
        truncated = exc.pos >= len(data.rstrip())
        what = "truncated JSON (unexpected end of file)" if truncated else "not valid JSON"
        raise ScenarioError(source, "<document>", f"{what}: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    except (UnicodeDecodeError, RecursionError) as exc:
        raise ScenarioError(source, "<document>", f"not valid JSON: {exc}") from None


def _get(container: Any, key: str, where: str, source: str) -> Any:
    """``container[key]``; ScenarioError naming ``where.key`` when missing."""
    if not isinstance(container, dict):
        raise ScenarioError(source, where or "<document>", f"expected a JSON object, got {type(container).__name__}")
    try:
        return container[key]
    except KeyError:
        raise ScenarioError(source, f"{where}.{key}" if where else key, "missing") from None


def _list(value: Any, field: str, source: str, length: int | None = None) -> list:
    if not isinstance(value, list):
        raise ScenarioError(source, field, f"expected a list, got {type(value).__name__}")
    if length is not None and len(value) != length:
        raise ScenarioError(source, field, f"trajectory length {len(value)}, expected {length}")
    return value


def _extend_xy(points: list, xs: list, ys: list, field: str, source: str) -> None:
    """Append the x and y of a list of {x, y[, z]} objects; names the bad element on failure."""
    try:
        xs += map(_GET_X, points)
        ys += map(_GET_Y, points)
    except (KeyError, TypeError):
        for t, p in enumerate(points):
            if not isinstance(p, dict):
                raise ScenarioError(source, f"{field}[{t}]", f"expected an {{x, y}} object, got {type(p).__name__}") from None
            for key in ("x", "y"):
                if key not in p:
                    raise ScenarioError(source, f"{field}[{t}].{key}", "missing") from None
        raise  # pragma: no cover - unreachable: one of the checks above fires


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _numeric(values: list, field_of: Callable[[int], str], source: str) -> np.ndarray:
    """Convert a flat list of numbers to float64.

    A flat list without a dtype is the fast NumPy path (a list of tuples is 5x slower) and
    keeps strings and nulls detectable (``dtype=float`` would convert "1.5" and map None to
    NaN). ``field_of(i)`` names the field holding item ``i``; used on the error path only.
    """
    arr = np.array(values) if values else np.zeros(0)
    if arr.dtype.kind in "iuf":
        return arr.astype(np.float64, copy=False)
    i = next(k for k, v in enumerate(values) if not _is_number(v))  # slow path: locate it
    raise ScenarioError(source, field_of(i), f"expected a number, got {values[i]!r:.40}")


def _parse_objects(objects: list, source: str) -> dict[str, np.ndarray]:
    """Build the agent arrays from the ``objects`` list (N objects)."""
    n = len(objects)
    xs: list = []
    ys: list = []
    vxs: list = []
    vys: list = []
    heading: list = []
    valid: list = []
    scalars: list[tuple[Any, Any, Any, Any]] = []  # (length, width, goal x, goal y)
    types = np.empty(n, np.int8)
    ids = np.empty(n, np.int64)
    first_with_id: dict[int, int] = {}  # object id -> index of the first object carrying it
    expert = np.zeros(n, bool)
    # A loop over objects is fine here (load time, once per file); the per-step data goes
    # through map/itemgetter and one bulk NumPy conversion per field.
    for i, obj in enumerate(objects):
        where = f"objects[{i}]"
        pos = _list(_get(obj, "position", where, source), f"{where}.position", source, NUM_STEPS)
        vv = _list(_get(obj, "velocity", where, source), f"{where}.velocity", source, NUM_STEPS)
        hh = _list(_get(obj, "heading", where, source), f"{where}.heading", source, NUM_STEPS)
        va = _list(_get(obj, "valid", where, source), f"{where}.valid", source, NUM_STEPS)
        length = _get(obj, "length", where, source)
        width = _get(obj, "width", where, source)
        goal = _get(obj, "goalPosition", where, source)
        kind = _get(obj, "type", where, source)
        for name, v in (("length", length), ("width", width)):
            if not _is_number(v):
                raise ScenarioError(source, f"{where}.{name}", f"expected a number, got {v!r:.40}")
            if not v > 0:  # also rejects NaN
                raise ScenarioError(source, f"{where}.{name}", f"must be a positive size in m, got {v}")
        if not isinstance(goal, dict):
            raise ScenarioError(source, f"{where}.goalPosition", "expected an {x, y} object")
        gx, gy = (_get(goal, k, f"{where}.goalPosition", source) for k in ("x", "y"))
        for k, g in (("x", gx), ("y", gy)):
            if not _is_number(g) or not np.isfinite(g):
                raise ScenarioError(source, f"{where}.goalPosition.{k}", f"expected a finite number, got {g!r:.40}")
        if not isinstance(kind, str):
            raise ScenarioError(source, f"{where}.type", f"expected a string, got {type(kind).__name__}")
        types[i] = _OBJECT_TYPES.get(kind.lower(), AgentType.OTHER)
        oid = obj.get("id", i)
        if not isinstance(oid, int) or isinstance(oid, bool):
            raise ScenarioError(source, f"{where}.id", f"expected an integer, got {oid!r:.40}")
        if oid in first_with_id:
            j = first_with_id[oid]
            defaulted = [f"objects[{k}]" for k in (j, i) if "id" not in objects[k]]
            note = f"; {' and '.join(defaulted)} has no 'id', whose default is the object's index" if defaulted else ""
            raise ScenarioError(source, f"{where}.id",
                                f"duplicate object id {oid} (objects[{j}] has the same id{note})")
        first_with_id[oid] = i
        ids[i] = oid
        flag = obj.get("mark_as_expert", False)
        if not isinstance(flag, bool):
            raise ScenarioError(source, f"{where}.mark_as_expert", f"expected true/false, got {flag!r:.40}")
        expert[i] = flag
        _extend_xy(pos, xs, ys, f"{where}.position", source)
        _extend_xy(vv, vxs, vys, f"{where}.velocity", source)
        heading += hh
        valid += va
        scalars.append((length, width, gx, gy))

    def obj_field(name: str, suffix: str = "") -> Callable[[int], str]:
        return lambda i: f"objects[{i // NUM_STEPS}].{name}[{i % NUM_STEPS}]{suffix}"

    def xy_array(x: list, y: list, name: str) -> np.ndarray:
        cols = [_numeric(x, obj_field(name, ".x"), source), _numeric(y, obj_field(name, ".y"), source)]
        return np.stack(cols, axis=-1).astype(np.float32).reshape(n, NUM_STEPS, 2)

    valid_arr = np.array(valid)
    if valid_arr.dtype != bool:
        bad = next(k for k, v in enumerate(valid) if not isinstance(v, bool))
        raise ScenarioError(source, f"objects[{bad // NUM_STEPS}].valid[{bad % NUM_STEPS}]",
                            f"expected true/false, got {valid[bad]!r:.40}")
    valid_arr = valid_arr.reshape(n, NUM_STEPS)
    with np.errstate(over="ignore", invalid="ignore"):  # -1e39 etc. become inf, checked below
        xy_arr = xy_array(xs, ys, "position")
        vel_arr = xy_array(vxs, vys, "velocity")
        head_arr = _numeric(heading, obj_field("heading"), source).astype(np.float32).reshape(n, NUM_STEPS)
        sc = np.array(scalars, np.float64)
        sc32 = sc.astype(np.float32)
    if not np.all(np.isfinite(sc32)):
        i, j = np.argwhere(~np.isfinite(sc32))[0]
        name = ("length", "width", "goalPosition.x", "goalPosition.y")[j]
        raise ScenarioError(source, f"objects[{i}].{name}", f"value {sc[i, j]:g} does not fit float32")
    for name, arr in (("position", xy_arr), ("velocity", vel_arr), ("heading", head_arr)):
        finite = np.isfinite(arr) if arr.ndim == 2 else np.isfinite(arr).all(axis=-1)
        bad = valid_arr & ~finite
        if np.any(bad):
            i, t = np.argwhere(bad)[0]
            raise ScenarioError(source, f"objects[{i}].{name}[{t}]", "NaN or infinite value at a valid step")
    if not np.any(valid_arr):
        raise ScenarioError(source, "objects[*].valid", "no object has a valid step")
    return {
        "log_xy": xy_arr,
        "log_velocity": vel_arr,
        "log_heading": head_arr,
        "log_valid": valid_arr,
        "sizes": sc32[:, :2].copy(),
        "goal_xy": sc32[:, 2:].copy(),
        "agent_types": types,
        "agent_ids": ids,
        "mark_as_expert": expert,
    }


def _parse_roads(roads: list, source: str) -> dict[str, np.ndarray]:
    """Build ``road_points``, ``road_offsets`` and ``road_types`` from the ``roads`` list."""
    xs: list = []
    ys: list = []
    offsets = np.empty(len(roads) + 1, np.int64)
    offsets[0] = 0
    types = np.empty(len(roads), np.int8)
    for r, road in enumerate(roads):
        where = f"roads[{r}]"
        geom = _list(_get(road, "geometry", where, source), f"{where}.geometry", source)
        if not geom:
            raise ScenarioError(source, f"{where}.geometry", "empty polyline (needs at least one point)")
        kind = _get(road, "type", where, source)
        if not isinstance(kind, str):
            raise ScenarioError(source, f"{where}.type", f"expected a string, got {type(kind).__name__}")
        types[r] = _ROAD_TYPES.get(kind.lower(), RoadType.OTHER)
        _extend_xy(geom, xs, ys, f"{where}.geometry", source)
        offsets[r + 1] = len(xs)

    def point_field(suffix: str) -> Callable[[int], str]:
        def field(i: int) -> str:
            r = int(np.searchsorted(offsets, i, side="right") - 1)
            return f"roads[{r}].geometry[{i - offsets[r]}]{suffix}"
        return field

    arr = np.stack([_numeric(xs, point_field(".x"), source), _numeric(ys, point_field(".y"), source)], axis=-1)
    with np.errstate(over="ignore", invalid="ignore"):
        pts = arr.astype(np.float32).reshape(-1, 2)
    bad = ~np.isfinite(pts).all(axis=1)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ScenarioError(source, point_field("")(i), "NaN or infinite value")
    if offsets[-1] > np.iinfo(np.int32).max:
        raise ScenarioError(source, "roads", "too many road points for int32 offsets")
    return {"road_points": pts, "road_offsets": offsets.astype(np.int32), "road_types": types}


def _parse_document(doc: Any, source: str) -> Scenario:
    if not isinstance(doc, dict):
        raise ScenarioError(source, "<document>", f"expected a JSON object at the top level, got {type(doc).__name__}")
    sid = doc.get("scenario_id", doc.get("name"))
    if sid is None:
        raise ScenarioError(source, "scenario_id", "missing (and no 'name' either)")
    if not isinstance(sid, (str, int)) or isinstance(sid, bool) or str(sid) == "":
        raise ScenarioError(source, "scenario_id", f"expected a non-empty string, got {sid!r:.40}")
    objects = _get(doc, "objects", "", source)
    if not isinstance(objects, list):
        raise ScenarioError(source, "objects", f"expected a list, got {type(objects).__name__}")
    if not objects:
        raise ScenarioError(source, "objects", "no objects (agents)")
    roads = _get(doc, "roads", "", source)
    if not isinstance(roads, list):
        raise ScenarioError(source, "roads", f"expected a list, got {type(roads).__name__}")
    if not roads:
        raise ScenarioError(source, "roads", "no roads")
    meta = _get(doc, "metadata", "", source)
    sdc = _get(meta, "sdc_track_index", "metadata", source)
    n = len(objects)
    if not isinstance(sdc, int) or isinstance(sdc, bool) or not 0 <= sdc < n:
        raise ScenarioError(source, "metadata.sdc_track_index", f"{sdc!r:.40} is not an object index in [0, {n})")
    ttp_raw = meta.get("tracks_to_predict", [])
    if not isinstance(ttp_raw, list):
        raise ScenarioError(source, "metadata.tracks_to_predict", f"expected a list, got {type(ttp_raw).__name__}")
    ttp = np.empty(len(ttp_raw), np.int32)
    for k, entry in enumerate(ttp_raw):
        field = f"metadata.tracks_to_predict[{k}]"
        if isinstance(entry, dict):
            entry = _get(entry, "track_index", field, source)
            field += ".track_index"
        if not isinstance(entry, int) or isinstance(entry, bool) or not 0 <= entry < n:
            raise ScenarioError(source, field, f"{entry!r:.40} is not an object index in [0, {n})")
        ttp[k] = entry
    agents = _parse_objects(objects, source)
    road = _parse_roads(roads, source)
    return Scenario(
        id=str(sid),
        ego_index=sdc,
        tracks_to_predict=ttp,
        source=source,
        family=FAMILY,
        **agents,
        **road,
    )


def _decompress(data: bytes, source: str) -> bytes:
    """Gunzip ``data`` when it starts with the gzip magic bytes; plain bytes pass through."""
    if not data.startswith(_GZIP_MAGIC):
        return data
    try:
        return gzip.decompress(data)
    except EOFError:
        raise ScenarioError(source, "<document>", "truncated gzip data (unexpected end of file)") from None
    except (OSError, zlib.error) as exc:  # gzip.BadGzipFile is an OSError
        raise ScenarioError(source, "<document>", f"not valid gzip data: {exc}") from None


def load_json(path: str | os.PathLike) -> Scenario:
    """Read one WOMD scenario JSON file (plain or gzip-compressed) into a validated :class:`Scenario`.

    Compression is recognised by content (the gzip magic bytes), whatever the name:
    ``x.json.gz`` and ``x.json`` load the same way. ``source`` is ``str(path)``, ``family``
    is ``"womd"``, ``id`` is ``scenario_id`` (else ``name``). Raises :class:`ScenarioError`
    naming the file and the field.
    """
    source = str(path)
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise ScenarioError(source, "path", "file not found") from None
    except OSError as exc:
        raise ScenarioError(source, "path", f"cannot read: {exc}") from None
    return _parse_document(_parse_json_bytes(_decompress(data, source), source), source)


# ---------------------------------------------------------------------------- .npz cache
def _origin_stat(path: Path) -> tuple[int, int]:
    st = path.stat()
    return int(st.st_size), int(st.st_mtime_ns)


def save_cache(
    scenario: Scenario,
    path: str | os.PathLike,
    origin: str | os.PathLike | None = None,
    compress: bool = True,
) -> Path:
    """Write ``scenario`` to a ``.npz`` cache at ``path``, atomically.

    One entry per array field of the :class:`Scenario` plus one ``meta`` entry (a JSON
    string: ``format_version``, ``id``, ``ego_index``, ``family``, ``source`` and
    ``origin``). ``origin`` is the JSON the scenario came from; its name, size and
    modification time are stored so that :func:`load_dir` / :func:`convert_dir` can tell
    whether the cache is fresh. ``compress`` uses ``savez_compressed`` (the default: 1.5-3x
    smaller for a load about 10-30% slower, see BENCHMARKS.md). The file is written to a
    temporary name in the same folder and moved into place with ``os.replace``, so readers
    never see a partial cache. Returns the path.
    """
    dst = Path(path)
    if dst.suffix != CACHE_SUFFIX:
        raise ValueError(f"path: cache files must end in {CACHE_SUFFIX}, got {dst.name!r}")
    meta: dict[str, Any] = {
        "format_version": CACHE_FORMAT_VERSION,
        "id": scenario.id,
        "ego_index": int(scenario.ego_index),
        "family": scenario.family,
        "source": scenario.source,
        "origin": None,
    }
    if origin is not None:
        size, mtime_ns = _origin_stat(Path(origin))
        meta["origin"] = {"name": Path(origin).name, "size": size, "mtime_ns": mtime_ns}
    payload: dict[str, np.ndarray] = {name: np.asarray(getattr(scenario, name)) for name in _ARRAY_FIELDS}
    # Scalars travel in one JSON entry: every .npz entry costs a header parse on load.
    payload[_META] = np.array(json.dumps(meta))
    writer = np.savez_compressed if compress else np.savez
    with atomic_path(dst) as tmp, open(tmp, "wb") as fh:
        writer(fh, **payload)
    return dst


def _read_cache(path: Path) -> tuple[Scenario, dict[str, Any]]:
    """Load a cache file; returns the scenario and its origin metadata (empty if none)."""
    source = str(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except FileNotFoundError:
        raise ScenarioError(source, "path", "file not found") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise ScenarioError(source, "<document>", f"not a readable .npz cache: {exc}") from None
    if _META not in data:
        raise ScenarioError(source, _META, "missing: not a cpsim scenario cache")
    raw = data[_META]
    try:
        meta = json.loads(str(raw)) if raw.shape == () and raw.dtype.kind == "U" else None
    except json.JSONDecodeError:
        meta = None
    if not isinstance(meta, dict):
        raise ScenarioError(source, _META, "not a JSON object")
    if meta.get("format_version") != CACHE_FORMAT_VERSION:
        raise ScenarioError(source, "format_version",
                            f"cache format {meta.get('format_version')!r} is not {CACHE_FORMAT_VERSION}")
    for name, kind in (("id", str), ("family", str), ("source", str), ("ego_index", int)):
        if not isinstance(meta.get(name), kind) or isinstance(meta.get(name), bool):
            raise ScenarioError(source, f"{_META}.{name}", f"missing or not a {kind.__name__}")
    for name in _ARRAY_FIELDS:
        if name not in data:
            raise ScenarioError(source, name, "missing from the cache")
        if data[name].dtype.kind not in "biuf":
            raise ScenarioError(source, name, f"unexpected dtype {data[name].dtype}")
    ids = data["agent_ids"]
    if ids.ndim == 1 and ids.size > 1:  # caches written before ids were checked on load
        uniq, counts = np.unique(ids, return_counts=True)
        if np.any(counts > 1):
            raise ScenarioError(source, "agent_ids", f"duplicate object id {int(uniq[np.argmax(counts > 1)])}")
    scenario = Scenario(
        id=meta["id"],
        ego_index=meta["ego_index"],
        family=meta["family"],
        # The cache is a transparent copy: keep the original source (the JSON path) so that
        # messages and reports about the scenario point at where it came from.
        source=meta["source"] or source,
        **{name: data[name] for name in _ARRAY_FIELDS},
    )
    origin = meta.get("origin")
    valid_origin = (isinstance(origin, dict) and isinstance(origin.get("size"), int)
                    and isinstance(origin.get("mtime_ns"), int) and isinstance(origin.get("name"), str))
    return scenario, (origin if valid_origin else {})


def load_cache(path: str | os.PathLike) -> Scenario:
    """Load a ``.npz`` cache written by :func:`save_cache`. ``source`` is the original source."""
    return _read_cache(Path(path))[0]


def is_json_file(path: str | os.PathLike) -> bool:
    """Whether ``path``'s name ends in ``.json`` or ``.json.gz`` (case-insensitive)."""
    name = Path(path).name.lower()
    return name.endswith(JSON_SUFFIX) or name.endswith(GZ_JSON_SUFFIX)


def _stem(path: Path) -> str:
    """File name without ``.json.gz`` / ``.json`` / ``.npz``: the key shared by a JSON and its cache."""
    name = path.name
    low = name.lower()
    for suffix in (GZ_JSON_SUFFIX, JSON_SUFFIX, CACHE_SUFFIX):
        if low.endswith(suffix):
            return name[: -len(suffix)]
    return path.stem


def load(path: str | os.PathLike) -> Scenario:
    """Load a scenario from a ``.json`` / ``.json.gz`` file or a ``.npz`` cache, chosen by suffix."""
    p = Path(path)
    if is_json_file(p):
        return load_json(p)
    if p.suffix.lower() == CACHE_SUFFIX:
        return load_cache(p)
    raise ScenarioError(str(path), "path", f"unknown suffix {p.suffix!r}: expected {JSON_SUFFIX}, "
                        f"{GZ_JSON_SUFFIX} or {CACHE_SUFFIX}")


# ---------------------------------------------------------------------------- folders
def _folder(path: str | os.PathLike, argument: str) -> Path:
    folder = Path(path)
    if not folder.is_dir():
        raise ScenarioError(str(path), argument, "folder does not exist")
    return folder


def _json_files(folder: Path, report: LoadReport | None = None) -> dict[str, Path]:
    """``{stem: path}`` of the ``.json`` and ``.json.gz`` files in ``folder``.

    When both ``x.json`` and ``x.json.gz`` exist, ``x.json`` wins and the ``.gz`` is
    recorded in ``report.skipped`` (when a report is given).
    """
    out: dict[str, Path] = {}
    gz: list[Path] = []
    for p in sorted(folder.iterdir()):
        if not p.is_file():
            continue
        low = p.name.lower()
        if low.endswith(JSON_SUFFIX):
            out[_stem(p)] = p
        elif low.endswith(GZ_JSON_SUFFIX):
            gz.append(p)
    for p in gz:
        stem = _stem(p)
        if stem in out:
            if report is not None:
                report.skipped.append((str(p), f"{out[stem].name} holds the same stem and is loaded instead"))
            continue
        out[stem] = p
    return dict(sorted(out.items()))


def _npz_files(folder: Path) -> dict[str, Path]:
    return {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() == CACHE_SUFFIX and p.is_file()}


def scenario_files(folder: str | os.PathLike) -> list[Path]:
    """The ``.json``, ``.json.gz`` and ``.npz`` files of ``folder`` (not recursive), sorted by name.

    For benchmarks and tools that want the file list without loading; :func:`load_dir`
    decides which of them it uses (a fresh cache over its JSON, ``x.json`` over
    ``x.json.gz``). Raises :class:`ScenarioError` when the folder does not exist.
    """
    f = _folder(folder, "folder")
    return sorted({*_json_files(f).values(), *_npz_files(f).values()}, key=lambda p: p.name)


def _fresh(origin: dict[str, Any], json_path: Path) -> bool:
    """Whether a cache with this origin metadata was made from ``json_path`` as it is now."""
    if not origin:
        return False
    size, mtime_ns = _origin_stat(json_path)
    return (origin["size"], origin["mtime_ns"], origin["name"]) == (size, mtime_ns, json_path.name)


def load_dir(
    path: str | os.PathLike, cache_dir: str | os.PathLike | None = None
) -> tuple[list[Scenario], LoadReport]:
    """Load every ``.json``, ``.json.gz`` and ``.npz`` scenario in a folder (not recursive).

    For each file stem, a fresh cache is preferred over the JSON: first
    ``cache_dir/<stem>.npz`` (when ``cache_dir`` is given), then ``<stem>.npz`` next to the
    JSON. A cache is fresh when the size and modification time it recorded match the JSON.
    With ``cache_dir``, missing, stale or unreadable caches are (re)written from the JSON,
    so the folder is converted once. A stale or unreadable ``.npz`` inside the folder itself
    is left alone and reported as skipped; ``.npz`` files without a JSON are loaded as they
    are. A second file with an already-loaded scenario id is skipped, and so is
    ``<stem>.json.gz`` when ``<stem>.json`` exists. A ``.json.gz`` is otherwise exactly a
    ``.json`` (its cache is ``<stem>.npz``, fresh against the ``.gz`` file's size and time).

    Returns the scenarios sorted by file name and a :class:`LoadReport`; anything skipped
    is also issued as a :class:`ScenarioLoadWarning`. Raises :class:`ScenarioError` when the
    folder is missing, holds no scenario files, or every file was skipped.
    """
    folder = _folder(path, "path")
    report = LoadReport()
    jsons, npzs = _json_files(folder, report), _npz_files(folder)
    if not jsons and not npzs:
        raise ScenarioError(str(path), "path",
                            f"no {JSON_SUFFIX}, {GZ_JSON_SUFFIX} or {CACHE_SUFFIX} files in the folder")
    cache = Path(cache_dir) if cache_dir is not None else None
    scenarios: list[Scenario] = []
    seen_ids: dict[str, str] = {}
    for stem in sorted(set(jsons) | set(npzs)):
        json_path = jsons.get(stem)
        scenario, used = None, None
        # The cache_dir copy of a JSON is "managed": rebuilt silently when stale or unreadable.
        managed_path = cache / f"{stem}{CACHE_SUFFIX}" if cache is not None and json_path is not None else None
        candidates = [managed_path] if managed_path is not None else []
        if stem in npzs and not (managed_path is not None and npzs[stem].resolve() == managed_path.resolve()):
            candidates.append(npzs[stem])
        for cand in candidates:
            managed = cand is managed_path
            if not cand.is_file():
                continue
            try:
                sc, origin = _read_cache(cand)
            except ScenarioError as exc:
                if not managed:
                    report.skipped.append((str(cand), str(exc) if json_path is None else
                                           f"unreadable cache, loaded {json_path.name} instead: {exc.reason}"))
                continue
            if json_path is not None and not _fresh(origin, json_path):
                if not managed:
                    report.skipped.append((str(cand), f"stale cache, loaded {json_path.name} instead"))
                continue
            scenario, used = sc, cand
            break
        if scenario is None and json_path is not None:
            try:
                scenario, used = load_json(json_path), json_path
            except ScenarioError as exc:
                report.skipped.append((str(json_path), str(exc)))
                continue
            if managed_path is not None:
                try:
                    save_cache(scenario, managed_path, origin=json_path)
                    report.written.append(str(managed_path))
                except OSError as exc:  # the scenario is fine; only the cache could not be written
                    report.skipped.append((str(managed_path), f"could not write cache: {exc}"))
        if scenario is None:
            continue
        if scenario.id in seen_ids:
            report.skipped.append((str(used), f"duplicate scenario id {scenario.id!r} (already loaded from {seen_ids[scenario.id]})"))
            continue
        seen_ids[scenario.id] = str(used)
        scenarios.append(scenario)
        report.loaded.append(str(used))
    if not scenarios:
        raise ScenarioError(str(path), "path", "no scenario could be loaded:\n" + report.summary())
    report._warn_if_skipped(f"load_dir({str(path)!r})")
    return scenarios, report


def convert_dir(
    src_dir: str | os.PathLike, dst_dir: str | os.PathLike, overwrite: bool = False
) -> LoadReport:
    """Convert every ``*.json`` / ``*.json.gz`` in ``src_dir`` to ``dst_dir/<stem>.npz`` (created if needed).

    A cache that is already fresh for its JSON is kept unless ``overwrite``. Malformed
    files are skipped and reported (also as a :class:`ScenarioLoadWarning`); no partial
    cache is ever left behind. ``loaded`` lists the JSON files that now have a fresh cache.
    Raises :class:`ScenarioError` when ``src_dir`` is missing or holds no ``.json`` / ``.json.gz`` file.
    """
    src = _folder(src_dir, "src_dir")
    report = LoadReport()
    jsons = _json_files(src, report)
    if not jsons:
        raise ScenarioError(str(src_dir), "src_dir", f"no {JSON_SUFFIX} or {GZ_JSON_SUFFIX} files in the folder")
    dst = Path(dst_dir)
    dst.mkdir(parents=True, exist_ok=True)
    for stem, json_path in sorted(jsons.items()):
        target = dst / f"{stem}{CACHE_SUFFIX}"
        if not overwrite and target.is_file():
            try:
                if _fresh(_read_cache(target)[1], json_path):
                    report.loaded.append(str(json_path))
                    continue
            except ScenarioError:
                pass  # unreadable cache: rebuild it below
        try:
            scenario = load_json(json_path)
        except ScenarioError as exc:
            report.skipped.append((str(json_path), str(exc)))
            continue
        save_cache(scenario, target, origin=json_path)
        report.loaded.append(str(json_path))
        report.written.append(str(target))
    report._warn_if_skipped(f"convert_dir({str(src_dir)!r})")
    return report


# ---------------------------------------------------------------------------- command line
def bench_load(folder: Path, repeat: int) -> list[dict[str, Any]]:
    """Best-of-``repeat`` load times (ms) of each JSON in ``folder`` and of its caches."""
    import time

    def best(fn: Callable[[], Any]) -> float:
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        return 1e3 * min(times)

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for stem, json_path in _json_files(_folder(folder, "folder")).items():
            scenario = load_json(json_path)
            packed = save_cache(scenario, Path(tmp) / f"{stem}.npz", compress=True)
            raw = save_cache(scenario, Path(tmp) / f"{stem}_raw.npz", compress=False)
            rows.append({
                "file": json_path.name,
                "agents": scenario.num_agents,
                "json_ms": best(lambda path=json_path: load_json(path)),
                "npz_ms": best(lambda path=packed: load_cache(path)),
                "npz_raw_ms": best(lambda path=raw: load_cache(path)),
                "json_kb": json_path.stat().st_size / 1024,
                "npz_kb": packed.stat().st_size / 1024,
                "npz_raw_kb": raw.stat().st_size / 1024,
            })
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cpsim.scenario.womd convert SRC DST`` | ``bench DIR [--repeat K]``."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m cpsim.scenario.womd", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    conv = sub.add_parser("convert", help="convert a folder of WOMD JSON (.json / .json.gz) into .npz caches")
    conv.add_argument("src")
    conv.add_argument("dst")
    conv.add_argument("--overwrite", action="store_true")
    bench = sub.add_parser("bench", help="time JSON vs cache loading for each JSON (.json / .json.gz) in a folder")
    bench.add_argument("folder")
    bench.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args(argv)
    folder = args.src if args.command == "convert" else args.folder
    if not Path(folder).is_dir():  # one error line, exit status 2, as for any bad argument
        parser.error(f"{'src' if args.command == 'convert' else 'folder'}: no such folder {folder!r}")
    if args.command == "convert":
        report = convert_dir(args.src, args.dst, overwrite=args.overwrite)
        print(report.summary())
        return 0 if report.ok else 1
    print(f"{'file':<36} {'json ms':>8} {'npz ms':>7} {'raw ms':>7} {'json KB':>8} {'npz KB':>7} {'raw KB':>7} {'speed-up':>8}")
    for row in bench_load(Path(args.folder), max(1, args.repeat)):
        print(f"{row['file']:<36} {row['json_ms']:8.2f} {row['npz_ms']:7.2f} {row['npz_raw_ms']:7.2f} "
              f"{row['json_kb']:8.0f} {row['npz_kb']:7.0f} {row['npz_raw_kb']:7.0f} {row['json_ms'] / row['npz_ms']:7.1f}x")
    return 0


if __name__ == "__main__":  # pragma: no cover - command-line entry
    raise SystemExit(main())
