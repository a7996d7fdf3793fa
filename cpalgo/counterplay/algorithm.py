"""CounterPlay: counterfactual post-training of a self-play policy on top of RecurrentPPO.

One generation = one rollout + one train step (DESIGN.md, "CounterPlay"):

1. **Roots.** During the rollout, every ``root_interval`` decisions of a world, the world is
   snapshotted and every agent's actor/critic LSTM memory and condition are kept; every
   agent's critic value, sampling uniform and action are traced at every decision.
2. **Failures.** A POLICY agent whose episode ends in collision, off-road or timeout
   requests one search; its root is chosen right away (``search.select_root``).
3. **Branches.** At the end of the rollout, the searches that fit the budget run, all
   together, in a second simulator on the same pool: per search one factual branch (w0)
   and one branch per panel profile (focal style fields replaced), every other agent
   keeping its memory and condition; shared inverse-CDF draws.
4. **Ranking, admission, verification** (``search``), then the verified retries become
   teachers for this generation's ``train``.
5. **Distillation**: ``distill_coef`` x KL(teacher || student under w_dep) added to
   ``distill_minibatches`` PPO minibatch updates; branch data never enters PPO / value
   losses.
6. **Budget** (``model.budget``): main + factual + candidate + verification transitions;
   branch transitions per generation <= ``branch_cap`` x main transitions.
7. **Masking**: inactive ``SelfPlayVecEnv`` slots contribute to no loss and no advantage
   normalisation.

The rollout / train loops are copies of sb3-contrib 2.9.2's ``RecurrentPPO`` with hook
points (their local variable names are kept for callbacks). With ``counterfactual=False``
and ``mask_inactive=False`` the computation is exactly the parent's: parameters after
``learn`` are bit-identical to ``RecurrentPPO`` for the same seed (tested).
"""

from __future__ import annotations

import time
from collections import Counter
from copy import deepcopy
from typing import Any, ClassVar, Sequence, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from sb3_contrib import RecurrentPPO
from sb3_contrib.common.recurrent.buffers import RecurrentDictRolloutBuffer, RecurrentRolloutBuffer
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from sb3_contrib.common.recurrent.type_aliases import RNNStates
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import FloatSchedule, explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv, unwrap_vec_normalize

from cpalgo.common.buffers import MaskedRecurrentDictRolloutBuffer, MaskedRecurrentRolloutBuffer
from cpalgo.common.policy_utils import inverse_cdf_sample, policy_step_logits
from cpalgo.policies import POLICY_ALIASES
from cpalgo.counterplay.branches import BranchJob, BranchResult, BranchRunner
from cpalgo.counterplay.budget import Budget
from cpalgo.counterplay.distill import DISTILL_MODES, Teacher, TeacherBatch, collate_teachers, distill_loss
from cpalgo.counterplay.records import check_keep_searches, keep_wave
from cpalgo.counterplay.roots import RootStore, SearchRequest
from cpalgo.counterplay.search import (
    BACKTRACK_MODES,
    SELECTION_MODES,
    admit,
    choose_teacher,
    select_root,
    verify,
)
from cpsim.conditions import PANEL, PROFILE_ALIASES, PROFILES, STYLE_MASK, resolve_condition

__all__ = ["CounterPlay", "FAILURE_OUTCOMES"]

SelfCounterPlay = TypeVar("SelfCounterPlay", bound="CounterPlay")

#: Outcome names / codes (cpsim.Outcome) of the episodes that start a search.
OUTCOME_CODES: dict[str, int] = {"running": 0, "goal": 1, "collision": 2, "offroad": 3, "timeout": 4}
FAILURE_OUTCOMES: tuple[int, ...] = (2, 3, 4)
_OUTCOME_NAMES = {v: k for k, v in OUTCOME_CODES.items()}


def _outcome_code(value: Any) -> int:
    """``info["outcome"]`` (name, enum or int) -> integer code; unknown -> -1."""
    if value is None:
        return -1
    if isinstance(value, str):
        return OUTCOME_CODES.get(value.lower(), -1)
    try:
        return int(value)
    except (TypeError, ValueError):
        return -1


def _to_numpy(x: Any) -> np.ndarray:
    return x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)


