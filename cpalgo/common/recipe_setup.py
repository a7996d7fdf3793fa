"""What the commands build from a zoo recipe (:class:`cpalgo.recipes.Recipe`), checked
before any work: :func:`check_algorithm_arguments` (the recipe's algorithm and env
arguments against an SB3 algorithm class, nothing built) and :func:`make_env` (the
recipe's self-play env with its ``vec_env_wrapper`` list). Problems are one-line
:class:`~cpalgo.common.checks.UsageError` naming the recipe file and the setting.
:func:`anchor_network` gives the network a post-training run builds: the anchor checkpoint's.
"""

from __future__ import annotations

import json
import os
import zipfile
from typing import Any, Mapping

from cpalgo.common.checks import UsageError
from cpalgo.recipes import Recipe, import_string

__all__ = ["check_algorithm_arguments", "make_env", "anchor_network"]


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



def anchor_network(anchor: str | os.PathLike, policy: Any, algo_kwargs: Mapping[str, Any],
                   aliases: Mapping[str, type]) -> tuple[Any, dict[str, Any], str | None]:
    """The network to build for post-training ``anchor``: the checkpoint's policy class and
    ``policy_kwargs``, whatever the recipe says (its weights load into no other network, and
    settings without weights, such as an activation, would otherwise be the recipe's silently).

    Returns ``(policy, algo_kwargs, note)``: ``policy`` is the checkpoint's class, or the name
    in ``aliases`` (the algorithm's ``policy_aliases``) of that class or of its fused subclass
    (``cpalgo.policies``: the same parameters and outputs, faster), so ``MlpLstmPolicy`` stays
    the fused one; ``algo_kwargs`` a copy with the checkpoint's ``policy_kwargs``; ``note`` one
    line naming what of the given ``policy`` / ``policy_kwargs`` differs (None when nothing
    does). A checkpoint without a readable policy class gives the arguments back unchanged.
    """
    from stable_baselines3.common.save_util import json_to_data

    kwargs = dict(algo_kwargs)
    try:
        with zipfile.ZipFile(anchor) as archive:
            data = json.loads(archive.read("data"))
        saved = json_to_data(json.dumps({k: data[k] for k in ("policy_class", "policy_kwargs") if k in data}))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return policy, kwargs, None
    cls = saved.get("policy_class")
    if not isinstance(cls, type):
        return policy, kwargs, None
    network = dict(saved.get("policy_kwargs") or {})
    chosen: Any = cls
    for name, alias in aliases.items():
        if alias is cls or cls in alias.__bases__:
            chosen = name
            break
    built = aliases[chosen] if isinstance(chosen, str) else chosen
    wanted = aliases.get(policy, policy) if isinstance(policy, str) else policy
    differs = []
    if wanted is not built:
        differs.append(f"policy {getattr(wanted, '__name__', wanted)} (the anchor's: {built.__name__})")
    if kwargs.get("policy_kwargs") is not None and dict(kwargs["policy_kwargs"]) != network:
        differs.append(f"policy_kwargs {dict(kwargs['policy_kwargs'])} (the anchor's: {network})")
    kwargs["policy_kwargs"] = network
    note = None
    if differs:
        note = f"{anchor}: post-training builds the anchor's network, not " + " and ".join(differs)
    return chosen, kwargs, note
