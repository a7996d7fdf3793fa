"""Self-play PPO for the anchor, from scratch, in resumable pieces, with a learning curve.

A run lives in one folder::

    run.json         the run's settings (recipe, seed, budget, segment length, pools, ...)
    checkpoint.zip   the latest checkpoint: weights, optimiser, counters, every RNG state,
                     the curve so far (one file, replaced atomically)
    curve.csv        one row per segment (rewritten from the checkpoint after each save)
    curve.png        ``counterplay curve RUN_DIR``
    commands.txt     every piece's command line, in order

Training is cut into *segments* of ``segment_timesteps`` counted (live) transitions. Each
segment builds a fresh :class:`cpsim.SelfPlayVecEnv` on a newly drawn procedural pool
(``pool_size`` scenes, seeded by the run seed and the segment index; BehaviorBench resamples
its maps the same way) plus the WOMD training scenes, and starts it from a reset; after
the segment the policy is measured on fixed held-out tasks under the aggressive, normal
and cautious profiles and the checkpoint is written. Because a segment depends only on
what the checkpoint holds (parameters, optimiser moments, ``num_timesteps``, the torch /
NumPy / Python RNG states) and on its index, a run resumed from a checkpoint computes
exactly what the uninterrupted run computes, and a killed piece loses at most the
transitions since its last checkpoint. One learning-rate schedule runs over the whole
budget (``CounterPlay(schedule_timesteps=...)``).

Building a segment's env (drawing the procedural pool, then the model's road grids) takes
about a minute on a CPU, and the held-out evaluation half a minute. A worker process (niced,
started once per piece) does both beside the training: it builds the next segment's pool and
model arrays (:func:`cpsim.model.build_model_host`; the same arrays) and evaluates each saved
checkpoint (the evaluation draws no random numbers), so the run computes the same either way.
A checkpoint is written as soon as its segment is trained; its curve row gets the held-out
columns when the worker returns them (before the next checkpoint, or at the end of the piece,
which then rewrites the checkpoint; a resumed piece first evaluates a row that lacks them).

Data-parallel (``workers`` > 1, ``counterplay train-anchor --workers N``): N training
processes (this one is rank 0, the others are spawned; gloo over a file store, one torch
thread each unless ``threads`` says otherwise) step ``num_worlds / N`` worlds each over the
same segment pool, with their own env seeds, and average their gradients before every
optimiser step (:mod:`cpalgo.common.distributed`, :func:`cpalgo.common.ppo_update.run_update`),
each on minibatches of ``batch_size / N`` live transitions: the update's global batch is the
recipe's. Rank 0 starts the parameters (broadcast), runs the worker (the other ranks adopt the
pool and model arrays it prepared), writes the checkpoint, curve and logs and evaluates; the
transition count and the curve's training columns cover every rank. The checkpoint holds
every rank's RNG states; a run resumes with its workers, or with another count set by
``--set workers=N`` (recorded in ``run.json`` like any change; ranks the checkpoint holds no
RNG state for start from :func:`_seed_new_rank`).
"""

from __future__ import annotations

import csv
import dataclasses
import datetime
import functools
import inspect
import json
import os
import random
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

__all__ = ["AnchorRunSettings", "CURVE_COLUMNS", "STYLES", "train_anchor_run", "read_curve", "plot_curve", "curve_table",
           "RUN_FILE", "CHECKPOINT_FILE", "CURVE_FILE", "STOP_FILE"]

RUN_FILE = "run.json"
CHECKPOINT_FILE = "checkpoint.zip"
CURVE_FILE = "curve.csv"
PLOT_FILE = "curve.png"
COMMANDS_FILE = "commands.txt"
#: create this file in the run folder to stop the run cleanly after the current segment
STOP_FILE = "STOP"
STYLES: tuple[str, ...] = ("aggressive", "normal", "cautious")
OUTCOMES: tuple[str, ...] = ("goal", "collision", "offroad", "timeout")
CURVE_COLUMNS: tuple[str, ...] = (
    ("segment", "timesteps", "wall_s", "learning_rate", "explained_variance", "train_episodes")
    + tuple(f"train_{o}" for o in OUTCOMES)
    + tuple(f"{s}_{o}" for s in STYLES for o in OUTCOMES)
    + ("value_failures", "value_falls", "value_change", "normal_entropy")
    + ("approx_kl", "clip_fraction", "entropy", "value_loss")
    + tuple(f"value_falls_{o}" for o in OUTCOMES[1:])
    + tuple(f"{split}_{m}" for split in ("interactive", "random") for m in ("score", "completion", "at_fault",
                                                                           "timeout"))
)
#: tasks per split of the curve's evaluator columns: the designated ego of BehaviorBench-style
#: Interactive and Random tasks (``cpalgo.evaluate.make_tasks``, task set 0), normal deployment,
#: the model itself as normal-profile traffic. The all-agent columns above average over easy
#: agents; a drift into waiting in the interactive tasks shows here first.
EGO_TASKS = 100
#: PPO update statistics averaged over a segment's updates: logger key -> curve column
#: (``entropy`` is the mean policy entropy over the trained decisions, in nats)
UPDATE_STATS: dict[str, str] = {"train/approx_kl": "approx_kl", "train/clip_fraction": "clip_fraction",
                                "train/entropy_loss": "entropy", "train/value_loss": "value_loss"}
#: PPO settings a resumed piece may change (``--set KEY=VALUE``): each value is parsed as the
#: recipe parses it, applied to the loaded model and recorded in ``run.json`` under "changes"
#: with the segment and transition count it applies from; the checkpoints then carry it.
CHANGEABLE: tuple[str, ...] = ("learning_rate", "ent_coef", "vf_coef", "clip_range", "max_grad_norm", "n_epochs",
                                "gamma", "gae_lambda")
#: ``SelfPlayVecEnv`` settings a resumed piece may change, with their parsers: unlike the PPO
#: settings (carried by the checkpoint) they live in ``run.json``'s "changes" only, and every
#: later piece applies them when it builds its envs (:func:`env_changes`).
ENV_CHANGEABLE: tuple[str, ...] = ("timeout_terminal", "eval_task_share")
#: run settings a resumed piece may change: torch threads (the results do not depend on them
#: beyond float rounding; useful when two runs share a machine) and the data-parallel workers
#: (each rank's share of the worlds and minibatch; ranks new to the run seeded by
#: :func:`_seed_new_rank`)
RUN_CHANGEABLE: tuple[str, ...] = ("threads", "workers")
#: seed of the held-out procedural tasks (``cpsim.scenario.eval_pool``), shared with the CLI
HELD_OUT_SEED = 0


