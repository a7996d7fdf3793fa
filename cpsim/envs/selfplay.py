"""SB3 self-play front-end: one VecEnv index per agent slot of a batched Simulator."""

from __future__ import annotations

import functools
import os
from typing import Any, Iterable, Sequence

import gymnasium
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecNormalize
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from cpsim.arrays import to_numpy as _np
from cpsim.conditions import (
    NUM_CONDITION_FIELDS,
    resolve_condition,
    sample_conditions,
    with_eval_task,
    with_panel_share,
)
from cpsim.scoring import episode_scores

OUTCOME_NAMES: tuple[str, ...] = ("running", "goal", "collision", "offroad", "timeout")
CONDITION_MODES = ("train",)
#: procedural scenarios generated when no scenarios are given (``num_scenarios`` overrides)
DEFAULT_POOL_SIZE = 16
#: episode metrics in the info of an agent's last step (:func:`cpsim.scoring.episode_scores`)
_SCORE_KEYS = ("at_fault_collision", "comfort", "lane_align", "lane_center", "score")


@functools.lru_cache(maxsize=8)
def _procedural_pool(n: int, seed: int, family: str | None) -> tuple:
    """Procedural training pool, memoised per process: scenarios are immutable, and vectorised
    wrappers (DummyVecEnv, rl-zoo3) build many envs on the same pool."""
    from cpsim.scenario import train_pool

    return tuple(train_pool(n, seed, families=None if family is None else [family]))


def resolve_scenarios(scenarios: Any = None, *, family: str | None = None, womd_dir: str | None = None,
                      num_scenarios: int | None = None, seed: int = 0) -> list:
    """Scenario list from exactly one source: a list, a procedural family, a WOMD folder
    (``.json``, ``.json.gz`` and ``.npz`` files, via :func:`cpsim.scenario.load_dir`), or
    (none given) the procedural training pool (``train_pool(DEFAULT_POOL_SIZE, seed)``).

    ``num_scenarios`` caps the count (procedural: how many scenarios to generate).
    """
    from cpsim import scenario as scen_mod
    from cpsim.scenario.datatypes import validate_scenarios

    given = [n for n, v in (("scenarios", scenarios), ("family", family), ("womd_dir", womd_dir)) if v is not None]
    if len(given) > 1:
        raise ValueError(f"give only one of scenarios / family / womd_dir, got {given}")
    if num_scenarios is not None and int(num_scenarios) < 1:
        raise ValueError(f"num_scenarios must be >= 1, got {num_scenarios}")
    if scenarios is not None:
        out = validate_scenarios(scenarios, needs="a pool")
    elif family is not None:
        families = tuple(scen_mod.FAMILIES)
        if family not in families:
            raise ValueError(f"family: unknown procedural family {family!r}; accepted: {list(families)}")
        n = DEFAULT_POOL_SIZE if num_scenarios is None else int(num_scenarios)
        out = list(_procedural_pool(n, int(seed), family))
    elif womd_dir is not None:
        # load_dir returns (scenarios, report); skipped files are already issued as a
        # ScenarioLoadWarning, and a folder with nothing loadable raises ScenarioError.
        loaded, _report = scen_mod.load_dir(womd_dir)
        out = list(loaded)
    else:
        n = DEFAULT_POOL_SIZE if num_scenarios is None else int(num_scenarios)
        out = list(_procedural_pool(n, int(seed), None))
    if num_scenarios is not None:
        out = out[: int(num_scenarios)]
    return out


