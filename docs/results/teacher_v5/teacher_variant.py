"""Run the evaluator or the ``counterplay`` CLI with a reactive-teacher style variant registered
as teacher NAME for this process only (screening and students of docs/results/README.md, "A
bolder teacher and imitation-only students"; not shipped):

    python docs/results/teacher_v5/teacher_variant.py reactive-x 'schedule=(0.95,1.6)' -- \\
        evaluate --policy reactive-x --traffic-policy zoo/anchor.zip --split both --n 50 ...
    python docs/results/teacher_v5/teacher_variant.py rx0.3 'exponent=0.3,schedule=(0.95,1.6)' -- \\
        train-anchor --teacher rx0.3 ...

The keyword arguments override :class:`cpsim.expert.ReactiveStyle` fields on top of teacher
version 2 (``goal_brake=None``; under the evaluation goal criterion version 3 drives the same).
After ``--``: ``evaluate`` and the arguments of ``python -m cpalgo.evaluate``, or a
``counterplay`` sub-command and its arguments.
"""
import sys

import cpalgo.cli as cli
import cpalgo.pretrain as pretrain
import cpsim.expert as ex
from cpalgo.evaluate.__main__ import main as evaluate

name, spec, rest = sys.argv[1], sys.argv[2], sys.argv[sys.argv.index("--") + 1:]
fields = dict(goal_brake=None)
fields.update(eval("dict(" + spec + ")"))  # a trusted command line: literals only
ex._VERSIONED_STYLES[name] = ex.ReactiveStyle(**fields)
ex.EXPERTS = ex.EXPERTS + (name,)
pretrain.TEACHERS = ex.EXPERTS
cli.TEACHERS = cli.TEACHERS + (name,)
print(f"teacher {name}:", ex._VERSIONED_STYLES[name], flush=True)
sys.exit(evaluate(rest[1:]) if rest[:1] == ["evaluate"] else cli.main(rest))