@dataclasses.dataclass(frozen=True)
class AnchorRunSettings:
    """What a run is; written to ``run.json`` at the start and read back by every piece.

    Attributes:
        recipe: zoo YAML of the algorithm and env (``zoo/anchor.yml``); its contents are
            copied into ``run.json`` so later edits of the file cannot change a running run.
        seed: seeds the model, the pools and the envs.
        timesteps: the run's budget in counted (live) agent transitions; the schedules run
            over it.
        segment_timesteps: transitions between checkpoints (and curve points, pool draws).
        pool_size: procedural training scenes drawn per segment.
        womd_dir: folder of WOMD scenes added to every segment's pool (None: none).
        eval_tasks: held-out procedural tasks of the curve (``eval_pool(n, 0)``).
        threads: torch intra-op threads (None: torch's choice; 1 per process with workers > 1).
        workers: data-parallel training processes (see the module docstring); must divide
            the recipe's worlds and minibatch size.
    """

    recipe: str
    seed: int = 0
    timesteps: int = 200_000_000
    segment_timesteps: int = 10_000_000
    pool_size: int = 512
    womd_dir: str | None = None
    eval_tasks: int = 200
    threads: int | None = None
    workers: int = 1

    def __post_init__(self) -> None:
        for name in ("seed", "timesteps", "segment_timesteps", "pool_size", "eval_tasks", "workers"):
            v = getattr(self, name)
            low = 0 if name == "seed" else 1
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
                raise ValueError(f"{name}: expected a whole number >= {low}, got {v!r}")
        if self.threads is not None and (not isinstance(self.threads, int) or self.threads < 1):
            raise ValueError(f"threads: expected None or a whole number >= 1, got {self.threads!r}")
        if self.womd_dir is not None and not os.path.isdir(self.womd_dir):
            raise ValueError(f"womd_dir: no such folder {self.womd_dir!r}")

    @classmethod
    def from_dict(cls, doc: dict[str, Any], source: str = RUN_FILE) -> "AnchorRunSettings":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(doc) - known)
        if unknown:
            raise ValueError(f"{source}: unknown settings {unknown}; accepted: {sorted(known)}")
        return cls(**doc)


class _SegmentStats(BaseCallback):
    """Training-episode outcomes, the critic's explained variance over live slots and the PPO
    update statistics (read at each rollout's end, when the logger still holds the previous
    update's values)."""

    def __init__(self) -> None:
        super().__init__()
        self.outcomes = dict.fromkeys(OUTCOMES, 0)
        self.ev: list[float] = []
        self.updates: dict[str, list[float]] = {column: [] for column in UPDATE_STATS.values()}

    def update_means(self) -> dict[str, float]:
        """Each update statistic's mean over the segment (NaN before any update)."""
        return {column: float(np.mean(v)) if v else float("nan") for column, v in self.updates.items()}

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", ()):
            outcome = info.get("outcome")
            if outcome in self.outcomes:
                self.outcomes[outcome] += 1
        return True

    def _on_rollout_end(self) -> None:
        buf = self.model.rollout_buffer
        active = getattr(buf, "active", None)
        mask = np.ones_like(buf.values, bool) if active is None else active.astype(bool)
        values, returns = buf.values[mask], buf.returns[mask]
        var = float(np.var(returns))
        if values.size > 1 and var > 0:
            self.ev.append(1.0 - float(np.var(returns - values)) / var)
        self.read_update(self.model.logger.name_to_value)

    def read_update(self, logged: dict[str, Any]) -> None:
        """Keep the update statistics in ``logged`` (a logger's ``name_to_value``)."""
        for key, column in UPDATE_STATS.items():
            if key in logged:
                value = float(logged[key])
                self.updates[column].append(-value if column == "entropy" else value)


