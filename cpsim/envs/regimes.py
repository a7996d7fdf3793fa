"""Traffic regimes: who drives the co-players (every agent slot except the ego).

Shared by :class:`cpsim.envs.drive.DriveEnv` and the BehaviorBench-style evaluation.
Everything is batched over worlds: :meth:`TrafficDriver.assign` sets controllers and
conditions for the co-players of any subset of worlds of a :class:`cpsim.Simulator`, and
:meth:`TrafficDriver.act` returns actions for every policy-driven co-player of every
world in one model call.

Regimes (:data:`REGIMES`):

========== ======================================================================
replay     co-players follow their logs (``Controller.REPLAY``)
idm        co-players follow their logged route with IDM (``Controller.IDM``)
static     co-players stand still at their t0 pose (``Controller.STATIC``)
policy     co-players are driven by ``model`` (SB3 model, callable or checkpoint) under
           ``condition`` (default: the simulator's own draw at reset)
aggressive ``model`` under the aggressive profile
normal     ``model`` under the normal profile
cautious   ``model`` under the cautious profile
mix        ``model``; the three profiles rotate over the co-players (BehaviorBench): the
           k-th co-player of a world in slot order gets aggressive / normal / cautious
           for k % 3 = 0 / 1 / 2 (deterministic per agent, no random draw)
========== ======================================================================

Aliases (:data:`REGIME_ALIASES`): ``expert`` = replay; ``log-imitation`` and
``self-play`` = policy (the evaluation passes the matching model).

Which agents are co-players is the driver's ``coplayers`` rule (:data:`COPLAYER_RULES`):

* ``controllable`` (default; training): the *controllable* agents of a world (vehicles
  valid at t0 with a goal >= 2 m away, :attr:`Scenario.controllable`, PufferDrive's
  controlled agents) other than the ego slot;
* ``vehicles`` (BehaviorBench's rule; the evaluator's default): every vehicle present at t0
  other than the ego slot, parked ones included. A parked vehicle has no task, so the
  simulator never scores it as arrived and it stays in the scene.

The remaining agents (pedestrians, cyclists, and under ``controllable`` the parked
vehicles) keep the simulator's default controller (log replay). Agents that appear after
t0 have no slot.
"""

from __future__ import annotations

import os
from typing import Any, Callable, Sequence

import numpy as np

from cpsim.arrays import to_numpy as _to_numpy
from cpsim.conditions import NUM_CONDITION_FIELDS, profile, resolve_condition

REGIMES: tuple[str, ...] = ("replay", "idm", "static", "policy", "aggressive", "normal", "cautious", "mix")
REGIME_ALIASES: dict[str, str] = {"expert": "replay", "log-imitation": "policy", "self-play": "policy"}
#: regimes whose co-players are POLICY agents and need a model
POLICY_REGIMES: tuple[str, ...] = ("policy", "aggressive", "normal", "cautious", "mix")
MIX_PROFILES: tuple[str, ...] = ("aggressive", "normal", "cautious")
#: Who the co-players are (see the module docstring).
COPLAYER_RULES: tuple[str, ...] = ("controllable", "vehicles")

# cpsim.config.Controller values (contract in docs/ARCHITECTURE.md)
_POLICY, _REPLAY, _IDM, _STATIC = 0, 1, 2, 3
_FIXED_CONTROLLER = {"replay": _REPLAY, "idm": _IDM, "static": _STATIC}

#: A co-player model that is not an SB3 model: (n, D) float32 observations -> (n,) actions.
CoplayerFn = Callable[[np.ndarray], np.ndarray]


def resolve_regime(name: str) -> str:
    """Canonical regime name; raises ``ValueError`` listing the accepted names."""
    if not isinstance(name, str):
        raise ValueError(f"regime must be a string, got {type(name).__name__}")
    key = REGIME_ALIASES.get(name, name)
    if key not in REGIMES:
        raise ValueError(
            f"unknown regime {name!r}; accepted: {list(REGIMES) + sorted(REGIME_ALIASES)}"
        )
    return key


