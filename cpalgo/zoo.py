"""rl-zoo3 launcher: ``python -m cpalgo.zoo train|enjoy [rl-zoo3 arguments]``.

What it adds to rl-zoo3 before handing over to its own ``train`` / ``enjoy`` entry points:

* ``counterplay`` in ``rl_zoo3.ALGOS`` (and in the copies the train script, the experiment
  manager and enjoy imported), so ``--algo counterplay`` works; ``ppo_lstm`` is
  rl-zoo3's RecurrentPPO and trains the anchor.
* the Gymnasium id ``cpsim/SelfPlay-v0``: the batched self-play env. rl-zoo3 builds
  ``n_envs`` env functions and hands them to ``ExperimentManager.default_vec_env_cls``;
  we plug in :class:`ZooSelfPlayVecEnv`, which builds one :class:`cpsim.SelfPlayVecEnv`
  with ``n_envs / max_agents`` worlds from the YAML's ``env_kwargs``. So in our YAML
  files ``n_envs`` counts agent slots, not processes.

Before rl-zoo3 starts, ``train`` checks the recipe's keys (:func:`check_train_recipe`):
rl-zoo3 hands every key it does not read itself to the algorithm's constructor, so a
misspelled one would end in a traceback; here it is one line naming the file and the key.

``-f file.yml`` is read as ``--conf-file file.yml`` (rl-zoo3's own ``-f`` is the log folder,
which stays available as ``--log-folder``). ``zoo/NAME`` after ``-f`` / ``--conf-file`` /
``-i`` / ``--trained-agent`` names the shipped file when no such file exists
(:func:`cpalgo.recipes.resolve_path`). On the self-play env, ``normalize`` uses
:class:`cpsim.envs.selfplay.SelfPlayVecNormalize` (statistics of active slots only), and
``enjoy`` prints the agents' episode outcomes (rl-zoo3 prints nothing for ``n_envs > 1``).
Example::

    python -m cpalgo.zoo train --algo counterplay --env cpsim/SelfPlay-v0 \\
        -f zoo/counterplay.yml -i zoo/anchor_imitation.zip -n 20000
    python -m cpalgo.zoo enjoy --algo counterplay --env cpsim/SelfPlay-v0 -f logs/ --no-render

``cpsim/SelfPlay-v0`` names a batched environment: made on its own (``gymnasium.make``)
it only carries its settings, and ``reset`` / ``step`` explain how to use it instead.
"""

from __future__ import annotations

import argparse
import difflib
import math
import os
import sys
from typing import Any, Callable, Sequence

import gymnasium
import numpy as np
from gymnasium import spaces

from cpalgo.recipes import SELFPLAY_ENV_ID


class SelfPlaySettings(gymnasium.Env):
    """Carrier of the self-play settings for rl-zoo3 (``gymnasium.make("cpsim/SelfPlay-v0", **kw)``).

    Holds the :class:`cpsim.SelfPlayVecEnv` keyword arguments and the matching spaces;
    :class:`ZooSelfPlayVecEnv` reads them. It cannot be stepped on its own: self-play
    needs every agent slot of a world at once.
    """

    metadata = {"render_modes": ["rgb_array", "human"]}

    def __init__(self, max_agents: int = 8, family: str | None = None, womd_dir: str | None = None,
                 num_scenarios: int | None = None, dynamics: str = "jerk", condition: Any = "train",
                 device: str = "cpu", render_mode: str | None = None, **config_overrides: Any):
        from cpsim.config import SimConfig
        from cpsim.envs.selfplay import OBS_BOUND
        from cpsim.observation import ObsLayout

        config = SimConfig.from_dict({"dynamics": dynamics, **config_overrides})
        layout = ObsLayout(num_partners=config.num_partners, num_road=config.num_road)
        self.observation_space = spaces.Box(-OBS_BOUND, OBS_BOUND, (layout.size,), np.float32)
        self.action_space = spaces.Discrete(int(config.num_actions))
        self.render_mode = render_mode
        self.selfplay_kwargs: dict[str, Any] = dict(
            max_agents=int(max_agents), family=family, womd_dir=womd_dir, num_scenarios=num_scenarios,
            dynamics=dynamics, condition=condition, device=device, render_mode=render_mode,
            **config_overrides,
        )

    def _batched_only(self) -> None:
        raise RuntimeError(
            f"{SELFPLAY_ENV_ID} is a batched self-play environment: build cpsim.SelfPlayVecEnv "
            "directly, or train through `python -m cpalgo.zoo`, which plugs it into rl-zoo3"
        )

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> Any:
        self._batched_only()

    def step(self, action: Any) -> Any:
        self._batched_only()