def _rng_state() -> dict[str, Any]:
    return {"torch": th.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def _set_rng_state(state: dict[str, Any]) -> None:
    th.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def _procedural_pool(settings: AnchorRunSettings, segment: int) -> list[Any]:
    from cpsim.scenario import train_pool

    # one seed per (run, segment): pools never repeat across segments or runs of other seeds
    pool_seed = int(np.random.SeedSequence([settings.seed, segment]).generate_state(1)[0])
    return list(train_pool(settings.pool_size, pool_seed))


def _segment_pool(settings: AnchorRunSettings, segment: int, womd: Sequence[Any]) -> list[Any]:
    return _procedural_pool(settings, segment) + list(womd)


def _build_env(recipe: Any, settings: AnchorRunSettings, segment: int, womd: Sequence[Any],
               procedural: Sequence[Any] | None = None, env_overrides: dict[str, Any] | None = None,
               rank: int = 0) -> Any:
    """The segment's env; ``procedural``: its procedural pool when already drawn;
    ``env_overrides``: the run's recorded env changes (:func:`env_changes`) over the recipe's;
    ``rank``: with ``settings.workers`` > 1, whose share of the worlds (its own env seed,
    ``num_worlds / workers`` worlds of the same pool)."""
    from stable_baselines3.common.vec_env import VecMonitor

    from cpsim import SelfPlayVecEnv

    kwargs = {k: v for k, v in recipe.env_kwargs.items() if k not in ("family", "num_scenarios", "womd_dir", "seed")}
    kwargs.update(env_overrides or {})
    entropy = [settings.seed, segment, 1] + ([rank] if settings.workers > 1 else [])
    env_seed = int(np.random.SeedSequence(entropy).generate_state(1)[0])
    pool = (list(procedural) + list(womd)) if procedural is not None else _segment_pool(settings, segment, womd)
    env = SelfPlayVecEnv(scenarios=pool, num_worlds=recipe.num_worlds // settings.workers, seed=env_seed, **kwargs)
    return VecMonitor(env)


_WORKER_WOMD: dict[str, list[Any]] = {}


_WORKER_TASKS: dict[tuple[int, int], list[Any]] = {}


def _evaluate_checkpoint(path: str, recipe_path: str, settings: AnchorRunSettings) -> dict[str, float]:
    """In the worker: the held-out columns of the checkpoint at ``path``."""
    from cpalgo.counterplay.algorithm import CounterPlay
    from cpalgo.recipes import load_recipe

    key = (settings.eval_tasks, HELD_OUT_SEED)
    if key not in _WORKER_TASKS:
        _WORKER_TASKS[key] = _held_out(settings)
    model = CounterPlay.load(path, device="cpu")
    return _evaluate(model, load_recipe(recipe_path), _WORKER_TASKS[key])


def _worker_init() -> None:
    os.nice(10)  # the trainer comes first; the worker fills the cores' idle time
    th.set_num_threads(1)


def _prepare_segment(settings: AnchorRunSettings, segment: int, config: Any) -> tuple[list[Any], Any]:
    """In the worker: segment ``segment``'s procedural pool and its whole pool's
    :class:`cpsim.model.ModelHost` under ``config``."""
    from cpsim.model import build_model_host
    from cpsim.scenario import load_dir

    womd: list[Any] = []
    if settings.womd_dir is not None:
        if settings.womd_dir not in _WORKER_WOMD:
            _WORKER_WOMD[settings.womd_dir] = list(load_dir(settings.womd_dir)[0])
        womd = _WORKER_WOMD[settings.womd_dir]
    procedural = _procedural_pool(settings, segment)
    return procedural, build_model_host(procedural + womd, config)


class _SegmentWorker:
    """One worker process beside the trainer: builds the next segment's pool and model
    arrays, and evaluates saved checkpoints (jobs run in submission order)."""

    def __init__(self, settings: AnchorRunSettings, log: Callable[[str], None]) -> None:
        self.settings = settings
        self.log = log
        self._workers: Any = None
        self._prepared: Any = None
        self._segment = -1
        self._evaluation: Any = None

    def _submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        import multiprocessing

        if self._workers is None:
            self._workers = multiprocessing.get_context("spawn").Pool(1, initializer=_worker_init)
        return self._workers.apply_async(fn, args)

    def prepare(self, segment: int, config: Any) -> None:
        """Start building segment ``segment``'s pool and model arrays under ``config``."""
        self._prepared = self._submit(_prepare_segment, self.settings, segment, config)
        self._segment = segment

    def take(self, segment: int) -> tuple[list[Any], Any] | None:
        """The prepared procedural pool of ``segment`` and its :class:`cpsim.model.ModelHost`
        (already offered to the next Model of that pool), or None when nothing was prepared
        for it or the worker failed."""
        from cpsim.model import offer_model_host

        job, self._prepared = self._prepared, None
        if job is None or self._segment != segment:
            return None
        try:
            procedural, host = job.get()
        except Exception as exc:  # the segment is then built here, as without a worker
            self.log(f"segment {segment}: preparing in the worker failed ({type(exc).__name__}: {exc}); building here")
            return None
        offer_model_host(host)
        return procedural, host

    def evaluate(self, checkpoint: Path, recipe_path: Path) -> None:
        """Start evaluating the checkpoint file (it must stay unchanged until :meth:`evaluation`)."""
        self._evaluation = self._submit(_evaluate_checkpoint, str(checkpoint), str(recipe_path), self.settings)

    def evaluation(self) -> dict[str, float] | None:
        """Wait for the pending evaluation: its columns, or None (none pending, or it failed)."""
        job, self._evaluation = self._evaluation, None
        if job is None:
            return None
        try:
            return job.get()
        except Exception as exc:
            self.log(f"evaluating in the worker failed ({type(exc).__name__}: {exc}); evaluating here")
            return None

    def close(self) -> None:
        if self._workers is not None:
            self._workers.terminate()
            self._workers.join()
            self._workers = None


def _held_out(settings: AnchorRunSettings) -> list[Any]:
    from cpsim.scenario import eval_pool

    return list(eval_pool(settings.eval_tasks, seed=HELD_OUT_SEED))


def _evaluate(model: Any, recipe: Any, tasks: Sequence[Any]) -> dict[str, float]:
    from cpalgo.anchor.critic import value_before_failures
    from cpalgo.anchor.outcomes import selfplay_outcomes

    config = {k: recipe.env_kwargs[k] for k in ("dynamics",) if k in recipe.env_kwargs}
    row: dict[str, float] = {}
    for style in STYLES:
        rates = selfplay_outcomes(model, tasks, condition=style, max_agents=int(recipe.env_kwargs.get("max_agents", 8)),
                                  config=config or None)
        for o in OUTCOMES:
            row[f"{style}_{o}"] = float(getattr(rates, o))
    # does the critic know the task: its value over the 2 s before each failure (normal style)
    trend = value_before_failures(model, tasks, condition="normal",
                                  max_agents=int(recipe.env_kwargs.get("max_agents", 8)), config=config or None)
    row.update(value_failures=trend.failures, value_falls=trend.falls, value_change=trend.mean_change,
               normal_entropy=_first_step_entropy(model, tasks, recipe, config))
    row.update({f"value_falls_{o}": trend.per_outcome[o]["falls"] for o in OUTCOMES[1:]})
    row.update(_ego_columns(model, min(EGO_TASKS, len(tasks))))
    return row


@functools.lru_cache(maxsize=2)
def _ego_tasks(n: int) -> tuple[Any, ...]:
    from cpalgo.evaluate.runner import make_tasks

    return tuple(make_tasks("procedural", "both", n=n, seed=0))


def _ego_columns(model: Any, n: int) -> dict[str, float]:
    """The evaluator's view (:data:`EGO_TASKS`): score, completion, at-fault collision and
    timeout rates of the designated ego per split, the model as its own normal traffic."""
    from cpalgo.evaluate.runner import evaluate

    summary = evaluate(model, list(_ego_tasks(n)), regimes=("normal",), deploy_condition="normal",
                       traffic_policy=model, label="anchor", progress=False).summary()
    out: dict[str, float] = {}
    for split in ("interactive", "random"):
        m = summary[split]["normal"]
        out.update({f"{split}_score": m["score"], f"{split}_completion": m["completion"],
                    f"{split}_at_fault": m["at_fault_collision"], f"{split}_timeout": m["timeout"]})
    return out


def _first_step_entropy(model: Any, tasks: Sequence[Any], recipe: Any, config: dict[str, Any]) -> float:
    """Mean entropy (nats) of the policy's action distribution at the first decision of the
    held-out tasks under the normal profile: a collapse to one action shows here first."""
    from cpsim import SimConfig, Simulator
    from cpsim.conditions import NUM_CONDITION_FIELDS, deployment_condition

    sim_config = SimConfig.from_dict(config or None).replace(goal_criterion="evaluation")
    max_agents = int(recipe.env_kwargs.get("max_agents", 8))
    sim = Simulator(list(tasks), num_worlds=len(tasks), max_agents=max_agents, config=sim_config, seed=0)
    cond = deployment_condition("normal", "condition")
    sim.reset(scenario_index=np.arange(len(tasks)),
              conditions=np.broadcast_to(cond, (len(tasks), max_agents, NUM_CONDITION_FIELDS)))
    live = sim.policy_mask.reshape(-1).cpu().numpy()
    obs = th.as_tensor(sim.obs.reshape(live.size, -1).cpu().numpy()[live])
    lstm = model.policy.lstm_actor
    zeros = th.zeros((lstm.num_layers, obs.shape[0], lstm.hidden_size))
    with th.no_grad():
        dist, _ = model.policy.get_distribution(obs, (zeros, zeros.clone()), th.ones(obs.shape[0]))
        return float(dist.entropy().mean())


def _write_curve(run_dir: Path, rows: Sequence[dict[str, Any]]) -> None:
    from cpsim.atomic import atomic_path

    with atomic_path(run_dir / CURVE_FILE) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(CURVE_COLUMNS))
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k, "") for k in CURVE_COLUMNS})


def read_curve(run_dir: str | os.PathLike) -> list[dict[str, float]]:
    """The rows of a run folder's ``curve.csv`` (numbers as floats)."""
    path = Path(run_dir) / CURVE_FILE
    if not path.is_file():
        raise ValueError(f"run_dir: {str(run_dir)!r} has no {CURVE_FILE} (not a train-anchor run folder?)")
    with open(path, newline="") as fh:
        return [{k: float(v) for k, v in row.items() if v != ""} for row in csv.DictReader(fh)]


