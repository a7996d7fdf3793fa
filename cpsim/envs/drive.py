"""Gymnasium front-ends: ``cpsim/Drive-v0`` (one ego) and its batched vector version.

:class:`DriveEnv` is a ``gymnasium.Env`` over a one-world :class:`cpsim.Simulator`;
:class:`DriveVectorEnv` is a ``gymnasium.vector.VectorEnv`` over one Simulator with
``num_envs`` worlds (``gymnasium.make_vec("cpsim/Drive-v0", num_envs=N)``). Both share
:class:`DriveCore`: slot 0 of every world is the ego (the scenario's designated ego),
driven by the caller; the co-players follow a traffic regime (:mod:`cpsim.envs.regimes`).
"""

from __future__ import annotations

from typing import Any, Sequence

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from cpsim.conditions import NUM_CONDITION_FIELDS, deployment_condition, sample_conditions
from cpsim.config import Controller, Outcome
from cpsim.envs.regimes import TrafficDriver
from cpsim.envs.selfplay import OUTCOME_NAMES, _np, copy_obs, make_simulator, observation_space_for, resolve_scenarios
from cpsim.envs.viewer import HumanViewer, tile
from cpsim.scoring import episode_scores

EGO_SLOT = 0
_POLICY = int(Controller.POLICY)
_TIMEOUT = int(Outcome.TIMEOUT)
#: the horizon ``cpsim/Drive-v0`` is registered with (``spec.max_episode_steps``):
#: SimConfig's default and largest ``episode_steps`` (the logs' 91 steps)
HORIZON = 91
#: episode metrics added to the info of an episode's last step
SCORE_KEYS = ("at_fault_collision", "comfort", "lane_align", "lane_center", "score")