def check_selfplay_arguments(*, scenarios: Any = None, num_worlds: Any = None, max_agents: Any = None,
                             family: Any = None, womd_dir: Any = None, num_scenarios: Any = None,
                             dynamics: Any = None, condition: Any = "train", seed: Any = 0, config: Any = None,
                             device: Any = "cpu", render_mode: Any = None, render_worlds: Any = 4,
                             timeout_terminal: Any = False, eval_task_share: Any = 0.0, panel_share: Any = 0.0,
                             **config_overrides: Any) -> None:
    """Check :class:`SelfPlayVecEnv` arguments without building anything (no scenarios, no
    simulator): ``ValueError`` whose message starts with the bad argument's name (a missing
    ``womd_dir`` is a :class:`cpsim.ScenarioError`, whose ``field`` names it). Grids and
    commands call it before they start work; the constructor runs the same checks."""
    from cpsim import scenario as scen_mod
    from cpsim.config import SimConfig

    for name, value in (("num_worlds", num_worlds), ("max_agents", max_agents), ("num_scenarios", num_scenarios),
                        ("render_worlds", render_worlds)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1):
            raise ValueError(f"{name}: must be a whole number >= 1, got {value!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: must be a whole number >= 0, got {seed!r}")
    if not (str(device) == "cpu" or str(device).startswith("cuda")):
        raise ValueError(f"device: expected 'cpu' or 'cuda[:n]', got {device!r}")
    if scenarios is not None and isinstance(scenarios, (str, bytes)):
        raise ValueError(f"scenarios: expected a list of Scenario objects, got a string {scenarios!r} "
                         "(a folder of WOMD files goes to womd_dir)")
    if family is not None and family not in scen_mod.FAMILIES:
        raise ValueError(f"family: unknown procedural family {family!r}; accepted: {list(scen_mod.FAMILIES)}")
    if womd_dir is not None and not os.path.isdir(str(womd_dir)):
        from cpsim.scenario.datatypes import ScenarioError

        raise ScenarioError(str(womd_dir), "womd_dir", "folder does not exist")
    if render_mode not in (None, "rgb_array", "human"):
        raise ValueError(f"render_mode: unsupported {render_mode!r}; accepted: [None, 'rgb_array', 'human']")
    fixed = not (isinstance(condition, str) and condition in CONDITION_MODES)
    if fixed:
        resolve_condition(condition, "condition")
    if not isinstance(timeout_terminal, (bool, np.bool_)):
        raise ValueError(f"timeout_terminal: expected a bool, got {timeout_terminal!r}")
    for name, value, reason in (("eval_task_share", eval_task_share, "a fixed condition already has its task fields"),
                                ("panel_share", panel_share, "a fixed condition already has its style fields")):
        share = float(value) if isinstance(value, (int, float, np.number)) and not isinstance(value, bool) \
            else float("nan")
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"{name}: expected a number in [0, 1], got {value!r}")
        if share > 0.0 and fixed:
            raise ValueError(f"{name}: only applies to condition='train' ({reason})")
    base = SimConfig.from_dict(config) if not isinstance(config, SimConfig) else config
    changes = dict(config_overrides)
    if dynamics is not None:
        changes["dynamics"] = dynamics
    if changes:
        base.replace(**changes)


def make_simulator(scenarios: list, num_worlds: int, max_agents: int, *, dynamics: str | None = None,
                   config: Any = None, device: str = "cpu", seed: int = 0, **overrides: Any) -> Any:
    """Build a :class:`cpsim.Simulator`; ``config`` (SimConfig or mapping) plus keyword
    overrides of its fields (unknown keys raise ``ValueError`` listing the valid ones)."""
    from cpsim.config import SimConfig
    from cpsim.simulator import Simulator

    base = SimConfig.from_dict(config) if not isinstance(config, SimConfig) else config
    changes = dict(overrides)
    if dynamics is not None:
        changes["dynamics"] = dynamics
    cfg = base.replace(**changes) if changes else base
    if int(num_worlds) < 1:
        raise ValueError(f"num_worlds must be >= 1, got {num_worlds}")
    if int(max_agents) < 1:
        raise ValueError(f"max_agents must be >= 1, got {max_agents}")
    return Simulator(scenarios, num_worlds=int(num_worlds), max_agents=int(max_agents), config=cfg,
                     device=device, seed=int(seed))


#: Bound of the observation Box. Features are normalised to about [-1, 1]; the widest
#: reachable ones (classic dynamics: speed up to 100 m/s / 20, relative velocity / 20, long
#: trucks' length / 10) stay below 10, so clipping to +-100 (done while copying) only
#: guards against non-physical values and keeps every observation inside the declared space.
OBS_BOUND = 100.0


def observation_space_for(sim: Any) -> spaces.Box:
    """Box(-OBS_BOUND, OBS_BOUND, (D,), float32) for the simulator's observation vector."""
    d = int(sim.obs_layout.size)
    return spaces.Box(low=-OBS_BOUND, high=OBS_BOUND, shape=(d,), dtype=np.float32)


def copy_obs(view: Any, shape: tuple[int, ...]) -> np.ndarray:
    """Fresh float32 array of ``shape`` from a simulator view, clipped to +-OBS_BOUND (one pass)."""
    src = _np(view).reshape(shape)
    return np.clip(src, -OBS_BOUND, OBS_BOUND, out=np.empty(shape, np.float32))


