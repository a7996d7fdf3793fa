"""Groups of closed-loop continuations from interaction states: the shared machinery of
the continuation-based baselines (DAPO, VinePPO, PlannerRFT, CRAFT).

Timeline of one generation (:class:`ContinuationPPO`):

1. **Roots.** Before every decision of the main self-play rollout, each live POLICY agent
   is tested for an *interaction trigger* (:func:`interaction_trigger`): another live agent
   within ``trigger_distance`` metres, or a time to collision below ``trigger_ttc``
   seconds (constant velocities, closing faster than 0.1 m/s, within 50 m). A triggered
   agent becomes a candidate root (its world is snapshotted before the decision, with
   every agent's actor/critic LSTM memory, condition and last action), at most once per
   ``trigger_cooldown`` decisions per agent, and only while ``min_horizon`` decisions are
   left before the episode's deadline. Candidates are kept by reservoir sampling
   (``root_pool`` per rollout), so the roots are a uniform sample of the rollout's
   interaction states whatever their number.
2. **Groups.** Right before the rollout's returns and advantages are computed (so the
   continuations run under the very policy that collected the rollout, and VinePPO can still
   change the values GAE reads), groups of ``group_size`` continuations (1 + 5, as
   CounterPlay's factual branch + 5 candidates) run from the roots, batched in a second
   simulator on the same pool: each continuation restores the root, every agent keeps its
   memory and condition, and the focal agent samples its own actions (fresh inverse-CDF
   draws, one per continuation unless a method pairs continuations). Co-players follow
   a per-continuation *traffic mode*: ``policy`` (closed loop: they keep driving with the
   policy and their own memories and draws), ``replay`` (they follow their logs:
   controller REPLAY from the root on) or ``proxy`` (their actions come from a method's
   traffic proxy). A continuation runs until its focal agent's task ends, at the latest at
   the original deadline (CounterPlay's branch horizon).
3. **Budget.** Groups are admitted in waves while their projected cost (an upper bound:
   ``group_size`` x agents alive at the root x decisions to the deadline) fits the
   generation's allowance of ``branch_cap`` x its main transitions (CounterPlay's cap).
   Every transition counts toward ``B_post`` exactly as CounterPlay's branches do: every
   agent that was a decision-making (POLICY) agent at the root and is still alive in a
   running continuation world counts once per step, whoever drives it then (policy, log or
   proxy), and whatever happens to the group afterwards (groups a method drops count too).
4. **Returns.** The return of a continuation is the focal agent's discounted conditioned
   return from the root, ``sum_k gamma^k r_k``, plus ``gamma^K V(s_K)`` from the critic when
   the focal task is cut at the deadline (a timeout bootstraps, as the main rollout's
   truncated episodes do), so a root's continuation mean estimates the same ``V(s_root)``
   the critic estimates.

Shapes: W worlds, A agent slots, G continuations per group, T decisions, D observation size.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch as th
from sb3_contrib.common.recurrent.type_aliases import RNNStates

from cpalgo.common.hooked_train import HookedPPO, check_number
from cpalgo.common.policy_utils import actor_logits, inverse_cdf_sample, policy_step_logits, put_states, take_states
from cpalgo.counterplay.branches import GrowingSimulator, branch_simulator_factory
from cpalgo.methods.base import base_vec_env
from cpsim.arrays import to_numpy as _np

__all__ = [
    "TRIGGER_MODES", "TRAFFIC_MODES", "action_grid", "neutral_action", "interaction_trigger",
    "ContinuationRoot", "RootReservoir", "GroupJob", "GroupResult", "ContinuationRunner",
    "ContinuationBatch", "collate_continuations", "continuation_logits", "group_normalized",
    "mixed_outcome", "ContinuationPPO",
]

#: Root triggers: distance to the nearest agent, time to collision, or either.
TRIGGER_MODES: tuple[str, ...] = ("distance", "ttc", "either")
#: How co-players drive in a continuation.
TRAFFIC_MODES: tuple[str, ...] = ("policy", "replay", "proxy")
_TRAFFIC_CODE = {name: i for i, name in enumerate(TRAFFIC_MODES)}
#: cpsim.Outcome codes (kept here so the array code needs no simulator import)
OUTCOME_GOAL, OUTCOME_TIMEOUT = 1, 4
#: Controller codes (cpsim.config.Controller)
_POLICY, _REPLAY = 0, 1
#: pairs further apart than this never trigger on time to collision (m)
TTC_RANGE_M = 50.0
#: closing speed below which there is no time to collision (m/s)
TTC_MIN_CLOSING = 0.1


# ============================================================================ actions
def action_grid(dynamics: str) -> tuple[np.ndarray, np.ndarray]:
    """The two control components of a discrete action set: ``(first, second)`` value
    tables, action index = ``i * len(second) + j``.

    ``jerk``: longitudinal jerk {-15, -4, 0, 4} x lateral jerk {-4, 0, 4} (m/s^3);
    ``classic``: acceleration (m/s^2) x steering angle (rad).
    """
    from cpsim.config import CLASSIC_ACCEL, CLASSIC_STEER, JERK_LAT, JERK_LONG

    if dynamics == "jerk":
        return JERK_LONG.copy(), JERK_LAT.copy()
    if dynamics == "classic":
        return CLASSIC_ACCEL.copy(), CLASSIC_STEER.copy()
    raise ValueError(f"dynamics: unknown model {dynamics!r}; accepted: ['classic', 'jerk']")


def neutral_action(dynamics: str) -> int:
    """The action whose two components are both zero (jerk: 7, classic: 45)."""
    first, second = action_grid(dynamics)
    return int(np.argmin(np.abs(first)) * second.size + np.argmin(np.abs(second)))


# ============================================================================ trigger
def interaction_trigger(xy: np.ndarray, velocity: np.ndarray, alive: np.ndarray, candidates: np.ndarray,
                        mode: str = "ttc", distance: float = 10.0, ttc: float = 3.0) -> np.ndarray:
    """Which candidate agents approach another agent of their world.

    Args:
        xy: (W, A, 2) positions (m); velocity: (W, A, 2) world-frame velocities (m/s).
        alive: (W, A) bool, present agents (any controller) that others can meet.
        candidates: (W, A) bool, the agents that may trigger (live POLICY agents).
        mode: ``distance`` (another alive agent closer than ``distance`` m, centre to
            centre), ``ttc`` (a time to collision below ``ttc`` s with another alive agent
            within 50 m that closes faster than 0.1 m/s) or ``either``.
    Returns:
        (W, A) bool.
    """
    if mode not in TRIGGER_MODES:
        raise ValueError(f"trigger: expected one of {TRIGGER_MODES}, got {mode!r}")
    xy = np.asarray(xy, np.float64)
    vel = np.asarray(velocity, np.float64)
    alive = np.asarray(alive, bool)
    cand = np.asarray(candidates, bool)
    out = np.zeros(cand.shape, bool)
    worlds = np.flatnonzero(cand.any(1))
    if worlds.size == 0:
        return out
    p = xy[worlds][:, None, :, :] - xy[worlds][:, :, None, :]  # (w, A, A, 2): j relative to i
    v = vel[worlds][:, None, :, :] - vel[worlds][:, :, None, :]
    d = np.sqrt((p ** 2).sum(-1))
    a = alive.shape[1]
    other = alive[worlds][:, None, :] & ~np.eye(a, dtype=bool)[None]
    hit = np.zeros(d.shape, bool)
    if mode in ("distance", "either"):
        hit |= other & (d < float(distance))
    if mode in ("ttc", "either"):
        with np.errstate(divide="ignore", invalid="ignore"):
            closing = -(p * v).sum(-1) / np.maximum(d, 1e-6)
            t = np.where(closing > TTC_MIN_CLOSING, d / closing, np.inf)
        hit |= other & (d < TTC_RANGE_M) & (t < float(ttc))
    out[worlds] = hit.any(-1) & cand[worlds]
    return out


# ============================================================================ roots
@dataclass
class ContinuationRoot:
    """One interaction state of the main rollout that a group of continuations restarts.

    Attributes:
        world, focal: main-simulator world and the focal agent's slot.
        step: the root decision (episode clock); deadline: the episode's decision count.
        snapshot, snapshot_row: simulator snapshot holding the world, and its row there.
        memory: (4, layers, A, hidden) actor h, c and critic h, c of every agent at the root.
        conditions: (A, 10) raw conditions of every agent.
        last_actions: (A,) the action each agent took at the previous decision (neutral at
            an episode's first decision).
        deciding: (A,) bool, live POLICY agents at the root (the agents whose transitions count).
        buffer_pos, env_index: where the root decision sits in the rollout buffer.
    """

    world: int
    focal: int
    step: int
    deadline: int
    snapshot: Any
    snapshot_row: int
    memory: th.Tensor
    conditions: np.ndarray
    last_actions: np.ndarray
    deciding: np.ndarray
    buffer_pos: int
    env_index: int

    @property
    def horizon(self) -> int:
        """Decisions from the root to the deadline."""
        return int(self.deadline - self.step)

    def projected_transitions(self, group_size: int) -> int:
        """Upper bound of the agent transitions of ``group_size`` continuations."""
        return int(group_size) * int(np.count_nonzero(self.deciding)) * self.horizon


class RootReservoir:
    """Uniform sample of at most ``capacity`` roots out of every root offered (reservoir
    sampling, Algorithm R), seeded."""

    def __init__(self, capacity: int, rng: np.random.Generator) -> None:
        self.capacity = int(capacity)
        self.rng = rng
        self.roots: list[ContinuationRoot] = []
        self.offered = 0

    def clear(self) -> None:
        self.roots, self.offered = [], 0

    def slots_for(self, n: int) -> list[int]:
        """Decide where ``n`` new candidates go: for each, the index it takes in
        :attr:`roots` (``len(roots)`` appends, -1 drops it). Call :meth:`put` with the
        accepted roots in the same order."""
        out = []
        size = len(self.roots)
        for _ in range(int(n)):
            self.offered += 1
            if size < self.capacity:
                out.append(size)
                size += 1
            else:
                j = int(self.rng.integers(self.offered))
                out.append(j if j < self.capacity else -1)
        return out

    def put(self, index: int, root: ContinuationRoot) -> None:
        if index == len(self.roots):
            self.roots.append(root)
        else:
            self.roots[index] = root


# ============================================================================ runner
@dataclass
class GroupJob:
    """One group: ``G`` continuations of one root.

    Attributes:
        root: the root.
        traffic: (G,) traffic mode of each continuation (names of :data:`TRAFFIC_MODES`).
        temperature: (G,) focal sampling temperature (> 0; 1 samples the policy itself).
        draw_ids: (G,) int, continuations with the same id share the focal agent's
            uniforms (default: all different, i.e. independent samples).
    """

    root: ContinuationRoot
    traffic: Sequence[str]
    temperature: np.ndarray | None = None
    draw_ids: np.ndarray | None = None

    @property
    def size(self) -> int:
        return len(self.traffic)


@dataclass
class GroupResult:
    """What the continuations of one group produced (all arrays over G continuations).

    Attributes:
        returns: (G,) focal discounted return from the root, bootstrapped at the deadline.
        completed: (G,) bool, the focal agent reached its goal; outcome: (G,) its Outcome code.
        transitions: (G,) agent transitions counted toward B_post.
        length: (G,) focal decisions taken.
        obs: (G, T, D) focal observations before each decision (what the policy saw).
        actions: (G, T) int64 focal actions; logp_old: (G, T) their log-probability under
            the (untempered) policy that sampled them; alive: (G, T) bool focal decided.
        rewards: (G, T) focal conditioned rewards.
        xy: (G, T + 1, A, 2) positions before each decision and after the last one.
        coplayer_actions: (G, T, A) int64 actions written for every agent (-1: none).
        controllers: (G, A) controllers right after the root was restored and the traffic
            mode applied.
    """

    returns: np.ndarray
    completed: np.ndarray
    outcome: np.ndarray
    transitions: np.ndarray
    length: np.ndarray
    obs: th.Tensor
    actions: th.Tensor
    logp_old: th.Tensor
    alive: th.Tensor
    rewards: th.Tensor
    xy: np.ndarray
    coplayer_actions: np.ndarray
    controllers: np.ndarray


#: (last actions (n,), decisions since the root (int)) -> actions (n,)
ProxyFn = Callable[[np.ndarray, int], np.ndarray]


class ContinuationRunner(GrowingSimulator):
    """Runs :class:`GroupJob` lists batched on a second simulator (see module docstring).

    Args:
        make_simulator: ``num_worlds -> Simulator`` (:func:`branch_simulator_factory`).
        policy: the recurrent policy (evaluated under ``th.no_grad``).
        gamma: discount of the continuation returns.
        generator: torch generator of the uniforms.
        proxy: co-player actions of ``proxy`` continuations (required when one is run).
        record: keep positions and every agent's actions (tests, inspection).
        clip_reward: see :class:`cpalgo.counterplay.branches.GrowingSimulator` (the
            algorithm's ``clip_reward``).
    """

    def __init__(self, make_simulator: Callable[[int], Any], policy: Any, gamma: float,
                 generator: th.Generator | None = None, proxy: ProxyFn | None = None, record: bool = True,
                 clip_reward: float | None = None) -> None:
        super().__init__(make_simulator, policy, generator, clip_reward)
        self.gamma = float(gamma)
        self.proxy = proxy
        self.record = bool(record)

    @th.no_grad()
    def run(self, jobs: Sequence[GroupJob]) -> list[GroupResult]:
        """Run every continuation of every job; one :class:`GroupResult` per job."""
        from cpsim.envs.selfplay import OBS_BOUND

        if not jobs:
            return []
        sizes = np.array([j.size for j in jobs], np.int64)
        sim, offsets, n_used = self.lay_out(sizes)
        n_worlds = self._capacity
        a = int(sim.max_agents)
        device = self.policy.device
        traffic = np.concatenate([[_TRAFFIC_CODE[m] for m in j.traffic] for j in jobs]).astype(np.int64)
        if np.any(traffic == _TRAFFIC_CODE["proxy"]) and self.proxy is None:
            raise ValueError("traffic: a proxy continuation needs the runner's proxy function")
        t_max = int(max(j.root.horizon for j in jobs))
        if t_max <= 0:
            raise ValueError("jobs: every root must lie before its deadline")

        # --- restore the roots, then apply the traffic modes
        by_snapshot: dict[int, tuple[Any, list[int], list[int]]] = {}
        for k, job in enumerate(jobs):
            entry = by_snapshot.setdefault(id(job.root.snapshot), (job.root.snapshot, [], []))
            for b in range(job.size):
                entry[1].append(int(offsets[k] + b))
                entry[2].append(int(job.root.snapshot_row))
        for snapshot, worlds, rows in by_snapshot.values():
            sim.restore(snapshot, np.asarray(worlds, np.int64), source=np.asarray(rows, np.int64))
        world_job = np.repeat(np.arange(len(jobs)), sizes)
        focal = np.concatenate([np.full(j.size, j.root.focal) for j in jobs]).astype(np.int64)
        counted = np.concatenate([np.repeat(j.root.deciding[None].astype(bool), j.size, 0) for j in jobs])  # (n, A)
        is_focal = np.zeros((n_used, a), bool)
        is_focal[np.arange(n_used), focal] = True
        replay = np.flatnonzero(traffic == _TRAFFIC_CODE["replay"])
        if replay.size:
            ctrl = _np(sim.controllers)[replay].astype(np.int32)
            co = (ctrl == _POLICY) & counted[replay] & ~is_focal[replay]  # live co-players of the root
            sim.set_controllers(np.where(co, _REPLAY, ctrl).astype(np.int32), worlds=replay)
        controllers = _np(sim.controllers)[:n_used].astype(np.int64).copy()
        proxy_rows = (traffic == _TRAFFIC_CODE["proxy"])[:, None] & ~is_focal & counted  # (n, A)
        last_actions = np.concatenate([np.repeat(j.root.last_actions[None], j.size, 0) for j in jobs]).astype(np.int64)

        # --- memories (layers, n_worlds * A, hidden)
        layers, hidden = jobs[0].root.memory.shape[1], jobs[0].root.memory.shape[3]

        def memory(part: int) -> th.Tensor:
            m = th.zeros(layers, n_worlds, a, hidden, device=device)
            for k, job in enumerate(jobs):
                m[:, offsets[k]:offsets[k + 1]] = job.root.memory[part].to(device)[:, None]
            return m.reshape(layers, n_worlds * a, hidden)

        states = RNNStates((memory(0), memory(1)), (memory(2), memory(3)))

        # --- per-world settings
        temp = np.concatenate([np.ones(j.size) if j.temperature is None else np.asarray(j.temperature, np.float64)
                               for j in jobs]).astype(np.float32)
        if np.any(~(temp > 0)):
            raise ValueError("temperature: every continuation's temperature must be > 0")
        draw = np.concatenate([np.arange(j.size) if j.draw_ids is None else np.asarray(j.draw_ids, np.int64)
                               for j in jobs])
        draw_key = world_job * (int(sizes.max()) + 1) + draw
        _, draw_index = np.unique(draw_key, return_inverse=True)
        n_draws = int(draw_index.max()) + 1
        steps_left = np.repeat([j.root.horizon for j in jobs], sizes)
        d = int(sim.obs.shape[-1])
        f_obs = th.zeros(n_used, t_max, d, device=device)
        f_actions = th.zeros(n_used, t_max, dtype=th.long, device=device)
        f_logp = th.zeros(n_used, t_max, device=device)
        f_rewards = th.zeros(n_used, t_max, device=device)
        f_alive = th.zeros(n_used, t_max, dtype=th.bool, device=device)
        all_actions = np.full((n_used, t_max, a), -1, np.int64) if self.record else np.zeros((n_used, 0, a), np.int64)
        xy = np.zeros((n_used, t_max + 1 if self.record else 0, a, 2), np.float32)
        transitions = np.zeros(n_used, np.int64)
        running = np.ones(n_used, bool)
        rows_u = np.arange(n_used)
        focal_flat = th.as_tensor(rows_u * a + focal, device=device)
        temp_t = th.as_tensor(temp, device=device)
        draw_t = th.as_tensor(draw_index, device=device)

        t = 0
        for t in range(t_max):
            deciding_all = _np(sim.policy_mask).astype(bool)  # (n_worlds, A)
            world_done = _np(sim.world_done).astype(bool)[:n_used]
            focal_live = deciding_all[rows_u, focal]
            running &= ~world_done & (t < steps_left) & focal_live
            if self.record:
                xy[:, t] = _np(sim.xy)[:n_used]
            if not running.any():
                break
            alive = _np(sim.alive).astype(bool)[:n_used]
            transitions += (alive & counted & running[:, None]).sum(1)
            deciding = np.zeros((n_worlds, a), bool)
            deciding[:n_used] = deciding_all[:n_used] & running[:, None]
            by_policy = deciding.copy()
            by_policy[:n_used] &= ~proxy_rows
            rows = th.as_tensor(np.flatnonzero(by_policy.reshape(-1)), device=device)
            obs = sim.obs.to(device).float().reshape(n_worlds * a, d).clamp(-OBS_BOUND, OBS_BOUND)
            logits, _, sub_states = policy_step_logits(self.policy, obs[rows], take_states(states, rows),
                                                       th.zeros(rows.numel(), device=device))
            states = put_states(states, rows, sub_states)
            full = th.zeros(n_worlds * a, logits.shape[-1], device=device)
            full[rows] = logits
            focal_logits = full[focal_flat]  # (n_used, n_actions), untempered
            scaled = full.clone()
            scaled[focal_flat] = focal_logits / temp_t[:, None]
            u = th.rand(n_worlds, a, generator=self.generator).to(device)
            u_focal = th.rand(n_draws, generator=self.generator).to(device)
            u[rows_u, focal] = u_focal[draw_t]
            actions = inverse_cdf_sample(scaled, u.reshape(-1)).reshape(n_worlds, a).cpu().numpy()
            if proxy_rows.any():
                pr = proxy_rows & deciding[:n_used]
                if pr.any():
                    actions[:n_used][pr] = np.asarray(self.proxy(last_actions[pr], t), np.int64)
            actions = np.where(deciding, actions, 0)

            f_dec = th.as_tensor(deciding[rows_u, focal], device=device)
            f_alive[:, t] = f_dec
            fa = th.as_tensor(actions[rows_u, focal], device=device)
            f_actions[:, t] = fa
            f_logp[:, t] = th.log_softmax(focal_logits, -1).gather(-1, fa[:, None]).squeeze(-1) * f_dec
            f_obs[:, t] = obs[focal_flat] * f_dec[:, None]
            if self.record:
                all_actions[:, t] = np.where(deciding[:n_used], actions[:n_used], -1)
            sim.step(actions)
            f_rewards[:, t] = self.focal_reward(sim, rows_u, focal, device) * f_dec
        else:
            if self.record:
                xy[:, t_max] = _np(sim.xy)[:n_used]

        # --- outcomes, returns, deadline bootstrap
        outcome = _np(sim.outcome)[rows_u, focal].astype(np.int64)
        length = f_alive.sum(1).cpu().numpy().astype(np.int64)
        discount = self.gamma ** th.arange(t_max, device=device, dtype=th.float32)
        returns = (f_rewards * discount[None]).sum(1).cpu().numpy().astype(np.float64)
        cut = np.flatnonzero((outcome == OUTCOME_TIMEOUT) & (length > 0))
        if cut.size:
            sel = th.as_tensor(cut * a + focal[cut], device=device)
            obs = sim.obs.to(device).float().reshape(n_worlds * a, d)[sel].clamp(-OBS_BOUND, OBS_BOUND)
            _, values, _ = policy_step_logits(self.policy, obs, take_states(states, sel),
                                              th.zeros(cut.size, device=device))
            returns[cut] += (self.gamma ** length[cut]) * values.reshape(-1).cpu().numpy()

        results = []
        for k in range(len(jobs)):
            lo, hi = int(offsets[k]), int(offsets[k + 1])
            results.append(GroupResult(
                returns=returns[lo:hi].copy(), completed=outcome[lo:hi] == OUTCOME_GOAL, outcome=outcome[lo:hi].copy(),
                transitions=transitions[lo:hi].copy(), length=length[lo:hi].copy(),
                obs=f_obs[lo:hi], actions=f_actions[lo:hi], logp_old=f_logp[lo:hi], alive=f_alive[lo:hi],
                rewards=f_rewards[lo:hi], xy=xy[lo:hi], coplayer_actions=all_actions[lo:hi],
                controllers=controllers[lo:hi],
            ))
        return results


# ============================================================================ training data
def group_normalized(returns: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Group-relative advantages ``(R - mean) / (std + eps)`` per row.

    Args:
        returns: (n_groups, G) returns.
    Returns:
        (n_groups, G) float32; a row whose returns are all equal gets zeros.
    """
    r = np.asarray(returns, np.float64)
    mean = r.mean(-1, keepdims=True)
    std = r.std(-1, keepdims=True)
    return ((r - mean) / (std + eps)).astype(np.float32)


def mixed_outcome(completed: np.ndarray) -> bool:
    """DAPO's dynamic-sampling test: some continuations completed and some did not."""
    c = np.asarray(completed, bool)
    return bool(c.any() and not c.all())


@dataclass
class ContinuationBatch:
    """Focal continuation trajectories padded into one batch (K continuations, T steps).

    Attributes:
        obs: (K * T, D) sequence-major focal observations.
        actions: (K, T) int64; logp_old: (K, T) behaviour log-probabilities.
        mask: (K, T) float32, 1 on decisions the focal agent took.
        pi_state, vf_state: (h, c), each (layers, K, hidden): the focal memory at the root.
        advantages: (K,) one advantage per continuation.
        group: (K,) int64 group index; returns: (K,) continuation returns.
    """

    obs: th.Tensor
    actions: th.Tensor
    logp_old: th.Tensor
    mask: th.Tensor
    pi_state: tuple[th.Tensor, th.Tensor]
    vf_state: tuple[th.Tensor, th.Tensor]
    advantages: th.Tensor
    group: th.Tensor
    returns: th.Tensor

    @property
    def size(self) -> int:
        return int(self.mask.shape[0])


def collate_continuations(roots: Sequence[ContinuationRoot], results: Sequence[GroupResult],
                          advantages: Sequence[np.ndarray], device: th.device | str = "cpu") -> ContinuationBatch | None:
    """Pad the continuations of the given groups (all G of each) into a :class:`ContinuationBatch`.

    Args:
        roots, results: the groups (same order).
        advantages: one (G,) array per group.
    Returns None when there is no group or no continuation took a decision.
    """
    keep = [(r, res, np.asarray(adv, np.float32)) for r, res, adv in zip(roots, results, advantages)]
    if not keep:
        return None
    t_max = max(int(res.length.max()) for _, res, _ in keep)
    if t_max == 0:
        return None
    obs, actions, logp, mask, h, c, vh, vc, adv, group, ret = ([] for _ in range(11))
    for g, (root, res, a_) in enumerate(keep):
        n = res.actions.shape[0]
        obs.append(res.obs[:, :t_max].to(device))
        actions.append(res.actions[:, :t_max].to(device))
        logp.append(res.logp_old[:, :t_max].to(device))
        mask.append(res.alive[:, :t_max].to(device).float())
        mem = root.memory[:, :, root.focal].to(device)  # (4, layers, hidden)
        for lst, part in ((h, 0), (c, 1), (vh, 2), (vc, 3)):
            lst.append(mem[part][:, None].expand(-1, n, -1))
        adv.append(th.as_tensor(a_, device=device))
        group.append(th.full((n,), g, dtype=th.long, device=device))
        ret.append(th.as_tensor(res.returns, dtype=th.float32, device=device))

    def pad_t(xs: list[th.Tensor]) -> th.Tensor:
        out = []
        for x in xs:
            if x.shape[1] < t_max:
                pad = th.zeros((x.shape[0], t_max - x.shape[1], *x.shape[2:]), dtype=x.dtype, device=device)
                x = th.cat([x, pad], 1)
            out.append(x)
        return th.cat(out)

    obs_t = pad_t(obs)
    k = obs_t.shape[0]
    mask_t = pad_t(mask)
    return ContinuationBatch(
        obs=(obs_t * mask_t[..., None]).reshape(k * t_max, -1), actions=pad_t(actions), logp_old=pad_t(logp),
        mask=mask_t, pi_state=(th.cat(h, 1).contiguous(), th.cat(c, 1).contiguous()),
        vf_state=(th.cat(vh, 1).contiguous(), th.cat(vc, 1).contiguous()),
        advantages=th.cat(adv), group=th.cat(group), returns=th.cat(ret),
    )


def continuation_logits(policy: Any, batch: ContinuationBatch) -> th.Tensor:
    """(K, T, n_actions) logits of ``policy`` on the batch, its actor LSTM run from each
    focal root memory over the continuation (with gradients when the policy has them)."""
    k, t_max = batch.mask.shape
    starts = th.zeros(k * t_max, device=batch.mask.device)
    logits, _ = actor_logits(policy, batch.obs, batch.pi_state, starts)
    return logits.reshape(k, t_max, -1)


# ============================================================================ algorithm base
@dataclass
class _RecorderState:
    last_trigger: np.ndarray  # (W, A) decision of the last trigger (-10**9: none this episode)
    last_actions: np.ndarray  # (W, A) previous action of every slot
    episode_step: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


class ContinuationPPO(HookedPPO):
    """PPO-Continue plus groups of continuations from interaction roots (module docstring).

    A subclass chooses each group's traffic modes / temperatures (:meth:`_group_jobs`) and
    what it learns from the results (:meth:`_use_groups`).

    Args:
        group_size: continuations per root (6 = CounterPlay's 1 factual + 5 candidates).
        trigger: ``ttc``, ``distance`` or ``either`` (:func:`interaction_trigger`).
        trigger_distance: metres, centre to centre (10).
        trigger_ttc: seconds (3.0, BehaviorBench's time-to-collision threshold).
        trigger_cooldown: decisions before the same agent may trigger again (10).
        min_horizon: decisions that must be left before the deadline at a root (5).
        root_pool: roots kept per rollout by reservoir sampling (64).
        max_groups: optional cap of groups per generation (None: the budget decides).
        group_coef: weight of the method's group objective (1.0).
        branch_cap: continuation transitions <= branch_cap x the generation's main
            transitions (0.5, CounterPlay's).
        Other arguments: :class:`HookedPPO`'s and :class:`cpalgo.CounterPlay`'s.

    Attributes:
        continuation_totals: running counts ``roots_offered``, ``groups``, ``continuations``,
            ``continuation_transitions``, ``completed`` and (subclasses) more.
        last_groups: ``(roots, results)`` of the last generation (inspection, tests).
    """

    _RUNTIME_ATTRS: ClassVar[tuple[str, ...]] = HookedPPO._RUNTIME_ATTRS + (
        "_rec", "_reservoir", "_runner", "_runner_sim", "_cont_generator", "_root_rng", "_group_batch", "last_groups",
    )
    #: traffic mode of the continuations (subclasses may choose per continuation)
    traffic_mode: ClassVar[str] = "policy"

    def __init__(self, policy: Any, env: Any, group_size: int = 6, trigger: str = "ttc",
                 trigger_distance: float = 10.0, trigger_ttc: float = 3.0, trigger_cooldown: int = 10,
                 min_horizon: int = 5, root_pool: int = 64, max_groups: int | None = None,
                 group_coef: float = 1.0, **kwargs: Any) -> None:
        self.group_size = group_size
        self.trigger = trigger
        self.trigger_distance = trigger_distance
        self.trigger_ttc = trigger_ttc
        self.trigger_cooldown = trigger_cooldown
        self.min_horizon = min_horizon
        self.root_pool = root_pool
        self.max_groups = max_groups
        self.group_coef = group_coef
        self.continuation_totals: dict[str, float] = {}
        super().__init__(policy, env, **kwargs)

    # ------------------------------------------------------------------ settings
    def _validate_settings(self) -> None:
        super()._validate_settings()
        check_number("group_size", self.group_size, low=2, integer=True)
        if self.trigger not in TRIGGER_MODES:
            raise ValueError(f"trigger: expected one of {TRIGGER_MODES}, got {self.trigger!r}")
        check_number("trigger_distance", self.trigger_distance, low=0.0, low_open=True)
        check_number("trigger_ttc", self.trigger_ttc, low=0.0, low_open=True)
        check_number("trigger_cooldown", self.trigger_cooldown, low=1, integer=True)
        check_number("min_horizon", self.min_horizon, low=1, integer=True)
        check_number("root_pool", self.root_pool, low=1, integer=True)
        if self.max_groups is not None:
            check_number("max_groups", self.max_groups, low=0, integer=True)
        check_number("group_coef", self.group_coef, low=0.0)

    def _reset_runtime(self) -> None:
        super()._reset_runtime()
        self._rec: _RecorderState | None = None
        seed = int(self.seed or 0)
        self._root_rng = np.random.default_rng(seed + 86028121)
        self._reservoir = RootReservoir(int(self.root_pool), self._root_rng)
        self._runner: ContinuationRunner | None = None
        self._runner_sim: Any = None
        self._cont_generator = th.Generator().manual_seed(seed + 49979693)
        self._group_batch: ContinuationBatch | None = None
        self.last_groups: tuple[list[ContinuationRoot], list[GroupResult]] = ([], [])

    def _on_env_reset(self) -> None:
        super()._on_env_reset()
        self._rec = None
        self._reservoir.clear()

    @property
    def dynamics(self) -> str:
        """The training simulator's dynamics model (``jerk`` or ``classic``)."""
        return str(base_vec_env(self.env).sim.config.dynamics)

    def _bump(self, key: str, value: float = 1) -> None:
        self.continuation_totals[key] = self.continuation_totals.get(key, 0) + value

    # ------------------------------------------------------------------ roots during the rollout
    def _rollout_start(self, env: Any) -> None:
        super()._rollout_start(env)
        self._reservoir.clear()
        self._group_batch = None

    def _recorder(self, base: Any) -> _RecorderState:
        if self._rec is None:
            w, a = int(base.num_worlds), int(base.max_agents)
            self._rec = _RecorderState(last_trigger=np.full((w, a), -10**9, np.int64),
                                       last_actions=np.full((w, a), neutral_action(self.dynamics), np.int64))
        return self._rec

    def _policy_step(self, env: Any, obs_tensor: th.Tensor, lstm_states: RNNStates, episode_starts: th.Tensor
                     ) -> tuple[th.Tensor, th.Tensor, th.Tensor, RNNStates]:
        base = base_vec_env(env)
        sim = base.sim
        rec = self._recorder(base)
        steps = _np(sim.step_count).astype(np.int64)
        fresh = steps == 0
        if fresh.any():
            rec.last_trigger[fresh] = -10**9
            rec.last_actions[fresh] = neutral_action(self.dynamics)
        self._record_roots(base, sim, steps, lstm_states, episode_starts)
        actions, values, log_probs, states = super()._policy_step(env, obs_tensor, lstm_states, episode_starts)
        live = np.asarray(self._last_active, bool).reshape(rec.last_actions.shape)
        acts = _np(actions).reshape(rec.last_actions.shape)
        rec.last_actions[live] = acts[live]
        return actions, values, log_probs, states

    def _record_roots(self, base: Any, sim: Any, steps: np.ndarray, lstm_states: RNNStates,
                      episode_starts: th.Tensor) -> None:
        rec = self._rec
        assert rec is not None
        deadline = int(sim.config.episode_steps)
        deciding = _np(sim.policy_mask).astype(bool)
        cand = (deciding & (steps[:, None] - rec.last_trigger >= int(self.trigger_cooldown))
                & ((deadline - steps) >= int(self.min_horizon))[:, None])
        if not cand.any():
            return
        hit = interaction_trigger(_np(sim.xy), _np(sim.velocity), _np(sim.alive).astype(bool), cand,
                                  mode=self.trigger, distance=float(self.trigger_distance), ttc=float(self.trigger_ttc))
        if not hit.any():
            return
        rec.last_trigger[hit] = steps[:, None].repeat(hit.shape[1], 1)[hit]
        worlds_, focals = np.nonzero(hit)
        self._bump("roots_offered", worlds_.size)
        slots = self._reservoir.slots_for(worlds_.size)
        accepted = [(int(w), int(f), s) for w, f, s in zip(worlds_, focals, slots) if s >= 0]
        if not accepted:
            return
        worlds = np.unique([w for w, _, _ in accepted])
        snapshot = sim.snapshot(worlds)
        row_of = {int(w): i for i, w in enumerate(worlds)}
        a = int(base.max_agents)
        keep = (1.0 - episode_starts).view(1, -1, 1)
        parts = [lstm_states.pi[0] * keep, lstm_states.pi[1] * keep, lstm_states.vf[0] * keep, lstm_states.vf[1] * keep]
        conditions = _np(sim.conditions)
        pos = int(self.rollout_buffer.pos)
        for w, f, slot in accepted:
            mem = th.stack([p[:, w * a:(w + 1) * a] for p in parts]).detach().clone()  # (4, layers, A, hidden)
            self._reservoir.put(slot, ContinuationRoot(
                world=w, focal=f, step=int(steps[w]), deadline=deadline, snapshot=snapshot, snapshot_row=row_of[w],
                memory=mem, conditions=conditions[w].astype(np.float32).copy(), last_actions=rec.last_actions[w].copy(),
                deciding=deciding[w].copy(), buffer_pos=pos, env_index=w * a + f,
            ))

    # ------------------------------------------------------------------ groups before GAE
    def _ensure_runner(self) -> ContinuationRunner:
        sim = base_vec_env(self.env).sim
        if self._runner is None or self._runner_sim is not sim:
            self._runner = ContinuationRunner(branch_simulator_factory(sim), self.policy, self.gamma,
                                              self._cont_generator, proxy=self._proxy_fn(), record=True,
                                              clip_reward=self.clip_reward)
            self._runner_sim = sim
        self._runner.policy = self.policy
        return self._runner

    def _proxy_fn(self) -> ProxyFn | None:
        """Co-player actions of ``proxy`` continuations (CRAFT); None: no proxy."""
        return None

    def _group_jobs(self, roots: list[ContinuationRoot]) -> list[GroupJob]:
        """One job per root: every continuation in :attr:`traffic_mode` at temperature 1."""
        g = int(self.group_size)
        return [GroupJob(root=r, traffic=[self.traffic_mode] * g) for r in roots]

    def _before_gae(self) -> None:
        """Run the rollout's groups in waves under the allowance and hand them to the method."""
        roots = list(self._reservoir.roots)
        self._reservoir.clear()
        order = self._root_rng.permutation(len(roots))
        queue = [roots[i] for i in order]
        self.budget.open_allowance(self.budget.generation_main)
        done_roots: list[ContinuationRoot] = []
        done_results: list[GroupResult] = []
        cap = None if self.max_groups is None else int(self.max_groups)
        wall = time.perf_counter()
        self.policy.set_training_mode(False)
        while queue and (cap is None or len(done_roots) < cap):
            accepted, rest, projected = [], [], 0
            for r in queue:
                cost = r.projected_transitions(int(self.group_size))
                room = cap is None or len(done_roots) + len(accepted) < cap
                if room and self.budget.fits(projected + cost):
                    accepted.append(r)
                    projected += cost
                else:
                    rest.append(r)
            if not accepted:
                break
            queue = rest
            results = self._ensure_runner().run(self._group_jobs(accepted))
            for res in results:
                n = int(res.transitions.sum())
                self.budget.add_branch(candidate=n)
                self.num_timesteps += n
                self._bump("continuation_transitions", n)
                self._bump("continuations", res.transitions.size)
                self._bump("completed", int(res.completed.sum()))
            self._bump("groups", len(accepted))
            done_roots += accepted
            done_results += results
        self._bump("groups_skipped", len(queue))
        self._bump("group_wall_s", time.perf_counter() - wall)
        self.last_groups = (done_roots, done_results)
        if done_roots:
            self._use_groups(done_roots, done_results)

    def _use_groups(self, roots: list[ContinuationRoot], results: list[GroupResult]) -> None:
        """What the method learns from this generation's groups (override)."""

    # ------------------------------------------------------------------ generation terms
    def _has_generation_terms(self) -> bool:
        return self._group_batch is not None and float(self.group_coef) > 0.0

    def _after_train(self) -> None:
        super()._after_train()
        self._group_batch = None
        for key, value in self.continuation_totals.items():
            self.logger.record(f"continuations/{key}", value)
