"""Search records: compact, tensor-free copies of CounterPlay searches, for inspection.

With ``CounterPlay(..., keep_searches=N)`` (default 4, 0 disables) the model keeps up to N
searches of every generation as :class:`SearchRecord` objects (NumPy arrays and plain
Python values only: no tensor, snapshot or memory of the search is retained). A record
holds what is needed to explain one search without the simulator:

* the task: scenario (id, family, pool index, road polylines), world, focal slot, the
  failure step and kind of the main rollout, the chosen root and the deadline;
* the backtracking: the focal agent's critic value trace up to the failure, the roots
  inside the window, ``V_max``, ``V_f`` and the threshold ``V_thr``;
* every branch run from the root (:class:`BranchTrace`): the factual branch (w0), one
  candidate per panel style and, when a teacher was chosen and verification is on, the
  two verification reruns; per branch the poses (x, y, heading) of every vehicle at every
  decision from the root, the focal outcome, arrival step, first collision / off-road
  step of every vehicle, the harmed other vehicles, the rank key and admission;
* the chosen candidate and the verification verdict.

A record's ``generation`` is the generation during which the search ran (0-based
``model.budget.generations`` at that time); the search driver runs the searches of a
generation's failures during the next generation, under the policy frozen at the end of
the failing one.

Which searches are kept: per generation at most N, the most informative first (verified
teacher > chosen but discarded > admissible retry > nothing admissible), latest first
among equals; at most ``max_records`` over the whole run (the least informative, oldest
go first). So a rare verified search is not pushed out by later, uneventful ones.

Headings come from the branch runner's positions: the heading at the root is the
simulator's own (read from the root snapshot), later ones follow the direction of motion
between consecutive decisions (held while a vehicle stands still).

:func:`save_records` / :func:`load_records` write and read a ``.npz`` file (no pickle),
atomically; :func:`search_records` returns a model's kept records; :func:`keep_wave` is
the one hook the search driver calls after a wave of searches.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from cpalgo.counterplay.search import BranchOutcome, admit
from cpsim.atomic import atomic_path

__all__ = [
    "failure_anatomy",
    "format_anatomy",
    "BranchTrace",
    "SearchRecord",
    "SearchRecords",
    "build_record",
    "check_keep_searches",
    "keep_wave",
    "load_records",
    "save_records",
    "search_records",
    "searches_path",
    "value_threshold",
    "format_table",
]

#: Outcome names of the focal agent of a branch (and of the main rollout's failure codes).
OUTCOME_NAMES: dict[int, str] = {0: "running", 1: "goal", 2: "collision", 3: "offroad", 4: "timeout"}
BRANCH_KINDS: tuple[str, ...] = ("factual", "candidate", "verify-factual", "verify-candidate")
#: Suffix of the search file written beside a checkpoint (``run/counterplay.zip`` ->
#: ``run/counterplay.searches.npz``).
SEARCHES_SUFFIX = ".searches.npz"
_FORMAT = "counterplay-searches/1"
_MOVING_M = 0.02  # displacement per decision below which a vehicle counts as standing


def check_keep_searches(value: Any) -> int:
    """``keep_searches`` as an int >= 0 (0: keep nothing); ``ValueError`` otherwise."""
    try:
        n = int(value)
    except (TypeError, ValueError):
        raise ValueError(f"keep_searches: expected an integer >= 0, got {value!r}") from None
    if n < 0 or n != value:
        raise ValueError(f"keep_searches: expected an integer >= 0, got {value!r}")
    return n


# ============================================================================ records
@dataclass
class BranchTrace:
    """One branch world of a search, from the root to the end of the world.

    Attributes:
        name: "factual", the panel style, or "verify:factual" / "verify:<style>".
        kind: one of :data:`BRANCH_KINDS`.
        xy: (L + 1, A, 2) float32, every slot's position before each of the L decisions
            the world ran from the root, then after the last one.
        heading: (L + 1, A) float32, radians (see the module docstring).
        valid: (L + 1, A) bool, the vehicle is in the world at that pose (its last valid
            pose is where it was removed: goal, collision or off-road).
        outcome: the focal agent's outcome: goal / collision / offroad / timeout.
        arrival_step: decision at which the focal agent reached its goal (-1 never).
        first_collision_step, first_offroad_step: (A,) int, per slot (-1 none).
        present: (A,) bool, slots holding a vehicle.
        rank_key: U(tau) = (completed, -harmed, -arrival) (:func:`search.rank_key`).
        admissible: candidates: passed :func:`search.admit` against the factual branch.
        transitions: decision-making agent transitions the branch cost.
        focal_return: the focal agent's conditioned return over the branch.
    """

    name: str
    kind: str
    xy: np.ndarray
    heading: np.ndarray
    valid: np.ndarray
    outcome: str
    arrival_step: int
    first_collision_step: np.ndarray
    first_offroad_step: np.ndarray
    present: np.ndarray
    rank_key: tuple[float, float, float]
    admissible: bool | None = None
    transitions: int = 0
    focal_return: float = 0.0

    @property
    def length(self) -> int:
        """Decisions the branch world ran from the root."""
        return int(self.xy.shape[0]) - 1

    def harmed(self, focal: int) -> list[int]:
        """Other slots that collided or went off-road in this branch."""
        hit = (self.first_collision_step >= 0) | (self.first_offroad_step >= 0)
        hit = hit & self.present
        hit[int(focal)] = False
        return np.flatnonzero(hit).astype(int).tolist()

    def focal_end(self, focal: int) -> int:
        """Index of the focal agent's last valid pose (where its outcome is marked)."""
        valid = np.flatnonzero(self.valid[:, int(focal)])
        return int(valid[-1]) if valid.size else 0


