"""Run the ``counterplay`` CLI with a reactive-teacher style variant registered as teacher NAME
for this process only (the imitation students of docs/results/README.md, "A bolder teacher").

    python docs/results/teacher_v5/train_variant.py NAME 'exponent=0.45,schedule=(0.95,1.6)' -- \\
        train-anchor --teacher NAME ...

The keyword arguments override :class:`cpsim.expert.ReactiveStyle` fields on top of teacher
version 2 (``goal_brake=None``).
"""
import sys

import cpalgo.cli as cli
import cpalgo.pretrain as pretrain
import cpsim.expert as ex

name, spec, rest = sys.argv[1], sys.argv[2], sys.argv[sys.argv.index("--") + 1:]
fields = dict(goal_brake=None)
fields.update(eval("dict(" + spec + ")"))  # a trusted command line: literals only
ex._VERSIONED_STYLES[name] = ex.ReactiveStyle(**fields)
ex.EXPERTS = ex.EXPERTS + (name,)
pretrain.TEACHERS = ex.EXPERTS
cli.TEACHERS = cli.TEACHERS + (name,)
print(f"teacher {name}:", ex._VERSIONED_STYLES[name], flush=True)
sys.exit(cli.main(rest))