def _settings_of(env: gymnasium.Env) -> dict[str, Any]:
    inner = env.unwrapped
    if not isinstance(inner, SelfPlaySettings):
        raise ValueError(f"ZooSelfPlayVecEnv: expected {SELFPLAY_ENV_ID} env functions, got {type(inner).__name__}")
    return dict(inner.selfplay_kwargs)


class EpisodeReport:
    """Counts the agents' episode outcomes and returns of a self-play run and prints them:
    one line per ``every`` finished agent episodes, and a total at :meth:`close`."""

    def __init__(self, num_envs: int, every: int, out: Any = None):
        self.every = max(1, int(every))
        self.out = out
        self.returns = np.zeros(num_envs)
        self.lengths = np.zeros(num_envs, np.int64)
        self.outcomes: dict[str, int] = {}
        self.episode_returns: list[float] = []
        self.episode_lengths: list[int] = []
        self._printed = 0

    def update(self, rewards: np.ndarray, dones: np.ndarray, infos: Sequence[dict]) -> None:
        self.returns += rewards
        self.lengths += 1
        for i in np.flatnonzero(dones):
            outcome = infos[i].get("outcome")
            if outcome is not None:  # an agent's episode (not an empty slot's)
                self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1
                self.episode_returns.append(float(self.returns[i]))
                self.episode_lengths.append(int(self.lengths[i]))
            self.returns[i] = 0.0
            self.lengths[i] = 0
        if len(self.episode_returns) - self._printed >= self.every:
            self.print()

    def line(self) -> str:
        n = len(self.episode_returns)
        if not n:
            return "0 agent episodes finished"
        rates = "  ".join(f"{k} {self.outcomes.get(k, 0) / n:.1%}" for k in ("goal", "collision", "offroad", "timeout"))
        return (f"{n} agent episodes: {rates}  mean reward {np.mean(self.episode_returns):.2f} "
                f"+/- {np.std(self.episode_returns):.2f}  mean length {np.mean(self.episode_lengths):.1f}")

    def print(self) -> None:
        self._printed = len(self.episode_returns)
        print(self.line(), file=self.out or sys.stdout, flush=True)


def make_zoo_vec_env_class(report: bool = False) -> type:
    """The VecEnv class rl-zoo3 instantiates with its ``env_fns`` (built lazily: it
    subclasses :class:`cpsim.SelfPlayVecEnv`, whose import loads the simulator).

    ``report``: print the agents' episode outcomes (:class:`EpisodeReport`; for ``enjoy``).
    """
    from cpsim.envs.selfplay import SelfPlayVecEnv

    class ZooSelfPlayVecEnv(SelfPlayVecEnv):
        """``SelfPlayVecEnv`` built from rl-zoo3's env functions: worlds = ceil(n / max_agents)."""

        def __init__(self, env_fns: Sequence[Callable[[], gymnasium.Env]], **kwargs: Any):
            if not env_fns:
                raise ValueError("env_fns: empty")
            carrier = env_fns[0]()
            settings = _settings_of(carrier)
            carrier.close()
            settings.update(kwargs)
            max_agents = int(settings.pop("max_agents"))
            worlds = max(1, math.ceil(len(env_fns) / max_agents))
            super().__init__(num_worlds=worlds, max_agents=max_agents, **settings)
            self.report = EpisodeReport(self.num_envs, every=self.num_envs) if report else None

        def step_wait(self) -> Any:
            obs, rewards, dones, infos = super().step_wait()
            if self.report is not None:
                self.report.update(rewards, dones, infos)
            return obs, rewards, dones, infos

        def close(self) -> None:
            if self.report is not None:
                self.report.print()
                self.report = None
            super().close()

    return ZooSelfPlayVecEnv


def register() -> None:
    """Register the self-play id and CounterPlay with rl-zoo3 (idempotent)."""
    import rl_zoo3
    import rl_zoo3.exp_manager
    import rl_zoo3.utils

    from cpalgo import CounterPlay

    if SELFPLAY_ENV_ID not in gymnasium.registry:
        gymnasium.register(id=SELFPLAY_ENV_ID, entry_point="cpalgo.zoo:SelfPlaySettings",
                           disable_env_checker=True)
    for module in (rl_zoo3, rl_zoo3.utils, rl_zoo3.exp_manager):
        algos = getattr(module, "ALGOS", None)
        if algos is not None:
            algos["counterplay"] = CounterPlay
    # rl-zoo3 evaluates policy_kwargs strings in its exp_manager's globals: make the
    # encoder of zoo/counterplay_fast.yml resolvable there, as load_recipe does
    from cpalgo.encoders import FEATURE_EXTRACTORS

    # (and in its utils, where `-params policy_kwargs:"..."` overrides are evaluated)
    for module in (rl_zoo3.exp_manager, rl_zoo3.utils):
        for name, extractor in FEATURE_EXTRACTORS.items():
            setattr(module, name, extractor)
    # schedule settings (learning_rate: cosine(3e-5), ...) read as load_recipe reads them
    from cpalgo.recipes import install_zoo_schedules

    install_zoo_schedules()


