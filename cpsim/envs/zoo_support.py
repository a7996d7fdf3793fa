"""Default rl-zoo3 hyperparameters for ``cpsim/*`` environments.

rl-zoo3 looks hyperparameters up by environment id in its own YAML files, which know
nothing about ``cpsim/Drive-v0``, so ``python -m rl_zoo3.train --algo ppo --env
cpsim/Drive-v0 --gym-packages cpsim`` would stop with "Hyperparameters not found".
``import cpsim`` calls :func:`install_if_zoo_loaded`: when rl-zoo3's experiment manager
is already imported (i.e. we are being loaded through ``--gym-packages``), it makes the
manager read this package's YAML (``zoo_hyperparams/<algo>.yml``) for ``cpsim/`` ids
whenever no ``--conf-file`` was given and the zoo's own file has no entry. An explicit
``--conf-file`` always wins. Nothing is patched when rl-zoo3 is not loaded.
"""

from __future__ import annotations

import functools
import importlib.resources
import os
import sys
from typing import Any

#: The YAML files, inside the package (read through importlib.resources; a file path for
#: every ordinary install, which is what rl-zoo3's ``--conf-file`` takes).
HYPERPARAMS_DIR = str(importlib.resources.files("cpsim.envs") / "zoo_hyperparams")
ENV_PREFIX = "cpsim/"


def hyperparams_file(algo: str) -> str | None:
    """Path of this package's YAML for ``algo`` (rl-zoo3 name, e.g. "ppo"), or None."""
    res = importlib.resources.files("cpsim.envs") / "zoo_hyperparams" / f"{algo}.yml"
    return str(res) if res.is_file() else None


def install(exp_manager_cls: Any) -> None:
    """Wrap ``ExperimentManager.read_hyperparameters`` (idempotent)."""
    original = exp_manager_cls.read_hyperparameters
    if getattr(original, "_cpsim_defaults", False):
        return

    @functools.wraps(original)
    def read_hyperparameters(self: Any) -> Any:
        gym_id = getattr(getattr(self, "env_name", None), "gym_id", "")
        ours = hyperparams_file(self.algo) if str(gym_id).startswith(ENV_PREFIX) else None
        if ours is not None and _is_zoo_default(self.config, self.algo) and not _zoo_has(self.config, gym_id):
            self.config = ours
        return original(self)

    read_hyperparameters._cpsim_defaults = True  # type: ignore[attr-defined]
    exp_manager_cls.read_hyperparameters = read_hyperparameters


def zoo_default_file(algo: str) -> str | None:
    """rl-zoo3's own hyperparameter file for ``algo`` (found without importing rl-zoo3)."""
    import importlib.util

    spec = importlib.util.find_spec("rl_zoo3")
    if spec is None or spec.origin is None:
        return None
    return os.path.join(os.path.dirname(spec.origin), "hyperparams", f"{algo}.yml")


def _is_zoo_default(config: str, algo: str) -> bool:
    default = zoo_default_file(algo)
    return default is not None and os.path.abspath(str(config)) == os.path.abspath(default)


def _zoo_has(config: str, gym_id: str) -> bool:
    import yaml

    try:
        with open(config) as f:
            return gym_id in (yaml.safe_load(f) or {})
    except OSError:
        return False


def install_if_zoo_loaded() -> bool:
    """Install the defaults when rl-zoo3's experiment manager is imported; returns whether it was."""
    mod = sys.modules.get("rl_zoo3.exp_manager")
    if mod is None or not hasattr(mod, "ExperimentManager"):
        return False
    install(mod.ExperimentManager)
    return True


__all__ = ["install", "install_if_zoo_loaded", "hyperparams_file", "zoo_default_file", "HYPERPARAMS_DIR"]
