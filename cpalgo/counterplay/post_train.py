"""CounterPlay post-training of an anchor checkpoint per a zoo recipe, end to end
(``counterplay post-train``): :func:`post_train` checks the files, trains, keeps the
searches beside the checkpoint, evaluates the anchor and the result on the same held-out
tasks (:mod:`cpalgo.evaluate.held_out`) and writes ``summary.json`` / ``summary.md``.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

from cpalgo.common.anchor_network import anchor_network
from cpalgo.common.checks import UsageError, brief, check_out_path
from cpalgo.common.recipe_setup import check_algorithm_arguments, make_env
from cpalgo.evaluate.held_out import held_out_outcomes
from cpalgo.recipes import DEFAULT_ANCHOR, DEFAULT_POST_CONFIG, load_recipe, resolve_path

__all__ = ["DEFAULT_ANCHOR", "DEFAULT_POST_CONFIG", "post_train", "write_searches"]


def post_train(anchor: str | os.PathLike = DEFAULT_ANCHOR, config: str | os.PathLike = DEFAULT_POST_CONFIG,
               out_dir: str | os.PathLike = "runs/counterplay", timesteps: int | None = None, seed: int = 0,
               eval_tasks: int = 256, progress: bool = True, verbose: int = 0, tensorboard: str | None = None,
               overrides: dict[str, Any] | None = None, worlds: int | None = None,
               scenarios: int | None = None) -> dict[str, Any]:
    """Post-train ``anchor`` with CounterPlay per the ``config`` recipe; returns the summary.

    ``anchor`` and ``config`` go through :func:`cpalgo.recipes.resolve_path` (``zoo/...``
    names the shipped files). ``worlds`` overrides the recipe's number of training worlds
    (``n_envs / max_agents``), ``scenarios`` its ``num_scenarios``. Writes ``out_dir/counterplay.zip`` (atomically, also every
    few generations while training) and ``out_dir/summary.json`` / ``summary.md``.
    Raises :class:`UsageError` when a file is missing or the anchor does not fit the recipe.
    """
    from sb3_contrib import RecurrentPPO

    from cpalgo import CounterPlay
    from cpalgo.checkpoint import AtomicCheckpointCallback, save_model_atomic

    anchor = Path(resolve_path(anchor))
    if not anchor.is_file():
        raise UsageError(f"--anchor: no such checkpoint {str(anchor)!r} (train one with `counterplay train-anchor`)")
    try:
        recipe = load_recipe(config)
    except ValueError as exc:
        raise UsageError(f"--config: {exc}") from None
    check_algorithm_arguments(CounterPlay, recipe, **(overrides or {}))
    out = check_out_path(out_dir, "--out", folder=True)
    out.mkdir(parents=True, exist_ok=True)
    max_agents = int(recipe.env_kwargs.get("max_agents", 8))
    algo_kwargs = dict(recipe.algo_kwargs)
    algo_kwargs.update(overrides or {})

    policy, algo_kwargs, note = anchor_network(anchor, recipe.policy, algo_kwargs, CounterPlay.policy_aliases)
    if note is not None:
        print(f"warning: {note}", file=sys.stderr)
    env = make_env(recipe, seed, num_worlds=worlds, **({} if scenarios is None else {"num_scenarios": scenarios}))
    model = CounterPlay(policy, env, seed=seed, verbose=verbose, tensorboard_log=tensorboard, **algo_kwargs)
    try:
        model.set_parameters(str(anchor), exact_match=True)
    except Exception as exc:  # noqa: BLE001 - reported with the file name
        raise UsageError(f"--anchor: {anchor} does not match the recipe's policy ({brief(exc)})") from None
    before_model = RecurrentPPO.load(str(anchor), device="cpu")
    print(f"evaluating the anchor on {eval_tasks} held-out procedural tasks (normal condition) ...")
    before = held_out_outcomes(before_model, eval_tasks, max_agents)
    print(f"  before: {before}")

    steps = timesteps or recipe.n_timesteps
    ckpt_path = out / "counterplay.zip"
    n_steps = int(algo_kwargs.get("n_steps", 128))
    ckpt = AtomicCheckpointCallback(save_freq=n_steps * 5, path=ckpt_path)
    t0 = time.perf_counter()
    model.learn(steps, progress_bar=progress, callback=ckpt)
    wall = time.perf_counter() - t0
    save_model_atomic(model, ckpt_path)
    search_files = write_searches(model, ckpt_path)
    after = held_out_outcomes(model, eval_tasks, max_agents)
    print(f"  after:  {after}")

    summary = {
        "anchor": str(anchor),
        "config": recipe.path,
        "checkpoint": str(ckpt_path),
        "timesteps": int(model.num_timesteps),
        "wall_s": round(wall, 1),
        "budget": model.budget.as_dict(),
        "search": _search_summary(getattr(model, "search_totals", {}), model.panel),
        "held_out_tasks": eval_tasks,
        "outcomes_before": before.as_dict(),
        "outcomes_after": after.as_dict(),
    }
    summary["search_files"] = search_files
    _write_summary(out, summary)
    return summary


def _search_summary(totals: dict[str, float], panel: Sequence[str]) -> dict[str, Any]:
    """The search counters a reader wants, from CounterPlay's running totals."""
    from cpalgo.counterplay.driver import OWN_CONDITION
    from cpalgo.counterplay.search import ADMISSION_VERDICTS

    keys = ("failures", "failures_collision", "failures_offroad", "failures_timeout", "searches",
            "searches_skipped", "factual_completed", "admissible", "teachers_chosen", "verified",
            "verification_failed", "teachers")
    out: dict[str, Any] = {k: int(totals.get(k, 0)) for k in keys}
    searches = out["searches"]
    out["mean_root_depth"] = round(totals.get("root_depth_sum", 0) / searches, 2) if searches else None
    out["winning_profiles"] = {name: int(totals.get(f"profile_{name}", 0)) for name in panel}
    if totals.get(f"profile_{OWN_CONDITION}"):
        out["winning_profiles"][OWN_CONDITION] = int(totals[f"profile_{OWN_CONDITION}"])
    out["retry_verdicts"] = {name: int(totals.get(f"retries_{name}", 0)) for name in ADMISSION_VERDICTS}
    out["search_cpu_s"] = round(float(totals.get("search_cpu_s", 0.0)), 2)
    return out