class SelfPlayVecEnv(VecEnv):
    """Self-play over a batched :class:`cpsim.Simulator`: every agent slot is one env index.

    ``num_envs = num_worlds * max_agents``; index ``i = w * max_agents + a`` is slot ``a`` of
    world ``w``. Every POLICY agent is driven by the same (learning) policy through its
    index; the simulator decides everything else (replay / IDM agents, events, rewards).

    Args:
        scenarios: list of :class:`~cpsim.scenario.Scenario`; None = the procedural
            training pool (``cpsim.scenario.train_pool(16, seed)``). ``family`` / ``womd_dir``
            (keyword) pick a procedural family or a folder of WOMD files instead.
        num_worlds, max_agents: W and A.
        dynamics: "jerk" (Discrete(12)) or "classic" (Discrete(91)).
        condition: "train" (default: every agent's condition is drawn from p_train at each
            world reset), a profile name (e.g. "normal") or a raw 10-vector, fixed for
            every agent (deployment-style runs).
        eval_task_share: with ``condition="train"``, the share of agents (in [0, 1], drawn
            independently per agent at each world reset) whose task fields (goal radius, goal
            speed) are the evaluation criterion's (:func:`cpsim.conditions.criterion_task_fields`:
            2 m, 30 m/s) instead of p_train draws; their style fields stay p_train draws.
            p_train's radius is U(2, 12) m, so the evaluator's 2 m sits at the edge of what a
            policy trains on; an anchor recipe can oversample it (0: plain p_train).
        panel_share: with ``condition="train"``, the share of agents (in [0, 1], drawn
            independently per agent at each world reset) whose style fields are those of a
            random panel profile (cautious ... aggressive, :data:`cpsim.conditions.PANEL`)
            instead of p_train draws; their task fields stay p_train draws. Oversamples the
            exact styles a policy is deployed and searched under (0: plain p_train).
        seed: seeds scenario draws and condition draws (and the simulator).
        config: a ``SimConfig`` or mapping; other keyword arguments override its fields.
        device: "cpu" or "cuda[:n]".
        render_mode: None, "rgb_array" (``render()`` tiles one top-down frame per world,
            camera on the whole scene; at most ``render_worlds`` worlds) or "human"
            (``render()`` shows that tiling in a matplotlib window, :mod:`cpsim.envs.viewer`).

    Episodes and auto-reset:
        A world resets (new scenario, new conditions) when its ``episode_steps`` decisions
        are up or no POLICY agent is left alive (``sim.world_done``).

    Active and inactive slots (what an algorithm must mask):
        A slot is *active* for an observation when it holds a POLICY agent that is alive
        (``sim.policy_mask``). ``active_mask()`` gives the (num_envs,) mask of the
        observation returned last; ``infos[i]["active"]`` is the same flag after a step.

        * An active slot whose agent ends its episode on this step (goal, collision,
          off-road, timeout) emits ``done=True``, its last reward,
          ``infos[i]["terminal_observation"]`` (the observation at the end),
          ``"TimeLimit.truncated"`` (True for timeouts, so SB3 bootstraps them with the
          critic; False with ``timeout_terminal=True``: the observation carries the time
          left, so the deadline is part of the task and a timeout is a terminal failure),
          ``"is_success"`` (goal reached),
          ``"outcome"`` ("goal" / "collision" / "offroad" / "timeout") and the episode's
          BehaviorBench metrics (:func:`cpsim.scoring.episode_scores`):
          ``"at_fault_collision"``, ``"comfort"``, ``"lane_align"``, ``"lane_center"`` and
          ``"score"`` (0-100). If its world resets on the same step the returned
          observation is the new episode's first observation (SB3 auto-reset semantics),
          otherwise the slot turns inactive.
        * An inactive slot (no agent, a non-POLICY agent, or an agent removed until its
          world resets) emits a zero observation, reward 0.0, ``done=False`` and
          ``infos[i]["active"] = False``, and its action is ignored. When its world resets
          and a new agent takes the slot, the slot simply becomes active again with
          ``done=False``, so an unmasked PPO sees zero observations with zero reward
          between episodes but never a spurious episode end; under ``VecMonitor`` those
          steps count into the next episode's length, not its return.
        * Empty episodes: a slot that held no POLICY agent during its world's whole
          episode (``max_agents`` above the scenario's controllable cars) emits
          ``done=True`` when the world resets, with reward 0, ``"empty": True``,
          ``"TimeLimit.truncated": False``, a zero ``"terminal_observation"`` and no
          ``"outcome"``. Every index thus ends episodes, which SB3's ``evaluate_policy``
          and ``EvalCallback`` need (they count episodes per index); their means then
          include those 0-reward episodes, and ``VecMonitor`` records them too. Use
          ``infos[i]["outcome"]`` (or ``"is_success"``) to count agents' episodes only.

    Observations and rewards are fresh NumPy float32 arrays (copies, never views on
    simulator memory). ``get_attr`` / ``set_attr`` / ``env_method`` act on this one
    object and return one entry per requested index.
    """

    def __init__(self, scenarios: Sequence[Any] | None = None, num_worlds: int = 4, max_agents: int = 16,
                 *, family: str | None = None, womd_dir: str | None = None, num_scenarios: int | None = None,
                 dynamics: str | None = None, condition: str | Sequence[float] | np.ndarray = "train",
                 seed: int = 0, config: Any = None, device: str = "cpu", render_mode: str | None = None,
                 render_worlds: int = 4, timeout_terminal: bool = False, eval_task_share: float = 0.0,
                 panel_share: float = 0.0,
                 **config_overrides: Any):
        check_selfplay_arguments(scenarios=scenarios, num_worlds=num_worlds, max_agents=max_agents, family=family,
                                 womd_dir=womd_dir, num_scenarios=num_scenarios, dynamics=dynamics,
                                 condition=condition, seed=seed, config=config, device=device,
                                 render_mode=render_mode, render_worlds=render_worlds,
                                 timeout_terminal=timeout_terminal, eval_task_share=eval_task_share,
                                 panel_share=panel_share, **config_overrides)
        self.scenarios = resolve_scenarios(scenarios, family=family, womd_dir=womd_dir,
                                           num_scenarios=num_scenarios, seed=seed)
        self.sim = make_simulator(self.scenarios, num_worlds, max_agents, dynamics=dynamics, config=config,
                                  device=device, seed=seed, **config_overrides)
        self.num_worlds = int(self.sim.num_worlds)
        self.max_agents = int(self.sim.max_agents)
        self.obs_layout = self.sim.obs_layout
        if isinstance(condition, str) and condition in CONDITION_MODES:
            self.fixed_condition: np.ndarray | None = None
        else:
            self.fixed_condition = resolve_condition(condition, "condition")
        self.condition = condition
        self.timeout_terminal = bool(timeout_terminal)  # values checked by check_selfplay_arguments above
        self.eval_task_share = float(eval_task_share)
        self.panel_share = float(panel_share)
        self.render_mode = render_mode
        self.render_worlds = int(render_worlds)
        self._renderer = None
        self._viewer: Any = None
        self._rng = np.random.default_rng(seed)
        self._seed = seed
        n = self.num_worlds * self.max_agents
        super().__init__(n, observation_space_for(self.sim), spaces.Discrete(int(self.sim.config.num_actions)))
        self._obs_dim = int(self.observation_space.shape[0])
        self._actions: np.ndarray | None = None
        self._active = np.zeros(n, bool)
        self._held = np.zeros(n, bool)  # the slot held an active agent since its world's reset
        self._flat_index = np.arange(n)

    # ------------------------------------------------------------------ internals
    def _reset_worlds(self, worlds: np.ndarray) -> None:
        """Reset ``worlds`` with a scenario and conditions drawn from this env's RNG."""
        k = worlds.size
        scenario_index = self._rng.integers(0, len(self.scenarios), size=k)
        if self.fixed_condition is None:
            cond = sample_conditions(self._rng, (k, self.max_agents))
            if self.panel_share > 0.0:
                cond = with_panel_share(self._rng, cond, self.panel_share)
            if self.eval_task_share > 0.0:
                with_eval_task(self._rng, cond, self.eval_task_share)
        else:
            cond = np.broadcast_to(self.fixed_condition, (k, self.max_agents, NUM_CONDITION_FIELDS)).copy()
        self.sim.reset(worlds=worlds, scenario_index=scenario_index, conditions=cond)

    def _observe(self) -> np.ndarray:
        """(num_envs, D) float32 copy of the observations, zero on inactive slots; updates the mask."""
        self._active = _np(self.sim.policy_mask).reshape(-1)  # a fresh array (NumPy on CPU)
        obs = copy_obs(self.sim.obs, (self.num_envs, self._obs_dim))
        obs[~self._active] = 0.0
        return obs

    # ------------------------------------------------------------------ VecEnv API
    def reset(self) -> np.ndarray:
        if self._seeds[0] is not None:
            self._seed = int(self._seeds[0])
            self._rng = np.random.default_rng(self._seed)
        self._reset_worlds(np.arange(self.num_worlds))
        self._reset_seeds()
        self._reset_options()
        obs = self._observe()
        self._held = self._active.copy()
        self.reset_infos = [{"active": bool(a)} for a in self._active]
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        a = np.asarray(actions)
        if a.size != self.num_envs:
            raise ValueError(f"actions: expected {self.num_envs} actions (one per env index), got shape {a.shape}")
        a = a.reshape(self.num_worlds, self.max_agents)
        if not np.issubdtype(a.dtype, np.integer):
            if not np.all(np.isfinite(a)) or not np.all(a == np.round(a)):
                raise ValueError("actions: must be integers (Discrete action space)")
            a = a.astype(np.int64)
        n = int(self.action_space.n)
        # inactive slots' actions are ignored by the simulator; clamp them so a policy that
        # emits anything there is harmless, but reject out-of-range actions on active slots
        active = self._active.reshape(self.num_worlds, self.max_agents)
        bad = active & ((a < 0) | (a >= n))
        if np.any(bad):
            i = int(np.flatnonzero(bad.reshape(-1))[0])
            raise ValueError(f"actions[{i}] = {a.reshape(-1)[i]} outside the action space; accepted: 0..{n - 1}")
        self._actions = np.where(active, a, 0).astype(np.int64)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait called without step_async")
        was_active = self._active
        self.sim.step(self._actions)
        self._actions = None
        n = self.num_envs
        reward = np.array(_np(self.sim.reward).reshape(n), dtype=np.float32, copy=True)
        agent_done = was_active & _np(self.sim.done).reshape(n)
        reward[~was_active] = 0.0
        world_done = _np(self.sim.world_done).copy()
        # a world that resets ends every episode still running in it (the simulator marks
        # them timed out; this also covers a world ended for another reason)
        cut = was_active & ~agent_done & np.repeat(world_done, self.max_agents)
        ended = agent_done | cut
        done_idx = np.flatnonzero(ended)
        terminal_obs = truncated = outcome = scores = None
        if done_idx.size:
            terminal_obs = copy_obs(_np(self.sim.obs).reshape(n, self._obs_dim)[done_idx], (done_idx.size, self._obs_dim))
            truncated = _np(self.sim.truncated).reshape(n)[done_idx] | cut[done_idx]
            outcome = np.where(cut[done_idx], 4, _np(self.sim.outcome).reshape(n)[done_idx])
            scores = episode_scores({k: _np(v).reshape(n)[done_idx] for k, v in self.sim.metrics.items()})
        # slots that held no agent during a world's episode end an empty one when it resets
        reset_slots = np.repeat(world_done, self.max_agents)
        empty = reset_slots & ~self._held & ~ended
        if np.any(world_done):
            self._reset_worlds(np.flatnonzero(world_done))
        obs = self._observe()
        self._held = np.where(reset_slots, self._active, self._held | self._active)
        # infos: one fresh dict per index (wrappers mutate them); extra keys only where done
        infos: list[dict[str, Any]] = [{"active": a} for a in self._active.tolist()]
        if done_idx.size:
            names = [OUTCOME_NAMES[o] if 0 <= o < len(OUTCOME_NAMES) else str(o) for o in outcome.tolist()]
            for k, i in enumerate(done_idx.tolist()):
                info = infos[i]
                info["terminal_observation"] = terminal_obs[k]
                # a deadline the observation shows (time_left) is part of the task: with
                # timeout_terminal a timeout is a failure, and PPO does not bootstrap it
                info["TimeLimit.truncated"] = bool(truncated[k]) and not self.timeout_terminal
                info["is_success"] = names[k] == "goal"
                info["outcome"] = names[k]
                for key in _SCORE_KEYS:
                    info[key] = scores[key][k].item()
        for i in np.flatnonzero(empty).tolist():
            infos[i].update({"terminal_observation": np.zeros(self._obs_dim, np.float32),
                             "TimeLimit.truncated": False, "empty": True})
        return obs, reward, ended | empty, infos

    def active_mask(self) -> np.ndarray:
        """(num_envs,) bool copy: which indices of the last observation hold a live POLICY agent."""
        return self._active.copy()

    def close(self) -> None:
        self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None

    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        """Seed the next ``reset()`` (scenario and condition draws); SB3 semantics."""
        if seed is None:
            seed = int(np.random.default_rng().integers(0, 2**31 - 1))
        self._seeds = [seed + idx for idx in range(self.num_envs)]
        return self._seeds

    def _indices(self, indices: VecEnvIndices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        if isinstance(indices, (int, np.integer)):
            return [int(indices)]
        return list(indices)

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        value = getattr(self, attr_name)
        return [value for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        """Call ``method_name`` once on this env (all indices share it); the result is
        repeated for each requested index."""
        result = getattr(self, method_name)(*method_args, **method_kwargs)
        return [result for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gymnasium.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._indices(indices)]

    # ------------------------------------------------------------------ rendering
    def get_images(self) -> Sequence[np.ndarray | None]:
        """One top-down frame per world (first ``render_worlds`` worlds), scene camera."""
        if self.render_mode not in ("rgb_array", "human"):
            return [None for _ in range(self.num_worlds)]
        if self._renderer is None:
            from cpsim.render import TopDownRenderer

            self._renderer = TopDownRenderer(width=320, height=320, camera="scene")
        return [self._renderer.render_sim(self.sim, w) for w in range(min(self.num_worlds, self.render_worlds))]

    def render(self, mode: str | None = None) -> np.ndarray | None:
        """``rgb_array``: the tiled frames; ``human``: show them in a window, return None."""
        if self.render_mode == "human" and mode in (None, "human"):
            from cpsim.envs.viewer import HumanViewer, tile

            if self._viewer is None:
                self._viewer = HumanViewer("cpsim self-play", fps=10)
            self._viewer.show(tile([f for f in self.get_images() if f is not None]))
            return None
        return super().render(mode)

    def world_frames(self, worlds: Iterable[int] | None = None, **renderer_kwargs: Any) -> list[np.ndarray]:
        """Frames of the given worlds (default all) regardless of ``render_mode``."""
        from cpsim.render import TopDownRenderer

        r = TopDownRenderer(**{"camera": "scene", **renderer_kwargs})
        worlds = range(self.num_worlds) if worlds is None else worlds
        return [r.render_sim(self.sim, int(w)) for w in worlds]


def _active_flags(infos: Sequence[dict[str, Any]]) -> np.ndarray:
    return np.fromiter((bool(i.get("active", True)) for i in infos), bool, count=len(infos))


class SelfPlayVecNormalize(VecNormalize):
    """``VecNormalize`` for :class:`SelfPlayVecEnv`: statistics from active slots only.

    SB3's ``VecNormalize`` updates its observation statistics with every index, so the
    zero observations of inactive slots pull the mean towards 0 and the variance down,
    and their zero rewards enter the return statistics. This subclass updates the
    observation statistics with the slots active after the step (``infos[i]["active"]``)
    and the return statistics with the slots that were active before it (whose reward is
    an agent's), and it returns zero observations on inactive slots, as the env does.
    Same arguments, ``save`` / ``load`` as ``VecNormalize``.
    """

    def _active_now(self) -> np.ndarray:
        try:
            return np.asarray(self.venv.env_method("active_mask", indices=[0])[0], bool)
        except AttributeError:  # not a self-play env: every slot counts
            return np.ones(self.num_envs, bool)

    def reset(self) -> np.ndarray:
        obs = self.venv.reset()
        self.old_obs = obs
        self.returns = np.zeros(self.num_envs)
        self._was_active = self._active_now()
        if self.training and self.norm_obs and self._was_active.any():
            self.obs_rms.update(obs[self._was_active])
        out = self.normalize_obs(obs)
        out[~self._was_active] = 0.0
        return out

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        self.old_obs, self.old_reward = obs, rewards
        active = _active_flags(infos)
        was_active = getattr(self, "_was_active", None)
        if was_active is None or was_active.shape != active.shape:
            was_active = np.ones_like(active)
        if self.training and self.norm_obs and active.any():
            self.obs_rms.update(obs[active])
        obs = self.normalize_obs(obs)
        obs[~active] = 0.0
        self.returns = self.returns * self.gamma + rewards
        if self.training and was_active.any():
            self.ret_rms.update(self.returns[was_active])
        rewards = self.normalize_reward(rewards)
        for idx in np.flatnonzero(dones):
            info = infos[idx]
            if "terminal_observation" in info and not info.get("empty", False):
                info["terminal_observation"] = self.normalize_obs(info["terminal_observation"])
        self.returns[dones] = 0
        self._was_active = active
        return obs, rewards, dones, infos


__all__ = ["SelfPlayVecEnv", "SelfPlayVecNormalize", "OUTCOME_NAMES", "resolve_scenarios", "make_simulator",
           "check_selfplay_arguments",
           "observation_space_for", "copy_obs", "OBS_BOUND"]