@dataclass
class SearchRecord:
    """One search, everything needed to list and draw it (see the module docstring).

    Steps are decisions of the main episode counted from its reset; branch index ``t``
    is decision ``root_step + t``.
    """

    generation: int
    timesteps: int
    scenario_id: str
    scenario_index: int
    family: str
    world: int
    episode: int
    focal: int
    failure_step: int
    failure: str
    root_step: int
    deadline: int
    backtrack: str
    rho: float
    window: tuple[int, int]
    root_interval: int
    values: np.ndarray
    root_steps: np.ndarray
    v_max: float
    v_fail: float
    threshold: float
    panel: tuple[str, ...]
    branches: list[BranchTrace]
    chosen: int | None
    verified: bool | None
    goal: np.ndarray
    size: np.ndarray
    agent_type: np.ndarray
    controller: np.ndarray
    road_points: np.ndarray
    road_offsets: np.ndarray
    road_types: np.ndarray
    goal_radius: float = float("nan")
    order: int = 0

    # ----------------------------------------------------------------- derived
    @property
    def depth(self) -> int:
        return int(self.failure_step - self.root_step)

    @property
    def factual(self) -> BranchTrace:
        return self.branches[0]

    @property
    def candidates(self) -> list[BranchTrace]:
        return [b for b in self.branches if b.kind == "candidate"]

    @property
    def verification(self) -> list[BranchTrace]:
        return [b for b in self.branches if b.kind.startswith("verify")]

    @property
    def admissible_styles(self) -> list[str]:
        return [b.name for b in self.candidates if b.admissible]

    @property
    def teacher(self) -> str | None:
        """The chosen candidate's style, or None."""
        return None if self.chosen is None else self.panel[int(self.chosen)]

    @property
    def status(self) -> str:
        """verified / discarded (chosen, failed verification) / unverified (chosen,
        verification off) / no teacher."""
        if self.chosen is None:
            return "no teacher"
        if self.verified is None:
            return "unverified"
        return "verified" if self.verified else "discarded"

    @property
    def priority(self) -> int:
        """How informative the search is (kept first): 3 verified, 2 chosen, 1 admissible."""
        if self.chosen is not None:
            return 3 if self.verified or self.verified is None else 2
        return 1 if self.admissible_styles else 0

    @property
    def chosen_branch(self) -> BranchTrace | None:
        return None if self.chosen is None else self.candidates[int(self.chosen)]

    def road(self, r: int) -> np.ndarray:
        return self.road_points[int(self.road_offsets[r]):int(self.road_offsets[r + 1])]

    def row(self) -> dict[str, Any]:
        """One line of the search table."""
        return {
            "gen": self.generation,
            "scenario": f"{self.scenario_id}",
            "focal": self.focal,
            "failure": f"{self.failure}@{self.failure_step}",
            "root": self.root_step,
            "depth": self.depth,
            "factual": self.factual.outcome,
            "admissible": ",".join(self.admissible_styles) or "-",
            "teacher": self.teacher or "-",
            "verified": {"verified": "yes", "discarded": "no", "unverified": "off"}.get(self.status, "-"),
        }

    def summary(self) -> str:
        return (f"search of generation {self.generation}: {self.scenario_id} ({self.family}), focal slot {self.focal}, "
                f"{self.failure} at decision {self.failure_step}, root {self.root_step} (depth {self.depth}), "
                f"teacher {self.teacher or '-'} ({self.status})")