def _uses_selfplay(argv: Sequence[str]) -> bool:
    args = list(argv)
    for i, a in enumerate(args):
        if a == "--env" and i + 1 < len(args):
            return args[i + 1] == SELFPLAY_ENV_ID
        if a.startswith("--env="):
            return a.split("=", 1)[1] == SELFPLAY_ENV_ID
    return False


def _translate_config_flag(args: list[str]) -> list[str]:
    """rl-zoo3's ``-f`` is the log folder; ``-f something.yml`` here means the hyperparameter
    file (``--conf-file``), so the short form in our docs works as written. The files after
    ``--conf-file`` and ``-i`` / ``--trained-agent`` go through
    :func:`cpalgo.recipes.resolve_path` (``zoo/NAME``: the shipped file)."""
    from cpalgo.recipes import resolve_path

    out = list(args)
    for i, a in enumerate(out[:-1]):
        if a in ("-f", "--log-folder") and out[i + 1].endswith((".yml", ".yaml")):
            out[i] = "--conf-file"
        if out[i] in ("--conf-file", "-conf", "-i", "--trained-agent"):
            out[i + 1] = resolve_path(out[i + 1])
    return out


#: Keys of a zoo entry that rl-zoo3 reads itself; it hands every other key to the
#: algorithm's constructor (``--algo``), where a misspelled one ends in a traceback.
ZOO_ENTRY_KEYS = frozenset({"n_envs", "n_timesteps", "policy", "env_kwargs", "normalize", "monitor_kwargs",
                            "frame_stack", "env_wrapper", "vec_env_wrapper", "callback", "noise_type", "noise_std"})


def _train_options(args: Sequence[str]) -> argparse.Namespace:
    """The rl-zoo3 ``train`` options this launcher checks (the rest goes to rl-zoo3 as given)."""
    p = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    p.add_argument("--algo", default="ppo")
    p.add_argument("--env", default="CartPole-v1")
    p.add_argument("-conf", "--conf-file", default=None)
    p.add_argument("-params", "--hyperparams", nargs="+", default=None)
    return p.parse_known_args(list(args))[0]