class DriveCore:
    """Shared engine of :class:`DriveEnv` and :class:`DriveVectorEnv` (W worlds, ego = slot 0).

    Args: see :class:`DriveEnv`. ``rng`` is replaced by the env on seeded resets.
    """

    def __init__(self, num_worlds: int, *, scenarios: Sequence[Any] | None = None, family: str | None = None,
                 womd_dir: str | None = None, num_scenarios: int | None = None, dynamics: str | None = None,
                 condition: str | Sequence[float] | np.ndarray | None = "train", regime: str = "replay",
                 coplayer_model: Any = None, coplayer_condition: str | Sequence[float] | None = None,
                 deterministic_coplayers: bool = True, seed: int | None = None, max_agents: int = 32,
                 config: Any = None, device: str = "cpu", **config_overrides: Any):
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
            raise ValueError(f"seed: must be None or a whole number >= 0, got {seed!r}")
        if not isinstance(deterministic_coplayers, (bool, np.bool_)):
            raise ValueError(f"deterministic_coplayers: expected a bool, got {deterministic_coplayers!r}")
        # regime first: a bad name fails before any scenario is generated or compiled
        self.driver = TrafficDriver(regime, coplayer_model, condition=coplayer_condition,
                                    deterministic=deterministic_coplayers, seed=seed, ego_slot=EGO_SLOT)
        if condition is None or (isinstance(condition, str) and condition == "train"):
            self.ego_condition: np.ndarray | None = None
        else:
            # a fixed deployment condition changes style fields only: one goal test
            self.ego_condition = deployment_condition(condition, "condition")
            if not (isinstance(config, dict) and "goal_criterion" in config):
                config_overrides.setdefault("goal_criterion", "evaluation")
        pool = resolve_scenarios(scenarios, family=family, womd_dir=womd_dir, num_scenarios=num_scenarios,
                                 seed=0 if seed is None else int(seed))
        usable = [s for s in pool if bool(s.controllable[s.ego_index])]
        if not usable:
            raise ValueError("scenarios: no scenario has a controllable ego (a vehicle valid at t0 with a goal)")
        self.scenarios = usable
        self.sim = make_simulator(usable, num_worlds, max_agents, dynamics=dynamics, config=config,
                                  device=device, seed=0 if seed is None else int(seed), **config_overrides)
        self.num_worlds = int(self.sim.num_worlds)
        self.max_agents = int(self.sim.max_agents)
        self.obs_layout = self.sim.obs_layout
        self.observation_space = observation_space_for(self.sim)
        self.action_space = spaces.Discrete(int(self.sim.config.num_actions))
        self.regime = self.driver.regime
        #: one generator per world (scenario and condition draws), so that world ``i`` of a
        #: vector env seeded with ``s + i`` replays ``DriveEnv`` seeded with ``s + i``
        self.rngs = [np.random.default_rng(None if seed is None else int(seed) + w) for w in range(self.num_worlds)]
        self._actions = np.zeros((self.num_worlds, self.max_agents), np.int64)
        steps = int(self.sim.config.episode_steps) + 2
        self.trail = np.full((self.num_worlds, steps, 2), np.nan, np.float32)  # ego positions, m
        self.trail_len = np.zeros(self.num_worlds, np.int64)

    # ------------------------------------------------------------------ episodes
    def reset_worlds(self, worlds: np.ndarray, scenario_index: np.ndarray | None = None) -> None:
        """Reset ``worlds``: draw scenarios and conditions, assign the regime, make slot 0 POLICY."""
        worlds = np.asarray(worlds, np.int64).reshape(-1)
        drawn = np.zeros(worlds.size, np.int64)
        cond = np.zeros((worlds.size, self.max_agents, NUM_CONDITION_FIELDS), np.float32)
        for j, w in enumerate(worlds.tolist()):  # each world draws from its own generator
            rng = self.rngs[w]
            if scenario_index is None:
                drawn[j] = rng.integers(0, len(self.scenarios), size=1)[0]
            cond[j] = sample_conditions(rng, (1, self.max_agents))[0]
        if scenario_index is None:
            scenario_index = drawn
        if self.ego_condition is not None:
            cond[:, EGO_SLOT] = self.ego_condition
        self.sim.reset(worlds=worlds, scenario_index=np.asarray(scenario_index), conditions=cond)
        self.driver.assign(self.sim, worlds, conditions=cond)
        ctrl = _np(self.sim.controllers)[worlds].astype(np.int32)
        if np.any(ctrl[:, EGO_SLOT] != _POLICY):
            ctrl[:, EGO_SLOT] = _POLICY
            self.sim.set_controllers(ctrl, worlds)
        self.trail[worlds] = np.nan
        self.trail[worlds, 0] = _np(self.sim.xy)[worlds, EGO_SLOT]
        self.trail_len[worlds] = 1

    def ego_obs(self) -> np.ndarray:
        """(W, D) float32 copy of the egos' observations."""
        return copy_obs(_np(self.sim.obs)[:, EGO_SLOT], (self.num_worlds, self.obs_layout.size))

    def check_actions(self, actions: Any) -> np.ndarray:
        a = np.asarray(actions)
        if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
            raise ValueError(f"action: expected integer action(s), got {actions!r}")
        if a.size != self.num_worlds:
            raise ValueError(f"action: expected {self.num_worlds} action(s), got shape {a.shape}")
        a = a.reshape(self.num_worlds)
        n = int(self.action_space.n)
        if not np.issubdtype(a.dtype, np.integer):
            if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
                raise ValueError(f"action: {a.tolist()} is not an integer; accepted: 0..{n - 1}")
            a = a.astype(np.int64)
        if np.any((a < 0) | (a >= n)):
            raise ValueError(f"action: {a.tolist()} outside the action space; accepted: 0..{n - 1}")
        return a.astype(np.int64)

    def step(self, ego_actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Step every world; returns ego (obs (W, D), reward (W,), terminated (W,),
        truncated (W,), outcome (W,) int) as fresh arrays."""
        actions = self._actions
        actions.fill(0)
        self.driver.act(out=actions)
        actions[:, EGO_SLOT] = ego_actions
        self.sim.step(actions)
        obs = self.ego_obs()
        reward = np.array(_np(self.sim.reward)[:, EGO_SLOT], dtype=np.float32, copy=True)
        terminated = _np(self.sim.terminated)[:, EGO_SLOT].copy()
        truncated = _np(self.sim.truncated)[:, EGO_SLOT].copy()
        outcome = _np(self.sim.outcome)[:, EGO_SLOT].astype(np.int64)
        # a world that ends without ending the ego's episode (should not happen) is a timeout
        cut = _np(self.sim.world_done) & ~(terminated | truncated)
        truncated |= cut
        outcome = np.where(cut, _TIMEOUT, outcome)
        w = np.arange(self.num_worlds)
        pos = np.minimum(self.trail_len, self.trail.shape[1] - 1)
        self.trail[w, pos] = _np(self.sim.xy)[:, EGO_SLOT]
        self.trail_len = pos + 1
        return obs, reward, terminated, truncated, outcome

    def episode_scores(self) -> dict[str, np.ndarray]:
        """(W,) the egos' episode metrics so far (:func:`cpsim.scoring.episode_scores`);
        read them on the step an episode ends, before its world resets."""
        return episode_scores({k: _np(v)[:, EGO_SLOT] for k, v in self.sim.metrics.items()})

    def scenario_ids(self, worlds: np.ndarray | None = None) -> list[str]:
        idx = _np(self.sim.world_scenario)
        if worlds is not None:
            idx = idx[np.asarray(worlds)]
        return [self.scenarios[int(i)].id for i in idx]

    def render_world(self, renderer: Any, world: int) -> np.ndarray:
        n = int(self.trail_len[world])
        return renderer.render_sim(self.sim, world, ego_slot=EGO_SLOT, trail=self.trail[world, :n])


class DriveEnv(gymnasium.Env):
    """``cpsim/Drive-v0``: drive one ego through a scenario among co-players.

    Observation: Box(-100, 100, (D,), float32), the ego's ego-frame observation
    (layout ``env.obs_layout``: ego features, its reward condition, K partners, M road
    segments, normalised to about [-1, 1]). Action: Discrete(12) (jerk dynamics) or
    Discrete(91) (classic). Reward: the ego's conditioned reward. ``terminated`` when the
    ego reaches its goal, collides or leaves the road; ``truncated`` at the 91-step
    horizon (``spec.max_episode_steps`` = 91, the longest ``episode_steps`` allows; a
    shorter ``episode_steps`` ends episodes earlier). ``info``: ``scenario_id``,
    ``step``, and at the end ``outcome`` ("goal" / "collision" / "offroad" / "timeout"),
    ``is_success`` and the episode's BehaviorBench metrics (:data:`SCORE_KEYS`:
    ``at_fault_collision``, ``comfort``, ``lane_align``, ``lane_center``, ``score`` 0-100).

    Args:
        scenarios: list of Scenario; or ``family`` (procedural family name) or
            ``womd_dir`` (folder of WOMD JSON / .npz); default the procedural training pool.
            Scenarios whose ego is not controllable are skipped.
        num_scenarios: cap on the pool (procedural family: number of seeds generated).
        dynamics: "jerk" (default) or "classic".
        condition: the ego's reward condition: "train" (drawn from p_train at each reset;
            every agent's goal test uses its own goal_radius / goal_speed), or a fixed
            deployment condition, a profile name ("normal", "cautious", ...) or a raw
            10-vector: the ego gets its style fields only, and the goal test is the
            evaluation criterion (``goal_criterion="evaluation"``: 2 m, no effective speed
            limit, :data:`cpsim.config.EVAL_GOAL`) for every agent, whatever the profile;
            pass ``goal_criterion="condition"`` to keep the per-agent test.
        regime: co-player traffic regime (:data:`cpsim.envs.regimes.REGIMES`).
        coplayer_model: SB3 model, callable or checkpoint path for policy regimes.
        coplayer_condition: co-players' condition under the "policy" regime.
        seed: default seed (``reset(seed=...)`` overrides).
        render_mode: None, "rgb_array" (``render()`` returns the frame) or "human" (a
            matplotlib window shows every step; :mod:`cpsim.envs.viewer`).
        camera: "ego" or "scene" (rendering). view_m: ego camera width, m.
        render_size: (width, height) of rendered frames, pixels.
        max_agents: agent slots simulated (the ego plus the nearest others).
        config / other keywords: ``SimConfig`` and field overrides.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}

    def __init__(self, scenarios: Sequence[Any] | None = None, *, family: str | None = None,
                 womd_dir: str | None = None, num_scenarios: int | None = None, dynamics: str | None = None,
                 condition: str | Sequence[float] | np.ndarray | None = "train", regime: str = "replay",
                 coplayer_model: Any = None, coplayer_condition: str | Sequence[float] | None = None,
                 deterministic_coplayers: bool = True, seed: int | None = None,
                 render_mode: str | None = None, camera: str = "ego", view_m: float = 70.0,
                 render_size: tuple[int, int] = (480, 480), max_agents: int = 32, config: Any = None,
                 device: str = "cpu", **config_overrides: Any):
        super().__init__()
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode: unsupported {render_mode!r}; accepted: "
                             f"{[None] + self.metadata['render_modes']}")
        self.core = DriveCore(1, scenarios=scenarios, family=family, womd_dir=womd_dir,
                              num_scenarios=num_scenarios, dynamics=dynamics, condition=condition,
                              regime=regime, coplayer_model=coplayer_model,
                              coplayer_condition=coplayer_condition,
                              deterministic_coplayers=deterministic_coplayers, seed=seed,
                              max_agents=max_agents, config=config, device=device, **config_overrides)
        self.observation_space = self.core.observation_space
        self.action_space = self.core.action_space
        self.render_mode = render_mode
        self._default_seed = seed
        self._renderer = None
        self._viewer: HumanViewer | None = None
        if render_mode is not None:
            from cpsim.render import TopDownRenderer

            self._renderer = TopDownRenderer(width=render_size[0], height=render_size[1], camera=camera,
                                             view_m=view_m)
        if render_mode == "human":
            self._viewer = HumanViewer("cpsim/Drive-v0", fps=self.metadata["render_fps"])
        self._needs_reset = True

    @property
    def sim(self) -> Any:
        return self.core.sim

    @property
    def obs_layout(self) -> Any:
        return self.core.obs_layout

    @property
    def driver(self) -> TrafficDriver:
        return self.core.driver

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode. ``options``: ``{"scenario_index": i}`` picks the scenario."""
        if seed is None and self._default_seed is not None and self._np_random is None:
            seed = self._default_seed
        super().reset(seed=seed)
        self.core.rngs = [self.np_random]
        if seed is not None:
            self.core.driver.seed(seed)
        scenario_index = None
        if options:
            unknown = sorted(set(options) - {"scenario_index"})
            if unknown:
                raise ValueError(f"options: unknown key(s) {unknown}; accepted: ['scenario_index']")
            i = int(options["scenario_index"])
            if not 0 <= i < len(self.core.scenarios):
                raise ValueError(f"options['scenario_index']: {i} outside [0, {len(self.core.scenarios)})")
            scenario_index = np.array([i])
        self.core.reset_worlds(np.array([0]), scenario_index)
        self._needs_reset = False
        if self._viewer is not None:
            self._viewer.show(self.core.render_world(self._renderer, 0))
        return self.core.ego_obs()[0], {"scenario_id": self.core.scenario_ids()[0], "step": 0}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._needs_reset:
            raise RuntimeError("DriveEnv.step called before reset()")
        a = self.core.check_actions(action)
        obs, reward, terminated, truncated, outcome = self.core.step(a)
        term, trunc = bool(terminated[0]), bool(truncated[0])
        info: dict[str, Any] = {"scenario_id": self.core.scenario_ids()[0],
                                "step": int(_np(self.core.sim.step_count)[0])}
        if term or trunc:
            name = OUTCOME_NAMES[int(outcome[0])]
            info["outcome"] = name
            info["is_success"] = name == "goal"
            scores = self.core.episode_scores()
            info.update({k: scores[k][0].item() for k in SCORE_KEYS})
        if self._viewer is not None:
            self._viewer.show(self.core.render_world(self._renderer, 0))
        return obs[0], float(reward[0]), term, trunc, info

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without render_mode; make the env with render_mode='rgb_array'")
            return None
        frame = self.core.render_world(self._renderer, 0)
        if self._viewer is not None:  # human: every step already shows its frame
            self._viewer.show(frame)
            return None
        return frame

    def close(self) -> None:
        self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None


class DriveVectorEnv(VectorEnv):
    """``gymnasium.make_vec("cpsim/Drive-v0", num_envs=N)``: N egos in one batched Simulator.

    Sub-environment ``i`` is world ``i`` (its ego = slot 0). Autoreset mode NEXT_STEP
    (gymnasium's default): the step after an episode ends resets that world and ignores
    its action, returning the new first observation with reward 0. ``infos`` (dict of
    arrays with ``_key`` masks) carries the single env's keys: ``scenario_id`` and
    ``step`` for every sub-environment, and where an episode ended ``outcome`` (str),
    ``is_success`` and :data:`SCORE_KEYS`. ``reset(seed=s)`` seeds sub-environment ``i``
    with ``s + i`` (as ``DriveEnv`` seeded with ``s + i`` draws), ``reset(seed=[s0, s1,
    ...])`` with one seed each (None: unseeded). Keyword arguments as :class:`DriveEnv`;
    ``rgb_array`` rendering returns one frame per world, ``human`` shows them tiled.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10,
                "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, *, render_mode: str | None = None, camera: str = "ego",
                 view_m: float = 70.0, render_size: tuple[int, int] = (320, 320), seed: int | None = None,
                 **kwargs: Any):
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode: unsupported {render_mode!r}; accepted: "
                             f"{[None] + self.metadata['render_modes']}")
        kwargs.pop("max_episode_steps", None)  # the simulator owns the horizon
        self.core = DriveCore(int(num_envs), seed=seed, **kwargs)
        self.num_envs = int(num_envs)
        self.single_observation_space = self.core.observation_space
        self.single_action_space = self.core.action_space
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.render_mode = render_mode
        self._renderer = None
        self._viewer: HumanViewer | None = None
        if render_mode is not None:
            from cpsim.render import TopDownRenderer

            self._renderer = TopDownRenderer(width=render_size[0], height=render_size[1], camera=camera,
                                             view_m=view_m)
        if render_mode == "human":
            self._viewer = HumanViewer("cpsim/Drive-v0 (vector)", fps=self.metadata["render_fps"])
        self._default_seed = seed
        self._autoreset = np.zeros(self.num_envs, bool)
        self._needs_reset = True

    @property
    def sim(self) -> Any:
        return self.core.sim

    @property
    def obs_layout(self) -> Any:
        return self.core.obs_layout

    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        if options:
            raise ValueError(f"options: unknown key(s) {sorted(options)}; accepted: []")
        if seed is None and self._default_seed is not None and self._np_random is None:
            seed = self._default_seed
        if seed is not None:
            if isinstance(seed, (int, np.integer)):
                seeds: list[int | None] = [int(seed) + i for i in range(self.num_envs)]
            else:
                seeds = [None if s is None else int(s) for s in seed]
                if len(seeds) != self.num_envs:
                    raise ValueError(f"seed: expected one seed per sub-environment ({self.num_envs}), "
                                     f"got {len(seeds)}")
            self.core.rngs = [gymnasium.utils.seeding.np_random(s)[0] for s in seeds]
            first = next((s for s in seeds if s is not None), None)
            self._np_random, self._np_random_seed = gymnasium.utils.seeding.np_random(first)
            self.core.driver.seed(first)
        self.core.reset_worlds(np.arange(self.num_envs))
        self._autoreset[:] = False
        self._needs_reset = False
        self._show()
        return self.core.ego_obs(), self._infos()

    def _infos(self) -> dict[str, Any]:
        """The keys every step reports for every sub-environment, with their ``_key`` masks."""
        every = np.ones(self.num_envs, bool)
        return {"scenario_id": np.array(self.core.scenario_ids(), dtype=object), "_scenario_id": every,
                "step": _np(self.core.sim.step_count).astype(np.int64), "_step": every.copy()}

    def _show(self) -> None:
        if self._viewer is not None:
            self._viewer.show(tile([self.core.render_world(self._renderer, w) for w in range(self.num_envs)]))

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if self._needs_reset:
            raise RuntimeError("DriveVectorEnv.step called before reset()")
        a = self.core.check_actions(actions)
        obs, reward, terminated, truncated, outcome = self.core.step(a)
        restart = np.flatnonzero(self._autoreset)
        if restart.size:
            self.core.reset_worlds(restart)
            obs[restart] = self.core.ego_obs()[restart]
            reward[restart] = 0.0
            terminated[restart] = False
            truncated[restart] = False
        ended = terminated | truncated
        self._autoreset = ended.copy()
        infos = self._infos()
        if np.any(ended):
            names = np.array([OUTCOME_NAMES[int(o)] for o in outcome], dtype=object)
            infos["outcome"] = np.where(ended, names, None)
            infos["_outcome"] = ended.copy()
            infos["is_success"] = ended & (outcome == 1)
            infos["_is_success"] = ended.copy()
            scores = self.core.episode_scores()
            for key in SCORE_KEYS:
                infos[key] = np.where(ended, scores[key], np.zeros_like(scores[key]))
                infos[f"_{key}"] = ended.copy()
        self._show()
        return obs, reward, terminated, truncated, infos

    def render(self) -> tuple[np.ndarray, ...] | None:
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without render_mode; make the env with render_mode='rgb_array'")
            return None
        if self._viewer is not None:  # human: every step already shows its frames
            self._show()
            return None
        return tuple(self.core.render_world(self._renderer, w) for w in range(self.num_envs))

    def close_extras(self, **kwargs: Any) -> None:
        self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None


__all__ = ["DriveEnv", "DriveVectorEnv", "DriveCore", "EGO_SLOT", "HORIZON", "SCORE_KEYS"]
