"""Batched BehaviorBench-style evaluation: every task x traffic regime in one simulator.

A *task* is one scenario with its designated ego (``Scenario.ego_index``, simulator slot
0). Tasks come from an Interactive-N and a Random-N split of an evaluation pool that is
disjoint from training (:func:`make_tasks`; procedural ``eval_pool`` by default, or a
folder of WOMD JSON / ``.npz``).

For each task and each traffic regime the ego policy drives under a fixed deployment
condition with deterministic (argmax) actions until the end of the episode. All
task-regimes are laid out over the worlds of one :class:`cpsim.Simulator` (in chunks of
``max_worlds``); co-players are driven by :class:`cpsim.envs.regimes.TrafficDriver`, one
driver per regime, each owning the worlds of its regime, so a step costs one simulator
step, one ego forward pass and one forward pass per model-driven regime.

Regimes (:data:`REGIMES`, BehaviorBench's eight):

============== ===================================================================
idm            co-players follow their logged routes with IDM
selfplay       co-players driven by the separately trained self-play PPO policy
               (``ppo_policy``, default :data:`DEFAULT_PPO_PATHS` of the dynamics, unconditioned: it sees
               the normal profile); without one, by ``traffic_policy`` under conditions
               drawn from p_train at reset
bc             co-players driven by the behaviour-cloning log-imitation model
               (``bc_policy``, default ``zoo/bc_traffic.pt``), stands in for SMART
replay         expert log replay
aggressive     ``traffic_policy`` under the aggressive profile
normal         ``traffic_policy`` under the normal profile
cautious       ``traffic_policy`` under the cautious profile
mix            ``traffic_policy``, the three profiles rotating over the co-players
============== ===================================================================

``static`` (co-players stand still) is accepted as an extra regime.

The simulator runs in the dynamics model (``jerk`` or ``classic``) of the learned policies
given, read from their action sets (:func:`policy_dynamics`); they must agree
(:class:`Evaluator`, docs/evaluation.md "Dynamics").
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from cpalgo.evaluate import metrics as M
from cpalgo.recipes import resolve_path, shipped_names, shipped_path
from cpsim.arrays import to_numpy as _np
from cpsim.conditions import deployment_condition
from cpsim.config import Controller, Outcome, known_fields
from cpsim.scenario.datatypes import AgentType

#: BehaviorBench's eight traffic regimes, in the column order of the tables.
REGIMES: tuple[str, ...] = ("idm", "selfplay", "bc", "replay", "aggressive", "normal", "cautious", "mix")
#: Extra regimes accepted on request.
EXTRA_REGIMES: tuple[str, ...] = ("static",)
REGIME_ALIASES: dict[str, str] = {
    "self-play": "selfplay", "policy": "selfplay", "ppo": "selfplay",
    "log-imitation": "bc", "smart": "bc", "expert": "replay", "log": "replay",
}
SPLITS: tuple[str, ...] = ("interactive", "random")
#: Ego "policies" that are built-in simulator controllers (baselines, sanity checks).
EGO_CONTROLLERS: dict[str, int] = {"replay": int(Controller.REPLAY), "expert": int(Controller.REPLAY),
                                   "idm": int(Controller.IDM), "static": int(Controller.STATIC)}
#: Default shipped BC traffic model (inside the package, ``zoo/bc_traffic.pt`` in a clone).
DEFAULT_BC_PATH = shipped_path("bc_traffic.pt")


def _shipped_or_zoo(name: str) -> Path:
    return shipped_path(name) if name in shipped_names() else Path("zoo", name)


#: The default co-player of the policy regimes, per dynamics model: the shipped
#: reward-conditioned anchor of that dynamics (the self-play anchor in classic, the
#: teacher-imitation anchor in jerk). Before a policy decides the dynamics, the first
#: entry's file decides them.
DEFAULT_TRAFFIC_PATHS: dict[str, Path] = {"classic": _shipped_or_zoo("anchor.zip"),
                                          "jerk": _shipped_or_zoo("anchor_imitation.zip")}
#: The default co-player of the ``selfplay`` (PPO) regime, per dynamics model: a shipped
#: self-play PPO policy of another recipe and seed than the anchor, trained under one fixed
#: condition. Without one for the evaluation's dynamics, the regime's co-players are the
#: traffic policy under p_train conditions (a note says so).
DEFAULT_PPO_PATHS: dict[str, Path] = {"classic": _shipped_or_zoo("ppo_traffic_classic.zip"),
                                      "jerk": _shipped_or_zoo("ppo_traffic.zip")}
#: Agent slots per world by default: every agent present at t0, up to BehaviorBench's 128.
MAX_EVAL_AGENTS = 128

_POLICY = int(Controller.POLICY)
_RUNNING, _GOAL, _COLLISION, _OFFROAD, _TIMEOUT = (int(o) for o in (Outcome.RUNNING, Outcome.GOAL, Outcome.COLLISION,
                                                                   Outcome.OFFROAD, Outcome.TIMEOUT))
_VEHICLE = int(AgentType.VEHICLE)


def resolve_regime(name: str) -> str:
    """Canonical evaluation regime name; ``ValueError`` listing accepted names otherwise."""
    key = REGIME_ALIASES.get(str(name).lower(), str(name).lower())
    if key not in REGIMES + EXTRA_REGIMES:
        raise ValueError(f"regimes: unknown regime {name!r}; accepted: "
                         f"{list(REGIMES + EXTRA_REGIMES) + sorted(REGIME_ALIASES)}")
    return key


def resolve_split(name: str) -> tuple[str, ...]:
    """``interactive``, ``random`` or ``both`` -> tuple of split names."""
    key = str(name).lower()
    if key == "both":
        return SPLITS
    if key not in SPLITS:
        raise ValueError(f"split: unknown split {name!r}; accepted: {list(SPLITS) + ['both']}")
    return (key,)


# ============================================================================ tasks
@dataclasses.dataclass(frozen=True)
class Task:
    """One evaluation task: a scenario whose ``ego_index`` is the ego, in a named split."""

    split: str
    index: int  # position within its split
    scenario: Any  # cpsim.Scenario

    @property
    def scenario_id(self) -> str:
        return self.scenario.id

    @property
    def ego(self) -> int:
        return int(self.scenario.ego_index)


def make_tasks(pool: str | os.PathLike | Sequence[Any] = "procedural", split: str = "both", n: int = 50,
               seed: int = 0, pool_size: int | None = None) -> list[Task]:
    """Interactive-N and/or Random-N tasks from an evaluation pool.

    Args:
        pool: ``"procedural"`` (``cpsim.scenario.eval_pool(pool_size, seed)``, disjoint
            from the training seeds; only the scenes whose ego log reaches its goal,
            ``cpsim.scenario.ego_log_reaches_goal``, become tasks, as every BehaviorBench
            goal lies on its log), a folder of WOMD ``.json`` / ``.json.gz`` / ``.npz``
            files (one task per ``tracks_to_predict`` vehicle, ``cpsim.scenario.track_tasks``;
            Random-N draws among eligible tasks), or a list of scenarios (tasks as given).
        split: ``interactive``, ``random`` or ``both``.
        n: tasks per split; clamped to what the pool offers (Interactive: eligible
            scenarios), an empty split raises ``ValueError``.
        seed: pool seed and Random-N draw.
        pool_size: procedural pool size (default ``4 n``, so Interactive-N picks the most
            interactive quarter).
    """
    from cpsim.scenario import splits as S

    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n: expected a positive integer, got {n!r}")
    if pool_size is not None and (isinstance(pool_size, bool) or not isinstance(pool_size, (int, np.integer))
                                  or pool_size < int(n)):
        raise ValueError(f"pool_size: expected a whole number >= n ({n}: each split takes n tasks of the pool), "
                         f"got {pool_size!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a whole number >= 0, got {seed!r}")
    names = resolve_split(split)
    folder = False
    if isinstance(pool, (str, os.PathLike)):
        if str(pool) == "procedural":
            from cpsim.scenario import ego_log_reaches_goal, eval_pool

            # a scene whose log falls short of its goal is not a task: the generator keeps
            # such a scene only when no clearing draw came up (3 of eval_pool(400, seed=0))
            scenarios = [sc for sc in eval_pool(pool_size or 4 * int(n), seed) if ego_log_reaches_goal(sc)]
        else:
            path = Path(pool)
            if not path.is_dir():
                raise ValueError(f"pool: {str(pool)!r} is neither 'procedural' nor a folder")
            from cpsim.scenario import load_dir

            # WOMD folder (.json, .json.gz, .npz): one task per tracks_to_predict vehicle,
            # Random-N among eligible tasks only (BehaviorBench; DESIGN.md "Evaluation")
            loaded, _report = load_dir(path)
            scenarios = S.track_tasks(loaded)
            folder = True
    else:
        scenarios = list(pool)
    if not scenarios:
        raise ValueError(f"pool: {pool!r} holds no scenarios")
    tasks: list[Task] = []
    eligible = sum(t.eligible for t in S.interactivity_report(scenarios))
    for name in names:
        if name == "interactive":
            chosen = S.interactive_split(scenarios, min(int(n), eligible)) if eligible else []
        elif folder:
            chosen = S.random_split(scenarios, min(int(n), eligible), seed, eligible_only=True) if eligible else []
        else:
            chosen = S.random_split(scenarios, min(int(n), len(scenarios)), seed)
        if not chosen:
            raise ValueError(f"split: the {name} split of pool {str(pool)!r} is empty "
                             f"(no scenario eligible among {len(scenarios)})")
        tasks += [Task(name, i, sc) for i, sc in enumerate(chosen)]
    return tasks


# ============================================================================ policies
class EgoPolicy:
    """What drives the ego. Subclasses: :class:`ModelEgo`, :class:`FunctionEgo`,
    :class:`ControllerEgo`.

    Attributes:
        label: row name in the tables.
        checkpoint: where it came from (path or description).
        controller: ``cpsim.Controller`` value of the ego slot (POLICY for learned policies).
        obs_size: observation size the policy expects (None: any).
    """

    label: str = "policy"
    checkpoint: str = ""
    controller: int = _POLICY
    obs_size: int | None = None

    def reset(self, n: int) -> None:
        """Start ``n`` new episodes (clears recurrent memory)."""

    def bind(self, sim: Any) -> None:
        """Called once per chunk after the ego's condition is set (teachers read the simulator)."""

    def act(self, obs: np.ndarray, episode_start: np.ndarray) -> np.ndarray:
        """(n, D) float32 observations -> (n,) int64 deterministic actions."""
        return np.zeros(obs.shape[0], np.int64)


