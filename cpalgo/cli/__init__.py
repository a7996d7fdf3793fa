"""The ``counterplay`` command.

Sub-commands (``counterplay SUB-COMMAND --help`` lists each one's options and defaults):

* ``run``: post-train the shipped anchor with PPO-Continue and with CounterPlay at the same
  budget and seed, evaluate the anchor and both on the same held-out tasks, write the
  checkpoints, tables and a summary (the README's main job; :mod:`cpalgo.experiments.mainjob`);
* ``post-train``: CounterPlay alone, with every option exposed;
* ``experiment``: a grid of methods x seeds on Ray or in-process, with the paper's tables;
* ``methods``: the registered post-training methods, one line each;
* ``train-anchor``: train the reward-conditioned self-play anchor (RecurrentPPO);
* ``outcomes``: self-play outcome rates of a checkpoint on held-out tasks;
* ``pool``: generate and summarise a procedural scenario pool;
* ``searches``: list the searches a CounterPlay run kept; draw one (PNG / GIF).

Paths spelled ``zoo/NAME`` (the README's) name the files shipped inside the package when
no such file exists (:func:`cpalgo.recipes.resolve_path`). A wrong argument or a file that
is missing or does not fit ends the command with one ``error:`` line and exit status 2,
as argparse does for its own errors.

Layout: :mod:`~cpalgo.cli.parser` (the parser, its argument types and :func:`main`), and
the commands by topic: :mod:`~cpalgo.cli.anchor` (``train-anchor``, ``curve``,
``outcomes``), :mod:`~cpalgo.cli.post` (``post-train``, ``searches``),
:mod:`~cpalgo.cli.scenarios` (``pool``); ``run``, ``experiment`` and ``methods`` come from
:mod:`cpalgo.experiments.command`, ``compress-anchor`` from :mod:`cpalgo.anchor.compress`.
The library code the commands run lives outside the CLI: :mod:`cpalgo.counterplay.post_train`
(:func:`post_train`), :mod:`cpalgo.evaluate.held_out` (the held-out tasks),
:mod:`cpalgo.common.recipe_setup` (env and algorithm arguments from a recipe). Their names
are re-exported here under the names this module has always had.
"""

from __future__ import annotations

from cpalgo.cli.anchor import cmd_curve, cmd_outcomes, cmd_train_anchor
from cpalgo.cli.parser import DEFAULT_ANCHOR_CONFIG, DEFAULT_SELFPLAY_CONFIG, TEACHERS, _version, build_parser, main
from cpalgo.cli.post import cmd_post_train, cmd_searches
from cpalgo.cli.scenarios import cmd_pool
from cpalgo.common.checks import UsageError, check_out_path
from cpalgo.common.checks import brief as _brief
from cpalgo.common.recipe_setup import check_algorithm_arguments
from cpalgo.common.recipe_setup import make_env as _make_env
from cpalgo.counterplay.post_train import DEFAULT_ANCHOR, DEFAULT_POST_CONFIG, post_train
from cpalgo.counterplay.post_train import write_searches as _write_searches
from cpalgo.evaluate.held_out import HELD_OUT_SEED
from cpalgo.evaluate.held_out import held_out_outcomes as _outcomes
from cpalgo.evaluate.held_out import held_out_tasks as _held_out

__all__ = ["main", "build_parser", "TEACHERS", "DEFAULT_ANCHOR", "DEFAULT_ANCHOR_CONFIG", "DEFAULT_SELFPLAY_CONFIG", "DEFAULT_POST_CONFIG",
           "HELD_OUT_SEED", "post_train", "check_algorithm_arguments", "check_out_path", "UsageError",
           "cmd_pool", "cmd_train_anchor", "cmd_curve", "cmd_outcomes", "cmd_post_train", "cmd_searches",
           "_held_out", "_outcomes", "_make_env", "_brief", "_write_searches", "_version"]
