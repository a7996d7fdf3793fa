"""The search driver: roots during the rollout, failures to search requests, budgeted
searches in waves, ranking, verification and teachers.

Timeline (the seed paper's integration; DESIGN.md, "CounterPlay"):

* During generation g's rollout, :meth:`SearchDriver.policy_step` stores roots every
  ``root_interval`` decisions and traces values / uniforms / actions;
  :meth:`SearchDriver.after_step` turns each failed task into a :class:`SearchRequest`
  whose root is chosen right away from the roots and values of its episode. A root lives
  as long as its world's episode (``root_lifetime="episode"``): with rollouts about as
  long as an episode, most episodes begin in the previous rollout, and dropping roots at
  the generation boundary left a failure at decision 90 only the roots of the current
  rollout. Its memory and value then come from the previous generation's policy and critic
  (post-training moves them little); ``root_lifetime="generation"`` keeps one generation's.
* At the end of rollout g, :meth:`SearchDriver.end_rollout` freezes a copy of the policy
  and hands g's requests over. They run in waves *during generation g+1's rollout*
  (:meth:`SearchDriver.advance`, interleaved with the main steps in this process), under
  g's frozen policy, against an allowance of ``branch_cap`` x g's main transitions. What is
  left runs at the end of rollout g+1, and the verified retries are distilled in g+1's
  update (:meth:`SearchDriver.take_teachers`).
"""

from __future__ import annotations

import time
from collections import Counter
from copy import deepcopy
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
import torch as th
from sb3_contrib.common.recurrent.type_aliases import RNNStates

from cpalgo.common.policy_utils import inverse_cdf_sample, policy_step_logits, put_states, take_states
from cpalgo.counterplay.branches import BranchJob, BranchResult, BranchRunner, branch_simulator_factory
from cpalgo.counterplay.budget import Budget
from cpalgo.counterplay.distill import Teacher
from cpalgo.counterplay.roots import RootStore, SearchRequest
from cpalgo.counterplay.search import (
    ADMISSION_VERDICTS,
    BACKTRACK_MODES,
    ROOT_LIFETIMES,
    SELECTION_MODES,
    admission_verdict,
    choose_teacher,
    select_root,
    verify,
)
from cpsim.arrays import to_numpy as _to_numpy
from cpsim.conditions import PANEL, PROFILE_ALIASES, PROFILES, STYLE_MASK
from cpsim.config import Outcome

if TYPE_CHECKING:
    from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy

    from cpsim.simulator import Simulator

__all__ = ["SearchSettings", "SearchStats", "SearchDriver", "FAILURE_OUTCOMES", "outcome_code"]

#: Style counter name of teachers whose search kept the focal agent's own condition w0
#: (``style_change=False``): they drive no style of the panel.
OWN_CONDITION = "own"
#: Outcomes of the episodes that start a search.
FAILURE_OUTCOMES: tuple[int, ...] = (int(Outcome.COLLISION), int(Outcome.OFFROAD), int(Outcome.TIMEOUT))
_FAILURE_NAMES = {int(Outcome.COLLISION): "collision", int(Outcome.OFFROAD): "offroad", int(Outcome.TIMEOUT): "timeout"}


def outcome_code(value: Any) -> int:
    """``info["outcome"]`` (name, enum or int) -> integer code; unknown -> -1."""
    if value is None:
        return -1
    if isinstance(value, str):
        try:
            return int(Outcome[value.upper()])
        except KeyError:
            return -1
    try:
        return int(value)
    except (TypeError, ValueError):
        return -1