class ControllerEgo(EgoPolicy):
    """The ego follows a built-in controller (``replay``/``expert``, ``idm``, ``static``)."""

    def __init__(self, name: str):
        key = name.lower()
        if key not in EGO_CONTROLLERS:
            raise ValueError(f"policy: unknown built-in controller {name!r}; accepted: {sorted(EGO_CONTROLLERS)}")
        self.label = "expert-replay" if key in ("replay", "expert") else key
        self.checkpoint = f"controller:{key}"
        self.controller = EGO_CONTROLLERS[key]


class TeacherEgo(EgoPolicy):
    """The ego is driven by an imitation teacher of :mod:`cpsim.expert` (``reactive`` or
    ``tracking``), under the deployment condition: the reference a student policy imitates.

    The teacher reads the simulator (logged route, other vehicles, the ego's live condition),
    so it is rebuilt on every chunk (:meth:`bind`); its actions are batched over the chunk's
    worlds and agents, and only slot 0 (the ego) is used.
    """

    def __init__(self, name: str):
        from cpsim.expert import EXPERTS

        key = name.lower()
        if key not in EXPERTS:
            raise ValueError(f"policy: unknown teacher {name!r}; accepted: {list(EXPERTS)}")
        self.name = key
        self.label = f"{key}-teacher"
        self.checkpoint = f"teacher:{key}"
        self._expert: Any = None

    def bind(self, sim: Any) -> None:
        from cpsim.expert import make_expert

        self._expert = make_expert(self.name, sim)

    def act(self, obs: np.ndarray, episode_start: np.ndarray) -> np.ndarray:
        if self._expert is None:
            raise RuntimeError("TeacherEgo.act before bind(sim)")
        return _np(self._expert.actions())[:, 0].astype(np.int64)


class ModelEgo(EgoPolicy):
    """An SB3 model (PPO, RecurrentPPO, CounterPlay) or anything with SB3's ``predict``.

    Recurrent state is kept per ego, batched as the model returns it.
    """

    def __init__(self, model: Any, label: str = "policy", checkpoint: str = ""):
        if not hasattr(model, "predict"):
            raise ValueError("policy: model has no predict(obs, state, episode_start, deterministic)")
        self.model = model
        self.label = label
        self.checkpoint = checkpoint
        space = getattr(model, "observation_space", None)
        shape = getattr(space, "shape", None)
        self.obs_size = int(np.prod(shape)) if shape else getattr(model, "obs_size", None)
        self._state: tuple[np.ndarray, ...] | None = None

    def reset(self, n: int) -> None:
        self._state = None

    def act(self, obs: np.ndarray, episode_start: np.ndarray) -> np.ndarray:
        actions, self._state = self.model.predict(obs, state=self._state, episode_start=episode_start,
                                                  deterministic=True)
        return np.asarray(actions).reshape(-1).astype(np.int64)