# ============================================================================ building
def value_threshold(values: np.ndarray, root_steps: np.ndarray, failure_step: int, window: Sequence[int],
                    rho: float) -> tuple[np.ndarray, float, float, float]:
    """Roots inside the window and ``(V_max, V_f, V_thr)`` as :func:`search.select_root`
    computes them (NaN when no root lies in the window)."""
    values = np.asarray(values, np.float64).reshape(-1)
    roots = np.unique(np.asarray(root_steps, np.int64))
    depth = int(failure_step) - roots
    inside = roots[(depth >= int(window[0])) & (depth <= int(window[1])) & (roots >= 0)]
    v_fail = float(values[int(failure_step)]) if 0 <= failure_step < values.size else float("nan")
    if inside.size == 0:
        return inside, float("nan"), v_fail, float("nan")
    v_max = float(values[inside].max())
    return inside, v_max, v_fail, v_max - float(rho) * (v_max - v_fail)


def _focal_outcome(out: BranchOutcome) -> str:
    if out.completed:
        return "goal"
    f = out.focal
    col, off = int(out.first_collision_step[f]), int(out.first_offroad_step[f])
    if col >= 0 and (off < 0 or col <= off):
        return "collision"
    if off >= 0:
        return "offroad"
    return "timeout"


def _headings(xy: np.ndarray, h0: np.ndarray) -> np.ndarray:
    """(L + 1, A) headings: ``h0`` at the root, then the direction of motion (held while
    standing; a move against the current heading counts as reversing)."""
    out = np.empty(xy.shape[:2], np.float32)
    out[0] = h0
    if xy.shape[0] == 1:
        return out
    d = np.diff(xy.astype(np.float64), axis=0)
    ang = np.arctan2(d[..., 1], d[..., 0])
    moving = np.hypot(d[..., 0], d[..., 1]) > _MOVING_M
    for t in range(d.shape[0]):
        prev = out[t].astype(np.float64)
        back = np.cos(ang[t] - prev) < -0.5  # moving backwards
        new = np.where(back, ang[t] + np.pi, ang[t])
        out[t + 1] = np.where(moving[t], np.angle(np.exp(1j * new)), prev)
    return out


def _valid(actions: np.ndarray, length: int, alive0: np.ndarray, decides0: np.ndarray,
           outcome: BranchOutcome, root_step: int) -> np.ndarray:
    """(L + 1, A) presence: deciders until their last decision's result, other vehicles
    until their first collision / off-road."""
    a = alive0.shape[0]
    valid = np.zeros((length + 1, a), bool)
    valid[0] = alive0
    decided = actions[:length] >= 0  # (L, A)
    valid[1:] = decided
    stop = np.where(outcome.first_collision_step >= 0, outcome.first_collision_step, np.iinfo(np.int64).max)
    stop = np.minimum(stop, np.where(outcome.first_offroad_step >= 0, outcome.first_offroad_step,
                                     np.iinfo(np.int64).max))
    t = np.arange(length + 1)[:, None]
    others = alive0 & ~decides0
    valid[:, others] = (root_step + t - 1 <= stop[None, :])[:, others]
    valid[0] = alive0
    return valid