@dataclass(frozen=True)
class SearchSettings:
    """The CounterPlay arguments the search needs; ``ValueError`` names a bad one.

    See :class:`cpalgo.counterplay.algorithm.CounterPlay` for their meaning.
    """

    root_interval: int = 5
    window: tuple[int, int] = (5, 60)
    rho: float = 0.5
    backtrack: str = "value"
    fixed_depth: int = 20
    panel: tuple[str, ...] = PANEL
    shared_randomness: bool = True
    style_change: bool = True
    selection: str = "rank"
    verify: bool = True
    max_searches: int | None = None
    root_lifetime: str = "episode"
    seed: int = 0
    clip_reward: float | None = None

    def __post_init__(self) -> None:
        if len(self.panel) == 0:
            raise ValueError("panel: needs at least one profile")
        for name in self.panel:
            if PROFILE_ALIASES.get(name, name) not in PROFILES:
                raise ValueError(f"panel: unknown profile {name!r}; accepted: {sorted(PROFILES)}")
        if isinstance(self.window, str) or len(self.window) != 2:
            raise ValueError(f"window: expected (start, end), got {self.window!r}")
        start, end = int(self.window[0]), int(self.window[1])
        if start < 1 or start >= end:
            raise ValueError(f"window: need 1 <= start < end, got {self.window!r}")
        if not 0.0 <= float(self.rho) <= 1.0:
            raise ValueError(f"rho: must lie in [0, 1], got {self.rho!r}")
        if int(self.root_interval) < 1:
            raise ValueError(f"root_interval: must be >= 1, got {self.root_interval!r}")
        if self.backtrack not in BACKTRACK_MODES:
            raise ValueError(f"backtrack: expected one of {BACKTRACK_MODES}, got {self.backtrack!r}")
        if int(self.fixed_depth) < 1:
            raise ValueError(f"fixed_depth: must be >= 1, got {self.fixed_depth!r}")
        if self.selection not in SELECTION_MODES:
            raise ValueError(f"selection: expected one of {SELECTION_MODES}, got {self.selection!r}")
        if self.root_lifetime not in ROOT_LIFETIMES:
            raise ValueError(f"root_lifetime: expected one of {ROOT_LIFETIMES}, got {self.root_lifetime!r}")
        if self.max_searches is not None and int(self.max_searches) < 0:
            raise ValueError(f"max_searches: must be >= 0 or None, got {self.max_searches!r}")


@dataclass
class SearchStats:
    """Counts of one generation (or, summed, of a whole run).

    ``failures_by_outcome`` is keyed by "collision" / "offroad" / "timeout",
    ``root_depths`` by depth in decisions, ``profiles`` by the winning panel profile and
    ``retry_verdicts`` by :func:`~cpalgo.counterplay.search.admission_verdict` (one per retry).
    Seconds are wall (``search_wall_s``) and process CPU (``search_cpu_s``) time spent in
    branch rollouts.
    """

    failures: int = 0
    failures_by_outcome: Counter = field(default_factory=Counter)
    failures_without_root: int = 0
    searches: int = 0
    searches_skipped: int = 0
    search_waves: int = 0
    root_depths: Counter = field(default_factory=Counter)
    factual_completed: int = 0
    retry_verdicts: Counter = field(default_factory=Counter)
    admissible: int = 0
    teachers_chosen: int = 0
    verified: int = 0
    verification_failed: int = 0
    teachers: int = 0
    profiles: Counter = field(default_factory=Counter)
    search_cpu_s: float = 0.0
    search_wall_s: float = 0.0

    @property
    def root_depth_mean(self) -> float:
        n = sum(self.root_depths.values())
        return sum(d * k for d, k in self.root_depths.items()) / n if n else 0.0

    def record(self, record: Callable[[str, Any], None], panel: tuple[str, ...], verify: bool) -> None:
        """Write this generation's counts through ``logger.record`` (``counterplay/...``)."""
        record("counterplay/failures", self.failures)
        for name in ("collision", "offroad", "timeout"):
            record(f"counterplay/failures_{name}", self.failures_by_outcome[name])
        for name in ("failures_without_root", "searches", "searches_skipped", "search_waves", "root_depth_mean",
                     "admissible", "teachers_chosen", "search_cpu_s", "search_wall_s"):
            record(f"counterplay/{name}", getattr(self, name))
        for name in ADMISSION_VERDICTS:
            record(f"counterplay/retries_{name}", self.retry_verdicts[name])
        for depth in sorted(self.root_depths):
            record(f"counterplay/roots_by_depth/{depth}", self.root_depths[depth])
        record("counterplay/verified_teachers", self.teachers)
        chosen = self.teachers_chosen
        record("counterplay/verification_pass_rate", (self.verified / chosen) if (verify and chosen) else float("nan"))
        for name in panel:
            record(f"counterplay/profile/{name}", self.profiles[name])

    def add(self, other: SearchStats) -> None:
        """Accumulate ``other`` into this one."""
        for f in fields(self):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if isinstance(mine, Counter):
                mine.update(theirs)
            else:
                setattr(self, f.name, mine + theirs)

    def as_dict(self) -> dict[str, float]:
        """Flat JSON-able view: ``failures_timeout``, ``root_depth_12``, ``profile_aggressive``..."""
        out: dict[str, float] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, Counter):
                out[f.name] = value
        out.update({f"failures_{k}": v for k, v in self.failures_by_outcome.items()})
        out.update({f"root_depth_{k}": v for k, v in self.root_depths.items()})
        out.update({f"profile_{k}": v for k, v in self.profiles.items()})
        out.update({f"retries_{k}": v for k, v in self.retry_verdicts.items()})
        out["root_depth_sum"] = sum(d * k for d, k in self.root_depths.items())
        return out