class FunctionEgo(EgoPolicy):
    """A plain callable ``f(obs (n, D)) -> (n,) actions``."""

    def __init__(self, fn: Callable[[np.ndarray], Any], label: str = "callable"):
        self.fn = fn
        self.label = label
        self.checkpoint = getattr(fn, "__name__", "callable")

    def act(self, obs: np.ndarray, episode_start: np.ndarray) -> np.ndarray:
        out = np.asarray(self.fn(obs))
        if out.size != obs.shape[0] or not (np.issubdtype(out.dtype, np.integer)
                                            or (np.issubdtype(out.dtype, np.floating)
                                                and np.all(out == np.round(out)))):
            raise ValueError(f"policy: the callable {self.checkpoint!r} must return {obs.shape[0]} integer "
                             f"actions (one per observation row), got {out.dtype} of shape {out.shape}")
        return out.reshape(-1).astype(np.int64)


def load_model(path: str | os.PathLike, argument: str = "policy") -> Any:
    """Load a checkpoint: an SB3 ``.zip`` (CounterPlay, RecurrentPPO or PPO) or a BC ``.pt``.

    ``zoo/NAME`` names a shipped file (:func:`cpalgo.recipes.resolve_path`). A zip saved by
    CounterPlay loads as :class:`~cpalgo.CounterPlay`, other zips through
    :func:`cpsim.envs.regimes.load_policy` (RecurrentPPO, PPO, A2C, DQN). Raises ``ValueError`` naming the argument and the
    file when nothing can load it.
    """
    p = Path(resolve_path(path))
    if not p.is_file():
        raise ValueError(f"{argument}: checkpoint {str(p)!r} does not exist")
    if p.suffix == ".pt":
        from cpalgo.traffic.bc import BCPolicy

        try:
            return BCPolicy.load(p)
        except Exception as exc:  # noqa: BLE001 - reported with the file name
            raise ValueError(f"{argument}: cannot load BC checkpoint {str(p)!r}: {exc}") from None
    from sb3_contrib import RecurrentPPO

    from cpalgo import CounterPlay
    from cpsim.envs.regimes import load_policy

    if _saved_by(p, CounterPlay, RecurrentPPO):
        try:
            return CounterPlay.load(str(p), device="cpu")
        except Exception as exc:  # noqa: BLE001 - reported with the file name
            raise ValueError(f"{argument}: cannot load CounterPlay checkpoint {str(p)!r}: {exc}") from None
    return load_policy(p, argument)


def _saved_by(path: Path, cls: type, parent: type) -> bool:
    """Whether the SB3 zip at ``path`` holds constructor arguments that ``cls`` adds to
    ``parent`` (SB3 saves an algorithm's settings under its argument names)."""
    import inspect
    import json
    import zipfile

    own = set(inspect.signature(cls.__init__).parameters) - set(inspect.signature(parent.__init__).parameters)
    try:
        with zipfile.ZipFile(path) as z:
            data = json.loads(z.read("data"))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return False
    return isinstance(data, dict) and bool(own & set(data))


def as_ego_policy(policy: Any, label: str | None = None) -> EgoPolicy:
    """Wrap a policy spec: an :class:`EgoPolicy`, a built-in controller name
    (``replay``/``expert``, ``idm``, ``static``), a teacher name (``reactive``, ``tracking``),
    a checkpoint path, an SB3 model or a callable."""
    if isinstance(policy, EgoPolicy):
        if label:
            policy.label = label
        return policy
    if isinstance(policy, (str, os.PathLike)):
        s = str(policy)
        from cpsim.expert import EXPERTS

        if s.lower() in EXPERTS:
            ego = TeacherEgo(s)
            if label:
                ego.label = label
            return ego
        if s.lower() in EGO_CONTROLLERS:
            ego = ControllerEgo(s)
            if label:
                ego.label = label
            return ego
        model = load_model(s, "policy")
        return ModelEgo(model, label or Path(s).stem, checkpoint=s)
    if hasattr(policy, "predict"):
        return ModelEgo(policy, label or type(policy).__name__, checkpoint=type(policy).__name__)
    if callable(policy):
        return FunctionEgo(policy, label or getattr(policy, "__name__", "callable"))
    raise ValueError(f"policy: expected a checkpoint path, controller or teacher name, SB3 model or callable, "
                     f"got {type(policy).__name__}")


# ============================================================================ dynamics
def _checkpoint_num_actions(path: Path) -> int | None:
    """The discrete action count an SB3 zip records in its ``data`` (None: not recorded)."""
    import json
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            data = json.loads(z.read("data"))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return None
    space = data.get("action_space") if isinstance(data, dict) else None
    n = space.get("n") if isinstance(space, dict) else None
    return int(n) if isinstance(n, (int, np.integer)) and not isinstance(n, bool) else None


def policy_dynamics(model: Any, argument: str = "policy") -> str | None:
    """The dynamics model (``jerk`` or ``classic``) a learned policy acts in, read from the
    size of its discrete action set (:func:`cpsim.config.num_actions`: 12 jerk, 91 classic).

    ``model``: an SB3 model (its ``action_space``), an :class:`EgoPolicy`, a BC model, or a
    checkpoint path (an SB3 zip is read without loading it). None when the policy works
    under either dynamics or does not say: built-in controllers and imitation teachers
    (they read the simulator's dynamics), callables, a BC model with the ``targets`` head
    (converted to the simulator's action set, :func:`adapt_bc_policy`). Raises
    ``ValueError`` naming ``argument`` when the action count matches no dynamics model.
    """
    from cpsim.config import DYNAMICS_MODELS, num_actions

    if isinstance(model, EgoPolicy):
        if model.controller != _POLICY or not isinstance(model, ModelEgo):
            return None
        model = model.model
    n: Any = None
    if isinstance(model, (str, os.PathLike)):
        s = str(model)
        if s.lower() in EGO_CONTROLLERS:
            return None
        from cpsim.expert import EXPERTS

        if s.lower() in EXPERTS:
            return None
        p = Path(resolve_path(s))
        n = _checkpoint_num_actions(p) if p.suffix == ".zip" else None
        if n is None:
            model = load_model(p, argument)
    if n is None:
        from cpalgo.traffic.bc import BCPolicy

        if isinstance(model, BCPolicy):
            if model.head == "targets":
                return None
            n = model.num_actions
        else:
            n = getattr(getattr(model, "action_space", None), "n", None)
    if n is None:
        return None
    table = {num_actions(d): d for d in sorted(DYNAMICS_MODELS)}
    if int(n) not in table:
        known = ", ".join(f"{k} ({d})" for k, d in table.items())
        raise ValueError(f"{argument}: {int(n)} discrete actions match no dynamics model; known: {known}")
    return table[int(n)]


def _describe(dynamics: str) -> str:
    from cpsim.config import num_actions

    return f"{dynamics} dynamics ({num_actions(dynamics)} actions)"