def curve_table(rows: Sequence[dict[str, float]], every: int = 1) -> str:
    """A markdown table of curve rows (every ``every``-th segment and the last): transitions,
    training wall time, training and held-out outcome rates (%), entropy and critic EV."""
    picked = [r for i, r in enumerate(rows) if i % every == every - 1 or i == len(rows) - 1]

    def pct(r: dict[str, float], *keys: str) -> str:
        return " / ".join(f"{100 * r[k]:.1f}" if k in r else "-" for k in keys)

    lines = ["| transitions | training wall (s) | train goal / collision / off-road / timeout | held-out goal "
             "aggr / normal / caut | held-out normal collision / off-road / timeout | ego completion / at-fault / "
             "timeout, Interactive | same, Random | first-decision entropy (nats) | critic EV |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in picked:
        entropy = f"{r['normal_entropy']:.2f}" if "normal_entropy" in r else "-"
        lines.append(f"| {r['timesteps'] / 1e6:.1f}M | {r['wall_s']:,.0f} | "
                     f"{pct(r, 'train_goal', 'train_collision', 'train_offroad', 'train_timeout')} | "
                     f"{pct(r, 'aggressive_goal', 'normal_goal', 'cautious_goal')} | "
                     f"{pct(r, 'normal_collision', 'normal_offroad', 'normal_timeout')} | "
                     f"{pct(r, 'interactive_completion', 'interactive_at_fault', 'interactive_timeout')} | "
                     f"{pct(r, 'random_completion', 'random_at_fault', 'random_timeout')} | {entropy} | "
                     f"{r.get('explained_variance', float('nan')):.2f} |")
    return "\n".join(lines)


def curve_rise(rows: Sequence[dict[str, float]], key: str = "normal_goal", share: float = 1 / 3) -> dict[str, float]:
    """How much ``key`` (a held-out rate) rose over the last ``share`` of a run's transitions,
    the plateau test of an anchor run: the least-squares line through the evaluated points
    from ``(1 - share) x`` the last point's transitions on, taken across that span.

    Returns ``start`` and ``end`` (transitions of the span), ``points`` (evaluated rows in it),
    ``rise`` (the line's change over the span, a rate difference) and ``first`` / ``last``
    (the mean rate of the span's first and last quarter of points, at least one each).
    Raises ``ValueError`` when fewer than 3 points fall in the span.
    """
    if not 0.0 < share <= 1.0:
        raise ValueError(f"share: expected a share in (0, 1], got {share!r}")
    evaluated = [r for r in rows if key in r]
    if not evaluated:
        raise ValueError(f"key: no curve row has {key!r}")
    end = evaluated[-1]["timesteps"]
    start = (1.0 - share) * end
    span = [r for r in evaluated if r["timesteps"] >= start * (1 - 1e-9)]  # a point on the boundary is in
    if len(span) < 3:
        raise ValueError(f"curve: {len(span)} evaluated point(s) in the last {share:.0%} of the run; need 3")
    x = np.array([r["timesteps"] for r in span], dtype=np.float64)
    y = np.array([r[key] for r in span], dtype=np.float64)
    slope = np.polyfit(x, y, 1)[0]
    quarter = max(1, len(span) // 4)
    return {"start": float(start), "end": float(end), "points": len(span), "rise": float(slope * (end - start)),
            "first": float(y[:quarter].mean()), "last": float(y[-quarter:].mean())}


def plot_curve(run_dir: str | os.PathLike, out: str | os.PathLike | None = None) -> Path:
    """Draw ``curve.png``: held-out goal rate per style and the normal style's failure
    classes against transitions (wall time on the top axis), and the critic's explained
    variance. Returns the image's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cpsim.atomic import atomic_path

    rows = read_curve(run_dir)
    if not rows:
        raise ValueError(f"run_dir: {str(run_dir)!r}: {CURVE_FILE} has no rows yet")
    x = np.array([r["timesteps"] for r in rows]) / 1e6
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for style, color in zip(STYLES, ("tab:red", "tab:blue", "tab:green")):
        axes[0].plot(x, [100 * r.get(f"{style}_goal", np.nan) for r in rows], marker="o", ms=3, color=color, label=style)
    axes[0].plot(x, [100 * r.get("train_goal", np.nan) for r in rows], ls="--", color="gray", label="training (p_train)")
    for split, ls in (("interactive", ":"), ("random", "-.")):
        if any(f"{split}_completion" in r for r in rows):
            axes[0].plot(x, [100 * r.get(f"{split}_completion", np.nan) for r in rows], ls=ls, marker="^", ms=3,
                         color="black", label=f"ego completion, {split} (normal)")
    axes[0].set(title="goal rate, held-out tasks", xlabel="transitions (M)", ylabel="%")
    axes[0].legend(fontsize=8)
    for o, color in zip(OUTCOMES[1:], ("tab:red", "tab:orange", "tab:purple")):
        axes[1].plot(x, [100 * r.get(f"normal_{o}", np.nan) for r in rows], marker="o", ms=3, color=color, label=o)
    axes[1].set(title="normal style: failures", xlabel="transitions (M)", ylabel="%")
    axes[1].legend(fontsize=8)
    axes[2].plot(x, [r.get("explained_variance", np.nan) for r in rows], marker="o", ms=3,
                 label="explained variance")
    if any("value_falls" in r for r in rows):
        axes[2].plot(x, [r.get("value_falls", np.nan) for r in rows], marker="s", ms=3,
                     label="value falls before failure")
    axes[2].set(title="critic", xlabel="transitions (M)")
    axes[2].legend(fontsize=8)
    top = axes[0].secondary_xaxis("top", functions=(
        lambda v: np.interp(v, x, [r["wall_s"] / 3600 for r in rows]),
        lambda h: np.interp(h, [r["wall_s"] / 3600 for r in rows], x)))
    top.set_xlabel("wall time (h)")
    fig.tight_layout()
    path = Path(out) if out is not None else Path(run_dir) / PLOT_FILE
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def _new_model(recipe: Any, settings: AnchorRunSettings, env: Any, rank: int = 0) -> Any:
    """The run's model. With ``settings.workers`` > 1: minibatches of ``batch_size / workers``
    (the ranks' minibatches together are the recipe's), rank 0's initial parameters on every
    rank, and the other ranks seeded apart (their own action draws and minibatch orders)."""
    from cpalgo.common.distributed import broadcast_parameters
    from cpalgo.counterplay.algorithm import CounterPlay

    kwargs = dict(recipe.algo_kwargs)
    kwargs.pop("schedule_timesteps", None)
    seed = settings.seed
    if settings.workers > 1:
        batch_size = _batch_size(recipe)
        kwargs["batch_size"] = None if batch_size is None else batch_size // settings.workers
        if rank:
            seed = int(np.random.SeedSequence([settings.seed, rank, 2]).generate_state(1)[0])
    model = CounterPlay(recipe.policy, env, counterfactual=False, seed=seed,
                        schedule_timesteps=settings.timesteps, **kwargs)
    if settings.workers > 1:
        broadcast_parameters(model.policy)  # the ranks start from rank 0's parameters
    return model


def _batch_size(recipe: Any) -> int | None:
    """The recipe's minibatch size in live transitions (CounterPlay's default when unset;
    None: the whole rollout)."""
    from cpalgo.counterplay.algorithm import CounterPlay

    default = inspect.signature(CounterPlay.__init__).parameters["batch_size"].default
    value = recipe.algo_kwargs.get("batch_size", default)
    return None if value is None else int(value)


def _check_workers(recipe: Any, workers: int) -> None:
    """``workers`` must divide the recipe's worlds and minibatch size (every rank steps the
    same share, the ranks' minibatches add up to the recipe's). Raises ``ValueError`` naming
    ``--workers``."""
    if workers == 1:
        return
    if recipe.num_worlds % workers:
        raise ValueError(f"--workers: {workers} does not divide the recipe's {recipe.num_worlds} worlds "
                         f"(n_envs {recipe.n_envs} / max_agents); every worker steps the same share")
    batch_size = _batch_size(recipe)
    if batch_size is not None and batch_size % workers:
        raise ValueError(f"--workers: {workers} does not divide the recipe's batch_size {batch_size}; "
                         f"every worker takes batch_size / workers of each minibatch")


def _check_cores(settings: AnchorRunSettings) -> None:
    """Data-parallel ranks must not ask for more torch threads than the machine has cores:
    oversubscribed OpenMP threads spin-wait on each other, and a piece then runs many times
    slower than one process. Raises ``ValueError`` naming ``threads``."""
    if settings.workers == 1 or settings.threads is None:
        return
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if settings.threads * settings.workers > cores:
        raise ValueError(f"threads: {settings.threads} torch threads in each of {settings.workers} workers exceed "
                         f"this machine's {cores} cores; set fewer (--set threads=N, or --threads N for a new run)")


def _recipe_from_run(run_dir: Path) -> Any:
    from cpalgo.recipes import load_recipe

    path = run_dir / "recipe.yml"
    if not path.is_file():
        raise ValueError(f"resume: {run_dir} has no recipe.yml (not a train-anchor run folder?)")
    return load_recipe(path)


def parse_changes(items: Sequence[str]) -> dict[str, Any]:
    """``["ent_coef=0.01", "learning_rate=cosine(3e-3)"]`` -> checked ``{key: value}``.

    Keys must be in :data:`CHANGEABLE`, :data:`ENV_CHANGEABLE` or :data:`RUN_CHANGEABLE`;
    schedules (``learning_rate``, ``clip_range``) take the recipe's forms, ``timeout_terminal``
    true / false, ``eval_task_share`` a share in [0, 1], ``n_epochs``, ``threads`` and ``workers`` a whole
    number >= 1, the rest a number >= 0. Raises ``ValueError`` naming the item.
    """
    from cpalgo.recipes import parse_schedule

    changes: dict[str, Any] = {}
    for item in items:
        key, sep, text = str(item).partition("=")
        key, text = key.strip(), text.strip()
        if not sep or not key or not text:
            raise ValueError(f"set: expected KEY=VALUE, got {item!r}")
        if key not in CHANGEABLE + ENV_CHANGEABLE + RUN_CHANGEABLE:
            raise ValueError(f"set: {key!r} cannot be changed in a resumed run; changeable: "
                             f"{', '.join(CHANGEABLE + ENV_CHANGEABLE + RUN_CHANGEABLE)}")
        if key in ("learning_rate", "clip_range"):
            parse_schedule(text, key)  # raises naming the key
            changes[key] = text
        elif key in ("n_epochs", "threads", "workers"):
            if not text.isdigit() or int(text) < 1:
                raise ValueError(f"set: {key} must be a whole number >= 1, got {text!r}")
            changes[key] = int(text)
        elif key == "timeout_terminal":
            if text.lower() not in ("true", "false"):
                raise ValueError(f"set: timeout_terminal must be true or false, got {text!r}")
            changes[key] = text.lower() == "true"
        else:
            try:
                value = float(text)
            except ValueError:
                raise ValueError(f"set: {key} must be a number, got {text!r}") from None
            unit = key in ("eval_task_share", "gamma", "gae_lambda")
            if not np.isfinite(value) or value < 0 or (unit and value > 1):
                bound = "in [0, 1]" if unit else ">= 0"
                raise ValueError(f"set: {key} must be a finite number {bound}, got {text!r}")
            changes[key] = value
    return changes


def _recorded(doc: dict[str, Any], keys: Sequence[str]) -> dict[str, Any]:
    """The values of ``keys`` recorded in a ``run.json`` document's "changes", later entries
    over earlier ones."""
    merged: dict[str, Any] = {}
    for entry in doc.get("changes", []):
        merged.update({k: v for k, v in entry.get("set", {}).items() if k in keys})
    return merged


def env_changes(doc: dict[str, Any]) -> dict[str, Any]:
    """The :data:`ENV_CHANGEABLE` settings recorded in a ``run.json`` document: what every env
    of the run's next pieces is built with."""
    return _recorded(doc, ENV_CHANGEABLE)


