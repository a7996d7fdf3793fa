"""A ``learn`` progress bar that counts what ``learn`` really runs.

SB3's ``ProgressBarCallback`` adds ``num_envs`` per step against ``total_timesteps``, so with
a batched self-play env it overshoots (245,760 / 200,000) and sits at 100 % through the
last update. This bar follows ``model.num_timesteps`` (B_post for CounterPlay: live
transitions of main rollouts and branches), re-estimates its total after every rollout
as the target when the model cuts its last rollout there (``stops_exactly``: a budget
is set), else as "the generations still needed x the last generation's size"
(exact once the last generation has run), and names the phase: rollout, search, train.
"""

from __future__ import annotations

from stable_baselines3.common.callbacks import BaseCallback

__all__ = ["LearnProgressBar"]


class LearnProgressBar(BaseCallback):
    """tqdm bar over ``model.num_timesteps`` with the current phase as its description."""

    def __init__(self) -> None:
        super().__init__()
        self.pbar = None
        self._start = 0
        self._target = 0
        self._generation_start = 0

    def _on_training_start(self) -> None:
        from tqdm.auto import tqdm

        self._start = int(self.model.num_timesteps)
        self._generation_start = self._start
        self._target = max(0, int(self.locals["total_timesteps"]) - self._start)
        self.pbar = tqdm(total=self._target, unit="transitions", unit_scale=True, dynamic_ncols=True)

    def set_phase(self, phase: str) -> None:
        """Show ``phase`` ("rollout", "search", "train") in front of the bar."""
        if self.pbar is not None:
            self._sync()
            self.pbar.set_description_str(phase, refresh=True)

    def _sync(self) -> None:
        if self.pbar is not None:
            self.pbar.n = int(self.model.num_timesteps) - self._start
            self.pbar.refresh()

    def _on_step(self) -> bool:
        if self.pbar is not None:
            self.pbar.n = int(self.model.num_timesteps) - self._start
            self.pbar.update(0)  # tqdm refreshes at most every mininterval
        return True

    def _on_rollout_end(self) -> None:
        if self.pbar is None:
            return
        done = int(self.model.num_timesteps) - self._start
        per_generation = max(1, int(self.model.num_timesteps) - self._generation_start)
        self._generation_start = int(self.model.num_timesteps)
        left = max(0, self._target - done)
        if getattr(self.model, "stops_exactly", False):
            self.pbar.total = max(self._target, done)  # the last rollout is cut at the target
        else:
            # learn stops at the first generation boundary at or past the target
            self.pbar.total = done + -(-left // per_generation) * per_generation
        self._sync()

    def _on_training_end(self) -> None:
        if self.pbar is not None:
            self._sync()
            self.pbar.total = self.pbar.n
            self.pbar.set_description_str("done", refresh=True)
            self.pbar.close()
            self.pbar = None