#: SB3 algorithms :func:`load_policy` tries, in order (``module:Class``).
POLICY_LOADERS: tuple[str, ...] = ("sb3_contrib:RecurrentPPO", "stable_baselines3:PPO", "stable_baselines3:A2C",
                                   "stable_baselines3:DQN")


def load_policy(path: str | os.PathLike, argument: str = "coplayer_model") -> Any:
    """An SB3 checkpoint for the policy regimes, loaded on the CPU by the first of
    :data:`POLICY_LOADERS` that accepts it (a CounterPlay checkpoint loads as RecurrentPPO,
    which acts the same). Raises ``ValueError`` naming ``argument`` and the file otherwise."""
    import importlib

    if not os.path.isfile(path):
        raise ValueError(f"{argument}: no such checkpoint {str(path)!r}")
    errors = []
    for spec in POLICY_LOADERS:
        module, _, name = spec.partition(":")
        cls = getattr(importlib.import_module(module), name)
        try:
            return cls.load(str(path), device="cpu")
        except Exception as exc:  # noqa: BLE001 - try the next algorithm
            errors.append(f"{name}: {type(exc).__name__}: {exc}")
    raise ValueError(f"{argument}: cannot load {str(path)!r} as an SB3 checkpoint ({'; '.join(errors)[:400]})")


def controllable_table(scenarios: Sequence[Any], rule: str = "controllable") -> np.ndarray:
    """(S, N_max + 1) bool: ``table[s, i]`` = agent i of scenario s is a co-player candidate
    under ``rule`` (:data:`COPLAYER_RULES`): controllable, or a vehicle valid at t0
    (``vehicles``). False past N (the last column pads index -1)."""
    if rule not in COPLAYER_RULES:
        raise ValueError(f"coplayers: unknown rule {rule!r}; accepted: {list(COPLAYER_RULES)}")
    from cpsim.scenario.datatypes import AgentType

    n_max = max(sc.num_agents for sc in scenarios)
    table = np.zeros((len(scenarios), n_max + 1), bool)  # last column: padding for index -1
    for s, sc in enumerate(scenarios):  # once per pool, not per step
        if rule == "controllable":
            table[s, : sc.num_agents] = sc.controllable
        else:
            table[s, : sc.num_agents] = (sc.agent_types == AgentType.VEHICLE) & sc.log_valid[:, 0]
    return table