def _run_changes(settings: "AnchorRunSettings", doc: dict[str, Any]) -> "AnchorRunSettings":
    """``settings`` with the :data:`RUN_CHANGEABLE` values recorded in ``doc``'s "changes"."""
    return dataclasses.replace(settings, **_recorded(doc, RUN_CHANGEABLE))


def _apply_changes(model: Any, changes: dict[str, Any]) -> None:
    """Set the parsed ``changes`` on a loaded model (schedules rebuilt as SB3 builds them)."""
    try:
        from stable_baselines3.common.utils import FloatSchedule as get_schedule_fn
    except ImportError:  # stable-baselines3 < 2.7
        from stable_baselines3.common.utils import get_schedule_fn

    from cpalgo.recipes import parse_schedule

    for key, value in changes.items():
        if key in ENV_CHANGEABLE + RUN_CHANGEABLE:
            continue  # applied from run.json where envs are built / the piece starts
        if key == "learning_rate":
            model.learning_rate = parse_schedule(value, key)
            model.lr_schedule = get_schedule_fn(model.learning_rate)
        elif key == "clip_range":
            model.clip_range = get_schedule_fn(parse_schedule(value, key))
        else:
            setattr(model, key, value)
            if key in ("gamma", "gae_lambda"):  # the buffer computes the returns with its own copy
                setattr(model.rollout_buffer, key, value)


