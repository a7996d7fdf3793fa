"""CounterPlay: counterfactual post-training of a self-play policy on top of RecurrentPPO.

One generation = one rollout + one update (DESIGN.md, "CounterPlay"; the search itself
lives in :mod:`cpalgo.counterplay.driver`):

1. **Roots.** During rollout g, every ``root_interval`` decisions of a world, the world is
   snapshotted and every agent's actor/critic LSTM memory and condition are kept; every
   agent's critic value, sampling uniform and action are traced at every decision.
2. **Failures.** A POLICY agent whose episode ends in collision, off-road or timeout
   requests one search; its root is chosen right away from the roots of its episode (those
   of rollout g-1 included, unless ``root_lifetime="generation"``).
3. **Branches.** g's searches run in waves during rollout g+1, under g's frozen policy, in
   a second simulator on the same pool: per search one factual branch (w0) and one branch
   per panel profile (focal style fields replaced), every other agent keeping its memory
   and condition; shared inverse-CDF draws.
4. **Ranking, admission, verification** (``search``); the verified retries become
   teachers of g+1's update.
5. **Distillation**: ``distill_coef`` x KL(teacher || student under w_dep) added to
   ``distill_minibatches`` PPO minibatch updates; branch data never enters PPO / value
   losses.
6. **Budget** (``model.budget``): B_post = main + factual + candidate + verification live
   agent transitions. ``num_timesteps`` counts B_post, so ``learn(B)`` stops at the first
   generation boundary where B_post >= B. With ``post_budget`` (every registered method's
   ``learn(B)``, :mod:`cpalgo.methods`) the rollout stops at the step that reaches it
   instead: that last rollout is cut there and still learned from.
   Branch transitions of g's searches <= ``branch_cap`` x g's main transitions.
7. **Live slots only**: inactive ``SelfPlayVecEnv`` slots are skipped by rollout inference
   and by every minibatch (:mod:`cpalgo.common.buffers`), and count in no budget.

The rollout loop is a copy of sb3-contrib 2.9.2's ``RecurrentPPO`` with hook points (its
local variable names are kept for callbacks); the update is the one PPO update of cpalgo,
:mod:`cpalgo.common.ppo_update`. With ``counterfactual=False``, ``mask_inactive=False`` and
sb3-contrib's policy class the computation is exactly the parent's: parameters after
``learn`` are bit-identical to ``RecurrentPPO`` (tested).

This module keeps the constructor, model setup / save / load, ``learn``, the rollout loop
and the update; the rest of the class comes from its bases, one module each:
:mod:`~cpalgo.counterplay.settings` (argument checks, settings of older checkpoints),
:mod:`~cpalgo.counterplay.rollout_hooks` (the rollout loop's hooks, live slots),
:mod:`~cpalgo.counterplay.driver_glue` (the search driver: building it, its statistics,
root replays, the generation log) and :mod:`~cpalgo.counterplay.distill` (the distillation
batch of a generation).
"""

from __future__ import annotations

from copy import deepcopy
from typing import Any, ClassVar, Sequence

import numpy as np
import torch as th
from gymnasium import spaces
from sb3_contrib import RecurrentPPO
from sb3_contrib.common.recurrent.buffers import RecurrentDictRolloutBuffer, RecurrentRolloutBuffer
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, ConvertCallback
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv

from cpalgo.common.buffers import MaskedRecurrentDictRolloutBuffer, MaskedRecurrentRolloutBuffer
from cpalgo.common.distributed import all_reduce_sum, data_parallel
from cpalgo.common.ppo_update import ScheduledTerms, begin_update, run_update
from cpalgo.common.progress import LearnProgressBar
from cpalgo.counterplay.budget import Budget
from cpalgo.counterplay.distill import DistillationMixin, Teacher, distill_loss
from cpalgo.counterplay.driver import FAILURE_OUTCOMES, SearchDriver
from cpalgo.counterplay.driver_glue import SearchDriverMixin
from cpalgo.counterplay.records import check_keep_searches
from cpalgo.counterplay.rollout_hooks import RolloutHooksMixin
from cpalgo.counterplay.settings import (
    SettingsMixin,
    check_sequences,
    check_switches,
    checked_clip_reward,
    checked_schedule_timesteps,
)
from cpalgo.policies import POLICY_ALIASES, BehaviorLstmPolicy
from cpsim.conditions import PANEL

