"""Small fake VecEnvs for the CounterPlay tests (no simulator needed)."""

from __future__ import annotations

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env.base_vec_env import VecEnv


class SlotVecEnv(VecEnv):
    """Self-play-like VecEnv with inactive slots whose data is garbage.

    Active slots see a deterministic observation sequence (independent of the actions)
    and end an episode every ``episode`` steps. Slot 3 is never active; slot 2 is inactive
    for steps 5..11 of every 16 (it leaves with done=True and comes back without a done,
    like SelfPlayVecEnv). An
    inactive slot's observation and reward are random draws from ``garbage_seed``.
    """

    render_mode = None

    def __init__(self, garbage_seed: int = 0, num_envs: int = 4, episode: int = 8):
        super().__init__(num_envs, spaces.Box(-np.inf, np.inf, (3,), np.float32), spaces.Discrete(3))
        self.garbage = np.random.default_rng(garbage_seed)
        self.episode = episode
        self.t = 0
        self._actions = None

    def _active(self, t: int) -> np.ndarray:
        active = np.ones(self.num_envs, bool)
        active[3] = False
        if 5 <= t % 16 <= 11:
            active[2] = False
        return active

    def _obs(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        active = self._active(t)
        base = np.stack([np.sin(0.3 * t + np.arange(self.num_envs)), np.cos(0.2 * t * np.ones(self.num_envs)),
                         (t % self.episode) / self.episode * np.ones(self.num_envs)], axis=1).astype(np.float32)
        noise = self.garbage.normal(size=base.shape).astype(np.float32) * 3.0
        return np.where(active[:, None], base, noise), active

    def reset(self):
        self.t = 0
        obs, self._act = self._obs(0)
        return obs

    def active_mask(self) -> np.ndarray:
        return self._act.copy()

    def step_async(self, actions):
        self._actions = np.asarray(actions)

    def step_wait(self):
        was = self._act
        self.t += 1
        reward = np.where(was, np.cos(0.5 * self.t + np.arange(self.num_envs)), self.garbage.normal(size=self.num_envs) * 5)
        obs, self._act = self._obs(self.t)
        # like SelfPlayVecEnv: an episode ends with done=True on its last active step,
        # either at the episode length or when the agent leaves (slot 2 at t % 16 == 5)
        dones = was & ((self.t % self.episode == 0) | ~self._act)
        infos = [{"active": bool(a)} for a in self._act]
        for i in np.flatnonzero(dones):
            infos[i]["terminal_observation"] = obs[i].copy()
            infos[i]["TimeLimit.truncated"] = False
        return obs, reward.astype(np.float32), dones, infos

    def close(self):
        pass

    def get_attr(self, attr_name, indices=None):
        return [getattr(self, attr_name)] * self.num_envs

    def set_attr(self, attr_name, value, indices=None):
        setattr(self, attr_name, value)

    def env_method(self, method_name, *args, indices=None, **kwargs):
        return [getattr(self, method_name)(*args, **kwargs)] * self.num_envs

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * self.num_envs


def minibatch_logits(model):
    """Yield ``(data, mask, logits)`` for every minibatch of a collected recurrent rollout:
    the policy's action logits on the stored actions, under ``torch.no_grad``."""
    import torch as th

    with th.no_grad():
        for data in model.rollout_buffer.get(model.batch_size):
            mask = data.mask > 1e-8
            model.policy.evaluate_actions(data.observations, data.actions.long().flatten(), data.lstm_states,
                                          data.episode_starts)
            yield data, mask, model.policy.action_dist.distribution.logits