def train_anchor_run(run_dir: str | os.PathLike, settings: AnchorRunSettings | None = None, *,
                     resume: bool = False, stop_after_s: float | None = None, command: str | None = None,
                     changes: Sequence[str] = (), worker: bool = True, workers: int | None = None,
                     log: Callable[[str], None] = print) -> Any:
    """Start (``settings`` given) or resume (``resume=True``) the run in ``run_dir``.

    ``changes`` (resume only): ``KEY=VALUE`` items of :data:`CHANGEABLE` PPO settings,
    :data:`ENV_CHANGEABLE` env settings or :data:`RUN_CHANGEABLE` run settings that hold from
    this piece on (recorded in ``run.json``; see :func:`parse_changes`).
    ``worker``: build each next segment's env and evaluate each finished segment in a
    worker process beside the training (same results, less wall time).
    ``workers``: data-parallel training processes; a new run takes ``settings.workers``
    (``workers``, when given, must agree), a resumed run the count it was started with
    (``workers``, when given, must equal it).

    Runs segments until the budget is spent, ``stop_after_s`` seconds of this piece have
    passed (checked after each segment), or a ``STOP`` file appears in the run folder.
    Returns the model (rank 0's). Raises ``ValueError`` naming the folder when it is not a
    run folder (resume) or already holds one (start), naming ``--workers`` when the worker
    count does not divide the recipe's worlds and minibatch or differs from the run's.
    """
    from cpalgo.recipes import load_recipe
    from cpsim.atomic import atomic_path

    run_dir = Path(run_dir)
    parsed = parse_changes(changes)
    if parsed and not resume:
        raise ValueError("set: settings change only in a resumed run (the recipe holds a new run's)")
    if resume:
        if settings is not None:
            raise ValueError("settings: a resumed run reads its settings from run.json; give none")
        if not (run_dir / RUN_FILE).is_file() or not (run_dir / CHECKPOINT_FILE).is_file():
            raise ValueError(f"resume: {str(run_dir)!r} holds no {RUN_FILE} and {CHECKPOINT_FILE}")
        doc = json.loads((run_dir / RUN_FILE).read_text())
        settings = AnchorRunSettings.from_dict(doc["settings"], str(run_dir / RUN_FILE))
        running = _run_changes(settings, doc).workers
        if workers is not None and workers != parsed.get("workers", running):
            # the checkpoint holds one RNG state per rank and each rank's share of the worlds
            raise ValueError(f"--workers: the run in {str(run_dir)!r} runs with {running} worker(s) and "
                             f"resumes with them only, got {workers} (change it with --set workers=N)")
        recipe = _recipe_from_run(run_dir)
    else:
        if settings is None:
            raise ValueError("settings: needed to start a run")
        if workers is not None and workers != settings.workers:
            raise ValueError(f"--workers: {workers} given beside settings.workers={settings.workers}; give one")
        if (run_dir / CHECKPOINT_FILE).exists() or (run_dir / RUN_FILE).exists():
            raise ValueError(f"run_dir: {str(run_dir)!r} already holds a run; resume it with --resume")
        recipe = load_recipe(settings.recipe)
        _check_workers(recipe, settings.workers)  # before anything is written
        _check_cores(settings)
        run_dir.mkdir(parents=True, exist_ok=True)
        with atomic_path(run_dir / "recipe.yml") as tmp:
            Path(tmp).write_text(Path(recipe.path).read_text())
        with atomic_path(run_dir / RUN_FILE) as tmp:
            Path(tmp).write_text(json.dumps({"settings": dataclasses.asdict(settings)}, indent=2) + "\n")
        recipe = load_recipe(run_dir / "recipe.yml")
        doc = {}

    # env and run settings changed in earlier pieces (or this one) hold for every later piece
    later = {"changes": [*doc.get("changes", []), {"set": parsed}]} if parsed else doc
    env_overrides = env_changes(later)
    settings = _run_changes(settings, later)
    _check_workers(recipe, settings.workers)  # a count set now or in an earlier piece
    _check_cores(settings)
    if command:
        with open(run_dir / COMMANDS_FILE, "a") as fh:
            fh.write(command + "\n")
    ranks = _Ranks(settings.workers) if settings.workers > 1 else None
    try:
        if ranks is not None:  # started first: the other ranks load while this one does
            ranks.start(run_dir, settings, resume, parsed, env_overrides)
        model = _piece(run_dir, settings, recipe, resume, parsed, doc, env_overrides, worker, stop_after_s, log)
    except BaseException:
        if ranks is not None:
            ranks.close(failed=True)
        raise
    if ranks is not None:
        ranks.close(failed=False)
    return model


def _piece(run_dir: Path, settings: AnchorRunSettings, recipe: Any, resume: bool, parsed: dict[str, Any],
           doc: dict[str, Any], env_overrides: dict[str, Any], worker: bool, stop_after_s: float | None,
           log: Callable[[str], None]) -> Any:
    """Rank 0's part of :func:`train_anchor_run` (the only rank of a one-worker run): load
    the checkpoint (resume), record ``parsed`` changes in ``run.json``, run the segments."""
    from cpsim.atomic import atomic_path

    womd = _load_womd(settings)
    tasks = _held_out(settings)
    if resume:
        model, state = _load_checkpoint(run_dir, parsed, 0, settings, recipe)
        log(f"resumed {run_dir} at {model.num_timesteps:,} transitions (segment {state['segment']})")
        if parsed:
            doc.setdefault("changes", []).append({"segment": int(state["segment"]),
                                                  "timesteps": int(model.num_timesteps), "set": parsed})
            with atomic_path(run_dir / RUN_FILE) as tmp:
                Path(tmp).write_text(json.dumps(doc, indent=2) + "\n")
            log(f"from segment {state['segment']} on: " + ", ".join(f"{k}={v}" for k, v in parsed.items()))
    else:
        state = {"segment": 0, "wall_s": 0.0, "rows": []}
        model = None
    _set_threads(settings)

    helper = _SegmentWorker(settings, log) if worker else None
    try:
        return _run_segments(run_dir, settings, recipe, model, state, womd, tasks, helper, stop_after_s, log,
                             env_overrides)
    finally:
        if helper is not None:
            helper.close()


def _set_threads(settings: AnchorRunSettings) -> None:
    """torch threads of a training process: ``settings.threads``; data-parallel, 1 when unset
    (the processes share the cores)."""
    threads = settings.threads if settings.threads is not None or settings.workers == 1 else 1
    if threads is not None:
        th.set_num_threads(threads)


def _load_womd(settings: AnchorRunSettings) -> list[Any]:
    if settings.womd_dir is None:
        return []
    from cpsim.scenario import load_dir

    return list(load_dir(settings.womd_dir)[0])