def _choose_dynamics(policies: Sequence[tuple[str, Any]], dynamics: str | None = None,
                     source: str = "dynamics") -> tuple[str, str | None]:
    """(dynamics, what decided it: an argument name, or None for the default)."""
    from cpsim.config import DYNAMICS_MODELS, SimConfig

    if dynamics is not None and dynamics not in DYNAMICS_MODELS:
        raise ValueError(f"{source}: unknown dynamics model {dynamics!r}; accepted: {sorted(DYNAMICS_MODELS)}")
    chosen, by = dynamics, (source if dynamics is not None else None)
    for argument, model in policies:
        if model is None:
            continue
        d = policy_dynamics(model, argument)
        if d is None:
            continue
        if chosen is None:
            chosen, by = d, argument
        elif d != chosen:
            raise ValueError(f"{argument}: acts in {_describe(d)}, but {by} gives {_describe(chosen)}; every "
                             "learned policy of one evaluation (ego policies, traffic policy, PPO co-player) "
                             "must use the same dynamics")
    return (chosen, by) if chosen is not None else (SimConfig().dynamics, None)


def resolve_dynamics(policies: Sequence[tuple[str, Any]], dynamics: str | None = None,
                     source: str = "dynamics") -> str:
    """The one dynamics model of an evaluation.

    ``policies``: ``(argument name, policy)`` pairs (anything :func:`policy_dynamics`
    reads; None entries are skipped). ``dynamics``: an explicit choice (named ``source``
    in messages) the policies must agree with. Without either, the simulator's default
    (``SimConfig().dynamics``, jerk). Raises ``ValueError`` naming the argument and both
    dynamics models when two disagree.
    """
    return _choose_dynamics(policies, dynamics, source)[0]


def adapt_bc_policy(model: Any, dynamics: str, dt: float = 0.1, argument: str = "bc_policy") -> Any:
    """A BC traffic model for a simulator of ``dynamics`` (step ``dt``).

    A ``targets``-head :class:`~cpalgo.traffic.bc.BCPolicy` regresses target accelerations,
    so it drives under either dynamics: a copy that converts them with that dynamics' rule
    (:func:`~cpalgo.traffic.bc.targets_to_logits`) is returned when the model was saved for
    another. An ``actions``-head model classifies over its own action set: ``ValueError``
    naming ``argument`` when that set is another dynamics'. Anything else is returned as is.
    """
    from cpalgo.traffic.bc import BCPolicy
    from cpsim.config import num_actions

    if not isinstance(model, BCPolicy):
        return model
    if model.head == "targets":
        if model.dynamics == dynamics and model.dt == float(dt):
            return model
        return model.for_dynamics(dynamics, dt)
    if model.num_actions != num_actions(dynamics):
        raise ValueError(f"{argument}: the BC model has an 'actions' head over {model.num_actions} actions "
                         f"({model.dynamics} dynamics) and cannot drive a simulator of {_describe(dynamics)}; "
                         "only a 'targets'-head model (the shipped zoo/bc_traffic.pt) converts to another dynamics")
    return model


def _policy_name(policy: Any) -> str:
    """How messages name an ego policy: its checkpoint or label, a path, or its type."""
    if isinstance(policy, EgoPolicy):
        return policy.checkpoint or policy.label
    if isinstance(policy, (str, os.PathLike)):
        return str(policy)
    return getattr(policy, "__name__", type(policy).__name__)


def _obs_size_of(model: Any) -> int | None:
    shape = getattr(getattr(model, "observation_space", None), "shape", None)
    return int(np.prod(shape)) if shape else getattr(model, "obs_size", None)


def check_obs_size(model: Any, expected: int, argument: str) -> None:
    """Raise ``ValueError`` when a model's observation size differs from the simulator's."""
    size = model.obs_size if isinstance(model, EgoPolicy) else _obs_size_of(model)
    if size is not None and int(size) != int(expected):
        raise ValueError(f"{argument}: observation size {size} does not match the simulator's {expected} "
                         "(checkpoint trained with another observation layout)")


