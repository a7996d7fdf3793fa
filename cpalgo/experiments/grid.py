"""Grid files: which post-training runs an experiment holds and how they are evaluated.

A grid file is YAML (``zoo/experiments/paper_small.yml`` is the reference)::

    name: paper_small
    anchor: zoo/anchor.zip              # checkpoint every method starts from
    recipe: zoo/counterplay_selfplay.yml   # PPO settings, network and env shared by every method
    budget: 150000                      # B_post of every run (live agent transitions)
    seeds: [0, 1, 2]
    methods: all                        # or a list of registry names (counterplay methods)
    order: seeds                        # start every method's seed 0 first; methods: a method's seeds together
    overrides: {learning_rate: cosine(3e-5)}   # algorithm arguments over the recipe's (all methods)
    env: {num_scenarios: 192}           # SelfPlayVecEnv arguments over the recipe's env_kwargs
    worlds: 32                          # training worlds (default: the recipe's n_envs / max_agents)
    method_settings: {ppo-opponent: {opponent_fraction: 0.25}}
    checkpoint_every: 2                 # generations between resumable checkpoints
    torch_threads: 1                    # torch threads of each run
    device: cpu
    resources: {num_cpus: 1, num_gpus: 0}     # what each Ray task declares
    evaluation:
      tasks: 50                         # per split
      splits: [interactive, random]
      regimes: all                      # BehaviorBench's eight, or a list
      deployments: {normal: all, halfway: [anchor, ppo-continue, counterplay]}
      pool: procedural                  # or a folder of WOMD files
      seed: 0                           # task set; a list ([0, 1]) evaluates every run on each
      traffic_policy: null              # co-player checkpoint (default: the anchor)
      ppo_policy: null                  # selfplay regime's PPO co-player (default: the shipped one of the dynamics)
      coplayers: vehicles               # who follows the regime: vehicles (BehaviorBench) or controllable
      max_worlds: 256

Several task sets (``evaluation.seed: [0, 1]``, distinct whole numbers) evaluate every run
and the anchor on each set (procedural pools only): the tables pool the sets, ``results.csv``
has a row per set (:mod:`cpalgo.experiments.tables`). The first set is the folder's own: a
resumed folder keeps it first, and more sets may be added later (see
:mod:`cpalgo.experiments.runner`).

Every key is checked before anything runs: an unknown key, an unknown method, a budget
<= 0, a missing anchor or recipe, an unknown deployment condition or regime, a setting a
method does not take, each raise :class:`GridError` (a ``ValueError``) whose one-line
message starts with the file and names the key.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.resources
import json
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import yaml

from cpalgo.recipes import DEFAULT_POST_CONFIG, load_recipe

__all__ = ["GridError", "GridConfig", "EvalSettings", "RunSpec", "load_grid", "resolve_grid_path", "ANCHOR"]

#: Name of the anchor's pseudo-method (its evaluations, the reference of every table).
ANCHOR = "anchor"
_TOP_KEYS = ("name", "anchor", "recipe", "budget", "seeds", "methods", "overrides", "env", "worlds",
             "method_settings", "checkpoint_every", "torch_threads", "device", "resources", "evaluation",
             "description", "order")
#: How a grid queues its runs: ``seeds`` (every method's first seed, then the next seed) or
#: ``methods`` (every seed of the first listed method, then the next method), so a long grid
#: whose most wanted methods come first has their seeds complete early.
RUN_ORDERS = ("seeds", "methods")
_EVAL_KEYS = ("tasks", "splits", "regimes", "deployments", "pool", "pool_size", "seed", "traffic_policy",
              "bc_policy", "ppo_policy", "coplayers", "max_worlds", "max_agents", "sim_config")
_RESOURCE_KEYS = ("num_cpus", "num_gpus", "memory")


class GridError(ValueError):
    """A grid file that cannot run; the message is one line naming the file and the key."""


def resolve_grid_path(path: str | os.PathLike) -> str:
    """``path`` when it exists; ``zoo/...`` -> the file shipped in ``cpalgo/shipped/...``
    (so ``zoo/experiments/paper_small.yml`` works after a plain ``pip install``)."""
    if os.path.exists(path):
        return str(path)
    parts = Path(path).parts
    if len(parts) >= 2 and parts[0] == "zoo":
        res = importlib.resources.files("cpalgo") / "shipped"
        for part in parts[1:]:
            res = res / part
        if res.is_file():
            from cpalgo.recipes import resolve_path

            if len(parts) == 2:
                return resolve_path(path)
            return str(res)  # package data of an ordinary (unzipped) install
    return str(path)


@dataclasses.dataclass(frozen=True)
class EvalSettings:
    """How every run (and the anchor) is evaluated: the evaluator's tasks, regimes and
    deployment conditions (see :mod:`cpalgo.evaluate.runner`).

    Attributes:
        tasks: tasks per split (Interactive-N, Random-N).
        splits: ``interactive`` and/or ``random``.
        regimes: traffic regimes (canonical names).
        deployments: deployment condition -> the methods evaluated under it (``anchor``
            included). Profile names (``normal``, ``halfway``, ``aggressive``, ...).
        pool, pool_size, seed: the evaluation pool (:func:`cpalgo.evaluate.make_tasks`);
            ``seed`` is one task set (an int) or several (a tuple of distinct ints, each run
            evaluated on every one; :attr:`task_sets`).
        traffic_policy, bc_policy: co-player checkpoints (None: the anchor; the shipped BC model).
        ppo_policy: the ``selfplay`` regime's PPO co-player checkpoint (None: the evaluator's
            default, the shipped one of the evaluation's dynamics when there is one, else the
            traffic policy under p_train conditions, with a warning).
        coplayers: who follows the regime (``EvalConfig.coplayers``): ``vehicles`` (every
            vehicle present at t0, BehaviorBench) or ``controllable`` (the earlier rule).
        max_worlds, max_agents: simulator size of the evaluator.
        sim_config: SimConfig overrides of the evaluator (must give the training layout; its
            dynamics default to the anchor's, read from its action set, and must agree with it).
    """

    tasks: int = 50
    splits: tuple[str, ...] = ("interactive", "random")
    regimes: tuple[str, ...] = ()
    deployments: Mapping[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    pool: str = "procedural"
    pool_size: int | None = None
    seed: int | tuple[int, ...] = 0
    traffic_policy: str | None = None
    bc_policy: str | None = None
    ppo_policy: str | None = None
    coplayers: str = "vehicles"
    max_worlds: int = 256
    max_agents: int | None = None
    sim_config: Mapping[str, Any] | None = None

    @property
    def task_sets(self) -> tuple[int, ...]:
        """The task sets (pool seeds) every run is evaluated on, the folder's own first."""
        return tuple(int(s) for s in self.seed) if isinstance(self.seed, (tuple, list)) else (int(self.seed),)

    @property
    def split_arg(self) -> str:
        return "both" if set(self.splits) == {"interactive", "random"} else self.splits[0]

    def deployments_of(self, method: str) -> tuple[str, ...]:
        """Deployment conditions ``method`` is evaluated under, in grid order."""
        return tuple(d for d, methods in self.deployments.items() if method in methods)


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One post-training run of a grid (or the anchor's evaluations: ``method == ANCHOR``)."""

    method: str
    seed: int | None

    @property
    def key(self) -> str:
        return ANCHOR if self.method == ANCHOR else f"{self.method}/seed{self.seed}"

    def __str__(self) -> str:
        return self.key


@dataclasses.dataclass(frozen=True)
class GridConfig:
    """A validated grid (see the module docstring for the keys)."""

    path: str
    name: str
    anchor: str
    recipe: str
    budget: int
    seeds: tuple[int, ...]
    methods: tuple[str, ...]
    overrides: Mapping[str, Any]
    env: Mapping[str, Any]
    worlds: int | None
    method_settings: Mapping[str, Mapping[str, Any]]
    evaluation: EvalSettings
    checkpoint_every: int = 2
    torch_threads: int = 1
    device: str = "cpu"
    resources: Mapping[str, float] = dataclasses.field(default_factory=lambda: {"num_cpus": 1, "num_gpus": 0})
    description: str = ""
    order: str = "seeds"

    def runs(self) -> list[RunSpec]:
        """The anchor's evaluations, then every (method, seed), in :attr:`order`: seeds
        outermost (``seeds``) or methods outermost (``methods``), each in the file's order."""
        if self.order == "methods":
            pairs = [(m, s) for m in self.methods for s in self.seeds]
        else:
            pairs = [(m, s) for s in self.seeds for m in self.methods]
        return [RunSpec(ANCHOR, None)] + [RunSpec(m, s) for m, s in pairs]

    def settings_of(self, method: str) -> dict[str, Any]:
        """Algorithm arguments of ``method``'s runs on top of the recipe's: the grid's
        overrides, then its ``method_settings`` (the registry's own settings come first)."""
        return {**dict(self.overrides), **dict(self.method_settings.get(method, {}))}

    def run_fingerprint(self) -> dict[str, Any]:
        """What a finished run depends on (a folder of another grid must not be resumed)."""
        anchor = Path(self.anchor)
        return {
            "anchor": str(anchor.resolve()), "anchor_bytes": anchor.stat().st_size,
            "anchor_weights_sha1": _weights_sha1(anchor),
            "recipe_sha1": hashlib.sha1(Path(self.recipe).read_bytes()).hexdigest(),
            "budget": self.budget, "overrides": _jsonable(self.overrides), "env": _jsonable(self.env),
            "worlds": self.worlds, "method_settings": _jsonable(self.method_settings),
            # coplayers: controllable was the only rule before the setting existed, and no
            # ppo_policy the only choice before that one; leaving them out keeps those grids'
            # folders resumable. seed: the first task set only, whose files carry no task-set
            # name (runs.eval_path), so that more task sets may be added to a folder later
            "evaluation": _jsonable({k: (self.evaluation.task_sets[0] if k == "seed" else v)
                                     for k, v in dataclasses.asdict(self.evaluation).items()
                                     if k != "deployments" and not (k == "coplayers" and v == "controllable")
                                     and not (k == "ppo_policy" and v is None)}),
        }

    def as_dict(self) -> dict[str, Any]:
        return _jsonable(dataclasses.asdict(self))


def _weights_sha1(path: Path) -> str:
    """SHA-1 of a checkpoint's weights (its ``policy.pth``; the whole file when it has none):
    another anchor at the same path must not resume this grid's runs, a re-saved copy may."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            return hashlib.sha1(archive.read("policy.pth")).hexdigest()
    except (KeyError, zipfile.BadZipFile, OSError):
        return hashlib.sha1(path.read_bytes()).hexdigest()


def _jsonable(x: Any) -> Any:
    return json.loads(json.dumps(x, default=lambda o: list(o) if isinstance(o, (tuple, set)) else str(o)))


# ----------------------------------------------------------------------------- parsing
def _fail(where: str, key: str, message: str) -> GridError:
    return GridError(f"{where}: {key}: {message}")


def _whole(value: Any, where: str, key: str, minimum: int) -> int:
    if isinstance(value, bool):
        raise _fail(where, key, f"expected a whole number, got {value!r}")
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise _fail(where, key, f"expected a whole number, got {value!r}") from None
    if not f.is_integer():
        raise _fail(where, key, f"expected a whole number, got {value!r}")
    if f < minimum:
        raise _fail(where, key, f"must be >= {minimum}, got {value!r}" if minimum != 1 else f"must be > 0, got {value!r}")
    return int(f)


def _task_sets(value: Any, where: str, key: str) -> int | tuple[int, ...]:
    """``evaluation.seed``: one task set (a whole number) or a list of distinct ones (a list
    of one is that set alone)."""
    if isinstance(value, Sequence) and not isinstance(value, str):
        if not value:
            raise _fail(where, key, f"expected a whole number or a non-empty list of distinct whole numbers, "
                        f"got {value!r}")
        sets = tuple(_whole(v, where, key, 0) for v in value)
        if len(set(sets)) != len(sets):
            raise _fail(where, key, f"lists a task set twice: {list(value)!r}")
        return sets[0] if len(sets) == 1 else sets
    if isinstance(value, Mapping):
        raise _fail(where, key, f"expected a whole number or a non-empty list of distinct whole numbers, "
                    f"got {value!r}")
    return _whole(value, where, key, 0)


def _mapping(value: Any, where: str, key: str) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise _fail(where, key, f"expected a mapping, got {type(value).__name__}")
    return dict(value)


def _names(value: Any, where: str, key: str) -> list[str]:
    if isinstance(value, str):
        return [value]
    if not isinstance(value, Sequence) or not value:
        raise _fail(where, key, f"expected a name or a non-empty list of names, got {value!r}")
    return [str(v) for v in value]


def _existing(value: Any, where: str, key: str, base: Path, what: str) -> str:
    if not isinstance(value, (str, os.PathLike)) or not str(value):
        raise _fail(where, key, f"expected a path, got {value!r}")
    for candidate in (resolve_grid_path(value), str(base / str(value))):
        if os.path.isfile(candidate):
            return candidate
    raise _fail(where, key, f"no such {what} {str(value)!r}")


def _checkpoint(path: str, where: str, key: str) -> str:
    """An SB3 checkpoint (a zip holding ``policy.pth``), not merely a file that exists."""
    import zipfile

    if not path.endswith(".zip"):
        return path  # other policy kinds (a BC ``.pt``) are checked where they are loaded
    try:
        with zipfile.ZipFile(path) as archive:
            if "policy.pth" in archive.namelist():
                return path
    except (zipfile.BadZipFile, OSError):
        pass
    raise _fail(where, key, f"{path} is not an SB3 checkpoint (a .zip with policy.pth)")


def load_grid(source: str | os.PathLike | Mapping[str, Any], *, base_dir: str | os.PathLike | None = None) -> GridConfig:
    """Read and validate a grid (a YAML path, ``zoo/experiments/...``, or a mapping).

    Relative paths inside the grid are tried as given (and ``zoo/NAME``) first, then
    relative to the grid file's folder (``base_dir`` for a mapping).
    Raises :class:`GridError` naming the file and the key (see the module docstring).
    """
    from cpalgo.evaluate.runner import REGIMES, resolve_regime, resolve_split
    from cpalgo.methods import GROUPS, check_settings, check_values, get_method, method_names  # noqa: F401
    from cpsim.conditions import resolve_condition

    if isinstance(source, Mapping):
        doc, where = dict(source), "grid"
        base = Path(base_dir or ".")
    else:
        path = resolve_grid_path(source)
        where = str(source)
        if not os.path.isfile(path):
            raise GridError(f"{where}: no such grid file")
        try:
            with open(path, encoding="utf-8") as fh:
                doc = yaml.safe_load(fh)
        except yaml.YAMLError as exc:
            raise GridError(f"{where}: not valid YAML: {str(exc).splitlines()[0]}") from None
        base = Path(base_dir) if base_dir is not None else Path(path).parent
        if not isinstance(doc, dict):
            raise GridError(f"{where}: expected a mapping of grid keys, got {type(doc).__name__}")
    unknown = sorted(set(doc) - set(_TOP_KEYS))
    if unknown:
        raise _fail(where, unknown[0], f"unknown key; accepted: {list(_TOP_KEYS)}")
    for key in ("anchor", "budget", "methods"):
        if key not in doc:
            raise _fail(where, key, "missing (required)")

    # methods first: an unknown method is the commonest mistake
    names = _names(doc["methods"], where, "methods")
    known = method_names()
    if names == ["all"]:
        names = known
    for name in names:
        if name == ANCHOR:
            raise _fail(where, "methods", f"{ANCHOR!r} is always evaluated; do not list it")
        if name not in known:
            raise _fail(where, "methods", f"unknown method {name!r}; known: {known}")
    if len(set(names)) != len(names):
        raise _fail(where, "methods", "lists a method twice")
    budget = _whole(doc["budget"], where, "budget", 1)
    anchor = _checkpoint(_existing(doc["anchor"], where, "anchor", base, "checkpoint"), where, "anchor")
    recipe_path = _existing(doc.get("recipe", DEFAULT_POST_CONFIG), where, "recipe", base, "recipe")
    try:
        recipe = load_recipe(recipe_path)
    except ValueError as exc:
        raise _fail(where, "recipe", str(exc)) from None
    seeds_raw = doc.get("seeds", [0])
    if isinstance(seeds_raw, (int, float)) and not isinstance(seeds_raw, bool):
        seeds_raw = [seeds_raw]
    if not isinstance(seeds_raw, Sequence) or isinstance(seeds_raw, str) or not seeds_raw:
        raise _fail(where, "seeds", f"expected a non-empty list of whole numbers, got {seeds_raw!r}")
    seeds = tuple(_whole(s, where, "seeds", 0) for s in seeds_raw)
    if len(set(seeds)) != len(seeds):
        raise _fail(where, "seeds", "lists a seed twice")
    order = str(doc.get("order", "seeds"))
    if order not in RUN_ORDERS:
        raise _fail(where, "order", f"expected one of {list(RUN_ORDERS)}, got {doc.get('order')!r}")

    overrides = _mapping(doc.get("overrides"), where, "overrides")
    from cpalgo.recipes import SCHEDULE_KEYS, parse_schedule

    for key in SCHEDULE_KEYS:
        if key in overrides:
            try:
                overrides[key] = parse_schedule(overrides[key], key, where)
            except ValueError as exc:
                raise _fail(where, f"overrides.{key}", str(exc).split(": ", 1)[-1]) from None
    for key in ("window", "panel"):
        if key in overrides and isinstance(overrides[key], list):
            overrides[key] = tuple(overrides[key])
    env = _mapping(doc.get("env"), where, "env")
    import inspect

    from cpalgo.methods import algorithm_parameters
    from cpsim import SelfPlayVecEnv

    env_params = set(inspect.signature(SelfPlayVecEnv.__init__).parameters) - {"self", "config_overrides", "num_worlds"}
    from cpsim.config import SimConfig

    sim_fields = {f.name for f in dataclasses.fields(SimConfig)}
    for key in env:
        if key not in env_params and key not in sim_fields:
            raise _fail(where, f"env.{key}", "not an argument of cpsim.SelfPlayVecEnv or a SimConfig field")
    worlds = doc.get("worlds")
    worlds = None if worlds is None else _whole(worlds, where, "worlds", 1)

    method_settings_raw = _mapping(doc.get("method_settings"), where, "method_settings")
    method_settings: dict[str, dict[str, Any]] = {}
    for name, settings in method_settings_raw.items():
        if name not in names:
            raise _fail(where, f"method_settings.{name}", "is not one of the grid's methods")
        method_settings[name] = _mapping(settings, where, f"method_settings.{name}")
    def origin(method: str, setting: str) -> str:
        """The grid key that set ``setting`` for ``method`` (its settings, then overrides, then the recipe)."""
        if setting in method_settings.get(method, {}):
            return f"method_settings.{method}.{setting}"
        return f"overrides.{setting}" if setting in overrides else f"recipe ({recipe_path}): {setting}"

    for name in names:
        merged = {**recipe.algo_kwargs, **overrides, **method_settings.get(name, {})}
        params = algorithm_parameters(get_method(name).resolve())
        bad = sorted(set(merged) - params)
        if bad:
            raise _fail(where, origin(name, bad[0]), f"not an argument of method {name!r}'s algorithm")
        for reserved in ("seed", "post_budget", "device", "verbose", "policy", "env"):
            if reserved in method_settings.get(name, {}) or reserved in overrides:
                raise _fail(where, f"overrides.{reserved}", "is set by the grid itself (seeds, budget, device)")
        try:  # values, before any run starts (the algorithm's own checks, no env or network)
            check_values(name, merged, recipe.policy)
        except (TypeError, ValueError) as exc:
            bad_key, _, why = str(exc).partition(": ")
            raise _fail(where, origin(name, bad_key), f"{why or exc} (method {name!r})") from None
    from cpsim.envs.selfplay import check_selfplay_arguments

    try:
        check_selfplay_arguments(**{**recipe.env_kwargs, **env})
    except ValueError as exc:
        bad_key, _, why = str(exc).partition(": ")
        if getattr(exc, "field", None):  # a ScenarioError names its field apart
            bad_key, why = exc.field, exc.reason
        field = bad_key.removeprefix("SimConfig.")
        key = f"env.{field}" if field in env else f"recipe ({recipe_path}): env_kwargs.{field}"
        raise _fail(where, key, why or str(exc)) from None

    checkpoint_every = _whole(doc.get("checkpoint_every", 2), where, "checkpoint_every", 1)
    torch_threads = _whole(doc.get("torch_threads", 1), where, "torch_threads", 1)
    device = str(doc.get("device", "cpu"))
    if device != "cpu" and not device.startswith("cuda"):
        raise _fail(where, "device", f"expected 'cpu' or 'cuda[:n]', got {device!r}")
    resources_raw = _mapping(doc.get("resources"), where, "resources")
    bad = sorted(set(resources_raw) - set(_RESOURCE_KEYS))
    if bad:
        raise _fail(where, f"resources.{bad[0]}", f"unknown key; accepted: {list(_RESOURCE_KEYS)}")
    resources: dict[str, float] = {"num_cpus": 1.0, "num_gpus": 1.0 if device.startswith("cuda") else 0.0}
    for key, value in resources_raw.items():
        try:
            resources[key] = float(value)
        except (TypeError, ValueError):
            raise _fail(where, f"resources.{key}", f"expected a number, got {value!r}") from None
        if resources[key] < 0:
            raise _fail(where, f"resources.{key}", f"must be >= 0, got {value!r}")

    # evaluation
    ev = _mapping(doc.get("evaluation"), where, "evaluation")
    bad = sorted(set(ev) - set(_EVAL_KEYS))
    if bad:
        raise _fail(where, f"evaluation.{bad[0]}", f"unknown key; accepted: {list(_EVAL_KEYS)}")
    tasks = _whole(ev.get("tasks", 50), where, "evaluation.tasks", 1)
    splits_raw = _names(ev.get("splits", ["interactive", "random"]), where, "evaluation.splits")
    splits: list[str] = []
    for s in splits_raw:
        try:
            splits += [x for x in resolve_split(s) if x not in splits]
        except ValueError as exc:
            raise _fail(where, "evaluation.splits", str(exc).split(": ", 1)[-1]) from None
    regimes_raw = ev.get("regimes", "all")
    regimes_list = list(REGIMES) if regimes_raw in ("all", ["all"], None) else _names(regimes_raw, where, "evaluation.regimes")
    try:
        regimes = tuple(dict.fromkeys(resolve_regime(r) for r in regimes_list))
    except ValueError as exc:
        raise _fail(where, "evaluation.regimes", str(exc).split(": ", 1)[-1]) from None
    dep_raw = ev.get("deployments", ["normal"])
    if isinstance(dep_raw, (str, list, tuple)):
        dep_raw = {d: "all" for d in _names(dep_raw, where, "evaluation.deployments")}
    if not isinstance(dep_raw, Mapping) or not dep_raw:
        raise _fail(where, "evaluation.deployments", f"expected a list of conditions or condition -> methods, got {dep_raw!r}")
    deployments: dict[str, tuple[str, ...]] = {}
    for cond, who in dep_raw.items():
        try:
            resolve_condition(str(cond), "condition")
        except ValueError:
            from cpsim.conditions import PROFILE_ALIASES, PROFILES

            raise _fail(where, "evaluation.deployments", f"unknown deployment {cond!r}; accepted: "
                        f"{sorted(PROFILES) + sorted(PROFILE_ALIASES)}") from None
        members = (ANCHOR, *names) if who in ("all", None) else tuple(_names(who, where, f"evaluation.deployments.{cond}"))
        for m in members:
            if m != ANCHOR and m not in names:
                raise _fail(where, f"evaluation.deployments.{cond}", f"{m!r} is not one of the grid's methods")
        deployments[str(cond)] = tuple(dict.fromkeys(members))
    pool = str(ev.get("pool", "procedural"))
    if pool != "procedural":
        pool_path = pool if os.path.isdir(pool) else str(base / pool)
        if not os.path.isdir(pool_path):
            raise _fail(where, "evaluation.pool", f"neither 'procedural' nor a folder: {pool!r}")
        pool = pool_path
    seed = _task_sets(ev.get("seed", 0), where, "evaluation.seed")
    if not isinstance(seed, int) and pool != "procedural" and "interactive" in splits:
        raise _fail(where, "evaluation.seed", "several task sets need pool: procedural (the interactive split "
                    "of a folder is the same for every seed)")
    pool_size = ev.get("pool_size")
    pool_size = None if pool_size is None else _whole(pool_size, where, "evaluation.pool_size", tasks)
    traffic = ev.get("traffic_policy")
    traffic = None if traffic is None else _checkpoint(
        _existing(traffic, where, "evaluation.traffic_policy", base, "checkpoint"), where, "evaluation.traffic_policy")
    bc = ev.get("bc_policy")
    bc = None if bc is None else _existing(bc, where, "evaluation.bc_policy", base, "checkpoint")
    ppo = ev.get("ppo_policy")
    ppo = None if ppo is None else _checkpoint(
        _existing(ppo, where, "evaluation.ppo_policy", base, "checkpoint"), where, "evaluation.ppo_policy")
    max_agents = ev.get("max_agents")
    coplayers = ev.get("coplayers", "vehicles")
    if coplayers not in ("vehicles", "controllable"):
        raise _fail(where, "evaluation.coplayers", f"expected 'vehicles' or 'controllable', got {coplayers!r}")
    sim_config = ev.get("sim_config")
    if sim_config is not None:
        sim_config = _mapping(sim_config, where, "evaluation.sim_config")
        bad = sorted(set(sim_config) - sim_fields)
        if bad:
            raise _fail(where, f"evaluation.sim_config.{bad[0]}", "not a SimConfig field")
        try:
            SimConfig.from_dict(sim_config)
        except ValueError as exc:
            field, _, why = str(exc).partition(": ")
            raise _fail(where, f"evaluation.sim_config.{field.removeprefix('SimConfig.')}", why or str(exc)) from None
    evaluation = EvalSettings(
        tasks=tasks, splits=tuple(splits), regimes=regimes, deployments=deployments, pool=pool,
        pool_size=pool_size, seed=seed,
        traffic_policy=traffic, bc_policy=bc, ppo_policy=ppo, coplayers=coplayers,
        max_worlds=_whole(ev.get("max_worlds", 256), where, "evaluation.max_worlds", 1),
        max_agents=None if max_agents is None else _whole(max_agents, where, "evaluation.max_agents", 1),
        sim_config=sim_config,
    )
    name = str(doc.get("name") or (Path(where).stem if where != "grid" else "grid"))
    return GridConfig(
        path=where, name=name, anchor=anchor, recipe=recipe_path, budget=budget, seeds=seeds,
        methods=tuple(names), overrides=overrides, env=env, worlds=worlds, method_settings=method_settings,
        evaluation=evaluation, checkpoint_every=checkpoint_every, torch_threads=torch_threads, device=device,
        resources=resources, description=str(doc.get("description", "")), order=order,
    )