def _load_checkpoint(run_dir: Path, parsed: dict[str, Any], rank: int, settings: AnchorRunSettings,
                     recipe: Any) -> tuple[Any, dict[str, Any]]:
    """The run's model and resume state from its checkpoint, ``rank``'s RNG states restored
    and the ``parsed`` changes applied. When ``parsed`` changes the worker count, the model
    takes its rank's share of the worlds and minibatch, and a rank the checkpoint holds no
    RNG state for starts from :func:`_seed_new_rank`."""
    from cpalgo.counterplay.algorithm import CounterPlay

    model = CounterPlay.load(run_dir / CHECKPOINT_FILE, device="cpu")
    state = dict(model.resume_state)
    rank_rng = state.get("rank_rng") or [state["rng"]]   # a one-worker run's checkpoint holds one
    if rank < len(rank_rng):
        _set_rng_state(rank_rng[rank])
    elif "workers" in parsed:
        _seed_new_rank(settings.seed, int(state["segment"]), rank)
    else:
        raise ValueError(f"resume: {run_dir / CHECKPOINT_FILE} holds no RNG state of worker {rank}")
    if "workers" in parsed:
        batch_size = _batch_size(recipe)
        model.batch_size = None if batch_size is None else batch_size // settings.workers
        model.resize_envs(recipe.n_envs // settings.workers)
    if parsed:
        _apply_changes(model, parsed)
    return model, state


def _seed_new_rank(seed: int, segment: int, rank: int) -> None:
    """Seed the Python, NumPy and torch RNGs of a rank new to a resumed run from the run's
    seed, the segment it joins at and its rank (its action draws and minibatch orders)."""
    import torch

    state = np.random.SeedSequence([seed, segment, rank, 3]).generate_state(2)
    random.seed(int(state[0]))
    np.random.seed(int(state[1]))
    torch.manual_seed(int(state[0]) << 32 | int(state[1]))


class _Ranks:
    """The spawned ranks 1 .. workers - 1 of a data-parallel piece and the gloo group that
    this process joins as rank 0 (rendezvous in a file store of a fresh temporary folder)."""

    #: collectives wait this long for a rank: rank 0 alone builds or evaluates between them
    TIMEOUT = datetime.timedelta(minutes=30)
    #: the closing barrier waits this long (rank 0 may still wait for its last evaluation)
    CLOSING = datetime.timedelta(minutes=10)

    def __init__(self, workers: int) -> None:
        self.workers = int(workers)
        self.folder: tempfile.TemporaryDirectory | None = None   # the group's rendezvous file store
        self.processes: list[Any] = []

    def start(self, run_dir: Path, settings: AnchorRunSettings, resume: bool, parsed: dict[str, Any],
              env_overrides: dict[str, Any]) -> None:
        """Spawn the other ranks and join the group as rank 0."""
        import multiprocessing

        import torch.distributed as dist

        self.folder = tempfile.TemporaryDirectory(prefix="counterplay-ranks-", ignore_cleanup_errors=True)
        store = os.path.join(self.folder.name, "store")
        context = multiprocessing.get_context("spawn")
        for rank in range(1, self.workers):
            process = context.Process(target=_rank_main, daemon=True, name=f"counterplay-rank-{rank}",
                                      args=(rank, self.workers, store, str(run_dir), settings, resume, parsed,
                                            env_overrides))
            process.start()
            self.processes.append(process)
        dist.init_process_group("gloo", init_method=f"file://{store}", rank=0, world_size=self.workers,
                                timeout=self.TIMEOUT)

    def close(self, failed: bool) -> None:
        """Leave the group and end the other ranks: wait for them after a finished piece
        (``RuntimeError`` naming a rank that failed), terminate them after a failed one."""
        import torch.distributed as dist

        if dist.is_available() and dist.is_initialized():
            if not failed:
                try:  # the ranks leave together, with no collective left in flight
                    dist.monitored_barrier(timeout=self.CLOSING)
                except RuntimeError:  # a rank that died or hangs after its last segment: its exit code names it
                    pass
            dist.destroy_process_group()
        for process in self.processes:
            process.join(timeout=5 if failed else 120)
            if process.is_alive():
                process.terminate()
                process.join()
        if self.folder is not None:
            self.folder.cleanup()
            self.folder = None
        bad = [(i + 1, p.exitcode) for i, p in enumerate(self.processes) if p.exitcode != 0]
        self.processes = []
        if bad and not failed:
            raise RuntimeError("data-parallel worker(s) failed: " + ", ".join(f"rank {r} (exit code {c})"
                                                                              for r, c in bad))


def _rank_main(rank: int, workers: int, store: str, run_dir: str, settings: AnchorRunSettings, resume: bool,
               parsed: dict[str, Any], env_overrides: dict[str, Any]) -> None:
    """A spawned rank (1 .. workers - 1) of a data-parallel piece: joins the group first (so
    a later failure reaches rank 0 as a closed connection), then trains its share of every
    segment in step with rank 0; writes nothing."""
    import torch.distributed as dist

    _set_threads(settings)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=workers,
                            timeout=_Ranks.TIMEOUT)
    finished = False
    try:
        path = Path(run_dir)
        recipe = _recipe_from_run(path)
        womd = _load_womd(settings)
        if resume:
            model, state = _load_checkpoint(path, parsed, rank, settings, recipe)
        else:
            model, state = None, {"segment": 0, "wall_s": 0.0, "rows": []}
        _run_segments(path, settings, recipe, model, state, womd, [], None, None, _silent, env_overrides)
        dist.monitored_barrier(timeout=_Ranks.CLOSING)  # matches rank 0's in _Ranks.close
        finished = True
    finally:  # an exception's traceback is printed by multiprocessing; rank 0 sees the closed connection
        dist.destroy_process_group()
    if finished:
        # Gloo's threads can abort the interpreter's finalisation ("terminate called without an
        # active exception", exit code -6) after a finished piece; this rank writes nothing, so
        # it leaves without finalising
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed pipe loses only the rank's silent log
                pass
        os._exit(0)


def _silent(_message: str) -> None:
    """The log of ranks other than 0."""


def _held_out_line(row: dict[str, Any]) -> str:
    return (f"held-out goal aggr/normal/caut {row['aggressive_goal']:.1%} / {row['normal_goal']:.1%} / "
            f"{row['cautious_goal']:.1%}, normal collision {row['normal_collision']:.1%} off-road "
            f"{row['normal_offroad']:.1%} timeout {row['normal_timeout']:.1%}, first-decision entropy "
            f"{row['normal_entropy']:.2f}, value falls {row['value_falls']:.0%} of {row['value_failures']} failures; "
            f"ego completion / at-fault / timeout Interactive {row['interactive_completion']:.0%} / "
            f"{row['interactive_at_fault']:.0%} / {row['interactive_timeout']:.0%}, Random "
            f"{row['random_completion']:.0%} / {row['random_at_fault']:.0%} / {row['random_timeout']:.0%}")


def _segment_columns(stats: _SegmentStats, parallel: bool) -> tuple[dict[str, int], float, dict[str, float]]:
    """A segment's training columns: outcome counts, explained variance (mean over the
    rollouts) and update statistics (means over the updates); data-parallel, over every
    rank's (counts summed; the ranks ran the same updates, so their means are averaged)."""
    ev = float(np.mean(stats.ev)) if stats.ev else float("nan")
    means = stats.update_means()
    if not parallel:
        return dict(stats.outcomes), ev, means
    from cpalgo.common.distributed import all_reduce_sum, world_size

    counts = all_reduce_sum([stats.outcomes[o] for o in OUTCOMES])
    ev_sum, ev_count = all_reduce_sum([float(np.sum(stats.ev)), len(stats.ev)])
    columns = list(means)
    averaged = all_reduce_sum([means[c] for c in columns]) / world_size()
    return ({o: int(c) for o, c in zip(OUTCOMES, counts)}, float(ev_sum / ev_count) if ev_count else float("nan"),
            {c: float(v) for c, v in zip(columns, averaged)})