# ============================================================================ results
@dataclasses.dataclass
class EvalResult:
    """All task-regime outcomes of one policy checkpoint.

    Attributes:
        label: policy name (table row); results sharing a label are checkpoints of one policy.
        checkpoint: path or description.
        columns: per task-regime arrays (n,): ``split``, ``regime``, ``scenario_id`` (str);
            ``task``, ``ego``, ``steps_alive``, ``goal_step`` and ``collision_step`` (step
            count at the event, -1: none), ``collision_partner`` (slot, -1: none),
            ``co_player_harm``, ``outcome_class`` (int); ``goal``, ``at_fault_collision``,
            ``non_at_fault_collision``, ``offroad``, ``timeout`` (bool); ``comfort``,
            ``lane_align``, ``lane_center`` ([0, 1]) and ``score`` (0-100) (float).
        trajectories: row -> recorded episode (``xy`` (A, T+1, 2) m, ``heading`` (A, T+1)
            rad, ``speed`` (A, T+1) m/s, ``velocity`` (A, T+1, 2) m/s, ``alive`` (A, T+1);
            index k = state after k steps;
            ``sizes`` (A, 2), ``outcome`` (A,) simulator codes, ``goal_xy`` (2,) the ego's
            goal) for the rows asked for with ``record``.
        meta: run settings (deploy condition, timings, ...).
    """

    label: str
    checkpoint: str
    columns: dict[str, np.ndarray]
    trajectories: dict[int, dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def num_rows(self) -> int:
        return int(self.columns["score"].shape[0])

    def summary(self) -> dict[str, dict[str, dict[str, float]]]:
        """``{split: {regime: metrics.summarize(...)}}`` plus ``"mean"`` over regimes per split."""
        out: dict[str, dict[str, dict[str, float]]] = {}
        c = self.columns
        for split in dict.fromkeys(c["split"].tolist()):
            per: dict[str, dict[str, float]] = {}
            for regime in dict.fromkeys(c["regime"].tolist()):
                m = (c["split"] == split) & (c["regime"] == regime)
                if m.any():
                    per[regime] = M.summarize({k: v[m] for k, v in c.items()})
            keys = [k for k in next(iter(per.values())) if k != "n"]
            per["mean"] = {k: float(np.mean([v[k] for v in per.values()])) for k in keys}
            out[split] = per
        return out


# ============================================================================ evaluator


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Settings of an evaluation run (frozen; unknown keys rejected by :meth:`from_dict`).

    Attributes:
        deploy_condition: the ego's condition: profile name (``normal``, ``halfway`` =
            normal-aggressive, ...) or an explicit raw 10-vector. It sets the style fields
            only; the task fields and the goal test are the evaluation criterion's
            (:data:`cpsim.config.EVAL_GOAL`, 2 m, no effective speed limit).
        max_worlds: worlds per simulator chunk (task-regimes evaluated at once).
        max_agents: agent slots per world (None: the most agents present at t0 in any task,
            capped at :data:`MAX_EVAL_AGENTS` = 128, BehaviorBench's limit; slots go to the
            ego, then controllable vehicles, then the other agents by distance to the ego).
        coplayers: who follows the traffic regime (``cpsim.envs.regimes.COPLAYER_RULES``):
            ``vehicles`` (default, BehaviorBench's rule: every vehicle present at t0 except
            the ego, parked ones included) or ``controllable`` (vehicles present at t0 whose
            goal is >= 2 m away, PufferDrive's controlled agents; parked vehicles replay their
            logs; the rule of the earliest tables). A parked vehicle has
            no task, so the simulator never scores it as arrived (its start lies inside the
            2 m radius): under ``vehicles`` it stays in the scene and drives (or stays put)
            as its regime decides.
        seed: simulator seed and mix-regime draw.
        device: simulator device (``cpu`` or ``cuda``).
        progress: show a progress bar over task-regimes.
        record: rows whose full episodes are kept for figures (None: none).
        torch_threads: torch intra-op threads while a run lasts (restored afterwards; None
            leaves torch alone). Inference batches here are small, and on a shared CPU
            several threads per forward pass contend badly: 1 thread measured 5-10x faster
            on the 2-core test machine.
    """

    deploy_condition: str | tuple[float, ...] = "normal"
    max_worlds: int = 256
    max_agents: int | None = None
    coplayers: str = "vehicles"
    seed: int = 0
    device: str = "cpu"
    progress: bool = True
    record: tuple[int, ...] | None = None
    torch_threads: int | None = 1

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "EvalConfig":
        return cls(**known_fields(cls, d, "EvalConfig"))

    def __post_init__(self) -> None:
        if self.max_worlds < 1:
            raise ValueError(f"max_worlds: must be >= 1, got {self.max_worlds}")
        if self.max_agents is not None and self.max_agents < 1:
            raise ValueError(f"max_agents: must be >= 1, got {self.max_agents}")
        if self.torch_threads is not None and self.torch_threads < 1:
            raise ValueError(f"torch_threads: must be >= 1 or None, got {self.torch_threads}")
        from cpsim.envs.regimes import COPLAYER_RULES

        if self.coplayers not in COPLAYER_RULES:
            raise ValueError(f"coplayers: must be one of {list(COPLAYER_RULES)}, got {self.coplayers!r}")


class Evaluator:
    """Holds one simulator over a task set; evaluates any number of policies on it.

    Args:
        tasks: from :func:`make_tasks` (or any list of :class:`Task`).
        regimes: regime names (:data:`REGIMES` by default).
        traffic_policy: model (or checkpoint path) driving co-players in ``aggressive``,
            ``normal``, ``cautious`` and ``mix`` (and ``selfplay`` when there is no PPO
            policy); needed only for those.
        ppo_policy: model or checkpoint path for ``selfplay``, driven under the normal
            profile (default: the :data:`DEFAULT_PPO_PATHS` file of the evaluation's dynamics
            when it exists; otherwise ``traffic_policy`` under p_train conditions,
            recorded in :attr:`notes` and each result's ``meta``, with one warning line).
        bc_policy: model or ``.pt`` path for ``bc`` (default :data:`DEFAULT_BC_PATH`); a
            ``targets``-head model drives under the evaluation's dynamics
            (:func:`adapt_bc_policy`).
        config: :class:`EvalConfig`; ``sim_config``: a ``cpsim.SimConfig`` or mapping.
        policies: the ego policies this evaluator will :meth:`run` (anything
            :func:`as_ego_policy` takes; a mapping names them ``{argument: policy}``), read
            only to choose the dynamics.
        dynamics: ``jerk`` or ``classic``; with ``sim_config``'s ``dynamics`` (a mapping's
            key or a ``SimConfig``), an explicit choice the policies must agree with.

    Dynamics: the simulator acts in the dynamics model of the learned policies given (ego
    ``policies``, ``traffic_policy``, ``ppo_policy``), read from the size of their discrete
    action sets (:func:`policy_dynamics`); they and an explicit choice must all agree
    (``ValueError`` naming the argument and both dynamics). Without any, the default
    co-player checkpoints decide, and without those the simulator's default (jerk). Built-in controllers and teachers drive under either. :attr:`dynamics`
    holds the choice, :attr:`dynamics_source` what made it.
    """

    def __init__(self, tasks: Sequence[Task], regimes: Sequence[str] = REGIMES, *,
                 traffic_policy: Any = None, bc_policy: Any = None, ppo_policy: Any = None,
                 config: EvalConfig | None = None, sim_config: Any = None,
                 policies: Sequence[Any] | Mapping[str, Any] = (), dynamics: str | None = None):
        from cpsim.config import SimConfig

        self.config = config or EvalConfig()
        self.tasks = list(tasks)
        if not self.tasks:
            raise ValueError("tasks: empty; nothing to evaluate")
        self.regimes = [resolve_regime(r) for r in ((regimes,) if isinstance(regimes, str) else regimes)]
        if not self.regimes:
            raise ValueError("regimes: empty; give at least one regime")
        if len(set(self.regimes)) != len(self.regimes):
            raise ValueError(f"regimes: duplicates in {list(regimes)}")
        self.deploy = deployment_condition(
            self.config.deploy_condition if isinstance(self.config.deploy_condition, str)
            else np.asarray(self.config.deploy_condition, np.float32), "deploy_condition")
        base = SimConfig.from_dict(sim_config)
        explicit, source = dynamics, "dynamics"
        if isinstance(sim_config, SimConfig) or (isinstance(sim_config, Mapping) and "dynamics" in sim_config):
            if dynamics is not None and dynamics != base.dynamics:
                raise ValueError(f"dynamics: {dynamics!r} disagrees with sim_config.dynamics {base.dynamics!r}")
            explicit, source = base.dynamics, "sim_config.dynamics"
        # the learned policies given: their action sets choose the dynamics
        if "selfplay" in self.regimes and isinstance(ppo_policy, (str, os.PathLike)):
            ppo_policy = load_model(ppo_policy, "ppo_policy")
        if isinstance(traffic_policy, (str, os.PathLike)):
            traffic_policy = load_model(traffic_policy, "traffic_policy")
        named = list(policies.items()) if isinstance(policies, Mapping) else [
            (f"policy {_policy_name(p)!r}", p) for p in policies]
        given = [*named, ("traffic_policy", traffic_policy)]
        if "selfplay" in self.regimes:
            given.append(("ppo_policy", ppo_policy))
        self.dynamics, self.dynamics_source = _choose_dynamics(given, explicit, source)
        #: what this evaluation does other than asked (e.g. the selfplay co-player fallback)
        self.notes: dict[str, str] = {}
        needs_traffic = {"aggressive", "normal", "cautious", "mix"} & set(self.regimes)
        #: the default co-player files this evaluation loaded (argument -> path)
        self.default_paths: dict[str, Path] = {}
        if self.dynamics_source is None and (needs_traffic or "selfplay" in self.regimes):
            # nothing learned decides: the first shipped anchor does, whichever co-players follow
            first = next(((d, p) for d, p in DEFAULT_TRAFFIC_PATHS.items() if p.is_file()), None)
            if first is not None:
                self.dynamics, self.dynamics_source = first[0], f"the default traffic_policy {first[1].name}"
        if needs_traffic and traffic_policy is None:
            traffic_policy = self._default_coplayer(DEFAULT_TRAFFIC_PATHS, "traffic_policy", needs_traffic)
        if "selfplay" in self.regimes and ppo_policy is None:
            path = self._default_path(DEFAULT_PPO_PATHS)
            default = load_model(path, "ppo_policy") if path is not None else None
            if default is not None and self._agrees(default, "ppo_policy", path):
                ppo_policy, self.default_paths["ppo_policy"] = default, path
            else:
                found = (f"the default PPO co-player {path.name} acts in "
                         f"{_describe(policy_dynamics(default, 'ppo_policy'))}" if default is not None
                         else "no PPO co-player ships for it")
                self.notes["selfplay"] = (
                    f"this evaluation acts in {self.dynamics} and {found}: "
                    "'selfplay' co-players are the traffic policy under p_train conditions instead "
                    f"(give a {self.dynamics} --ppo-policy / ppo_policy for the PPO column)")
                print(f"warning: {self.notes['selfplay']}", file=sys.stderr)
        self.ppo_policy = ppo_policy
        if "selfplay" in self.regimes and ppo_policy is None:
            needs_traffic.add("selfplay")
            if traffic_policy is None:
                traffic_policy = self._default_coplayer(DEFAULT_TRAFFIC_PATHS, "traffic_policy", needs_traffic)
        if needs_traffic and traffic_policy is None:
            raise ValueError(f"traffic_policy: regimes {sorted(needs_traffic)} need a co-player policy "
                             "(the self-play / conditioned anchor checkpoint)")
        self.traffic_policy = traffic_policy
        sim_cfg = base.replace(dynamics=self.dynamics, goal_criterion="evaluation")
        if "bc" in self.regimes:
            if bc_policy is None:
                if not DEFAULT_BC_PATH.is_file():
                    raise ValueError(f"bc_policy: regime 'bc' needs a behaviour-cloning model; "
                                     f"none given and {DEFAULT_BC_PATH} is missing (python -m cpalgo.traffic)")
                bc_policy = DEFAULT_BC_PATH
            if isinstance(bc_policy, (str, os.PathLike)):
                bc_policy = load_model(bc_policy, "bc_policy")
            bc_policy = adapt_bc_policy(bc_policy, self.dynamics, sim_cfg.dt, "bc_policy")
        self.bc_policy = bc_policy

        import cpsim

        # unique (scenario id, ego) -> simulator pool: WOMD gives several tasks (egos) per
        # scene, and the simulator puts the scenario's ego_index in slot 0
        self.scenarios: list[Any] = []
        index: dict[tuple[str, int], int] = {}
        for t in self.tasks:
            if (t.scenario_id, t.ego) not in index:
                index[(t.scenario_id, t.ego)] = len(self.scenarios)
                self.scenarios.append(t.scenario)
        self.scenario_index = {k: v for k, v in index.items()}
        max_agents = self.config.max_agents or min(
            MAX_EVAL_AGENTS, max(max(int(s.log_valid[:, 0].sum()) for s in self.scenarios), 1))
        n_items = len(self.tasks) * len(self.regimes)
        self.num_worlds = int(min(self.config.max_worlds, n_items))
        # one goal test for every deployment condition and every agent (DESIGN.md,
        # "Evaluation goal criterion"): 2 m, no effective speed limit
        self.sim = cpsim.Simulator(self.scenarios, num_worlds=self.num_worlds, max_agents=max_agents,
                                   device=self.config.device, seed=self.config.seed, config=sim_cfg)
        self.obs_size = int(self.sim.obs_layout.size)
        for model, arg in ((self.traffic_policy, "traffic_policy"), (self.bc_policy, "bc_policy"),
                           (self.ppo_policy, "ppo_policy")):
            if model is not None:
                check_obs_size(model, self.obs_size, arg)
        # per-scenario vehicle table (co-player harm counts vehicles only)
        n_max = max(s.num_agents for s in self.scenarios)
        self._vehicle = np.zeros((len(self.scenarios), n_max + 1), bool)
        for s, sc in enumerate(self.scenarios):
            self._vehicle[s, :sc.num_agents] = sc.agent_types == _VEHICLE
        self._drivers = self._make_drivers()
        # item layout: rows ordered split -> regime -> task (tables group this way)
        self.items = self._layout()

    # ---------------------------------------------------------------- defaults
    def _agrees(self, model: Any, argument: str, path: Path) -> bool:
        """Whether a default co-player acts in the evaluation's dynamics. When no policy or
        explicit choice has decided them yet, the default decides."""
        d = policy_dynamics(model, argument)
        if d is None or d == self.dynamics:
            return True
        if self.dynamics_source is None:
            self.dynamics, self.dynamics_source = d, f"the default {argument} {path.name}"
            return True
        return False

    def _default_path(self, defaults: Mapping[str, Path]) -> Path | None:
        """The default file for the evaluation's dynamics (None when missing); while nothing
        has decided the dynamics, the first default file that exists."""
        if self.dynamics_source is not None:
            path = defaults.get(self.dynamics)
            return path if path is not None and path.is_file() else None
        return next((p for p in defaults.values() if p.is_file()), None)

    def _default_coplayer(self, defaults: Mapping[str, Path], argument: str, regimes: set[str]) -> Any:
        """The default traffic policy for the evaluation's dynamics (None when missing);
        ``ValueError`` when it acts in other dynamics than the evaluation's."""
        path = self._default_path(defaults)
        if path is None:
            return None
        model = load_model(path, argument)
        self.default_paths[argument] = path
        if not self._agrees(model, argument, path):
            raise ValueError(f"{argument}: regimes {sorted(regimes)} need a co-player policy; the default "
                             f"{path.name} acts in {_describe(policy_dynamics(model, argument))}, but "
                             f"{self.dynamics_source} gives {_describe(self.dynamics)}: give a "
                             f"{self.dynamics} traffic policy (--traffic-policy)")
        return model

    # ---------------------------------------------------------------- layout
    def _make_drivers(self) -> dict[str, Any]:
        from cpsim.envs.regimes import TrafficDriver

        drivers = {}
        rule = self.config.coplayers
        for i, regime in enumerate(self.regimes):
            seed = self.config.seed + i
            if regime == "bc":
                drv = TrafficDriver("policy", self.bc_policy, condition="normal", seed=seed, coplayers=rule)
            elif regime == "selfplay" and self.ppo_policy is not None:
                drv = TrafficDriver("policy", self.ppo_policy, condition="normal", seed=seed, coplayers=rule)
            elif regime == "selfplay":
                drv = TrafficDriver("policy", self.traffic_policy, seed=seed, coplayers=rule)
            elif regime in ("aggressive", "normal", "cautious", "mix"):
                drv = TrafficDriver(regime, self.traffic_policy, seed=seed, coplayers=rule)
            else:
                drv = TrafficDriver(regime, None, seed=seed, coplayers=rule)
            drivers[regime] = drv
        return drivers

    def _layout(self) -> dict[str, np.ndarray]:
        splits = list(dict.fromkeys(t.split for t in self.tasks))
        rows = [(t, r) for s in splits for r in self.regimes for t in self.tasks if t.split == s]
        return {
            "task": np.array([t.index for t, _ in rows], np.int64),
            "split": np.array([t.split for t, _ in rows]),
            "regime": np.array([r for _, r in rows]),
            "scenario_id": np.array([t.scenario_id for t, _ in rows]),
            "ego": np.array([t.ego for t, _ in rows], np.int64),
            "scenario": np.array([self.scenario_index[(t.scenario_id, t.ego)] for t, _ in rows], np.int64),
        }

    @property
    def num_rows(self) -> int:
        return int(self.items["task"].shape[0])

    # ---------------------------------------------------------------- run
    def run(self, policy: Any, label: str | None = None) -> EvalResult:
        """Evaluate one policy on every task-regime; returns its :class:`EvalResult`."""
        ego = as_ego_policy(policy, label)
        if ego.controller == _POLICY:
            name = f"policy {ego.checkpoint or ego.label!r}"
            check_obs_size(ego, self.obs_size, name)
            d = policy_dynamics(ego, name)
            if d is not None and d != self.dynamics:
                by = f" (from {self.dynamics_source})" if self.dynamics_source else " (the default)"
                raise ValueError(f"{name}: acts in {_describe(d)}, but this evaluator's simulator uses "
                                 f"{_describe(self.dynamics)}{by}; give the policy to Evaluator(policies=...) "
                                 f"or build it with dynamics={d!r}")
            if isinstance(ego, ModelEgo):  # a BC model as the ego: the simulator's action set
                model = adapt_bc_policy(ego.model, self.dynamics, float(self.sim.config.dt), name)
                if model is not ego.model:
                    ego = ModelEgo(model, ego.label, ego.checkpoint)
        cfg = self.config
        n = self.num_rows
        W = self.num_worlds
        out = _empty_columns(n)
        record = set(cfg.record or ())
        trajectories: dict[int, dict[str, np.ndarray]] = {}
        bar = _progress(n, cfg.progress, ego.label)
        threads = None
        if cfg.torch_threads is not None:
            import torch

            threads = torch.get_num_threads()
            torch.set_num_threads(cfg.torch_threads)
        t0 = time.perf_counter()
        steps = 0
        try:
            for start in range(0, n, W):
                rows = np.arange(start, min(start + W, n))
                chunk_steps, traj = self._run_chunk(ego, rows, record)
                steps += chunk_steps
                self._collect(rows, out)
                trajectories.update(traj)
                bar.update(rows.size)
        finally:
            bar.close()
            if threads is not None:
                import torch

                torch.set_num_threads(threads)
        elapsed = time.perf_counter() - t0
        cols = {k: self.items[k].copy() for k in ("split", "regime", "task", "scenario_id", "ego")}
        cols.update(out)
        meta = {"deploy_condition": self.deploy.tolist(), "regimes": list(self.regimes),
                "seconds": elapsed, "task_regimes_per_second": n / max(elapsed, 1e-9),
                "simulator_steps": steps, "num_worlds": W, "max_agents": int(self.sim.max_agents),
                "dynamics": self.dynamics, **({"notes": dict(self.notes)} if self.notes else {})}
        return EvalResult(ego.label, ego.checkpoint, cols, trajectories, meta)

    def _run_chunk(self, ego: EgoPolicy, rows: np.ndarray, record: set[int]
                   ) -> tuple[int, dict[int, dict[str, np.ndarray]]]:
        sim = self.sim
        W, A = self.num_worlds, int(sim.max_agents)
        k = rows.size
        # pad a short last chunk by repeating its first row (results of padded worlds are ignored)
        world_rows = np.concatenate([rows, np.full(W - k, rows[0], np.int64)])
        sim.reset(scenario_index=self.items["scenario"][world_rows])
        # ego slot: its controller and the deployment condition; co-players: per regime
        ctrl = _np(sim.controllers).astype(np.int32).copy()
        ctrl[:, 0] = ego.controller
        sim.set_controllers(ctrl)
        cond = _np(sim.conditions).astype(np.float32).copy()
        cond[:, 0] = self.deploy
        sim.set_conditions(cond)
        regimes = self.items["regime"][world_rows]
        active = []
        for regime, drv in self._drivers.items():
            worlds = np.flatnonzero(regimes == regime)
            if worlds.size:
                drv.assign(sim, worlds)
                active.append(drv)
        ego.reset(W)
        ego.bind(sim)
        episode_start = np.ones(W, bool)
        keep = [i for i, r in enumerate(world_rows[:k]) if int(r) in record]
        rec: dict[str, list[np.ndarray]] = {"xy": [], "heading": [], "alive": [], "speed": [], "velocity": []}
        horizon = int(sim.config.episode_steps)
        actions = np.zeros((W, A), np.int64)
        steps = 0
        for _ in range(horizon):
            if keep:
                self._record(rec, keep)
            actions[:] = 0
            if ego.controller == _POLICY:
                obs = _np(sim.obs)
                actions[:, 0] = ego.act(np.ascontiguousarray(obs[:, 0], np.float32), episode_start)
                episode_start[:] = False
            else:
                obs = None
            for drv in active:
                drv.act(obs, out=actions)
            sim.step(actions)
            steps += 1
            if bool(_np(sim.step_count).min() >= horizon):
                break
        traj: dict[int, dict[str, np.ndarray]] = {}
        if keep:
            self._record(rec, keep)
            sizes, goal = self._slot_sizes_goals(keep)
            outcome = _np(sim.outcome)
            for j, w in enumerate(keep):
                traj[int(world_rows[w])] = {
                    "xy": np.stack([x[j] for x in rec["xy"]], 1),
                    "heading": np.stack([x[j] for x in rec["heading"]], 1),
                    "alive": np.stack([x[j] for x in rec["alive"]], 1),
                    "speed": np.stack([x[j] for x in rec["speed"]], 1),
                    "velocity": np.stack([x[j] for x in rec["velocity"]], 1),
                    "sizes": sizes[j], "goal_xy": goal[j], "outcome": outcome[w].copy(),
                }
        return steps, traj

    def _record(self, rec: dict[str, list[np.ndarray]], worlds: list[int]) -> None:
        sim = self.sim
        rec["xy"].append(_np(sim.xy)[worlds].copy())
        rec["heading"].append(_np(sim.heading)[worlds].copy())
        rec["alive"].append(_np(sim.alive)[worlds].copy())
        rec["speed"].append(_np(sim.speed)[worlds].copy())
        rec["velocity"].append(_np(sim.velocity)[worlds].copy())

    def _slot_sizes_goals(self, worlds: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """(len(worlds), A, 2) box sizes of each slot and (len(worlds), 2) ego goals."""
        agent_index = _np(self.sim.agent_index)[worlds]
        scen = _np(self.sim.world_scenario)[worlds]
        sizes = np.zeros((len(worlds), agent_index.shape[1], 2), np.float32)
        goals = np.zeros((len(worlds), 2), np.float32)
        for j in range(len(worlds)):  # figures only, a handful of worlds
            sc = self.scenarios[int(scen[j])]
            ok = agent_index[j] >= 0
            sizes[j, ok] = sc.sizes[agent_index[j, ok]]
            goals[j] = sc.goal_xy[sc.ego_index]
        return sizes, goals

    def _collect(self, rows: np.ndarray, out: dict[str, np.ndarray]) -> None:
        """Read the ego's outcome and metric accumulators of the chunk into ``out[rows]``."""
        sim = self.sim
        k = rows.size
        met = {name: _np(v)[:k] for name, v in sim.metrics.items()}
        # events from the accumulators (an ego not removed by its first event may reach its
        # goal and collide later; the score and the outcome class must see both)
        ep = M.episode_scores({name: v[:, 0] for name, v in met.items()})
        goal, collision, offroad = ep["goal"], ep["collision"], ep["offroad"]
        fault = ep["at_fault_collision"]
        # co-player harm: other vehicles that collided or went off-road during the episode
        agent_index = _np(sim.agent_index)[:k]
        scen = _np(sim.world_scenario)[:k]
        vehicle = self._vehicle[scen[:, None], agent_index] & (agent_index >= 0)
        harmed = (met["first_collision_step"] >= 0) | (met["first_offroad_step"] >= 0)
        harmed[:, 0] = False
        out["goal"][rows] = goal
        out["at_fault_collision"][rows] = fault
        out["non_at_fault_collision"][rows] = collision & ~fault
        out["offroad"][rows] = offroad
        for key in ("timeout", "comfort", "lane_align", "lane_center", "score"):
            out[key][rows] = ep[key]
        out["co_player_harm"][rows] = (harmed & vehicle).sum(1)
        out["steps_alive"][rows] = met["steps_alive"][:, 0]
        out["goal_step"][rows] = met["goal_step"][:, 0]
        out["collision_step"][rows] = met["first_collision_step"][:, 0]
        out["collision_partner"][rows] = met["collision_partner"][:, 0]
        out["outcome_class"][rows] = M.outcome_class(goal, fault, collision & ~fault, offroad)


def _empty_columns(n: int) -> dict[str, np.ndarray]:
    return {
        "goal": np.zeros(n, bool), "at_fault_collision": np.zeros(n, bool),
        "non_at_fault_collision": np.zeros(n, bool), "offroad": np.zeros(n, bool),
        "timeout": np.zeros(n, bool), "comfort": np.zeros(n), "lane_align": np.zeros(n),
        "lane_center": np.zeros(n), "score": np.zeros(n), "co_player_harm": np.zeros(n, np.int64),
        "steps_alive": np.zeros(n, np.int64), "goal_step": np.full(n, -1, np.int64),
        "collision_step": np.full(n, -1, np.int64), "collision_partner": np.full(n, -1, np.int64),
        "outcome_class": np.zeros(n, np.int8),
    }


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, enabled: bool, label: str) -> Any:
    if not enabled:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=f"evaluate {label}", unit="task-regime", leave=False)


