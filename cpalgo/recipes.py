"""Read the rl-zoo3 style YAML recipes in ``zoo/`` without rl-zoo3.

The same file drives ``python -m cpalgo.zoo train`` (through rl-zoo3) and the
``counterplay`` command (directly), so the anchor and the post-training runs have one
source of truth for their hyperparameters.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
from pathlib import Path
from typing import Any

import yaml

#: The Gymnasium id under which the batched self-play env is known to rl-zoo3.
SELFPLAY_ENV_ID = "cpsim/SelfPlay-v0"
ZOO_DIR = Path(__file__).resolve().parent.parent / "zoo"

# Keys of a zoo entry that are not constructor arguments of the algorithm.
_ZOO_ONLY = {"n_envs", "n_timesteps", "env_kwargs", "vec_env_wrapper", "env_wrapper", "normalize",
             "normalize_kwargs", "callback", "frame_stack", "monitor_kwargs", "policy"}


@dataclasses.dataclass(frozen=True)
class Recipe:
    """One zoo entry, split into what builds the env and what builds the algorithm.

    Attributes:
        path: the YAML file.
        policy: policy name (e.g. "MlpLstmPolicy").
        n_envs: agent slots (worlds x max_agents).
        n_timesteps: training length in agent transitions.
        env_kwargs: keyword arguments of :class:`cpsim.SelfPlayVecEnv` (besides num_worlds).
        algo_kwargs: keyword arguments of the algorithm constructor (policy_kwargs evaluated).
    """

    path: str
    policy: str
    n_envs: int
    n_timesteps: int
    env_kwargs: dict[str, Any]
    algo_kwargs: dict[str, Any]

    @property
    def num_worlds(self) -> int:
        max_agents = int(self.env_kwargs.get("max_agents", 16))
        return max(1, -(-self.n_envs // max_agents))


def _eval_policy_kwargs(value: Any, path: str) -> dict[str, Any]:
    """rl-zoo3 writes policy_kwargs as a Python expression string; evaluate it safely-ish
    (builtins off, only ``dict`` and ``torch.nn`` in scope)."""
    if isinstance(value, dict):
        return dict(value)
    import torch.nn as nn

    try:
        out = eval(str(value), {"__builtins__": {}}, {"dict": dict, "nn": nn})  # noqa: S307
    except Exception as exc:  # the file is user input: say where it is wrong
        raise ValueError(f"{path}: policy_kwargs: cannot evaluate {value!r}: {exc}") from None
    if not isinstance(out, dict):
        raise ValueError(f"{path}: policy_kwargs: expected a dict, got {type(out).__name__}")
    return out


def load_recipe(path: str | os.PathLike, env_id: str = SELFPLAY_ENV_ID) -> Recipe:
    """Parse the ``env_id`` entry of a zoo YAML file into a :class:`Recipe`.

    Raises ``ValueError`` naming the file and key when the file or entry is malformed.
    """
    path = str(path)
    if not os.path.isfile(path):
        raise ValueError(f"config: no such file {path!r}")
    with open(path) as fh:
        try:
            doc = yaml.safe_load(fh)
        except yaml.YAMLError as exc:
            raise ValueError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(doc, dict) or env_id not in doc:
        raise ValueError(f"{path}: no entry for env id {env_id!r}")
    entry = dict(doc[env_id])
    for key in ("policy", "n_envs", "n_timesteps"):
        if key not in entry:
            raise ValueError(f"{path}: {env_id}: missing key {key!r}")
    algo_kwargs = {k: v for k, v in entry.items() if k not in _ZOO_ONLY}
    if "policy_kwargs" in algo_kwargs:
        algo_kwargs["policy_kwargs"] = _eval_policy_kwargs(algo_kwargs["policy_kwargs"], path)
    if "window" in algo_kwargs:
        algo_kwargs["window"] = tuple(algo_kwargs["window"])
    if "panel" in algo_kwargs:
        algo_kwargs["panel"] = tuple(algo_kwargs["panel"])
    env_kwargs = entry.get("env_kwargs") or {}
    if isinstance(env_kwargs, str):
        env_kwargs = _eval_policy_kwargs(env_kwargs, path)
    return Recipe(path=path, policy=str(entry["policy"]), n_envs=int(entry["n_envs"]),
                  n_timesteps=int(float(entry["n_timesteps"])), env_kwargs=dict(env_kwargs),
                  algo_kwargs=algo_kwargs)


def import_string(name: str) -> Any:
    """``package.module.Attr`` -> the attribute (for wrapper names in recipes)."""
    module, _, attr = name.rpartition(".")
    return getattr(importlib.import_module(module), attr)