def _save(model: Any, run_dir: Path, state: dict[str, Any]) -> None:
    from cpalgo.checkpoint import save_model_atomic

    model.resume_state = state
    # the next segment starts from a reset: the last observations (5.7 MB at 2,048 slots,
    # which SB3 would save) are not needed to continue
    model._last_obs = model._last_original_obs = None
    save_model_atomic(model, run_dir / CHECKPOINT_FILE)
    _write_curve(run_dir, state["rows"])


def _run_segments(run_dir: Path, settings: AnchorRunSettings, recipe: Any, model: Any, state: dict[str, Any],
                  womd: list[Any], tasks: list[Any], helper: _SegmentWorker | None,
                  stop_after_s: float | None, log: Callable[[str], None],
                  env_overrides: dict[str, Any] | None = None) -> Any:
    """The segment loop of :func:`train_anchor_run`, run by every rank of a data-parallel
    piece in step (only rank 0 has a ``helper``, evaluates, logs and writes the files)."""
    from cpalgo.common import distributed
    from cpsim.model import offer_model_host

    lead = distributed.rank() == 0
    parallel = settings.workers > 1
    state["rows"] = [dict(r) for r in state["rows"]]
    pending = False  # the last row waits for the worker's evaluation

    def complete_last_row(fetch: Callable[[], dict[str, float] | None] | None, trained_on: bool = False) -> None:
        """Add the held-out columns to the last row: ``fetch()``'s (the worker's), else
        measured here on the last checkpoint (``trained_on``: the model has trained past it)."""
        from cpalgo.counterplay.algorithm import CounterPlay

        row = state["rows"][-1]
        t_eval = time.perf_counter()
        evaluated = fetch() if fetch is not None else None
        where = "evaluated by the worker"
        if evaluated is None:
            where = "evaluated here"
            saved = CounterPlay.load(run_dir / CHECKPOINT_FILE, device="cpu") if trained_on else model
            evaluated = _evaluate(saved, recipe, tasks)
        row.update(evaluated)
        where += f", waited {time.perf_counter() - t_eval:.0f} s"
        log(f"segment {int(row['segment'])} ({where}): {_held_out_line(row)}")

    if lead and model is not None and state["rows"] and "normal_goal" not in state["rows"][-1]:
        # the piece that trained the last segment ended before its evaluation came back
        complete_last_row(None)
        _save(model, run_dir, state)

    stop = None
    start = time.perf_counter()
    while (model.num_timesteps if model is not None else 0) < settings.timesteps:
        segment = int(state["segment"])
        t_build = time.perf_counter()
        prepared = helper.take(segment) if helper is not None else None
        if parallel:  # the other ranks adopt what rank 0's worker prepared (the same pool and arrays)
            prepared = distributed.broadcast_object(prepared)
            if not lead and prepared is not None:
                offer_model_host(prepared[1])
        procedural = prepared[0] if prepared is not None else None
        env = _build_env(recipe, settings, segment, womd, procedural, env_overrides, rank=distributed.rank())
        build_s = time.perf_counter() - t_build
        prebuilt = bool(getattr(env.venv.sim.model, "prebuilt", False))
        target = min((segment + 1) * settings.segment_timesteps, settings.timesteps)
        if helper is not None and target < settings.timesteps:
            helper.prepare(segment + 1, env.venv.sim.config)
        if model is None:
            model = _new_model(recipe, settings, env, rank=distributed.rank())
        else:
            model.set_env(env)  # force_reset: the segment starts from a reset of the new env
        stats = _SegmentStats()
        t0 = time.perf_counter()
        model.learn(max(target - model.num_timesteps, 1), reset_num_timesteps=False, callback=stats,
                    progress_bar=False)
        stats.read_update(model.logger.name_to_value)  # the segment's last update: no rollout end follows it
        env.close()
        train_wall = time.perf_counter() - t0
        if pending:  # the previous segment's evaluation ran during this one's training
            complete_last_row(helper.evaluation, trained_on=True)
            pending = False
        outcomes, ev, update_means = _segment_columns(stats, parallel)
        row: dict[str, Any] = {"segment": segment, "timesteps": int(model.num_timesteps),
                               "wall_s": round(float(state["wall_s"]) + train_wall, 1),
                               "learning_rate": float(model.policy.optimizer.param_groups[0]["lr"]),
                               "explained_variance": ev}
        episodes = sum(outcomes.values())
        row["train_episodes"] = episodes
        for o in OUTCOMES:
            row[f"train_{o}"] = outcomes[o] / episodes if episodes else float("nan")
        row.update(update_means)
        previous = state["rows"][-1]["timesteps"] if state["rows"] else 0
        state["rows"].append(row)
        state["segment"] = segment + 1
        state["wall_s"] = row["wall_s"]
        state["rng"] = _rng_state()
        if parallel:  # every rank continues from its own RNG states
            state["rank_rng"] = distributed.gather_objects(state["rng"])
        if not lead:  # rank 0 logs, evaluates and saves; the ranks stop together on its word
            if distributed.broadcast_object(None):
                break
            continue
        log(f"segment {segment}: {model.num_timesteps:,} transitions, {train_wall:.0f} s "
            f"({(row['timesteps'] - previous) / train_wall:,.0f} /s), env {build_s:.0f} s"
            f"{' (prepared ahead)' if prebuilt else ''}, approx_kl {row['approx_kl']:.4f}, clip "
            f"{row['clip_fraction']:.3f}, entropy {row['entropy']:.2f}, train goal / collision / off-road "
            f"{row['train_goal']:.1%} / {row['train_collision']:.1%} / {row['train_offroad']:.1%}, "
            f"EV {row['explained_variance']:.2f}")
        if helper is None:
            complete_last_row(None)
        _save(model, run_dir, state)
        if helper is not None:
            helper.evaluate(run_dir / CHECKPOINT_FILE, run_dir / "recipe.yml")
            pending = True
        if (run_dir / STOP_FILE).exists():
            stop = f"{STOP_FILE} found in {run_dir}: stopping after segment {segment}"
        elif stop_after_s is not None and time.perf_counter() - start >= stop_after_s:
            stop = f"stopping after {time.perf_counter() - start:.0f} s of this piece (--stop-after)"
        if parallel:
            distributed.broadcast_object(stop)
        if stop is not None:
            break
    if pending:  # the piece ends: wait for the last evaluation and keep it in the checkpoint
        complete_last_row(helper.evaluation)
        _save(model, run_dir, state)
    if stop is not None:
        log(stop)
    return model