# ============================================================================ convenience
def evaluate(policy: Any, tasks: Sequence[Task], regimes: Sequence[str] = REGIMES,
             deploy_condition: str | Sequence[float] = "normal", *, traffic_policy: Any = None,
             bc_policy: Any = None, ppo_policy: Any = None, label: str | None = None,
             dynamics: str | None = None, sim_config: Any = None, **config: Any) -> EvalResult:
    """Evaluate one policy on ``tasks`` x ``regimes`` (see :class:`Evaluator`).

    ``policy``: checkpoint path, SB3 model, callable or built-in controller name
    (``replay``/``expert``, ``idm``). The simulator's dynamics follow the learned policies
    (``dynamics`` / ``sim_config``: an explicit choice they must agree with). Extra keyword
    arguments go to :class:`EvalConfig`.
    """
    dc = deploy_condition if isinstance(deploy_condition, str) else tuple(float(x) for x in deploy_condition)
    cfg = EvalConfig.from_dict({"deploy_condition": dc, **config})
    ego = as_ego_policy(policy, label)
    ev = Evaluator(tasks, regimes, traffic_policy=traffic_policy, bc_policy=bc_policy, ppo_policy=ppo_policy,
                   config=cfg, policies=[ego], dynamics=dynamics, sim_config=sim_config)
    return ev.run(ego)


