"""What the commands build from a zoo recipe (:class:`cpalgo.recipes.Recipe`), checked
before any work: :func:`check_algorithm_arguments` (the recipe's algorithm and env
arguments against an SB3 algorithm class, nothing built) and :func:`make_env` (the
recipe's self-play env with its ``vec_env_wrapper`` list). Problems are one-line
:class:`~cpalgo.common.checks.UsageError` naming the recipe file and the setting.
"""

from __future__ import annotations

from typing import Any

from cpalgo.common.checks import UsageError
from cpalgo.recipes import Recipe, import_string

__all__ = ["check_algorithm_arguments", "make_env"]


def check_algorithm_arguments(cls: type, recipe: Recipe, argument: str = "--config", **extra: Any) -> None:
    """``UsageError`` naming the recipe file and the setting when ``cls`` (an SB3 algorithm)
    rejects one of the recipe's algorithm arguments (plus ``extra``), or the recipe's
    env_kwargs are not valid :class:`cpsim.SelfPlayVecEnv` arguments. Nothing is built: the
    algorithm is constructed without env and network, which runs its argument checks only."""
    from cpalgo.methods import algorithm_parameters, check_algorithm_values
    from cpsim.envs.selfplay import check_selfplay_arguments

    kwargs = {**recipe.algo_kwargs, **extra}
    unknown = sorted(set(kwargs) - algorithm_parameters(cls))
    if unknown:
        raise UsageError(f"{argument}: {recipe.path}: {unknown[0]!r} is not an argument of {cls.__name__}")
    try:
        check_algorithm_values(cls, kwargs, recipe.policy)
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{argument}: {recipe.path}: {exc}") from None
    try:
        check_selfplay_arguments(**recipe.env_kwargs)
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{argument}: {recipe.path}: env_kwargs: {exc}") from None


def make_env(recipe: Recipe, seed: int, num_worlds: int | None = None, **overrides: Any) -> Any:
    """The recipe's self-play env with its ``vec_env_wrapper`` list (a ``VecMonitor`` first
    when the list has none: it gives SB3 its episode statistics)."""
    from stable_baselines3.common.vec_env import VecMonitor

    import cpsim

    if recipe.zoo_only:
        raise UsageError(f"--config: {sorted(recipe.zoo_only)} in {recipe.path} are applied by rl-zoo3 only "
                         "(python -m cpalgo.zoo train); remove them for the counterplay command")
    if recipe.normalize is not None:
        raise UsageError(f"--config: normalize in {recipe.path}: the counterplay command evaluates and "
                         "post-trains on raw observations (as the shipped anchor was trained); train with "
                         "normalisation through python -m cpalgo.zoo train")
    try:
        wrappers = [(import_string(name), kwargs) for name, kwargs in recipe.vec_env_wrappers]
    except ValueError as exc:
        raise UsageError(f"--config: vec_env_wrapper in {recipe.path}: {exc}") from None
    kwargs = dict(recipe.env_kwargs)
    kwargs.update(overrides)
    kwargs.setdefault("seed", seed)
    env = cpsim.SelfPlayVecEnv(num_worlds=num_worlds or recipe.num_worlds, **kwargs)
    # attribute access (env.sim, env.obs_layout) passes through the wrappers
    if not any(isinstance(cls, type) and issubclass(cls, VecMonitor) for cls, _ in wrappers):
        env = VecMonitor(env)
    for cls, kw in wrappers:
        env = cls(env, **kw)
    return env
