"""The batched simulator: W worlds x A agent slots stepped together by Warp kernels.

See ``docs/ARCHITECTURE.md`` (Simulator) for the public contract. Layout of a step:

1. ``idm_kernel`` (only when some agent is on IDM): IDM accelerations from current poses;
2. ``dynamics_kernel``: every controller moves its agent (policy actions, log replay, IDM,
   static); replayed agents whose log ends vanish;
3. ``prepare_kernel`` (per world): heading (cos, sin) of the present agents and the roster
   of present and tracked slots;
4. ``events_kernel``: collisions, off-road, goal, lanes, outcome, metrics, reward, removal,
   timeout (every event and metric for tracked agents; scenery, i.e. REPLAY / STATIC agents
   without a task, gets collisions with tracked agents, off-road, goal and timeout only; see
   ``track_all``);
5. ``finish_kernel``: step counter, ``world_done``;
6. ``observation_kernel``: the next observation.

Per-step scratch passed from one kernel to a later one of the same step (``present`` from
the motion to the prepare and events kernels, ``idm_accel`` from the IDM to the motion
kernel) lives in ``self.scratch`` (:class:`cpsim.state.StepScratch`), not in the State: a
snapshot, restore or ``state_dict`` leaves it out.

All six are recorded launches (their arguments never change), made by the launchers
beside the kernels (``cpsim.kernels.<module>.launch_*`` with ``record=True``; this module
never calls ``wp.launch`` itself). On CPU the events and observation kernels (and the
motion / IDM kernels where their modules offer a per-world variant) run one thread per
world looping over its slots: a Warp CPU thread copies the kernel's State / ModelArrays /
Params arguments on entry (about 60 ns, as much as a scenery agent's whole events), so per
world rather than per slot. CUDA keeps one thread per slot;
both shapes run the same ``wp.func`` in the same order. A reset is two recorded launches
(``reset_kernel`` and the observation of the reset worlds) over staging buffers written in
place: no per-reset allocation or upload.

Outputs are torch tensors that are zero-copy views of the Warp state (torch is imported
here only, never in kernels); they are overwritten by the next ``step`` / ``reset``.

Threads: Warp's CPU kernels run serially on the calling thread (one core). On CPU the step
path (``step``, ``reset``, ``policy_mask``, the action checks) runs no torch operator: the
checks, the action copy and the masks use NumPy views of the Warp arrays, so the simulator
never waits on torch's intra-op thread pool, whatever ``torch.get_num_threads()`` is (on a
machine shared with other jobs that pool waits for descheduled threads at every parallel
operator: 10-27 ms each was measured on a loaded 2-core machine once W*A passed torch's
parallel grain of 32,768 elements). The torch thread count is thus the caller's choice for
its own torch work (the policy: ``cpalgo``'s ``--threads``, ``EvalConfig.torch_threads``).
On CUDA the same checks and masks are torch operators on the device.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch
import warp as wp

from cpsim import kernels as K
from cpsim.conditions import NUM_CONDITION_FIELDS, sample_conditions, validate_conditions
from cpsim.config import CONTROLLER_NAMES, Controller, SimConfig
from cpsim.kernels.common import make_params
from cpsim.model import Model
from cpsim.observation import ObsLayout
from cpsim.scenario.datatypes import Scenario
from cpsim.state import (
    METRIC_FIELDS,
    REWARD_TERMS,
    Control,
    State,
    allocate_scratch,
    allocate_state,
    state_field_names,
    state_to_numpy,
)


@dataclass
class Snapshot:
    """Copies of the full state of some worlds, on the simulator's device.

    Attributes:
        state: a :class:`State` whose world axis has ``num_worlds`` rows.
        num_worlds: number of worlds held.
        worlds: (num_worlds,) the simulator worlds they were taken from (informative).
        fingerprint, config, max_agents, device: compatibility keys checked by ``restore``.
    """

    state: State
    num_worlds: int
    worlds: np.ndarray
    fingerprint: str
    config: SimConfig
    max_agents: int
    device: str

    def state_dict(self) -> dict[str, np.ndarray]:
        """NumPy copies of every field (leading axis: snapshot world)."""
        return state_to_numpy(self.state)


#: Index of ``force`` among the observation kernel's arguments (set per recorded launch).
_OBS_FORCE_ARG = K.observation.OBS_FORCE_ARG


def _is_torch(x: Any) -> bool:
    return isinstance(x, torch.Tensor)


class _Staging:
    """A device buffer written in place from host data (a NumPy view on CPU, a torch copy on
    CUDA): the recorded launches that read it never see a new array."""

    def __init__(self, shape: tuple[int, ...], dtype: Any, device: str):
        self.array = wp.zeros(shape, dtype=dtype, device=device)
        self._host = self.array.numpy() if self.array.device.is_cpu else None
        self._torch = None if self._host is not None else wp.to_torch(self.array)

    def put(self, values: np.ndarray) -> None:
        n = values.shape[0]
        if self._host is not None:
            self._host[:n] = values
        else:
            self._torch[:n].copy_(torch.from_numpy(np.ascontiguousarray(values)))


class Simulator:
    """Batched driving simulator (see module docstring and ``docs/ARCHITECTURE.md``).

    Args:
        scenarios: the pool (a sequence of :class:`cpsim.Scenario`) or a prebuilt :class:`Model`
            (built for the same config and device).
        num_worlds: W, worlds stepped together.
        max_agents: A, agent slots per world (slot 0 = the scenario's ego).
        config: :class:`SimConfig` or a dict of its fields.
        device: "cpu" or "cuda[:N]".
        seed: seed of the NumPy generator used for scenario draws and p_train conditions.
        track_all: compute every event and metric for every agent. By default (False) only
            *tracked* agents get them: POLICY and IDM agents (and those the ``stop`` rule made
            STATIC), task agents (controllable at reset, whatever their controller now),
            slot 0 (the ego), and everyone with ``config.observe_all``. *Scenery* (REPLAY /
            STATIC agents without a task: parked cars, pedestrians, replayed traffic without a
            goal) is tested for collisions with tracked agents only (so the ego or a
            co-player hitting it is recorded on both sides: ``first_collision_step``,
            ``collision_partner``, outcome, fault), for off-road, goal and timeout; its lane
            fields, metrics accumulators and reward stay 0. Co-player harm (other vehicles that collided or went off-road) is therefore
            exact for everything the tracked agents do; only collisions between two scenery
            agents (both following their logs, so no agent's doing) go unrecorded. Set True
            for log statistics over every agent (``python -m cpsim.bench``'s replay sanity).
    """

    def __init__(self, scenarios: Sequence[Scenario] | Model, num_worlds: int, max_agents: int,
                 config: SimConfig | dict | None = None, device: str = "cpu", seed: int = 0,
                 track_all: bool = False):
        for name, value in (("num_worlds", num_worlds), ("max_agents", max_agents)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name}: must be a positive integer, got {value!r}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed: must be an integer >= 0, got {seed!r}")
        self.config = config if isinstance(config, SimConfig) else SimConfig.from_dict(config)
        wp.init()
        try:
            wp_device = wp.get_device(device)
        except Exception as exc:  # unknown or unavailable device
            raise ValueError(f"device: {device!r} is not available ({exc})") from None
        self.device = str(wp_device)
        self._cpu = bool(wp_device.is_cpu)
        # Per-agent kernels with a large body come in two launch shapes: one thread per agent
        # (CUDA) or one thread per world looping over its slots (CPU, where every thread
        # copies the State / ModelArrays arguments on entry). Same function, same results.
        self._events_kernel = K.metrics.events_world_kernel if self._cpu else K.metrics.events_kernel
        self._obs_kernel = K.observation.observation_world_kernel if self._cpu else K.observation.observation_kernel
        # the motion and IDM kernels get the same treatment where their modules offer a
        # per-world variant (``dynamics_world_kernel`` / ``idm_world_kernel``)
        world_dyn = getattr(K.dynamics, "dynamics_world_kernel", None) if self._cpu else None
        world_idm = getattr(K.controllers, "idm_world_kernel", None) if self._cpu else None
        self._dyn_kernel, self._dyn_per_world = (world_dyn, True) if world_dyn else (K.dynamics.dynamics_kernel, False)
        self._idm_kernel, self._idm_per_world = (world_idm, True) if world_idm else (K.controllers.idm_kernel, False)
        self.track_all = bool(track_all)
        self._torch_device = wp.device_to_torch(wp_device)
        if wp_device.is_cuda:
            # launch on torch's current stream so torch reads of the zero-copy outputs are
            # ordered after the kernels that wrote them
            wp.set_stream(wp.stream_from_torch(torch.cuda.current_stream(self._torch_device)), device=wp_device)
        K.load(self.device)
        if isinstance(scenarios, Model):
            if scenarios.config != self.config or scenarios.device != self.device:
                raise ValueError("scenarios: the Model was built for another config or device")
            self.model = scenarios
        else:
            self.model = Model(scenarios, self.config, self.device)
        self.num_worlds = int(num_worlds)
        self.max_agents = int(max_agents)
        self.num_actions = self.config.num_actions
        self.obs_layout = ObsLayout(num_partners=self.config.num_partners, num_road=self.config.num_road)
        self._params = make_params(self.config, self.obs_layout)
        self._rng = np.random.default_rng(int(seed))
        W, A, D = self.num_worlds, self.max_agents, self.obs_layout.size
        self.state = allocate_state(W, A, self.device)
        # per-step scratch (``present``, ``idm_accel``): rewritten by every step before it is
        # read, so never part of a snapshot, a restore or ``state_dict``
        self.scratch = allocate_scratch(W, A, self.device)
        self.control = Control.allocate(W, A, self.device)
        self._obs = wp.zeros((W, A, D), dtype=wp.float32, device=self.device)
        kp = max(self.config.num_partners, 1)
        self._sel_idx = wp.zeros((W, A, kp), dtype=wp.int32, device=self.device)
        self._sel_d2 = wp.zeros((W, A, kp), dtype=wp.float32, device=self.device)
        self._obs_clear = wp.zeros((W, A), dtype=wp.bool, device=self.device)
        # (partners, road segments, grid cell) written last per row: nothing yet, no cell
        filled = np.zeros((W, A, 3), np.int32)
        filled[..., 2] = -1
        self._obs_filled = wp.array(filled, dtype=wp.int32, device=self.device)
        self._trig = wp.zeros((W, A), dtype=wp.vec2f, device=self.device)
        self._prev_trig = wp.zeros((W, A), dtype=wp.vec2f, device=self.device)
        self._present_idx = wp.zeros((W, A), dtype=wp.int32, device=self.device)
        self._tracked_idx = wp.zeros((W, A), dtype=wp.int32, device=self.device)
        self._roster_n = wp.zeros((W, 2), dtype=wp.int32, device=self.device)
        self._radius = wp.zeros((W, A), dtype=wp.float32, device=self.device)
        self._all_worlds = wp.array(np.arange(W, dtype=np.int32), dtype=wp.int32, device=self.device)
        self._build_slot_tables()
        # reset staging: worlds, scenarios, conditions (written in place, read by recorded launches)
        self._reset_worlds = _Staging((W,), wp.int32, self.device)
        self._reset_scen = _Staging((W,), wp.int32, self.device)
        self._reset_cond = _Staging((W, A, NUM_CONDITION_FIELDS), wp.float32, self.device)
        self._make_views()
        self._has_idm = False
        self._step_launches = None
        self._reset_launch = None
        self._obs_launches: dict[int, tuple[Any, Any, wp.array]] = {}
        self._index_buffers: dict[int, _Staging] = {}
        self._arange: wp.array | None = None
        self.reset()

    # ------------------------------------------------------------------ setup
    def _build_slot_tables(self) -> None:
        G, A = self.model.num_scenarios, self.max_agents
        default = int(CONTROLLER_NAMES[self.config.default_controller])
        other = int(CONTROLLER_NAMES[self.config.other_controller])
        self._slot_table = np.full((G, A), -1, np.int32)
        self._ctrl_table = np.full((G, A), int(Controller.NONE), np.int32)
        self._task_table = np.zeros((G, A), bool)
        for g in range(G):
            order = self.model.slot_order[g][:A]
            ctrl = self.model.slot_controllable[g][:A]
            self._slot_table[g, :order.size] = order
            self._ctrl_table[g, :order.size] = np.where(ctrl, default, other)
            self._task_table[g, :order.size] = ctrl
        # device copies, uploaded once: reset_kernel reads them by scenario index
        dev = self.device
        self._slot_table_wp = wp.array(self._slot_table, dtype=wp.int32, device=dev)
        self._ctrl_table_wp = wp.array(self._ctrl_table, dtype=wp.int32, device=dev)
        self._task_table_wp = wp.array(self._task_table, dtype=wp.bool, device=dev)

    def _make_views(self) -> None:
        s = self.state
        t = wp.to_torch
        self.obs = t(self._obs)
        self.reward = t(s.reward)
        self.alive = t(s.alive)
        self.done = t(s.done)
        self.outcome = t(s.outcome)
        self.terminated = t(s.terminated)
        self.truncated = t(s.truncated)
        self.world_done = t(s.world_done)
        self.step_count = t(s.step_count)
        self.controllers = t(s.controller)
        self.conditions = t(s.conditions)
        self.xy = t(s.pos)
        self.heading = t(s.heading)
        self.speed = t(s.speed)
        self.accel = t(s.accel)
        self.steer = t(s.steer)
        self.velocity = t(s.vel)
        self.agent_index = t(s.agent_index)
        self.task_agent = t(s.task_agent)
        self.world_scenario = t(s.scenario)
        self.size = t(s.size)
        self.goal = t(s.goal)
        raw, wtd = t(s.reward_raw), t(s.reward_w)
        self.reward_terms: dict[str, torch.Tensor] = {}
        for i, name in enumerate(REWARD_TERMS):
            self.reward_terms[f"raw_{name}"] = raw[..., i]
            self.reward_terms[f"w_{name}"] = wtd[..., i]
        self.metrics: dict[str, torch.Tensor] = {name: t(getattr(s, name)) for name in METRIC_FIELDS}
        self._actions_t = t(self.control.actions)
        # NumPy views of the same memory (CPU only): the step path's host work uses these
        self._actions_np = self.control.actions.numpy() if self._cpu else None
        self._alive_np = s.alive.numpy() if self._cpu else None
        self._ctrl_np = s.controller.numpy() if self._cpu else None

    # ------------------------------------------------------------------ properties
    @property
    def policy_mask(self) -> torch.Tensor:
        """(W, A) bool: alive agents driven by the policy (a new tensor; on CPU computed with
        NumPy, no torch operator)."""
        if self._cpu:
            return torch.from_numpy(self._alive_np & (self._ctrl_np == int(Controller.POLICY)))
        return self.alive & (self.controllers == int(Controller.POLICY))

    def num_policy_agents(self) -> int:
        """Number of alive POLICY agents over all worlds (``policy_mask.sum()`` without a
        torch reduction on CPU)."""
        if self._cpu:
            return int(np.count_nonzero(self._alive_np & (self._ctrl_np == int(Controller.POLICY))))
        return int(self.policy_mask.sum())

    @property
    def scenarios(self) -> list[Scenario]:
        return self.model.scenarios

    @property
    def num_scenarios(self) -> int:
        return self.model.num_scenarios

    # ------------------------------------------------------------------ validation helpers
    def _worlds(self, worlds: Any, argument: str = "worlds", allow_duplicates: bool = False) -> np.ndarray:
        if worlds is None:
            return np.arange(self.num_worlds, dtype=np.int32)
        if _is_torch(worlds):
            worlds = worlds.detach().cpu().numpy()
        arr = np.asarray(worlds)
        if arr.ndim == 0:
            arr = arr.reshape(1)
        if arr.ndim != 1:
            raise ValueError(f"{argument}: expected a 1-D array of world indices, got shape {arr.shape}")
        if arr.size and not (np.issubdtype(arr.dtype, np.integer)):
            raise ValueError(f"{argument}: expected integer world indices, got dtype {arr.dtype}")
        if arr.size and (arr.min() < 0 or arr.max() >= self.num_worlds):
            raise ValueError(f"{argument}: world index out of range [0, {self.num_worlds})")
        if not allow_duplicates and arr.size > 1 and (
                len(set(arr.tolist())) if arr.size <= 64 else np.unique(arr).size) != arr.size:
            raise ValueError(f"{argument}: contains duplicate world indices")
        return arr.astype(np.int32)

    def _per_world_agents(self, values: np.ndarray, n: int, argument: str, trailing: tuple[int, ...] = ()) -> np.ndarray:
        """Broadcast values to (n, A, *trailing)."""
        shape = (n, self.max_agents, *trailing)
        try:
            return np.ascontiguousarray(np.broadcast_to(values, shape))
        except ValueError:
            raise ValueError(f"{argument}: shape {np.shape(values)} does not broadcast to {shape}") from None

    def _conditions(self, conditions: Any, n: int, argument: str = "conditions") -> np.ndarray:
        if _is_torch(conditions):
            conditions = conditions.detach().cpu().numpy()
        c = validate_conditions(np.asarray(conditions, dtype=np.float32), argument)
        return self._per_world_agents(c, n, argument, (NUM_CONDITION_FIELDS,)).astype(np.float32)

    def _actions_error(self, lo: int, hi: int) -> ValueError:
        return ValueError(f"actions: values must lie in [0, {self.num_actions}) for "
                          f"{self.config.dynamics} dynamics, got range [{lo}, {hi}]")

    def _write_actions(self, actions: Any) -> None:
        """Check ``actions`` and copy them into the int32 control array (nothing is written
        when a check fails). On CPU with NumPy: no torch operator over W*A."""
        W, A = self.num_worlds, self.max_agents
        if _is_torch(actions):
            t = actions.detach()
            if t.dtype == torch.bool or t.is_complex():
                raise ValueError(f"actions: expected integer action indices, got dtype {t.dtype}")
            if t.device.type != "cpu":
                self._write_actions_torch(t)
                return
            arr = t.numpy()
        else:
            arr = np.asarray(actions)
            if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
                raise ValueError(f"actions: expected a numeric array, got dtype {arr.dtype}")
        if arr.shape not in ((W, A), (W * A,)):
            raise ValueError(f"actions: expected shape ({W}, {A}) or ({W * A},), got {tuple(arr.shape)}")
        if arr.dtype == np.bool_ or np.issubdtype(arr.dtype, np.complexfloating):
            raise ValueError(f"actions: expected integer action indices, got dtype {arr.dtype}")
        if np.issubdtype(arr.dtype, np.floating):
            if not np.isfinite(arr).all():
                raise ValueError("actions: contains NaN or infinite values")
            if not (arr == np.round(arr)).all():
                raise ValueError("actions: floating-point actions must hold integral values")
        if arr.size:
            lo, hi = arr.min(), arr.max()
            if lo < 0 or hi >= self.num_actions:
                raise self._actions_error(int(lo), int(hi))
        arr = arr.reshape(W, A)
        if self._cpu:
            np.copyto(self._actions_np, arr, casting="unsafe")
        else:
            self._actions_t.copy_(torch.from_numpy(np.ascontiguousarray(arr, dtype=np.int32)))

    def _write_actions_torch(self, t: torch.Tensor) -> None:
        """Device tensors (CUDA): the same checks as torch operators on that device."""
        W, A = self.num_worlds, self.max_agents
        if tuple(t.shape) not in ((W, A), (W * A,)):
            raise ValueError(f"actions: expected shape ({W}, {A}) or ({W * A},), got {tuple(t.shape)}")
        if t.is_floating_point():
            if not bool(torch.isfinite(t).all()):
                raise ValueError("actions: contains NaN or infinite values")
            if not bool((t == torch.round(t)).all()):
                raise ValueError("actions: floating-point actions must hold integral values")
        if t.numel():
            lo, hi = int(t.min()), int(t.max())
            if lo < 0 or hi >= self.num_actions:
                raise self._actions_error(lo, hi)
        self._actions_t.copy_(t.reshape(W, A))

    # ------------------------------------------------------------------ launches
    def _obs_dim(self, n: int) -> int | tuple[int, int]:
        """Launch dimension of the observation kernel over ``n`` worlds (see __init__)."""
        return n if self._cpu else (n, self.max_agents)

    def _obs_launch_pair(self, worlds_wp: wp.array) -> tuple[Any, Any]:
        """Recorded (heading_trig, observation) launches over the index buffer ``worlds_wp``
        (dimension and ``force`` are set per call)."""
        key = id(worlds_wp)
        pair = self._obs_launches.get(key)
        if pair is None or pair[2] is not worlds_wp:
            dev, A = self.device, self.max_agents
            trig = K.observation.launch_heading_trig(self.state, worlds_wp, self._trig, dim=(1, A), device=dev,
                                                     record=True)
            obs = K.observation.launch_observation(
                self.state, self.model.arrays, self._params, worlds_wp, self._trig, 1, self._obs, self._sel_idx,
                self._sel_d2, self._obs_clear, self._obs_filled, dim=self._obs_dim(1), device=dev, record=True,
                kernel=self._obs_kernel)
            pair = (trig, obs, worlds_wp)
            self._obs_launches[key] = pair
        return pair[0], pair[1]

    def _launch_obs(self, worlds_wp: wp.array, n: int, force: bool = True, trig: bool = True) -> None:
        """Observation of the first ``n`` worlds listed in ``worlds_wp`` (after the heading
        (cos, sin) pre-pass unless ``trig`` is False). ``force`` rewrites whole rows; without
        it only entries that changed are written, which is exact as long as nobody wrote into
        ``obs`` (rows hold what the kernel's bookkeeping says they hold)."""
        if n == 0:
            return
        trig_launch, obs_launch = self._obs_launch_pair(worlds_wp)
        if trig:
            trig_launch.set_dim((n, self.max_agents))
            trig_launch.launch()
        obs_launch.set_dim(self._obs_dim(n))
        obs_launch.set_param_at_index(_OBS_FORCE_ARG, int(force))
        obs_launch.launch()

    def _world_array(self, worlds: np.ndarray, slot: int = 0) -> wp.array:
        """Index buffer ``slot`` holding ``worlds`` in its first entries (kernels launched over
        len(worlds) read only those); reused across calls to avoid per-call allocations."""
        n = worlds.size
        buf = self._index_buffers.get(slot)
        if buf is None or buf.array.shape[0] < n:
            buf = _Staging((max(n, self.num_worlds),), wp.int32, self.device)
            self._index_buffers[slot] = buf
        if n:
            buf.put(np.asarray(worlds, dtype=np.int32))
        return buf.array

    def _arange_array(self, n: int) -> wp.array:
        if self._arange is None or self._arange.shape[0] < n:
            self._arange = wp.array(np.arange(max(n, self.num_worlds), dtype=np.int32), dtype=wp.int32,
                                    device=self.device)
        return self._arange

    def _controllers_np(self, worlds: np.ndarray | None = None) -> np.ndarray:
        """Controllers of ``worlds`` (all when None) as NumPy (a view on CPU when all)."""
        if self._cpu:
            return self._ctrl_np if worlds is None else self._ctrl_np[worlds]
        c = self.controllers if worlds is None else self.controllers[torch.as_tensor(
            worlds.astype(np.int64), device=self._torch_device)]
        return c.cpu().numpy()

    def _refresh_has_idm(self, worlds: np.ndarray | None = None) -> None:
        """Whether a step must run the IDM kernel. With ``worlds``, only those worlds changed
        (an IDM agent there switches it on; it stays on until the next full check)."""
        if worlds is None:
            self._has_idm = bool((self._controllers_np() == int(Controller.IDM)).any())
        elif not self._has_idm:
            self._has_idm = bool((self._controllers_np(worlds) == int(Controller.IDM)).any())

    # ------------------------------------------------------------------ public API
    def reset(self, worlds: Any = None, scenario_index: Any = None, conditions: Any = None) -> None:
        """(Re)start worlds on scenarios of the pool.

        Args:
            worlds: None (all) or world indices.
            scenario_index: None (seeded uniform draw from the pool), an int, or one per world.
            conditions: None (p_train draw per agent), or raw conditions broadcastable to
                (len(worlds), A, 10).
        Draw order on the simulator's RNG: scenario indices, then conditions.
        """
        w = self._worlds(worlds)
        n = w.size
        if n == 0:
            return
        G = self.model.num_scenarios
        if scenario_index is None:
            scen = None
        else:
            if _is_torch(scenario_index):
                scenario_index = scenario_index.detach().cpu().numpy()
            s_arr = np.asarray(scenario_index)
            if not np.issubdtype(s_arr.dtype, np.integer):
                raise ValueError(f"scenario_index: expected integers, got dtype {s_arr.dtype}")
            try:
                scen = np.broadcast_to(s_arr, (n,)).astype(np.int32)
            except ValueError:
                raise ValueError(f"scenario_index: shape {s_arr.shape} does not match {n} worlds") from None
            if scen.min() < 0 or scen.max() >= G:
                raise ValueError(f"scenario_index: out of range [0, {G})")
        cond = None if conditions is None else self._conditions(conditions, n)
        # validated: from here on the state changes
        if scen is None:
            scen = self._rng.integers(0, G, size=n).astype(np.int32)
        if cond is None:
            cond = sample_conditions(self._rng, (n, self.max_agents))
        self._reset_worlds.put(w)
        self._reset_scen.put(scen)
        self._reset_cond.put(cond)
        if self._reset_launch is None:
            self._reset_launch = K.snapshot.launch_reset(
                self.state, self.model.arrays, self._params, self._reset_worlds.array, self._reset_scen.array,
                self._slot_table_wp, self._ctrl_table_wp, self._task_table_wp, self._reset_cond.array,
                int(self.track_all), self._trig, dim=(1, self.max_agents), device=self.device, record=True)
        self._reset_launch.set_dim((n, self.max_agents))
        self._reset_launch.launch()
        # reset_kernel wrote the heading (cos, sin); rows not forced: exact (see _launch_obs)
        self._launch_obs(self._reset_worlds.array, n, force=False, trig=False)
        idm = bool((self._ctrl_table[scen] == int(Controller.IDM)).any())
        self._has_idm = idm if n == self.num_worlds else (self._has_idm or idm)

    def step(self, actions: Any) -> None:
        """Advance every world by one decision. ``actions`` (W, A) (or (W*A,)) integer
        indices, NumPy or torch; only alive POLICY agents read them. Worlds whose episode is
        over (step_count == episode_steps) do not move; their done flags and rewards read 0."""
        self._write_actions(actions)
        if self._step_launches is None:
            self._step_launches = self._record_step_launches()
        idm, rest = self._step_launches
        if self._has_idm:
            idm.launch()
        for launch in rest:
            launch.launch()

    def _record_step_launches(self):
        """Recorded launches of the step kernels (their arguments never change: the state
        arrays are allocated once), which skips most of wp.launch's per-call overhead. Each
        comes from the kernel's launcher (``cpsim.kernels.*.launch_*``) with ``record=True``."""
        dim = (self.num_worlds, self.max_agents)
        s, sc, m, p, dev = self.state, self.scratch, self.model.arrays, self._params, self.device
        track_all = int(self.track_all)
        roster = [self._trig, self._prev_trig, self._present_idx, self._tracked_idx, self._roster_n, self._radius]
        W = self.num_worlds
        rec = {"device": dev, "record": True}
        idm = K.controllers.launch_idm(s, sc, m, p, dim=W if self._idm_per_world else dim, kernel=self._idm_kernel,
                                       **rec)
        rest = [
            K.dynamics.launch_dynamics(s, sc, m, p, self.control.actions, dim=W if self._dyn_per_world else dim,
                                       kernel=self._dyn_kernel, **rec),
            K.observation.launch_prepare(s, sc, p, track_all, *roster, dim=W, **rec),
            K.metrics.launch_events(s, sc, m, p, track_all, *roster, dim=W if self._cpu else dim,
                                    kernel=self._events_kernel, **rec),
            K.metrics.launch_finish(s, p, self._all_worlds, 1, dim=W, **rec),
            K.observation.launch_observation(s, m, p, self._all_worlds, self._trig, 0, self._obs, self._sel_idx,
                                             self._sel_d2, self._obs_clear, self._obs_filled,
                                             dim=self._obs_dim(W), kernel=self._obs_kernel, **rec),
        ]
        return idm, rest

    def set_conditions(self, conditions: Any, worlds: Any = None) -> None:
        """Set raw conditions, shape broadcastable to (len(worlds), A, 10); refreshes the
        observation of those worlds (its condition slice)."""
        w = self._worlds(worlds)
        cond = self._conditions(conditions, w.size)
        if w.size == 0:
            return
        if self._cpu:
            self.state.conditions.numpy()[w] = cond
        else:
            idx = torch.as_tensor(w.astype(np.int64), device=self._torch_device)
            self.conditions[idx] = torch.as_tensor(cond, device=self._torch_device)
        self._launch_obs(self._world_array(w), w.size)

    def set_controllers(self, controllers: Any, worlds: Any = None) -> None:
        """Set controllers (``Controller`` codes, broadcastable to (len(worlds), A)).

        Empty slots keep NONE whatever is given; occupied slots must get POLICY, REPLAY,
        IDM or STATIC. Agents switched to IDM continue from the nearest point of their path.
        """
        w = self._worlds(worlds)
        if _is_torch(controllers):
            controllers = controllers.detach().cpu().numpy()
        c = np.asarray(controllers)
        if c.dtype == object or not np.issubdtype(c.dtype, np.integer):
            raise ValueError(f"controllers: expected integer Controller codes, got dtype {c.dtype}")
        c = self._per_world_agents(c, w.size, "controllers").astype(np.int32)
        if c.size and (c.min() < 0 or c.max() > int(Controller.NONE)):
            raise ValueError(f"controllers: codes must lie in [0, {int(Controller.NONE)}]")
        if w.size == 0:
            return
        if self._cpu:
            occupied = self.state.agent_index.numpy()[w] >= 0
        else:
            idx = torch.as_tensor(w.astype(np.int64), device=self._torch_device)
            occupied = (self.agent_index[idx] >= 0).cpu().numpy()
        if np.any(occupied & (c == int(Controller.NONE))):
            raise ValueError("controllers: NONE is only valid for empty slots")
        new = np.where(occupied, c, int(Controller.NONE)).astype(np.int32)
        old = self._controllers_np(w)
        attach = (new == int(Controller.IDM)) & (old != int(Controller.IDM))
        if self._cpu:
            self._ctrl_np[w] = new
        else:
            self.controllers[idx] = torch.as_tensor(new, device=self._torch_device)
        w_wp = self._world_array(w)
        if attach.any():
            K.controllers.launch_idm_attach(self.state, self.model.arrays, w_wp,
                                            wp.array(attach, dtype=wp.bool, device=self.device),
                                            dim=(w.size, self.max_agents), device=self.device)
        K.metrics.launch_finish(self.state, self._params, w_wp, 0, dim=w.size, device=self.device)
        self._refresh_has_idm()

    # ------------------------------------------------------------------ snapshots
    def snapshot(self, worlds: Any, out: Snapshot | None = None) -> Snapshot:
        """Copy the full state of ``worlds`` into device storage (``out`` is reused when given
        and of the same size)."""
        w = self._worlds(worlds, allow_duplicates=True)
        n = w.size
        if n == 0:
            raise ValueError("worlds: snapshot of zero worlds")
        if out is not None:
            self._check_snapshot(out, "out")
            if out.num_worlds != n:
                raise ValueError(f"out: holds {out.num_worlds} worlds, {n} requested")
            snap = out
            snap.worlds = w.copy()
        else:
            snap = Snapshot(state=allocate_state(n, self.max_agents, self.device), num_worlds=n, worlds=w.copy(),
                            fingerprint=self.model.fingerprint, config=self.config,
                            max_agents=self.max_agents, device=self.device)
        K.snapshot.launch_copy_worlds(self.state, snap.state, self._world_array(w), self._arange_array(n),
                                      dim=(n, self.max_agents), device=self.device)
        return snap

    def _check_snapshot(self, snapshot: Any, argument: str = "snapshot") -> None:
        if not isinstance(snapshot, Snapshot):
            raise ValueError(f"{argument}: expected a cpsim.Snapshot, got {type(snapshot).__name__}")
        if snapshot.fingerprint != self.model.fingerprint:
            raise ValueError(f"{argument}: taken on a different scenario pool")
        if snapshot.config != self.config:
            raise ValueError(f"{argument}: taken with a different SimConfig")
        if snapshot.max_agents != self.max_agents:
            raise ValueError(f"{argument}: max_agents {snapshot.max_agents} != {self.max_agents}")
        if snapshot.device != self.device:
            raise ValueError(f"{argument}: lives on {snapshot.device}, simulator on {self.device}")

    def restore(self, snapshot: Snapshot, worlds: Any, source: Any = None) -> None:
        """Write snapshot worlds back: world ``worlds[i]`` gets snapshot world ``source[i]``
        (default ``i``; repeat a source index to broadcast one root into many worlds).
        Works across Simulators built on the same pool, config and max_agents."""
        self._check_snapshot(snapshot)
        w = self._worlds(worlds)
        n = w.size
        if source is None:
            if n != snapshot.num_worlds:
                raise ValueError(f"worlds: {n} given for a snapshot of {snapshot.num_worlds} worlds "
                                 "(pass source= to map them)")
            src = np.arange(n, dtype=np.int32)
        else:
            if _is_torch(source):
                source = source.detach().cpu().numpy()
            src_arr = np.asarray(source)
            if not np.issubdtype(src_arr.dtype, np.integer):
                raise ValueError(f"source: expected integers, got dtype {src_arr.dtype}")
            try:
                src = np.broadcast_to(src_arr, (n,)).astype(np.int32)
            except ValueError:
                raise ValueError(f"source: shape {src_arr.shape} does not match {n} worlds") from None
            if n and (src.min() < 0 or src.max() >= snapshot.num_worlds):
                raise ValueError(f"source: index out of range [0, {snapshot.num_worlds})")
        if n == 0:
            return
        w_wp = self._world_array(w)
        K.snapshot.launch_copy_worlds(snapshot.state, self.state, self._world_array(src, slot=1), w_wp,
                                      dim=(n, self.max_agents), device=self.device)
        self._launch_obs(w_wp, n)
        self._refresh_has_idm(w)

    def refresh(self, worlds: Any = None) -> None:
        """Recompute the observation of ``worlds`` from the current state (after editing the
        state through the output views, e.g. to place agents in tests or tools)."""
        w = self._worlds(worlds)
        self._launch_obs(self._world_array(w), w.size)

    def state_dict(self) -> dict[str, np.ndarray]:
        """NumPy copies of the complete state (every State field) and the observation."""
        d = state_to_numpy(self.state)
        d["obs"] = self._obs.numpy().copy()
        return d

    # ------------------------------------------------------------------ convenience
    def scenario_of(self, world: int) -> Scenario:
        """The Scenario world ``world`` is running."""
        return self.model.scenarios[int(self.world_scenario[int(world)])]

    def __repr__(self) -> str:
        return (f"Simulator(W={self.num_worlds}, A={self.max_agents}, scenarios={self.num_scenarios}, "
                f"dynamics={self.config.dynamics!r}, device={self.device!r})")


__all__ = ["Simulator", "Snapshot", "state_field_names"]
