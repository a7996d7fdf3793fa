"""The files that ship inside the package, and the rl-zoo3 style YAML recipes among them.

Shipped files (``cpalgo/shipped/``, inside the wheel): the self-play anchor ``anchor.zip``
(with its record ``anchor.json``; trained by ``anchor_selfplay.yml``, post-trained by
``counterplay_selfplay.yml``), the earlier teacher-imitation anchor ``anchor_imitation.zip``
of the jerk dynamics (with ``anchor.yml``, ``anchor_finetune.yml``, ``counterplay.yml``),
the PPO co-players and the behaviour-cloning traffic model ``bc_traffic.pt``.
They are read through :mod:`importlib.resources`, so a plain ``pip install`` (no clone,
no ``-e``) has them. In a clone, ``zoo/`` is a link to that folder; everywhere else the
commands (``counterplay``, ``python -m cpalgo.zoo``, ``python -m cpalgo.evaluate``) read a
path spelled ``zoo/NAME`` that does not exist as the shipped ``NAME``
(:func:`resolve_path`), so the README's commands work from any folder.

The same recipe drives ``python -m cpalgo.zoo train`` (through rl-zoo3) and the
``counterplay`` command (directly, :func:`load_recipe`), so the anchor and the
post-training runs have one source of truth for their hyperparameters.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import functools
import importlib
import importlib.resources
import math
import os
from pathlib import Path
from typing import Any

import yaml

#: The Gymnasium id under which the batched self-play env is known to rl-zoo3.
SELFPLAY_ENV_ID = "cpsim/SelfPlay-v0"
#: How the README and the repository spell the folder of shipped files.
ZOO_PREFIX = "zoo"
#: The anchor commands post-train by default, and its post-training recipe (they resolve to
#: the shipped files from any folder).
DEFAULT_ANCHOR = "zoo/anchor.zip"
DEFAULT_POST_CONFIG = "zoo/counterplay_selfplay.yml"
#: ``train-anchor``'s recipes: a resumable self-play run (``--run-dir``) from scratch on
#: BehaviorBench's recipe (the shipped anchor's), and the one-checkpoint teacher-imitation path.
DEFAULT_SELFPLAY_CONFIG = "zoo/anchor_selfplay.yml"
DEFAULT_ANCHOR_CONFIG = "zoo/anchor.yml"
_SHIPPED = importlib.resources.files("cpalgo") / "shipped"
# files extracted from a zipped install stay on disk until the process ends
_EXTRACTED = contextlib.ExitStack()
atexit.register(_EXTRACTED.close)


def shipped_names() -> list[str]:
    """The shipped files, as paths relative to the shipped folder (``anchor.zip``,
    ``counterplay.yml``, ``experiments/paper_small.yml``, ...)."""
    out: list[str] = []

    def walk(folder: Any, prefix: str) -> None:
        for f in folder.iterdir():
            if f.name.startswith((".", "_")):
                continue
            if f.is_dir():
                walk(f, f"{prefix}{f.name}/")
            elif f.is_file():
                out.append(prefix + f.name)

    walk(_SHIPPED, "")
    return sorted(out)


@functools.lru_cache(maxsize=None)
def shipped_path(name: str) -> Path:
    """A file-system path to the shipped file ``name`` (e.g. ``"anchor.zip"``,
    ``"experiments/paper_small.yml"``).

    Raises ``FileNotFoundError`` listing the shipped files when there is no such file.
    """
    res = _SHIPPED.joinpath(*Path(name).parts)
    if not res.is_file():
        raise FileNotFoundError(f"{name!r} is not a shipped file; shipped: {shipped_names()}")
    return Path(_EXTRACTED.enter_context(importlib.resources.as_file(res)))


def resolve_path(path: str | os.PathLike) -> str:
    """``path`` as given when it exists; else ``zoo/NAME`` (or ``zoo/NAME`` without the
    ``.zip`` SB3 appends; ``NAME`` may be in a sub-folder) -> the shipped file; anything
    else is returned unchanged (the caller reports it missing)."""
    if os.path.exists(path):
        return str(path)
    parts = Path(path).parts
    if len(parts) >= 2 and parts[0] == ZOO_PREFIX:
        names = set(shipped_names())
        rel = "/".join(parts[1:])
        for name in (rel, rel + ".zip"):
            if name in names:
                return str(shipped_path(name))
    return str(path)


#: The folder of the shipped files (``cpalgo/shipped``), e.g. ``ZOO_DIR / "anchor.yml"``.
#: Prefer :func:`shipped_path`, which also works from a zipped install.
ZOO_DIR = Path(str(_SHIPPED))

# Keys of a zoo entry that are not constructor arguments of the algorithm.
_ZOO_ONLY = {"n_envs", "n_timesteps", "env_kwargs", "vec_env_wrapper", "env_wrapper", "normalize",
             "normalize_kwargs", "callback", "frame_stack", "monitor_kwargs", "policy"}
#: rl-zoo3 keys that only rl-zoo3 applies (per-env gym wrappers, callbacks, frame stacking):
#: kept in :attr:`Recipe.zoo_only` so that a command that cannot apply them says so.
ZOO_ONLY_KEYS = ("env_wrapper", "frame_stack", "callback", "monitor_kwargs")


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
        vec_env_wrappers: rl-zoo3's ``vec_env_wrapper``, as ``(dotted class name, kwargs)``
            pairs in the order they wrap the env.
        normalize: rl-zoo3's ``normalize``: None (off) or the ``VecNormalize`` keyword
            arguments (``{}`` for ``normalize: true``).
        zoo_only: the entry's :data:`ZOO_ONLY_KEYS` (what only rl-zoo3 applies).
    """

    path: str
    policy: str
    n_envs: int
    n_timesteps: int
    env_kwargs: dict[str, Any]
    algo_kwargs: dict[str, Any]
    vec_env_wrappers: tuple[tuple[str, dict[str, Any]], ...] = ()
    normalize: dict[str, Any] | None = None
    zoo_only: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def num_worlds(self) -> int:
        max_agents = int(self.env_kwargs.get("max_agents", 16))
        return max(1, -(-self.n_envs // max_agents))


def _eval_policy_kwargs(value: Any, path: str, key: str = "policy_kwargs") -> dict[str, Any]:
    """rl-zoo3 writes policy_kwargs as a Python expression string; evaluate it safely-ish
    (builtins off, only ``dict``, ``torch.nn`` and :data:`cpalgo.encoders.FEATURE_EXTRACTORS`
    in scope)."""
    if isinstance(value, dict):
        return dict(value)
    import torch.nn as nn

    from cpalgo.encoders import FEATURE_EXTRACTORS

    try:
        out = eval(str(value), {"__builtins__": {}},  # noqa: S307
                   {"dict": dict, "nn": nn, **FEATURE_EXTRACTORS})
    except Exception as exc:  # the file is user input: say where it is wrong
        raise ValueError(f"{path}: {key}: cannot evaluate {value!r}: {exc}") from None
    if not isinstance(out, dict):
        raise ValueError(f"{path}: {key}: expected a dict, got {type(out).__name__}")
    return out


def _wrappers(value: Any, path: str) -> tuple[tuple[str, dict[str, Any]], ...]:
    """rl-zoo3's ``vec_env_wrapper``: a class name, a ``{name: kwargs}`` mapping, or a list of either."""
    if value is None:
        return ()
    items = value if isinstance(value, list) else [value]
    out = []
    for item in items:
        if isinstance(item, str):
            out.append((item, {}))
        elif isinstance(item, dict) and len(item) == 1:
            (name, kwargs), = item.items()
            out.append((str(name), dict(kwargs or {})))
        else:
            raise ValueError(f"{path}: vec_env_wrapper: expected a class name or {{name: kwargs}}, got {item!r}")
    return tuple(out)


def _normalize(value: Any, path: str) -> dict[str, Any] | None:
    """rl-zoo3's ``normalize``: a bool, or the VecNormalize kwargs as a mapping or expression string."""
    if value is None or value is False:
        return None
    if value is True:
        return {}
    if isinstance(value, str):
        value = _eval_policy_kwargs(value, path, key="normalize")
    if not isinstance(value, dict):
        raise ValueError(f"{path}: normalize: expected true/false or VecNormalize kwargs, got {value!r}")
    return dict(value)


def load_recipe(path: str | os.PathLike, env_id: str = SELFPLAY_ENV_ID) -> Recipe:
    """Parse the ``env_id`` entry of a zoo YAML file into a :class:`Recipe`.

    ``path`` goes through :func:`resolve_path` (``zoo/counterplay.yml`` works anywhere).
    Raises ``ValueError`` naming the file and key when the file or entry is malformed.
    """
    path = resolve_path(path)
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
    for key in SCHEDULE_KEYS:
        if key in algo_kwargs:
            algo_kwargs[key] = parse_schedule(algo_kwargs[key], key, path)
    env_kwargs = entry.get("env_kwargs") or {}
    if isinstance(env_kwargs, str):
        env_kwargs = _eval_policy_kwargs(env_kwargs, path, key="env_kwargs")
    return Recipe(path=path, policy=str(entry["policy"]), n_envs=int(entry["n_envs"]),
                  n_timesteps=int(float(entry["n_timesteps"])), env_kwargs=dict(env_kwargs),
                  algo_kwargs=algo_kwargs, vec_env_wrappers=_wrappers(entry.get("vec_env_wrapper"), path),
                  normalize=_normalize(entry.get("normalize"), path),
                  zoo_only={k: entry[k] for k in ZOO_ONLY_KEYS if k in entry})


def import_string(name: str) -> Any:
    """``package.module.Attr`` -> the attribute (the wrapper names of a recipe).

    Raises ``ValueError`` naming ``name`` when it does not import.
    """
    module, _, attr = name.rpartition(".")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError, ValueError) as exc:
        raise ValueError(f"cannot import {name!r}: {exc}") from None


# ----------------------------------------------------------------------------- schedules
#: Recipe keys that take a schedule (SB3 calls it with progress_remaining, 1 -> 0).
SCHEDULE_KEYS: tuple[str, ...] = ("learning_rate", "clip_range", "clip_range_vf")
_SCHEDULE_FORMS = ("a number (constant)", "'constant(x)'", "'lin_x' or 'linear(x)' (x * progress)",
                   "'cosine(x)' (x * 0.5 (1 + cos(pi (1 - progress))))")


@dataclasses.dataclass(frozen=True)
class LinearSchedule:
    """``initial * progress_remaining`` (rl-zoo3's ``lin_x``); progress clipped to [0, 1]."""

    initial: float

    def __call__(self, progress_remaining: float) -> float:
        return self.initial * min(max(float(progress_remaining), 0.0), 1.0)


@dataclasses.dataclass(frozen=True)
class CosineSchedule:
    """Cosine annealing from ``initial`` to 0: ``initial * 0.5 * (1 + cos(pi * (1 - p)))``
    with ``p`` = SB3's progress_remaining (1 at the start, 0 at the end), clipped to [0, 1].
    The seed paper's post-training optimiser: ``cosine(3e-5)``."""

    initial: float

    def __call__(self, progress_remaining: float) -> float:
        p = min(max(float(progress_remaining), 0.0), 1.0)
        return self.initial * 0.5 * (1.0 + math.cos(math.pi * (1.0 - p)))


def parse_schedule(value: Any, key: str = "learning_rate", path: str | None = None) -> Any:
    """A recipe's schedule setting -> what SB3 takes: a float (constant) or a callable of
    progress_remaining (:class:`LinearSchedule`, :class:`CosineSchedule`).

    Accepted: a number or numeric string (``3e-4``), ``constant(x)``, ``lin_x`` /
    ``linear(x)``, ``cosine(x)`` (also ``cos_x`` / ``cosine_x``); ``x`` must be a finite
    number > 0. ``clip_range_vf`` also accepts ``null`` (no value clipping). Raises
    ``ValueError`` naming the key (and the file) for anything else.
    """
    where = f"{path}: {key}" if path else key

    def bad(why: str) -> ValueError:
        return ValueError(f"{where}: {why}; accepted: {', '.join(_SCHEDULE_FORMS)}")

    def number(text: Any) -> float:
        try:
            x = float(text)
        except (TypeError, ValueError):
            raise bad(f"cannot read {text!r} as a number") from None
        if not math.isfinite(x) or x <= 0:
            raise bad(f"{text!r} must be a finite number > 0")
        return x

    if value is None and key == "clip_range_vf":
        return None
    if isinstance(value, bool) or value is None:
        raise bad(f"got {value!r}")
    if isinstance(value, (int, float)):
        return number(value)
    if callable(value):
        return value
    if not isinstance(value, str):
        raise bad(f"got {type(value).__name__} {value!r}")
    text = value.strip().lower().replace(" ", "")
    forms = {"constant": float, "const": float, "lin": LinearSchedule, "linear": LinearSchedule,
             "cos": CosineSchedule, "cosine": CosineSchedule}
    for name, make in forms.items():
        for prefix, suffix in ((f"{name}(", ")"), (f"{name}_", "")):
            if text.startswith(prefix) and text.endswith(suffix):
                arg = text[len(prefix):len(text) - len(suffix)]
                return make(number(arg))
    try:
        float(text)
    except ValueError:
        raise bad(f"cannot parse {value!r}") from None
    return number(text)


def zoo_preprocess_schedules(original: Any) -> Any:
    """Wrap rl-zoo3's ``ExperimentManager._preprocess_schedules`` so that ``python -m
    cpalgo.zoo`` reads schedule settings exactly as :func:`load_recipe` does (rl-zoo3 alone
    knows only ``lin_x`` and would read ``cos_x`` as linear)."""
    if getattr(original, "_cpalgo_schedules", False):
        return original

    def preprocess(hyperparams: dict[str, Any]) -> dict[str, Any]:
        ours = {k: parse_schedule(hyperparams[k], k) for k in SCHEDULE_KEYS
                if k in hyperparams and isinstance(hyperparams[k], str)}
        rest = original({k: v for k, v in hyperparams.items() if k not in ours})
        rest.update(ours)
        return rest

    preprocess._cpalgo_schedules = True  # type: ignore[attr-defined]
    return preprocess


def install_zoo_schedules() -> None:
    """Make rl-zoo3's experiment manager parse schedules with :func:`parse_schedule` (idempotent)."""
    from rl_zoo3.exp_manager import ExperimentManager

    ExperimentManager._preprocess_schedules = staticmethod(  # type: ignore[method-assign]
        zoo_preprocess_schedules(ExperimentManager._preprocess_schedules))