def _trace(name: str, kind: str, res: Any, b: int, alive0: np.ndarray, decides0: np.ndarray,
           h0: np.ndarray, root_step: int, admissible: bool | None = None) -> BranchTrace:
    out: BranchOutcome = res.outcomes[b]
    actions = np.asarray(res.actions[b])  # (T, A), -1 when the slot did not decide
    ran = np.flatnonzero((actions >= 0).any(axis=1))
    length = int(ran[-1]) + 1 if ran.size else 0
    xy = np.asarray(res.xy[b, : length + 1], np.float32).copy()
    return BranchTrace(
        name=name, kind=kind, xy=xy, heading=_headings(xy, h0),
        valid=_valid(actions, length, alive0, decides0, out, root_step),
        outcome=_focal_outcome(out), arrival_step=int(out.arrival_step),
        first_collision_step=out.first_collision_step.astype(np.int32).copy(),
        first_offroad_step=out.first_offroad_step.astype(np.int32).copy(),
        present=out.present.astype(bool).copy(), rank_key=tuple(float(k) for k in out.key),
        admissible=admissible, transitions=int(res.transitions[b]), focal_return=float(out.focal_return),
    )


def _snapshot_row(snapshot: Any, row: int, names: Iterable[str]) -> dict[str, np.ndarray]:
    """Fields of one world of a root snapshot, as NumPy (copies)."""
    state = snapshot.state
    return {n: np.asarray(getattr(state, n).numpy()[row]).copy() for n in names}


def build_record(req: Any, res: Any, *, panel: Sequence[str], scenario: Any, window: Sequence[int], rho: float,
                 backtrack: str, root_interval: int, chosen: int | None = None, verified: bool | None = None,
                 verification: Any = None, generation: int = 0, timesteps: int = 0) -> SearchRecord:
    """A :class:`SearchRecord` from a search request, its branch result and its verdict.

    Args:
        req: the :class:`~cpalgo.counterplay.roots.SearchRequest` (root snapshot, values).
        res: the :class:`~cpalgo.counterplay.branches.BranchResult` of the factual and
            candidate branches (factual first, then ``panel`` order).
        scenario: the :class:`cpsim.scenario.Scenario` the world runs (map, id).
        chosen: index into ``panel`` of the chosen candidate (None: none admissible).
        verified: verification verdict of the chosen candidate (None: not verified).
        verification: the BranchResult of the two verification reruns, or None.
    """
    policy_code = 0  # cpsim.config.Controller.POLICY
    root = _snapshot_row(req.snapshot, int(req.snapshot_row),
                         ("alive", "heading", "controller", "goal", "size", "agent_type"))
    alive0 = root["alive"].astype(bool)
    decides0 = alive0 & (root["controller"] == policy_code)
    h0 = root["heading"].astype(np.float32)
    rs = int(req.root_step)
    factual = res.outcomes[0]
    branches = [_trace("factual", "factual", res, 0, alive0, decides0, h0, rs)]
    for j, name in enumerate(panel):
        branches.append(_trace(str(name), "candidate", res, 1 + j, alive0, decides0, h0, rs,
                               admissible=bool(admit(factual, res.outcomes[1 + j]))))
    if verification is not None and chosen is not None:
        branches.append(_trace("verify:factual", "verify-factual", verification, 0, alive0, decides0, h0, rs))
        branches.append(_trace(f"verify:{panel[int(chosen)]}", "verify-candidate", verification, 1,
                               alive0, decides0, h0, rs))
    fs = int(req.failure_step)
    values = np.asarray(req.values, np.float32).reshape(-1).copy()
    all_roots = np.arange(0, fs + 1, int(root_interval), dtype=np.int64)
    if backtrack == "value":
        inside, v_max, v_fail, thr = value_threshold(values, all_roots, fs, window, rho)
    else:
        inside, v_max, v_fail, thr = all_roots, float("nan"), float(values[fs]), float("nan")
    return SearchRecord(
        generation=int(generation), timesteps=int(timesteps),
        scenario_id=str(getattr(scenario, "id", "?")), scenario_index=-1, family=str(getattr(scenario, "family", "")),
        world=int(req.world), episode=int(req.episode), focal=int(req.focal), failure_step=fs,
        failure=OUTCOME_NAMES.get(int(req.outcome), str(req.outcome)), root_step=rs, deadline=int(req.deadline),
        backtrack=str(backtrack), rho=float(rho), window=(int(window[0]), int(window[1])),
        root_interval=int(root_interval), values=values, root_steps=np.asarray(inside, np.int64),
        v_max=v_max, v_fail=v_fail, threshold=thr, panel=tuple(str(p) for p in panel), branches=branches,
        chosen=None if chosen is None else int(chosen), verified=None if verified is None else bool(verified),
        goal=root["goal"].astype(np.float32), size=root["size"].astype(np.float32),
        agent_type=root["agent_type"].astype(np.int32), controller=root["controller"].astype(np.int32),
        road_points=np.asarray(scenario.road_points, np.float32),
        road_offsets=np.asarray(scenario.road_offsets, np.int64),
        road_types=np.asarray(scenario.road_types, np.int8),
        goal_radius=float(np.asarray(req.conditions)[int(req.focal), 0]),
    )


