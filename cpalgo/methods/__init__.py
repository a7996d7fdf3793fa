"""Post-training methods by name: the registry behind ``counterplay methods`` and grids.

Every method starts from an anchor checkpoint and post-trains it on the same self-play
environment with the same PPO settings (a zoo recipe), and stops at the same budget.

The equal-budget contract (what a method must do to be registered)
------------------------------------------------------------------
* Its algorithm class is an SB3 on-policy algorithm built as
  ``cls(policy, env, seed=..., post_budget=B, device=..., verbose=..., **recipe_kwargs,
  **settings)`` whose every new argument has a default (so ``cls.load`` works); in practice
  a subclass of :class:`cpalgo.CounterPlay` with :class:`cpalgo.methods.base.EqualBudgetMixin`
  first in its bases (``class MyMethod(EqualBudgetMixin, CounterPlay)``).
* ``model.budget`` (:class:`cpalgo.counterplay.budget.Budget`) counts **every agent
  transition the method simulates**, one live agent stepping once: the main rollout
  (``budget.add_main``; CounterPlay's rollout already does it for the learner's slots) and
  anything else it runs (branches, continuations, groups of rollouts: ``budget.add_branch``
  or ``add_main``), rejected or not.
* ``model.learn(B)`` stops at the rollout step where ``model.budget.total >= B``
  (the mixin does this and anneals the learning-rate schedule over ``B``).
* Optional hook ``model.on_anchor_loaded()``: called right after the anchor's weights are
  loaded (freeze a teacher, start an opponent pool, ...).
* Optional ``search_totals`` / other ``*_totals`` dicts of counts: the experiment runner
  stores them with the run.

Registering a method is one line (at import time of the module that defines it)::

    from cpalgo.methods import register
    register("spiced", "PPO + KL to a frozen behaviour-cloning policy (SPICED)",
             "cpalgo.baselines.spiced.spiced:Spiced", group="baseline", label="SPICED")

``algorithm`` may be the class itself or ``"module:Class"`` (imported when first built);
keyword arguments other than the documented ones become constructor settings of that
method (``register("cp-fixed-10", ..., BudgetedCounterPlay, backtrack="fixed",
fixed_depth=10)``). A module whose methods should be known to ``counterplay methods`` and
to grid files without an explicit import is listed in :data:`METHOD_MODULES`.

Groups order the tables: ``baseline`` and ``counterplay`` rows form Table I and the
repair table, ``ablation`` Table II, ``distillation`` Table IV, ``panel`` Table V.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import os
import sys
from typing import Any, Mapping

__all__ = [
    "MethodSpec", "register", "get_method", "method_names", "describe_methods", "build_method",
    "check_settings", "check_values", "check_algorithm_values", "algorithm_parameters", "GROUPS", "METHOD_MODULES",
]

#: Table groups, in table order.
GROUPS: tuple[str, ...] = ("baseline", "counterplay", "ablation", "panel", "distillation")
#: Modules imported before the registry is read (each registers its methods on import).
METHOD_MODULES: list[str] = ["cpalgo.baselines"]  # the six adapted baselines (docs/baselines.md)


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """One registered post-training method.

    Attributes:
        name: registry name (``ppo-continue``), lower case with dashes.
        summary: one line for ``counterplay methods``.
        algorithm: the algorithm class, or ``"module:Class"`` imported on first use.
        settings: constructor settings that make this method (on top of the recipe's).
        group: one of :data:`GROUPS`.
        label: row label in the tables (default: the name).
        components: Table II's columns ``B`` (backtracking), ``C`` (style change), ``S``
            (selection and verification), ``D`` (distillation), as the table prints them.
    """

    name: str
    summary: str
    algorithm: Any
    settings: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    group: str = "baseline"
    label: str = ""
    components: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def resolve(self) -> type:
        """The algorithm class (imports ``"module:Class"``)."""
        algo = self.algorithm
        if isinstance(algo, str):
            module, _, attr = algo.partition(":")
            try:
                algo = getattr(importlib.import_module(module), attr)
            except (ImportError, AttributeError) as exc:
                raise ValueError(f"method {self.name!r}: cannot import its algorithm {self.algorithm!r}: {exc}") from None
        return algo

    @property
    def row_label(self) -> str:
        return self.label or self.name


_REGISTRY: dict[str, MethodSpec] = {}
_LOADED_MODULES: set[str] = set()


def register(name: str, summary: str, algorithm: Any, *, group: str = "baseline", label: str = "",
             components: Mapping[str, str] | None = None, replace: bool = False, **settings: Any) -> MethodSpec:
    """Register a post-training method (see the module docstring); returns its spec.

    Raises ``ValueError`` for an empty or duplicate name (unless ``replace``), a multi-line
    summary or an unknown group.
    """
    if not isinstance(name, str) or not name or name != name.strip().lower() or " " in name:
        raise ValueError(f"name: expected a lower-case name without spaces, got {name!r}")
    if name in _REGISTRY and not replace:
        raise ValueError(f"name: method {name!r} is already registered")
    if not isinstance(summary, str) or not summary.strip() or "\n" in summary:
        raise ValueError(f"summary: expected one non-empty line for method {name!r}")
    if group not in GROUPS:
        raise ValueError(f"group: expected one of {GROUPS}, got {group!r}")
    if not (isinstance(algorithm, type) or (isinstance(algorithm, str) and ":" in algorithm)):
        raise ValueError(f"algorithm: expected a class or 'module:Class' for method {name!r}, got {algorithm!r}")
    spec = MethodSpec(name=name, summary=summary.strip(), algorithm=algorithm, settings=dict(settings),
                      group=group, label=label, components=dict(components or {}))
    _REGISTRY[name] = spec
    return spec


def _load_modules() -> None:
    for module in list(METHOD_MODULES) + [m for m in os.environ.get("COUNTERPLAY_METHOD_MODULES", "").split(",") if m]:
        if module not in _LOADED_MODULES:
            _LOADED_MODULES.add(module)
            importlib.import_module(module)


def method_names() -> list[str]:
    """Registered names, in table order (group, then registration order)."""
    _load_modules()
    return sorted(_REGISTRY, key=lambda n: (GROUPS.index(_REGISTRY[n].group), list(_REGISTRY).index(n)))


def get_method(name: str) -> MethodSpec:
    """The spec of ``name``; ``ValueError`` listing the known names otherwise."""
    _load_modules()
    if name not in _REGISTRY:
        raise ValueError(f"method: unknown method {name!r}; known: {method_names()}")
    return _REGISTRY[name]


def describe_methods() -> str:
    """One line per method: name, group and summary (``counterplay methods``)."""
    names = method_names()
    width = max(len(n) for n in names)
    return "\n".join(f"{n:<{width}}  {_REGISTRY[n].group:<12}  {_REGISTRY[n].summary}" for n in names)


def algorithm_parameters(cls: type) -> set[str]:
    """Constructor argument names of ``cls`` along its MRO (through ``**kwargs``)."""
    names: set[str] = set()
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        params = inspect.signature(init).parameters
        names |= {p for p, v in params.items() if v.kind not in (v.VAR_KEYWORD, v.VAR_POSITIONAL) and p != "self"}
        if not any(v.kind == v.VAR_KEYWORD for v in params.values()):
            break
    return names - {"policy", "env", "_init_setup_model"}


def check_settings(name: str, settings: Mapping[str, Any], argument: str = "settings") -> None:
    """``ValueError`` naming ``argument`` and the key when a setting is not a constructor
    argument of the method's algorithm."""
    spec = get_method(name)
    known = algorithm_parameters(spec.resolve())
    unknown = sorted(set(settings) - known)
    if unknown:
        raise ValueError(f"{argument}: unknown setting {unknown[0]!r} for method {name!r}; accepted: {sorted(known)}")


def check_algorithm_values(cls: type, settings: Mapping[str, Any], policy: str = "MlpLstmPolicy") -> None:
    """``ValueError`` (or ``TypeError`` for an unknown name) when the SB3 algorithm ``cls``
    rejects one of ``settings``, found without an env or a network: ``cls`` is constructed
    with ``env=None`` and no model, which runs its argument checks only. CounterPlay's
    messages start with the setting's name (``rho: must lie in [0, 1], got 7.5``)."""
    cls(policy, None, _init_setup_model=False, **settings)


def check_values(name: str, settings: Mapping[str, Any], policy: str = "MlpLstmPolicy") -> None:
    """:func:`check_algorithm_values` for method ``name`` (its registry settings under
    ``settings``). Check names first with :func:`check_settings`."""
    spec = get_method(name)
    check_algorithm_values(spec.resolve(), {**spec.settings, **settings}, policy)


def build_method(name: str, anchor: str | os.PathLike, env: Any, *, policy: str = "MlpLstmPolicy",
                 algo_kwargs: Mapping[str, Any] | None = None, settings: Mapping[str, Any] | None = None,
                 budget: int | None = None, seed: int = 0, device: str = "cpu", verbose: int = 0) -> Any:
    """Build method ``name`` on ``env``, starting from the ``anchor`` checkpoint's weights.

    Args:
        anchor: SB3 checkpoint; the model gets its network (policy class and
            ``policy_kwargs``, :func:`cpalgo.common.anchor_network.anchor_network`), and a
            ``policy`` / ``algo_kwargs["policy_kwargs"]`` that differ print one warning line.
        env: the self-play VecEnv (e.g. :class:`cpsim.SelfPlayVecEnv`, possibly wrapped).
        algo_kwargs: the recipe's algorithm arguments (PPO settings, policy_kwargs, ...).
        settings: extra settings of this method (override the recipe and the registry's).
        budget: B_post (``post_budget``); ``model.learn(budget)`` trains to it.
    Returns the model, anchor weights loaded and ``on_anchor_loaded`` called.
    Raises ``ValueError`` naming the argument for an unknown method or setting, a missing
    anchor or an anchor that does not fit the network.
    """
    spec = get_method(name)
    cls = spec.resolve()
    kwargs: dict[str, Any] = dict(algo_kwargs or {})
    kwargs.update(spec.settings)
    kwargs.update(settings or {})
    check_settings(name, {k: v for k, v in kwargs.items()}, "settings")
    if budget is not None:
        if int(budget) <= 0:
            raise ValueError(f"budget: must be > 0, got {budget!r}")
        kwargs["post_budget"] = int(budget)
    from cpalgo.recipes import resolve_path

    anchor = resolve_path(anchor)  # zoo/anchor.zip names the shipped file from any folder
    if not os.path.isfile(anchor):
        raise ValueError(f"anchor: no such checkpoint {anchor!r}")
    from cpalgo.common.anchor_network import anchor_network

    policy, kwargs, note = anchor_network(anchor, policy, kwargs, getattr(cls, "policy_aliases", {}))
    if note is not None:
        print(f"warning: {note}", file=sys.stderr)
    model = cls(policy, env, seed=seed, device=device, verbose=verbose, **kwargs)
    try:
        model.set_parameters(anchor, exact_match=True, device=device)
    except Exception as exc:  # noqa: BLE001 - reported with the file name
        raise ValueError(f"anchor: {anchor} does not fit the network of method {name!r} ({exc})") from None
    hook = getattr(model, "on_anchor_loaded", None)
    if callable(hook):
        hook()
    return model


# ----------------------------------------------------------------------------- built-in methods
def _register_builtins() -> None:
    base = "cpalgo.methods.base:BudgetedCounterPlay"
    ppo = "cpalgo.methods.ppo"
    distill = "cpalgo.methods.distill_controls:StyleDistillation"
    no = {"B": "-", "C": "-", "S": "-", "D": "-"}
    full = {"B": "value", "C": "yes", "S": "yes", "D": "yes"}

    register("ppo-continue", "factual self-play PPO from the anchor (inactive slots masked)", base,
             group="baseline", label="PPO-Continue", components=no, counterfactual=False)
    register("ppo-rewind", "PPO that restores failed worlds 8 decisions before the failure and continues there",
             f"{ppo}:RewindPPO", group="baseline", label="PPO-Rewind", components=no)
    register("ppo-opponent", "PPO with 25% of agents driven by earlier checkpoints (the anchor at the start)",
             f"{ppo}:OpponentPPO", group="baseline", label="PPO-Opponent", components=no)
    register("counterplay", "CounterPlay: value-guided backtracking, 5-style search, verification, KL distillation",
             base, group="counterplay", label="CounterPlay", components=full)
    # 70 lies beyond the paper's window (5-60): the 91-step tasks' timeouts are decided in their
    # first seconds (RESULTS.md, "The paper grid")
    for depth in (10, 30, 50, 70):
        beyond = " (beyond the paper)" if depth > 60 else ""
        register(f"cp-fixed-{depth}", f"CounterPlay with roots fixed {depth} decisions before the failure{beyond}",
                 base, group="ablation", label=f"{depth} decisions before failure",
                 components={**full, "B": str(depth)}, backtrack="fixed", fixed_depth=depth)
    register("cp-no-style", "CounterPlay whose retries keep w0 (focal draws independent, co-players shared)",
             base, group="ablation", label="No change in driving style", components={**full, "C": "-"},
             style_change=False)
    register("cp-select-reward", "CounterPlay choosing the retry with the highest own-condition return",
             base, group="ablation", label="Selection by reward", components={**full, "S": "return"},
             selection="return")
    register("cp-no-verify", "CounterPlay without the verification rerun", base, group="ablation",
             label="Without verification", components={**full, "S": "no rerun"}, verify=False)
    register("cp-ppo-recoveries", "CounterPlay with PPO on the accepted recoveries instead of the KL",
             base, group="ablation", label="PPO on recovery trajectories", components={**full, "D": "-"},
             distill="ppo")
    for style, label in (("cautious", "Cautious"), ("cautious-normal", "Cautious-normal midpoint"),
                         ("normal", "Normal"), ("normal-aggressive", "Normal-aggressive midpoint"),
                         ("aggressive", "Aggressive")):
        register(f"cp-only-{style}", f"CounterPlay searching 5 retries of the {style} style only "
                 "(focal draws independent, co-players shared)", base, group="panel", label=label,
                 panel=(style,) * 5, shared_randomness=False)
    register("distill-aggressive", "PPO + KL to the frozen anchor's aggressive probabilities on the main rollouts",
             distill, group="distillation", label="Aggressive distillation", teacher_style="aggressive")
    register("distill-cautious", "PPO + KL to the frozen anchor's cautious probabilities on the main rollouts",
             distill, group="distillation", label="Cautious distillation", teacher_style="cautious")


_register_builtins()