class CounterPlay(RecurrentPPO):
    """RecurrentPPO with counterfactual retries of failed tasks distilled into the policy.

    Every argument of :class:`sb3_contrib.RecurrentPPO` is accepted unchanged. The
    CounterPlay arguments (all with defaults, so ``load`` can rebuild the model):

    Args:
        counterfactual: run roots / searches / distillation. Needs a branching-capable
            self-play env (``.sim``, ``.obs_layout``, ``num_envs = num_worlds * max_agents``,
            Discrete actions), e.g. :class:`cpsim.SelfPlayVecEnv`.
        root_interval: decisions between roots (5).
        window: (start, end) backtracking depths in decisions, inclusive ((5, 60)).
        rho: value-threshold position in [0, 1] (0.5).
        backtrack: "value" (value-guided root) or "fixed" (``fixed_depth`` decisions back).
        fixed_depth: depth of the "fixed" ablation (20).
        panel: candidate profiles (names of ``cpsim.conditions.PROFILES``).
        shared_randomness: one uniform per agent per decision shared by a search's
            branches; False gives the focal agent independent draws in every branch.
        style_change: False keeps w0 for the candidates (ablation; candidates then draw
            their focal actions independently, else they would replay the factual branch).
        selection: "rank" (rank key) or "return" (candidate's own conditioned return).
        verify: rerun factual + chosen with fresh draws; a failed rerun discards the search.
        distill: "kl" (KL(teacher || student)) or "ppo" (PPO on the recovery trajectories).
        distill_coef: weight of the distillation term (0.5).
        distill_minibatches: minibatch updates per generation that carry the term (4).
        deploy_condition: profile name or raw 10-vector the student is trained under.
        branch_cap: branch transitions per generation <= branch_cap x main transitions.
        post_budget: stop ``learn`` once main + branch transitions reach it (None: never).
        mask_inactive: mask inactive slots (``info["active"]`` / ``env.active_mask()``).
        max_searches: optional cap on searches per generation (None: the budget decides).
        keep_searches: searches kept per generation as tensor-free records for inspection
            (``cpalgo.counterplay.records``; 0 keeps nothing).
    """

    #: "MlpLstmPolicy" & co. are the fused-sequence versions (cpalgo.policies); pass
    #: sb3-contrib's classes explicitly to get its stepping LSTM
    policy_aliases: ClassVar = POLICY_ALIASES

    #: runtime state that is rebuilt, never saved
    _RUNTIME_ATTRS: ClassVar[tuple[str, ...]] = (
        "_roots", "_runner", "_requests", "_teachers", "_uniform_generator", "_last_active",
        "_step_count_before", "_gen_stats", "_deploy_raw", "_sim_for_roots", "_search_records",
    )

    def __init__(
        self,
        policy: str | type[RecurrentActorCriticPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        n_steps: int = 128,
        batch_size: int | None = 128,
        n_epochs: int = 10,
        gamma: float = 0.99,
        gae_lambda: float = 0.95,
        clip_range: float | Schedule = 0.2,
        clip_range_vf: float | Schedule | None = None,
        normalize_advantage: bool = True,
        ent_coef: float = 0.0,
        vf_coef: float = 0.5,
        max_grad_norm: float = 0.5,
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        target_kl: float | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        counterfactual: bool = True,
        root_interval: int = 5,
        window: Sequence[int] = (5, 60),
        rho: float = 0.5,
        backtrack: str = "value",
        fixed_depth: int = 20,
        panel: Sequence[str] = PANEL,
        shared_randomness: bool = True,
        style_change: bool = True,
        selection: str = "rank",
        verify: bool = True,
        distill: str = "kl",
        distill_coef: float = 0.5,
        distill_minibatches: int = 4,
        deploy_condition: str | Sequence[float] = "normal",
        branch_cap: float = 0.5,
        post_budget: int | None = None,
        mask_inactive: bool = True,
        max_searches: int | None = None,
        keep_searches: int = 4,
        _init_setup_model: bool = True,
    ):
        super().__init__(
            policy,
            env,
            learning_rate=learning_rate,
            n_steps=n_steps,
            batch_size=batch_size,
            n_epochs=n_epochs,
            gamma=gamma,
            gae_lambda=gae_lambda,
            clip_range=clip_range,
            clip_range_vf=clip_range_vf,
            normalize_advantage=normalize_advantage,
            ent_coef=ent_coef,
            vf_coef=vf_coef,
            max_grad_norm=max_grad_norm,
            use_sde=use_sde,
            sde_sample_freq=sde_sample_freq,
            target_kl=target_kl,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
        )
        self.counterfactual = bool(counterfactual)
        self.root_interval = root_interval
        self.window = tuple(window) if not isinstance(window, str) else window
        self.rho = rho
        self.backtrack = backtrack
        self.fixed_depth = fixed_depth
        self.panel = tuple(panel) if not isinstance(panel, str) else (panel,)
        self.shared_randomness = bool(shared_randomness)
        self.style_change = bool(style_change)
        self.selection = selection
        self.verify = bool(verify)
        self.distill = distill
        self.distill_coef = distill_coef
        self.distill_minibatches = distill_minibatches
        self.deploy_condition = deploy_condition
        self.branch_cap = branch_cap
        self.post_budget = post_budget
        self.mask_inactive = bool(mask_inactive)
        self.max_searches = max_searches
        self.keep_searches = check_keep_searches(keep_searches)
        self._validate_settings()
        self.budget = Budget(branch_cap=float(branch_cap), post_budget=post_budget)
        self._reset_runtime()

        if _init_setup_model:
            self._setup_model()

    # ================================================================== settings
    def _validate_settings(self) -> None:
        """Check every CounterPlay argument; ``ValueError`` names the argument."""
        # a saved model comes back from JSON with lists where tuples were
        if isinstance(self.panel, list):
            self.panel = tuple(self.panel)
        if isinstance(self.window, list):
            self.window = tuple(self.window)
        if isinstance(self.deploy_condition, (list, tuple)):
            self.deploy_condition = tuple(float(x) for x in self.deploy_condition)
        panel = self.panel
        if len(panel) == 0:
            raise ValueError("panel: needs at least one profile")
        for name in panel:
            if PROFILE_ALIASES.get(name, name) not in PROFILES:
                raise ValueError(f"panel: unknown profile {name!r}; accepted: {sorted(PROFILES)}")
        self._deploy_raw = resolve_condition(self.deploy_condition, "deploy_condition")
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
        if self.distill not in DISTILL_MODES:
            raise ValueError(f"distill: expected one of {DISTILL_MODES}, got {self.distill!r}")
        if not float(self.distill_coef) >= 0.0:
            raise ValueError(f"distill_coef: must be >= 0, got {self.distill_coef!r}")
        if int(self.distill_minibatches) < 1:
            raise ValueError(f"distill_minibatches: must be >= 1, got {self.distill_minibatches!r}")
        if not float(self.branch_cap) > 0.0:
            raise ValueError(f"branch_cap: must be > 0, got {self.branch_cap!r}")
        if self.post_budget is not None and not float(self.post_budget) > 0:
            raise ValueError(f"post_budget: must be > 0 or None, got {self.post_budget!r}")
        if self.max_searches is not None and int(self.max_searches) < 0:
            raise ValueError(f"max_searches: must be >= 0 or None, got {self.max_searches!r}")

    def _check_branching_env(self, env: VecEnv | None) -> None:
        """A counterfactual run needs a self-play env the search can branch from."""
        if not self.counterfactual or env is None:
            return
        missing = [name for name in ("sim", "obs_layout", "num_worlds", "max_agents") if not hasattr(env, name)]
        if missing:
            raise ValueError(
                f"env: counterfactual=True needs a branching-capable self-play env (e.g. cpsim.SelfPlayVecEnv) "
                f"exposing .sim, .obs_layout, .num_worlds, .max_agents; missing {missing} on {type(env).__name__}"
            )
        if int(env.num_worlds) * int(env.max_agents) != env.num_envs:
            raise ValueError(
                f"env: num_envs ({env.num_envs}) must equal num_worlds * max_agents "
                f"({env.num_worlds} x {env.max_agents}) for branching"
            )
        if not isinstance(self.action_space, spaces.Discrete):
            raise ValueError(f"env: counterfactual=True needs a Discrete action space, got {self.action_space}")

    def _reset_runtime(self) -> None:
        self._roots: RootStore | None = None
        self._runner: BranchRunner | None = None
        self._requests: list[SearchRequest] = []
        self._teachers: list[Teacher] = []
        self._uniform_generator: th.Generator | None = None
        self._last_active: np.ndarray | None = None
        self._step_count_before: np.ndarray | None = None
        self._gen_stats: Counter = Counter()
        self._sim_for_roots: Any = None

    @property
    def _branching(self) -> bool:
        return self.counterfactual and self.env is not None

    # ================================================================== model setup
    def _setup_model(self) -> None:
        """RecurrentPPO's setup with the masked rollout buffer (same RNG use as the parent)."""
        self._validate_settings()
        self.budget.branch_cap = float(self.branch_cap)
        self.budget.post_budget = self.post_budget
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)

        buffer_cls = (
            MaskedRecurrentDictRolloutBuffer
            if isinstance(self.observation_space, spaces.Dict)
            else MaskedRecurrentRolloutBuffer
        )

        self.policy = self.policy_class(
            self.observation_space,
            self.action_space,
            self.lr_schedule,
            use_sde=self.use_sde,
            **self.policy_kwargs,
        )
        self.policy = self.policy.to(self.device)

        # We assume that LSTM for the actor and the critic
        # have the same architecture
        lstm = self.policy.lstm_actor

        if not isinstance(self.policy, RecurrentActorCriticPolicy):
            raise ValueError("Policy must subclass RecurrentActorCriticPolicy")

        single_hidden_state_shape = (lstm.num_layers, self.n_envs, lstm.hidden_size)
        # hidden and cell states for actor and critic
        self._last_lstm_states = RNNStates(
            (
                th.zeros(single_hidden_state_shape, device=self.device),
                th.zeros(single_hidden_state_shape, device=self.device),
            ),
            (
                th.zeros(single_hidden_state_shape, device=self.device),
                th.zeros(single_hidden_state_shape, device=self.device),
            ),
        )

        hidden_state_buffer_shape = (self.n_steps, lstm.num_layers, self.n_envs, lstm.hidden_size)

        self.rollout_buffer = buffer_cls(
            self.n_steps,
            self.observation_space,
            self.action_space,
            hidden_state_buffer_shape,
            self.device,
            gamma=self.gamma,
            gae_lambda=self.gae_lambda,
            n_envs=self.n_envs,
        )
        # inactive slots cost no forward/backward pass in train (see cpalgo.common.buffers)
        self.rollout_buffer.active_only = self.mask_inactive

        # Initialize schedules for policy/value clipping
        self.clip_range = FloatSchedule(self.clip_range)
        if self.clip_range_vf is not None:
            if isinstance(self.clip_range_vf, (float, int)):
                assert self.clip_range_vf > 0, "`clip_range_vf` must be positive, pass `None` to deactivate vf clipping"

            self.clip_range_vf = FloatSchedule(self.clip_range_vf)

        self._reset_runtime()
        self._check_branching_env(self.env)

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        super().set_env(env, force_reset=force_reset)
        self._check_branching_env(self.env)
        self._reset_runtime()

    def _excluded_save_params(self) -> list[str]:
        return super()._excluded_save_params() + list(self._RUNTIME_ATTRS)

    # ================================================================== learn
    def _setup_learn(self, total_timesteps: int, callback: MaybeCallback = None, reset_num_timesteps: bool = True,
                     tb_log_name: str = "run", progress_bar: bool = False) -> tuple[int, BaseCallback]:
        previous_obs = self._last_obs
        out = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        if self._last_obs is not previous_obs or self._last_active is None:
            self._on_env_reset()
        return out

    def learn(
        self: SelfCounterPlay,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "CounterPlay",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfCounterPlay:
        """``OnPolicyAlgorithm.learn`` that also stops when ``post_budget`` is reached."""
        iteration = 0

        total_timesteps, callback = self._setup_learn(
            total_timesteps,
            callback,
            reset_num_timesteps,
            tb_log_name,
            progress_bar,
        )

        callback.on_training_start(locals(), globals())

        assert self.env is not None

        while self.num_timesteps < total_timesteps and not self.budget.exhausted:
            continue_training = self.collect_rollouts(self.env, callback, self.rollout_buffer, n_rollout_steps=self.n_steps)

            if not continue_training:
                break

            iteration += 1
            self._update_current_progress_remaining(self.num_timesteps, total_timesteps)

            # Display training infos
            if log_interval is not None and iteration % log_interval == 0:
                assert self.ep_info_buffer is not None
                self.dump_logs(iteration)

            self.train()

        callback.on_training_end()

        return self

    # ================================================================== rollout
    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """RecurrentPPO's rollout with hooks: roots and traces before each decision,
        inverse-CDF sampling from recorded uniforms, activity masks, failure detection
        after each step, and the generation's searches at the end."""
        assert isinstance(
            rollout_buffer, (RecurrentRolloutBuffer, RecurrentDictRolloutBuffer)
        ), f"{rollout_buffer} doesn't support recurrent policy"

        assert self._last_obs is not None, "No previous observation was provided"
        # Switch to eval mode (this affects batch norm / dropout)
        self.policy.set_training_mode(False)

        n_steps = 0
        rollout_buffer.reset()
        # Sample new weights for the state dependent exploration
        if self.use_sde:
            self.policy.reset_noise(env.num_envs)

        callback.on_rollout_start()

        lstm_states = deepcopy(self._last_lstm_states)
        self._rollout_start(env)

        while n_steps < n_rollout_steps:
            if self.use_sde and self.sde_sample_freq > 0 and n_steps % self.sde_sample_freq == 0:
                # Sample a new noise matrix
                self.policy.reset_noise(env.num_envs)

            with th.no_grad():
                # Convert to pytorch tensor or to TensorDict
                obs_tensor = obs_as_tensor(self._last_obs, self.device)
                episode_starts = th.tensor(self._last_episode_starts, dtype=th.float32, device=self.device)
                if self._branching:
                    actions, values, log_probs, lstm_states = self._branching_policy_step(
                        env, obs_tensor, lstm_states, episode_starts
                    )
                elif self.mask_inactive:
                    actions, values, log_probs, lstm_states = self._active_policy_step(
                        obs_tensor, lstm_states, episode_starts
                    )
                else:
                    actions, values, log_probs, lstm_states = self.policy(obs_tensor, lstm_states, episode_starts)

            actions = actions.cpu().numpy()

            # Rescale and perform action
            clipped_actions = actions
            # Clip the actions to avoid out of bound error
            if isinstance(self.action_space, spaces.Box):
                clipped_actions = np.clip(actions, self.action_space.low, self.action_space.high)

            new_obs, rewards, dones, infos = env.step(clipped_actions)

            self.num_timesteps += env.num_envs

            # Give access to local variables
            callback.update_locals(locals())
            if not callback.on_step():
                return False

            self._update_info_buffer(infos, dones)
            n_steps += 1

            if isinstance(self.action_space, spaces.Discrete):
                # Reshape in case of discrete action
                actions = actions.reshape(-1, 1)

            # Handle timeout by bootstraping with value function (GitHub issue #633)
            self._bootstrap_timeouts(rewards, dones, infos, lstm_states)

            rollout_buffer.add(
                self._last_obs,
                actions,
                rewards,
                self._last_episode_starts,
                values,
                log_probs,
                lstm_states=self._last_lstm_states,
                active=self._last_active if self.mask_inactive else None,
            )

            new_active, revived = self._after_env_step(env, dones, infos)

            self._last_obs = new_obs
            # a slot that turns active again without a done starts a new episode for the LSTM
            self._last_episode_starts = dones if revived is None else (dones | revived)
            self._last_lstm_states = lstm_states
            self._last_active = new_active

        with th.no_grad():
            # Compute value for the last timestep
            episode_starts = th.tensor(dones, dtype=th.float32, device=self.device)
            values = self.policy.predict_values(obs_as_tensor(new_obs, self.device), lstm_states.vf, episode_starts)

        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)

        self._rollout_end(env)

        callback.on_rollout_end()

        return True

    def _bootstrap_timeouts(self, rewards: np.ndarray, dones: np.ndarray, infos: list[dict], lstm_states: RNNStates) -> None:
        """Add gamma * V(terminal obs) to truncated episodes' last reward.

        Features off: the parent's per-index code (bit-identical), visiting only done
        indices. Otherwise one batched critic pass over every truncated index.
        """
        done_idx = np.flatnonzero(dones)
        if done_idx.size == 0:
            return
        truncated = [
            idx for idx in done_idx.tolist()
            if infos[idx].get("terminal_observation") is not None and infos[idx].get("TimeLimit.truncated", False)
        ]
        if not truncated:
            return
        batched = (self.counterfactual or self.mask_inactive) and not isinstance(self.observation_space, spaces.Dict)
        if not batched:
            for idx in truncated:
                terminal_obs = self.policy.obs_to_tensor(infos[idx]["terminal_observation"])[0]
                with th.no_grad():
                    terminal_lstm_state = (
                        lstm_states.vf[0][:, idx : idx + 1, :].contiguous(),
                        lstm_states.vf[1][:, idx : idx + 1, :].contiguous(),
                    )
                    episode_starts = th.tensor([False], dtype=th.float32, device=self.device)
                    terminal_value = self.policy.predict_values(terminal_obs, terminal_lstm_state, episode_starts)[0]
                rewards[idx] += self.gamma * terminal_value
            return
        idx = np.asarray(truncated, np.int64)
        terminal_obs = np.stack([infos[i]["terminal_observation"] for i in truncated])
        with th.no_grad():
            obs_t = self.policy.obs_to_tensor(terminal_obs)[0]
            sel = th.as_tensor(idx, device=self.device)
            state = (lstm_states.vf[0][:, sel].contiguous(), lstm_states.vf[1][:, sel].contiguous())
            starts = th.zeros(idx.size, dtype=th.float32, device=self.device)
            terminal_values = self.policy.predict_values(obs_t, state, starts).reshape(-1).cpu().numpy()
        rewards[idx] += (self.gamma * terminal_values).astype(rewards.dtype)

    # ------------------------------------------------------------------ activity
    def _observed_active(self, env: VecEnv, infos: list[dict] | None) -> np.ndarray:
        """(num_envs,) bool: slots whose current observation belongs to a live agent."""
        if hasattr(env, "active_mask"):
            return np.asarray(env.active_mask(), bool).reshape(-1)
        if infos is not None and infos and "active" in infos[0]:
            return np.fromiter((bool(i.get("active", True)) for i in infos), bool, count=len(infos))
        return np.ones(env.num_envs, bool)

    def _on_env_reset(self) -> None:
        """Called when ``learn`` reset the env: fresh activity mask, stale roots dropped."""
        assert self.env is not None
        self._last_active = self._observed_active(self.env, getattr(self.env, "reset_infos", None))
        if self._branching:
            self._ensure_branching_state(self.env)
        if self._roots is not None:
            self._roots.invalidate()
        self._requests = []

    # ------------------------------------------------------------------ hooks
    def _rollout_start(self, env: VecEnv) -> None:
        self.budget.start_generation()
        self._gen_stats = Counter()
        if self._last_active is None:
            self._last_active = self._observed_active(env, None)
        if self._branching:
            self._ensure_branching_state(env)

    def _ensure_branching_state(self, env: VecEnv) -> None:
        sim = env.sim
        if self._roots is None or self._sim_for_roots is not sim:
            lstm = self.policy.lstm_actor
            self._roots = RootStore(
                num_worlds=int(env.num_worlds),
                max_agents=int(env.max_agents),
                episode_steps=int(sim.config.episode_steps),
                root_interval=int(self.root_interval),
                window_end=int(self.window[1]) if self.backtrack == "value" else max(int(self.window[1]), int(self.fixed_depth)),
                lstm_layers=lstm.num_layers,
                lstm_hidden=lstm.hidden_size,
                device=self.device,
            )
            self._sim_for_roots = sim
            self._runner = None
        if self._uniform_generator is None:
            self._uniform_generator = th.Generator().manual_seed(int(self.seed or 0) + 7919)
        if self._runner is None:
            vec_normalize = unwrap_vec_normalize(env)
            transform = None
            if vec_normalize is not None:
                def transform(obs: th.Tensor) -> th.Tensor:
                    return th.as_tensor(vec_normalize.normalize_obs(obs.cpu().numpy()), device=obs.device)
            branch_generator = th.Generator().manual_seed(int(self.seed or 0) + 104729)
            self._runner = BranchRunner(self._make_branch_simulator(env), self.policy, transform, branch_generator)

    @staticmethod
    def _make_branch_simulator(env: VecEnv) -> Any:
        source = env.sim

        def make(num_worlds: int) -> Any:
            from cpsim.simulator import Simulator

            # the main simulator's static Model is shared: no second road grid / pool build
            pool = getattr(source, "model", None) or source.scenarios
            return Simulator(pool, num_worlds=int(num_worlds), max_agents=int(source.max_agents),
                             config=source.config, device=str(source.device))

        return make

    def _active_index(self, n: int) -> th.Tensor | None:
        """Indices of the slots whose observation belongs to a live agent, or None when
        every slot does (then the network runs on the full batch)."""
        active = self._last_active
        if active is None or active.size != n or active.all():
            return None
        return th.as_tensor(np.flatnonzero(active), device=self.device)

    @staticmethod
    def _take_states(states: RNNStates, idx: th.Tensor) -> RNNStates:
        return RNNStates((states.pi[0][:, idx], states.pi[1][:, idx]), (states.vf[0][:, idx], states.vf[1][:, idx]))

    @staticmethod
    def _put_states(states: RNNStates, idx: th.Tensor, part: RNNStates) -> RNNStates:
        """``states`` with the columns ``idx`` replaced by ``part`` (inactive slots keep
        their memory; they restart with an episode start when they come back)."""
        def put(full: th.Tensor, sub: th.Tensor) -> th.Tensor:
            out = full.clone()
            out[:, idx] = sub
            return out

        return RNNStates((put(states.pi[0], part.pi[0]), put(states.pi[1], part.pi[1])),
                         (put(states.vf[0], part.vf[0]), put(states.vf[1], part.vf[1])))

    def _active_policy_step(
        self, obs_tensor: th.Tensor, lstm_states: RNNStates, episode_starts: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, RNNStates]:
        """``policy.forward`` on the live slots only; inactive slots get action 0, value 0
        and log-prob 0, which the masked buffer never uses."""
        n = obs_tensor.shape[0]
        idx = self._active_index(n)
        if idx is None:
            return self.policy(obs_tensor, lstm_states, episode_starts)
        actions, values, log_probs, states = self.policy(
            obs_tensor[idx], self._take_states(lstm_states, idx), episode_starts[idx]
        )
        full_actions = th.zeros((n, *actions.shape[1:]), dtype=actions.dtype, device=self.device)
        full_values = th.zeros((n, *values.shape[1:]), dtype=values.dtype, device=self.device)
        full_log_probs = th.zeros(n, dtype=log_probs.dtype, device=self.device)
        full_actions[idx], full_values[idx], full_log_probs[idx] = actions, values, log_probs
        return full_actions, full_values, full_log_probs, self._put_states(lstm_states, idx, states)

    def _branching_policy_step(
        self, env: VecEnv, obs_tensor: th.Tensor, lstm_states: RNNStates, episode_starts: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, RNNStates]:
        """Roots (before the decision), one actor+critic pass over the live slots,
        inverse-CDF sampling from fresh recorded uniforms, trace of values / uniforms /
        actions (inactive slots: value 0, action 0)."""
        assert self._roots is not None and self._uniform_generator is not None
        sim = env.sim
        step_count = _to_numpy(sim.step_count).astype(np.int64).copy()
        self._step_count_before = step_count
        due = self._roots.due(step_count)
        if due.size:
            keep = (1.0 - episode_starts).view(1, -1, 1)  # memory the LSTM will actually use
            pi = (lstm_states.pi[0] * keep, lstm_states.pi[1] * keep)
            vf = (lstm_states.vf[0] * keep, lstm_states.vf[1] * keep)
            snapshot = sim.snapshot(due, out=self._roots.take_free(due.size))
            conditions = _to_numpy(sim.conditions)[due].astype(np.float32)
            alive = _to_numpy(sim.policy_mask)[due].sum(axis=1)
            self._roots.store(due, step_count[due], snapshot, pi, vf, conditions, alive)

        n = obs_tensor.shape[0]
        # one draw per slot whether or not it is live, so the stream does not depend on activity
        uniforms = th.rand(n, generator=self._uniform_generator).to(self.device)
        idx = self._active_index(n) if self.mask_inactive else None
        if idx is None:
            logits, values, new_states = policy_step_logits(self.policy, obs_tensor, lstm_states, episode_starts)
            actions = inverse_cdf_sample(logits, uniforms)
            log_probs = th.log_softmax(logits, dim=-1).gather(-1, actions[:, None]).squeeze(-1)
        else:
            logits, sub_values, sub_states = policy_step_logits(
                self.policy, obs_tensor[idx], self._take_states(lstm_states, idx), episode_starts[idx]
            )
            sub_actions = inverse_cdf_sample(logits, uniforms[idx])
            actions = th.zeros(n, dtype=th.int64, device=self.device)
            values = th.zeros((n, 1), dtype=sub_values.dtype, device=self.device)
            log_probs = th.zeros(n, dtype=logits.dtype, device=self.device)
            actions[idx] = sub_actions
            values[idx] = sub_values
            log_probs[idx] = th.log_softmax(logits, dim=-1).gather(-1, sub_actions[:, None]).squeeze(-1)
            new_states = self._put_states(lstm_states, idx, sub_states)
        self._roots.record_step(step_count, values.reshape(-1).cpu().numpy(), uniforms.cpu().numpy(),
                                actions.cpu().numpy())
        return actions, values, log_probs, new_states

    def _after_env_step(self, env: VecEnv, dones: np.ndarray, infos: list[dict]) -> tuple[np.ndarray, np.ndarray | None]:
        """Budget count, failures -> search requests, episode bookkeeping.

        Returns the new activity mask and the slots revived without a done (or None).
        """
        assert self._last_active is not None
        was_active = self._last_active
        self.budget.add_main(int(np.count_nonzero(was_active)))
        new_active = self._observed_active(env, infos)
        if self._branching:
            self._detect_failures(env, dones, infos, was_active)
        revived = None
        if self.mask_inactive:
            revived = new_active & ~was_active & ~np.asarray(dones, bool)
        return new_active, revived

    def _detect_failures(self, env: VecEnv, dones: np.ndarray, infos: list[dict], was_active: np.ndarray) -> None:
        assert self._roots is not None and self._step_count_before is not None
        roots = self._roots
        a = roots.max_agents
        for idx in np.flatnonzero(np.asarray(dones, bool) & was_active).tolist():
            code = _outcome_code(infos[idx].get("outcome"))
            if code not in FAILURE_OUTCOMES:
                continue
            self._gen_stats["failures"] += 1
            self._gen_stats[f"failures_{_OUTCOME_NAMES[code]}"] += 1
            w, slot = divmod(idx, a)
            failure_step = int(self._step_count_before[w])
            root_steps, _ = roots.roots_of(w)
            root_steps = root_steps[root_steps <= failure_step]
            root = select_root(
                roots.values[w, slot], root_steps, failure_step,
                window=self.window, rho=self.rho, mode=self.backtrack, fixed_depth=self.fixed_depth,
            )
            if root is None:
                self._gen_stats["failures_without_root"] += 1
                continue
            self._requests.append(roots.request(w, slot, failure_step, code, root))
        step_after = _to_numpy(env.sim.step_count).astype(np.int64)
        reset = np.flatnonzero(step_after <= self._step_count_before)
        roots.new_episodes(reset)

    def _rollout_end(self, env: VecEnv) -> None:
        start = time.process_time()
        if self._branching and self._requests:
            self._run_searches()
        self._gen_stats["search_cpu_s"] = time.process_time() - start
        if self._roots is not None:
            self._roots.collect_garbage()
        self._requests = []
        summary = self.budget.end_generation()
        self._log_generation(summary)

    # ================================================================== search
    def _candidate_conditions(self, base: np.ndarray, focal: int) -> np.ndarray:
        """(1 + J, A, 10): factual w0 then one world per panel profile (focal style only)."""
        out = np.repeat(base[None].astype(np.float32), 1 + len(self.panel), axis=0)
        if self.style_change:
            for j, name in enumerate(self.panel, start=1):
                style = PROFILES[PROFILE_ALIASES.get(name, name)]
                out[j, focal, STYLE_MASK] = style[STYLE_MASK]
        return out

    def _independent_flags(self, num_branches: int) -> np.ndarray:
        flags = np.zeros(num_branches, bool)
        if not self.shared_randomness:
            flags[:] = True
        elif not self.style_change:
            flags[1:] = True  # otherwise the candidates would replay the factual branch
        return flags

    def _run_searches(self) -> None:
        """Budgeted searches of this generation, in waves; fills teachers.

        A search is admitted when its projected cost (an upper bound: every agent alive at
        the root runs to the deadline in every branch) fits the generation's remaining
        allowance. Branches end early when agents finish, so after each wave the allowance
        is recomputed from the transitions actually run and the searches that did not fit
        are offered again; the cap holds throughout.
        """
        assert self._runner is not None
        stats = self._gen_stats
        n_branch = 1 + len(self.panel)
        per_search = n_branch + (2 if self.verify else 0)
        pending = list(self._requests)
        if self.max_searches is not None:
            stats["searches_skipped"] += max(0, len(pending) - int(self.max_searches))
            pending = pending[: int(self.max_searches)]
        while pending:
            accepted: list[SearchRequest] = []
            rest: list[SearchRequest] = []
            projected = 0
            for req in pending:
                cost = req.projected_transitions(per_search)
                if self.budget.fits(projected + cost):
                    accepted.append(req)
                    projected += cost
                else:
                    rest.append(req)
            if not accepted:
                break
            self._run_wave(accepted, n_branch)
            pending = rest
        stats["searches_skipped"] += len(pending)
        stats["teachers"] = len(self._teachers)

    def _run_wave(self, accepted: list[SearchRequest], n_branch: int) -> None:
        """Run one batch of searches (all branches together), rank, verify, keep teachers."""
        stats = self._gen_stats
        stats["searches"] += len(accepted)
        stats["search_waves"] += 1
        for req in accepted:
            stats[f"root_depth_{req.depth}"] += 1
        stats["root_depth_sum"] += sum(r.depth for r in accepted)

        jobs = [
            BranchJob(
                snapshot=req.snapshot, snapshot_row=req.snapshot_row,
                conditions=self._candidate_conditions(req.conditions, req.focal),
                pi_state=req.pi_state, vf_state=req.vf_state, focal=req.focal,
                root_step=req.root_step, deadline=req.deadline,
                independent_focal=self._independent_flags(n_branch), record=True,
            )
            for req in accepted
        ]
        results = self._runner.run(jobs)
        chosen: list[tuple[SearchRequest, BranchJob, BranchResult, int]] = []
        for req, job, res in zip(accepted, jobs, results):
            self.budget.add_branch(factual=int(res.transitions[0]), candidate=int(res.transitions[1:].sum()))
            factual, candidates = res.outcomes[0], res.outcomes[1:]
            stats["factual_completed"] += int(factual.completed)
            stats["admissible"] += sum(admit(factual, c) for c in candidates)
            j = choose_teacher(factual, candidates, self.selection)
            if j is not None:
                chosen.append((req, job, res, j))
        stats["teachers_chosen"] += len(chosen)

        passed = [True] * len(chosen)
        if self.verify and chosen:
            vjobs = [
                BranchJob(
                    snapshot=req.snapshot, snapshot_row=req.snapshot_row,
                    conditions=job.conditions[[0, 1 + j]],
                    pi_state=req.pi_state, vf_state=req.vf_state, focal=req.focal,
                    root_step=req.root_step, deadline=req.deadline,
                    independent_focal=self._independent_flags(n_branch)[[0, 1 + j]], record=False,
                )
                for req, job, _, j in chosen
            ]
            vresults = self._runner.run(vjobs)
            for k, vres in enumerate(vresults):
                self.budget.add_branch(verification=int(vres.transitions.sum()))
                passed[k] = verify(vres.outcomes[0], vres.outcomes[1])
            stats["verified"] += int(sum(passed))
            stats["verification_failed"] += len(chosen) - int(sum(passed))
        keep_wave(self, accepted, results, chosen, passed, vresults if self.verify and chosen else None)

        for (req, job, res, j), ok in zip(chosen, passed):
            if not ok:
                continue
            teacher = self._make_teacher(req, res, 1 + j)
            if teacher is not None:
                self._teachers.append(teacher)
                stats[f"profile_{self.panel[j]}"] += 1

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
            profile=self.panel[branch - 1],
            root_step=req.root_step,
            failure_step=req.failure_step,
        )

    def replay_root(self, world: int, root_step: int, main_draws: bool = True) -> BranchResult:
        """Re-run a stored root of ``world``'s current episode as one factual branch.

        With ``main_draws`` the branch samples every decision from the uniforms the main
        rollout used (fresh draws once those run out), so it reproduces the recorded
        actions and trajectory: the check that branches start from the true state.
        Returns the :class:`BranchResult` (``actions`` (1, T, A), ``xy`` (1, T + 1, A, 2)).
        """
        if self._roots is None or self._runner is None:
            raise ValueError("world: no roots recorded yet (counterfactual=True and a rollout are needed)")
        roots = self._roots
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
            snapshot=roots.snapshots[int(roots.snapshot_id[world, p])],
            snapshot_row=int(roots.snapshot_row[world, p]),
            conditions=roots.conditions[world, p][None].copy(),
            pi_state=(roots.pi_h[world, p], roots.pi_c[world, p]),
            vf_state=(roots.vf_h[world, p], roots.vf_c[world, p]),
            focal=0, root_step=int(root_step), deadline=roots.episode_steps, uniforms=draws, record=False,
        )
        return self._runner.run([job])[0]

    # ================================================================== logging
    def _log_generation(self, summary: dict[str, int]) -> None:
        if not self.counterfactual:
            return
        s = self._gen_stats
        # running totals over every generation of this model (for summaries and reports)
        totals = self.__dict__.setdefault("search_totals", {})
        for key, value in s.items():
            totals[key] = totals.get(key, 0) + value
        record = self.logger.record
        record("counterplay/failures", s["failures"])
        for name in ("collision", "offroad", "timeout"):
            record(f"counterplay/failures_{name}", s[f"failures_{name}"])
        record("counterplay/failures_without_root", s["failures_without_root"])
        record("counterplay/searches", s["searches"])
        record("counterplay/searches_skipped", s["searches_skipped"])
        record("counterplay/search_waves", s["search_waves"])
        record("counterplay/root_depth_mean", s["root_depth_sum"] / s["searches"] if s["searches"] else 0.0)
        for key in sorted(k for k in s if k.startswith("root_depth_") and k[11:].isdigit()):
            record(f"counterplay/roots_by_depth/{key[11:]}", s[key])
        record("counterplay/admissible", s["admissible"])
        record("counterplay/teachers_chosen", s["teachers_chosen"])
        record("counterplay/verified_teachers", s["teachers"])
        chosen = s["teachers_chosen"]
        record("counterplay/verification_pass_rate", (s["verified"] / chosen) if (self.verify and chosen) else float("nan"))
        for name in self.panel:
            record(f"counterplay/profile/{name}", s[f"profile_{name}"])
        gen_total = summary["main"] + summary["branch"]
        record("counterplay/search_cpu_s", s["search_cpu_s"])
        record("counterplay/branch_share", summary["branch"] / gen_total if gen_total else 0.0)
        for key in ("main", "factual", "candidate", "verification", "total"):
            record(f"counterplay/budget_{key}", getattr(self.budget, key))

    # ================================================================== train
    def _distill_schedule(self, total_updates: int) -> set[int]:
        """Minibatch update indices (of this generation) that carry the distillation term."""
        k = int(self.distill_minibatches)
        if total_updates <= 0:
            return set()
        return set(np.linspace(0, total_updates - 1, min(k, total_updates)).round().astype(int).tolist())

    def _prepare_distillation(self) -> TeacherBatch | None:
        if not self._teachers or self.env is None or float(self.distill_coef) == 0.0:
            return None
        layout = self.env.obs_layout
        return collate_teachers(
            self._teachers, self._deploy_raw, layout.replace_condition, STYLE_MASK, device=self.device,
            policy=self.policy if self.distill == "ppo" else None, gamma=self.gamma,
        )

    def train(self) -> None:
        """RecurrentPPO's update with masked inactive slots and the distillation term."""
        # Switch to train mode (this affects batch norm / dropout)
        self.policy.set_training_mode(True)
        # Update optimizer learning rate
        self._update_learning_rate(self.policy.optimizer)
        # Compute current clip range
        clip_range = self.clip_range(self._current_progress_remaining)
        # Optional: clip range for the value function
        if self.clip_range_vf is not None:
            clip_range_vf = self.clip_range_vf(self._current_progress_remaining)

        entropy_losses = []
        pg_losses, value_losses = [], []
        clip_fractions = []

        continue_training = True

        distill_batch = self._prepare_distillation()
        distill_losses: list[float] = []
        distill_at: set[int] = set()
        if distill_batch is not None:
            per_epoch = self.rollout_buffer.num_minibatches(self.batch_size)
            distill_at = self._distill_schedule(self.n_epochs * per_epoch)
            self._teachers = []
        distill_pending = len(distill_at)
        update = 0

        # train for n_epochs epochs
        for epoch in range(self.n_epochs):
            approx_kl_divs = []
            # Do a complete pass on the rollout buffer
            for rollout_data in self.rollout_buffer.get(self.batch_size):
                actions = rollout_data.actions
                if isinstance(self.action_space, spaces.Discrete):
                    # Convert discrete action from float to long
                    actions = rollout_data.actions.long().flatten()

                # Convert mask from float to bool
                mask = rollout_data.mask > 1e-8
                with_distill = update in distill_at
                update += 1
                if self.mask_inactive and not bool(mask.any()):
                    # every transition of this minibatch is an inactive slot: nothing to learn
                    continue

                values, log_prob, entropy = self.policy.evaluate_actions(
                    rollout_data.observations,
                    actions,
                    rollout_data.lstm_states,
                    rollout_data.episode_starts,
                )

                values = values.flatten()
                # Normalize advantage
                advantages = rollout_data.advantages
                if self.normalize_advantage:
                    advantages = (advantages - advantages[mask].mean()) / (advantages[mask].std() + 1e-8)

                # ratio between old and new policy, should be one at the first iteration
                ratio = th.exp(log_prob - rollout_data.old_log_prob)

                # clipped surrogate loss
                policy_loss_1 = advantages * ratio
                policy_loss_2 = advantages * th.clamp(ratio, 1 - clip_range, 1 + clip_range)
                policy_loss = -th.mean(th.min(policy_loss_1, policy_loss_2)[mask])

                # Logging
                pg_losses.append(policy_loss.item())
                clip_fraction = th.mean((th.abs(ratio - 1) > clip_range).float()[mask]).item()
                clip_fractions.append(clip_fraction)

                if self.clip_range_vf is None:
                    # No clipping
                    values_pred = values
                else:
                    # Clip the different between old and new value
                    # NOTE: this depends on the reward scaling
                    values_pred = rollout_data.old_values + th.clamp(
                        values - rollout_data.old_values, -clip_range_vf, clip_range_vf
                    )
                # Value loss using the TD(gae_lambda) target
                # Mask padded sequences
                value_loss = th.mean(((rollout_data.returns - values_pred) ** 2)[mask])

                value_losses.append(value_loss.item())

                # Entropy loss favor exploration
                if entropy is None:
                    # Approximate entropy when no analytical form
                    entropy_loss = -th.mean(-log_prob[mask])
                else:
                    entropy_loss = -th.mean(entropy[mask])

                entropy_losses.append(entropy_loss.item())

                loss = policy_loss + self.ent_coef * entropy_loss + self.vf_coef * value_loss

                if with_distill and distill_batch is not None:
                    # branch data enters through this term only, never the PPO / value losses
                    distill_term = distill_loss(self.policy, distill_batch, self.distill, clip_range)
                    loss = loss + self.distill_coef * distill_term

                # Calculate approximate form of reverse KL Divergence for early stopping
                # see issue #417: https://github.com/DLR-RM/stable-baselines3/issues/417
                # and discussion in PR #419: https://github.com/DLR-RM/stable-baselines3/pull/419
                # and Schulman blog: http://joschu.net/blog/kl-approx.html
                with th.no_grad():
                    log_ratio = log_prob - rollout_data.old_log_prob
                    approx_kl_div = th.mean(((th.exp(log_ratio) - 1) - log_ratio)[mask]).cpu().numpy()
                    approx_kl_divs.append(approx_kl_div)

                if self.target_kl is not None and approx_kl_div > 1.5 * self.target_kl:
                    continue_training = False
                    if self.verbose >= 1:
                        print(f"Early stopping at step {epoch} due to reaching max kl: {approx_kl_div:.2f}")
                    break

                # Optimization step
                self.policy.optimizer.zero_grad()
                loss.backward()
                # Clip grad norm
                th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
                self.policy.optimizer.step()
                if with_distill and distill_batch is not None:
                    distill_losses.append(distill_term.item())
                    distill_pending -= 1

            self._n_updates += 1
            if not continue_training:
                break

        # distillation updates that did not happen inside PPO minibatches (early stop,
        # skipped all-inactive minibatches): run them on their own
        while distill_batch is not None and distill_pending > 0:
            distill_term = distill_loss(self.policy, distill_batch, self.distill, clip_range)
            self.policy.optimizer.zero_grad()
            (self.distill_coef * distill_term).backward()
            th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
            self.policy.optimizer.step()
            distill_losses.append(distill_term.item())
            distill_pending -= 1

        buffer_values = self.rollout_buffer.values.flatten()
        buffer_returns = self.rollout_buffer.returns.flatten()
        if self.mask_inactive:
            active = np.asarray(self.rollout_buffer.active).reshape(-1) > 0
            buffer_values, buffer_returns = buffer_values[active], buffer_returns[active]
        explained_var = explained_variance(buffer_values, buffer_returns) if buffer_values.size else float("nan")

        # Logs
        self.logger.record("train/entropy_loss", np.mean(entropy_losses))
        self.logger.record("train/policy_gradient_loss", np.mean(pg_losses))
        self.logger.record("train/value_loss", np.mean(value_losses))
        self.logger.record("train/approx_kl", np.mean(approx_kl_divs))
        self.logger.record("train/clip_fraction", np.mean(clip_fractions))
        if pg_losses:
            self.logger.record("train/loss", loss.item())
        self.logger.record("train/explained_variance", explained_var)
        if hasattr(self.policy, "log_std"):
            self.logger.record("train/std", th.exp(self.policy.log_std).mean().item())

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/clip_range", clip_range)
        if self.clip_range_vf is not None:
            self.logger.record("train/clip_range_vf", clip_range_vf)
        if distill_batch is not None:
            self.logger.record(f"counterplay/distill_{self.distill}", float(np.mean(distill_losses)) if distill_losses else float("nan"))
            self.logger.record("counterplay/distill_teachers", distill_batch.num_teachers)