# ============================================================================ store
class SearchRecords:
    """The kept searches of a model (see the module docstring for the keep rule).

    Args:
        per_generation: searches kept per generation (>= 1).
        max_records: bound over the whole run.
    """

    def __init__(self, per_generation: int = 4, max_records: int = 256) -> None:
        self.per_generation = max(1, int(per_generation))
        self.max_records = max(1, int(max_records))
        self.records: list[SearchRecord] = []
        self._order = 0

    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self):
        return iter(self.records)

    def __getitem__(self, k: int) -> SearchRecord:
        return self.records[k]

    @staticmethod
    def _rank(r: SearchRecord) -> tuple[int, int]:
        return (r.priority, r.order)

    def add(self, record: SearchRecord) -> None:
        record.order = self._order
        self._order += 1
        self.records.append(record)
        same = [r for r in self.records if r.generation == record.generation]
        if len(same) > self.per_generation:
            self.records.remove(min(same, key=self._rank))
        while len(self.records) > self.max_records:
            self.records.remove(min(self.records, key=lambda r: (r.priority, r.generation, r.order)))
        self.records.sort(key=lambda r: r.order)

    def latest(self, status: str | None = None) -> SearchRecord | None:
        """The latest kept record, optionally of a given :attr:`SearchRecord.status`."""
        for r in reversed(self.records):
            if status is None or r.status == status:
                return r
        return None


def search_records(model: Any) -> SearchRecords:
    """A model's kept searches (an empty store when it kept none)."""
    store = getattr(model, "__dict__", {}).get("_search_records")
    return store if store is not None else SearchRecords()