class SearchDriver:
    """Roots, requests, waves and teachers of a CounterPlay run (see module docstring).

    Args:
        settings: the search arguments.
        budget: the run's transition accounting (branch transitions are added here).
        device: torch device of the policy.
        count_transitions: called with every batch of branch transitions that ran, so the
            algorithm's ``num_timesteps`` (B_post) includes them.
    """

    def __init__(self, settings: SearchSettings, budget: Budget, device: th.device,
                 count_transitions: Callable[[int], None] | None = None) -> None:
        self.settings = settings
        self.budget = budget
        self.device = device
        self.count_transitions = count_transitions or (lambda n: None)
        self.roots: RootStore | None = None
        self.runner: BranchRunner | None = None
        self.stats = SearchStats()
        self.totals = SearchStats()
        self._sim: Simulator | None = None
        self._requests: list[SearchRequest] = []   # failures of the generation in progress
        self._pending: list[SearchRequest] = []    # the previous generation's, being searched
        self._frozen: RecurrentActorCriticPolicy | None = None
        self._teachers: list[Teacher] = []
        self._step_count_before: np.ndarray | None = None
        self._uniforms = th.Generator().manual_seed(int(settings.seed) + 7919)
        self._branch_draws = th.Generator().manual_seed(int(settings.seed) + 104729)
        #: optional hook called once per wave (inspection records, ``records.keep_wave``):
        #: ``(requests, results, chosen, passed, verifications or None)``
        self.on_wave: Callable[..., None] | None = None

    # ================================================================== set-up
    def attach(self, env: Any, policy: RecurrentActorCriticPolicy,
               obs_transform: Callable[[th.Tensor], th.Tensor] | None = None) -> None:
        """Build the root store and the branch runner for ``env``'s simulator (once)."""
        sim = env.sim
        if self.roots is not None and self._sim is sim:
            return
        s = self.settings
        lstm = policy.lstm_actor
        self.roots = RootStore(
            num_worlds=int(env.num_worlds), max_agents=int(env.max_agents),
            episode_steps=int(sim.config.episode_steps), root_interval=int(s.root_interval),
            window_end=int(s.window[1]) if s.backtrack == "value" else max(int(s.window[1]), int(s.fixed_depth)),
            lstm_layers=lstm.num_layers, lstm_hidden=lstm.hidden_size, device=self.device,
        )
        self._sim = sim
        self.runner = BranchRunner(branch_simulator_factory(sim), policy, obs_transform, self._branch_draws,
                                   clip_reward=s.clip_reward)

    @property
    def sim(self) -> Simulator | None:
        return self._sim

    def on_env_reset(self) -> None:
        """``learn`` reset every world: the current episodes' roots and traces are gone.
        Requests already made keep their own copies and still run."""
        if self.roots is not None:
            self.roots.invalidate()

    # ================================================================== rollout
    def start_rollout(self) -> None:
        """New generation: fresh stats. With ``root_lifetime="generation"`` the roots of
        earlier generations stop being usable; with "episode" they stay until their
        world's episode ends, so a failure late in an episode that began in the previous
        rollout can still backtrack into that rollout (an episode of T decisions spans two
        rollouts whenever ``n_steps`` is near T)."""
        self.stats = SearchStats()
        if self.roots is not None and self.settings.root_lifetime == "generation":
            self.roots.drop_roots(pinned=[req.snapshot for req in self._pending])

    def policy_step(self, sim: Simulator, policy: RecurrentActorCriticPolicy, obs: th.Tensor,
                    lstm_states: RNNStates, episode_starts: th.Tensor, active: th.Tensor | None,
                    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, RNNStates]:
        """Roots (before the decision), one actor+critic pass over the live slots
        (``active`` indices; None: every slot), inverse-CDF sampling from fresh recorded
        uniforms, and the trace of values / uniforms / actions (inactive: value 0, action 0).

        Returns actions (N,), values (N, 1), log-probs (N,) and the new LSTM states.
        """
        assert self.roots is not None
        step_count = _to_numpy(sim.step_count).astype(np.int64).copy()
        self._step_count_before = step_count
        due = self.roots.due(step_count)
        if due.size:
            keep = (1.0 - episode_starts).view(1, -1, 1)  # the memory the LSTM will actually use
            pi = (lstm_states.pi[0] * keep, lstm_states.pi[1] * keep)
            vf = (lstm_states.vf[0] * keep, lstm_states.vf[1] * keep)
            snapshot = sim.snapshot(due, out=self.roots.take_free(due.size))
            conditions = _to_numpy(sim.conditions)[due].astype(np.float32)
            alive = _to_numpy(sim.policy_mask)[due].sum(axis=1)
            self.roots.store(due, step_count[due], snapshot, pi, vf, conditions, alive)

        n = obs.shape[0]
        # one draw per slot whether or not it is live, so the stream does not depend on activity
        uniforms = th.rand(n, generator=self._uniforms).to(self.device)
        if active is None:
            logits, values, new_states = policy_step_logits(policy, obs, lstm_states, episode_starts)
            actions = inverse_cdf_sample(logits, uniforms)
            log_probs = th.log_softmax(logits, dim=-1).gather(-1, actions[:, None]).squeeze(-1)
        else:
            logits, sub_values, sub_states = policy_step_logits(
                policy, obs[active], take_states(lstm_states, active), episode_starts[active]
            )
            sub_actions = inverse_cdf_sample(logits, uniforms[active])
            actions = th.zeros(n, dtype=th.int64, device=self.device)
            values = th.zeros((n, 1), dtype=sub_values.dtype, device=self.device)
            log_probs = th.zeros(n, dtype=logits.dtype, device=self.device)
            actions[active] = sub_actions
            values[active] = sub_values
            log_probs[active] = th.log_softmax(logits, dim=-1).gather(-1, sub_actions[:, None]).squeeze(-1)
            new_states = put_states(lstm_states, active, sub_states)
        self.roots.record_step(step_count, values.reshape(-1).cpu().numpy(), uniforms.cpu().numpy(),
                               actions.cpu().numpy())
        return actions, values, log_probs, new_states

    def after_step(self, sim: Simulator, dones: np.ndarray, infos: list[dict], was_active: np.ndarray) -> None:
        """Failed tasks of live slots become search requests; reset worlds start new episodes."""
        assert self.roots is not None and self._step_count_before is not None
        roots, s, stats = self.roots, self.settings, self.stats
        for idx in np.flatnonzero(np.asarray(dones, bool) & was_active).tolist():
            code = outcome_code(infos[idx].get("outcome"))
            if code not in FAILURE_OUTCOMES:
                continue
            stats.failures += 1
            stats.failures_by_outcome[_FAILURE_NAMES[code]] += 1
            w, slot = divmod(idx, roots.max_agents)
            failure_step = int(self._step_count_before[w])
            root_steps, _ = roots.roots_of(w)
            root_steps = root_steps[root_steps <= failure_step]
            root = select_root(roots.values[w, slot], root_steps, failure_step, window=s.window, rho=s.rho,
                               mode=s.backtrack, fixed_depth=s.fixed_depth)
            if root is None:
                stats.failures_without_root += 1
                continue
            self._requests.append(roots.request(w, slot, failure_step, code, root))
        step_after = _to_numpy(sim.step_count).astype(np.int64)
        roots.new_episodes(np.flatnonzero(step_after <= self._step_count_before))

    @property
    def has_pending(self) -> bool:
        """Whether the previous generation's searches are still waiting to run."""
        return bool(self._pending)

    def advance(self, step: int, n_steps: int) -> None:
        """Interleave the previous generation's searches with this rollout: one wave at
        each quarter of the rollout while searches are pending."""
        if self._pending and step % max(1, n_steps // 4) == 0:
            self._run_wave()

    def end_rollout(self, policy: RecurrentActorCriticPolicy, main_transitions: int) -> None:
        """Finish the previous generation's searches, then freeze this generation's policy
        and requests for the next rollout, with an allowance of ``branch_cap`` x
        ``main_transitions``."""
        while self._pending and self._run_wave():
            pass
        self.stats.searches_skipped += len(self._pending)
        self.stats.teachers = len(self._teachers)
        requests = self._requests
        if self.settings.max_searches is not None:
            self.stats.searches_skipped += max(0, len(requests) - int(self.settings.max_searches))
            requests = requests[: int(self.settings.max_searches)]
        self._pending, self._requests = requests, []
        self.budget.open_allowance(main_transitions)
        if requests:
            self._freeze(policy)
        if self.roots is not None:
            self.roots.collect_garbage(pinned=[req.snapshot for req in self._pending])
        self.totals.add(self.stats)

    def _freeze(self, policy: RecurrentActorCriticPolicy) -> None:
        """Copy ``policy``'s weights into the frozen search policy (built once)."""
        if self._frozen is None or type(self._frozen) is not type(policy):
            # the shared action distribution holds the last forward's non-leaf logits,
            # which deepcopy refuses; the copy gets its own empty one
            dist = policy.action_dist
            held = getattr(dist, "distribution", None)
            dist.distribution = None
            try:
                self._frozen = deepcopy(policy)
            finally:
                dist.distribution = held
        self._frozen.load_state_dict(policy.state_dict())
        self._frozen.set_training_mode(False)

    def take_teachers(self) -> list[Teacher]:
        """The verified retries found so far (handed over once)."""
        teachers, self._teachers = self._teachers, []
        return teachers

    # ================================================================== waves
    def _run_wave(self) -> bool:
        """Run the pending searches that fit the remaining allowance (all branches in one
        batch), rank, verify, keep teachers. Returns False when none fit.

        A search is admitted when its projected cost (an upper bound: every agent alive at
        the root runs to the deadline in every branch) fits. Branches end early when
        agents finish, so the next wave sees the allowance left by what actually ran.
        """
        assert self.runner is not None and self._frozen is not None
        n_branch = 1 + len(self.settings.panel)
        per_search = n_branch + (2 if self.settings.verify else 0)
        accepted, rest, projected = [], [], 0
        for req in self._pending:
            cost = req.projected_transitions(per_search)
            if self.budget.fits(projected + cost):
                accepted.append(req)
                projected += cost
            else:
                rest.append(req)
        if not accepted:
            return False
        self._pending = rest
        cpu, wall = time.process_time(), time.perf_counter()
        self.runner.policy = self._frozen
        self._search(accepted, n_branch)
        self.stats.search_cpu_s += time.process_time() - cpu
        self.stats.search_wall_s += time.perf_counter() - wall
        return True

    def _search(self, accepted: list[SearchRequest], n_branch: int) -> None:
        assert self.runner is not None
        stats = self.stats
        stats.searches += len(accepted)
        stats.search_waves += 1
        stats.root_depths.update(r.depth for r in accepted)
        independent = self._independent_flags(n_branch)
        jobs = [
            BranchJob(snapshot=req.snapshot, snapshot_row=req.snapshot_row,
                      conditions=self._candidate_conditions(req.conditions, req.focal),
                      pi_state=req.pi_state, vf_state=req.vf_state, focal=req.focal,
                      root_step=req.root_step, deadline=req.deadline, independent_focal=independent, record=True)
            for req in accepted
        ]
        results = self.runner.run(jobs)
        chosen: list[tuple[SearchRequest, BranchJob, BranchResult, int]] = []
        for req, job, res in zip(accepted, jobs, results):
            self._add_branch(factual=int(res.transitions[0]), candidate=int(res.transitions[1:].sum()))
            factual, candidates = res.outcomes[0], res.outcomes[1:]
            stats.factual_completed += int(factual.completed)
            verdicts = [admission_verdict(factual, c) for c in candidates]
            stats.retry_verdicts.update(verdicts)
            stats.admissible += verdicts.count("admitted")
            j = choose_teacher(factual, candidates, self.settings.selection)
            if j is not None:
                chosen.append((req, job, res, j))
        stats.teachers_chosen += len(chosen)

        passed: list[bool] = [True] * len(chosen)
        vresults: list[BranchResult | None] = [None] * len(chosen)
        if self.settings.verify and chosen:
            vjobs = [
                BranchJob(snapshot=req.snapshot, snapshot_row=req.snapshot_row, conditions=job.conditions[[0, 1 + j]],
                          pi_state=req.pi_state, vf_state=req.vf_state, focal=req.focal, root_step=req.root_step,
                          deadline=req.deadline, independent_focal=independent[[0, 1 + j]], record=False)
                for req, job, _, j in chosen
            ]
            for k, vres in enumerate(self.runner.run(vjobs)):
                self._add_branch(verification=int(vres.transitions.sum()))
                passed[k] = verify(vres.outcomes[0], vres.outcomes[1])
                vresults[k] = vres
            stats.verified += int(sum(passed))
            stats.verification_failed += len(chosen) - int(sum(passed))

        if self.on_wave is not None:
            self.on_wave(accepted, results, chosen, passed, vresults if self.settings.verify and chosen else None)
        for (req, _, res, j), ok in zip(chosen, passed):
            if not ok:
                continue
            teacher = self._make_teacher(req, res, 1 + j)
            if teacher is not None:
                self._teachers.append(teacher)
                # without a style change every candidate drives the focal agent's own condition
                stats.profiles[self.settings.panel[j] if self.settings.style_change else OWN_CONDITION] += 1

    def _add_branch(self, factual: int = 0, candidate: int = 0, verification: int = 0) -> None:
        self.budget.add_branch(factual=factual, candidate=candidate, verification=verification)
        self.count_transitions(factual + candidate + verification)

    def _candidate_conditions(self, base: np.ndarray, focal: int) -> np.ndarray:
        """(1 + J, A, 10): factual w0 then one world per panel profile (focal style only)."""
        out = np.repeat(base[None].astype(np.float32), 1 + len(self.settings.panel), axis=0)
        if self.settings.style_change:
            for j, name in enumerate(self.settings.panel, start=1):
                style = PROFILES[PROFILE_ALIASES.get(name, name)]
                out[j, focal, STYLE_MASK] = style[STYLE_MASK]
        return out

    def _independent_flags(self, num_branches: int) -> np.ndarray:
        flags = np.zeros(num_branches, bool)
        if not self.settings.shared_randomness:
            flags[:] = True
        elif not self.settings.style_change:
            flags[1:] = True  # otherwise the candidates would replay the factual branch
        return flags

    def _make_teacher(self, req: SearchRequest, res: BranchResult, branch: int) -> Teacher | None:
        """The winning branch's focal trajectory from the root to the end of its task."""
        assert res.focal_alive is not None and res.focal_obs is not None and res.focal_logits is not None
        alive = res.focal_alive[branch].cpu().numpy()
        length = int(np.argmin(alive)) if not alive.all() else alive.size
        if length == 0:
            return None
        return Teacher(
            obs=res.focal_obs[branch, :length].detach().clone(),
            logits=res.focal_logits[branch, :length].detach().clone(),
            actions=res.focal_actions[branch, :length].detach().clone(),
            rewards=res.focal_rewards[branch, :length].detach().clone(),
            pi_state=(req.pi_state[0][:, req.focal].clone(), req.pi_state[1][:, req.focal].clone()),
            vf_state=(req.vf_state[0][:, req.focal].clone(), req.vf_state[1][:, req.focal].clone()),
            condition=req.conditions[req.focal].copy(),
            profile=self.settings.panel[branch - 1],
            root_step=req.root_step,
            failure_step=req.failure_step,
        )

    # ================================================================== replay
    def replay_root(self, policy: RecurrentActorCriticPolicy, world: int, root_step: int,
                    main_draws: bool = True) -> BranchResult:
        """Re-run a stored root of ``world``'s current episode as one factual branch under
        ``policy``; with ``main_draws`` from the uniforms the main rollout used (see
        :meth:`CounterPlay.replay_root`)."""
        if self.roots is None or self.runner is None:
            raise ValueError("world: no roots recorded yet (counterfactual=True and a rollout are needed)")
        roots = self.roots
        steps, positions = roots.roots_of(int(world))
        match = positions[steps == int(root_step)]
        if match.size == 0:
            raise ValueError(f"root_step: no root at decision {root_step} in world {world}'s current episode")
        p = int(match[0])
        draws = None
        if main_draws:
            trace = roots.uniforms[world, :, root_step:roots.episode_steps].T  # (steps, A)
            recorded = ~np.isnan(trace).any(axis=1)
            n = int(np.argmin(recorded)) if not recorded.all() else recorded.size
            draws = trace[:n].copy()
        job = BranchJob(
            snapshot=roots.snapshots[int(roots.snapshot_id[world, p])], snapshot_row=int(roots.snapshot_row[world, p]),
            conditions=roots.conditions[world, p][None].copy(),
            pi_state=(roots.pi_h[world, p], roots.pi_c[world, p]), vf_state=(roots.vf_h[world, p], roots.vf_c[world, p]),
            focal=0, root_step=int(root_step), deadline=roots.episode_steps, uniforms=draws, record=False,
        )
        self.runner.policy = policy
        return self.runner.run([job])[0]


# ---------------------------------------------------------------------- helpers
