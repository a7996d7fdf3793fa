"""Evaluate a reactive-teacher style variant as the evaluator's ego (screening, not shipped).

    python docs/results/teacher_v5/teacher_variant.py 'exponent=0.3,schedule=(0.95,1.6)' -- \\
        --policy reactive-x --traffic-policy zoo/anchor.zip --split both --n 50 --deploy normal \\
        --no-plots --no-progress --out runs/tv5/D_normal

The keyword arguments override :class:`cpsim.expert.ReactiveStyle` fields on top of teacher
version 2 (``goal_brake=None``; under the evaluation goal criterion version 3 drives the same),
and the style is registered as the teacher ``reactive-x`` for this process only.
"""
import sys

import cpsim.expert as ex
from cpalgo.evaluate.__main__ import main

spec, rest = sys.argv[1], sys.argv[sys.argv.index("--") + 1:]
fields = dict(goal_brake=None)
fields.update(eval("dict(" + spec + ")"))  # a trusted command line: literals only
ex._VERSIONED_STYLES["reactive-x"] = ex.ReactiveStyle(**fields)
ex.EXPERTS = ex.EXPERTS + ("reactive-x",)
print("teacher reactive-x:", ex._VERSIONED_STYLES["reactive-x"], flush=True)
sys.exit(main(rest))