def keep_wave(model: Any, requests: Sequence[Any], results: Sequence[Any],
              chosen: Sequence[tuple], passed: Sequence[bool], verifications: Sequence[Any] | None) -> None:
    """Keep records of one wave of searches on ``model`` (the search driver's hook).

    ``requests`` / ``results``: the wave's searches and their branch results; ``chosen``:
    ``(req, job, res, j)`` per search with a teacher; ``passed``: their verdicts;
    ``verifications``: the reruns' results aligned with ``chosen`` (None when not run).
    Does nothing, and touches nothing, when ``model.keep_searches`` is 0.
    """
    n = int(getattr(model, "keep_searches", 0) or 0)
    if n <= 0 or not requests:
        return
    store = model.__dict__.get("_search_records")
    if store is None:
        store = model._search_records = SearchRecords(n)
    store.per_generation = n
    driver = getattr(model, "_driver", None)
    sim = getattr(driver, "sim", None) or getattr(model, "_sim_for_roots", None) or model.env.sim
    verdict: dict[int, tuple[int, bool, Any]] = {}
    for k, (req, _job, _res, j) in enumerate(chosen):
        vres = verifications[k] if verifications is not None else None
        ok = bool(passed[k]) if verifications is not None else None
        verdict[id(req)] = (int(j), ok, vres)
    generation = int(getattr(getattr(model, "budget", None), "generations", 0))
    for req, res in zip(requests, results):
        j, ok, vres = verdict.get(id(req), (None, None, None))
        index = int(req.snapshot.state.scenario.numpy()[int(req.snapshot_row)])
        scenario = sim.model.scenarios[index] if hasattr(sim, "model") else sim.scenarios[index]
        record = build_record(req, res, panel=model.panel, scenario=scenario, window=model.window, rho=model.rho,
                              backtrack=model.backtrack, root_interval=model.root_interval, chosen=j, verified=ok,
                              verification=vres, generation=generation, timesteps=int(model.num_timesteps))
        record.scenario_index = index
        store.add(record)


# ============================================================================ files
def searches_path(path: str | os.PathLike) -> Path:
    """The search file of ``path``: itself for a ``.npz``, else the file beside a checkpoint
    (``run/counterplay.zip`` -> ``run/counterplay.searches.npz``)."""
    path = Path(path)
    if path.name.endswith(".npz"):
        return path
    stem = path.name[: -len(".zip")] if path.name.endswith(".zip") else path.name
    return path.with_name(stem + SEARCHES_SUFFIX)


_BRANCH_ARRAYS = ("xy", "heading", "valid", "first_collision_step", "first_offroad_step", "present")
_RECORD_ARRAYS = ("values", "root_steps", "goal", "size", "agent_type", "controller")


def save_records(records: Iterable[SearchRecord] | Any, path: str | os.PathLike) -> Path:
    """Write records (or a model's kept searches) to a ``.npz`` file atomically.

    ``path`` may be a checkpoint path (``.zip``): the file goes beside it
    (:func:`searches_path`). Road polylines are stored once per scenario. Returns the path.
    """
    if not isinstance(records, (list, tuple, SearchRecords)) and hasattr(records, "__dict__") \
            and not isinstance(records, SearchRecord):
        records = search_records(records)
    records = list(records)
    path = searches_path(path)
    arrays: dict[str, np.ndarray] = {}
    metas = []
    roads: dict[str, int] = {}
    for i, r in enumerate(records):
        key = f"{r.scenario_id}|{r.road_points.shape[0]}"
        if key not in roads:
            roads[key] = k = len(roads)
            arrays[f"road{k}.points"] = r.road_points
            arrays[f"road{k}.offsets"] = r.road_offsets
            arrays[f"road{k}.types"] = r.road_types
        for name in _RECORD_ARRAYS:
            arrays[f"r{i}.{name}"] = np.asarray(getattr(r, name))
        branches = []
        for b, br in enumerate(r.branches):
            for name in _BRANCH_ARRAYS:
                arrays[f"r{i}.b{b}.{name}"] = np.asarray(getattr(br, name))
            branches.append({"name": br.name, "kind": br.kind, "outcome": br.outcome,
                             "arrival_step": br.arrival_step, "rank_key": [_json_float(x) for x in br.rank_key],
                             "admissible": br.admissible, "transitions": br.transitions,
                             "focal_return": _json_float(br.focal_return)})
        metas.append({
            "road": roads[key], "generation": r.generation, "timesteps": r.timesteps, "scenario_id": r.scenario_id,
            "scenario_index": r.scenario_index, "family": r.family, "world": r.world, "episode": r.episode,
            "focal": r.focal, "failure_step": r.failure_step, "failure": r.failure, "root_step": r.root_step,
            "deadline": r.deadline, "backtrack": r.backtrack, "rho": r.rho, "window": list(r.window),
            "root_interval": r.root_interval, "v_max": _json_float(r.v_max), "v_fail": _json_float(r.v_fail),
            "threshold": _json_float(r.threshold), "panel": list(r.panel), "chosen": r.chosen,
            "verified": r.verified, "order": r.order, "goal_radius": _json_float(r.goal_radius), "branches": branches,
        })
    arrays["meta"] = np.array(json.dumps({"format": _FORMAT, "records": metas}))
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return path