class TrafficDriver:
    """Drives the co-players of a batched simulator under one traffic regime.

    Args:
        regime: one of :data:`REGIMES` (or an alias).
        model: for policy regimes, an SB3 model (anything with
            ``predict(obs, state, episode_start, deterministic)``), a callable
            ``f(obs (n, D) float32) -> (n,) actions``, or the path of an SB3 checkpoint
            (:func:`load_policy`; so YAML files and command lines can name one).
            Ignored (may be None) otherwise.
        condition: ``policy`` regime only: co-players' condition, a profile name or a raw
            10-vector; None keeps the simulator's draw at reset.
        deterministic: passed to ``model.predict``.
        seed: kept for compatibility (``mix`` rotates its profiles deterministically).
        ego_slot: the slot driven by the caller (never a co-player).
        coplayers: who the co-players are (:data:`COPLAYER_RULES`): ``controllable``
            (default) or ``vehicles`` (every vehicle present at t0, BehaviorBench).

    Each co-player slot keeps its own recurrent state (batched as
    ``(layers, W * A, hidden)`` arrays); :meth:`assign` marks the slots of the reset
    worlds as episode starts, so a recurrent model starts them from zero memory.
    """

    def __init__(self, regime: str, model: Any = None, *, condition: str | Sequence[float] | None = None,
                 deterministic: bool = True, seed: int | None = 0, ego_slot: int = 0,
                 coplayers: str = "controllable"):
        self.regime = resolve_regime(regime)
        if coplayers not in COPLAYER_RULES:
            raise ValueError(f"coplayers: unknown rule {coplayers!r}; accepted: {list(COPLAYER_RULES)}")
        self.coplayers = coplayers
        if self.regime in POLICY_REGIMES and isinstance(model, (str, os.PathLike)):
            model = load_policy(model)
        if self.regime in POLICY_REGIMES:
            if model is None:
                raise ValueError(
                    f"regime {regime!r} needs a co-player model (coplayer_model / model); regimes "
                    f"that need none: {sorted(_FIXED_CONTROLLER)}"
                )
            if not (hasattr(model, "predict") or callable(model)):
                raise ValueError("model must be an SB3 model (with .predict) or a callable obs -> actions")
        if condition is not None and self.regime != "policy":
            raise ValueError(f"condition applies to the 'policy' regime only, not {self.regime!r}")
        self.model = model
        self.condition = None if condition is None else resolve_condition(condition, "condition")
        self.deterministic = bool(deterministic)
        self.ego_slot = int(ego_slot)
        self.rng = np.random.default_rng(seed)
        self._sim: Any = None
        self._table: np.ndarray | None = None
        self._coplayer: np.ndarray | None = None      # (W, A) bool
        self._state: Any = None                        # recurrent state over W * A slots
        self._episode_start: np.ndarray | None = None  # (W * A,) bool
        #: (W, A) int8 index into MIX_PROFILES of each co-player under ``mix`` (-1: none), for logs
        self.mix_choice: np.ndarray | None = None

    @property
    def needs_model(self) -> bool:
        return self.regime in POLICY_REGIMES

    def seed(self, seed: int | None) -> None:
        """Reseed the driver's generator (``mix`` no longer draws from it)."""
        self.rng = np.random.default_rng(seed)

    def _bind(self, sim: Any) -> None:
        if self._sim is not sim:
            self._sim = sim
            self._table = controllable_table(sim.scenarios, self.coplayers)
            w, a = sim.num_worlds, sim.max_agents
            self._coplayer = np.zeros((w, a), bool)
            self._episode_start = np.ones(w * a, bool)
            self._state = None
            self.mix_choice = np.full((w, a), -1, np.int8)

    def release(self, worlds: np.ndarray | Sequence[int] | None = None) -> None:
        """Stop driving the co-players of ``worlds`` (default all) until the next assign."""
        if self._coplayer is not None:
            self._coplayer[slice(None) if worlds is None else np.asarray(worlds, np.int64)] = False

    def coplayer_mask(self, sim: Any, worlds: np.ndarray | None = None) -> np.ndarray:
        """(len(worlds), A) bool: slots of co-players (the ``coplayers`` rule), never the ego slot."""
        self._bind(sim)
        worlds = np.arange(sim.num_worlds) if worlds is None else np.asarray(worlds, np.int64)
        agent_index = _to_numpy(sim.agent_index)[worlds]
        scen = _to_numpy(sim.world_scenario)[worlds]
        mask = self._table[scen[:, None], agent_index]  # index -1 hits the padding column (False)
        mask[:, self.ego_slot] = False
        return mask

    def assign(self, sim: Any, worlds: np.ndarray | Sequence[int] | None = None,
               conditions: np.ndarray | None = None) -> np.ndarray:
        """Set co-player controllers (and conditions for policy regimes) of ``worlds``.

        Call right after ``sim.reset(worlds)``. ``conditions`` (len(worlds), A, 10): the
        raw conditions to start from (default: ``sim.conditions`` of those worlds); the
        co-player rows are overwritten and the result is written with
        ``sim.set_conditions``. Returns the (len(worlds), A, 10) conditions written.
        """
        self._bind(sim)
        worlds = np.arange(sim.num_worlds) if worlds is None else np.asarray(worlds, np.int64).reshape(-1)
        co = self.coplayer_mask(sim, worlds)
        # several drivers may share one simulator (one per regime, each owning some worlds):
        # a world reset since its last step belongs to whichever driver assigns it now, so
        # drop freshly reset worlds this driver is not given
        fresh = _to_numpy(sim.step_count) == 0
        fresh[worlds] = False
        self._coplayer[fresh] = False
        self._coplayer[worlds] = co
        ctrl = _to_numpy(sim.controllers)[worlds].astype(np.int32)
        cond = (_to_numpy(sim.conditions)[worlds] if conditions is None
                else np.asarray(conditions, np.float32)).astype(np.float32).copy()
        if cond.shape != (worlds.size, sim.max_agents, NUM_CONDITION_FIELDS):
            raise ValueError(f"conditions: expected shape {(worlds.size, sim.max_agents, NUM_CONDITION_FIELDS)}, "
                             f"got {cond.shape}")
        self.mix_choice[worlds] = -1
        if self.regime in _FIXED_CONTROLLER:
            ctrl[co] = _FIXED_CONTROLLER[self.regime]
        else:
            ctrl[co] = _POLICY
            if self.regime == "mix":
                # rotate the profiles over the co-players of each world, in slot order
                choice = ((np.cumsum(co, axis=1) - 1) % len(MIX_PROFILES)).astype(np.int8)
                table = np.stack([profile(p) for p in MIX_PROFILES])
                cond[co] = table[choice[co]]
                self.mix_choice[worlds] = np.where(co, choice, -1)
            elif self.regime in MIX_PROFILES:
                cond[co] = profile(self.regime)
            elif self.condition is not None:
                cond[co] = self.condition
        sim.set_controllers(ctrl, worlds)
        sim.set_conditions(cond, worlds)
        a = sim.max_agents
        flat = (worlds[:, None] * a + np.arange(a)[None, :]).reshape(-1)
        self._episode_start[flat] = True
        return cond

    def act(self, obs: Any = None, out: np.ndarray | None = None) -> np.ndarray:
        """Actions for every policy-driven co-player still alive, batched over all worlds.

        ``obs``: (W, A, D) observations (default ``sim.obs``); ``out``: optional (W, A)
        integer array to fill (other entries untouched). Returns the (W, A) int64 actions
        (zeros where no co-player acts). Fixed-controller regimes return ``out`` unchanged.
        """
        sim = self._sim
        if sim is None:
            raise RuntimeError("TrafficDriver.act called before assign(sim, worlds)")
        w, a = sim.num_worlds, sim.max_agents
        actions = np.zeros((w, a), np.int64) if out is None else out
        if not self.needs_model:
            return actions
        obs = _to_numpy(sim.obs if obs is None else obs)
        acting = (self._coplayer & _to_numpy(sim.policy_mask)).reshape(-1)
        idx = np.flatnonzero(acting)
        if idx.size == 0:
            return actions
        batch = np.ascontiguousarray(obs.reshape(w * a, -1)[idx], dtype=np.float32)
        if hasattr(self.model, "predict"):
            state = None
            if self._state is not None:
                state = tuple(s[:, idx] for s in self._state)
            act, new_state = self.model.predict(
                batch, state=state, episode_start=self._episode_start[idx], deterministic=self.deterministic
            )
            if new_state is not None:
                if self._state is None:  # first call: allocate per-slot memory
                    self._state = tuple(np.zeros((s.shape[0], w * a, *s.shape[2:]), s.dtype) for s in new_state)
                for full, part in zip(self._state, new_state):
                    full[:, idx] = part
        else:
            act = self.model(batch)
        self._episode_start[idx] = False
        act = np.asarray(_to_numpy(act)).reshape(-1).astype(np.int64)
        if act.size != idx.size:
            raise ValueError(f"model returned {act.size} actions for {idx.size} co-players")
        actions[idx // a, idx % a] = act
        return actions


__all__ = ["REGIMES", "REGIME_ALIASES", "POLICY_REGIMES", "MIX_PROFILES", "COPLAYER_RULES", "TrafficDriver",
           "resolve_regime", "controllable_table", "load_policy", "CoplayerFn"]