__all__ = ["CounterPlay", "FAILURE_OUTCOMES", "ANCHOR_NETWORK"]

#: The teacher-imitation anchor's network (``zoo/anchor_imitation.zip``), CounterPlay's default
#: ``policy_kwargs`` for the sb3-contrib-shaped policies.
ANCHOR_NETWORK: dict[str, Any] = dict(lstm_hidden_size=128, enable_critic_lstm=False,
                                      net_arch=dict(pi=[128, 128], vf=[128, 128]))


def _default_network(policy: Any) -> dict[str, Any]:
    """``policy_kwargs`` when none are given: the teacher-imitation anchor's network for the
    sb3-contrib-shaped policies, the class's own defaults (the self-play anchor's) for
    BehaviorBench's shape."""
    if policy == "BehaviorLstmPolicy" or (isinstance(policy, type) and issubclass(policy, BehaviorLstmPolicy)):
        return {}
    return deepcopy(ANCHOR_NETWORK)


class CounterPlay(SettingsMixin, RolloutHooksMixin, SearchDriverMixin, DistillationMixin, RecurrentPPO):
    """RecurrentPPO with counterfactual retries of failed tasks distilled into the policy.

    Every argument of :class:`sb3_contrib.RecurrentPPO` is accepted. Defaults that differ,
    so that ``CounterPlay("MlpLstmPolicy", SelfPlayVecEnv())`` trains at batched self-play
    speed: ``n_steps=64``, ``batch_size=4096`` (live transitions per minibatch),
    ``n_epochs=3``, ``policy_kwargs=ANCHOR_NETWORK``, and "MlpLstmPolicy" is the fused
    policy of :mod:`cpalgo.policies`. The CounterPlay arguments (all with defaults, so
    ``load`` can rebuild the model):

    Args:
        counterfactual: run roots / searches / distillation. Needs a branching-capable
            self-play env (``.sim``, ``.obs_layout``, ``num_envs = num_worlds * max_agents``,
            Discrete actions), e.g. :class:`cpsim.SelfPlayVecEnv`.
        root_interval: decisions between roots (5).
        window: (start, end) backtracking depths in decisions, inclusive ((5, 60)).
        rho: value-threshold position in [0, 1] (0.5).
        backtrack: "value" (value-guided root) or "fixed" (``fixed_depth`` decisions back).
        fixed_depth: depth of the "fixed" ablation (20).
        root_lifetime: "episode" (a root stays usable until its world's episode ends, across
            the generation boundary) or "generation" (roots are dropped when a new rollout
            starts, so an episode that began in the previous rollout offers roots only from
            the current one).
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
        branch_cap: branch transitions of g's searches <= branch_cap x g's main transitions.
        post_budget: optional hard cap: the rollout stops at the step where B_post reaches
            it, and branch work never runs past it (``learn(total_timesteps)`` already
            counts B_post; None: no extra cap).
        mask_inactive: skip inactive slots (``info["active"]`` / ``env.active_mask()``) in
            inference, minibatches, losses and the budget.
        max_searches: optional cap on searches per generation (None: the budget decides).
        keep_searches: searches kept per generation as tensor-free records for inspection
            (``cpalgo.counterplay.records``; 0 keeps nothing).
        clip_reward: clamp every step's reward to [-c, c] before it enters the rollout
            buffer (BehaviorBench's trainer uses 1.0; None: no clamp), and the focal rewards of
            branches and continuations alike (selection by return, PPO on recoveries, the
            continuation baselines' returns). Logged episode returns stay unclamped.
        schedule_timesteps: the length (in counted transitions) over which schedules of
            progress (learning rate, clip range) run, whatever ``learn`` is asked for; a run
            trained in several ``learn`` calls (pieces) then follows one schedule (None: SB3's
            rule, the current ``learn`` call's total).
    """

    #: "MlpLstmPolicy" & co. are the fused-sequence versions (cpalgo.policies); pass
    #: sb3-contrib's classes explicitly to get its stepping LSTM
    policy_aliases: ClassVar = POLICY_ALIASES

    #: runtime state that is rebuilt, never saved
    _RUNTIME_ATTRS: ClassVar[tuple[str, ...]] = (
        "_driver", "_teachers", "_last_active", "_deploy_raw", "_search_records", "_progress",
    )

    def __init__(
        self,
        policy: str | type[RecurrentActorCriticPolicy],
        env: GymEnv | str,
        n_steps: int = 64,
        batch_size: int | None = 4096,
        n_epochs: int = 3,
        policy_kwargs: dict[str, Any] | None = None,
        counterfactual: bool = True,
        root_interval: int = 5,
        window: Sequence[int] = (5, 60),
        rho: float = 0.5,
        backtrack: str = "value",
        fixed_depth: int = 20,
        root_lifetime: str = "episode",
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
        clip_reward: float | None = None,
        schedule_timesteps: int | None = None,
        _init_setup_model: bool = True,
        **ppo_kwargs: Any,
    ):
        super().__init__(
            policy, env, n_steps=n_steps, batch_size=batch_size, n_epochs=n_epochs,
            policy_kwargs=_default_network(policy) if policy_kwargs is None else policy_kwargs,
            _init_setup_model=False, **ppo_kwargs,
        )
        check_switches(counterfactual=counterfactual, shared_randomness=shared_randomness, style_change=style_change,
                       verify=verify, mask_inactive=mask_inactive)
        check_sequences(window=window, panel=panel)
        self.counterfactual = bool(counterfactual)
        self.root_interval = root_interval
        self.window = tuple(window) if not isinstance(window, str) else window
        self.rho = rho
        self.backtrack = backtrack
        self.fixed_depth = fixed_depth
        self.root_lifetime = root_lifetime
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
        self.clip_reward = checked_clip_reward(clip_reward)
        self.schedule_timesteps = checked_schedule_timesteps(schedule_timesteps)
        self._validate_settings()
        self.budget = Budget(branch_cap=float(branch_cap), post_budget=post_budget)
        #: running totals of every generation's search counts (SearchStats.as_dict keys)
        self.search_totals: dict[str, float] = {}
        self._reset_runtime()

        if _init_setup_model:
            self._setup_model()

    def _reset_runtime(self) -> None:
        self._driver: SearchDriver | None = None
        self._teachers: list[Teacher] = []
        self._last_active: np.ndarray | None = None
        self._progress: LearnProgressBar | None = None

    # ================================================================== model setup
    def _setup_model(self) -> None:
        """RecurrentPPO's setup, then its rollout buffer swapped for the masked one (built
        from the same arguments; neither consumes random numbers, so the RNG stream is the
        parent's)."""
        self._validate_settings()
        self.budget.branch_cap = float(self.branch_cap)
        self.budget.post_budget = self.post_budget
        super()._setup_model()
        parent = self.rollout_buffer
        buffer_cls = (
            MaskedRecurrentDictRolloutBuffer if isinstance(self.observation_space, spaces.Dict)
            else MaskedRecurrentRolloutBuffer
        )
        self.rollout_buffer = buffer_cls(
            self.n_steps, self.observation_space, self.action_space, parent.hidden_state_shape, self.device,
            gamma=self.gamma, gae_lambda=self.gae_lambda, n_envs=self.n_envs,
        )
        # inactive slots cost no forward/backward pass in train (see cpalgo.common.buffers)
        self.rollout_buffer.active_only = self.mask_inactive
        self._reset_runtime()
        self._check_branching_env(self.env)

    def resize_envs(self, n_envs: int) -> None:
        """Take ``n_envs`` envs from the next ``set_env`` on (a resumed anchor run that changes
        its data-parallel workers): the rollout buffer and the recurrent states are rebuilt
        for them; the policy, the optimiser and the counters stay."""
        if int(n_envs) < 1:
            raise ValueError(f"n_envs: expected a whole number >= 1, got {n_envs!r}")
        from sb3_contrib.common.recurrent.type_aliases import RNNStates

        self.n_envs = int(n_envs)
        lstm = self.policy.lstm_actor
        shape = (lstm.num_layers, self.n_envs, lstm.hidden_size)

        def zeros() -> tuple[th.Tensor, th.Tensor]:
            return th.zeros(shape, device=self.device), th.zeros(shape, device=self.device)

        self._last_lstm_states = RNNStates(zeros(), zeros())
        buffer_cls = type(self.rollout_buffer)
        self.rollout_buffer = buffer_cls(
            self.n_steps, self.observation_space, self.action_space, (self.n_steps, *shape), self.device,
            gamma=self.gamma, gae_lambda=self.gae_lambda, n_envs=self.n_envs,
        )
        self.rollout_buffer.active_only = self.mask_inactive
        self._reset_runtime()

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        super().set_env(env, force_reset=force_reset)
        self._check_branching_env(self.env)
        self._reset_runtime()

    def _excluded_save_params(self) -> list[str]:
        return super()._excluded_save_params() + list(self._RUNTIME_ATTRS)

    @classmethod
    def load(cls, path: Any, env: GymEnv | None = None, device: th.device | str = "auto",
             custom_objects: dict[str, Any] | None = None, print_system_info: bool = False,
             force_reset: bool = True, **kwargs: Any) -> "CounterPlay":
        model = super().load(path, env=env, device=device, custom_objects=custom_objects,
                             print_system_info=print_system_info, force_reset=force_reset, **kwargs)
        model.apply_legacy_settings(path, keep=tuple(kwargs))
        return model

    # ================================================================== learn
    def _update_current_progress_remaining(self, num_timesteps: int, total_timesteps: int) -> None:
        super()._update_current_progress_remaining(num_timesteps, self.schedule_timesteps or total_timesteps)

    def _setup_learn(self, total_timesteps: int, callback: MaybeCallback = None, reset_num_timesteps: bool = True,
                     tb_log_name: str = "run", progress_bar: bool = False) -> tuple[int, BaseCallback]:
        previous_obs = self._last_obs
        out = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        if self._last_obs is not previous_obs or self._last_active is None:
            self._on_env_reset()
        return out

    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        """SB3's, with a progress bar that counts what ``learn`` runs (B_post) and shows
        the phase of the generation, instead of SB3's slot-step bar."""
        self._progress = None
        if progress_bar:
            callbacks = callback if isinstance(callback, list) else ([] if callback is None else [callback])
            callbacks = [c if isinstance(c, BaseCallback) else ConvertCallback(c) for c in callbacks]
            self._progress = LearnProgressBar()
            callback = CallbackList([*callbacks, self._progress])
        return super()._init_callback(callback, progress_bar=False)

    def _set_phase(self, phase: str) -> None:
        if self._progress is not None:
            self._progress.set_phase(phase)

    def learn(self, total_timesteps: int, callback: MaybeCallback = None, log_interval: int = 1,
              tb_log_name: str = "CounterPlay", reset_num_timesteps: bool = True, progress_bar: bool = False) -> Any:
        """``RecurrentPPO.learn`` where ``total_timesteps`` is B_post: live agent transitions
        of the main rollouts plus every branch transition (all slots when
        ``mask_inactive=False``). Stops at the first generation boundary that reaches it; with
        ``post_budget`` set, at the rollout step that reaches that (see ``post_budget``)."""
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    # ================================================================== rollout
    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """RecurrentPPO's rollout with hooks: roots and traces before each decision,
        inference on live slots, inverse-CDF sampling from recorded uniforms, activity
        masks, failure detection after each step, the previous generation's searches in
        waves between steps. ``num_timesteps`` advances by the transitions that count;
        data-parallel (:mod:`cpalgo.common.distributed`) by those of every rank, summed at the
        rollout's end, so every rank's schedules and stopping test see the run's count."""
        assert isinstance(
            rollout_buffer, (RecurrentRolloutBuffer, RecurrentDictRolloutBuffer)
        ), f"{rollout_buffer} doesn't support recurrent policy"

        assert self._last_obs is not None, "No previous observation was provided"
        if self.budget.exhausted:
            return False  # post_budget reached: SB3's learn loop stops here
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
        rollout_start_timesteps = self.num_timesteps

        while n_steps < n_rollout_steps:
            if self.use_sde and self.sde_sample_freq > 0 and n_steps % self.sde_sample_freq == 0:
                # Sample a new noise matrix
                self.policy.reset_noise(env.num_envs)

            with th.no_grad():
                # Convert to pytorch tensor or to TensorDict
                obs_tensor = obs_as_tensor(self._last_obs, self.device)
                episode_starts = th.tensor(self._last_episode_starts, dtype=th.float32, device=self.device)
                actions, values, log_probs, lstm_states = self._policy_step(env, obs_tensor, lstm_states, episode_starts)

            actions = actions.cpu().numpy()

            # Rescale and perform action
            clipped_actions = actions
            # Clip the actions to avoid out of bound error
            if isinstance(self.action_space, spaces.Box):
                clipped_actions = np.clip(actions, self.action_space.low, self.action_space.high)

            new_obs, rewards, dones, infos = env.step(clipped_actions)
            if self.clip_reward is not None:  # BehaviorBench's trainer clamps every step's reward
                rewards = np.clip(rewards, -self.clip_reward, self.clip_reward)

            self.num_timesteps += self._counted_transitions(env)

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

            if self._driver is not None and self._driver.has_pending:
                self._set_phase("search")
                self._driver.advance(n_steps, n_rollout_steps)
                self._set_phase("rollout")

            if n_steps < n_rollout_steps and self.budget.exhausted:
                # B_post reached mid-rollout: learn from the steps taken, so every method
                # stops within one step of live agents of the same budget
                rollout_buffer.truncate(n_steps)
                break

        if data_parallel():  # the run's count: every rank's transitions of this rollout
            local = self.num_timesteps - rollout_start_timesteps
            total = int(all_reduce_sum(local))
            self.num_timesteps = rollout_start_timesteps + total
            self.budget.add_main(total - local)  # the other ranks' main transitions, so it counts the run's too

        with th.no_grad():
            # Compute value for the last timestep
            episode_starts = th.tensor(dones, dtype=th.float32, device=self.device)
            values = self.policy.predict_values(obs_as_tensor(new_obs, self.device), lstm_states.vf, episode_starts)

        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)

        self._rollout_end(env)

        callback.on_rollout_end()

        return True

    # ================================================================== train

    def train(self) -> None:
        """RecurrentPPO's update (:func:`cpalgo.common.ppo_update.run_update`) with masked
        inactive slots and the distillation term: ``distill_coef`` x the distillation loss
        of this generation's teachers on ``distill_minibatches`` minibatch updates; branch
        data enters through this term only, never the PPO / value losses."""
        clip_range, clip_range_vf = begin_update(self)
        distill_batch = self._prepare_distillation()
        scheduled: list[ScheduledTerms] = []
        if distill_batch is not None:
            self._teachers = []
            scheduled = [ScheduledTerms(
                compute=lambda: {"distill": distill_loss(self.policy, distill_batch, self.distill, clip_range)},
                minibatches=int(self.distill_minibatches), weight=self.distill_coef,
            )]
        run_update(self, clip_range, clip_range_vf, masked=self.mask_inactive, scheduled=scheduled)
        if distill_batch is not None:
            losses = scheduled[0].logs.get("distill", [])
            self.logger.record(f"counterplay/distill_{self.distill}", float(np.mean(losses)) if losses else float("nan"))
            self.logger.record("counterplay/distill_teachers", distill_batch.num_teachers)