def _json_float(x: float) -> float | str:
    x = float(x)
    if np.isnan(x):
        return "nan"
    if np.isinf(x):
        return "inf" if x > 0 else "-inf"
    return x


def _float(x: Any) -> float:
    return float(x)  # float("nan") / float("-inf") read the strings back


def load_records(path: str | os.PathLike) -> list[SearchRecord]:
    """Read records written by :func:`save_records` (a ``.npz`` or the checkpoint beside it)."""
    path = searches_path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no search file {str(path)!r}")
    with np.load(path, allow_pickle=False) as data:
        try:
            meta = json.loads(str(data["meta"]))
        except KeyError:
            raise ValueError(f"{path}: not a CounterPlay search file (no meta entry)") from None
        if meta.get("format") != _FORMAT:
            raise ValueError(f"{path}: unknown search file format {meta.get('format')!r}")
        out = []
        for i, m in enumerate(meta["records"]):
            k = m["road"]
            branches = [
                BranchTrace(name=b["name"], kind=b["kind"], outcome=b["outcome"], arrival_step=int(b["arrival_step"]),
                            rank_key=tuple(_float(x) for x in b["rank_key"]), admissible=b["admissible"],
                            transitions=int(b["transitions"]), focal_return=_float(b["focal_return"]),
                            **{name: data[f"r{i}.b{j}.{name}"] for name in _BRANCH_ARRAYS})
                for j, b in enumerate(m["branches"])
            ]
            out.append(SearchRecord(
                generation=m["generation"], timesteps=m["timesteps"], scenario_id=m["scenario_id"],
                scenario_index=m["scenario_index"], family=m["family"], world=m["world"], episode=m["episode"],
                focal=m["focal"], failure_step=m["failure_step"], failure=m["failure"], root_step=m["root_step"],
                deadline=m["deadline"], backtrack=m["backtrack"], rho=m["rho"], window=tuple(m["window"]),
                root_interval=m["root_interval"], v_max=_float(m["v_max"]), v_fail=_float(m["v_fail"]),
                threshold=_float(m["threshold"]), panel=tuple(m["panel"]), branches=branches, chosen=m["chosen"],
                verified=m["verified"], order=m["order"], goal_radius=_float(m.get("goal_radius", "nan")),
                road_points=data[f"road{k}.points"], road_offsets=data[f"road{k}.offsets"],
                road_types=data[f"road{k}.types"],
                **{name: data[f"r{i}.{name}"] for name in _RECORD_ARRAYS},
            ))
    return out


# ============================================================================ table
TABLE_COLUMNS: tuple[str, ...] = ("gen", "scenario", "focal", "failure", "root", "depth", "factual", "admissible",
                                  "teacher", "verified")


