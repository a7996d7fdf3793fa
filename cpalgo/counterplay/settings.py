"""CounterPlay's settings: the checks of its arguments and the settings of older checkpoints.

:class:`SettingsMixin` is one of :class:`~cpalgo.counterplay.algorithm.CounterPlay`'s bases:
``_validate_settings`` (every CounterPlay argument; ``ValueError`` names it; subclasses
extend it), ``_search_settings`` (the :class:`~cpalgo.counterplay.driver.SearchSettings` of
the arguments), ``_check_branching_env`` and ``apply_legacy_settings``
(:attr:`~SettingsMixin.LEGACY_SETTINGS`). The ``check_*`` functions are the constructor's
checks of the arguments it stores as given.
"""

from __future__ import annotations

import os
from typing import Any, ClassVar, Sequence

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

from cpalgo.counterplay.distill import DISTILL_MODES
from cpalgo.counterplay.driver import SearchSettings
from cpsim.conditions import resolve_condition

__all__ = ["SettingsMixin", "check_switches", "check_sequences", "checked_clip_reward", "checked_schedule_timesteps"]


def check_switches(**flags: Any) -> None:
    """``ValueError`` naming the first of ``flags`` that is not a bool."""
    for name, flag in flags.items():
        if not isinstance(flag, (bool, np.bool_)):  # bool("no") is True: take no chances with a switch
            raise ValueError(f"{name}: expected True or False, got {flag!r}")


def check_sequences(**seqs: Any) -> None:
    """``ValueError`` naming the first of ``seqs`` that is not a sequence (a string counts)."""
    for name, seq in seqs.items():
        if not isinstance(seq, (str, Sequence, np.ndarray)):
            raise ValueError(f"{name}: expected a sequence, got {seq!r}")


def checked_clip_reward(clip_reward: Any) -> float | None:
    """``clip_reward`` as stored: None or a finite float > 0."""
    if clip_reward is not None and (isinstance(clip_reward, bool) or not isinstance(clip_reward, (int, float))
                                    or not np.isfinite(clip_reward) or clip_reward <= 0):
        raise ValueError(f"clip_reward: expected None or a number > 0, got {clip_reward!r}")
    return None if clip_reward is None else float(clip_reward)


def checked_schedule_timesteps(schedule_timesteps: Any) -> int | None:
    """``schedule_timesteps`` as stored: None or an int >= 1."""
    if schedule_timesteps is not None and (isinstance(schedule_timesteps, bool)
                                           or not isinstance(schedule_timesteps, (int, np.integer))
                                           or schedule_timesteps < 1):
        raise ValueError(f"schedule_timesteps: expected None or a whole number >= 1, got {schedule_timesteps!r}")
    return None if schedule_timesteps is None else int(schedule_timesteps)


class SettingsMixin:
    """CounterPlay's argument checks and legacy settings (see the module docstring)."""

    #: settings added after checkpoints were first written, with the behaviour such an older
    #: checkpoint was trained with (it comes back with that, not with today's default)
    LEGACY_SETTINGS: ClassVar[dict[str, Any]] = {"root_lifetime": "generation"}

    def _validate_settings(self) -> None:
        """Check every CounterPlay argument; ``ValueError`` names the argument."""
        # a saved model comes back from JSON with lists where tuples were
        if isinstance(self.panel, list):
            self.panel = tuple(self.panel)
        if isinstance(self.window, list):
            self.window = tuple(self.window)
        if isinstance(self.deploy_condition, (list, tuple)):
            self.deploy_condition = tuple(float(x) for x in self.deploy_condition)
        for name, integer, optional in (("rho", False, False), ("root_interval", True, False),
                                        ("fixed_depth", True, False), ("distill_coef", False, False),
                                        ("distill_minibatches", True, False), ("branch_cap", False, False),
                                        ("post_budget", False, True), ("max_searches", True, True)):
            value = getattr(self, name)
            if value is None and optional:
                continue
            kinds = (int, np.integer) if integer else (int, float, np.integer, np.floating)
            if isinstance(value, bool) or not isinstance(value, kinds):
                raise ValueError(f"{name}: expected {'a whole number' if integer else 'a number'}"
                                 f"{' or None' if optional else ''}, got {value!r}")
        for name in ("n_steps", "n_epochs"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name}: must be a whole number >= 1, got {value!r}")
        if self.batch_size is not None and (isinstance(self.batch_size, bool)
                                            or not isinstance(self.batch_size, (int, np.integer))
                                            or self.batch_size < 1):
            raise ValueError(f"batch_size: must be a whole number >= 1 or None, got {self.batch_size!r}")
        self._search_settings()  # validates the search arguments
        self._deploy_raw = resolve_condition(self.deploy_condition, "deploy_condition")
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

    def _search_settings(self) -> SearchSettings:
        window = self.window if isinstance(self.window, str) or len(self.window) != 2 else \
            (int(self.window[0]), int(self.window[1]))
        return SearchSettings(
            root_interval=int(self.root_interval), window=window,
            rho=float(self.rho), backtrack=self.backtrack, fixed_depth=int(self.fixed_depth), panel=tuple(self.panel),
            shared_randomness=self.shared_randomness, style_change=self.style_change, selection=self.selection,
            verify=self.verify, max_searches=None if self.max_searches is None else int(self.max_searches),
            root_lifetime=self.root_lifetime, seed=int(self.seed or 0), clip_reward=self.clip_reward,
        )

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

    def apply_legacy_settings(self, path: Any, keep: Sequence[str] = ()) -> None:
        """Give every :attr:`LEGACY_SETTINGS` entry that the checkpoint at ``path`` (a path or
        an open binary file) did not save its value of that time (``keep``: names set explicitly by the caller). Used by
        :meth:`CounterPlay.load <cpalgo.counterplay.algorithm.CounterPlay.load>` and by grid resumes
        (``set_parameters`` of a checkpoint)."""
        from cpalgo.checkpoint import saved_data_keys

        saved = saved_data_keys(path) if isinstance(path, (str, os.PathLike)) or hasattr(path, "seek") else None
        if saved is None:
            return
        for name, value in self.LEGACY_SETTINGS.items():
            if name not in saved and name not in keep:
                setattr(self, name, value)