def _md_value(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        return ", ".join(f"{k} {_md_value(v)}" for k, v in value.items()) or "none"
    return "n/a" if value is None else str(value)


def _md_table(title: str, values: dict[str, Any]) -> list[str]:
    """A two-column Markdown table (one row per key) under a heading."""
    rows = [f"| {key.replace('_', ' ')} | {_md_value(value)} |" for key, value in values.items()]
    return [f"## {title}", "", "| | |", "|---|---|", *rows, ""]


def _write_summary(out: Path, summary: dict[str, Any]) -> None:
    from cpalgo.evaluate.tables import write_text_atomic

    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2, default=str))
    b, a = summary["outcomes_before"], summary["outcomes_after"]
    lines = [
        "# CounterPlay post-training summary", "",
        f"- anchor: `{summary['anchor']}`, recipe `{summary['config']}`",
        f"- checkpoint: `{summary['checkpoint']}` after {summary['timesteps']} main transitions, "
        f"{summary['wall_s']} s", "",
        f"Held-out procedural tasks ({summary['held_out_tasks']}), self-play, normal condition:", "",
        "| | goal | collision | off-road | timeout | agents |", "|---|---|---|---|---|---|",
        f"| anchor | {b['goal']:.1%} | {b['collision']:.1%} | {b['offroad']:.1%} | {b['timeout']:.1%} | {b['agents']} |",
        f"| CounterPlay | {a['goal']:.1%} | {a['collision']:.1%} | {a['offroad']:.1%} | {a['timeout']:.1%} | {a['agents']} |",
        "",
        *_md_table("Search", summary["search"]),
        *_md_table("Budget (transitions)", summary["budget"]),
    ]
    write_text_atomic(out / "summary.md", "\n".join(lines))
    print("\n".join(lines))


def write_searches(model: Any, ckpt_path: Path) -> dict[str, str]:
    """The kept searches beside the checkpoint, and the figure of the latest verified one
    (``search.png`` in the same folder) when there is one."""
    from cpalgo.viz import write_search_files

    files = write_search_files(model, ckpt_path)
    if files:
        print(f"kept searches: {files}")
    return files