def failure_anatomy(records: Sequence[SearchRecord], stuck_m: float = 5.0) -> dict[str, float]:
    """What the searched failures were and how much room their roots left (kept searches).

    A retry can only repair what a style change can change from its root. This summary tells
    where that room is missing: timeouts in which the focal agent passed inside its goal
    radius (it arrived, but faster than its goal speed allows), timeouts in which it barely
    moved after the root (stuck or crawling), and how many decisions the root left.

    Args:
        records: kept searches (:func:`search_records`, :func:`load_records`).
        stuck_m: a focal agent that drove less than this (m) from the root to the end of
            the factual branch counts as stuck.
    Returns:
        ``searches``; ``timeout`` / ``collision`` / ``offroad`` / ``goal``: the factual
        branch's focal outcome, counts (a ``goal`` is a lucky factual rerun);
        ``timeout_passed_goal`` and ``timeout_stuck``: counts among the timeouts;
        ``decisions_after_root_median`` / ``_mean``: decisions from the root to the end of
        the factual branch; ``candidates_completed``: share of the candidate branches whose
        focal agent reached its goal (NaN when there are none); ``roots_at_reset``: searches
        whose root is the episode's first decision (the value rule found no earlier peak);
        ``verified``: searches whose teacher passed verification, and
        ``verified_factual_completed`` those among them whose factual branch completed the
        task on the verification's fresh draws too (a failure that did not recur: the teacher
        repairs sampling noise, not the policy).
    """
    out: dict[str, float] = {"searches": float(len(records)), "timeout": 0.0, "collision": 0.0, "offroad": 0.0,
                             "goal": 0.0, "timeout_passed_goal": 0.0, "timeout_stuck": 0.0,
                             "roots_at_reset": 0.0, "verified": 0.0, "verified_factual_completed": 0.0}
    lengths: list[int] = []
    completed = candidates = 0
    for r in records:
        f, a = r.factual, int(r.focal)
        out[f.outcome] = out.get(f.outcome, 0.0) + 1.0
        lengths.append(int(f.length))
        path = f.xy[f.valid[:, a], a]  # (n, 2) focal positions the branch kept
        if f.outcome == "timeout" and len(path):
            gap = np.linalg.norm(path - r.goal[a][None, :], axis=1).min()
            out["timeout_passed_goal"] += float(np.isfinite(r.goal_radius) and gap < r.goal_radius)
            out["timeout_stuck"] += float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum() < stuck_m)
        for b in r.branches:
            if b.kind == "candidate":
                candidates += 1
                completed += b.outcome == "goal"
        out["roots_at_reset"] += float(r.root_step == 0)
        if r.verified:
            out["verified"] += 1.0
            out["verified_factual_completed"] += float(any(
                b.kind == "verify-factual" and b.outcome == "goal" for b in r.branches))
    out["decisions_after_root_median"] = float(np.median(lengths)) if lengths else float("nan")
    out["decisions_after_root_mean"] = float(np.mean(lengths)) if lengths else float("nan")
    out["candidates_completed"] = completed / candidates if candidates else float("nan")
    return out


def format_anatomy(anatomy: dict[str, float]) -> str:
    """:func:`failure_anatomy` as three plain-text lines."""
    t, v = anatomy["timeout"], anatomy["verified"]
    share = (lambda k: f"{100 * anatomy[k] / t:.0f}%") if t else (lambda k: "-")
    recur = f"{100 * anatomy['verified_factual_completed'] / v:.0f}%" if v else "-"
    return (f"factual failures: {anatomy['timeout']:.0f} timeouts ({share('timeout_passed_goal')} passed inside the "
            f"goal radius too fast, {share('timeout_stuck')} stuck), {anatomy['collision']:.0f} collisions, "
            f"{anatomy['offroad']:.0f} off-road, {anatomy['goal']:.0f} completed on the rerun\n"
            f"roots: median {anatomy['decisions_after_root_median']:.0f} decisions before the end, "
            f"{anatomy['roots_at_reset']:.0f} at the episode's first decision; candidates "
            f"completed: {100 * anatomy['candidates_completed']:.1f}%\n"
            f"verified teachers: {v:.0f}, of which the factual branch completed on the fresh draws too: {recur}")


def format_table(records: Sequence[SearchRecord]) -> str:
    """The kept searches as a plain-text table (first column: the index ``--show`` takes)."""
    rows = [{"#": str(k), **{c: str(v) for c, v in r.row().items()}} for k, r in enumerate(records)]
    cols = ("#",) + TABLE_COLUMNS
    width = {c: max([len(c)] + [len(row[c]) for row in rows]) for c in cols}
    lines = ["  ".join(c.ljust(width[c]) for c in cols)]
    lines.append("  ".join("-" * width[c] for c in cols))
    for row in rows:
        lines.append("  ".join(row[c].ljust(width[c]) for c in cols))
    return "\n".join(lines)