def _unknown_keys(keys: Sequence[str], known: set[str], where: str, algo_class: type) -> ValueError:
    """The error for ``keys`` (each with its nearest known key, when one is close)."""
    named = []
    for key in keys:
        close = difflib.get_close_matches(key, sorted(known), n=1)
        named.append(f"{key!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
    return ValueError(f"{where}: unknown key{'s' if len(keys) > 1 else ''} {', '.join(named)}: neither an rl-zoo3 "
                      f"setting nor an argument of {algo_class.__name__}")


def check_train_recipe(args: Sequence[str], algos: dict[str, type]) -> None:
    """Check the recipe keys of an rl-zoo3 ``train`` command line before rl-zoo3 runs it.

    The entry rl-zoo3 would read (``--env``'s, else ``default``) of a YAML ``--conf-file``,
    and the ``-params key:value`` overrides, may hold only :data:`ZOO_ENTRY_KEYS` and
    constructor arguments of ``--algo``'s class (``algos``: rl-zoo3's ``ALGOS``). Raises
    ``ValueError`` naming the file, the entry and every unknown key. An unknown ``--algo``, a missing
    or non-YAML file are left to rl-zoo3 (it reports them in one line).
    """
    import yaml

    from cpalgo.methods import algorithm_parameters

    opts = _train_options(args)
    algo_class = algos.get(opts.algo)
    if algo_class is None:
        return
    known = set(ZOO_ENTRY_KEYS) | algorithm_parameters(algo_class)
    conf = opts.conf_file
    if conf is not None and conf.endswith((".yml", ".yaml")) and os.path.isfile(conf):
        with open(conf) as fh:
            try:
                doc = yaml.safe_load(fh)
            except yaml.YAMLError as exc:
                raise ValueError(f"{conf}: not valid YAML: {exc}") from None
        if not isinstance(doc, dict):
            raise ValueError(f"{conf}: expected a mapping of env ids to hyperparameters")
        name = opts.env if opts.env in doc else "default" if "default" in doc else None
        if name is None:
            raise ValueError(f"{conf}: no entry for env id {opts.env!r} (and no 'default' entry)")
        entry = doc[name]
        if not isinstance(entry, dict):
            raise ValueError(f"{conf}: {name}: expected a mapping of hyperparameters, got {entry!r}")
        unknown = [str(key) for key in entry if key not in known]
        if unknown:
            raise _unknown_keys(unknown, known, f"{conf}: {name}", algo_class)
    unknown = [key for key in (item.split(":")[0] for item in opts.hyperparams or ()) if key not in known]
    if unknown:
        raise _unknown_keys(unknown, known, "-params", algo_class)


def _enjoy_n_envs(args: list[str]) -> list[str]:
    """rl-zoo3's enjoy treats ``--n-envs 1`` (its default) as one scalar env, but one
    self-play world already has ``max_agents`` env indices: default to 64 slots."""
    for i, a in enumerate(args[:-1]):
        if a == "--n-envs":
            if int(args[i + 1]) == 1:
                raise SystemExit("--n-envs: cpsim/SelfPlay-v0 counts agent slots; use at least max_agents (e.g. 64)")
            return args
    return [*args, "--n-envs", "64"]


def _no_zoo_evaluation(args: list[str]) -> list[str]:
    """rl-zoo3's ``EvalCallback`` cannot evaluate the batched self-play env: it builds its
    env without the recipe's ``env_kwargs`` (another dynamics than the policy's) and saves
    per-slot episode lists of varying length. Training on ``cpsim/SelfPlay-v0`` therefore
    runs with ``--eval-freq -1``; an explicit positive ``--eval-freq`` is a ``ValueError``
    that names the evaluator to use instead."""
    given = False
    for i, a in enumerate(args):
        value = args[i + 1] if a == "--eval-freq" and i + 1 < len(args) else (
            a.split("=", 1)[1] if a.startswith("--eval-freq=") else None)
        if value is None:
            continue
        given = True
        try:
            freq = int(value)
        except ValueError:
            raise ValueError(f"--eval-freq: expected an integer, got {value!r}") from None
        if freq > 0:
            raise ValueError(f"--eval-freq {freq}: rl-zoo3's evaluation callback cannot evaluate "
                             f"{SELFPLAY_ENV_ID} (a batched self-play env); leave it out and evaluate the "
                             "saved model with python -m cpalgo.evaluate")
    return args if given else [*args, "--eval-freq", "-1"]


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in ("train", "enjoy"):
        print("usage: python -m cpalgo.zoo {train,enjoy} [rl-zoo3 arguments]", file=sys.stderr)
        return 2
    command, rest = argv[0], _translate_config_flag(argv[1:])
    register()
    from rl_zoo3.exp_manager import ExperimentManager

    if command == "train":
        import rl_zoo3

        try:
            check_train_recipe(rest, {**rl_zoo3.ALGOS, "counterplay": sys.modules["cpalgo"].CounterPlay})
        except ValueError as exc:
            print(f"python -m cpalgo.zoo train: error: {exc}", file=sys.stderr)
            return 2

    if _uses_selfplay(rest):
        import rl_zoo3.exp_manager

        from cpsim.envs.selfplay import SelfPlayVecNormalize

        ExperimentManager.default_vec_env_cls = make_zoo_vec_env_class(report=command == "enjoy")
        # normalize: statistics of active slots only (rl-zoo3 builds VecNormalize by this name;
        # enjoy unpickles the class it was saved with)
        rl_zoo3.exp_manager.VecNormalize = SelfPlayVecNormalize  # type: ignore[attr-defined]
        if command == "enjoy":
            rest = _enjoy_n_envs(rest)
        else:
            try:
                rest = _no_zoo_evaluation(rest)
            except ValueError as exc:
                print(f"python -m cpalgo.zoo train: error: {exc}", file=sys.stderr)
                return 2
    sys.argv = [f"rl_zoo3.{command}", *rest]
    if command == "train":
        import rl_zoo3.train

        for module in (rl_zoo3.train,):
            module.ALGOS["counterplay"] = sys.modules["cpalgo"].CounterPlay
        rl_zoo3.train.train()
    else:
        import rl_zoo3.enjoy

        rl_zoo3.enjoy.ALGOS["counterplay"] = sys.modules["cpalgo"].CounterPlay
        rl_zoo3.enjoy.enjoy()
    return 0


if __name__ == "__main__":
    # run the copy of this module that gymnasium's entry point imports (cpalgo.zoo), not
    # __main__, so that the carrier class is one and the same
    from cpalgo import zoo as _zoo

    raise SystemExit(_zoo.main())