def evaluate_checkpoints(policies: Sequence[Any], tasks: Sequence[Task], regimes: Sequence[str] = REGIMES,
                         deploy_condition: str | Sequence[float] = "normal", *, labels: Sequence[str] | None = None,
                         traffic_policy: Any = None, bc_policy: Any = None, ppo_policy: Any = None,
                         dynamics: str | None = None, sim_config: Any = None, **config: Any) -> list[EvalResult]:
    """Evaluate several policies / checkpoints on the same task-regimes (one simulator,
    in the dynamics of the learned policies, which must agree).

    Checkpoints that share a label are aggregated as seeds of one policy by
    :func:`cpalgo.evaluate.tables.summarize_results` (mean and std).
    """
    dc = deploy_condition if isinstance(deploy_condition, str) else tuple(float(x) for x in deploy_condition)
    cfg = EvalConfig.from_dict({"deploy_condition": dc, **config})
    egos = [as_ego_policy(p, labels[i] if labels else None) for i, p in enumerate(policies)]
    ev = Evaluator(tasks, regimes, traffic_policy=traffic_policy, bc_policy=bc_policy, ppo_policy=ppo_policy,
                   config=cfg, policies=egos, dynamics=dynamics, sim_config=sim_config)
    for e in egos:  # fail before any run when a checkpoint does not fit the simulator
        if e.controller == _POLICY:
            check_obs_size(e, ev.obs_size, f"policy {e.checkpoint or e.label!r}")
    return [ev.run(e) for e in egos]
